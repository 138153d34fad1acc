"""Tests of common/web/compose.py: pictures joined at a pose reassemble what was cut apart."""

import math

import cv2
import numpy as np
import pytest

from common.web.compose import (encode_png, join_at_pose, linear_to_srgb8, outline_detected, raking_light,
                                relative_pose, side_by_side)

MAGENTA = (255, 0, 255)


def _texture(h, w):
    """Smooth colourful picture (values 30..200, never magenta) so bilinear resampling is near exact."""
    r, c = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([115 + 80 * np.sin(c / 9.0), 115 + 80 * np.cos(r / 7.0), 115 + 60 * np.sin((r + c) / 11.0)], axis=2)
    return img.astype(np.uint8)


def _cut(pose, pixel_mm):
    """An original picture split in two: A = left half in the original frame, B = right half moved
    into its own frame so that ``pose`` (B frame -> A frame, mm) puts it back."""
    h, w = 100, 140
    img = _texture(h, w)
    mask_a = np.zeros((h, w), bool)
    mask_a[:, :70] = True
    mask_right = ~mask_a
    # B pixel q -> A pixel p = R q + t/pixel_mm ; sample the original at p for every q
    angle, tx, ty = pose
    c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    m = np.array([[c, -s, tx / pixel_mm], [s, c, ty / pixel_mm]])
    size = (170, 170)
    img_b = cv2.warpAffine(img, m, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    mask_b = cv2.warpAffine(mask_right.astype(np.uint8), m, size,
                            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0).astype(bool)
    # where the inverse map falls outside the original, there is no fragment
    inside = cv2.warpAffine(np.ones((h, w), np.uint8), m, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                            borderValue=0).astype(bool)
    return img, img.copy(), mask_a, img_b, mask_b & inside


def _pose_putting_piece_in_frame(angle, pixel_mm):
    """Pose whose B frame holds the right half: B's centre (85, 85) px maps to the half's centre (105, 50) px."""
    c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    qx, qy = 85.0, 85.0
    tx, ty = 105.0 - (c * qx - s * qy), 50.0 - (s * qx + c * qy)
    return (angle, tx * pixel_mm, ty * pixel_mm)


def _reassembly_error(canvas, original):
    """Mean absolute error between the original and the non-background part of the canvas."""
    fg = np.any(canvas != MAGENTA, axis=2)
    rows, cols = np.flatnonzero(fg.any(axis=1)), np.flatnonzero(fg.any(axis=0))
    h, w = original.shape[:2]
    crop = canvas[rows[0]:rows[0] + h, cols[0]:cols[0] + w].astype(float)
    if crop.shape[:2] != (h, w):
        return float("inf")
    inner = np.zeros((h, w), bool)
    inner[3:-3, 3:-3] = True
    inner[:, 66:74] = False  # the cut itself: nearest-neighbour masks leave a one-pixel seam
    return float(np.abs(crop - original)[inner].mean())


@pytest.mark.parametrize("angle", [0.0, 33.0, -120.0])
def test_join_at_pose_reassembles_a_picture_cut_in_two(angle):
    pixel_mm = 25.4 / 300
    pose = _pose_putting_piece_in_frame(angle, pixel_mm)
    original, img_a, mask_a, img_b, mask_b = _cut(pose, pixel_mm)
    canvas = join_at_pose(img_a, mask_a, img_b, mask_b, pose, pixel_mm, outline=False, background=MAGENTA,
                          max_side_px=4096, margin_px=5)
    assert _reassembly_error(canvas, original) < 4.0


def test_join_at_a_wrong_pose_does_not_reassemble():
    pixel_mm = 25.4 / 300
    pose = _pose_putting_piece_in_frame(33.0, pixel_mm)
    original, img_a, mask_a, img_b, mask_b = _cut(pose, pixel_mm)
    wrong = (pose[0] + 8.0, pose[1], pose[2])
    canvas = join_at_pose(img_a, mask_a, img_b, mask_b, wrong, pixel_mm, outline=False, background=MAGENTA,
                          max_side_px=4096, margin_px=5)
    assert _reassembly_error(canvas, original) > 10.0


def test_join_at_pose_is_scaled_to_fit_and_outlines_both_fragments():
    pixel_mm = 25.4 / 300
    pose = _pose_putting_piece_in_frame(10.0, pixel_mm)
    _, img_a, mask_a, img_b, mask_b = _cut(pose, pixel_mm)
    canvas = join_at_pose(img_a, mask_a, img_b, mask_b, pose, pixel_mm, max_side_px=64)
    assert max(canvas.shape[:2]) <= 64
    canvas = join_at_pose(img_a, mask_a, img_b, mask_b, pose, pixel_mm)
    for colour in ((0, 158, 255), (255, 140, 0)):
        assert np.all(canvas == colour, axis=2).sum() > 50


def test_join_at_pose_names_bad_arguments():
    m = np.ones((4, 4), bool)
    img = np.zeros((4, 4, 3), np.uint8)
    with pytest.raises(ValueError, match="pixel_mm"):
        join_at_pose(img, m, img, m, (0, 0, 0), 0.0)
    with pytest.raises(ValueError, match="mask_b"):
        join_at_pose(img, m, img, np.ones((3, 3), bool), (0, 0, 0), 0.1)
    with pytest.raises(ValueError, match="pose"):
        join_at_pose(img, m, img, m, (0, float("nan"), 0), 0.1)


def test_relative_pose_maps_points_like_the_two_wall_poses():
    rng = np.random.default_rng(4)
    for _ in range(20):
        pa = (rng.uniform(-180, 180), *rng.uniform(-200, 200, 2))
        pb = (rng.uniform(-180, 180), *rng.uniform(-200, 200, 2))
        p_b = rng.uniform(-50, 50, 2)

        def rot(deg):
            c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
            return np.array([[c, -s], [s, c]])

        wall = rot(pb[0]) @ p_b + pb[1:]
        expected_a = rot(pa[0]).T @ (wall - pa[1:])
        rel = relative_pose(pa, pb)
        np.testing.assert_allclose(rot(rel[0]) @ p_b + rel[1:], expected_a, atol=1e-9)


def test_outline_detected_draws_on_the_fragment_boundary():
    h, w = 120, 160
    prescan = np.full((h, w, 3), 30, np.uint8)
    r, c = np.mgrid[0:h, 0:w]
    disk = (r - 60) ** 2 + (c - 70) ** 2 <= 30 ** 2
    out = outline_detected(prescan, disk, thickness_px=1)
    drawn = np.any(out != 30, axis=2)
    dist = np.hypot(r - 60, c - 70)[drawn]
    assert drawn.sum() > 2 * math.pi * 30 * 0.7
    assert np.all(np.abs(dist - 30) < 2.0)
    with pytest.raises(ValueError, match="mask"):
        outline_detected(prescan, disk[:10])


def test_raking_light_brightens_slopes_facing_the_light():
    n = np.zeros((2, 2, 3), np.float32)
    n[..., 2] = 1
    flat = raking_light(n)[0, 0, 0]
    assert abs(int(flat) - 128) <= 1
    facing = np.array([math.cos(math.radians(135)), math.sin(math.radians(135)), 1.0])
    facing /= np.linalg.norm(facing)
    away = facing * [-1, -1, 1]
    n2 = np.array([[facing, away]], np.float32)
    out = raking_light(n2)
    assert out[0, 0, 0] > flat > out[0, 1, 0]


def test_srgb_encoding_matches_the_standard_curve():
    # IEC 61966-2-1: linear 0.5 -> 0.7354 -> 188 ; linear 0.002 -> 12.92*0.002 -> 7
    np.testing.assert_array_equal(linear_to_srgb8(np.array([0.0, 0.002, 0.5, 1.0])), [0, 7, 188, 255])


def test_side_by_side_and_png_round_trip():
    a = np.full((40, 20, 3), 200, np.uint8)
    b = np.full((80, 80, 3), 50, np.uint8)
    out = side_by_side([a, b], gap_px=4)
    assert out.shape == (40, 20 + 4 + 40, 3)
    back = cv2.cvtColor(cv2.imdecode(np.frombuffer(encode_png(out), np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(back, out)


def test_side_by_side_at_one_scale_draws_each_picture_at_its_physical_size():
    """Given each picture's pixel size the row is at one mm a pixel: a 105 mm piece at 100 dpi next to a 149 mm
    piece at 50 dpi is drawn 105/149 as tall (both were scaled to one height), centred on the row."""
    a = np.full((int(round(105 / 25.4 * 100)), 80, 3), 200, np.uint8)    # 105 mm at 100 dpi: 413 px
    b = np.full((int(round(149 / 25.4 * 50)), 60, 3), 90, np.uint8)      # 149 mm at 50 dpi: 293 px
    out = side_by_side([a, b], gap_px=4, pixel_mm=[25.4 / 100, 25.4 / 50])
    assert out.shape[0] == b.shape[0]   # the tallest piece keeps its pixels
    rows_a = np.flatnonzero((out == 200).all(axis=2).any(axis=1))
    rows_b = np.flatnonzero((out == 90).all(axis=2).any(axis=1))
    assert len(rows_b) == b.shape[0]
    assert len(rows_a) / len(rows_b) == pytest.approx(105 / 149, abs=0.01)
    assert abs((rows_a[0] + rows_a[-1]) / 2 - (out.shape[0] - 1) / 2) <= 1   # centred
    cols_a = np.flatnonzero((out == 200).all(axis=2).any(axis=0))
    assert len(cols_a) == 40   # its width at the same scale: 80 px at 100 dpi are 40 px at 50 dpi
    with pytest.raises(ValueError, match="pixel_mm"):
        side_by_side([a, b], pixel_mm=[0.1])
    with pytest.raises(ValueError, match="pixel_mm"):
        side_by_side([a, b], pixel_mm=[0.1, 0.0])


def test_join_at_pose_rescales_a_fragment_scanned_at_another_dpi():
    pixel_mm = 25.4 / 300
    pose = _pose_putting_piece_in_frame(33.0, pixel_mm)
    original, img_a, mask_a, img_b, mask_b = _cut(pose, pixel_mm)
    # B scanned at twice the dpi: same physical fragment, twice the pixels, half the pixel size
    img_b2 = cv2.resize(img_b, None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR)
    mask_b2 = cv2.resize(mask_b.astype(np.uint8), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST).astype(bool)
    canvas = join_at_pose(img_a, mask_a, img_b2, mask_b2, pose, pixel_mm, pixel_mm_b=pixel_mm / 2,
                          outline=False, background=MAGENTA, max_side_px=4096, margin_px=5)
    assert _reassembly_error(canvas, original) < 6.0
