import cv2
import numpy as np
import pytest

from common.render._util import as_light, dot_light
from common.render.enhance import (block_artefacts, coarse_normals, detail_shading, level_light, level_normals,
                                   gamut_map_lab, lab_to_linear_rgb, lightness_relief, normal_noise, normal_unsharp_masking, relief_scale_px,
                                   robust_range, shoulder, specular_enhancement, tone_curve)
from common.rgbn.io import linear_to_srgb
from tests.rgbn.analytic import gaussian_bump, normals_from_height, tilted_plane


def _flat(size=256):
    n = np.zeros((size, size, 3), np.float32)
    n[..., 2] = 1
    return n


def test_robust_range_clips_at_most_the_stated_share():
    v = np.random.default_rng(0).standard_normal(100_000).astype(np.float32)
    lo, hi = robust_range(v, clip_percent=0.5)
    assert np.mean(v < lo) <= 0.0051 and np.mean(v > hi) <= 0.0051
    assert lo == pytest.approx(-2.576, abs=0.05) and hi == pytest.approx(2.576, abs=0.05)


def test_tone_curve_puts_the_percentiles_at_a_fifth_and_four_fifths_and_rolls_off_the_tails():
    v = np.random.default_rng(1).standard_normal(200_000).astype(np.float32)
    lo, hi = robust_range(v, clip_percent=5.0)
    t = tone_curve(v, lo, hi)
    p5, p95 = np.percentile(t, [5, 95])
    assert p5 == pytest.approx(0.2, abs=0.01) and p95 == pytest.approx(0.8, abs=0.01)
    # a Gaussian has nothing beyond ~4.5 half-ranges: nothing saturates in 8 bits
    assert np.mean(np.round(t * 255) >= 255) + np.mean(np.round(t * 255) <= 0) < 1e-3


def test_shoulder_is_the_identity_below_the_knee_and_never_reaches_white():
    v = np.array([0.0, 0.5, 0.8, 1.0, 3.0], np.float32)
    out = shoulder(v)
    assert np.allclose(out[:3], v[:3]) and out[3] < 1.0 and out[4] <= 1.0 and out[3] > 0.9


def test_noise_of_a_normal_map_is_measured_in_normal_units():
    rng = np.random.default_rng(2)
    n = normals_from_height(*np.gradient(gaussian_bump_height(256)))
    noisy = n.copy()
    noisy[..., :2] += rng.normal(0, 0.02, n[..., :2].shape).astype(np.float32)
    assert normal_noise(n) < 0.003  # a smooth surface has (almost) no pixel noise
    assert normal_noise(noisy) == pytest.approx(0.02, rel=0.15)


def gaussian_bump_height(size):
    y, x = np.mgrid[0:size, 0:size] - size / 2
    return (8.0 * np.exp(-(x * x + y * y) / (2 * (size / 6) ** 2))).astype(np.float32)


def test_jpeg_blocks_are_detected_and_raise_the_smoothing_scale():
    rng = np.random.default_rng(3)
    n = _flat(256)
    n[..., 0] = rng.normal(0, 0.005, (256, 256))
    clean = block_artefacts(n)
    blocky = n.copy()
    steps = rng.normal(0, 0.03, (32, 32)).astype(np.float32)
    blocky[..., 0] += np.kron(steps, np.ones((8, 8), np.float32))  # constant 8x8 offsets: JPEG-like
    assert clean < 1.2 and block_artefacts(blocky) > 1.5
    sigma, evidence = relief_scale_px(blocky, 300.0)
    assert sigma >= 2.0 and evidence["blocks"] > 1.3


def test_smoothing_scale_has_a_physical_floor_from_the_dpi():
    sigma, evidence = relief_scale_px(_flat(64), 600.0, min_mm=0.2)
    assert sigma == pytest.approx(0.2 * 600 / 25.4, rel=1e-6)


def test_levelling_takes_a_tilted_plane_to_the_view_axis_and_keeps_detail():
    plane = tilted_plane(64, 30.0, 0.0)
    assert np.allclose(level_normals(plane, 8.0), (0, 0, 1), atol=1e-5)
    # a bump on a tilted panel: levelled, it looks like the bump on a level panel
    height = gaussian_bump_height(128) * 0.2
    gy, gx = np.gradient(height)
    tilted = normals_from_height(gx + 0.4, -gy)  # the panel rises 0.4 per pixel to the right
    level = normals_from_height(gx, -gy)
    out = level_normals(tilted, 40.0)
    centre = (slice(40, 88), slice(40, 88))
    assert np.abs(out[centre] - level[centre]).max() < 0.05
    # the levelled light is the same lighting as the levelled normals
    a = dot_light(out, as_light((135.0, 12.0)))
    b = dot_light(tilted, level_light((135.0, 12.0), coarse_normals(tilted, 40.0, full_size=False), (128, 128)))
    assert np.abs(a - b)[centre].max() < 1e-3


def test_lightness_relief_keeps_hue_and_chroma_and_never_saturates():
    albedo = np.zeros((32, 32, 3), np.float32)
    albedo[:] = (0.4, 0.1, 0.05)  # a red ochre
    relief = np.linspace(-1, 1, 32 * 32, dtype=np.float32).reshape(32, 32)
    out = lightness_relief(albedo, relief, strength=0.6)
    lab_in = cv2.cvtColor(linear_to_srgb(albedo), cv2.COLOR_RGB2Lab)
    lab_out = cv2.cvtColor(out, cv2.COLOR_RGB2Lab)
    hue_in = np.arctan2(lab_in[..., 2], lab_in[..., 1])
    hue_out = np.arctan2(lab_out[..., 2], lab_out[..., 1])
    inside = (out.max(axis=2) < 0.999) & (out.min(axis=2) > 0.001)  # sRGB gamut clipping aside
    assert np.degrees(np.abs(hue_out - hue_in))[inside].max() < 3.0
    # lightness moves with the relief, monotonically
    L = lab_out[..., 0].ravel()
    assert L[0] < lab_in[0, 0, 0] < L[-1] and np.all(np.diff(L) >= -0.5)
    assert L.min() > 0 and L.max() < 100
    # zero relief = the colour itself
    same = lightness_relief(albedo, np.zeros((32, 32), np.float32))
    assert np.allclose(same, linear_to_srgb(albedo), atol=2e-3)


def test_detail_shading_is_zero_on_smooth_shape_and_signed_on_a_bump():
    plane = tilted_plane(64, 20.0, 10.0)
    assert np.abs(detail_shading(plane, sigma_px=4.0, fine_px=1.0)).max() < 1e-4
    bump = gaussian_bump(96, 0.1, 0.05, 0.2)  # 0.2 mm wide: detail at a 1 mm unsharp scale
    d = detail_shading(bump, (180.0, 30.0), sigma_px=10.0, fine_px=0.0)
    # light from the left: the bump's left flank (facing it) lights up, the right one darkens
    assert d[48, 44] > 0.01 and d[48, 52] < -0.01


def test_normal_unsharp_masking_of_a_plane_is_plain_lambert_and_amplifies_a_bump():
    plane = tilted_plane(32, 20.0, 0.0)
    l = as_light((0.0, 45.0))
    assert np.allclose(normal_unsharp_masking(plane, l, sigma_px=3.0, gain=4.0), np.maximum(dot_light(plane, l), 0),
                       atol=1e-5)
    bump = gaussian_bump(96, 0.1, 0.05, 0.3)
    plain = np.maximum(dot_light(bump, as_light((180.0, 30.0))), 0)
    sharp = normal_unsharp_masking(bump, (180.0, 30.0), sigma_px=12.0, gain=3.0)
    assert sharp.std() > 2 * plain.std()


def test_specular_enhancement_peaks_where_the_normal_is_the_half_vector():
    l = as_light((0.0, 60.0))
    h = (l + np.array([0, 0, 1], np.float32)) / np.linalg.norm(l + np.array([0, 0, 1], np.float32))
    n = np.zeros((3, 1, 3), np.float32)
    n[0, 0] = h
    n[1, 0] = (0, 0, 1)
    n[2, 0] = (0, 1, 0)
    out = specular_enhancement(n, l, albedo=np.zeros_like(n), kd=0.0, ks=0.7, exponent=40.0)
    assert out[0, 0, 0] == pytest.approx(0.7, abs=1e-4)
    assert out[1, 0, 0] == pytest.approx(0.7 * float(h[2]) ** 40, abs=1e-4)
    assert out[2, 0, 0] < 1e-6


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="clip_percent"):
        robust_range(np.zeros(4), clip_percent=30)
    with pytest.raises(ValueError, match="strength"):
        lightness_relief(np.zeros((2, 2, 3)), np.zeros((2, 2)), strength=2)
    with pytest.raises(ValueError, match="exponent"):
        specular_enhancement(_flat(4), exponent=0)
    with pytest.raises(ValueError, match="dpi"):
        relief_scale_px(_flat(4), 0)


def _lab_of_display(rgb):
    """CIELAB of display sRGB in float64 by scikit-image (an implementation independent of ours and
    more precise than OpenCV's float tables)."""
    from skimage.color import rgb2lab

    return rgb2lab(np.asarray(rgb, np.float64))


def test_an_out_of_gamut_colour_is_mapped_with_its_hue_and_lightness_kept_and_chroma_reduced():
    """Pure sRGB blue lightened by relief leaves the gamut (sRGB has no light saturated blue).
    Documented: L* = L + strength r (100 - L) exactly, the hue kept, the chroma reduced to the
    largest that fits — so the colour lands on the gamut's surface (a channel at 0 or 1)."""
    blue = np.zeros((1, 4, 3), np.float32)
    blue[..., 2] = 1.0
    relief = np.array([[0.0, 0.3, 0.6, 1.0]], np.float32)
    out = lightness_relief(blue, relief, strength=0.6)
    lab_in = cv2.cvtColor(blue, cv2.COLOR_LRGB2Lab)[0, 0]
    expected_L = lab_in[0] + 0.6 * relief[0] * (100.0 - lab_in[0])     # the documented soft light
    lab_out = _lab_of_display(out)[0]
    hue_in = np.degrees(np.arctan2(lab_in[2], lab_in[1]))
    hue_out = np.degrees(np.arctan2(lab_out[:, 2], lab_out[:, 1]))
    assert np.abs(lab_out[:, 0] - expected_L).max() < 0.05
    assert np.abs(hue_out - hue_in).max() < 0.2
    chroma_in, chroma_out = np.hypot(lab_in[1], lab_in[2]), np.hypot(lab_out[:, 1], lab_out[:, 2])
    assert np.all(np.diff(chroma_out) < -5) and chroma_out[0] == pytest.approx(chroma_in, rel=0.01)
    # on the gamut's surface: the chroma cannot grow (blue stays at 1, red and green above 0)
    assert np.all(out.max(axis=2) > 0.999) and out.min() >= 0.0 and out.max() <= 1.0
    # what clipping each channel does instead (OpenCV's float Lab2RGB): the hue turns by degrees
    lab_req = np.stack([expected_L, np.full(4, lab_in[1]), np.full(4, lab_in[2])], axis=1)[None].astype(np.float32)
    clipped = _lab_of_display(cv2.cvtColor(lab_req, cv2.COLOR_Lab2RGB))[0]
    assert np.abs(np.degrees(np.arctan2(clipped[1:, 2], clipped[1:, 1])) - hue_in).max() > 3.0


def test_gamut_mapping_of_a_primary_pushed_outwards_returns_the_primary():
    """At blue's lightness and hue, the most chroma sRGB can show is blue's own: the cube's corner.
    Twice that chroma maps back onto (0, 0, 1) exactly (analytic), and a colour inside is unchanged."""
    lab = cv2.cvtColor(np.array([[[0.0, 0.0, 1.0], [0.3, 0.2, 0.1]]], np.float32), cv2.COLOR_LRGB2Lab)[0]
    L, a, b = lab[:, 0], lab[:, 1] * np.array([2.0, 1.0], np.float32), lab[:, 2] * np.array([2.0, 1.0], np.float32)
    assert lab_to_linear_rgb(L[:1], a[:1], b[:1]).min() < -0.05        # really outside
    out = gamut_map_lab(L, a, b)
    assert np.allclose(out[0], (0.0, 0.0, 1.0), atol=2e-3)
    assert np.allclose(out[1], (0.3, 0.2, 0.1), atol=1e-4)
    assert np.allclose(lab_to_linear_rgb(L, lab[:, 1], lab[:, 2]), [(0.0, 0.0, 1.0), (0.3, 0.2, 0.1)], atol=1e-4)


def test_lightness_relief_recomputes_only_what_opencv_clipped():
    """Colours inside the gamut come out as OpenCV's Lab2RGB draws them; none is left clipped."""
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.0, 1.0, (64, 64, 3)).astype(np.float32)
    relief = rng.uniform(-1.0, 1.0, (64, 64)).astype(np.float32)
    out = lightness_relief(albedo, relief, strength=0.9)
    lab = cv2.cvtColor(albedo, cv2.COLOR_LRGB2Lab)
    L = lab[..., 0]
    r = relief * 0.9
    lab[..., 0] = L + r * np.where(r > 0, 100.0 - L, L)
    exact = lab_to_linear_rgb(lab[..., 0], lab[..., 1], lab[..., 2])
    inside = ((exact >= 0) & (exact <= 1)).all(axis=2)
    assert 0.05 < 1 - inside.mean() < 0.95                              # both kinds present
    assert np.abs(out[inside] - cv2.cvtColor(lab, cv2.COLOR_Lab2RGB)[inside]).max() < 1e-6
    lab_out = _lab_of_display(out)
    hue_err = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(lab_out[..., 2], lab_out[..., 1])
                                                       - np.arctan2(lab[..., 2], lab[..., 1]))))))
    # the mapped colours keep their hue (where there is chroma to have one) and lightness
    chromatic = ~inside & (np.hypot(lab_out[..., 1], lab_out[..., 2]) > 5)
    assert hue_err[chromatic].max() < 0.2
    assert np.abs(lab_out[..., 0] - lab[..., 0])[~inside].max() < 0.05


def test_masked_stride_is_every_kth_mask_pixel_in_order():
    from common.render.enhance import masked_stride
    rng = np.random.default_rng(2)
    v = rng.random((1500, 1100, 3)).astype(np.float32)
    m = rng.random((1500, 1100)) > 0.4
    for limit in (1, 1000, 123457, 10 ** 8):
        step = int(np.ceil(np.count_nonzero(m) / limit))
        assert np.array_equal(masked_stride(v, m, limit), v[m][::step])
        assert np.array_equal(masked_stride(v[..., 1], m, limit), v[..., 1][m][::step])


def _low_contrast_fragment(spread_l, noise_l, size=256, seed=4):
    """An RGBN image of one colour whose CIELAB lightness varies smoothly over ``spread_l`` L*
    (5th-95th percentile) around L* 75, plus white noise of ``noise_l`` L* (a metal coin's
    albedo), on a flat surface."""
    import cv2

    from common.rgbn.image import RGBNImage
    rng = np.random.default_rng(seed)
    pattern = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), 12)
    lo, hi = np.percentile(pattern, [5, 95])
    L = 75.0 + spread_l * ((pattern - lo) / (hi - lo) - 0.5) + rng.normal(0, noise_l, (size, size))
    lab = np.dstack([L, np.full_like(L, 4.0), np.full_like(L, 14.0)]).astype(np.float32)
    albedo = cv2.cvtColor(lab, cv2.COLOR_Lab2LRGB)
    normals = np.zeros((size, size, 3), np.float32)
    normals[..., 2] = 1.0
    return RGBNImage(albedo=albedo, mask=np.ones((size, size), bool), dpi=600.0, normals=normals)


def _tone_span(rgb):
    """5th-95th percentile span of the 8-bit luminance, as a share of the range (the bench's measure)."""
    lum = np.round(np.clip(rgb, 0, 1) * 255) @ np.array([0.2126, 0.7152, 0.0722])
    p5, p95 = np.percentile(lum, [5, 95])
    return (p95 - p5) / 255


@pytest.mark.parametrize("style", ["albedo", "toon", "specular", "watercolour"])
def test_a_low_contrast_colour_is_exposed_over_half_the_tone_range_by_default(style):
    """A colour that varies 8 L* with 0.5 L* of noise (the flatbed coin: 7.9 and 0.58) is
    stretched to L* 20-80 (the old fixed 15-L* floor drew it over a third of the range)."""
    from common.render.recipes import render
    image = _low_contrast_fragment(8.0, 0.5)
    out = render(image, style)
    assert _tone_span(out.rgb) >= 0.5


def test_a_colour_that_is_mostly_noise_is_not_stretched_into_amplified_noise():
    """1.5 L* of spread with 0.5 L* of noise: the range is widened to 10 x the noise (5 L*) or
    6 L*, so the noise is drawn at most ~6 L* strong (gain <= 10), not at 60 L* / 1.5."""
    from common.render.enhance import MIN_LIGHTNESS_RANGE, lightness_noise, lightness_range
    image = _low_contrast_fragment(1.5, 0.5)
    assert abs(lightness_noise(image.albedo) - 0.5) < 0.1
    lo, hi = lightness_range(image.albedo)
    assert hi - lo >= MIN_LIGHTNESS_RANGE - 1e-6
    image = _low_contrast_fragment(1.0, 1.0)   # noise 1 L*: 10 L* of range
    lo, hi = lightness_range(image.albedo)
    assert 9.0 <= hi - lo <= 11.0


def test_median_is_numpys_median_for_odd_and_even_counts_and_any_nan():
    from common.render.enhance import median

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 10, 11, 1000, 1001):
        for dtype in (np.float32, np.float64):
            v = rng.standard_normal(n).astype(dtype)
            v[: n // 3] = v[0]        # ties, as in quantised residuals
            assert median(v) == np.median(v)
            assert median(v).dtype == np.median(v).dtype
    v = rng.standard_normal(101)
    v[7] = np.nan
    assert np.isnan(median(v)) and np.isnan(np.median(v))


def test_exposing_an_encoded_picture_decodes_it_strip_by_strip_to_the_same_colours(monkeypatch):
    """lightness_relief / lightness_range of display colour with encoded=True against the same of its
    decoded copy (srgb_to_linear of the whole), narrow enough for the noise floor to count."""
    from common.rgbn import smoothing
    from common.rgbn.io import srgb_to_linear
    from common.render.enhance import lightness_range

    monkeypatch.setattr(smoothing, "STRIP_PIXELS", 64 * 7)   # strips of 7 rows
    rng = np.random.default_rng(4)
    display = np.clip(0.55 + 0.03 * rng.standard_normal((90, 64, 3)), 0, 1).astype(np.float32)
    mask = np.zeros((90, 64), bool)
    mask[5:80, 3:60] = True
    rng_lin = lightness_range(srgb_to_linear(display), mask)
    assert lightness_range(display, mask, encoded=True) == rng_lin
    expect = lightness_relief(srgb_to_linear(display), np.zeros((90, 64), np.float32), strength=0.0, exposure=rng_lin)
    assert np.array_equal(lightness_relief(display, None, strength=0.0, exposure=rng_lin, encoded=True), expect)


def test_a_window_of_a_tiles_coarse_field_is_the_whole_fields_on_its_pixels():
    """:func:`coarse_window` of a field that is itself a window's (a tile's, any offset) gives the
    whole field's values on the window's pixels, as the window taken from the whole field does."""
    from common.render.enhance import coarse_window

    rng = np.random.default_rng(0)
    n = rng.normal(0, 0.2, (400, 300, 3)).astype(np.float32)
    n[..., 2] = 1.0
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    field = coarse_normals(n, 40.0, full_size=False)
    assert field.factor > 1
    tile = coarse_window(field, 37, 261, 53, 290)
    for r0, r1, c0, c1 in ((0, 40, 0, 30), (101, 180, 77, 200), (150, 224, 200, 237)):
        direct = coarse_window(field, 37 + r0, 37 + r1, 53 + c0, 53 + c1).full((r1 - r0, c1 - c0))
        nested = coarse_window(tile, r0, r1, c0, c1).full((r1 - r0, c1 - c0))
        assert np.array_equal(nested, direct)
        whole = field.full((400, 300))[37 + r0:37 + r1, 53 + c0:53 + c1]
        assert np.abs(nested - whole).max() < 1e-5


@pytest.mark.parametrize("factor", [1, 2, 3, 4, 16, 24])
def test_a_coarse_fields_rows_are_the_bilinear_map_of_its_cells_with_edges_replicated(factor):
    """:meth:`Coarse.full` (a resize of the cells the rows read, shifted and edge-replicated)
    against OpenCV's warpAffine of the same map, which it replaced for factors 2-16 (a power of two:
    the map's positions fall on warpAffine's 1/32-pixel grid) and still draws for others: equal to
    float rounding; any offset, any rows, windows that start before or end past the cells."""
    from common.render.enhance import Coarse

    rng = np.random.default_rng(factor)
    for trial in range(12):
        ch = () if trial % 2 else (3,)
        cells = rng.random((int(rng.integers(2, 9)), int(rng.integers(2, 9))) + ch).astype(np.float32)
        offset = (int(rng.integers(-2 * factor, 2 * factor + 1)), int(rng.integers(-2 * factor, 2 * factor + 1)))
        h, w = int(rng.integers(1, 12 * factor)), int(rng.integers(1, 12 * factor))
        r0 = int(rng.integers(0, h))
        r1 = int(rng.integers(r0 + 1, h + 1))
        got = Coarse(cells, factor, offset).full((h, w), rows=(r0, r1))
        f = float(factor)
        m = np.array([[1 / f, 0.0, (0.5 - offset[1]) / f - 0.5], [0.0, 1 / f, (0.5 + r0 - offset[0]) / f - 0.5]])
        ref = cv2.warpAffine(cells, m, (w, r1 - r0), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE).reshape((r1 - r0, w) + ch)
        assert got.shape == ref.shape
        assert np.abs(got - ref).max() <= 2e-6, (trial, offset, (h, w), (r0, r1))
