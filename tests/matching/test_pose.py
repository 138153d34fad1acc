"""A pair's pose chosen among the docking's candidates by geometry and paint (common/matching/pose.py).

Analytic case: a plaster slab cut straight through with 3 mm of material lost; A is left of the cut,
B right of it, both rectangles as tall as the slab. B fits as well turned over (180°) and against A's
other long side, so the outline alone cannot place it; a red band crossing the cut at a slant
continues from A into B only at the true pose.
"""

import cv2
import numpy as np
import pytest

from common.matching.docking import Docking, dock_outlines, docking_contact_mm
from common.matching.paint import paint_continuity, paint_field
from common.matching.pose import choose_pose, pose_scores

PX_MM = 0.25
PLASTER = (0.74, 0.70, 0.62)
RED = (0.55, 0.12, 0.08)


def _contour_mm(mask):
    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return max(cs, key=len)[:, 0, :].astype(float) * PX_MM


def _case(band=True, gap_mm=3.0, cut_mm=30.0, width_mm=24.0, seed=0):
    """A (the slab left of the cut) and B (``width_mm`` right of it, as tall as A), 60 mm tall: albedo,
    mask and the true pose of B in A's frame (B's image is the slab's region right of the lost
    material). The band runs at 20° to the cut's normal, so it continues only at the true pose."""
    rng = np.random.default_rng(seed)
    h, w = int(60 / PX_MM), int(80 / PX_MM)
    slab = np.empty((h, w, 3), np.float32)
    slab[:] = PLASTER
    slab *= 1 + rng.normal(0, 0.01, (h, w, 1)).astype(np.float32)
    if band:  # 5 mm wide red band through the point (cut, 22 mm) at 20° from the horizontal
        yy, xx = np.mgrid[0:h, 0:w] * PX_MM
        a = np.radians(20.0)
        slab[np.abs(-(xx - cut_mm) * np.sin(a) + (yy - 22.0) * np.cos(a)) < 2.5] = RED
    ca = int(round((cut_mm - gap_mm / 2) / PX_MM))
    cb = int(round((cut_mm + gap_mm / 2) / PX_MM))
    mask_a = np.zeros((h, w), bool)
    mask_a[4:h - 4, 4:ca] = True
    alb_a = np.where(mask_a[..., None], slab, 0).astype(np.float32)
    piece = slab[:, cb:cb + int(width_mm / PX_MM) + 4].copy()
    mask_b = np.zeros(piece.shape[:2], bool)
    mask_b[4:h - 4, :-4] = True
    alb_b = np.where(mask_b[..., None], piece, 0).astype(np.float32)
    return alb_a, mask_a, alb_b, mask_b, (0.0, cb * PX_MM, 0.0)


def _error(pose, truth, centre_b):
    """Angle (deg) and displacement of B's centre (mm) between a pose and the truth."""
    d_angle = abs((pose[0] - truth[0] + 180) % 360 - 180)

    def place(p):
        a = np.radians(p[0])
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ centre_b + p[1:3]

    return d_angle, float(np.hypot(*(place(np.array(pose, float)) - place(np.array(truth, float)))))


def _candidates(band=True):
    alb_a, mask_a, alb_b, mask_b, truth = _case(band=band)
    ca, cb = _contour_mm(mask_a), _contour_mm(mask_b)
    docks = dock_outlines(ca, cb, n_poses=30, per_angle=3)
    poses = np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks])
    paint = paint_continuity(paint_field(alb_a, mask_a, PX_MM), paint_field(alb_b, mask_b, PX_MM), poses)
    errors = np.array([_error(p, truth, cb.mean(axis=0)) for p in poses])
    return docks, paint, errors


@pytest.fixture(scope="module")
def banded():
    return _candidates(band=True)


def test_the_outline_alone_cannot_place_the_short_piece(banded):
    docks, _, errors = banded
    right = (errors[:, 0] <= 5) & (errors[:, 1] <= 5)
    assert right.any(), "the docking's candidates must include the true pose"
    contact = np.array([docking_contact_mm(d) for d in docks])
    # a pose at least 8 mm away scores as well as the true one, to within 10 % (turned over, other side)
    far = errors[:, 1] > 8
    assert contact[far].max() >= 0.9 * contact[right].max()


def test_paint_across_the_crack_picks_the_true_pose(banded):
    docks, paint, errors = banded
    chosen = choose_pose(docks, paint)
    e = errors[docks.index(chosen)]
    assert e[0] <= 5 and e[1] <= 5, f"chosen pose off by {e[0]:.1f} deg, {e[1]:.1f} mm"
    # geometry alone picks a wrong pose here (ties broken by order); the paint is what moved the choice
    geometric = int(np.argmax([d.score for d in docks]))
    assert errors[geometric][1] > 8 and paint[docks.index(chosen)] > paint[geometric] + 5.0


def test_plain_plaster_leaves_the_geometric_choice():
    docks, paint, _ = _candidates(band=False)
    assert np.all(np.abs(paint) < 1.0)        # plaster meeting plaster is no evidence either way
    best = max(docks, key=docking_contact_mm)
    chosen = choose_pose(docks, paint)
    assert docking_contact_mm(chosen) >= docking_contact_mm(best) - 1.0


def test_weight_zero_is_geometry_alone(banded):
    docks, paint, _ = banded
    assert choose_pose(docks, paint, weight=0.0) is docks[int(np.argmax([d.score for d in docks]))]


def test_scores_add_paint_to_contact_in_mm():
    d = [Docking(0.0, 0.0, 0.0, 40.0, 30.0, 0.0), Docking(10.0, 1.0, 2.0, 20.0, 15.0, 0.0)]
    # score in 1.5 mm cells counts both outlines: 40 cells = 30 mm of crack
    np.testing.assert_allclose(pose_scores(d, [1.0, np.nan], weight=2.0), [32.0, 15.0])


@pytest.mark.parametrize("kwargs, message", [
    (dict(dockings=[], paint_mm=[]), "empty"),
    (dict(dockings=[Docking(0, 0, 0, 1, 1, 0)], paint_mm=[1.0, 2.0]), "2 values for 1"),
    (dict(dockings=[Docking(0, 0, 0, 1, 1, 0)], paint_mm=[1.0], weight=-1.0), "weight"),
])
def test_bad_input_is_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        pose_scores(**kwargs)


def _apply(pose, p):
    a = np.radians(pose[0])
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ p + pose[1:]


def test_a_person_turns_b_about_its_centre_and_moves_it_in_as_frame():
    from common.matching.pose import adjusted_pose

    pose, centre = (30.0, 12.0, -4.0), np.array([20.0, 10.0])
    corner = np.array([0.0, 0.0])
    new = adjusted_pose(pose, centre, turn_deg=90.0, shift_mm=(2.0, -3.0))
    # B's centre moved by the shift exactly, and the angle gained the turn
    assert np.allclose(_apply(np.array(new), centre), _apply(np.array(pose), centre) + (2.0, -3.0))
    assert new[0] == pytest.approx(120.0)
    # the rest of B turned a quarter about its centre: the corner's offset from the centre turned by 90°
    before = _apply(np.array(pose), corner) - _apply(np.array(pose), centre)
    after = _apply(np.array(new), corner) - _apply(np.array(new), centre)
    assert np.allclose(after, [[0, -1], [1, 0]] @ before)
    assert adjusted_pose(pose, centre) == pytest.approx(pose)                  # nothing changed
    assert adjusted_pose((170.0, 0, 0), centre, turn_deg=20.0)[0] == pytest.approx(-170.0)   # wrapped


def test_an_adjustment_that_is_not_a_number_is_refused():
    from common.matching.pose import adjusted_pose

    with pytest.raises(ValueError, match="finite"):
        adjusted_pose((0, 0, 0), (1, 1), turn_deg=float("nan"))
    with pytest.raises(ValueError, match="shift_mm"):
        adjusted_pose((0, 0, 0), (1, 1), shift_mm=(1, 2, 3))


def test_ranked_poses_start_with_the_chosen_one_and_skip_near_repeats(banded):
    """The poses a proposal offers: the chosen one first, then the others by score, none within 3° and
    3 mm of a better one; where geometry alone chooses a wrong pose, the true pose is among the
    first ten offered (a person finds it by stepping through)."""
    from common.matching.pose import ranked_poses

    docks, paint, _ = banded
    ranked = ranked_poses(docks, paint)
    assert ranked[0] is choose_pose(docks, paint)
    scores = dict(zip(map(id, docks), pose_scores(docks, paint)))
    assert all(scores[id(a)] >= scores[id(b)] for a, b in zip(ranked, ranked[1:]))
    for i, a in enumerate(ranked):
        for b in ranked[:i]:
            assert abs((a.angle_deg - b.angle_deg + 180) % 360 - 180) > 3 or np.hypot(a.tx_mm - b.tx_mm, a.ty_mm - b.ty_mm) > 3
    errors = banded[2]
    offered = [errors[docks.index(d)] for d in ranked_poses(docks, paint, weight=0.0)[:10]]
    assert not (offered[0][0] <= 5 and offered[0][1] <= 5)          # not the one geometry chooses ...
    assert any(e[0] <= 5 and e[1] <= 5 for e in offered)           # ... but offered beside it


def test_the_adjustment_between_two_poses_is_what_adjusted_pose_undoes():
    from common.matching.pose import adjusted_pose, adjustment_between

    rng = np.random.default_rng(4)
    for _ in range(50):
        pose, other = rng.uniform([-180, -80, -80], [180, 80, 80], (2, 3))
        centre = rng.uniform(-30, 60, 2)
        turn, sx, sy = adjustment_between(pose, other, centre)
        assert -180 < turn <= 180
        got = adjusted_pose(pose, centre, turn_deg=turn, shift_mm=(sx, sy))
        assert abs((got[0] - other[0] + 180) % 360 - 180) < 1e-9 and np.allclose(got[1:], other[1:], atol=1e-9)
    with pytest.raises(ValueError, match="finite"):
        adjustment_between((0, 0, 0), (0, float("nan"), 0), (1, 1))


# ------------------------------------------------------------------------------------------------------------
# the learned chooser (session 13)

@pytest.fixture(scope="module")
def banded_outlines():
    alb_a, mask_a, alb_b, mask_b, _ = _case(band=True)
    return _contour_mm(mask_a), _contour_mm(mask_b)


def test_the_learned_chooser_picks_the_true_pose_of_the_banded_slab(banded, banded_outlines):
    """On the analytic slab (3 mm lost, B fits as well turned over and against A's other side) the station's
    learned chooser — weights fitted on synthetic walls, never on this case — puts the true pose first."""
    from common.matching.pose import learned_pose_scores, pose_features, ranked_poses

    docks, paint, errors = banded
    scores = learned_pose_scores(pose_features(docks, paint, *banded_outlines))
    chosen = choose_pose(docks, paint, scores=scores)
    e = errors[docks.index(chosen)]
    assert e[0] <= 5 and e[1] <= 5, f"learned choice off by {e[0]:.1f} deg, {e[1]:.1f} mm"
    assert ranked_poses(docks, paint, scores=scores)[0] is chosen


def test_pose_features_are_the_contact_the_paint_and_the_facing_geometry(banded, banded_outlines):
    from common.matching.facing import FACING_COLUMNS, facing_geometry
    from common.matching.pose import POSE_FEATURES, POSE_MODEL_RAW, POSE_MODEL_Z, pose_features

    docks, paint, _ = banded
    gappy = np.array(paint, float)
    gappy[0] = np.nan
    f = pose_features(docks, gappy, *banded_outlines)
    assert f.shape == (len(docks), len(POSE_FEATURES)) == (len(docks), 2 + len(FACING_COLUMNS))
    assert len(POSE_MODEL_RAW) == len(POSE_MODEL_Z) == len(POSE_FEATURES)
    np.testing.assert_allclose(f[:, 0], [docking_contact_mm(d) for d in docks])
    assert f[0, 1] == 0 and np.allclose(f[1:, 1], paint[1:])                      # NaN paint: no evidence
    geometry, _, _ = facing_geometry(*banded_outlines, [(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks])
    np.testing.assert_allclose(f[:, 2:], geometry)


def test_learned_scores_rank_within_a_pair_only():
    """A shift of one feature for every candidate of a pair (a bigger piece, a paler plaster) moves all
    its scores together: the order is unchanged; the z part does not see it at all."""
    from common.matching.pose import learned_pose_scores

    rng = np.random.default_rng(1)
    x = rng.normal(size=(30, 14))
    s = learned_pose_scores(x)
    shifted = x + rng.normal(size=14) * 10
    np.testing.assert_array_equal(np.argsort(s), np.argsort(learned_pose_scores(shifted)))
    zero = (np.zeros(14), np.ones(14))
    np.testing.assert_allclose(learned_pose_scores(x, zero), learned_pose_scores(shifted, zero), atol=1e-9)


def test_the_ranker_finds_a_planted_cue_and_is_deterministic():
    """Pairs of 30 candidates with three noise features; the right candidate stands out in the second by
    2σ. Fitted on 60 pairs, the ranker weighs that feature most and picks right on 60 new pairs far above
    the 1/30 of chance; a second fit gives the same weights."""
    from common.matching.pose import fit_pose_ranker, learned_pose_scores

    def pairs(seed, n):
        rng = np.random.default_rng(seed)
        xs, ys = [], []
        for _ in range(n):
            x = rng.normal(size=(30, 3)) * (1.0, 1.0, 1.0) + rng.normal(size=3) * 5   # each pair its own offset
            y = np.zeros(30, bool)
            y[rng.integers(30)] = True
            x[y, 1] += 2.0
            xs.append(x)
            ys.append(y)
        return xs, ys

    xs, ys = pairs(0, 60)
    for kind in ("pairwise", "pointwise"):
        raw, z = fit_pose_ranker(xs, ys, C=1.0, kind=kind)
        assert np.argmax(np.abs(z)) == 1 and z[1] > 0
        tx, ty = pairs(1, 60)
        hit = np.mean([y[np.argmax(learned_pose_scores(x, (raw, z)))] for x, y in zip(tx, ty)])
        assert hit > 0.4, f"{kind}: {hit}"
        raw2, z2 = fit_pose_ranker(xs, ys, C=1.0, kind=kind)
        np.testing.assert_array_equal(raw, raw2)
        np.testing.assert_array_equal(z, z2)
    with pytest.raises(ValueError, match="both a right and a wrong"):
        fit_pose_ranker([np.zeros((3, 2))], [np.zeros(3, bool)])


def test_the_fitting_script_computes_the_stations_features_on_a_tiny_wall():
    """The weights in pose.py come from tests/bench/bench_pose_learned.py: on a tiny synthetic wall its
    cached cues, turned into features, are those the station computes (pose.pose_features of the same
    docking, paint and outlines), and its ranker is pose.fit_pose_ranker."""
    import sys
    from pathlib import Path

    from common.matching.pose import POSE_FEATURES, fit_pose_ranker, pose_features
    from common.synth.wall import generate_wall

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import bench_pose_learned as bench

    wall = generate_wall(5, seed=3, dpi=40, preset="pompeii", colour_only=True)
    pairs, _ = bench.wall_cache(wall, with_lines=False)
    assert pairs
    feats, rights = [], []
    for p in pairs:
        x, names = bench.candidate_features(p)
        cols = [names.index(n) for n in POSE_FEATURES]
        docks = [Docking(*row) for row in p["docks"]]
        want = pose_features(docks, p["paint"], *p["contours"])
        np.testing.assert_allclose(x[:, cols], want, atol=1e-9)
        feats.append(want)
        rights.append(np.arange(len(want)) == 0)        # any labels: the two fits must agree
    r = bench.Ranker("pairwise", C=0.1, columns=cols).fit([bench.candidate_features(p)[0] for p in pairs], rights)
    np.testing.assert_allclose(np.concatenate(r.weights), np.concatenate(fit_pose_ranker(feats, rights, C=0.1)))


def test_the_offer_bench_counts_what_the_station_offers(tmp_path, capsys):
    """bench_pose_learned.py ``cache --more 70`` keeps the station's 30 candidates first (the same search) and the
    70 more after; ``offer`` counts a pair as offered when a right pose is among pose.offered_poses' first 1 + k,
    here checked against the pairs' own labels."""
    import pickle
    import sys
    from pathlib import Path

    from common.matching.pose import offered_poses, pose_features
    from common.synth.wall import generate_wall

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import bench_pose_learned as bench

    wall = generate_wall(5, seed=3, dpi=40, preset="pompeii", colour_only=True)
    pairs, _ = bench.wall_cache(wall, with_lines=False, with_probes=False, more_poses=70)
    plain, _ = bench.wall_cache(wall, with_lines=False, with_probes=False)
    assert len(pairs) == len(plain) > 0
    for p, q in zip(pairs, plain):
        np.testing.assert_array_equal(p["docks"][:30], q["docks"])
        assert len(p["docks"]) > 30
    # label a pair's fifth alternative (of all 100, as offered) right: offered with 9 or 19 alternatives from all
    # 100; among the first 30's proposed pose and 9 alternatives only where it is one of those
    want = []
    for p in pairs:
        docks = [Docking(*row) for row in p["docks"]]
        f = pose_features(docks, p["paint"], *p["contours"])
        target = offered_poses(docks, p["paint"], f, choose_among=30)[5]
        i = docks.index(target)
        p["err"] = np.where((np.arange(len(docks)) == i)[:, None], [[0.0, 0.0]], [[90.0, 90.0]])
        want.append(i < 30 and target in offered_poses(docks[:30], p["paint"], f[:30], choose_among=30)[:10])
    with open(tmp_path / "wall3.pkl", "wb") as fh:
        pickle.dump({"pairs": pairs, "cpu": {}}, fh)
    assert bench.main(["offer", "--cache", str(tmp_path), "--train", "3", "--test", "", "--sizes", "30,100"]) == 0
    out = capsys.readouterr().out
    assert f"offered from the first 100: with 9 alternatives 1.000, with 19 1.000" in out
    assert f"offered from the first  30: with 9 alternatives {np.mean(want):.3f}" in out


def test_offered_poses_keep_the_choice_among_the_first_and_order_the_rest_by_all():
    """offered_poses: the proposed pose is the chooser's best among the first ``choose_among`` (scored among
    them only: a candidate further on cannot take its place however good), the others follow by the scores
    among all, and a near repeat of a better one is left out."""
    from common.matching.pose import offered_poses

    d = [Docking(0, 0, 0, 60.0, 45, 0), Docking(90, 5, 0, 50.0, 37.5, 0), Docking(45, 9, 0, 20.0, 15, 0),
         Docking(46, 10, 0, 19.0, 14, 0), Docking(180, 0, 0, 10.0, 7.5, 0)]
    x = np.array([[1.0], [2.0], [9.0], [8.0], [5.0]])
    w = ([1.0], [0.0])
    got = offered_poses(d, np.zeros(5), x, choose_among=2, weights=w)
    assert [p.angle_deg for p in got] == [90, 45, 180, 0]        # 46° repeats 45° (1°, 1.4 mm): left out
    assert offered_poses(d, np.zeros(5), x, choose_among=5, weights=w)[0].angle_deg == 45
    with pytest.raises(ValueError, match="choose_among"):
        offered_poses(d, np.zeros(5), x[:3], choose_among=2, weights=w)


def test_the_margin_bench_counts_hits_per_query():
    """bench_pose_margin.hits: each fragment of a pair is a query; @1 / @3 over the queries with a true neighbour."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import bench_pose_margin as bench

    pairs = [dict(src="w", a="A", b="B", true=True), dict(src="w", a="A", b="C", true=False),
             dict(src="w", a="A", b="D", true=False), dict(src="w", a="A", b="E", true=False),
             dict(src="w", a="B", b="C", true=False)]
    # A: B scored 3rd of 4 -> miss @1, hit @3; B: A beats C -> hit; C, D, E have no neighbour (not counted)
    at1, at3, n = bench.hits(pairs, [1.0, 3.0, 2.0, 0.0, 0.5])
    assert (at1, at3, n) == (0.5, 1.0, 2)


def test_a_wall_seen_at_a_dpi_too_low_is_the_same_wall_with_every_length_longer():
    """bench_pose_learned.py ``cache --scale S`` (a station told 150 dpi for RePAIR's 187.2): the fragments' outlines
    come out S times longer, the true poses' translations S times, the angles unchanged, so the true relative pose of
    every neighbour pair is the same pose with its translation scaled (each fragment's frame is its image's pixel
    grid × the pixel size, which grows S times)."""
    import sys
    from pathlib import Path

    from scipy.spatial import cKDTree

    from common.matching.online import wall_cues
    from common.synth.wall import generate_wall

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import bench_pose_learned as bench

    wall = generate_wall(4, seed=3, dpi=40, preset="pompeii", colour_only=True)
    seen = bench.wall_seen_at(wall, 1.25)
    t1, _, p1 = wall_cues(wall)
    t2, _, p2 = wall_cues(seen)
    for f in t1:   # the same outline, 1.25 times longer, up to the features' 0.1 mm working grid
        longer, seen_outline = 1.25 * t1[f].contour_mm, t2[f].contour_mm
        assert cKDTree(longer).query(seen_outline)[0].max() < 0.25
        assert cKDTree(seen_outline).query(longer)[0].max() < 0.25
        if p1[f] is not None:
            assert p2[f][0] == p1[f][0] and np.allclose(p2[f][1:], 1.25 * np.asarray(p1[f][1:]))
    assert [(a, b) for a, b, _ in seen.adjacency] == [(a, b) for a, b, _ in wall.adjacency]
    assert np.allclose([n for *_, n in seen.adjacency], [1.25 * n for *_, n in wall.adjacency])
    assert seen.dpi == wall.dpi / 1.25 and wall.fragments[0].rgbn.dpi == 40      # the original is left alone
