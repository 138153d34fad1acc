"""Gap-tolerant docking (common/matching/docking.py) against generated ground truth: a plaster
slab broken along a jagged crack, material lost on both sides, one piece turned and moved."""

import cv2
import numpy as np
import pytest

from common.matching.collection import relative_pose_error
from common.matching.docking import Docking, dock_outlines, docking_contact_mm, hub_corrected, invert_docking

PX_MM = 0.25


def _broken_slab(seed, gap_mm=3.0, size_mm=90.0):
    """Two pieces of one blob split by a jagged crack, ``gap_mm`` of plaster lost between them;
    outlines in the slab's frame (mm)."""
    rng = np.random.default_rng(seed)
    n = int(size_mm / PX_MM)
    yy, xx = np.mgrid[0:n, 0:n] * PX_MM
    c = size_mm / 2
    ang = np.arctan2(yy - c, xx - c)
    radius = size_mm * 0.42 * (1 + sum(rng.uniform(-0.08, 0.08) * np.cos(k * ang + rng.uniform(0, 6.3))
                                       for k in range(2, 6)))
    blob = np.hypot(yy - c, xx - c) < radius
    x = np.arange(n) * PX_MM
    crack = c + rng.uniform(-8, 8) * np.sin(x / rng.uniform(12, 25) + rng.uniform(0, 6.3)) \
        + np.cumsum(rng.normal(0, 0.4, n)) + rng.uniform(-0.3, 0.3) * (x - c)
    pieces = []
    for side in (-1, 1):
        m = blob & (side * (yy - crack[None, :]) > gap_mm / 2)
        cs, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        pieces.append(max(cs, key=len).reshape(-1, 2).astype(float) * PX_MM)
    return pieces


def _move(points, angle_deg, t):
    a = np.radians(angle_deg)
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return points @ r.T + t


@pytest.mark.parametrize("seed,angle", [(1, 37.0), (2, 151.0), (3, -100.0)])
def test_docking_recovers_the_pose_across_lost_material(seed, angle):
    a, b = _broken_slab(seed, gap_mm=3.0)
    moved = _move(b, angle, (120.0, -40.0))
    d = dock_outlines(a, moved)[0]
    # truth: the moved piece's frame -> the slab's (A's) frame is the inverse of the move
    back = invert_docking(Docking(angle, 120.0, -40.0, 0.0, 0.0, 0.0))
    err_angle, err_mm = relative_pose_error((0, 0, 0), (back.angle_deg, back.tx_mm, back.ty_mm),
                                            (d.angle_deg, d.tx_mm, d.ty_mm), moved.mean(axis=0))
    assert err_angle <= 3.0
    assert err_mm <= 3.0 + 1.5  # within the lost material (any place in the gap fits) plus a cell
    assert d.contact_mm > 40.0 and d.overlap_mm2 < 20.0


def test_true_partner_outdocks_pieces_of_other_cracks():
    a, b = _broken_slab(11)
    decoys = [p for s in (12, 13, 14) for p in _broken_slab(s)]
    true_contact = docking_contact_mm(dock_outlines(a, _move(b, 70.0, (0.0, 0.0)))[0])
    others = [docking_contact_mm(dock_outlines(a, _move(p, 70.0, (0.0, 0.0)))[0]) for p in decoys]
    assert true_contact > max(others)


def test_docking_from_either_side_agrees():
    a, b = _broken_slab(5)
    ab = dock_outlines(a, b)[0]
    ba = invert_docking(dock_outlines(b, a)[0])
    e = relative_pose_error((0, 0, 0), (ab.angle_deg, ab.tx_mm, ab.ty_mm), (ba.angle_deg, ba.tx_mm, ba.ty_mm),
                            b.mean(axis=0))
    assert e[0] <= 3.0 and e[1] <= 4.0


def test_invert_docking_is_an_involution():
    d = Docking(33.0, 12.0, -7.0, 10.0, 5.0, 0.0)
    dd = invert_docking(invert_docking(d))
    assert np.allclose([dd.angle_deg, dd.tx_mm, dd.ty_mm], [33.0, 12.0, -7.0])


def test_hub_correction_removes_each_fragments_excess():
    # a hub (mean best contact 90 mm against a median of 50) loses half of its 40 mm excess
    assert hub_corrected(100.0, 90.0, 50.0, 50.0) == pytest.approx(80.0)
    assert np.allclose(hub_corrected([60.0, 60.0], 50.0, [50.0, 70.0], 50.0), [60.0, 50.0])


@pytest.mark.parametrize("kw,message", [({"cell_mm": 0}, "cell_mm"), ({"step_deg": 0}, "step_deg"),
                                        ({"gap_mm": -1}, "gap_mm"), ({"n_poses": 0}, "n_poses")])
def test_bad_arguments_are_named(kw, message):
    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    with pytest.raises(ValueError, match=message):
        dock_outlines(sq, sq, **kw)


def test_degenerate_outline_is_refused():
    with pytest.raises(ValueError, match="contour_b_mm"):
        dock_outlines(np.zeros((5, 2)) + [[0, 0], [1, 0], [1, 1], [0, 1], [0, 0.5]], np.zeros((2, 2)))


def test_score_at_a_pose_matches_the_search_at_its_best_pose():
    from common.matching.docking import docking_score_at

    a, b = _broken_slab(7)
    best = dock_outlines(a, b)[0]
    at_best = docking_score_at(a, b, (best.angle_deg, best.tx_mm, best.ty_mm))
    # same maps on another grid: equal up to the rasterisation of the outlines (a few cells)
    assert at_best == pytest.approx(best.score, rel=0.1)
    # the pieces in place (identity pose) score near the best; far apart they score nothing
    assert docking_score_at(a, b, (0.0, 0.0, 0.0)) > 0.6 * best.score
    assert docking_score_at(a, b, (0.0, 500.0, 0.0)) == 0.0


def test_candidate_poses_hold_the_best_pose_and_several_per_rotation():
    a, b = _broken_slab(5, gap_mm=3.0)
    moved = _move(b, 63.0, (80.0, 10.0))
    one = dock_outlines(a, moved, n_poses=1, coarse_angles=0)[0]
    cands = dock_outlines(a, moved, n_poses=40, per_angle=5, min_shift_mm=6.0)
    assert cands[0] == one                      # the best candidate is the single best pose
    assert [d.score for d in cands] == sorted((d.score for d in cands), reverse=True)
    angles = [round(d.angle_deg, 3) for d in cands]
    assert len(cands) == 40 and len(set(angles)) < 40  # some rotations give more than one candidate
    centre = moved.mean(axis=0)
    for i, d in enumerate(cands):                # distinct: other angle, or B's centre >= 6 mm away
        for e in cands[:i]:
            da = abs((d.angle_deg - e.angle_deg + 180) % 360 - 180)
            ca = _move(centre[None], d.angle_deg, (d.tx_mm, d.ty_mm))[0]
            cb = _move(centre[None], e.angle_deg, (e.tx_mm, e.ty_mm))[0]
            assert da >= 8.0 - 1e-6 or np.hypot(*(ca - cb)) >= 6.0 - 1e-6
    with pytest.raises(ValueError, match="per_angle"):
        dock_outlines(a, moved, per_angle=0)


def test_more_poses_follow_the_search_unchanged():
    """``more_poses``: the first ``n_poses`` candidates are exactly the search without them; the further ones
    follow, best first, distinct from every earlier one, with more local maxima per rotation than
    ``per_angle`` allows (so a rotation holds more than ``per_angle`` of them)."""
    a, b = _broken_slab(5, gap_mm=3.0)
    moved = _move(b, 63.0, (80.0, 10.0))
    plain = dock_outlines(a, moved, n_poses=12, per_angle=2)
    wide = dock_outlines(a, moved, n_poses=12, per_angle=2, more_poses=20, more_per_angle=6)
    assert wide[:12] == plain
    more = wide[12:]
    assert 0 < len(more) <= 20
    assert [d.score for d in more] == sorted((d.score for d in more), reverse=True)
    centre = moved.mean(axis=0)
    for i, d in enumerate(more, start=12):
        for e in wide[:i]:
            da = abs((d.angle_deg - e.angle_deg + 180) % 360 - 180)
            ca = _move(centre[None], d.angle_deg, (d.tx_mm, d.ty_mm))[0]
            cb = _move(centre[None], e.angle_deg, (e.tx_mm, e.ty_mm))[0]
            assert da >= 8.0 - 1e-6 or np.hypot(*(ca - cb)) >= 6.0 - 1e-6
    per_rotation = np.unique([round(d.angle_deg, 6) for d in wide], return_counts=True)[1]
    assert per_rotation.max() > 2
    for kw in ({"per_angle": 1}, {"more_per_angle": 1}, {"rescore": lambda p: np.zeros(len(p))}):
        with pytest.raises(ValueError, match="more_poses"):
            dock_outlines(a, moved, n_poses=12, **{"per_angle": 2, "more_poses": 5, **kw})


def test_rescore_reranks_candidates_and_refines_the_winner():
    """Extra evidence (e.g. paint) that marks one candidate pose makes it the docking's pose, refined
    to a finer angle than the 4° grid; a rescore of the wrong length is refused."""
    a, b = _broken_slab(7, gap_mm=3.0)
    moved = _move(b, 41.0, (60.0, 30.0))
    cands = dock_outlines(a, moved, n_poses=30, per_angle=5)
    target = cands[7]                           # not the geometric best
    centre = moved.mean(axis=0)

    def bonus(poses):
        c = _move(centre[None], 0.0, (0.0, 0.0))[0]
        at = np.array([_move(c[None], p[0], p[1:])[0] for p in poses])
        want = _move(c[None], target.angle_deg, (target.tx_mm, target.ty_mm))[0]
        near = (np.hypot(*(at - want).T) < 3.0) & (np.abs((poses[:, 0] - target.angle_deg + 180) % 360 - 180) < 3.0)
        return np.where(near, 1000.0, 0.0)

    best = dock_outlines(a, moved, n_poses=30, per_angle=5, rescore=bonus)[0]
    assert abs((best.angle_deg - target.angle_deg + 180) % 360 - 180) < 3.0
    assert best.score > cands[0].score          # the bonus is in the score, in cells
    plain = dock_outlines(a, moved, n_poses=30, per_angle=5, rescore=lambda p: np.zeros(len(p)))[0]
    assert plain.score >= cands[0].score         # refinement never loses the best candidate
    with pytest.raises(ValueError, match="rescore"):
        dock_outlines(a, moved, n_poses=5, rescore=lambda p: np.zeros(2))


@pytest.mark.parametrize("seed,angle", [(1, 37.0), (3, -100.0)])
def test_coarse_to_fine_finds_the_pose_the_full_search_finds(seed, angle):
    a, b = _broken_slab(seed, gap_mm=3.0)
    moved = _move(b, angle, (120.0, -40.0))
    full = dock_outlines(a, moved, coarse_angles=0)[0]
    quick = dock_outlines(a, moved, coarse_angles=3)[0]
    # within one step of the angle grid and two cells at B's centre
    assert abs((full.angle_deg - quick.angle_deg + 180) % 360 - 180) <= 4.0 + 1e-6
    c = moved.mean(axis=0)
    at_full = _move(c[None], full.angle_deg, (full.tx_mm, full.ty_mm))[0]
    at_quick = _move(c[None], quick.angle_deg, (quick.tx_mm, quick.ty_mm))[0]
    assert np.hypot(*(at_full - at_quick)) <= 3.0
    assert quick.score >= 0.95 * full.score
    with pytest.raises(ValueError, match="coarse_angles"):
        dock_outlines(a, moved, coarse_angles=-1)
