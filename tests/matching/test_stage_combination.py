"""Stage 3's learned combination of the stage scores, and the stage-by-stage trace of the ranking."""

from dataclasses import replace

import numpy as np
import pytest

from common.matching.evaluation import StageTrace, stage_recall, trace_stages
from common.matching.index import MatchIndex
from common.matching.online import ribbon_calibration, stage_combination, train_model, with_combination
from common.matching.pairs import training_set


_MODELS: dict = {}


def _model(small_wall, **kw):
    wall, tables, cues, poses = small_wall
    if id(small_wall) not in _MODELS:   # one fit per session (the fixture is session-scoped)
        _MODELS[id(small_wall)] = train_model(training_set(cues, poses, wall.adjacency, seed=1),
                                              ribbon=ribbon_calibration(tables, wall.adjacency), docking=(0.05, -2.0))[0]
    model = _MODELS[id(small_wall)]
    return with_combination(model, kw["combination"]) if "combination" in kw else model


def _sigmoid(z):
    return 1.0 / (1.0 + np.exp(-z))


def _cluster(wall, n):
    """``n`` fragments of the wall that touch one another (breadth first from the best connected)."""
    nb: dict = {}
    for a, b, *_ in wall.adjacency:
        nb.setdefault(a, set()).add(b)
        nb.setdefault(b, set()).add(a)
    start = max(nb, key=lambda f: len(nb[f]))
    out, queue = [], [start]
    while queue and len(out) < n:
        f = queue.pop(0)
        if f not in out:
            out.append(f)
            queue += sorted(nb[f] - set(out))
    return out


def test_combination_is_validated_stored_and_versioned(tmp_path, small_wall):
    from common.matching.models import load_model, save_model
    from common.store import Store

    model = _model(small_wall)
    combo = (0.5, 1.0, 2.0, 0.25, -1.5, 0.1, -2.0, -3.0, 0.0)
    m = with_combination(model, combo)
    assert m.combination == combo and m.version != model.version and m.sequence == model.sequence
    store = Store(tmp_path)
    back = load_model(store, save_model(store, m))
    assert back.combination == combo and back.version == m.version
    assert load_model(store, save_model(store, model)).combination is None
    with pytest.raises(ValueError, match="9 finite numbers"):
        replace(model, combination=combo[:5])
    with pytest.raises(ValueError, match="9 finite numbers"):
        replace(model, combination=(np.nan,) + combo[1:])
    with pytest.raises(ValueError, match="docking calibration"):
        replace(model, docking=None, combination=combo)


def test_combined_probability_weighs_the_stage_logits_and_fills_missing_terms(small_wall):
    model = replace(_model(small_wall), ribbon=(2.0, -1.0), docking=(0.1, -3.0),
                    combination=(0.5, 1.0, 2.0, 4.0, -1.0, 0.3, -0.7, -1.1, 0.2))
    p = model.combined_probability([1.0, np.nan], [0.5, np.nan], [20.0, 10.0], [3.0, np.nan])
    # by hand: terms (patch logit, 2·0.5 − 1, 0.1·20 − 3, 0.1·3) and, for the second, the stored fills
    first = 0.5 * 1.0 + 1.0 * 0.0 + 2.0 * -1.0 + 4.0 * 0.3 - 1.0
    second = 0.5 * 0.3 + 1.0 * -0.7 + 2.0 * (0.1 * 10 - 3) + 4.0 * 0.2 - 1.0
    assert p == pytest.approx(_sigmoid(np.array([first, second])))
    with pytest.raises(ValueError, match="no learned stage combination"):
        replace(model, combination=None).combined_probability([0.0], [0.0], [0.0], [0.0])


def test_docking_stage_ranks_its_candidates_by_the_learned_combination(small_wall):
    """With a combination that weighs only the docking term, the docked candidates are ordered by their
    hub-corrected contact and get exactly σ(w·(slope·contact + b) + b0); the rest stay below them."""
    wall, tables, cues, poses = small_wall
    model = _model(small_wall, combination=(0.0, 0.0, 1.5, 0.0, -0.5, 0.0, 0.0, 0.0, 0.0))
    ids = [f for f in cues if len(cues[f]) >= 3 and tables[f].boundary_profile is not None][:9]
    index = MatchIndex()
    for f in ids:
        index.add(cues[f], tables[f].contour_mm, tables[f].boundary_profile)
    q = ids[0]
    ranked = index.rank(cues[q], ids[1:], model, dock_candidates=4)
    head, tail = ranked[:4], ranked[4:]
    contact = np.array([c.docking_contact_mm for c in head])
    assert np.all(np.isfinite(contact)) and list(contact) == sorted(contact, reverse=True)
    assert [c.probability for c in head] == pytest.approx(list(_sigmoid(1.5 * (0.05 * contact - 2.0) - 0.5)))
    assert all(c.probability <= head[-1].probability for c in tail)
    assert all(np.isfinite(c.patch_logit) for c in head if c.patch_a >= 0)


def test_trace_follows_the_ranking_stage_by_stage(small_wall):
    wall, tables, cues, poses = small_wall
    model = _model(small_wall)
    ids = [f for f in cues if len(cues[f]) >= 3 and tables[f].boundary_profile is not None][:9]
    index = MatchIndex()
    for f in ids:
        index.add(cues[f], tables[f].contour_mm, tables[f].boundary_profile)
    q = ids[0]
    t = trace_stages(index, model, q, ids, ribbon_candidates=5, dock_candidates=3)
    ranked = index.rank(cues[q], ids[1:], model, ribbon_candidates=5, dock_candidates=3)
    assert t.order["dock"] == [c.other for c in ranked]
    assert t.probability == pytest.approx({c.other: c.probability for c in ranked})
    assert set(t.order["ribbon"]) <= set(t.order["patch"]) | set(ids[1:]) and len(t.order["patch"]) >= 5
    assert set(t.order["dock"][:3]) == set(t.order["ribbon"][:3])     # stage 3 re-orders the docked 3 only
    assert all(np.isfinite(t.evidence[o]["contact_mm"]) for o in t.order["dock"][:3])


def test_stage_recall_counts_each_link_where_each_stage_left_it():
    nan = float("nan")
    ev = {"patch_logit": nan, "ribbon": nan, "contact_mm": nan, "paint_mm": nan}
    a = StageTrace("a", {"prune": ["b", "c", "d"], "patch": ["c", "b", "d"], "ribbon": ["c", "b"], "dock": ["b", "c"]},
                   {"b": 0.9, "c": 0.5}, {o: ev for o in "bcd"})
    d = StageTrace("d", {"prune": ["a"], "patch": ["b", "c", "a"], "ribbon": ["b", "c"], "dock": ["b", "c"]},
                   {"b": 0.4, "c": 0.3}, {o: ev for o in "abc"})
    # true pairs a–b and a–d; links: a→b, a→d, d→a (b and c not traced)
    rec = stage_recall([a, d], [("a", "b"), ("a", "d")], ks=(1, 2))
    assert rec["links"] == [("a", "b"), ("a", "d"), ("d", "a")]
    assert rec["ranks"]["prune"] == [0, 2, 0] and rec["prune"] == {"kept": 1.0, 1: 2 / 3, 2: 2 / 3}
    assert rec["ranks"]["patch"] == [1, 2, 2] and rec["patch"][2] == pytest.approx(1 / 3)
    assert rec["ranks"]["ribbon"] == [1, None, None] and rec["ribbon"]["kept"] == pytest.approx(1 / 3)
    assert rec["ranks"]["dock"] == [0, None, None]
    # pooled in the station's order (mutual proximity): a's list b, c; d's list b, c; b and c have none;
    # a–d never scored by either side
    assert rec["ranks"]["final"] == [0, None, None] and rec["final"][1] == pytest.approx(1 / 3)


def test_stage_combination_learns_weights_that_rank_true_neighbours_higher(small_wall):
    wall, tables, cues, poses = small_wall
    model = _model(small_wall)
    ids = [f for f in _cluster(wall, 8) if tables[f].boundary_profile is not None]
    adj = [p for p in wall.adjacency if p[0] in ids and p[1] in ids]
    combo = stage_combination({f: tables[f] for f in ids}, {f: cues[f] for f in ids}, adj, model)
    assert combo is not None and len(combo) == 9 and np.all(np.isfinite(combo))
    m = with_combination(model, combo)
    index = MatchIndex()
    for f in ids:
        index.add(cues[f], tables[f].contour_mm, tables[f].boundary_profile)
    truth = {frozenset(p[:2]) for p in adj}
    true_p, other_p = [], []
    for f in ids:
        for c in index.rank(cues[f], [o for o in ids if o != f], m):
            if np.isfinite(c.docking_contact_mm):
                (true_p if frozenset((f, c.other)) in truth else other_p).append(c.probability)
    assert len(true_p) >= 5 and np.mean(true_p) > np.mean(other_p)
    # too few docked candidates of one kind: no combination
    assert stage_combination({f: tables[f] for f in ids[:3]}, {f: cues[f] for f in ids[:3]}, adj[:1], model) is None
