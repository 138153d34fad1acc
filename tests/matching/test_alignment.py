"""The 2-D ribbon matcher recovers known poses of pieces cut from analytic shapes."""

import cv2
import numpy as np
import pytest

from common.matching.alignment import (align_fragments, apply_pose, overlap_area_mm2, procrustes_all_pairs,
                                       resample_contour, signed_area_mm2)


def cut_disc(seed, radius=30.0, px=0.1, amplitude=5.0):
    """Cut a disc with a random jagged line into two pieces; contours in mm (x right, y down)."""
    rng = np.random.default_rng(seed)
    n = int(2 * radius / px) + 40
    yy, xx = np.mgrid[0:n, 0:n] * px
    c = n * px / 2
    disc = (xx - c) ** 2 + (yy - c) ** 2 <= radius ** 2
    kx = np.linspace(0, n * px, 14)
    ky = c + rng.uniform(-amplitude, amplitude, len(kx))
    below = yy >= np.interp(xx, kx, ky)
    out = []
    for m in (disc & ~below, disc & below):
        cs, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        out.append(max(cs, key=len)[:, 0, :].astype(float) * px)
    return out


def inverse_pose(angle_deg, t):
    r = np.radians(-angle_deg)
    rot = np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]])
    return -angle_deg, -rot @ np.asarray(t)


@pytest.mark.parametrize("seed,angle,t", [(1, 73.0, (50.0, -20.0)), (4, -140.0, (-35.0, 80.0)), (7, 180.0, (0.0, 0.0))])
def test_cut_disc_piece_moved_by_known_pose_is_put_back(seed, angle, t):
    a, b = cut_disc(seed)
    moved = apply_pose(b, angle, *t)
    al = align_fragments(a, moved)
    want_angle, want_t = inverse_pose(angle, t)
    d_angle = (al.angle_deg - want_angle + 180) % 360 - 180
    assert abs(d_angle) < 1.0
    # compare where the piece lands, not the translation (which depends on the rotation centre)
    back = apply_pose(moved, al.angle_deg, al.tx_mm, al.ty_mm)
    assert np.max(np.linalg.norm(back - b, axis=1)) < 1.0  # within one 1 mm strip sample
    assert al.overlap_mm2 < 5.0
    assert al.contact_mm > 60.0  # the jagged break is longer than the 60 mm chord


def test_true_partner_outscores_a_piece_of_another_disc():
    a, b = cut_disc(1)
    _, foreign = cut_disc(2)
    good = align_fragments(a, apply_pose(b, 30, 10, 10))
    bad = align_fragments(a, apply_pose(foreign, 30, 10, 10))
    assert good.score > bad.score + 15.0


def test_anchored_search_finds_the_same_pose_as_the_exhaustive_one():
    a, b = cut_disc(3)
    moved = apply_pose(b, 45.0, 20.0, 5.0)
    full = align_fragments(a, moved)

    def arc_at(contour, i):
        seg = np.hypot(*np.diff(np.vstack([contour, contour[:1]]), axis=0).T)
        return np.concatenate([[0], np.cumsum(seg)])[i]

    # a point in the middle of the break on A, and its partner on B (same vertex order after the move)
    centre = np.array([a[:, 0].mean(), 0.0])
    on_break = np.abs(np.linalg.norm(a - [centre[0], centre[0]], axis=1) - 30.0) > 1.0
    ia = np.flatnonzero(on_break)[np.argmin(np.abs(a[on_break, 0] - centre[0]))]
    ib = np.argmin(np.linalg.norm(b - a[ia], axis=1))
    anchored = align_fragments(a, moved, anchors=(np.array([arc_at(a, ia)]), np.array([arc_at(moved, ib)])))
    assert abs(anchored.angle_deg - full.angle_deg) < 1.0
    assert np.hypot(anchored.tx_mm - full.tx_mm, anchored.ty_mm - full.ty_mm) < 1.0
    assert anchored.contact_mm > 60.0


def test_procrustes_recovers_rotation_of_every_window_pair():
    rng = np.random.default_rng(0)
    win_a = rng.normal(size=(5, 12, 2))
    theta = np.radians(37.0)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    win_b = (win_a - 3.0) @ rot  # b = R^T (a - 3), so a = R b + 3
    rms, ang = procrustes_all_pairs(win_a, win_b)
    assert np.allclose(np.diag(rms), 0.0, atol=1e-6)
    assert np.allclose(np.diag(ang), theta)
    assert np.all(rms[~np.eye(5, dtype=bool)] > 0.1)


def test_overlap_area_of_two_squares_is_their_intersection():
    sq = np.array([[0, 0], [20, 0], [20, 20], [0, 20]], float)
    assert overlap_area_mm2(sq, sq + [10, 0], cell_mm=0.25) == pytest.approx(200.0, rel=0.05)
    assert overlap_area_mm2(sq, sq + [20, 0], cell_mm=0.25) < 2.0   # touching edges: no overlap
    assert overlap_area_mm2(sq, sq + [30, 0]) == 0.0


def test_resample_contour_gives_equal_steps_and_positive_orientation():
    t = np.linspace(0, 2 * np.pi, 37, endpoint=False)[::-1]
    circle = np.column_stack([10 * np.cos(t), 10 * np.sin(t)])
    r = resample_contour(circle, 0.5)
    steps = np.linalg.norm(np.diff(np.vstack([r, r[:1]]), axis=0), axis=1)
    assert signed_area_mm2(r) > 0
    assert np.allclose(steps, steps.mean(), rtol=0.05)
    assert len(r) == pytest.approx(2 * np.pi * 10 / 0.5, rel=0.02)


def test_bad_contour_is_refused_with_its_name():
    with pytest.raises(ValueError, match="contour_b_mm"):
        align_fragments(np.zeros((5, 2)) + np.arange(5)[:, None], np.zeros((2, 2)))
