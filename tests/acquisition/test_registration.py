"""Tests of scan-to-scan registration (common/acquisition/registration.py)."""

import numpy as np
import pytest

from common.acquisition.errors import RegistrationError
from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface, scan_to_scan_affine
from common.acquisition.locate import fragment_mask
from common.acquisition.registration import (ScanOrderError, TurnDirectionError, register_scan, register_scans,
                                             registration_image, warp_to_target)

DPI = 150


def _rotated_scans(seed=3, n=4, surface_seed=2, turn=90):
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=seed)
    sim.place(demo_surface(25, DPI, seed=surface_seed), centre_mm=(50, 50))
    scans = []
    for k in range(n):
        if k:
            sim.rotate(turn)
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


def test_counter_clockwise_turns_are_named_with_what_to_do_not_rescan():
    sim, scans = _rotated_scans(seed=7, n=4, turn=-90)
    with pytest.raises(TurnDirectionError, match=r"counter-clockwise.*--turn ccw") as info:
        register_scans(scans, DPI, nominal_deg=[0, 90, 180, 270])
    assert info.value.turn == "ccw" and "rescanning is not needed" in str(info.value)
    # the registrations found the other way round are right
    mask = fragment_mask(scans[0], DPI)
    for i in range(1, 4):
        err = _error_px(info.value.registrations[i].affine, scan_to_scan_affine(sim.history[i], sim.history[0]), mask)
        assert err.mean() < 0.3


def test_scans_out_of_turning_order_are_named_as_such():
    sim, scans = _rotated_scans(seed=8, n=3)
    shuffled = [scans[0], scans[2], scans[1]]          # 0°, 180°, 90°
    with pytest.raises(ScanOrderError, match="out of turning order") as info:
        register_scans(shuffled, DPI, nominal_deg=[0, 90, 180])
    true = [(sim.history[k].poses[0][0] - sim.history[0].poses[0][0]) % 360 for k in (0, 2, 1)]
    assert np.allclose(info.value.angles_deg, true, atol=1.0)


def test_registration_image_chroma_term_does_not_change_with_the_lamp_side_across_a_groove():
    # a paint edge (red-brown | blue-grey) with a groove's two flanks beside it, lit from one side and
    # from the other. Under one white lamp the log chromaticity of every pixel is independent of the
    # shading, so with the log taken before the blur the chroma term is the same image for both lamp
    # sides; blurring the linear image first mixes a bright and a dark flank and moves the edge
    # (the 0.35-0.6 px registration bias of issue 16)
    x = np.arange(200)
    paint = np.where(x[:, None] < 100, [0.7, 0.45, 0.3], [0.35, 0.45, 0.6])
    def scan(side):
        shade = np.ones(200)
        shade[96:100], shade[100:104] = 1.0 + 0.6 * side, 1.0 - 0.6 * side
        return np.repeat((paint * shade[:, None] * 0.6)[None], 40, axis=0).astype(np.float32)
    a = registration_image(scan(+1), luminance_weight=0.0)
    b = registration_image(scan(-1), luminance_weight=0.0)
    assert np.abs(a - b).max() < 0.01 * a.max()        # blurring first: 0.59 of the peak


def test_a_scan_without_the_fragment_is_named_by_its_own_index():
    sim, scans = _rotated_scans(seed=9, n=3)
    sim.clear()
    empty = sim.scan((28, 28, 72, 72), DPI)                # the lid only
    with pytest.raises(RegistrationError, match=r"^scan 0: no fragment visible"):
        register_scans([empty, scans[1], scans[2]], DPI, nominal_deg=[0, 90, 180])
    with pytest.raises(RegistrationError, match=r"^scan 2: no fragment visible"):
        register_scans([scans[0], scans[1], empty], DPI, nominal_deg=[0, 90, 180])


def test_scans_cropped_inside_the_piece_are_refused_saying_the_piece_may_fill_the_picture():
    """Seen on real scans: pictures already cropped to the piece (a coin filling the frame) have no bed to tell
    the piece from, and were refused as if blank. The message names that case and what to do."""
    sim, scans = _rotated_scans(seed=9, n=3)
    ys, xs = np.nonzero(fragment_mask(scans[0], DPI))
    cy, cx = int(ys.mean()), int(xs.mean())
    inside = [s[cy - 15:cy + 15, cx - 15:cx + 15] for s in scans]      # 30 px = 7.6 mm, all piece
    with pytest.raises(RegistrationError, match=r"^scan 0: no fragment visible") as err:
        register_scans(inside, DPI, nominal_deg=[0, 90, 180])
    assert "fill the picture" in str(err.value) and "margin of bed" in str(err.value)


def test_rough_turns_far_from_90_degrees_still_register():
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=10)
    sim.place(demo_surface(25, DPI, seed=2), centre_mm=(50, 50))
    scans = [sim.scan((28, 28, 72, 72), DPI)]
    for turn in (90, 135, 60):               # outside the ±20° search around each nominal step
        sim.rotate(turn, error_deg=0)
        scans.append(sim.scan((28, 28, 72, 72), DPI))
    regs = register_scans(scans, DPI, nominal_deg=[0, 90, 180, 270])
    mask = fragment_mask(scans[0], DPI)
    for i in range(1, 4):
        err = _error_px(regs[i].affine, scan_to_scan_affine(sim.history[i], sim.history[0]), mask)
        assert err.mean() < 0.3, (i, err.mean())
