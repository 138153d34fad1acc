"""Tests of common/acquisition/discontinuity.py: multi-flash depth edges (Raskar et al. 2004)."""

import cv2
import numpy as np
import pytest

from common.acquisition.discontinuity import depth_discontinuities
from common.acquisition.handheld import simulate_flash_capture
from common.acquisition.surface import FragmentSurface

SIZE, RADIUS, DPI = 96, 24, 254.0


def _ring_of_flashes(n=8, elevation_deg=45.0):
    az = np.radians(np.arange(n) * 360.0 / n + 10)
    el = np.radians(elevation_deg)
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(n, np.sin(el))])


def _textured(height_mm, seed=0):
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.3, 0.9, (SIZE, SIZE, 3)).astype(np.float32)  # albedo edges everywhere
    return FragmentSurface(albedo, height_mm, np.ones((SIZE, SIZE), bool), DPI)


def _raised_disk():
    rows, cols = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    disk = (cols - SIZE / 2) ** 2 + (rows - SIZE / 2) ** 2 < RADIUS ** 2
    return disk, np.where(disk, 6 * 25.4 / DPI, 0.0), rows, cols


def test_edges_of_a_raised_disk_are_found_on_its_outline():
    disk, height, _, _ = _raised_disk()
    lights = _ring_of_flashes()
    d = depth_discontinuities(simulate_flash_capture(_textured(height), lights, ambient=0.05), lights)
    edge = np.linalg.norm(d, axis=2) > 0
    outline = disk & ~cv2.erode(disk.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    dist = cv2.distanceTransform((~outline).astype(np.uint8), cv2.DIST_L2, 3)
    assert (dist[edge] <= 1.5).mean() > 0.97  # precision: edges lie on the outline ...
    near = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert near[outline].mean() > 0.95  # ... and cover it


def test_edge_direction_points_to_the_occluding_side():
    _, height, rows, cols = _raised_disk()
    lights = _ring_of_flashes()
    d = depth_discontinuities(simulate_flash_capture(_textured(height), lights, ambient=0.05), lights)
    s = np.linalg.norm(d, axis=2)
    edge = s > 0
    # the disk is the nearer side: towards its centre, in x right / y up
    to_centre = np.stack([SIZE / 2 - cols, rows - SIZE / 2], -1)[edge]
    to_centre /= np.linalg.norm(to_centre, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip((d[edge] / s[edge, None] * to_centre).sum(1), -1, 1)))
    assert ang.mean() < 10 and ang.max() < 25
    assert 0.5 < s[edge].mean() <= 1.0  # shadows are dark: strong steps


def test_flat_textured_surface_has_no_depth_edges():
    lights = _ring_of_flashes()
    images = simulate_flash_capture(_textured(np.zeros((SIZE, SIZE))), lights, ambient=0.05)
    assert not np.any(depth_discontinuities(images, lights))


def test_flash_on_the_view_axis_is_ignored():
    images = np.ones((3, 16, 16), np.float32)
    images[0, :, :8] = 0.0  # would be a step, but light 0 is on the axis and casts no shadow
    lights = np.array([[0, 0, 1.0], [0.5, 0, 0.87], [-0.5, 0, 0.87]])
    assert not np.any(depth_discontinuities(images, lights))


@pytest.mark.parametrize("kwargs, match", [
    (dict(directions=np.zeros((2, 3))), "directions"),
    (dict(min_step=1.5), "min_step"),
    (dict(sigma=-1), "sigma"),
    (dict(mask=np.ones((3, 3), bool)), "mask"),
])
def test_bad_arguments_are_refused(kwargs, match):
    args = dict(images=np.ones((3, 8, 8), np.float32), directions=_ring_of_flashes(3))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        depth_discontinuities(args.pop("images"), args.pop("directions"), **args)
