import numpy as np
import pytest

from common.synth.painting import Painting
from common.synth.relief import WallRelief, normals_from_height


def test_normals_follow_the_rgbn_convention():
    pm = 0.5
    rows, cols = np.mgrid[0:20, 0:30] * pm
    # rising 0.2 mm per mm to the right: the normal leans left (-x)
    n = normals_from_height(0.2 * cols, pm)
    assert n[10, 15] == pytest.approx(np.array([-0.2, 0, 1]) / np.hypot(0.2, 1), abs=1e-5)
    # rising towards the bottom of the image = falling upwards: the normal leans up (+y)
    n = normals_from_height(0.3 * rows, pm)
    assert n[10, 15] == pytest.approx(np.array([0, 0.3, 1]) / np.hypot(0.3, 1), abs=1e-5)


def _plain(width=120.0, height=80.0, strings=(), incisions=()):
    return Painting(np.full((int(height), int(width), 3), 0.5, np.float32), 1.0, list(strings), list(incisions))


def test_string_impression_is_a_groove_along_its_line():
    p = _plain(strings=[((0.0, 40.0), (120.0, 40.0))] * 3)  # three chances: some strings are skipped
    relief = WallRelief(p, np.random.default_rng(1), grain_depth_mm=0.0)
    x = np.full(41, 60.0, np.float32)
    y = np.linspace(30, 50, 41).astype(np.float32)
    macro = relief.height(x, y) - relief.strokes(x, y)
    centre = macro[20]
    assert centre < macro[0] - 0.05 and centre < macro[-1] - 0.05
    assert np.argmin(macro) in range(18, 23)


def test_relief_is_identical_for_the_same_wall_point():
    relief = WallRelief(_plain(), np.random.default_rng(2))
    x = np.array([10.0, 50.0], np.float32)
    y = np.array([20.0, 70.0], np.float32)
    assert np.array_equal(relief.height(x, y), relief.height(x.copy(), y.copy()))
    t = relief.thickness(x, y)
    assert np.all(t > 0)


def test_brush_strokes_run_along_their_region_orientation():
    relief = WallRelief(_plain(300, 300), np.random.default_rng(3), stroke_region_mm=1000.0)
    reg = relief.regions[0]
    d = np.array([np.cos(reg.angle_rad), np.sin(reg.angle_rad)])
    nrm = np.array([-d[1], d[0]])
    s = np.linspace(0, 20, 400)
    c = np.array([150.0, 150.0])
    along = relief.strokes(*(c[:, None] + d[:, None] * s).astype(np.float32))
    across = relief.strokes(*(c[:, None] + nrm[:, None] * s).astype(np.float32))
    # ridges vary much faster across the strokes than along them
    assert np.abs(np.diff(across)).mean() > 2 * np.abs(np.diff(along)).mean()
