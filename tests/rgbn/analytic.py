"""Analytic surfaces as normal maps (x right, y up, z to viewer) for the RGBN and render tests."""

from __future__ import annotations

import numpy as np


def grid_mm(size: int, pixel_mm: float):
    """x (right) and y (up) in mm of each pixel centre, origin at the image centre."""
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    c = (size - 1) / 2.0
    return (cols - c) * pixel_mm, -(rows - c) * pixel_mm


def normals_from_height(zx: np.ndarray, zy: np.ndarray) -> np.ndarray:
    """Unit normals of z(x, y) from its exact partial derivatives (y up)."""
    n = np.stack([-zx, -zy, np.ones_like(zx)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def sphere(size: int, radius_mm: float, pixel_mm: float, *, fill: float = 0.95):
    """Normals of a sphere cap of ``radius_mm`` seen from above and its mask (radius*fill)."""
    x, y = grid_mm(size, pixel_mm)
    rho2 = x * x + y * y
    mask = rho2 < (fill * radius_mm) ** 2
    z = np.sqrt(np.maximum(radius_mm ** 2 - rho2, 1e-12))
    n = np.stack([x, y, z], axis=-1) / radius_mm
    n[~mask] = (0.0, 0.0, 1.0)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32), mask


def tilted_plane(size: int, tilt_deg: float = 40.0, azimuth_deg: float = 30.0) -> np.ndarray:
    """A plane tilted by ``tilt_deg`` towards ``azimuth_deg``: every normal the same."""
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    n = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], np.float32)
    return np.broadcast_to(n, (size, size, 3)).copy()


def gaussian_bump(size: int, pixel_mm: float, height_mm: float, sigma_mm: float) -> np.ndarray:
    """Normals of z = h exp(-r^2 / 2 s^2)."""
    x, y = grid_mm(size, pixel_mm)
    z = height_mm * np.exp(-(x * x + y * y) / (2 * sigma_mm ** 2))
    return normals_from_height(-x / sigma_mm ** 2 * z, -y / sigma_mm ** 2 * z)
