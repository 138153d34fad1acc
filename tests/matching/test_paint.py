"""Paint continuity across a crack (common/matching/paint.py) on analytic cases: a plaster slab cut
straight through, 3 mm of material lost along the cut, the right-hand piece turned by 90 degrees into
its own image; a painted band crossing the cut, a band that does not continue, plain plaster."""

import numpy as np
import pytest

from common.matching.paint import PaintField, paint_continuity, paint_field

PX_MM = 0.25
PLASTER = (0.74, 0.70, 0.62)
RED = (0.55, 0.12, 0.08)


def _slab(seed=0, band=True, band_angle_deg=0.0, size=(60.0, 80.0)):
    """Linear albedo of a plaster slab (rows × cols = size mm) with faint texture and, optionally, a
    5 mm red band through its middle at ``band_angle_deg`` from the horizontal."""
    rng = np.random.default_rng(seed)
    h, w = int(size[0] / PX_MM), int(size[1] / PX_MM)
    img = np.empty((h, w, 3), np.float32)
    img[:] = PLASTER
    img *= 1 + rng.normal(0, 0.01, (h, w, 1)).astype(np.float32)
    if band:
        yy, xx = np.mgrid[0:h, 0:w] * PX_MM
        a = np.radians(band_angle_deg)
        across = -(xx - size[1] / 2) * np.sin(a) + (yy - size[0] / 2) * np.cos(a)
        img[np.abs(across) < 2.5] = RED
    return img


def _pieces(slab_a, slab_b=None, gap_mm=3.0, cut_mm=40.0):
    """A: the slab left of the cut (its frame = the slab's); B: right of it, material lost, turned
    90° counter-clockwise on screen into its own image. Returns (A albedo, A mask, B albedo, B mask,
    true pose of B in A's frame)."""
    slab_b = slab_a if slab_b is None else slab_b
    h, w = slab_a.shape[:2]
    ca = int(round((cut_mm - gap_mm / 2) / PX_MM))
    cb = int(round((cut_mm + gap_mm / 2) / PX_MM))
    alb_a = slab_a.copy()
    mask_a = np.zeros((h, w), bool)
    mask_a[4:h - 4, 4:ca] = True
    alb_a[~mask_a] = 0
    piece_b = slab_b[:, cb:].copy()
    mask_b = np.zeros(piece_b.shape[:2], bool)
    mask_b[4:h - 4, :piece_b.shape[1] - 4] = True
    piece_b[~mask_b] = 0
    wb = piece_b.shape[1]
    # np.rot90: new (row, col) = (wb − 1 − c, r), so p_slab = R(90°) p_new + ((wb − 1 + cb) px, 0)
    pose = (90.0, (wb - 1 + cb) * PX_MM, 0.0)
    return alb_a, mask_a, np.ascontiguousarray(np.rot90(piece_b)), np.ascontiguousarray(np.rot90(mask_b)), pose


def _fields(alb_a, mask_a, alb_b, mask_b):
    return paint_field(alb_a, mask_a, PX_MM), paint_field(alb_b, mask_b, PX_MM)


def _wrong_poses(pose):
    """Poses along the crack and turned: slid 8 and 15 mm along the cut, turned 12° and 180°."""
    a, tx, ty = pose
    return np.array([[a, tx, ty + 8.0], [a, tx, ty - 15.0], [a + 12.0, tx, ty], [a + 180.0, tx + 2 * 30, ty]])


def test_band_crossing_the_cut_scores_best_at_the_true_pose():
    fa, fb = _fields(*_pieces(_slab())[:4])
    pose = _pieces(_slab())[4]
    scores = paint_continuity(fa, fb, np.vstack([pose, _wrong_poses(pose)]))
    assert scores[0] > 3.0                      # mm of crack with continuing paint: the 5 mm band, both sides
    assert np.all(scores[0] > scores[1:] + 1.0)


def test_band_that_does_not_continue_gives_no_such_evidence():
    # B's band turned by 35°: at the true pose of the pieces it meets A's band only partly
    alb_a, mask_a, alb_b, mask_b, pose = _pieces(_slab(), _slab(band_angle_deg=35.0))
    turned = paint_continuity(*_fields(alb_a, mask_a, alb_b, mask_b), pose)[0]
    straight = paint_continuity(*_fields(*_pieces(_slab())[:4]), pose)[0]
    assert turned < straight - 2.0


def test_plain_plaster_is_neutral_at_every_pose():
    alb_a, mask_a, alb_b, mask_b, pose = _pieces(_slab(band=False))
    fa, fb = _fields(alb_a, mask_a, alb_b, mask_b)
    scores = paint_continuity(fa, fb, np.vstack([pose, _wrong_poses(pose)]))
    assert np.all(np.abs(scores) < 0.5)         # no evidence either way (a band gives > 3)


def test_many_poses_at_once_equal_one_at_a_time():
    fa, fb = _fields(*_pieces(_slab())[:4])
    pose = _pieces(_slab())[4]
    poses = np.vstack([pose, _wrong_poses(pose)])
    together = paint_continuity(fa, fb, poses)
    one_by_one = np.array([paint_continuity(fa, fb, p)[0] for p in poses])
    np.testing.assert_allclose(together, one_by_one, rtol=1e-5, atol=1e-6)


def test_field_carries_the_band_across_the_edge_and_replaces_the_rim():
    alb_a, mask_a, *_ = _pieces(_slab())
    alb_a = alb_a.copy()
    rim = mask_a & ~np.pad(mask_a[2:-2, 2:-2], 2)   # the outer 0.5 mm discoloured: darkened
    alb_a[rim] *= 0.3
    fa = paint_field(alb_a, mask_a, PX_MM)
    assert isinstance(fa, PaintField)
    red_lab = paint_field(np.tile(np.float32(RED), (40, 40, 1)), np.ones((40, 40), bool), PX_MM).plaster_lab
    for x_mm in (38.0, 40.0, 44.0):              # the rim, the lost material, 5.5 mm past the edge
        col, row = np.round((np.array([x_mm, 30.0]) - fa.origin_mm) / fa.cell_mm).astype(int)
        carried = fa.field[row, col] / np.array([0.5, 1, 1])
        assert np.linalg.norm(carried - red_lab) < 6.0, x_mm
    # every sample is in the band 1-4 mm inside the outline
    assert np.all(fa.samples_mm[:, 0] <= 38.5 - 1.0 + 1e-6)


@pytest.mark.parametrize("kwargs, match", [
    (dict(albedo=np.zeros((10, 10)), mask=np.ones((10, 10), bool), pixel_mm=0.25), "albedo"),
    (dict(albedo=np.zeros((10, 10, 3)), mask=np.ones((9, 10), bool), pixel_mm=0.25), "mask"),
    (dict(albedo=np.zeros((10, 10, 3)), mask=np.ones((10, 10), bool), pixel_mm=0.0), "pixel_mm"),
    (dict(albedo=np.zeros((10, 10, 3)), mask=np.zeros((10, 10), bool), pixel_mm=0.25), "no fragment"),
])
def test_bad_fragment_is_refused_naming_the_problem(kwargs, match):
    with pytest.raises(ValueError, match=match):
        paint_field(**kwargs)


def test_bad_poses_are_refused_naming_the_problem():
    fa, fb = _fields(*_pieces(_slab())[:4])
    with pytest.raises(ValueError, match="poses"):
        paint_continuity(fa, fb, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="poses"):
        paint_continuity(fa, fb, [[0.0, np.nan, 0.0]])
    with pytest.raises(ValueError, match="field_b"):
        paint_continuity(fa, np.zeros(3), [[0.0, 0.0, 0.0]])


def test_field_from_the_stored_boundary_profile_tells_the_true_pose_too():
    from common.features.boundary import boundary_profile
    from common.features.contour import fragment_contour
    from common.matching.paint import paint_field_from_profile

    alb_a, mask_a, alb_b, mask_b, pose = _pieces(_slab())
    fields = []
    for alb, mask in ((alb_a, mask_a), (alb_b, mask_b)):
        contour = fragment_contour(mask, PX_MM)
        profile, step = boundary_profile(contour, alb, PX_MM, weight=mask.astype(float))
        f = paint_field_from_profile(contour.points_mm, profile, step)
        rows, cols = np.round(f.samples_mm[:, ::-1] / PX_MM).astype(int).T
        assert mask[rows, cols].mean() > 0.95       # the samples lie inside the fragment
        fields.append(f)
    scores = paint_continuity(*fields, np.vstack([pose, _wrong_poses(pose)]))
    assert scores[0] > 3.0
    assert np.all(scores[0] > scores[1:] + 1.0)
    with pytest.raises(ValueError, match="profile"):
        paint_field_from_profile(fragment_contour(mask_a, PX_MM).points_mm, np.zeros((5, 3)), 1.0)


def test_pair_evidence_is_the_best_paint_over_the_docking_candidates():
    from common.features.contour import fragment_contour
    from common.matching.paint import paint_pair_mm

    alb_a, mask_a, alb_b, mask_b, _ = _pieces(_slab())
    fa, fb = _fields(alb_a, mask_a, alb_b, mask_b)
    ca, cb = fragment_contour(mask_a, PX_MM).points_mm, fragment_contour(mask_b, PX_MM).points_mm
    band_mm, found = paint_pair_mm(fa, fb, ca, cb)
    # the slab is symmetric (the band runs through A's far side too), so only the evidence is checked
    assert band_mm > 3.0
    assert band_mm == pytest.approx(paint_continuity(fa, fb, found)[0])
    plain_mm, _ = paint_pair_mm(*_fields(*_pieces(_slab(band=False))[:4]), ca, cb)
    assert abs(plain_mm) < 1.0 < band_mm


def test_paint_raises_a_join_probability_in_proportion_and_none_leaves_it():
    from common.matching.paint import with_paint

    p = np.array([0.1, 0.1, 0.1, 0.5])
    out = with_paint(p, [0.0, 5.0, -5.0, 0.0], docking_slope=0.02, weight=8.0)
    np.testing.assert_allclose(out[[0, 3]], p[[0, 3]])
    logit = np.log(out / (1 - out)) - np.log(p / (1 - p))
    np.testing.assert_allclose(logit[1:3], [0.8, -0.8], atol=1e-9)  # 8 × 0.02 × ±5 mm
    with pytest.raises(ValueError, match="paint_mm"):
        with_paint(p, [np.nan] * 4, docking_slope=0.02)
