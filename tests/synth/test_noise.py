import numpy as np
import pytest

from common.synth.noise import FractalField, affine_grid, periodic_noise_tile, sample_tile


def test_tile_is_normalised_and_seamless():
    tile = periodic_noise_tile(np.random.default_rng(0), 64, corr_px=4)
    assert abs(tile.mean()) < 1e-5 and abs(tile.std() - 1) < 1e-4
    # periodic: the jump across the wrap is like any neighbouring step, not larger
    inner = np.abs(np.diff(tile, axis=1)).mean()
    wrap = np.abs(tile[:, 0] - tile[:, -1]).mean()
    assert wrap < 2 * inner


def test_stroke_tile_has_its_ridge_frequency():
    tile = periodic_noise_tile(np.random.default_rng(1), 256, band=(16.0, 0.15))
    spec = np.abs(np.fft.fft2(tile)) ** 2
    fy = np.abs(np.fft.fftfreq(256) * 256)
    profile = spec.sum(axis=1)  # power per frequency across the ridges (along y)
    peak = fy[np.argmax(profile)]
    assert 13 <= peak <= 19


def test_grid_evaluation_matches_point_evaluation():
    field = FractalField(np.random.default_rng(2), 10.0, octaves=5, persistence=0.6)
    pm = 0.085
    a = np.deg2rad(33.0)
    G = np.array([[pm * np.cos(a), -pm * np.sin(a), 140.0], [pm * np.sin(a), pm * np.cos(a), 60.0]])
    x, y = affine_grid(G, (300, 400))
    exact = field(x, y)
    fast = field.grid(G, (300, 400))
    assert np.abs(fast - exact).mean() < 0.01 * exact.std()
    assert np.abs(fast - exact).max() < 0.05 * exact.std()


def test_field_is_a_function_of_wall_position_only():
    field = FractalField(np.random.default_rng(3), 5.0, octaves=3)
    x = np.array([10.0, 55.5, 300.25], np.float32)
    y = np.array([4.0, 80.0, 12.5], np.float32)
    # same points, in a different order and array shape
    a = field(x, y)
    b = field(x[::-1].reshape(3, 1), y[::-1].reshape(3, 1)).ravel()[::-1]
    assert np.allclose(a, b)


def test_bad_scale_is_refused():
    with pytest.raises(ValueError, match="scale_mm"):
        FractalField(np.random.default_rng(0), 0.0)


def test_sample_tile_is_periodic_in_the_tile():
    tile = periodic_noise_tile(np.random.default_rng(4), 64)
    x = np.array([[3.3]], np.float32)
    y = np.array([[7.1]], np.float32)
    # one full tile period along the tile's x axis: 64 px / 2 px per mm = 32 mm
    assert np.allclose(sample_tile(tile, x, y, px_per_mm=2.0), sample_tile(tile, x + 32, y, px_per_mm=2.0), atol=1e-3)
