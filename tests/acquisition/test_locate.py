"""Tests of fragment localisation on the pre-scan (common/acquisition/locate.py)."""

import re

import cv2
import numpy as np
import pytest

from common.acquisition.errors import MultipleFragmentsError, NoFragmentError
from common.acquisition.flatbed_normals import solve_face
from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface
from common.acquisition.locate import fragment_mask, locate_fragment, locate_fragments
from common.acquisition.surface import FragmentSurface


def _bed(seed=4):
    return SimulatedFlatbed(bed_mm=(120, 120), seed=seed, dust=60)


def test_locates_the_fragment_region_around_its_true_footprint():
    sim = _bed()
    sim.place(demo_surface(30, 100, seed=3), centre_mm=(70, 45))
    area = locate_fragment(sim.scan(None, 50), 50, margin_mm=5.0)
    truth = sim.truth(None, 50)
    rows, cols = np.nonzero(truth.mask)
    p = 25.4 / 50
    x0, x1, y0, y1 = cols.min() * p, (cols.max() + 1) * p, rows.min() * p, (rows.max() + 1) * p
    assert area[0] <= x0 and area[1] <= y0 and area[2] >= x1 and area[3] >= y1       # contains it
    assert area[0] > x0 - 8 and area[1] > y0 - 8 and area[2] < x1 + 8 and area[3] < y1 + 8   # tightly


def test_dust_and_bed_texture_alone_are_no_fragment():
    sim = _bed()
    with pytest.raises(NoFragmentError) as err:
        locate_fragment(sim.scan(None, 50), 50)
    assert "No fragment" in err.value.operator_message


def test_a_fragment_split_by_dark_paint_is_one_object():
    sim = _bed()
    s = demo_surface(30, 100, seed=3)
    s.albedo[:, 55:62] = 0.04                  # a black band across, as dark as the lid
    sim.place(s, centre_mm=(60, 60), angle_deg=0)
    blobs = locate_fragments(sim.scan(None, 50), 50)
    assert len(blobs) == 1 and blobs[0].bbox_mm[2] - blobs[0].bbox_mm[0] > 20


def test_two_fragments_are_refused_naming_both():
    sim = _bed()
    sim.place(demo_surface(25, 100, seed=1), centre_mm=(35, 35))
    sim.add(demo_surface(25, 100, seed=2), centre_mm=(85, 85))
    with pytest.raises(MultipleFragmentsError) as err:
        locate_fragment(sim.scan(None, 50), 50)
    assert "2 objects" in err.value.operator_message
    xs = sorted(int(v) for v in re.findall(r"x=(\d+) mm", str(err.value)))
    assert len(xs) == 2 and abs(xs[0] - 35) <= 3 and abs(xs[1] - 85) <= 3


def test_empty_bed_reference_background_also_works():
    sim = _bed()
    empty = sim.scan(None, 50)
    sim.place(demo_surface(20, 100, seed=5), centre_mm=(60, 60))
    blobs = locate_fragments(sim.scan(None, 50), 50, background=empty)
    rows, cols = np.nonzero(sim.truth(None, 50).mask)
    true_centroid = ((cols.mean() + 0.5) * 25.4 / 50, (rows.mean() + 0.5) * 25.4 / 50)
    assert len(blobs) == 1
    # (the lamp's shadow below the fragment may pull the centroid by a millimetre or two)
    assert np.hypot(blobs[0].centroid_mm[0] - true_centroid[0], blobs[0].centroid_mm[1] - true_centroid[1]) < 3.0
    p = 25.4 / 50
    x0, y0, x1, y1 = blobs[0].bbox_mm
    assert x0 <= cols.min() * p + p and y0 <= rows.min() * p + p and x1 >= cols.max() * p and y1 >= rows.max() * p


def test_fragment_mask_of_a_region_scan_excludes_the_lamp_shadow():
    sim = _bed()
    sim.place(demo_surface(25, 150, seed=6), centre_mm=(60, 60))
    area = (42, 42, 78, 78)
    m = fragment_mask(sim.scan(area, 150), 150)
    t = sim.truth(area, 150).mask
    iou = (m & t).sum() / (m | t).sum()
    assert iou > 0.97


def test_real_coin_is_found_in_each_raw_platen_scan(shared_data):
    for rot in (0, 90, 180, 270):
        raw = cv2.imread(str(shared_data / "flatbed-coin" / f"raw_{rot}.png"))[..., ::-1]
        # 826 × 1169 px of a letter-size platen: 100 dpi; the bed is framed, so the estimated
        # background must be local (a 30 mm window, fine for a 24 mm coin)
        x0, y0, x1, y1 = locate_fragment(raw, 100, margin_mm=0.0, background_mm=30.0)
        cx, cy = (x0 + x1) / 2 / 25.4 * 100, (y0 + y1) / 2 / 25.4 * 100
        # the coin lies near (400, 450) px in all four, inside the grey field
        assert 330 < cx < 480 and 380 < cy < 520, (rot, cx, cy)
        assert 15 < x1 - x0 < 40 and 15 < y1 - y0 < 40           # a coin of about 24 mm


# Outline (mm) of soak fragment s1n600-f880af-045 (generate_wall(600, seed=1)): about 9 × 9 mm,
# 41 mm², standing 20.5 mm tall. Its lamp shadow along a long edge was kept as fragment in one
# rotation (mask 20-40 % larger), so registration refused the face.
_SMALL_OUTLINE_MM = [(1.5, 2.8), (2.5, 5.3), (2.8, 7.4), (4.6, 9.7), (5.1, 11.2), (7.1, 9.4), (10.7, 8.1),
                     (9.7, 7.4), (7.6, 4.6), (4.6, 3.8), (2.8, 2.3), (2.0, 2.3)]
# the soak's four placements (angle °, centre mm) that put the shadow along a long edge in the last
_SMALL_POSES = [(43.8, (36.5, 47.6)), (131.9, (35.9, 51.2)), (222.8, (32.6, 54.5)), (307.5, (36.0, 57.1))]


@pytest.fixture(scope="module")
def small_thick_fragment_scans():
    """Four rotations of a small, thick ochre fragment at 100 dpi, captured as the station does
    (pre-scan at 25 dpi, region = located fragment + 5 mm), with the ground-truth masks."""
    dpi = 100
    p = 25.4 / dpi
    n = int(np.ceil(13 / p))
    mask = np.zeros((n, n), np.uint8)
    cv2.fillPoly(mask, [np.round(np.array(_SMALL_OUTLINE_MM) / p).astype(np.int32)], 1)
    albedo = np.empty((n, n, 3), np.float32)
    albedo[:] = (0.63, 0.46, 0.17)
    height = cv2.GaussianBlur((0.04 * np.random.default_rng(0).standard_normal((n, n))).astype(np.float32), (0, 0), 1.0)
    surface = FragmentSurface(albedo, height, mask.astype(bool), dpi, thickness_mm=20.5)
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=20)
    scans, truths = [], []
    for angle, centre in _SMALL_POSES:
        sim.place(surface, angle_deg=angle, centre_mm=centre)
        area = locate_fragment(sim.scan(None, 25), 25, margin_mm=5.0)
        scans.append(sim.scan(area, dpi))
        truths.append(sim.truth(area, dpi).mask)
    return scans, truths, dpi


def test_small_thick_fragment_masks_leave_out_the_lamp_shadow_in_every_rotation(small_thick_fragment_scans):
    scans, truths, dpi = small_thick_fragment_scans
    areas = []
    for scan, truth in zip(scans, truths):
        m = fragment_mask(scan, dpi)
        # (at 100 dpi the outline is uncertain by about a pixel: 1 px all round is ~15 % of 41 mm²)
        assert (m & truth).sum() / (m | truth).sum() > 0.8
        assert (m & ~cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)).sum() < 10
        areas.append(int(m.sum()))
    assert max(areas) / min(areas) < 1.06, areas


def test_small_thick_fragment_with_a_shadow_along_its_edge_is_registered_and_solved(small_thick_fragment_scans):
    scans, truths, dpi = small_thick_fragment_scans
    a = np.array([0.0, 0.33, 0.54, 0.21])        # a typical simulated-flatbed calibration
    out, regs = solve_face(scans, dpi, a, nominal_deg=[0, 90, 180, 270])
    for reg, (angle, _) in zip(regs[1:], _SMALL_POSES[1:]):
        assert (reg.angle_deg - (angle - _SMALL_POSES[0][0]) + 180) % 360 - 180 == pytest.approx(0, abs=1.0)
    assert (out.mask & truths[0]).sum() / (out.mask | truths[0]).sum() > 0.8


def _region_scan(shape=(80, 80), lid=0.04):
    """A 100-dpi region scan: dark lid with sensor noise, an ochre fragment body (rows 25-55, cols 15-45)."""
    img = np.full(shape + (3,), lid, np.float32)
    img[25:55, 15:45] = (0.45, 0.33, 0.12)
    return img


def _as_scan(img, rng):
    return np.clip((img + rng.normal(0, 0.001, img.shape)) * 65535, 0, 65535).astype(np.uint16)


def test_a_small_fragments_tip_beyond_a_black_band_is_not_dust():
    rng = np.random.default_rng(1)
    img = _region_scan()
    # a tip of dark green paint (4 × 3 px, 0.8 mm²; about 30 px in the blurred difference, under the
    # 2 mm² = 31 px dust limit) beyond 5 px of black paint as dark as the lid: soak fragment -080
    img[35:39, 50:53] = (0.05, 0.12, 0.05)
    m = fragment_mask(_as_scan(img, rng), 100)
    assert m[35:39, 50:53].all() and m[35:39, 45:50].all()
    assert not m[:20].any() and not m[60:].any()


def test_lid_texture_reaching_the_region_edge_is_not_fragment():
    rng = np.random.default_rng(2)
    img = _region_scan()
    img[0:14, 25:60] = 0.09                     # a brighter patch of lid, neutral and smooth, at the edge
    m = fragment_mask(_as_scan(img, rng), 100)
    assert not m[:18].any()
    assert m[27:53, 17:43].all()


def _ribbed_bar(length_mm, width_mm, dpi=25):
    """A dark ribbed bar of a frame or jig (like the bars around the real coin scans)."""
    h, w = int(width_mm / 25.4 * dpi), int(length_mm / 25.4 * dpi)
    rows = np.arange(h)[:, None] * np.ones((1, w))
    height = (0.6 * np.sin(2 * np.pi * rows * 25.4 / dpi / 3.0)).astype(np.float32)
    albedo = np.full((h, w, 3), 0.04, np.float32) * (1 + 0.3 * np.sin(rows * 1.3))[..., None].astype(np.float32)
    return FragmentSurface(albedo=albedo, height_mm=height, mask=np.ones((h, w), bool), dpi=dpi, thickness_mm=6.0)


def test_a_fragment_turned_inside_a_frame_of_bars_is_found_by_what_changes_between_scans():
    from common.acquisition.locate import locate_changing
    sim = SimulatedFlatbed(bed_mm=(160, 200), seed=3, dust=0)
    sim.place(demo_surface(25, 50, seed=5), angle_deg=10, centre_mm=(80, 100))
    for centre, angle, size in [((80, 25), 0, (140, 25)), ((80, 175), 0, (140, 25)),
                                ((15, 100), 90, (190, 18)), ((145, 100), 90, (190, 18))]:
        sim.add(_ribbed_bar(*size), angle_deg=angle, centre_mm=centre)
    scans = []
    for k in range(4):
        if k:
            sim._items[0].angle_deg += 90 + 5 * k          # the operator turns the fragment, not the frame
        scans.append(sim.scan(None, 50))
    # what changes between the scans is the fragment, wherever the frame is
    x0, y0, x1, y1 = locate_changing(scans, 50)
    assert x0 < 80 - 12 and x1 > 80 + 12 and y0 < 100 - 12 and y1 > 100 + 12       # the whole fragment ...
    assert x1 - x0 < 60 and y1 - y0 < 60                                          # ... and not the frame


def test_nothing_changing_between_scans_is_said():
    from common.acquisition.locate import locate_changing
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=3, dust=0)
    sim.place(demo_surface(25, 50, seed=5), centre_mm=(50, 50))
    scans = [sim.scan(None, 50) for _ in range(2)]
    with pytest.raises(NoFragmentError, match="turned"):
        locate_changing(scans, 50)
