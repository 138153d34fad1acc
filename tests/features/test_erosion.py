"""Cracking and erosion from top-hats (common/features/erosion.py)."""

import numpy as np
import pytest

from common.features.erosion import erosion_map, erosion_statistics, multiscale_erosion


def _surface(n=80):
    g = np.full((n, n), 0.6, np.float32)
    nz = np.ones((n, n), np.float32)
    return g, nz


def test_dark_steep_crack_is_marked_and_its_density_and_size_follow():
    g, nz = _surface()
    g[40, 10:70] = 0.1
    nz[40, 10:70] = 0.7
    m = np.ones_like(g, bool)
    e, bt, wt = erosion_map(g, nz, m)
    assert e[40, 10:70].all() and e.sum() == 60
    d, s = erosion_statistics(e, m, 0.1)
    assert d == pytest.approx(60 / 6400) and s == pytest.approx(60 * 0.01)


def test_dark_but_flat_or_steep_but_bright_is_not_erosion():
    g, nz = _surface()
    g[20, 10:70] = 0.1          # painted dark line, flat
    nz[60, 10:70] = 0.7         # steep ridge of the same colour
    assert not erosion_map(g, nz, np.ones_like(g, bool))[0].any()


def test_features_wider_than_the_structuring_element_are_not_marked():
    g, nz = _surface()
    g[20:60, 20:60] = 0.1       # a 40 px dark, steep patch: not a crack at radius 3
    nz[20:60, 20:60] = 0.7
    e = erosion_map(g, nz, np.ones_like(g, bool))[0]
    assert e[25:55, 25:55].sum() == 0


def test_smooth_fragment_has_no_erosion_at_any_scale():
    g, nz = _surface(120)
    m = np.zeros_like(g, bool)
    m[10:110, 10:110] = True
    out = multiscale_erosion(g, nz, m, 0.1)
    assert len(out) == 20
    assert all(v == 0.0 for v in out.values())


def test_pits_show_at_the_scales_that_fit_them():
    g, nz = _surface(160)
    yy, xx = np.mgrid[:160, :160]
    for cy, cx in ((40, 40), (40, 120), (120, 40), (120, 120)):  # pits of radius 6 px
        pit = (yy - cy) ** 2 + (xx - cx) ** 2 < 36
        g[pit] = 0.1
        nz[pit] = 0.7
    out = multiscale_erosion(g, nz, np.ones_like(g, bool), 0.1)
    # the radius-3 disk misses a 12 px pit; after 2x downsampling (size 3) it fits
    assert out["erosion_density_s0"] < out["erosion_density_s3"]
    assert out["erosion_size_s3"] > 0


def test_bad_input_is_refused():
    g, nz = _surface()
    with pytest.raises(ValueError, match="radius_px"):
        erosion_map(g, nz, np.ones_like(g, bool), radius_px=0)
    with pytest.raises(ValueError, match="share one shape"):
        erosion_map(g, nz[:10], np.ones_like(g, bool))
