import numpy as np
import pytest

from common.render._util import light_vector
from common.render.shading import (exaggerated_shading, gooch, lambertian, mean_curvature_shading,
                                   multiscale_mean_curvature_shading, quantize_colours, toon)
from tests.rgbn.analytic import gaussian_bump, grid_mm, sphere, tilted_plane


def test_lambertian_is_n_dot_l_clamped_with_ambient():
    n, mask = sphere(64, 3.0, 0.1)
    l = light_vector(30.0, 20.0)
    got = lambertian(n, (30.0, 20.0), ambient=0.2)
    expect = 0.2 + 0.8 * np.maximum(n @ l, 0)
    assert np.allclose(got, expect, atol=1e-6)
    albedo = np.full(n.shape, 0.5, np.float32)
    assert np.allclose(lambertian(n, l, albedo=albedo, ambient=0.2), 0.5 * expect[..., None], atol=1e-6)


def test_raking_light_shows_shallow_relief_with_more_contrast_than_overhead_light():
    n = gaussian_bump(96, 0.05, 0.05, 0.5)  # a 50 um high bump: a tool mark
    overhead = lambertian(n, (0.0, 70.0))
    raking = lambertian(n, (0.0, 10.0))
    # Weber contrast (what the eye sees): d(n.l) ~ slope*cos(elevation) over a mean of sin(elevation)
    assert raking.std() / raking.mean() > 5 * overhead.std() / overhead.mean()


def test_toon_boundaries_lie_on_isophotes():
    n, mask = sphere(128, 6.0, 0.1)
    light = (120.0, 40.0)
    s = np.maximum(n @ light_vector(*light), 0)
    levels = 4
    tone = toon(n, light, levels=levels, softness=0.0, dark=0.0)
    # a hard toon image is constant between isophotes and jumps exactly across them
    band = np.clip(np.floor(s * levels), 0, levels - 1) / (levels - 1)
    assert np.allclose(tone[mask], band[mask], atol=1e-6)
    # with smooth steps the tone is half-way on every isophote n.l = j/levels
    soft = toon(n, light, levels=levels, softness=0.05, dark=0.0)
    for j in range(1, levels):
        on = mask & (np.abs(s - j / levels) < 0.002)
        assert on.sum() > 10
        assert np.allclose(soft[on], (j - 0.5) / (levels - 1), atol=0.02)


def test_kmeans_quantization_recovers_the_palette():
    rng = np.random.default_rng(3)
    palette = np.array([[0.8, 0.2, 0.1], [0.1, 0.5, 0.2], [0.9, 0.9, 0.8]], np.float32)
    idx = rng.integers(0, 3, (40, 40))
    colours = palette[idx] + 0.02 * rng.standard_normal((40, 40, 3)).astype(np.float32)
    out = quantize_colours(colours, 3, seed=1)
    assert len(np.unique(out.reshape(-1, 3), axis=0)) == 3
    assert np.abs(out - palette[idx]).max() < 0.02


def test_gooch_goes_from_cool_to_warm():
    l = light_vector(0.0, 0.0)
    n = np.zeros((1, 2, 3), np.float32)
    n[0, 0] = l
    n[0, 1] = -l
    kd = np.full((1, 2, 3), 0.5, np.float32)
    out = gooch(n, l, albedo=kd, blue=0.4, yellow=0.4, alpha=0.2, beta=0.6)
    assert np.allclose(out[0, 0], [0.4 + 0.3, 0.4 + 0.3, 0.3])  # k_warm
    assert np.allclose(out[0, 1], [0.1, 0.1, 0.4 + 0.1])  # k_cool


def test_exaggerated_shading_of_a_plane_is_uniform_and_reveals_a_bump_whatever_the_tilt():
    flat = exaggerated_shading(tilted_plane(64, 30, 45), scales=4)
    assert flat.std() < 1e-5
    bump = gaussian_bump(96, 0.1, 0.3, 0.4)
    # the same bump on a strongly tilted base: normals rotated by 50 degrees about y
    t = np.radians(50)
    rot = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]], np.float32)
    tilted = bump @ rot.T
    a = exaggerated_shading(bump, (0.0, 45.0), scales=6, base_weight=0.0)
    b = exaggerated_shading(tilted, (0.0, 45.0), scales=6, base_weight=0.0)
    x, y = grid_mm(96, 0.1)
    near = np.hypot(x, y) < 1.0

    def spread(img):
        lo, hi = np.percentile(img[near], [5, 95])
        return hi - lo

    # light always grazes the coarse surface: the bump keeps most of its contrast on the tilted
    # base, where plain Lambertian shading under the same light washes it out
    assert spread(a) > 0.4
    assert spread(b) > 0.5 * spread(a)
    la, lb = lambertian(bump, (0.0, 45.0)), lambertian(tilted, (0.0, 45.0))
    assert spread(lb) < 0.3 * spread(la)
    # and the flank facing the light (x > 0 for azimuth 0) is the bright one
    row = np.abs(y) < 0.2
    assert a[row & (x > 0.2) & (x < 0.6)].mean() > a[row & (x < -0.2) & (x > -0.6)].mean() + 0.2


@pytest.mark.parametrize("fn", [mean_curvature_shading, multiscale_mean_curvature_shading])
def test_plane_curvature_shading_is_uniform_half(fn):
    out = fn(tilted_plane(48, 35, 70), 300.0)
    assert np.allclose(out, 0.5, atol=1e-6)


def test_mean_curvature_shading_of_a_sphere_follows_tanh_of_radius_ratio():
    n, mask = sphere(96, 4.0, 0.1)
    x, y = grid_mm(96, 0.1)
    inner = np.hypot(x, y) < 3.4
    out = mean_curvature_shading(n, 254.0, mask=mask, radius_mm=2.0)
    assert np.allclose(out[inner], 0.5 + 0.5 * np.tanh(2.0 / 4.0), atol=2e-3)
    bowl = n.copy()
    bowl[..., :2] *= -1
    assert np.allclose(mean_curvature_shading(bowl, 254.0, mask=mask, radius_mm=2.0)[inner],
                       0.5 - 0.5 * np.tanh(0.5), atol=2e-3)


def test_multiscale_shading_shows_convex_light_and_concave_dark():
    n = gaussian_bump(96, 0.05, 0.4, 0.6)
    out = multiscale_mean_curvature_shading(n, 508.0, scales=3, sigma0_mm=0.05)
    assert out[48, 48] > 0.6  # the top of the bump
    x, y = grid_mm(96, 0.05)
    foot = np.abs(np.hypot(x, y) - 1.4) < 0.05
    assert out[foot].mean() < 0.5


def test_bad_levels_are_refused_by_name():
    with pytest.raises(ValueError, match="levels"):
        toon(tilted_plane(4), levels=1)
    with pytest.raises(ValueError, match="sigma_ratio"):
        exaggerated_shading(tilted_plane(4), sigma_ratio=1.0)


def _rough_relief(size=384, seed=3):
    """Normals of a random multi-scale height field inside a disc (a fragment-like relief)."""
    import cv2
    rng = np.random.default_rng(seed)
    height = np.zeros((size, size), np.float32)
    for sigma, amp in ((size / 12, 3.0), (size / 48, 0.6), (2.0, 0.08)):
        layer = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigma)
        height += amp * layer / layer.std()
    gy, gx = np.gradient(height)
    n = np.dstack([-gx, gy, np.ones_like(gx)])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    yy, xx = np.mgrid[0:size, 0:size]
    return n.astype(np.float32), (xx - size / 2) ** 2 + (yy - size / 2) ** 2 < (0.45 * size) ** 2


@pytest.mark.parametrize("sigma0,scales", [(1.0, 6), (1.5, 8), (3.0, 5)])
def test_exaggerated_coarse_levels_match_the_full_resolution_reference(sigma0, scales):
    """Levels drawn on coarser grids stay within 1/255 of every level at full resolution."""
    n, mask = _rough_relief()
    ref = exaggerated_shading(n, mask=mask, sigma0_px=sigma0, scales=scales, coarse=False)
    fast = exaggerated_shading(n, mask=mask, sigma0_px=sigma0, scales=scales)
    d = np.abs(ref - fast)[mask]
    assert d.max() < 1 / 255
    assert d.mean() < 1e-3
    assert np.ptp(ref[mask]) > 0.3          # not a trivially flat picture


def test_exaggerated_coarse_grid_is_aligned_to_the_whole_image_for_tiles():
    """A window cut at an odd offset, told its origin, draws the whole image's values inside."""
    n, mask = _rough_relief(320)
    whole = exaggerated_shading(n, mask=mask, sigma0_px=1.0, scales=5)
    r0, c0 = 37, 53
    part = exaggerated_shading(n[r0:, c0:], mask=mask[r0:, c0:], sigma0_px=1.0, scales=5, origin=(r0, c0))
    halo = 4 * 32 + 8                   # 4 sigma of the coarsest level: the window's border effects
    inner = (slice(halo, None), slice(halo, None))
    m = mask[r0:, c0:][inner]
    assert np.abs(part[inner] - whole[r0:, c0:][inner])[m].max() < 1e-3


def test_nearest_colours_is_the_argmin_of_the_distances_and_keeps_the_background():
    from common.render.shading import nearest_colours

    rng = np.random.default_rng(3)
    colours = rng.random((1200, 1000, 3), dtype=np.float32)  # > 1 Mpx: more than one block of rows
    colours[0, :4] = (0.5, 0.5, 0.5)  # equally near centres 0 and 1: the first is kept, as argmin
    centres = np.array([[0.25, 0.5, 0.5], [0.75, 0.5, 0.5], [0.1, 0.9, 0.2], [0.9, 0.1, 0.8]], np.float32)
    mask = rng.random((1200, 1000)) > 0.2
    out = nearest_colours(colours, centres, mask=mask)
    d = ((colours[..., None, :] - centres) ** 2).sum(axis=3)
    expect = np.where(mask[..., None], centres[np.argmin(d, axis=2)], colours)
    assert np.array_equal(out, expect)
    assert np.array_equal(out[0, :4][mask[0, :4]], np.tile(centres[0], (int(mask[0, :4].sum()), 1)))


def test_exaggerated_with_its_finest_level_given_draws_the_same():
    """A recipe hands exaggerated shading the normals it already smoothed at sigma0: same picture
    (on the mask, what is drawn: off it, beyond the finest kernel's reach, smooth_normals keeps the
    input normal and exaggerated shading's own levels a zero vector)."""
    from common.rgbn.smoothing import smooth_normals

    n, mask = _rough_relief()
    own = exaggerated_shading(n, mask=mask, sigma0_px=1.5, scales=6)
    given = exaggerated_shading(n, mask=mask, sigma0_px=1.5, scales=6, finest=smooth_normals(n, 1.5, mask=mask))
    assert np.array_equal(own[mask], given[mask])
    with pytest.raises(ValueError, match="finest"):
        exaggerated_shading(n, mask=mask, sigma0_px=1.5, finest=n[1:])


def _relief(size=320, seed=3):
    """A multi-scale relief with a round outline (height in pixels of 25.4/1200 mm)."""
    import cv2

    from tests.rgbn.analytic import normals_from_height
    rng = np.random.default_rng(seed)
    blur = lambda a, s: cv2.GaussianBlur(a.astype(np.float32), (0, 0), s)  # noqa: E731
    h = blur(rng.standard_normal((size, size)), 24) * 600 + blur(rng.standard_normal((size, size)), 4) * 20
    gy, gx = np.gradient(h)
    n = normals_from_height(gx * 0.02, -gy * 0.02).astype(np.float32)
    yy, xx = np.mgrid[0:size, 0:size]
    mask = (xx - size / 2) ** 2 + (yy - size / 2) ** 2 < (0.47 * size) ** 2
    return n, mask


def test_multiscale_curvature_on_coarse_grids_is_within_a_level_of_the_exact_gaussian_scale_space():
    """Reference computed independently: every level an exact full-resolution Gaussian (OpenCV,
    no downsampling) of the 1/nz-weighted normals, its mean curvature at full resolution."""
    import cv2

    from common.render.enhance import robust_range, tone_curve
    from common.rgbn.curvature import mean_curvature
    n, mask = _relief()
    dpi, sigmas = 1200.0, [0.1 * 2 ** i for i in range(5)]      # 4.7 ... 76 px: grids 1, 2, 4, 8, 8
    w = np.where(mask, 1.0 / np.maximum(n[..., 2], 0.05), 0.0).astype(np.float32)
    stack = np.dstack([n * w[..., None], w]).astype(np.float32)
    exact = np.zeros(mask.shape, np.float64)
    for s in sigmas:
        b = cv2.GaussianBlur(stack, (0, 0), s * dpi / 25.4, borderType=cv2.BORDER_REFLECT)[..., :3]
        v = (b / np.maximum(np.linalg.norm(b, axis=2, keepdims=True), 1e-12)).astype(np.float32)
        exact += s / len(sigmas) * mean_curvature(v, dpi)
    exact[~mask] = 0
    got = multiscale_mean_curvature_shading(n, dpi, mask=mask, sigma0_mm=0.1, raw=True)
    lo, hi = robust_range(exact, mask, clip_percent=5.0)
    d = np.abs(tone_curve(exact, lo, hi) - tone_curve(got, lo, hi))[mask] * 255
    assert d.max() < 1.5 and d.mean() < 0.5


def test_multiscale_curvature_coarse_grids_are_aligned_to_the_whole_image_for_tiles():
    n, mask = _relief(512)
    whole = multiscale_mean_curvature_shading(n, 600.0, mask=mask, raw=True)   # 2.4 ... 38 px: grids 1-8
    r0, c0 = 37, 21          # a window whose origin is not on any coarse grid
    part = multiscale_mean_curvature_shading(n[r0:, c0:], 600.0, mask=mask[r0:, c0:], raw=True, origin=(r0, c0))
    inner = (slice(200 - r0, 320 - r0), slice(200 - c0, 320 - c0))   # 4 sigma from both windows' edges
    assert np.abs(part[inner] - whole[r0:, c0:][inner]).max() < 1e-4 * np.abs(whole).max()


@pytest.mark.parametrize("strip_pixels", [4096, 1 << 30])
def test_exaggerated_shading_drawn_in_row_strips_equals_the_whole_image_drawing(monkeypatch, strip_pixels):
    """The full-resolution levels are drawn strip by strip with a halo of the kernel's reach:
    strips of 13 rows and one strip of the whole image draw the same picture."""
    from common.rgbn import smoothing
    n, mask = _relief(200)
    monkeypatch.setattr(smoothing, "STRIP_PIXELS", 1 << 30)
    ref = exaggerated_shading(n, mask=mask, scales=4, sigma0_px=1.5)
    monkeypatch.setattr(smoothing, "STRIP_PIXELS", strip_pixels)
    got = exaggerated_shading(n, mask=mask, scales=4, sigma0_px=1.5)
    assert np.abs(got - ref).max() < 1e-6

