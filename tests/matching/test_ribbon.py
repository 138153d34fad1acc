"""The colour ribbon: two pieces of one painted slab match along their shared crack."""

import numpy as np
import pytest

from common.features.boundary import boundary_channel_names, boundary_profile
from common.features.contour import fragment_contour
from common.matching.ribbon import (fit_ribbon_calibration, pair_ribbon_scores, prepare_ribbon, ribbon_population,
                                    ribbon_probability, ribbon_rankings, ribbon_scores, sample_rarity)

PX = 0.2           # mm per pixel
W, H = 300, 200    # a 60 × 40 mm slab
NAMES = boundary_channel_names()


def _painting(seed):
    """Oblique stripes 3–8 mm wide in random colours (so they cross the crack and the slab's
    edges alike), and a plaster thickness varying along x."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:H, :W] * PX
    u = xx * np.cos(np.radians(30)) + yy * np.sin(np.radians(30))     # across the stripes, mm
    edges = np.cumsum(rng.uniform(3, 8, 40))
    palette = rng.uniform(0.1, 0.9, (len(edges) + 1, 3)).astype(np.float32)
    albedo = palette[np.searchsorted(edges, u)]
    thickness = (15 + 3 * np.sin(xx / 9 + seed)).astype(np.float32)
    return albedo, thickness


def _cut(seed):
    """Row of a jagged crack across the slab for each column (a random walk around the middle)."""
    rng = np.random.default_rng(100 + seed)
    return np.clip(H / 2 + np.cumsum(rng.normal(0, 1.2, W)), 60, 140)


def _piece(albedo, thickness, cut, upper, fade=0.0):
    rows = np.arange(H)[:, None]
    mask = rows < cut[None, :] - 1 if upper else rows > cut[None, :] + 1   # a thin gap: erosion
    mask[:2], mask[-2:], mask[:, :2], mask[:, -2:] = False, False, False, False
    a = albedo * (1 - fade) + fade * np.array([0.78, 0.75, 0.68], np.float32)
    contour = fragment_contour(mask, PX)
    prof, step = boundary_profile(contour, a, PX, weight=mask.astype(float), thickness_mm=thickness)
    return prof, contour


def _ribbon(prof, **kw):
    return prepare_ribbon(prof, NAMES, step_mm=1.0, **kw)


def _decoys(n=6):
    out = []
    for s in range(1, n + 1):
        albedo, thickness = _painting(s)
        out.append(_ribbon(_piece(albedo, thickness, _cut(s), upper=False)[0]))
    return out


def test_the_true_partner_ranks_first_and_the_best_run_lies_on_the_crack():
    albedo, thickness = _painting(0)
    cut = _cut(0)
    a, ca = _piece(albedo, thickness, cut, upper=True)
    b, cb = _piece(albedo, thickness, cut, upper=False)
    s, arc_a, arc_b = ribbon_scores(_ribbon(a), [_ribbon(b)] + _decoys())
    assert np.argmax(s) == 0 and s[0] > np.sort(s)[-2] + 0.02, s
    # both pieces are in the slab's frame: the run's middle points lie on the crack and face each other
    pa, _ = ca.at(arc_a[0] + 10)
    pb, _ = cb.at(arc_b[0] - 10)
    col = int(round(pa[0] / PX))
    assert abs(pa[1] / PX - cut[col]) * PX < 1.5
    assert np.hypot(*(pa - pb)) < 6.0   # within the tolerance (3 mm) plus a 2 mm step


def test_a_faded_partner_still_ranks_first():
    albedo, thickness = _painting(0)
    cut = _cut(0)
    a, _ = _piece(albedo, thickness, cut, upper=True)
    b, _ = _piece(albedo, thickness, cut, upper=False, fade=0.5)
    s, _, _ = ribbon_scores(_ribbon(a), [_ribbon(b)] + _decoys())
    assert np.argmax(s) == 0, s
    # thickness is used only where both have it: a colour-only partner still ranks first
    b[:, [NAMES.index(n) for n in NAMES if n.startswith("thickness@")]] = np.nan
    s, _, _ = ribbon_scores(_ribbon(a), [_ribbon(b)] + _decoys())
    assert np.argmax(s) == 0, s


def test_score_does_not_depend_on_where_a_contour_starts():
    albedo, thickness = _painting(0)
    cut = _cut(0)
    a, _ = _piece(albedo, thickness, cut, upper=True)
    b, _ = _piece(albedo, thickness, cut, upper=False)
    b = b[:len(b) // 2 * 2]       # whole pairs of 1 mm samples: a roll by 16 keeps the 2 mm averages
    s, arc_a, arc_b = ribbon_scores(_ribbon(a), [_ribbon(b), _ribbon(np.roll(b, 16, axis=0))])
    assert s[0] == pytest.approx(s[1], abs=1e-6)
    assert (arc_b[1] - arc_b[0]) % len(b) == pytest.approx(16.0) and arc_a[0] == arc_a[1]


def test_pair_scores_cover_every_pair_once_and_short_profiles_score_nan():
    albedo, thickness = _painting(0)
    cut = _cut(0)
    a, _ = _piece(albedo, thickness, cut, upper=True)
    b, _ = _piece(albedo, thickness, cut, upper=False)
    c, _ = _piece(*_painting(1), _cut(1), upper=False)
    scores = pair_ribbon_scores({"a": a, "b": b, "c": c}, NAMES)
    assert set(scores) == {("a", "b"), ("a", "c"), ("b", "c")}
    assert max(scores, key=scores.get) == ("a", "b")
    s, _, _ = ribbon_scores(_ribbon(a), [_ribbon(b[:2])])
    assert np.isnan(s[0])


def test_each_fragment_ranks_the_others_from_its_own_side():
    albedo, thickness = _painting(0)
    cut = _cut(0)
    a, _ = _piece(albedo, thickness, cut, upper=True)
    b, _ = _piece(albedo, thickness, cut, upper=False)
    profiles = {"a": a, "b": b, "c": _piece(*_painting(1), _cut(1), upper=False)[0],
                "d": _piece(*_painting(2), _cut(2), upper=True)[0], "short": b[:2]}
    lists = ribbon_rankings(profiles, NAMES)
    assert set(lists) == {"a", "b", "c", "d"} and lists["a"][0] == "b" and lists["b"][0] == "a"
    # the definition: each list is its fragment's own ribbon scores, best first, with its own rarity
    prepared = {f: _ribbon(p) for f, p in profiles.items() if f != "short"}
    population = ribbon_population(prepared)
    for f, ranked in lists.items():
        others = [o for o in prepared if o != f]
        s, _, _ = ribbon_scores(prepared[f], [prepared[o] for o in others],
                                rarity=sample_rarity(prepared[f], population, fragment=f))
        assert ranked == [others[i] for i in np.argsort(-s, kind="stable")]


def test_calibration_recovers_a_known_logistic_relation():
    rng = np.random.default_rng(0)
    s = rng.normal(0, 1, 20000)
    y = rng.random(20000) < 1 / (1 + np.exp(-(3.0 * s - 2.0)))
    slope, intercept = fit_ribbon_calibration(s, y)
    assert slope == pytest.approx(3.0, abs=0.25) and intercept == pytest.approx(-2.0, abs=0.15)
    p = ribbon_probability([-10.0, 0.0, 10.0], (slope, intercept))
    assert p[0] < 1e-6 and p[2] > 1 - 1e-6 and 0.05 < p[1] < 0.25
    with pytest.raises(ValueError, match="both"):
        fit_ribbon_calibration(s, np.zeros(len(s), bool))


def test_ribbon_profiles_without_colour_channels_or_of_the_wrong_width_are_refused():
    a = np.zeros((30, len(NAMES)), np.float32)
    with pytest.raises(ValueError, match="sqrt_"):
        prepare_ribbon(a[:, :2], ["thickness@0.8", "thickness@1.6"])
    with pytest.raises(ValueError, match="profile must be"):
        prepare_ribbon(a[:, :5], NAMES)
    with pytest.raises(ValueError, match="step_mm"):
        prepare_ribbon(a, NAMES, step_mm=0)
    with pytest.raises(ValueError, match="windows_mm"):
        ribbon_scores(_ribbon(a), [_ribbon(a)], windows_mm=(20.0, 0.0))
    with pytest.raises(ValueError, match="windows_mm"):
        ribbon_scores(_ribbon(a), [_ribbon(a)], windows_mm=())


def _flat_profile(colours):
    """A profile whose √albedo and standardised channels both hold ``colours`` (K, 3) at both
    depths, without thickness."""
    c = np.asarray(colours, np.float32)
    p = np.full((len(c), len(NAMES)), np.nan, np.float32)
    for k, name in enumerate(NAMES):
        if not name.startswith("thickness@"):
            p[:, k] = c[:, "rgb".index(name.split("_")[1][0])]
    return _ribbon(p)


def test_rarity_is_low_for_common_colours_and_ignores_the_fragments_own_samples():
    from common.matching.ribbon import ribbon_population, sample_rarity

    grey, red = np.full((40, 3), 0.6), np.tile([0.9, 0.2, 0.2], (40, 1))
    profiles = {f"g{i}": _flat_profile(grey) for i in range(5)} | {"red": _flat_profile(red)}
    pop = ribbon_population(profiles)
    assert np.allclose(sample_rarity(profiles["g0"], pop, fragment="g0"), 0.0, atol=1e-6)
    # the red fragment's own samples do not count: its nearest others are grey, |Δ| over 6 channels
    expected = np.sqrt(2 * ((0.9 - 0.6) ** 2 + 2 * (0.2 - 0.6) ** 2))
    np.testing.assert_allclose(sample_rarity(profiles["red"], pop, fragment="red"), expected, rtol=1e-4)
    assert np.allclose(sample_rarity(profiles["red"], pop), 0.0, atol=1e-6)


def test_rarity_lets_a_match_of_unusual_colours_beat_a_match_of_a_plain_field():
    """Query A: half of its boundary plain grey (a field many fragments share), half painted bands.
    C is plain grey and fits A's grey half exactly; B is the true partner, whose bands face A's
    with a little noise. Without the rarity correction C wins, with it B."""
    from common.matching.ribbon import ribbon_population, sample_rarity

    rng = np.random.default_rng(0)
    bands = np.repeat(rng.uniform(0.1, 0.9, (8, 3)), 6, axis=0)            # 48 samples, 6 mm bands
    a = np.vstack([np.full((48, 3), 0.6), bands])
    b = np.vstack([bands[::-1] + rng.normal(0, 0.02, bands.shape), np.tile([0.2, 0.5, 0.3], (48, 1))])
    c = np.full((96, 3), 0.6) + rng.normal(0, 0.002, (96, 3))
    profiles = {"a": _flat_profile(a), "b": _flat_profile(b), "c": _flat_profile(c)}
    profiles |= {f"g{i}": _flat_profile(np.full((60, 3), 0.6) + rng.normal(0, 0.01, (60, 3))) for i in range(8)}
    others = [profiles["b"], profiles["c"]]
    plain, _, _ = ribbon_scores(profiles["a"], others)
    assert plain[1] > plain[0], plain
    rarity = sample_rarity(profiles["a"], ribbon_population(profiles), fragment="a")
    assert rarity[30:].mean() > 5 * rarity[:20].mean()                     # bands rare, grey common
    corrected, _, _ = ribbon_scores(profiles["a"], others, rarity=rarity)
    assert corrected[0] > corrected[1], corrected


def _ribbon_by_definition(a, b, window_mm, tolerance_mm, offset):
    """The module docstring's score written out directly: D of every sample pair (B run backwards,
    both closed), its minimum over ±tolerance along either profile, the best mean over a run."""
    flag = a.has_thickness and b.has_thickness
    d2 = np.minimum(*[a.rows[(k, flag)][0] @ b.rows[(k, flag)][1].T for k in ("sqrt", "std")])
    d = np.sqrt(np.maximum(d2, 0.0))[:, ::-1] - offset[:, None]        # column j: B sample nb-1-j
    tol, win = round(tolerance_mm / a.step_mm), min(round(window_mm / a.step_mm), len(a))
    along_a = np.min([np.roll(d, s, axis=0) for s in range(-tol, tol + 1)], axis=0)
    along_b = np.min([np.roll(d, s, axis=1) for s in range(-tol, tol + 1)], axis=0)
    t = np.minimum(along_a, along_b)
    runs = sum(np.roll(np.roll(t, -s, axis=0), -s, axis=1) for s in range(win)) / win   # run from (i, j)
    return -runs.min(), runs


@pytest.mark.parametrize("block_cells", [1 << 17, 1])   # all candidates in one block, or one each
@pytest.mark.parametrize("windows_mm, tolerance_mm", [((20.0,), 3.0), ((4.0,), 2.0), ((500.0,), 0.0),
                                                      ((20.0, 40.0, 80.0), 3.0), ((80.0, 6.0), 1.0),
                                                      ((4.0, 500.0), 2.0),
                                                      ((20.0, 500.0, 600.0), 2.0)])   # two capped to one length
def test_scores_and_best_runs_equal_the_definition(windows_mm, tolerance_mm, block_cells, monkeypatch):
    """The score is the mean over the run lengths of each length's best run, each found on its own (a longer
    length at most a third of A's outline); the reported run is the shortest length's best."""
    import common.matching.ribbon as ribbon

    monkeypatch.setattr(ribbon, "RIBBON_BLOCK_CELLS", block_cells)
    a = _decoys(1)[0]
    others = _decoys(4)[1:] + [_ribbon(_piece(*_painting(9), _cut(9), upper=True)[0])]
    offset = np.random.default_rng(0).uniform(0, 0.05, len(a))
    score, arc_a, arc_b = ribbon_scores(a, others, rarity=offset, rarity_weight=1.0,
                                        windows_mm=windows_mm, tolerance_mm=tolerance_mm)
    # the longer lengths are cut to a third of A's outline, never below the shortest length
    shortest, *longer = sorted(windows_mm)
    first = min(round(shortest / a.step_mm), len(a))
    lengths = [shortest] + [min(round(w / a.step_mm), len(a), max(first, len(a) // 3)) * a.step_mm for w in longer]
    for b, s, i0, j_arc in zip(others, score, arc_a, arc_b):
        by_length = [_ribbon_by_definition(a, b, w, tolerance_mm, offset) for w in lengths]
        assert s == pytest.approx(np.mean([best for best, _ in by_length]), abs=1e-6)
        # the reported run (A forwards from arc_a, B backwards from arc_b) is a best one of the shortest length
        best, runs = by_length[0]
        i, j = int(round(i0 / a.step_mm)), len(b) - 1 - int(round(j_arc / b.step_mm))
        assert -runs[i, j] == pytest.approx(best, abs=1e-6)


@pytest.mark.parametrize("k", [1, 10, 40])
def test_rarity_equals_its_definition_by_brute_force(k):
    """sample_rarity finds neighbours with two KD-trees; the docstring's definition, written out:
    every population sample not of A, its distance the smaller of the two colour kinds', the mean of
    the k nearest."""
    from common.matching.ribbon import ribbon_population, sample_rarity

    rng = np.random.default_rng(3)

    def two_kinds(n):   # √albedo and standardised channels unrelated, so the smaller distance switches kind
        prof = np.full((n, len(NAMES)), np.nan, np.float32)
        for c, name in enumerate(NAMES):
            if not name.startswith("thickness@"):
                prof[:, c] = rng.uniform(0.1, 0.9, n)   # each channel drawn on its own
        return _ribbon(prof)

    profiles = {f"f{i}": two_kinds(int(rng.integers(20, 60))) for i in range(12)}
    pop = ribbon_population(profiles, max_samples=300, seed=1)
    for fid in ("f0", "f5"):
        a = profiles[fid]
        got = sample_rarity(a, pop, fragment=fid, k=k)
        d = np.min([np.linalg.norm(a.rows[(kind, False)][0][:, None, :-2]
                                   + 0.5 * pop.rows[(kind, False)][None, :, :-2], axis=2) for kind in ("sqrt", "std")],
                   axis=0)
        d = d[:, pop.owner[False] != fid]
        np.testing.assert_allclose(got, np.sort(d, axis=1)[:, :k].mean(axis=1), rtol=1e-9, atol=1e-12)
