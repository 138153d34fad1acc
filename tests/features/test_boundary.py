"""Boundary profiles: colour and thickness sampled along the contour, just inside it."""

import numpy as np
import pytest

from common.features import extract_features
from common.features.boundary import (BOUNDARY_DEPTHS_MM, STD_FLOOR, STD_SCALE, boundary_channel_names,
                                      boundary_profile)
from common.features.contour import fragment_contour
from common.rgbn.image import RGBNImage

PX = 0.1  # mm


def _disc(radius_mm=15.0, n=360):
    yy, xx = np.mgrid[:n, :n].astype(float)
    x, y = (xx - n / 2) * PX, (yy - n / 2) * PX
    return x, y, np.hypot(x, y) < radius_mm


def _cols(names, prefix):
    return [i for i, n in enumerate(names) if n.startswith(prefix)]


def test_samples_are_one_mm_apart_and_see_a_painted_rim_at_the_shallow_depth_only():
    """A disc of radius 15 mm with a 1.2 mm wide blue rim around a red field: the samples 0.8 mm
    inside lie on the rim, those 1.6 mm inside on the field; one sample per mm of perimeter."""
    x, y, mask = _disc()
    r = np.hypot(x, y)
    albedo = np.where((r > 15.0 - 1.2)[..., None], (0.1, 0.2, 0.8), (0.8, 0.2, 0.1)).astype(np.float32)
    contour = fragment_contour(mask, PX)
    prof, step = boundary_profile(contour, albedo, PX, weight=mask.astype(float))
    names = boundary_channel_names()
    assert prof.shape == (round(2 * np.pi * 15.0), len(names))
    assert step == pytest.approx(2 * np.pi * 15.0 / len(prof), rel=0.02)
    shallow = prof[:, [names.index(f"sqrt_{c}@0.8") for c in "rgb"]]
    deep = prof[:, [names.index(f"sqrt_{c}@1.6") for c in "rgb"]]
    np.testing.assert_allclose(shallow, np.sqrt([0.1, 0.2, 0.8])[None].repeat(len(prof), 0), atol=0.02)
    np.testing.assert_allclose(deep, np.sqrt([0.8, 0.2, 0.1])[None].repeat(len(prof), 0), atol=0.02)
    # no height map: the thickness channels are missing, not zero
    assert np.isnan(prof[:, _cols(names, "thickness@")]).all()


def test_profile_follows_colour_along_the_arc_and_thickness_where_given():
    """Left half yellow, right half green: the contour runs clockwise on screen from its start, so
    the colour switches at the two arcs where the contour crosses x = 0; thickness 12 mm + 0.1 x."""
    x, y, mask = _disc()
    albedo = np.where((x < 0)[..., None], (0.7, 0.6, 0.1), (0.1, 0.5, 0.2)).astype(np.float32)
    thickness = (12.0 + 0.1 * x).astype(np.float32)
    contour = fragment_contour(mask, PX)
    prof, step = boundary_profile(contour, albedo, PX, weight=mask.astype(float), thickness_mm=thickness)
    names = boundary_channel_names()
    pts, nrm = contour.at(np.arange(len(prof)) * step)
    at = pts - nrm * 0.8 - 180 * PX       # where the 0.8 mm samples lie, centred like x and y
    left = at[:, 0] < -0.5
    right = at[:, 0] > 0.5
    assert left.sum() > 40 and right.sum() > 40
    g = prof[:, names.index("sqrt_g@0.8")]
    assert np.allclose(g[left], np.sqrt(0.6), atol=0.01) and np.allclose(g[right], np.sqrt(0.5), atol=0.01)
    np.testing.assert_allclose(prof[:, names.index("thickness@0.8")], 12.0 + 0.1 * at[:, 0], atol=0.02)


def test_standardised_colour_does_not_change_when_the_fragment_fades_or_is_tinted():
    """Fading towards plaster white and a burial tint are per-channel affine changes of the albedo:
    the std_* channels stay (up to the small floor in the denominator), the sqrt_* channels move."""
    x, y, mask = _disc()
    rng = np.random.default_rng(0)
    bands = (np.floor((x + 20) / 4) % 3).astype(int)
    palette = np.array([(0.7, 0.3, 0.2), (0.2, 0.4, 0.6), (0.8, 0.75, 0.5)], np.float32)
    albedo = palette[bands] + rng.normal(0, 0.005, bands.shape + (3,)).astype(np.float32)
    faded = albedo * 0.6 + 0.4 * np.array([0.78, 0.75, 0.68], np.float32)
    tinted = albedo * np.array([0.95, 0.80, 0.58], np.float32)
    contour = fragment_contour(mask, PX)
    names = boundary_channel_names()
    std = _cols(names, "std_")
    sq = _cols(names, "sqrt_")
    base, _ = boundary_profile(contour, albedo, PX, weight=mask.astype(float))
    for changed in (faded, tinted):
        p, _ = boundary_profile(contour, changed, PX, weight=mask.astype(float))
        spread = np.abs(base[:, std]).mean()
        assert np.abs(p[:, std] - base[:, std]).mean() < 0.1 * spread
        assert np.abs(p[:, sq] - base[:, sq]).mean() > 0.03
    # the scale: standardised values are (a − mean) / (std + floor) × scale
    m = mask
    z = (albedo[m].mean(0), albedo[m].std(0))
    assert np.abs(base[:, std]).max() <= np.max(np.abs(albedo[m] - z[0]) / (z[1] + STD_FLOOR)) * STD_SCALE + 1e-3


def test_feature_table_carries_and_stores_the_profile(tmp_path):
    from common.features.table import load_features, save_features
    from common.store import Store

    x, y, mask = _disc(radius_mm=10.0, n=260)
    img = RGBNImage(np.where(mask[..., None], (0.5, 0.4, 0.3), 0.0).astype(np.float32), mask, dpi=25.4 / PX,
                    height_mm=np.where(mask, 15.0, 0.0).astype(np.float32))
    t = extract_features(img)
    assert t.boundary_names == boundary_channel_names() and len(BOUNDARY_DEPTHS_MM) == 2
    assert len(t.boundary_profile) == round(2 * np.pi * 10.0)
    np.testing.assert_allclose(t.boundary_profile[:, t.boundary_names.index("thickness@1.6")], 15.0, atol=0.05)
    store = Store(tmp_path)
    ref = save_features(store, "f.h5", t)
    back = load_features(store, ref)
    np.testing.assert_array_equal(back.boundary_profile, t.boundary_profile)
    assert back.boundary_names == t.boundary_names and back.boundary_step_mm == t.boundary_step_mm


def test_boundary_profile_rejects_bad_arguments():
    x, y, mask = _disc(n=120, radius_mm=4.0)
    contour = fragment_contour(mask, PX)
    a = np.full(mask.shape + (3,), 0.5, np.float32)
    with pytest.raises(ValueError, match="albedo"):
        boundary_profile(contour, a[..., 0], PX)
    with pytest.raises(ValueError, match="pixel_mm"):
        boundary_profile(contour, a, 0.0)
    with pytest.raises(ValueError, match="no pixels"):
        boundary_profile(contour, a, PX, weight=np.zeros(mask.shape))


def test_a_table_written_before_boundary_profiles_reads_with_an_empty_profile(tmp_path):
    """Schema-1 feature tables have no boundary datasets: they load, and the matcher falls back to
    the patch ranking for them (an empty profile is not indexed)."""
    import h5py

    from common.features.table import read_features, write_features
    from common.matching.index import MatchIndex
    from common.matching.pairs import fragment_cues

    x, y, mask = _disc(radius_mm=10.0, n=260)
    img = RGBNImage(np.where(mask[..., None], (0.5, 0.4, 0.3), 0.0).astype(np.float32), mask, dpi=25.4 / PX)
    with h5py.File(tmp_path / "old.h5", "w") as f:
        write_features(f.create_group("front"), extract_features(img))
        del f["front/boundary_names"], f["front/boundary_profile"]
        del f["front"].attrs["boundary_step_mm"]
        old = read_features(f["front"])
    assert old.boundary_profile.shape == (0, 0) and old.boundary_names == []
    index = MatchIndex()
    index.add(fragment_cues(old, "old"), old.contour_mm, old.boundary_profile)
    assert "old" in index and "old" not in index.profiles


def test_a_sample_is_the_paint_there_not_one_pixels_noise():
    # RePAIR-like plaster scanned at 150 dpi (0.17 mm a pixel: one sample is one pixel) with a scanner's
    # noise of 2 grey levels (sRGB): the samples scatter along a crack whose paint is uniform, and the
    # matcher reads the scatter as paint that does not continue. Smoothed at paint scale first
    # (sigma 0.15 mm), the scatter falls by the averaging's factor, ~1 / (2 sqrt(pi) sigma_px) ~ 1/3.
    from common.rgbn.io import linear_to_srgb, srgb_to_linear
    px = 25.4 / 150
    yy, xx = np.mgrid[:300, :300]
    mask = (yy - 150) ** 2 + (xx - 150) ** 2 < 130 ** 2
    clean = np.broadcast_to(srgb_to_linear(np.float32([0.80, 0.79, 0.77])), (300, 300, 3)).copy()
    noisy = srgb_to_linear(np.clip(linear_to_srgb(clean) + np.random.default_rng(0).normal(0, 2 / 255, clean.shape), 0, 1))
    contour = fragment_contour(mask, px)
    names = boundary_channel_names()

    def scatter(albedo, **kw):
        prof, _ = boundary_profile(contour, albedo.astype(np.float32), px, weight=mask.astype(np.float32), **kw)
        return float(prof[:, _cols(names, "sqrt_")].std(axis=0).mean())

    assert scatter(clean) == pytest.approx(0.0, abs=1e-6)
    raw, smoothed = scatter(noisy, sigma_mm=0.0), scatter(noisy)
    assert raw > 0.004 and smoothed < 0.45 * raw, (raw, smoothed)


def test_smoothing_keeps_the_edge_colour_and_a_band_in_place():
    # the normalised convolution does not mix the background's zeros into the edge, and a painted rim
    # sampled 0.4 mm from its inner border (2.7 sigma) keeps its colour: the first test's disc again
    x, y, mask = _disc()
    albedo = np.where((np.hypot(x, y) > 15.0 - 1.2)[..., None], (0.1, 0.2, 0.8), (0.8, 0.2, 0.1)).astype(np.float32)
    albedo[~mask] = 0
    contour = fragment_contour(mask, PX)
    sharp, _ = boundary_profile(contour, albedo, PX, weight=mask.astype(float), sigma_mm=0.0)
    smooth, _ = boundary_profile(contour, albedo, PX, weight=mask.astype(float))
    cols = _cols(boundary_channel_names(), "sqrt_")
    np.testing.assert_allclose(smooth[:, cols], sharp[:, cols], atol=0.01)
