import numpy as np
import pytest

from common.render.lines import (discontinuity_lines, prune_short_lines, ridges_valleys, suggestive_contours,
                                 suggestive_contours_object)
from tests.rgbn.analytic import gaussian_bump, grid_mm, normals_from_height, tilted_plane


def crease(size=48, angle_deg=60.0):
    """Two planes meeting along the vertical centre line (a roof: normals tilted left and right)."""
    n = tilted_plane(size, angle_deg / 2, 180.0)
    n[:, size // 2:] = tilted_plane(size, angle_deg / 2, 0.0)[:, size // 2:]
    return n


def test_discontinuity_lines_follow_a_crease_and_not_a_plane():
    lines = discontinuity_lines(crease(), threshold_deg=20, outline=False)
    assert lines[:, 23:25].min() > 0.9
    assert lines[:, :20].max() == 0 and lines[:, 28:].max() == 0
    assert discontinuity_lines(tilted_plane(32, 50), outline=False).max() == 0


def test_discontinuity_lines_use_the_flash_discontinuity_map_and_the_outline():
    d = np.zeros((32, 32, 2), np.float32)
    d[10, 5:25] = (0.0, 1.0)
    mask = np.zeros((32, 32), bool)
    mask[4:28, 4:28] = True
    lines = discontinuity_lines(None, mask=mask, discontinuity=d, outline=True)
    assert lines[10, 5:25].min() == 1.0  # strength 1 x flash_gain, clipped
    assert lines[4, 10] == 1.0 and lines[15, 27] == 1.0  # the outline
    assert lines[16, 16] == 0.0


def test_object_space_suggestive_contours_lie_on_the_inflection_circle_of_a_bump():
    s = 1.0
    n = gaussian_bump(128, 0.04, 0.8, s)
    lines = suggestive_contours_object(n, 25.4 / 0.04, sigma_px=1.0, min_length_px=20)
    x, y = grid_mm(128, 0.04)
    r = np.hypot(x, y)[lines > 0.5]
    assert r.size > 100
    # radial curvature vanishes at r = s (inflection of exp(-r^2/2s^2))
    assert np.abs(r - s).max() < 0.1


def test_object_space_suggestive_contours_avoid_a_sphere():
    # a sphere has kr = 1/r everywhere: no zero, no suggestive contour
    from tests.rgbn.analytic import sphere

    n, mask = sphere(96, 4.0, 0.1)
    assert suggestive_contours_object(n, 254.0, mask=mask).max() == 0


def test_image_space_suggestive_contours_mark_a_valley_of_n_dot_v_and_prune_short_pieces():
    # a straight groove: z = -h exp(-x^2/2s^2); n.v is darkest on its flanks
    h, s, pixel_mm = 0.6, 0.5, 0.05
    x, y = grid_mm(96, pixel_mm)
    z = -h * np.exp(-x * x / (2 * s * s))
    n = normals_from_height(-x / s ** 2 * z, np.zeros_like(z))
    lines = suggestive_contours(n, radius_px=4, depth=0.01, min_length_px=40, sigma_px=0)
    nz = n[..., 2]
    cols = np.flatnonzero(lines[48] > 0.5)
    assert cols.size >= 2
    darkest = np.argsort(nz[48])[:2]
    assert all(np.min(np.abs(cols - c)) <= 1 for c in darkest)
    # a short piece of the same groove is pruned away
    short = suggestive_contours(n[40:56], radius_px=4, depth=0.01, min_length_px=40, sigma_px=0)
    assert short.max() == 0


def test_ridges_and_valleys_of_a_crest_and_a_trough():
    h, s, pixel_mm = 0.5, 0.4, 0.05
    x, y = grid_mm(80, pixel_mm)
    z = h * np.exp(-x * x / (2 * s * s))
    crest = normals_from_height(-x / s ** 2 * z, np.zeros_like(z))
    ridge, valley = ridges_valleys(crest, 25.4 / pixel_mm, sigma_px=0.5, threshold=0.5)
    ridge_cols = np.unique(np.nonzero(ridge[10:-10] > 0.5)[1])
    assert set(ridge_cols) <= {39, 40}  # the crest line x = 0 lies between columns 39 and 40
    # the crest's flanks turn concave at its foot: valleys there, symmetric
    vcols = np.unique(np.nonzero(valley[10:-10] > 0.5)[1])
    assert vcols.size and np.all(np.abs(np.abs(x[0, vcols]) - np.sqrt(3) * s) < 0.1)
    trough = crest.copy()
    trough[..., :2] *= -1
    r2, v2 = ridges_valleys(trough, 25.4 / pixel_mm, sigma_px=0.5, threshold=0.5)
    assert set(np.unique(np.nonzero(v2[10:-10] > 0.5)[1])) <= {39, 40}


def test_prune_short_lines_keeps_long_pieces():
    lines = np.zeros((20, 20), bool)
    lines[2, 2:18] = True
    lines[10, 5:8] = True
    out = prune_short_lines(lines, 5)
    assert out[2].sum() == 16 and not out[10].any()


def test_bad_arguments_are_refused_by_name():
    with pytest.raises(ValueError, match="fraction"):
        suggestive_contours(tilted_plane(8), fraction=1.5)
    with pytest.raises(ValueError, match="dpi"):
        ridges_valleys(tilted_plane(8), -1)


def test_a_sphere_has_no_ridges_or_valleys():
    # every point of a sphere is umbilic: no line of curvature, no ridge, however the threshold
    from tests.rgbn.analytic import sphere

    n, mask = sphere(96, 4.0, 0.1)
    ridge, valley = ridges_valleys(n, 254.0, mask=mask, percentile=50.0)
    assert ridge.max() == 0 and valley.max() == 0
