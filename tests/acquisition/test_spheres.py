"""Tests of common/acquisition/spheres.py: mirror- and diffuse-sphere light calibration."""

import cv2
import numpy as np
import pytest

from common.acquisition.lightfile import read_lights
from common.acquisition.spheres import (diffuse_sphere_intensities, find_sphere, fit_circle, highlight_positions,
                                        mirror_sphere_directions, sphere_normals)

SHAPE = (120, 140)
CIRCLE = (72.3, 58.6, 40.2)


def _lights(n, seed=0):
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(30, 85, n))
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _render_chrome(lights, source_deg=5.0):
    """A mirror sphere reflecting round light sources (angular radius ~source_deg, a few pixels wide)."""
    normals, inside = sphere_normals(SHAPE, CIRCLE)
    view = np.array([0.0, 0.0, 1.0])
    refl = 2 * (normals @ view)[..., None] * normals - view
    imgs = []
    for l in lights:
        ang = np.degrees(np.arccos(np.clip(refl @ l, -1, 1)))
        img = np.exp(-(ang / source_deg) ** 2) + 0.02 * inside  # plus a dim reflected room
        imgs.append(np.where(inside, img, 0.0))
    return np.stack(imgs).astype(np.float32)


def test_circle_fit_through_exact_points():
    t = np.linspace(0, 2 * np.pi, 30, endpoint=False)
    pts = np.column_stack([5 + 7 * np.cos(t), -3 + 7 * np.sin(t)])
    np.testing.assert_allclose(fit_circle(pts), [5, -3, 7], atol=1e-9)
    with pytest.raises(ValueError, match="collinear"):
        fit_circle(np.column_stack([np.arange(5.0), np.arange(5.0)]))


def test_sphere_found_from_its_mask():
    _, inside = sphere_normals(SHAPE, CIRCLE)
    cx, cy, r = find_sphere(inside)
    assert abs(cx - CIRCLE[0]) < 0.3 and abs(cy - CIRCLE[1]) < 0.3 and abs(r - CIRCLE[2]) < 0.6


def test_sphere_found_in_a_shaded_image():
    normals, inside = sphere_normals(SHAPE, CIRCLE)
    img = np.where(inside, 0.2 + 0.6 * np.clip(normals @ np.array([0.3, 0.4, 0.866]), 0, None), 0.03)
    cx, cy, r = find_sphere(img.astype(np.float32))
    assert abs(cx - CIRCLE[0]) < 1.5 and abs(cy - CIRCLE[1]) < 1.5 and abs(r - CIRCLE[2]) < 2.0


def test_empty_mask_is_refused():
    with pytest.raises(ValueError, match="empty"):
        find_sphere(np.zeros(SHAPE, bool))


def test_mirror_sphere_gives_the_rendered_light_directions():
    lights = _lights(10)
    found = mirror_sphere_directions(_render_chrome(lights), CIRCLE)
    err = np.degrees(np.arccos(np.clip((found * lights).sum(1), -1, 1)))
    assert err.max() < 0.5, err


def test_highlight_is_found_at_the_half_vector_position():
    # light straight along +x at 45° elevation: highlight where n bisects l and v
    l = np.array([[np.sqrt(0.5), 0.0, np.sqrt(0.5)]])
    h = (l[0] + [0, 0, 1]) / np.linalg.norm(l[0] + [0, 0, 1])
    (x, y), = highlight_positions(_render_chrome(l), CIRCLE)
    assert abs(x - (CIRCLE[0] + h[0] * CIRCLE[2])) < 0.5 and abs(y - CIRCLE[1]) < 0.5


def test_dark_sphere_has_no_highlight():
    with pytest.raises(ValueError, match="no highlight"):
        highlight_positions(np.zeros((1,) + SHAPE, np.float32), CIRCLE)


def test_diffuse_sphere_gives_relative_rgb_intensities():
    lights = _lights(8, seed=3)
    rng = np.random.default_rng(4)
    e = rng.uniform(0.5, 1.5, (8, 3))
    normals, inside = sphere_normals(SHAPE, CIRCLE)
    imgs = np.stack([0.6 * np.clip(normals @ l, 0, None)[..., None] * ei for l, ei in zip(lights, e)])
    imgs[:, ~inside] = 0.02
    got = diffuse_sphere_intensities(imgs.astype(np.float32), CIRCLE, lights)
    np.testing.assert_allclose(got, e / e.mean(), rtol=2e-3)


def test_diffuse_sphere_needs_lit_pixels():
    lights = np.array([[0, 0, -1.0]] * 3)  # all behind the sphere
    with pytest.raises(ValueError, match="fewer than 10"):
        diffuse_sphere_intensities(np.ones((3,) + SHAPE, np.float32), CIRCLE, lights)


def test_chrome_sphere_lights_agree_with_the_source_estimate(shared_data):
    """psm-seitz: directions from the chrome sphere vs the source's own lights.txt."""
    root = shared_data / "psm-seitz"
    mask = cv2.imread(str(root / "chrome" / "chrome.mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    imgs = np.stack([cv2.imread(str(root / "chrome" / f"chrome.{i:02d}.png"))[..., ::-1] for i in range(12)])
    found = mirror_sphere_directions(imgs.astype(np.float32) / 255, find_sphere(mask))
    ref = read_lights(root / "lights.txt").directions
    ang = np.degrees(np.arccos(np.clip((found * ref).sum(1), -1, 1)))
    # measured 3.0° mean, 8.5° max (lights 0 and 1); the grey sphere sides with ours (docs/handheld.md)
    assert ang.mean() < 4.0 and ang.max() < 10.0, ang


def _scene_with_both_spheres(lights):
    """A dim table, a mirror sphere (left) and a diffuse sphere (right) under each flash."""
    shape = (100, 200)
    mirror, diffuse = (50.0, 50.0, 30.0), (140.0, 48.0, 32.0)
    nm, im = sphere_normals(shape, mirror)
    nd, idf = sphere_normals(shape, diffuse)
    refl = 2 * nm[..., 2:3] * nm - [0, 0, 1]
    frames = []
    for l in lights:
        img = 0.04 * np.clip(l[2], 0, None) * np.ones(shape)  # the table
        img[im] = (np.exp(-(np.degrees(np.arccos(np.clip(refl @ l, -1, 1))) / 6) ** 2) + 0.02)[im]
        img[idf] = (0.7 * np.clip(nd @ l, 0, None))[idf] + 0.01
        frames.append(img)
    return np.stack(frames).astype(np.float32), mirror, diffuse


def test_mirror_and_diffuse_spheres_are_found_and_told_apart():
    from common.acquisition.spheres import find_calibration_spheres

    images, mirror, diffuse = _scene_with_both_spheres(_lights(12, seed=8))
    got_m, got_d = find_calibration_spheres(images)
    assert np.hypot(*(got_m[:2] - mirror[:2])) < 1.5 and abs(got_m[2] - mirror[2]) < 1.5
    assert got_d is not None
    assert np.hypot(*(got_d[:2] - diffuse[:2])) < 1.5 and abs(got_d[2] - diffuse[2]) < 1.5


def test_without_a_mirror_sphere_the_search_says_so():
    from common.acquisition.spheres import find_calibration_spheres

    lights = _lights(8, seed=9)
    normals, inside = sphere_normals(SHAPE, CIRCLE)
    images = np.stack([np.where(inside, 0.7 * np.clip(normals @ l, 0, None), 0.02) for l in lights])
    with pytest.raises(ValueError, match="no mirror sphere"):
        find_calibration_spheres(images.astype(np.float32))
