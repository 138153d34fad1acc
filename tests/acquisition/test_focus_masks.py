"""Masks of an object of the bed's own grey (the real coin's case, issue 16): focus, consistency, lamp side."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.acquisition.calibration import (NOMINAL_A, lamp_direction_from_shadows, newest_calibration,
                                            nominal_calibration)
from common.acquisition.flatbed_normals import consistent_mask
from common.acquisition.locate import area_spread, face_masks, focus_mask, fragment_mask
from common.acquisition.registration import Registration

DPI = 100.0
PX = DPI / 25.4


def _scene(angle_deg: float, centre=(100.0, 90.0), shadow_to=(1.0, 0.0), seed=0, size=(180, 240)):
    """A textured oval object of the bed's grey, turned by ``angle_deg`` (clockwise on the image).

    The lamp's shadow (dark, blurred over ~1.5 mm) falls towards ``shadow_to`` (image x, y) in
    every scan; the object's texture (engraving-like, sharp) and outline turn with it. Returns the
    scan (uint8 RGB) and the object's true mask.
    """
    H, W = size
    rng = np.random.default_rng(seed)
    # texture in the object's own frame, fixed by a seed shared by every scan
    tex_rng = np.random.default_rng(123)
    tex = cv2.GaussianBlur(tex_rng.normal(0, 1, (241, 241)).astype(np.float32), (0, 0), 0.8)
    tex = 0.12 * tex / tex.std()
    yy, xx = np.mgrid[-120:121, -120:121].astype(np.float32)
    obj = ((xx / 46.0) ** 2 + (yy / 38.0) ** 2 <= 1).astype(np.float32)     # an oval, 92 x 76 px
    rim = obj - cv2.erode(obj, np.ones((3, 3), np.uint8))
    M = cv2.getRotationMatrix2D((120, 120), -angle_deg, 1.0)   # positive = clockwise on the image
    M[:, 2] += np.array(centre) - 120
    obj_w = cv2.warpAffine(obj, M, (W, H), flags=cv2.INTER_LINEAR) > 0.5
    tex_w = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR)
    rim_w = cv2.warpAffine(rim, M, (W, H), flags=cv2.INTER_LINEAR)
    bed = 0.45
    img = np.full((H, W), bed, np.float32)
    # the shadow: the object's silhouette pushed 8 px towards shadow_to, blurred, darkening the bed
    S = np.float32([[1, 0, 8 * shadow_to[0]], [0, 1, 8 * shadow_to[1]]])
    sh = cv2.warpAffine(obj_w.astype(np.float32), S, (W, H))
    sh = cv2.GaussianBlur(sh, (0, 0), 1.5 * PX)      # a penumbra of ~1.5 mm
    img *= 1 - 0.55 * np.clip(sh * 1.6, 0, 1)
    img = np.where(obj_w, bed + tex_w - 0.25 * rim_w, img)
    img += rng.normal(0, 0.004, img.shape).astype(np.float32)
    rgb = np.clip(np.stack([img, img * 0.97, img * 1.02], axis=2), 0, 1)
    return (rgb * 255).round().astype(np.uint8), obj_w


def _iou(a, b):
    return np.count_nonzero(a & b) / np.count_nonzero(a | b)


def test_focus_mask_takes_the_sharp_object_not_its_blurred_shadow():
    scan, truth = _scene(0.0)
    colour = fragment_mask(scan, DPI)
    focus = focus_mask(scan, DPI)
    assert _iou(focus, truth) > 0.9
    # colour alone cannot tell the object of the bed's grey from its shadow
    assert _iou(colour, truth) < _iou(focus, truth)


def test_register_face_uses_focus_masks_when_the_colour_masks_hold_the_scanners_shadow():
    """The colour masks take the object plus its shadow, which does not turn with it: focus is used."""
    from common.acquisition.flatbed_normals import register_face
    scans, truths = zip(*[_scene(a, centre=(100 + 4 * k, 90 - 3 * k)) for k, a in enumerate((0, 90, 180, 270))])
    turn, regs, mask, method = register_face(list(scans), DPI, turn="auto")
    assert method == "focus" and turn == "cw"
    assert _iou(mask, truths[0]) > 0.9
    assert np.allclose([r.angle_deg % 360 for r in regs], [0, 90, 180, 270], atol=1.5)


def test_face_masks_fall_back_on_focus_when_colour_masks_disagree_in_area():
    scans, truths = zip(*[_scene(a, centre=(100 + 4 * k, 90 - 3 * k)) for k, a in enumerate((0, 90, 180, 270))])
    # scans 1 and 3 also show a blurred bluish glow touching the object (the real coin's lifted rim,
    # out of focus): their colour masks take it, their focus masks do not
    scans = [s.astype(np.float32) for s in scans]
    for k in (1, 3):
        glow = np.zeros(scans[k].shape[:2], np.float32)
        ys, xs = np.nonzero(truths[k])
        cv2.circle(glow, (int(xs.max()) + 10, int(ys.mean())), 30, 1.0, -1)
        glow = cv2.GaussianBlur(glow, (0, 0), 4.0) * ~truths[k]
        scans[k] += glow[..., None] * np.float32([60, 70, 110])
    scans = [np.clip(s, 0, 255).astype(np.uint8) for s in scans]
    masks, method = face_masks(list(scans), DPI)
    assert method == "focus"
    assert area_spread(masks) < 1.1
    for m, t in zip(masks, truths):
        assert _iou(m, t) > 0.88


def test_face_masks_keep_the_colour_mask_when_it_is_consistent():
    # a painted object clearly unlike the bed: the colour masks agree, nothing changes
    scans = []
    for k in range(4):
        s = np.full((120, 140, 3), 60, np.uint8)
        cv2.circle(s, (70 + k, 60), 30, (200, 150, 90), -1)
        scans.append(s)
    masks, method = face_masks(scans, DPI)
    assert method == "colour"


def test_consistent_mask_drops_what_stays_with_the_scanner():
    """A blob fixed in the scan frame (a shadow) leaves the intersection; the turned object stays."""
    H, W = 100, 100
    yy, xx = np.mgrid[0:H, 0:W]
    obj = (xx - 50) ** 2 + (yy - 50) ** 2 < 20 ** 2
    shadow = (xx - 75) ** 2 + (yy - 50) ** 2 < 8 ** 2          # to the right in every scan
    masks, regs = [], []
    for k, ang in enumerate((0, 90, 180, 270)):
        # scan k: the object turned by ang about (50, 50): target pixel -> scan pixel
        M = cv2.getRotationMatrix2D((50, 50), -ang, 1.0)
        regs.append(Registration(M, float(ang), 1.0, 0.0))
        masks.append(obj | shadow)     # the object is round: its mask looks alike; the shadow stays right
    out = consistent_mask(masks, regs, (H, W))
    assert not out[shadow & ~obj].any()
    assert out[obj].mean() > 0.99


def test_lamp_direction_from_shadows_ignores_shade_that_turns_with_the_object():
    """The shadow falls to the right in every scan (lamp on the left, 180°)."""
    scans, truths = zip(*[_scene(a, centre=(100 + 4 * k, 90 - 3 * k)) for k, a in enumerate((0, 90, 180, 270))])
    d, agreement = lamp_direction_from_shadows(list(scans), list(truths), DPI)
    assert abs((d - 180 + 180) % 360 - 180) < 15
    scans2, truths2 = zip(*[_scene(a, centre=(100, 100), shadow_to=(0, -1), size=(200, 200))
                            for a in (0, 90, 180, 270)])
    d2, _ = lamp_direction_from_shadows(list(scans2), list(truths2), DPI)   # shadow up: lamp at the bottom
    assert abs((d2 - 270 + 180) % 360 - 180) < 15


def test_nominal_calibration_turns_the_simulator_model_to_the_lamp_side():
    top = nominal_calibration("x", 90.0)
    assert np.allclose(top.a, NOMINAL_A, atol=1e-12)
    left = nominal_calibration("x", 180.0)
    assert np.allclose(left.a, [-np.hypot(*NOMINAL_A[:2]), 0, NOMINAL_A[2], NOMINAL_A[3]], atol=1e-12)
    with pytest.raises(ValueError):
        nominal_calibration("x", float("nan"))


def test_calibrate_nominal_stores_a_usable_calibration(tmp_path):
    from common.store import Store
    from services.cli import main
    root = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{root}"', "--nominal", "--device", "flatbed-x"]) == 2
    assert main(["calibrate", "--set", f'storage.root="{root}"', "--nominal", "--lamp-direction-deg", "0",
                 "--device", "flatbed-x"]) == 0
    cal, _ = newest_calibration(Store(root), "flatbed-x")
    assert np.allclose(cal.a, [np.hypot(*NOMINAL_A[:2]), 0, NOMINAL_A[2], NOMINAL_A[3]], atol=1e-9)
    assert cal.report[0]["nominal"]


