import numpy as np
import pytest

from common.rgbn.curvature import curvature, mean_curvature
from tests.rgbn.analytic import gaussian_bump, grid_mm, normals_from_height, sphere, tilted_plane


@pytest.mark.parametrize("dpi,radius_mm", [(254.0, 10.0), (600.0, 4.0)])
def test_sphere_mean_curvature_is_one_over_radius_in_mm(dpi, radius_mm):
    pixel_mm = 25.4 / dpi
    size = int(2.2 * radius_mm / pixel_mm)
    n, mask = sphere(size, radius_mm, pixel_mm, fill=0.95)
    x, y = grid_mm(size, pixel_mm)
    inner = np.hypot(x, y) < 0.85 * radius_mm
    c = curvature(n, dpi, mask=mask)
    assert np.allclose(c.mean[inner], 1 / radius_mm, rtol=0.01)
    assert np.allclose(c.gaussian[inner], 1 / radius_mm ** 2, rtol=0.02)
    assert np.allclose(c.k1[inner], 1 / radius_mm, rtol=0.02)
    assert np.allclose(c.k2[inner], 1 / radius_mm, rtol=0.02)
    assert np.allclose(mean_curvature(n, dpi, mask=mask)[inner], 1 / radius_mm, rtol=0.01)


def test_concave_bowl_has_negative_mean_curvature():
    n, mask = sphere(96, 5.0, 0.1)
    bowl = n.copy()
    bowl[..., :2] *= -1  # the inside of a sphere seen from above
    x, y = grid_mm(96, 0.1)
    inner = np.hypot(x, y) < 4.0
    assert np.allclose(mean_curvature(bowl, 254.0, mask=mask)[inner], -0.2, rtol=0.01)


@pytest.mark.parametrize("method", ["central", "sobel"])
def test_plane_has_zero_curvature(method):
    c = curvature(tilted_plane(32, 50, 120), 300.0, method=method)
    for arr in (c.mean, c.gaussian, c.k1, c.k2):
        assert np.abs(arr).max() < 1e-5


def test_cylinder_principal_curvatures_and_directions():
    # z = sqrt(r^2 - x^2): curved across x, straight along y
    r, pixel_mm = 5.0, 0.05
    x, y = grid_mm(160, pixel_mm)
    z = np.sqrt(r * r - x * x)
    n = normals_from_height(-x / z, np.zeros_like(x))
    inner = np.abs(x) < 3.5
    c = curvature(n, 25.4 / pixel_mm)
    assert np.allclose(c.k1[inner], 1 / r, rtol=0.01)
    assert np.abs(c.k2[inner]).max() < 1e-4
    assert np.allclose(np.abs(c.dir1[inner][:, 0]), 1.0, atol=1e-4)  # across the axis: x
    assert np.allclose(np.abs(c.dir2[inner][:, 1]), 1.0, atol=1e-4)  # along the axis: y
    assert np.abs(c.gaussian[inner]).max() < 1e-4


def test_saddle_has_negative_gaussian_curvature_matching_the_formula():
    # z = (x^2 - y^2) / (2a): at the origin k1 = 1/a, k2 = -1/a, K = -1/a^2
    a, pixel_mm = 8.0, 0.05
    x, y = grid_mm(81, pixel_mm)
    n = normals_from_height(x / a, -y / a)
    c = curvature(n, 25.4 / pixel_mm)
    centre = (40, 40)
    assert c.k1[centre] == pytest.approx(1 / a, rel=1e-3)
    assert c.k2[centre] == pytest.approx(-1 / a, rel=1e-3)
    assert c.gaussian[centre] == pytest.approx(-1 / a ** 2, rel=1e-3)
    assert abs(c.mean[centre]) < 1e-5
    # closed form of H for a graph over the whole image: H = div(grad z / W) / 2 with convex-up sign
    zx, zy = x / a, -y / a
    W = np.sqrt(1 + zx ** 2 + zy ** 2)
    H = -((1 + zy ** 2) / a - (1 + zx ** 2) / a) / (2 * W ** 3)
    assert np.allclose(c.mean[2:-2, 2:-2], H[2:-2, 2:-2], atol=2e-4)


def test_gaussian_bump_mean_curvature_matches_closed_form():
    h, s, pixel_mm = 1.0, 2.0, 0.05
    n = gaussian_bump(128, pixel_mm, h, s)
    x, y = grid_mm(128, pixel_mm)
    z = h * np.exp(-(x * x + y * y) / (2 * s * s))
    zx, zy = -x / s ** 2 * z, -y / s ** 2 * z
    zxx = (x * x / s ** 4 - 1 / s ** 2) * z
    zyy = (y * y / s ** 4 - 1 / s ** 2) * z
    zxy = x * y / s ** 4 * z
    # mean curvature of a graph (convex-up positive = -standard formula for z up)
    H = -((1 + zy ** 2) * zxx - 2 * zx * zy * zxy + (1 + zx ** 2) * zyy) / (2 * (1 + zx ** 2 + zy ** 2) ** 1.5)
    got = curvature(n, 25.4 / pixel_mm).mean
    assert np.abs(got - H)[2:-2, 2:-2].max() < 0.01 * np.abs(H).max()


def test_curvature_is_zero_outside_the_mask():
    n, mask = sphere(64, 3.0, 0.1)
    c = curvature(n, 254.0, mask=mask)
    assert not c.mean[~mask].any() and not c.dir1[~mask].any()


def test_bad_dpi_is_refused_by_name():
    with pytest.raises(ValueError, match="dpi"):
        curvature(tilted_plane(8), 0)


@pytest.mark.parametrize("method", ["central", "sobel"])
def test_row_blocks_give_exactly_the_whole_image_result(method, monkeypatch):
    import sys

    module = sys.modules["common.rgbn.curvature"]
    rng = np.random.default_rng(0)
    n = rng.normal(size=(90, 40, 3)).astype(np.float32)
    n[..., 2] = np.abs(n[..., 2]) + 3
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    monkeypatch.setattr(module, "_BLOCK_ROWS", 10 ** 6)
    whole = curvature(n, 300.0, method=method)
    monkeypatch.setattr(module, "_BLOCK_ROWS", 7)
    blocks = curvature(n, 300.0, method=method)
    for name in ("mean", "gaussian", "k1", "k2", "dir1", "dir2"):
        assert np.array_equal(getattr(whole, name), getattr(blocks, name)), name
    assert np.allclose(mean_curvature(n, 300.0, method=method), whole.mean, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", ["central", "sobel"])
@pytest.mark.parametrize("shape", [(61, 47), (2, 9), (9, 1)])
def test_mean_curvature_matches_eq_7_7_from_the_fundamental_forms_everywhere(shape, method):
    """Independent reference: eq. 7.7 written out from OpenCV's derivatives (central differences or
    the Sobel operator, borders reflected) on random tilted normals, including the border pixels and
    thin images."""
    import cv2

    rng = np.random.default_rng(3)
    n = rng.normal(0, 0.4, shape + (3,)).astype(np.float32)
    n[..., 2] = np.abs(n[..., 2]) + 0.3
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    dpi = 300.0
    ksize, s = (1, 0.5 * dpi / 25.4) if method == "central" else (3, 0.125 * dpi / 25.4)
    dx = cv2.Sobel(n, cv2.CV_32F, 1, 0, ksize=ksize, scale=s, borderType=cv2.BORDER_REFLECT)
    dy = cv2.Sobel(n, cv2.CV_32F, 0, 1, ksize=ksize, scale=-s, borderType=cv2.BORDER_REFLECT)
    nx, ny, nz = n[..., 0], n[..., 1], np.maximum(n[..., 2], 0.05)
    E, F, G = nz ** 2 + nx ** 2, nx * ny, nz ** 2 + ny ** 2
    e = nz * dx[..., 0] - nx * dx[..., 2]
    g = nz * dy[..., 1] - ny * dy[..., 2]
    f = 0.5 * ((nz * dx[..., 1] - ny * dx[..., 2]) + (nz * dy[..., 0] - nx * dy[..., 2]))
    ref = (G * e - 2 * F * f + E * g) / (2 * nz)
    got = mean_curvature(n, dpi, method=method)
    assert np.abs(got - ref).max() <= 1e-5 * max(1.0, float(np.abs(ref).max()))
