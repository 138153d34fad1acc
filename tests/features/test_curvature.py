"""Contour curvature, area-based (eq. 5.1) and three-point (eq. 5.2) (common/features/curvature.py)."""

import cv2
import numpy as np
import pytest

from common.features.contour import fragment_contour
from common.features.curvature import area_curvature, three_point_curvature
from common.features.registry import CURVATURE_SCALES_MM


def _coverage_disc(n, c, r_px, supersample=4):
    """Area-averaged mask of a disc (sub-pixel exact up to the supersampling)."""
    s = supersample
    yy, xx = np.mgrid[:n * s, :n * s]
    big = ((((yy + 0.5) / s - 0.5 - c) ** 2 + ((xx + 0.5) / s - 0.5 - c) ** 2) < r_px ** 2).astype(np.float32)
    return cv2.resize(big, (n, n), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope="module")
def disc():
    px, R = 0.25, 40.0  # a disc of radius 40 mm at 0.25 mm per pixel
    n = int(2 * R / px) + 40
    cov = _coverage_disc(n, (n - 1) / 2, R / px)
    return cov, px, R, fragment_contour(cov, px)


@pytest.mark.parametrize("scale", CURVATURE_SCALES_MM)
def test_disc_of_radius_R_has_curvature_one_over_R_by_both_measures(disc, scale):
    cov, px, R, c = disc
    pts = c.points_mm[::40]
    ka = area_curvature(cov, px, pts, scale)
    kt = three_point_curvature(c, c.arc_mm[::40], scale)
    # eq. 5.1 drops the O(r^4) term of the area expansion: it is exact to ~(r/R)^2 / 8;
    # pixel noise of the area weighs 1/r^3, hence the looser bound at the smallest scale
    tol_a = 0.25 if scale < 5 else 0.05 + (scale / R) ** 2 / 4
    assert np.median(ka) * R == pytest.approx(1.0, abs=tol_a)
    assert np.median(kt) * R == pytest.approx(1.0, abs=0.02)
    if scale >= 5:
        assert np.all(np.abs(kt * R - 1) < 0.1)


def test_concave_notch_is_negative_and_straight_edge_is_zero():
    # an anti-aliased mask (as area-averaging a fine scan gives): a binary one cannot show a
    # sagitta below one pixel, and the top row of a rasterised circle is a flat run
    px, n, s4 = 0.25, 400, 4
    yy, xx = (np.mgrid[:n * s4, :n * s4] + 0.5) / s4 - 0.5
    fine = (yy < 299.5) & ((yy - 299.5) ** 2 + (xx - 199.5) ** 2 >= 80 ** 2)  # edge with a 20 mm bite
    mask = cv2.resize(fine.astype(np.float32), (n, n), interpolation=cv2.INTER_AREA)
    c = fragment_contour(mask, px)
    # contour point at the bottom of the bite: (x, y) = (200, 220) px
    s = c.arc_mm[np.argmin(np.hypot(c.points_mm[:, 0] - 199.5 * px, c.points_mm[:, 1] - 219.5 * px))]
    p, _ = c.at([s])
    assert three_point_curvature(c, [s], 5.0)[0] == pytest.approx(-1 / 20, rel=0.05)
    assert area_curvature(mask, px, p, 5.0)[0] == pytest.approx(-1 / 20, rel=0.15)
    s2 = c.arc_mm[np.argmin(np.hypot(c.points_mm[:, 0] - 10, c.points_mm[:, 1] - 75))]
    assert abs(three_point_curvature(c, [s2], 5.0)[0]) < 0.002
    assert abs(area_curvature(mask, px, c.at([s2])[0], 5.0)[0]) < 0.01


def test_bad_scales_are_refused(disc):
    cov, px, R, c = disc
    with pytest.raises(ValueError, match="radius_mm"):
        area_curvature(cov, px, c.points_mm[:1], 0.0)
    with pytest.raises(ValueError, match="span_mm"):
        three_point_curvature(c, [0.0], c.length_mm)


def test_two_pieces_of_one_cut_have_opposite_curvature_along_it():
    # a square broken along a wavy crack y = 40 + 6 sin(2 pi x / 30) mm: at every point of the
    # crack the upper piece's curvature is minus the lower one's (rule abs_sum: |a + b| ~ 0)
    px, n, s4 = 0.2, 500, 4
    yy, xx = (np.mgrid[:n * s4, :n * s4] + 0.5) / s4 - 0.5
    crack = (40 + 6 * np.sin(2 * np.pi * xx * px / 30)) / px
    square = (xx > 50) & (xx < 450) & (yy > 50) & (yy < 450)
    upper = cv2.resize((square & (yy < crack)).astype(np.float32), (n, n), interpolation=cv2.INTER_AREA)
    lower = cv2.resize((square & (yy >= crack)).astype(np.float32), (n, n), interpolation=cv2.INTER_AREA)
    cu, cl = fragment_contour(upper, px), fragment_contour(lower, px)
    x = np.linspace(25.0, 75.0, 21)                      # crack points away from the corners
    pts = np.stack([x, 40 + 6 * np.sin(2 * np.pi * x / 30)], axis=1)
    su = np.array([cu.arc_mm[np.argmin(np.linalg.norm(cu.points_mm - p, axis=1))] for p in pts])
    sl = np.array([cl.arc_mm[np.argmin(np.linalg.norm(cl.points_mm - p, axis=1))] for p in pts])
    for scale in (2.5, 5.0):
        ku, kl = three_point_curvature(cu, su, scale), three_point_curvature(cl, sl, scale)
        assert np.max(np.abs(ku + kl)) < 0.01 and np.max(np.abs(ku)) > 0.1
        au = area_curvature(upper, px, cu.at(su)[0], scale)
        al = area_curvature(lower, px, cl.at(sl)[0], scale)
        assert np.median(np.abs(au + al)) < 0.15 * np.median(np.abs(au))
