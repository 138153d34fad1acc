"""extract_features / FeatureTable / save_features / load_features (common/features/table.py).

The invariance tests hold every descriptor to the tolerance stated in the registry
(``Descriptor.tolerance + rel_tolerance * max(|a|, |b|)``) when the same fragment is turned by an
arbitrary angle on the scanner (image AND normals' x, y rotated) or when scanner noise is added.
"""

import numpy as np
import pytest

from common.features import (DESCRIPTORS, FeatureTable, correspondence, extract_features,
                             fragment_descriptors, load_features, patch_descriptors, save_features)
from common.features.patches import MIN_COVERAGE
from common.rgbn.image import RGBNImage
from common.store import Store
from tests.features._fragments import (add_scanner_noise, match_patches, rotate_rgbn, rotation_back,
                                       textured_fragment)

ANGLES = (17.0, 143.0, 251.0)


_FRAGMENTS = {}


def _fragment(seed):
    if seed not in _FRAGMENTS:
        img = textured_fragment(dpi=150, seed=seed)
        _FRAGMENTS[seed] = (img, extract_features(img))
    return _FRAGMENTS[seed]


@pytest.fixture(scope="module")
def fragment():
    return _fragment(0)


@pytest.fixture(scope="module")
def stroke_fragment():
    img = textured_fragment(dpi=150, seed=3, crack=False, bumps=False)
    return img, extract_features(img)


def _variants(img, table, kind):
    if kind == "noise":
        return add_scanner_noise(img), (lambda p: p), table.contour_mm[0]
    a = float(kind)
    start = rotation_back(img.shape, img.pixel_mm, -a)(table.contour_mm[:1])[0]
    return rotate_rgbn(img, a), rotation_back(img.shape, img.pixel_mm, a), start


def _violations(ref: FeatureTable, other: FeatureTable, pairs, names=None):
    bad = []
    for d in fragment_descriptors():
        if names and d.name not in names:
            continue
        a, b = ref.values[d.name], other.values[d.name]
        if np.isnan(a) and np.isnan(b):
            continue
        c = correspondence(d, a, b)
        if not c <= d.tolerance + d.rel_tolerance * max(abs(a), abs(b)):
            bad.append((d.key, a, b, c))
    for d in patch_descriptors():
        if names and d.name not in names:
            continue
        a = np.array([ref.patch_column(d.name)[i] for i, _ in pairs])
        b = np.array([other.patch_column(d.name)[j] for _, j in pairs])
        # the same contour point: convex stays convex, so compare a with -(-b) under abs_sum
        c = correspondence(d, a, -b if d.rule == "abs_sum" else b)
        ok = np.isfinite(a) & np.isfinite(b)
        lim = d.tolerance + d.rel_tolerance * np.maximum(np.abs(a), np.abs(b))
        if np.any(c[ok] > lim[ok]) or np.any(np.isfinite(a) != np.isfinite(b)):
            k = int(np.nanargmax(np.where(ok, c - lim, -np.inf)))
            bad.append((d.key, a[k], b[k], c[k]))
    return bad


@pytest.mark.parametrize("seed,kind", [(0, a) for a in (*ANGLES, "noise")] + [(1, 143.0), (1, "noise")])
def test_descriptors_within_tolerance_under_rotation_and_scanner_noise(seed, kind):
    img, ref = _fragment(seed)
    other_img, back, start = _variants(img, ref, kind)
    other = extract_features(other_img, contour_start_mm=start)
    pairs = match_patches(ref, other, back, max_mm=1.0)
    assert len(pairs) == ref.n_patches and ref.n_patches > 40
    skip = {"orient_frequency", "orient_amplitude", "orient_angle"}  # held on the stroke fragment
    names = [d.name for d in DESCRIPTORS.values() if d.name not in skip]
    assert _violations(ref, other, pairs, names) == []


@pytest.mark.parametrize("kind", [17.0, 251.0, "noise"])
def test_dominant_orientation_within_tolerance_on_a_stroke_pattern(stroke_fragment, kind):
    img, ref = stroke_fragment
    other_img, back, start = _variants(img, ref, kind)
    other = extract_features(other_img, contour_start_mm=start)
    pairs = match_patches(ref, other, back, max_mm=1.0)
    assert len(pairs) == ref.n_patches
    assert _violations(ref, other, pairs, {"orient_frequency", "orient_amplitude", "orient_angle"}) == []


def test_dominant_frequency_is_twice_the_stroke_frequency(stroke_fragment):
    # nz of a sinusoidal relief h = A sin(2 pi u / P) oscillates at 2 / P (nz ~ 1 - h'^2 / 2)
    _, t = stroke_fragment
    assert t.values["orient_frequency"] == pytest.approx(2 / 3.0, rel=0.03)
    assert np.nanmedian(t.patch_column("orient_frequency")) == pytest.approx(2 / 3.0, rel=0.05)


def test_patch_orientation_angle_follows_the_contour_normal(stroke_fragment):
    # strokes at 30 deg: wave vector at 30 deg (x right, y down); relative to the normal it is
    # 30 - angle(normal), axially
    _, t = stroke_fragment
    ok = np.isfinite(t.patch_column("orient_angle")) & (t.patch_kind == "p10")
    normal_angle = np.degrees(np.arctan2(t.patch_normals[ok, 1], t.patch_normals[ok, 0]))
    expect = np.mod(30.0 - normal_angle, 180.0)
    d = correspondence(DESCRIPTORS["patch.orient_angle"], t.patch_column("orient_angle")[ok], expect)
    assert np.median(d) < 3.0 and np.mean(d < 8.0) > 0.9


def test_a_300_and_a_600_dpi_scan_of_one_fragment_are_described_alike():
    # both share the 0.0847 mm working grid; every descriptor but the dominant orientation (held
    # on stroke patterns only) agrees within its rotation/noise tolerance
    a = textured_fragment(dpi=300, seed=0, size_mm=40, canvas=1.2)
    b = textured_fragment(dpi=600, seed=0, size_mm=40, canvas=1.2)
    ta = extract_features(a)
    ca = (np.array(a.shape[::-1]) - 1) / 2 * a.pixel_mm  # the canvases share their centre
    cb = (np.array(b.shape[::-1]) - 1) / 2 * b.pixel_mm
    tb = extract_features(b, contour_start_mm=ta.contour_mm[0] - ca + cb)
    assert ta.work_pixel_mm == pytest.approx(tb.work_pixel_mm)
    pairs = match_patches(ta, tb, lambda p: p - cb + ca, max_mm=1.0)
    assert len(pairs) == ta.n_patches == tb.n_patches
    names = [d.name for d in DESCRIPTORS.values() if not d.name.startswith("orient")]
    assert _violations(ta, tb, pairs, names) == []


def test_table_columns_match_the_registry(fragment):
    _, t = fragment
    assert list(t.values) == [d.name for d in fragment_descriptors()]
    assert t.patch_names == [d.name for d in patch_descriptors()]
    assert t.patch_values.shape == (t.n_patches, len(t.patch_names))
    assert set(t.patch_kind) == {"p10", "p20"}


def test_patches_are_5mm_apart_and_inset_from_the_contour(fragment):
    _, t = fragment
    p10 = t.patch_indices("p10")
    assert np.allclose(np.diff(t.patch_arc_mm[p10]), 5.0)
    inset = np.linalg.norm(t.patch_centers_mm - t.patch_contour_mm, axis=1)
    assert np.allclose(inset[p10], 8.0) and np.allclose(inset[t.patch_indices("p20")], 13.0)


def test_colour_only_image_gives_missing_normal_features_not_a_crash(fragment):
    img, ref = fragment
    t = extract_features(RGBNImage(img.albedo, img.mask, img.dpi))
    assert t.missing_data == ["height", "normal"]
    for d in fragment_descriptors():
        assert np.isnan(t.values[d.name]) == bool(d.needs & {"normal", "height"}), d.name
    covered = t.patch_coverage >= MIN_COVERAGE
    for d in patch_descriptors():
        col = t.patch_column(d.name)[covered]
        assert np.all(np.isnan(col)) == bool(d.needs & {"normal", "height"}), d.name
    # colour and contour descriptors do not depend on the normals
    assert t.values["colour_mean_r"] == ref.values["colour_mean_r"]
    assert np.array_equal(t.patch_column("curv_3pt_5"), ref.patch_column("curv_3pt_5"))


def test_patches_falling_off_a_thin_fragment_are_missing_with_their_coverage():
    # a 12 mm wide strip: 10 mm patches 8 mm in stick out of the far side, 20 mm ones more
    dpi = 100.0
    px = 25.4 / dpi
    yy, xx = np.mgrid[:260, :120]
    mask = (np.abs((xx - 60) * px) < 6.0) & (np.abs((yy - 130) * px) < 30.0)
    t = extract_features(RGBNImage(np.full(mask.shape + (3,), 0.4), mask, dpi))
    assert t.n_patches > 0
    low = t.patch_coverage < MIN_COVERAGE
    long_side = np.abs(t.patch_normals[:, 0]) > 0.9
    assert low[long_side & (t.patch_kind == "p20")].all() and not low[long_side & (t.patch_kind == "p10")].any()
    assert np.isnan(t.patch_column("colour_mean_r")[low]).all()
    assert np.allclose(t.patch_column("colour_mean_r")[~low], 0.4, atol=1e-5)
    assert np.isfinite(t.patch_column("curv_3pt_5")).any()  # contour cues stay


def test_uniform_fragment_has_zero_colour_variance_and_flat_normals():
    yy, xx = np.mgrid[:300, :300]
    mask = (yy - 150) ** 2 + (xx - 150) ** 2 < 130 ** 2
    n = np.zeros((300, 300, 3), np.float32)
    n[..., 2] = 1
    t = extract_features(RGBNImage(np.full((300, 300, 3), [0.6, 0.3, 0.3]), mask, 150.0, normals=n,
                                   height_mm=np.full((300, 300), 7.5)))
    assert t.values["colour_variance"] == pytest.approx(0.0, abs=1e-9)
    assert t.values["saturation"] == pytest.approx(0.5, abs=1e-6)
    assert t.values["normal_z_mean"] == pytest.approx(1.0) and t.values["normal_z_variance"] == pytest.approx(0, abs=1e-9)
    assert t.values["thickness_mean"] == pytest.approx(7.5)
    assert t.values["erosion_density_s0"] == 0.0
    ok = t.patch_coverage >= MIN_COVERAGE
    assert np.allclose(t.patch_column("colour_variance")[ok], 0.0, atol=1e-7)
    # a disc of radius 130 px = 22.0 mm: every contour patch sees curvature 1/22 mm
    R = 130 * 25.4 / 150
    for name in ("curv_3pt_10", "curv_area_10"):
        assert np.allclose(t.patch_column(name), 1 / R, rtol=0.05), name


def test_saved_table_loads_back_identically(tmp_path, fragment):
    _, t = fragment
    store = Store(tmp_path)
    ref = save_features(store, "fragments/F1/features/front-x.h5", t, provenance={"test": 1})
    u = load_features(store, ref)
    assert u.values.keys() == t.values.keys()
    assert all(np.array_equal(u.values[k], t.values[k], equal_nan=True) for k in t.values)
    assert u.patch_names == t.patch_names
    for name in ("patch_values", "patch_centers_mm", "patch_normals", "patch_arc_mm", "patch_coverage",
                 "patch_contour_mm", "contour_mm", "contour_normals"):
        assert np.array_equal(getattr(u, name), getattr(t, name), equal_nan=True), name
    assert list(u.patch_kind) == list(t.patch_kind)
    assert (u.dpi, u.face, u.fragment, u.missing_data) == (t.dpi, t.face, t.fragment, t.missing_data)


def test_unsolved_nan_pixels_do_not_poison_the_table(fragment):
    img, ref = fragment
    normals, albedo = img.normals.copy(), img.albedo.copy()
    rng = np.random.default_rng(5)
    holes = rng.random(img.shape) < 0.001
    normals[holes] = np.nan
    albedo[holes] = np.nan
    t = extract_features(RGBNImage(albedo, img.mask, img.dpi, normals=normals, height_mm=img.height_mm))
    assert all(np.isfinite(t.values[d.name]) == np.isfinite(ref.values[d.name]) for d in fragment_descriptors())
    assert np.array_equal(np.isfinite(t.patch_values), np.isfinite(ref.patch_values))
    assert t.values["normal_z_mean"] == pytest.approx(ref.values["normal_z_mean"], abs=1e-3)


def test_small_fragment_gets_patches_and_only_the_curvature_scales_that_fit():
    # a disc of radius 4 mm (perimeter 25 mm): 15 mm three-point spans would wrap around it
    yy, xx = np.mgrid[:100, :100]
    img = RGBNImage(np.full((100, 100, 3), 0.3), (yy - 50) ** 2 + (xx - 50) ** 2 < 40 ** 2, 254.0)
    t = extract_features(img)
    assert t.n_patches in (2 * 4, 2 * 5)  # every 5 mm of a ~25 mm outline
    assert np.isnan(t.patch_column("curv_3pt_15")).all()
    assert np.isfinite(t.patch_column("curv_area_15")).all()  # a disc of 15 mm still has an area
    assert np.allclose(t.patch_column("curv_3pt_5"), 1 / 4.0, rtol=0.1)
    assert np.isnan(t.patch_column("colour_mean_r")).all()  # 10 mm discs 8 mm in: off the fragment


def test_a_speck_of_a_fragment_is_described_without_a_crash():
    mask = np.zeros((40, 40), bool)
    mask[20, 20] = True
    n = np.zeros((40, 40, 3), np.float32)
    n[..., 2] = 1
    t = extract_features(RGBNImage(np.full((40, 40, 3), 0.3), mask, 600.0, normals=n))
    assert t.n_patches == 0 and t.values["colour_mean_r"] == pytest.approx(0.3, rel=1e-5)


def test_bad_input_is_refused_with_a_named_error():
    with pytest.raises(ValueError, match="image"):
        extract_features(np.zeros((4, 4, 3)))
    with pytest.raises(ValueError, match="empty"):
        extract_features(RGBNImage(np.zeros((8, 8, 3)), np.zeros((8, 8), bool), 100.0))

