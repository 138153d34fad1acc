import numpy as np
import pytest

from common.synth import deterioration as det


def _disc(n=200, r=70):
    yy, xx = np.mgrid[0:n, 0:n]
    return (yy - n / 2) ** 2 + (xx - n / 2) ** 2 < r ** 2


def test_erosion_only_removes_material_from_the_edge():
    mask = _disc()
    pm = 0.1
    out = det.erode_edges(mask, pm, np.random.default_rng(0), depth_mm=0.8, chips=0)
    assert np.all(out <= mask)
    removed = mask & ~out
    dist = det.inner_distance_mm(mask, pm)
    assert removed.sum() > 0
    # the removed band hugs the edge: within a few mean depths of it
    assert np.percentile(dist[removed], 95) < 4 * 0.8
    # and its depth varies along the contour (not a uniform erosion): the distance from each
    # original edge pixel to the remaining fragment
    edge = mask & (dist <= pm)
    depth = det.inner_distance_mm(~out, pm)[edge]
    assert 0.3 < depth.mean() < 2.0
    assert depth.std() > 0.2 * depth.mean()


def test_worn_edges_drop_towards_the_contour():
    mask = _disc()
    h = det.wear_edges(np.zeros(mask.shape, np.float32), mask, 0.1, radius_mm=1.0)
    assert h[100, 100] == 0
    assert h[100, 31] < h[100, 36] < 0  # 70 px radius: the edge is at column 30


def test_fade_and_discolour():
    a = np.full((2, 2, 3), [0.4, 0.1, 0.05], np.float32)
    f = det.fade(a, 0.5)
    assert f[0, 0] == pytest.approx((a[0, 0] + np.array([0.78, 0.75, 0.68])) / 2)
    d = det.discolour(a, "soot", 1.0)
    assert np.all(d < a)
    with pytest.raises(ValueError, match="kind"):
        det.discolour(a, "gold")
    with pytest.raises(ValueError, match="amount"):
        det.fade(a, 2.0)


def test_pits_lower_the_surface_and_show_plaster():
    mask = _disc()
    h = np.zeros(mask.shape, np.float32)
    a = np.zeros(mask.shape + (3,), np.float32)
    det.pit_surface(h, a, mask, 0.1, np.random.default_rng(1), per_cm2=20.0)
    assert h.min() < -0.01 and h.max() == 0
    assert a[h < -0.01].mean() > 0.2  # black paint replaced by plaster in the pits
