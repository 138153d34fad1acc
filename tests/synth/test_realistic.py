import numpy as np
import pytest

from common.synth import generate_wall
from common.synth.realistic import (MaterialLoss, fragment_rgba, lose_material, paint_plaster, plaster_palette,
                                    round_outline, write_collection)
from common.synth.stats import neighbour_gaps, piece_statistics, read_collection, wall_collection

PM = 0.25  # mm per pixel of the analytic grids


def _halves(width=100, height=800):
    """Two pieces split by the vertical line col = width / 2: labels 0 (left) and 1 (right)."""
    labels = np.zeros((height, width), np.int32)
    labels[:, width // 2:] = 1
    G = np.array([[PM, 0.0, 0.0], [0.0, PM, 0.0]])
    return labels, G


def test_constant_loss_opens_a_gap_of_its_scale_split_between_both_sides():
    labels, G = _halves()
    loss = MaterialLoss(seed=3, median_mm=2.0, sigma=0.0, spread=0.0, touch_fraction=0.0)
    s, d = loss.crack(0, 1)
    assert s == pytest.approx(2.0) and d == 0.0
    left = lose_material(labels == 0, labels, 0, G, loss)
    right = lose_material(labels == 1, labels, 1, G, loss)
    rows = slice(40, 760)  # away from the top and bottom, where the wall edge is lost too
    last_left = np.array([np.nonzero(r)[0].max() for r in left[rows]])
    first_right = np.array([np.nonzero(r)[0].min() for r in right[rows]])
    gap_mm = (first_right - last_left - 1) * PM
    # the gap is the crack's scale (each side a share between 10 % and 90 % of it), to a pixel
    assert np.all(np.abs(gap_mm - 2.0) <= 2 * PM)
    lost_left = (50 - 1 - last_left) * PM
    assert lost_left.min() >= 0.1 * 2.0 - 2 * PM and lost_left.max() <= 0.9 * 2.0 + 2 * PM
    assert lost_left.std() > 0.05  # uneven along the crack


def test_touching_cracks_close_somewhere_and_others_do_not():
    loss = MaterialLoss(seed=1, touch_fraction=0.5)
    offsets = [loss.crack(a, a + 1)[1] for a in range(400)]
    share = np.mean(np.array(offsets) > 0)
    assert 0.4 < share < 0.6
    assert loss.crack(5, 9) == loss.crack(9, 5)  # one crack, one gap, seen from either side


def test_round_outline_softens_a_square_corner_but_keeps_straight_edges():
    m = np.zeros((100, 100), bool)
    m[20:80, 20:80] = True
    r = round_outline(m, 4.0)
    assert not r[20, 20] and r[50, 20] and r[20, 50]
    assert r.sum() > 0.98 * m.sum() - 4 * 4 * 4


def test_plaster_palette_is_shared_by_seed_and_paint_is_mostly_plain():
    assert plaster_palette(4)["paints"].keys() == plaster_palette(4)["paints"].keys()
    a, b = plaster_palette(4), plaster_palette(4)
    for k in a["paints"]:
        np.testing.assert_array_equal(a["paints"][k], b["paints"][k])
    p = paint_plaster(400, 300, np.random.default_rng(2), palette=a, res_mm=0.5)
    rgb = p.albedo
    # mostly plain: low saturation almost everywhere
    sat = (rgb.max(axis=2) - rgb.min(axis=2)) / np.maximum(rgb.max(axis=2), 1e-6)
    assert np.mean(sat < 0.12) > 0.6


def test_pompeii_wall_is_colour_only_with_big_pieces_and_gapped_neighbours():
    wall = generate_wall(12, seed=5, dpi=40, preset="pompeii", colour_only=True)
    assert len(wall.fragments) == 12
    assert all(f.rgbn.normals is None and f.surface is None for f in wall.fragments)
    sizes = np.sqrt([f.area_mm2 for f in wall.fragments])
    assert np.median(sizes) > 40 and sizes.max() < 200
    assert len(wall.adjacency) >= 5 and min(s for _, _, s in wall.adjacency) >= 10.0
    pairs = neighbour_gaps(wall_collection(wall), near_px=48 * 40 / 187, min_run_px=100 * 40 / 187)
    gaps_mm = np.array([p["median_gap_px"] for p in pairs]) * 25.4 / 40
    assert len(pairs) >= 3 and np.median(gaps_mm) > 1.0  # material lost along the cracks
    # correspondences exist for every pair, despite the gaps
    assert all(len(wall.correspondences[(a, b)][0]) > 0 for a, b, _ in wall.adjacency)


def test_same_palette_seed_shares_colours_across_walls():
    a = generate_wall(4, seed=1, dpi=20, preset="pompeii", colour_only=True, palette_seed=9)
    b = generate_wall(4, seed=2, dpi=20, preset="pompeii", colour_only=True, palette_seed=9)
    assert a.id != b.id and a.params["palette_seed"] == b.params["palette_seed"] == 9


def test_unknown_preset_or_argument_is_refused():
    with pytest.raises(ValueError, match="preset"):
        generate_wall(4, seed=1, preset="knossos")
    with pytest.raises(ValueError, match="unknown argument"):
        generate_wall(4, seed=1, preset="pompeii", round_m=1.0)
