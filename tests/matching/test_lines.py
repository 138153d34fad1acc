"""Painted-line pose hypotheses (common/matching/lines.py) on analytic cuts with a known pose."""

import numpy as np
import pytest

from common.matching.alignment import pose_matrix
from common.matching.collection import relative_pose_error
from common.matching.lines import END_COLUMNS, line_continuity, line_ends, line_pose_hypotheses, outline_contact_mm

PX_MM = 0.2
PLASTER = (0.60, 0.55, 0.48)
RED = (0.45, 0.08, 0.06)
CUT_X, LOST_MM = 40.0, 3.0          # the crack: wall x = 40 mm, 3 mm of plaster lost across it
BAND_DEG, BAND_W = 20.0, 4.0        # a red band at 20° to the crack's normal (x), 4 mm wide
BAND_AT = (40.0, 30.0)              # a point on the band's centre line, wall mm


def painting(p):
    """The wall's paint at wall points (N, 2): plaster with one straight red band."""
    u = np.array([np.cos(np.radians(BAND_DEG)), np.sin(np.radians(BAND_DEG))])
    off = (p - BAND_AT) @ np.array([-u[1], u[0]])
    inside = np.abs(off) < BAND_W / 2
    return np.where(inside[:, None], RED, PLASTER)


def piece(pose, side, size=(70, 70), paint=True):
    """Render one side of the cut in its own frame; ``pose`` maps it into the wall (deg, mm, mm)."""
    h, w = size
    rows, cols = np.mgrid[0:int(h / PX_MM), 0:int(w / PX_MM)]
    local = np.stack([cols.ravel() * PX_MM, rows.ravel() * PX_MM], 1)
    m = pose_matrix(*pose)
    wall = local @ m[:2, :2].T + m[:2, 2]
    keep = (wall[:, 1] > 5) & (wall[:, 1] < 55)
    keep &= (wall[:, 0] > 5) & (wall[:, 0] < CUT_X - LOST_MM / 2) if side == "a" else \
        (wall[:, 0] > CUT_X + LOST_MM / 2) & (wall[:, 0] < 75)
    colour = painting(wall) if paint else np.tile(PLASTER, (len(wall), 1))
    alb = colour.reshape(rows.shape + (3,)).astype(np.float32)
    return alb, keep.reshape(rows.shape)


POSE_A = (0.0, 0.0, 0.0)
POSE_B = (35.0, 45.0, -20.0)   # B's own frame turned 35° against the wall's


def _truth():
    m = np.linalg.inv(pose_matrix(*POSE_A)) @ pose_matrix(*POSE_B)
    return float(np.degrees(np.arctan2(m[1, 0], m[0, 0]))), float(m[0, 2]), float(m[1, 2])


@pytest.fixture(scope="module")
def cut():
    alb_a, mask_a = piece(POSE_A, "a")
    alb_b, mask_b = piece(POSE_B, "b")
    centre_b = np.argwhere(mask_b).mean(0)[::-1] * PX_MM
    return line_ends(alb_a, mask_a, PX_MM), line_ends(alb_b, mask_b, PX_MM), centre_b


def test_band_gives_its_two_edges_where_it_is_cut(cut):
    ends_a, ends_b, _ = cut
    assert ends_a.shape[1] == len(END_COLUMNS)
    # the band's two boundaries cross each piece's two edges it reaches: the crack and the slab's end
    assert len(ends_a) == 4 and len(ends_b) == 4
    at_crack = ends_a[np.abs(ends_a[:, 0] - (CUT_X - LOST_MM / 2)) < 1.0]
    assert len(at_crack) == 2
    # there the boundary runs into A (towards −x) at the band's angle
    d = (at_crack[:, 2] - (BAND_DEG + 180.0) + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(d) < 3.0)
    # and the paint changes colour across it by the band's contrast (plaster ↔ red, ΔE ≫ 10)
    assert np.all(at_crack[:, -1] > 10)


def test_hypothesis_recovers_the_known_pose(cut):
    ends_a, ends_b, centre_b = cut
    poses, pairs = line_pose_hypotheses(ends_a, ends_b, gaps_mm=np.arange(0.5, 8.01, 0.25),
                                        turns_deg=np.arange(-3, 3.01, 0.5), shifts_mm=np.arange(-1, 1.01, 0.25))
    # colours agree across the crack only edge with edge (plaster→red on A meets red→plaster on B):
    # 2 of the 4 × 4 pairs for each of the two orders of colour
    assert len(pairs) == 8
    err = np.array([relative_pose_error(POSE_A, POSE_B, p, centre_b) for p in poses.reshape(-1, 3)])
    assert np.any((err[:, 0] <= 1.0) & (err[:, 1] <= 1.0))
    # the collinear pose (no turn) of every pair has the true angle within 2°, or B turned over (a
    # crossing at the crack paired with one at the slab's far end: the same boundary met head-on)
    d = np.abs((poses[:, poses.shape[1] // 2, 0] - _truth()[0] + 180) % 360 - 180)
    assert np.all((d < 2.0) | (d > 178.0)) and np.sum(d < 2.0) >= 2


def test_continuity_counts_both_edges_at_the_truth_only(cut):
    ends_a, ends_b, _ = cut
    th, tx, ty = _truth()
    slid = (th, tx, ty + 15.0)         # slid 15 mm along the crack
    turned = (th + 40.0, tx, ty)
    assert line_continuity(ends_a, ends_b, [_truth(), slid, turned]).tolist() == [2.0, 0.0, 0.0]


def test_plain_piece_gives_no_end():
    alb, mask = piece(POSE_B, "b", paint=False)
    assert line_ends(alb, mask, PX_MM).shape == (0, len(END_COLUMNS))
    poses, pairs = line_pose_hypotheses(np.zeros((0, len(END_COLUMNS))), np.zeros((0, len(END_COLUMNS))))
    assert poses.shape[0] == 0 and pairs.shape == (0, 2)


@pytest.mark.parametrize("kwargs, message", [
    (dict(albedo=np.zeros((10, 10)), mask=np.ones((10, 10), bool), pixel_mm=0.2), "albedo"),
    (dict(albedo=np.zeros((10, 10, 3)), mask=np.ones((9, 10), bool), pixel_mm=0.2), "mask"),
    (dict(albedo=np.zeros((10, 10, 3)), mask=np.ones((10, 10), bool), pixel_mm=0.0), "pixel_mm"),
])
def test_bad_images_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        line_ends(**kwargs)


def test_bad_ends_are_named():
    with pytest.raises(ValueError, match="ends_a"):
        line_pose_hypotheses(np.zeros((3, 4)), np.zeros((0, len(END_COLUMNS))))
    with pytest.raises(ValueError, match="ends_b"):
        line_continuity(np.zeros((0, len(END_COLUMNS))), np.zeros(5), [(0, 0, 0)])
    with pytest.raises(ValueError, match="gaps_mm"):
        line_pose_hypotheses(np.zeros((0, len(END_COLUMNS))), np.zeros((0, len(END_COLUMNS))), gaps_mm=[])


def test_sampled_contact_rewards_facing_outlines_and_charges_overlap():
    square = np.array([(0, 0), (40, 0), (40, 40), (0, 40)], float)
    # B = the same square, 2 / 7 / 30 mm to the right of A, or pushed 10 mm into it
    near, far, apart, into = outline_contact_mm(square, square, [(0, 42, 0), (0, 47, 0), (0, 70, 0), (0, 30, 0)])
    assert apart == 0.0                      # beyond the 6 + 2 mm band nothing counts
    assert near > far > 0                    # a closer fit counts more (the docking's near weight)
    assert into < 0                          # overlap costs more than the contact it brings
    # facing across 2 mm over the 40 mm side: about the side's length × the band's weight there
    assert 40 * 2 < near < 40 * 3.5
    with pytest.raises(ValueError, match="contour_b_mm"):
        outline_contact_mm(square, square[:2], [(0, 0, 0)])
