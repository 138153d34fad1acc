import numpy as np
import pytest

from common.rgbn.bilateral import joint_bilateral
from common.rgbn.smoothing import smooth_normals
from tests.rgbn.analytic import tilted_plane


def step_normals(size=48, tilt_deg=35.0):
    n = np.zeros((size, size, 3), np.float32)
    n[..., 2] = 1
    t = np.radians(tilt_deg)
    n[:, size // 2:] = (np.sin(t), 0, np.cos(t))
    return n


def noisy(arr, sigma, seed):
    rng = np.random.default_rng(seed)
    return (arr + sigma * rng.standard_normal(arr.shape)).astype(np.float32)


@pytest.mark.parametrize("separable", [True, False])
def test_bilateral_preserves_a_normal_step_edge_and_removes_noise(separable):
    clean = step_normals()
    n = noisy(clean, 0.03, 0)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    _, out = joint_bilateral(None, n, sigma_x=3, sigma_n=0.15, separable=separable)
    err_in = np.linalg.norm(n - clean, axis=-1)
    err_out = np.linalg.norm(out - clean, axis=-1)
    # the columns at the step keep their own orientation (a Gaussian would mix them)
    seam = slice(22, 26)
    assert err_out[:, seam].max() < 0.08
    gauss = smooth_normals(n, 3.0)
    assert np.linalg.norm(gauss - clean, axis=-1)[:, seam].max() > 0.15
    # and the noise away from the edge is reduced
    assert err_out[:, 4:18].mean() < 0.5 * err_in[:, 4:18].mean()


def test_joint_filter_stops_at_a_colour_edge_even_where_normals_are_flat():
    albedo = np.zeros((40, 40, 3), np.float32)
    albedo[:, 20:] = 0.8
    normals = noisy(tilted_plane(40, 5), 0.05, 1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    out_a, out_n = joint_bilateral(albedo, normals, sigma_x=3, sigma_c=0.05, sigma_n=10.0)
    assert np.abs(out_a - albedo).max() < 1e-3
    # normals smoothed on each side, but not across the colour edge: the noise goes down
    assert np.std(out_n[:, 3:17, 0]) < 0.5 * np.std(normals[:, 3:17, 0])


def test_flat_input_is_unchanged_and_normals_stay_unit():
    n = tilted_plane(24, 30)
    albedo = np.full((24, 24, 3), 0.4, np.float32)
    a, out = joint_bilateral(albedo, n)
    assert np.allclose(a, albedo, atol=1e-6) and np.allclose(out, n, atol=1e-5)


def test_masked_pixels_neither_contribute_nor_change():
    n = step_normals(32)
    mask = np.ones((32, 32), bool)
    mask[:, 16:] = False
    garbage = n.copy()
    garbage[:, 16:] = (-1, 0, 0)
    _, a = joint_bilateral(None, n, mask=mask, sigma_n=10.0)
    _, b = joint_bilateral(None, garbage, mask=mask, sigma_n=10.0)
    assert np.allclose(a[mask], b[mask], atol=1e-5)
    assert np.array_equal(b[~mask], garbage[~mask])


def test_nothing_to_filter_is_refused():
    with pytest.raises(ValueError, match="nothing to filter"):
        joint_bilateral(None, None)
    with pytest.raises(ValueError, match="sigma_x"):
        joint_bilateral(None, step_normals(8), sigma_x=0)
