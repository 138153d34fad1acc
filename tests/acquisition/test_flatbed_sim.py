"""Tests of the simulated flatbed (common/acquisition/flatbed_sim.py)."""

import numpy as np
import pytest

from common.acquisition.errors import ScannerError
from common.acquisition.flatbed_sim import (LampGeometry, SimulatedFlatbed, calibration_target, demo_surface,
                                            lamp_irradiance, scan_to_scan_affine)
from common.acquisition.surface import FragmentSurface


def _closed_form(n, depth, lamp):
    """∫ (n_x sin α + (n_y d + n_z D) cos α / r) / r dα over |α| <= half, in closed form."""
    D = lamp.height_mm + depth
    d = lamp.offset_mm
    r = np.hypot(d, D)
    h = np.deg2rad(lamp.half_angle_deg)
    along = (n[1] * d + n[2] * D) / r
    direct = (n[0] * (-np.cos(h) + np.cos(-h)) + along * (np.sin(h) - np.sin(-h))) / r
    r0 = np.hypot(d, lamp.height_mm)
    ref = 2 * np.sin(h) * lamp.height_mm / r0 / r0 + lamp.ambient
    return (direct + lamp.ambient * (1 + n[2]) / 2) / ref


@pytest.mark.parametrize("normal,depth", [((0, 0, 1), 0.0), ((0.1, 0.2, 0.97), 1.0), ((-0.05, -0.2, 0.98), 3.0)])
def test_lamp_quadrature_matches_closed_form_line_integral(normal, depth):
    # normals for which no part of the lamp is behind the surface (no clamping)
    lamp = LampGeometry()
    n = np.array(normal) / np.linalg.norm(normal)
    got = lamp_irradiance(n[None].astype(np.float32), depth, lamp)[0]
    assert got == pytest.approx(_closed_form(n, depth, lamp), rel=1e-4)


def test_irradiance_falls_with_distance_from_glass_and_faces_the_lamp():
    lamp = LampGeometry()
    up = np.array([[0, 0, 1.0]], np.float32)
    assert lamp_irradiance(up, 0.0, lamp)[0] == pytest.approx(1.0, rel=1e-5)
    far = [lamp_irradiance(up, d, lamp)[0] for d in (1.0, 5.0, 20.0)]
    assert 1.0 > far[0] > far[1] > far[2]
    towards = np.array([[0, np.sin(0.3), np.cos(0.3)]], np.float32)     # tilted towards the lamp (+y)
    away = np.array([[0, -np.sin(0.3), np.cos(0.3)]], np.float32)
    assert lamp_irradiance(towards, 0.0, lamp)[0] > 1.0 > lamp_irradiance(away, 0.0, lamp)[0]


def test_flat_white_target_reads_the_exposure_level_with_noise():
    sim = SimulatedFlatbed(bed_mm=(60, 60), seed=3, dust=0)
    sim.place(calibration_target(0, 0, size_mm=20, dpi=100, albedo=1.0), angle_deg=0, centre_mm=(30, 30))
    img = sim.scan((25, 25, 35, 35), 100, 16).astype(float) / 65535
    assert img.mean() == pytest.approx(sim.exposure, rel=0.01)
    expected_sigma = np.sqrt(sim.noise ** 2 * sim.exposure + sim.read_noise ** 2)
    assert img.std() == pytest.approx(expected_sigma, rel=0.25)


def test_depth_8_and_16_bits_quantise_to_their_dtypes():
    sim = SimulatedFlatbed(bed_mm=(60, 60), seed=3)
    sim.place(demo_surface(20, 100), centre_mm=(30, 30))
    a16, a8 = sim.scan((10, 10, 50, 50), 100, 16), sim.scan((10, 10, 50, 50), 100, 8)
    assert a16.dtype == np.uint16 and a8.dtype == np.uint8 and a16.shape == a8.shape == (157, 157, 3)
    assert abs(a16.astype(float).mean() / 65535 - a8.astype(float).mean() / 255) < 0.01


def test_lamp_shadow_falls_on_the_side_away_from_the_lamp():
    sim = SimulatedFlatbed(bed_mm=(80, 80), seed=1, dust=0, noise=0, read_noise=0)
    sim._lid_tex[:] = 0                       # plain lid so only the shadow changes its brightness
    square = FragmentSurface(albedo=np.full((80, 80, 3), 0.5, np.float32), height_mm=np.zeros((80, 80), np.float32),
                             mask=np.ones((80, 80), bool), dpi=100, thickness_mm=10)
    sim.place(square, angle_deg=0, centre_mm=(40, 40))      # 20 mm square, rows 30..50 mm
    img = sim.scan(None, 100, 16).mean(axis=2)
    col = img.shape[1] // 2
    row = lambda mm: int(mm / 25.4 * 100)
    lit_side, shadow_side, far = img[row(27), col], img[row(53), col], img[row(75), col]
    # the lamp is towards row 0: the lid just below the fragment is shadowed, above it is lit
    assert shadow_side < 0.7 * far
    assert lit_side > 0.9 * far


def test_operator_rotation_is_90_plus_minus_10_and_flip_shows_the_mirrored_back():
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=5)
    s = demo_surface(20, 100, seed=1)
    sim.place(s, centre_mm=(50, 50))
    angles = []
    for _ in range(6):
        a0 = sim.pose_of(0)[0]
        sim.rotate(90)
        angles.append(sim.pose_of(0)[0] - a0)
    assert all(80 <= a <= 100 for a in angles)
    assert np.std(angles) > 1.0                 # not always exactly 90
    sim.flip()
    back = sim._items[0].surface
    np.testing.assert_array_equal(back.mask, s.mask[:, ::-1])
    assert back.back is s


def test_scan_to_scan_ground_truth_maps_the_same_fragment_point():
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=2)
    sim.place(demo_surface(20, 100, seed=1), centre_mm=(50, 50))
    sim.scan((30, 30, 70, 70), 100)
    sim.rotate(90)
    sim.scan((28, 28, 72, 72), 100)
    M = scan_to_scan_affine(sim.history[1], sim.history[0])
    ang = np.degrees(np.arctan2(M[1, 0], M[0, 0]))
    assert ang == pytest.approx(sim.history[1].poses[0][0] - sim.history[0].poses[0][0], abs=1e-9)


def test_device_fault_raises_a_scanner_error_and_bad_area_is_refused():
    sim = SimulatedFlatbed(bed_mm=(50, 50))
    with pytest.raises(ValueError, match="area_mm"):
        sim.scan((10, 10, 80, 20), 50)
    sim.fault = "SANE_STATUS_COVER_OPEN"
    with pytest.raises(ScannerError) as err:
        sim.scan(None, 50)
    assert err.value.status == "SANE_STATUS_COVER_OPEN"
