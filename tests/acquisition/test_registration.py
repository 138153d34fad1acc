"""Tests of scan-to-scan registration (common/acquisition/registration.py)."""

import numpy as np
import pytest

from common.acquisition.errors import RegistrationError
from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface, scan_to_scan_affine
from common.acquisition.locate import fragment_mask
from common.acquisition.registration import register_scan, register_scans, warp_to_target

DPI = 150


def _rotated_scans(seed=3, n=4, surface_seed=2):
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=seed)
    sim.place(demo_surface(25, DPI, seed=surface_seed), centre_mm=(50, 50))
    scans = []
    for k in range(n):
        if k:
            sim.rotate(90)
        scans.append(sim.scan((28, 28, 72, 72), DPI))
    return sim, scans


def _error_px(M_est, M_true, mask):
    ys, xs = np.nonzero(mask)
    P = np.vstack([xs, ys, np.ones_like(xs)])
    return np.linalg.norm(M_est @ P - M_true @ P, axis=0)


def test_rotated_scans_register_to_sub_pixel_accuracy_despite_shading_change():
    sim, scans = _rotated_scans()
    regs = register_scans(scans, DPI, nominal_deg=[0, 90, 180, 270])
    mask = fragment_mask(scans[0], DPI)
    for i in range(1, 4):
        true = scan_to_scan_affine(sim.history[i], sim.history[0])
        err = _error_px(regs[i].affine, true, mask)
        assert err.mean() < 0.3 and err.max() < 0.5, (i, err.mean())
        true_angle = sim.history[i].poses[0][0] - sim.history[0].poses[0][0]
        assert (regs[i].angle_deg - true_angle + 180) % 360 - 180 == pytest.approx(0, abs=0.3)
        assert regs[i].correlation > 0.6 and regs[i].residual >= 0


def test_registration_without_a_nominal_angle_searches_all_round():
    sim, scans = _rotated_scans(seed=4, n=2)
    reg = register_scan(scans[0], scans[1], DPI, nominal_deg=None)
    true = scan_to_scan_affine(sim.history[1], sim.history[0])
    err = _error_px(reg.affine, true, fragment_mask(scans[0], DPI))
    assert err.mean() < 0.3


def test_warping_brings_the_scan_onto_the_target():
    sim, scans = _rotated_scans(seed=5, n=2)
    reg = register_scan(scans[0], scans[1], DPI, nominal_deg=90)
    warped = warp_to_target(scans[1], reg, scans[0].shape[:2])
    # painted edges line up: the red/green chromaticity (independent of shading) agrees
    m = fragment_mask(scans[0], DPI)
    chroma = lambda f: np.log((f[..., 0] + 1e-3) / (f[..., 1] + 1e-3))
    a = chroma(scans[0].astype(np.float32) / 65535)[m]
    b = chroma(warped)[m]
    assert np.corrcoef(a, b)[0, 1] > 0.95


def test_a_different_fragment_is_refused_with_a_clear_error():
    _, a = _rotated_scans(seed=6, n=1, surface_seed=2)
    _, b = _rotated_scans(seed=6, n=1, surface_seed=9)
    with pytest.raises(RegistrationError, match="rescan|different|refusing"):
        register_scan(a[0], b[0], DPI, nominal_deg=90)
