"""Tests of fragment localisation on the pre-scan (common/acquisition/locate.py)."""

import re

import cv2
import numpy as np
import pytest

from common.acquisition.errors import MultipleFragmentsError, NoFragmentError
from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface
from common.acquisition.locate import fragment_mask, locate_fragment, locate_fragments


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
