"""The facing geometry of two outlines at a pose (common/matching/facing.py), against analytic cases."""

import numpy as np
import pytest

from common.matching.alignment import resample_contour
from common.matching.facing import FACING_COLUMNS, facing_geometry, probe_poses, turning_curvature


def _rect(w, h, x0=0.0, y0=0.0, step=0.25):
    """A rectangle's outline, densely sampled, traversed clockwise on screen (y down) like the features'."""
    xs, ys = np.arange(0, w, step), np.arange(0, h, step)
    pts = np.vstack([np.c_[xs, np.zeros_like(xs)], np.c_[np.full_like(ys, w), ys],
                     np.c_[w - xs, np.full_like(xs, h)], np.c_[np.zeros_like(ys), h - ys]])
    return pts + (x0, y0)


def _col(rows, name):
    return rows[:, FACING_COLUMNS.index(name)]


def test_two_slabs_a_known_gap_apart():
    """A 40 × 60 mm slab and a 20 × 60 mm one beside it, 3 mm of material lost between them: the two
    60 mm sides face each other at a steady 3 mm gap, nothing is pushed inside, and at both ends of the
    facing run both outlines turn away from the crack (convex corners: the curvatures agree in sign, so κ_A
    does not follow −κ_B)."""
    a, b = _rect(40, 60), _rect(20, 60)
    rows, directions, centres = facing_geometry(a, b, [(0.0, 43.0, 0.0)])
    assert _col(rows, "gap_median_mm")[0] == pytest.approx(3.0, abs=0.6)
    assert _col(rows, "gap_q10_mm")[0] == pytest.approx(3.0, abs=0.6)
    assert _col(rows, "gap_rough_mm")[0] < 0.5
    assert _col(rows, "inside_mm")[0] == 0 and _col(rows, "depth_mm")[0] == 0 and _col(rows, "tight_mm")[0] == 0
    # the facing side is 60 mm, plus the corners' few mm within the 8 mm band
    assert 55 <= _col(rows, "face_mm")[0] <= 75 and _col(rows, "run_mm")[0] <= _col(rows, "face_mm")[0] + 1e-9
    assert _col(rows, "curvature_correlation")[0] < -0.5
    assert abs(directions[0, 0]) < 0.05 and abs(abs(directions[0, 1]) - 1) < 0.05     # along the y axis
    np.testing.assert_allclose(centres[0], (41.5, 30.0), atol=4.0)                 # in the gap, mid-height


def test_a_pose_pushed_into_the_other_piece_and_one_slid_along():
    a, b = _rect(40, 60), _rect(20, 60)
    rows, _, _ = facing_geometry(a, b, [(0.0, 43.0, 0.0), (0.0, 37.0, 0.0), (0.0, 43.0, 30.0)])
    assert _col(rows, "inside_mm")[1] > 40 and _col(rows, "depth_mm")[1] == pytest.approx(3.0, abs=0.6)
    # pushed 3 mm in: A's facing run is the whole side, B's only its corners: their ends lie far apart
    assert _col(rows, "end_mismatch_mm")[1] > 30
    # slid 30 mm along the crack: half of the side faces, one end of the run turns away and one does not
    assert _col(rows, "face_mm")[2] < _col(rows, "face_mm")[0] - 20
    assert _col(rows, "curvature_correlation")[2] > _col(rows, "curvature_correlation")[0] + 0.5


def test_a_piece_far_away_faces_nothing():
    rows, _, _ = facing_geometry(_rect(40, 60), _rect(20, 60), [(0.0, 200.0, 0.0)])
    assert _col(rows, "face_mm")[0] == 0 and _col(rows, "run_mm")[0] == 0


def test_curvature_of_a_circle_and_its_sign_with_the_direction():
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    circle = resample_contour(np.c_[20 * np.cos(t), 20 * np.sin(t)], 1.0, positive=False)
    k = turning_curvature(circle, 4.0, 2 * np.pi * 20 / len(circle))
    np.testing.assert_allclose(k, 1 / 20, rtol=0.03)
    np.testing.assert_allclose(turning_curvature(circle[::-1], 4.0, 2 * np.pi * 20 / len(circle)), -1 / 20, rtol=0.03)


def test_probes_turn_about_the_facing_runs_centre():
    p = probe_poses([(10.0, 5.0, 0.0)], [(0.0, 1.0)], [(5.0, 0.0)])[0]
    np.testing.assert_allclose(p[1], (10.0, 5.0, 3.0))           # +3 mm along the run (y)
    np.testing.assert_allclose(p[3], (10.0, 3.5, 0.0))           # +1.5 mm across it (−x: the run's left)
    np.testing.assert_allclose(p[5][0], 12.0)
    np.testing.assert_allclose(p[5][1:], (5.0, 0.0), atol=1e-12)  # the centre (5, 0) stays where it was


@pytest.mark.parametrize("args, message", [
    ((np.zeros((2, 2)), _rect(5, 5), [(0, 0, 0)]), "N >= 3"),
    ((_rect(5, 5), _rect(5, 5), [(0, np.nan, 0)]), "finite"),
])
def test_bad_input_is_named(args, message):
    with pytest.raises(ValueError, match=message):
        facing_geometry(*args)


def test_longest_runs_of_many_rows_against_brute_force():
    """Each row's longest circular run of True, for rows of every kind at once (none, all, wrapping
    round the end, ties): the run found is all True, no longer circular run exists, and of equally long
    runs the first counted from the row's first False is taken."""
    from common.matching.facing import _longest_runs

    rng = np.random.default_rng(3)
    rows = [rng.random(n) < p for n in (1, 2, 7, 25) for p in (0.0, 0.3, 0.7, 1.0) for _ in range(4)]
    rows.append(np.array([1, 1, 0, 1, 1, 1, 0, 0, 1, 1, 1, 1], bool))   # the longest run wraps round the end
    rows.append(np.array([0, 1, 1, 0, 1, 1, 0], bool))                    # a tie
    for n in {len(r) for r in rows}:
        block = np.array([r for r in rows if len(r) == n])
        starts, lengths = _longest_runs(block)
        for row, s, k in zip(block, starts, lengths):
            best = max((m for i in range(n) for m in range(n + 1) if row[(i + np.arange(m)) % n].all()), default=0)
            assert k == (n if row.all() else best)
            assert row[(s + np.arange(k)) % n].all()
            if 0 < k < n:   # the first such run counted from the first False
                f = int(np.argmin(row))
                firsts = [i for i in range(n) if row[(i + np.arange(k)) % n].all() and not row[(i - 1) % n]]
                assert s == min(firsts, key=lambda i: (i - f) % n)
    starts, lengths = _longest_runs(np.array([[1, 1, 0, 1, 1, 1, 0, 0, 1, 1, 1, 1]], bool))
    assert (starts[0], lengths[0]) == (8, 6)        # 8, 9, 10, 11, 0, 1
    starts, lengths = _longest_runs(np.array([[0, 1, 1, 0, 1, 1, 0]], bool))
    assert (starts[0], lengths[0]) == (1, 2)
