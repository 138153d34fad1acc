import numpy as np
import pytest

from common.rgbn.image import RGBNImage
from common.rgbn.smoothing import foreshortening_weights, scale_space, smooth_normals, smooth_rgbn
from tests.rgbn.analytic import sphere, tilted_plane


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1, 1)))


def test_foreshortening_corrected_smoothing_leaves_a_tilted_plane_unchanged():
    n = tilted_plane(64, tilt_deg=60)
    mask = np.zeros((64, 64), bool)
    mask[8:56, 12:50] = True
    out = smooth_normals(n, 5.0, mask=mask)
    assert np.abs(out - n)[mask].max() < 1e-5  # float32 resolution


def test_foreshortening_weight_is_one_over_nz():
    n = tilted_plane(8, tilt_deg=60)
    assert np.allclose(foreshortening_weights(n), 2.0, atol=1e-5)


def test_weighting_by_one_over_nz_pulls_the_average_towards_the_steeper_normal():
    # two half-planes: flat and 70 deg tilted; at the seam the 1/nz weight favours the tilted one,
    # by the ratio of surface areas 1/cos(70 deg) ~ 2.9
    n = np.zeros((32, 32, 3), np.float32)
    n[..., 2] = 1
    t = np.radians(70)
    n[:, 16:] = (np.sin(t), 0, np.cos(t))
    plain = smooth_normals(n, 4.0, foreshortening=False)
    corrected = smooth_normals(n, 4.0, foreshortening=True)
    seam = (16, 15)
    assert corrected[seam][0] > plain[seam][0] + 0.1
    # the corrected normal at the seam is the area-weighted mean of the two orientations
    w = np.array([1.0, 1 / np.cos(t)])
    # Gaussian weights of the left and right halves at column 15.5-0.5
    cols = np.arange(32)
    g = np.exp(-((cols - 15) ** 2) / (2 * 16.0))
    wl, wr = g[:16].sum() * w[0], g[16:].sum() * w[1]
    expect = (wl * np.array([0, 0, 1]) + wr * np.array([np.sin(t), 0, np.cos(t)]))
    expect /= np.linalg.norm(expect)
    assert angle_deg(corrected[seam], expect) < 1.0


def test_smoothing_ignores_pixels_outside_the_mask():
    n, mask = sphere(64, 3.0, 0.1)
    garbage = n.copy()
    garbage[~mask] = (1.0, 0.0, 0.0)
    a = smooth_normals(n, 2.0, mask=mask)
    b = smooth_normals(garbage, 2.0, mask=mask)
    assert np.allclose(a[mask], b[mask], atol=1e-5)


def test_scale_space_levels_get_smoother_and_stay_unit_length():
    rng = np.random.default_rng(1)
    n = tilted_plane(64, 10).astype(np.float32) + 0.2 * rng.standard_normal((64, 64, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    levels = scale_space(n, [0, 1, 2, 4, 8])
    spread = [np.std(level[..., 0]) for level in levels]
    assert all(a > b for a, b in zip(spread, spread[1:]))
    for level in levels:
        assert np.allclose(np.linalg.norm(level, axis=-1), 1, atol=1e-5)


def test_smooth_rgbn_uses_physical_sigma():
    n = tilted_plane(32, 20)
    img = RGBNImage(albedo=np.random.default_rng(0).random((32, 32, 3)), mask=np.ones((32, 32), bool), dpi=254,
                    normals=n)
    out = smooth_rgbn(img, sigma_mm=0.3)  # 3 px
    ref = smooth_normals(n, 3.0)
    assert np.allclose(out.normals, ref, atol=1e-6)
    assert out.albedo.std() < img.albedo.std() / 3


@pytest.mark.parametrize("sigma", [-1.0, np.nan])
def test_bad_sigma_is_refused_by_name(sigma):
    with pytest.raises(ValueError, match="sigma_px"):
        smooth_normals(tilted_plane(8), sigma)


def test_wrong_normal_shape_is_refused():
    with pytest.raises(ValueError, match="normals"):
        smooth_normals(np.zeros((8, 8)), 1.0)


def _rough_normals(seed: int, mask_columns):
    """150 x 97 random unit normals around the view axis, and a rectangular mask over rows 20-130."""
    rng = np.random.default_rng(seed)
    n = rng.normal(0, 0.3, (150, 97, 3)).astype(np.float32)
    n[..., 2] = 1.0
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    mask = np.zeros((150, 97), bool)
    mask[20:130, mask_columns[0]:mask_columns[1]] = True
    return n, mask


def test_smoothing_in_row_strips_is_the_normalised_convolution_of_the_whole_image(monkeypatch):
    """Independent reference: the 1/nz-weighted stack blurred whole by OpenCV, normalised."""
    import cv2

    from common.rgbn import smoothing
    n, mask = _rough_normals(5, mask_columns=(10, 90))
    w = np.where(mask, 1.0 / np.maximum(n[..., 2], 0.05), 0.0).astype(np.float32)
    monkeypatch.setattr(smoothing, "STRIP_PIXELS", 97 * 9)   # strips of 9-16 rows
    for sigma in (0.8, 2.5, 4.0):
        b = cv2.GaussianBlur(np.dstack([n * w[..., None], w]), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        ref = b[..., :3] / np.maximum(np.linalg.norm(b[..., :3], axis=2, keepdims=True), 1e-30)
        got = smooth_normals(n, sigma, mask=mask)
        reach = b[..., 3] > 1e-6 * w.max()
        assert np.abs(got - ref)[reach].max() < 1e-5
        assert np.array_equal(got[~reach], n[~reach])   # nothing within reach: the input kept


def test_smoothed_cosines_are_the_smoothed_normals_cosines_with_each_light(monkeypatch):
    """Independent reference: the cosine of smooth_normals' unit normals with each direction, for
    a light vector and a per-pixel light given row by row, at a sigma blurred at full resolution
    (strips), one blurred on a downsampled copy, and 0; the input's where no mask pixel is within reach."""
    from common.rgbn import smoothing
    from common.rgbn.smoothing import smoothed_cosines

    n, mask = _rough_normals(7, mask_columns=(10, 60))
    rng = np.random.default_rng(8)
    l = np.array([0.3, -0.2, 0.9], np.float32)
    l /= np.linalg.norm(l)
    field = rng.normal(0, 0.2, (150, 97, 3)).astype(np.float32)
    field[..., 2] = 1.0
    field /= np.linalg.norm(field, axis=2, keepdims=True)
    asked = []

    def rows(r0, r1):
        asked.append((r0, r1))
        return field[r0:r1]

    monkeypatch.setattr(smoothing, "STRIP_PIXELS", 97 * 9)
    for sigma in (0.0, 1.5, 16.0):
        ref = smooth_normals(n, sigma, mask=mask)
        got_l, got_f = smoothed_cosines(n, sigma, [l, rows], mask=mask)
        assert np.abs(got_l - ref @ l).max() < 2e-6
        assert np.abs(got_f - np.einsum("...i,...i->...", ref, field)).max() < 2e-6
        if sigma == 1.5:
            assert len(asked) > 5   # strips
            assert np.abs(got_l[:, 80:] - n[:, 80:] @ l).max() < 1e-6   # nothing within reach: the input's
        asked.clear()


@pytest.mark.parametrize("shape", [(148, 96), (150, 97)])
def test_smoothed_cosines_of_a_coarse_sigma_equal_the_whole_stacks_blur_strip_by_strip(monkeypatch, shape):
    """A sigma blurred on a downsampled copy: the stack area-averaged, blurred and upsampled a
    strip at a time (an image a whole multiple of the grid) or as a whole (any other) gives the
    cosines of gaussian_blur's blur of the whole stack, bit for bit."""
    from common.rgbn import smoothing
    from common.rgbn._filters import decimation_factor, gaussian_blur
    from common.rgbn.smoothing import smoothed_cosines, weighted_stack

    n, mask = _rough_normals(7, mask_columns=(10, 60))
    n, mask = np.ascontiguousarray(n[:shape[0], :shape[1]]), np.ascontiguousarray(mask[:shape[0], :shape[1]])
    l = np.array([0.3, -0.2, 0.9], np.float32) / np.float32(np.linalg.norm([0.3, -0.2, 0.9]))
    assert decimation_factor(16.0, shape) == 4
    monkeypatch.setattr(smoothing, "STRIP_PIXELS", 96 * 9)
    b = gaussian_blur(weighted_stack(n, mask), 16.0)[..., :3]
    expect = (b @ l) / np.maximum(np.sqrt(np.einsum("...i,...i->...", b, b)), 1e-12)
    got = smoothed_cosines(n, 16.0, [l], mask=mask)[0]
    assert np.abs(got - expect).max() < 2e-6


def test_the_stack_without_its_weight_blurs_to_the_same_directions():
    """weighted_stack(weight=False) is the (w n) of the full stack, and OpenCV's Gaussian of its three
    channels equals that of the four's first three, bit for bit (what exaggerated shading's and
    multiscale curvature's strips rely on)."""
    import cv2

    from common.rgbn.smoothing import weighted_stack

    n, mask = _rough_normals(7, mask_columns=(10, 60))
    full, wn = weighted_stack(n, mask), weighted_stack(n, mask, weight=False)
    assert wn.shape == n.shape and np.array_equal(wn, full[..., :3])
    for sigma in (0.7, 2.8, 4.7):
        blur4 = cv2.GaussianBlur(full, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        blur3 = cv2.GaussianBlur(wn, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        assert np.array_equal(blur3, blur4[..., :3])
