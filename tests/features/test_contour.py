"""Sub-pixel fragment contour (common/features/contour.py)."""

import numpy as np
import pytest

from common.features.contour import fragment_contour


def _disc(n, cy, cx, r):
    yy, xx = np.mgrid[:n, :n]
    return (yy - cy) ** 2 + (xx - cx) ** 2 < r ** 2


def test_disc_perimeter_and_positions_in_mm():
    px = 0.2
    c = fragment_contour(_disc(200, 90, 110, 60), px)
    assert c.length_mm == pytest.approx(2 * np.pi * 60 * px, rel=0.005)
    r = np.hypot(c.points_mm[:, 0] - 110 * px, c.points_mm[:, 1] - 90 * px)  # x = col, y = row
    assert np.allclose(r, 60 * px, atol=0.6 * px)


def test_normals_are_unit_and_point_outward():
    px = 0.2
    c = fragment_contour(_disc(200, 100, 100, 60), px)
    assert np.allclose(np.linalg.norm(c.normals, axis=1), 1.0)
    radial = (c.points_mm - 100 * px) / np.linalg.norm(c.points_mm - 100 * px, axis=1, keepdims=True)
    assert np.all(np.sum(c.normals * radial, axis=1) > 0.99)


def test_arc_length_is_uniform_and_start_is_farthest_from_centroid():
    px = 0.1
    yy, xx = np.mgrid[:200, :300]
    ellipse = ((yy - 100) / 60.0) ** 2 + ((xx - 150) / 120.0) ** 2 < 1  # long axis along x
    c = fragment_contour(ellipse, px, step_mm=0.25)
    assert np.allclose(np.diff(c.arc_mm), 0.25, rtol=0.05)
    assert abs(abs(c.points_mm[0, 0] - 15.0) - 12.0) < 0.2 and abs(c.points_mm[0, 1] - 10.0) < 0.3


def test_largest_region_gives_the_outline():
    m = _disc(200, 100, 100, 50) | _disc(200, 10, 10, 5)
    c = fragment_contour(m, 1.0)
    assert c.length_mm == pytest.approx(2 * np.pi * 50, rel=0.01)


def test_explicit_start_point():
    c = fragment_contour(_disc(200, 100, 100, 60), 1.0, start_mm=(100.0, 160.0))
    assert np.allclose(c.points_mm[0], (100.0, 160.0), atol=1.0)


def test_empty_mask_and_bad_pixel_size_are_refused():
    with pytest.raises(ValueError, match="no fragment"):
        fragment_contour(np.zeros((20, 20), bool), 1.0)
    with pytest.raises(ValueError, match="pixel_mm"):
        fragment_contour(_disc(20, 10, 10, 5), 0.0)
