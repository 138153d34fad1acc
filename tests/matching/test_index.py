"""The staged index: incremental adds equal a rebuild, pruning follows the model's fragment cues."""

import numpy as np
import pytest

from common.matching.index import MatchIndex
from common.matching.online import train_model
from common.matching.pairs import pair_rows, training_set


def _model(small_wall):
    wall, _, cues, poses = small_wall
    model, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1))
    return model


def test_incremental_index_scores_like_direct_patch_pair_evaluation(small_wall):
    wall, tables, cues, poses = small_wall
    model = _model(small_wall)
    ids = [f for f in cues if len(cues[f]) >= 3][:12]
    index = MatchIndex()
    for f in ids[:6]:
        index.add(cues[f], tables[f].contour_mm)
    index._ensure()
    for f in ids[6:]:            # appended without a rebuild
        index.add(cues[f], tables[f].contour_mm)
    q = cues[ids[0]]
    got = {c.other: c.patch_probability for c in index.score(q, ids[1:], model)}
    for other in ids[1:]:
        p = np.sort(model.probability(pair_rows(q, cues[other])))[::-1][:model.top_m].mean()
        # stage 2 adds its grid up in float32 (index._patch_logits): ~1e-5 of the logit
        assert got[other] == __import__("pytest").approx(p, rel=1e-4)
    # removing the last fragment and adding it back changes nothing
    index.remove(ids[-1])
    index.add(cues[ids[-1]], tables[ids[-1]].contour_mm)
    again = {c.other: c.patch_probability for c in index.score(q, ids[1:], model)}
    assert again == __import__("pytest").approx(got)


def test_pruning_keeps_the_fragments_nearest_in_the_weighted_fragment_cues(small_wall):
    wall, tables, cues, poses = small_wall
    model = _model(small_wall)
    index = MatchIndex()
    ids = list(cues)
    for f in ids[:25]:
        index.add(cues[f])
    q = cues[ids[0]]
    index.candidates(q, model, n_candidates=5)   # builds the KD-tree over 25 fragments
    for f in ids[25:]:                            # these go to the tree's tail
        index.add(cues[f])
    assert index._tree is not None and index._tree_n == 25
    cand = index.candidates(q, model, n_candidates=5)
    assert len(cand) == 5 and q.fragment not in cand
    # brute force: the fragment-level part of the model's logit, largest first
    fcols = [i for i, c in enumerate(model.columns) if c.startswith("fragment.")]
    w = np.maximum(0, -model.coef[fcols]) / model.scale[fcols]
    index._ensure()
    med = np.nanmedian(index._values, axis=0)
    pts = np.where(np.isfinite(index._values), index._values, med) * w
    qp = np.where(np.isfinite(q.values), q.values, med) * w
    d = np.abs(pts - qp).sum(axis=1)
    order = [index._order[i] for i in np.argsort(d) if index._order[i] != q.fragment][:5]
    assert set(cand) == set(order)


def test_propose_aligns_the_best_candidates(small_wall):
    wall, tables, cues, poses = small_wall
    model = _model(small_wall)
    index = MatchIndex()
    for f in cues:
        index.add(cues[f], tables[f].contour_mm)
    q = max(cues.values(), key=len)
    found = index.propose(q, model, top=5, check=2)
    assert len(found) == 5
    assert [c.probability for c in found] == sorted((c.probability for c in found), reverse=True)
    assert found[0].alignment is not None and found[1].alignment is not None and found[2].alignment is None


def test_hubness_ranking_finds_more_true_neighbours_than_the_patch_probability(small_wall):
    """Top-k recall of the ground-truth neighbours (Wall.adjacency) on a wall the model never saw:
    the hubness-corrected ranking must beat the previous ranking (mean of the best 3 patch-pair
    probabilities) of the very same pairs."""
    from common.matching.evaluation import rank_all_pairs, top_k_recall
    from common.matching.online import wall_cues
    from common.synth.wall import generate_wall

    model = _model(small_wall)
    wall = generate_wall(40, seed=5, dpi=60)
    tables, cues, _ = wall_cues(wall)
    index = MatchIndex()
    for f, c in cues.items():
        index.add(c, tables[f].contour_mm)
    new = rank_all_pairs(index, model)
    plain = MatchIndex(use_hubness=False)
    for f, c in cues.items():
        plain.add(c, tables[f].contour_mm)
    old = rank_all_pairs(plain, model)
    assert set(old) == set(new)
    ks = (3, 5, 10)
    r_new, r_old = top_k_recall(new, wall.adjacency, ks), top_k_recall(old, wall.adjacency, ks)
    assert sum(r_new.values()) > sum(r_old.values()) + 0.05, (r_new, r_old)
    # every fragment with patches got its hubness under this model
    assert {f for f, c in cues.items() if len(c)} == {f for f, (v, _) in index.hubness.items() if v == model.version}


def test_hubness_is_kept_per_model_version_and_centres_the_pair_logit(small_wall):
    """μ of every fragment is the mean logit of its patch probability against its candidates; the
    ranking logit is logit(p_ab) − ½(μ_a − μ̄) − ½(μ_b − μ̄) with μ̄ the median (index docstring)."""
    import copy

    wall, tables, cues, poses = small_wall
    model = _model(small_wall)
    ids = [f for f in cues if len(cues[f]) >= 3][:25]
    index = MatchIndex()
    for f in ids:
        index.add(cues[f], tables[f].contour_mm)
    assert index.refresh_hubness(ids, model) == len(ids)
    assert index.refresh_hubness(ids, model) == 0          # already there under this model
    q = ids[0]
    found = index.score(cues[q], ids[1:], model)
    mu = {f: index.hubness[f][1] for f in ids}
    assert mu[q] == __import__("pytest").approx(np.mean([logit(c.patch_probability) for c in found]))
    centre = np.median(list(mu.values()))
    for c in found:
        want = logit(c.patch_probability) - 0.5 * (mu[q] - centre) - 0.5 * (mu[c.other] - centre)
        assert logit(c.probability) == __import__("pytest").approx(want, abs=1e-9)
    assert [c.probability for c in found] == sorted((c.probability for c in found), reverse=True)
    # a new model version makes every hubness stale
    model2 = copy.deepcopy(model)
    model2.version = "0002-test"
    assert index.refresh_hubness(ids, model2) == len(ids)
    # without the correction the ranking probability is the patch probability
    plain = MatchIndex(use_hubness=False)
    for f in ids:
        plain.add(cues[f], tables[f].contour_mm)
    for c in plain.score(cues[q], ids[1:], model):
        assert c.probability == c.patch_probability


def logit(p):
    return np.log(p) - np.log1p(-p)


def _ribbon_setup(small_wall):
    """A model with the ribbon calibration of the training wall, and an index of a second wall."""
    from common.matching.online import ribbon_calibration, wall_cues
    from common.synth.wall import generate_wall

    wall, tables, cues, poses = small_wall
    cal = ribbon_calibration(tables, wall.adjacency)
    model, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1), ribbon=cal)
    wall2 = generate_wall(40, seed=5, dpi=60)
    tables2, cues2, _ = wall_cues(wall2)
    index = MatchIndex()
    for f, c in cues2.items():
        index.add(c, tables2[f].contour_mm, tables2[f].boundary_profile)
    return model, wall2, cues2, index


def test_colour_ribbon_ranks_more_true_neighbours_than_stage_2_alone(small_wall, monkeypatch):
    """Top-k recall of the ground-truth neighbours of a wall the model never saw: the staged ranking
    with the colour ribbon (stage 2½) must beat stage 2 alone (the same model without calibration);
    the same-fresco step after stage 2½ (fresco.py) is off, so only the ribbon differs."""
    import dataclasses

    from common.matching import fresco

    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 0.0)

    from common.matching.evaluation import rank_all_pairs, top_k_recall

    model, wall2, _, index = _ribbon_setup(small_wall)
    assert model.ribbon is not None and model.ribbon[0] > 0   # a better fit is a likelier join
    ks = (3, 5, 10)
    with_ribbon = top_k_recall(rank_all_pairs(index, model), wall2.adjacency, ks)
    stage2 = top_k_recall(rank_all_pairs(index, dataclasses.replace(model, ribbon=None)), wall2.adjacency, ks)
    assert sum(with_ribbon.values()) > sum(stage2.values()) + 0.2, (with_ribbon, stage2)


def test_propose_with_the_ribbon_gives_calibrated_probabilities_even_without_patches(small_wall):
    from common.matching.ribbon import ribbon_probability

    model, _, cues2, index = _ribbon_setup(small_wall)
    q = max(cues2.values(), key=len)
    found = index.propose(q, model, top=8, check=1)
    assert len(found) == 8 and found[0].alignment is not None
    probs = [c.probability for c in found]
    assert probs == sorted(probs, reverse=True)
    # the ribbon's calibrated probability, with the same-fresco ratio added to its logit (fresco.py)
    from common.matching import fresco

    ribbon = ribbon_probability([c.ribbon_score for c in found], model.ribbon)
    np.testing.assert_allclose(probs, fresco.with_fresco(ribbon, [c.fresco_llr for c in found], fresco.FRESCO_WEIGHT))
    assert all(c.evidence is not None and len(c.evidence) == model.top_m for c in found if c.patch_a >= 0)
    # a fragment too small for a valid patch: stage 2 cannot score it, the ribbon still ranks it
    small = next(c for c in cues2.values() if len(c) == 0)
    assert index.score(small, [f for f in cues2 if f != small.fragment], model) == []
    found = index.propose(small, model, top=5, check=1)
    assert len(found) == 5 and all(c.patch_a == -1 and np.isfinite(c.ribbon_score) for c in found)
    assert found[0].alignment is not None


def test_docking_stage_reorders_the_best_candidates_by_hub_corrected_contact(small_wall):
    """Stage 3: with a docking calibration, the best DOCK_CANDIDATES are re-ranked by their docking
    contact less both hubnesses (computed independently here), carry the docked pose, and nothing
    after them is more probable; without one, the ranking is stage 2½'s unchanged."""
    from dataclasses import replace

    from common.matching.docking import dock_outlines, docking_contact_mm

    wall, tables, cues, poses = small_wall
    base = _model(small_wall)
    ids = [f for f in cues if len(cues[f]) >= 3][:10]
    index = MatchIndex()
    for f in ids:
        index.add(cues[f], tables[f].contour_mm)
    q, others = ids[0], ids[1:]
    before = index.rank(cues[q], others, base)
    plain = [c.other for c in before]
    p_before = {c.other: c.probability for c in before}
    model = replace(base, docking=(0.05, -2.0))
    ranked = index.rank(cues[q], others, model, dock_candidates=4)
    head, tail = ranked[:4], ranked[4:]
    assert {c.other for c in head} == set(plain[:4])          # the same four, re-ordered
    assert [c.other for c in tail] == plain[4:]
    contact = {o: docking_contact_mm(dock_outlines(tables[q].contour_mm, tables[o].contour_mm, n_poses=1)[0])
               for o in plain[:4]}
    mu_q = np.sort(list(contact.values()))[-3:].mean()
    assert index.dock_hubness[q] == __import__("pytest").approx(mu_q)
    # the others have no hubness yet: they take the median (the query's own), so the contact is
    # uncorrected; the earlier stages' logit, relative to the four's mean, is added (naive Bayes), and that logit
    # is recalibrated (index.JOIN_CALIBRATION: Platt scaling, slope a and intercept b)
    from common.matching.index import JOIN_CALIBRATION
    a, b = JOIN_CALIBRATION["slope"], JOIN_CALIBRATION["intercept"]
    logit = {o: np.log(p_before[o] / (1 - p_before[o])) for o in contact}
    mean_logit = np.mean(list(logit.values()))
    expect = {o: 1 / (1 + np.exp(-(a * (0.05 * contact[o] - 2.0 + logit[o] - mean_logit) + b))) for o in contact}
    assert [c.other for c in head] == sorted(expect, key=lambda o: -expect[o])
    for c in head:
        assert c.alignment is not None and c.docking is not None
        assert c.docking_contact_mm == __import__("pytest").approx(contact[c.other])
        assert c.probability == __import__("pytest").approx(expect[c.other], rel=1e-6)
    assert max(c.probability for c in tail) <= min(c.probability for c in head)
    # the pair is docked once: asking from the other side reuses (inverts) the cached docking
    d_qo, d_oq = index.docking(q, head[0].other), index.docking(head[0].other, q)
    assert d_oq.angle_deg == __import__("pytest").approx(-d_qo.angle_deg)
    assert len(index._dockings) == 4
    # a model without docking ranks as before
    assert [c.other for c in index.rank(cues[q], others, base)] == plain


def test_model_keeps_its_docking_calibration_through_storage(tmp_path, small_wall):
    from dataclasses import replace

    from common.matching.models import load_model, save_model
    from common.store import Store

    model = replace(_model(small_wall), docking=(0.02, -3.0))
    store = Store(tmp_path)
    back = load_model(store, save_model(store, model))
    assert back.docking == (0.02, -3.0)
    assert replace(model, docking=(0.03, -3.0)).digest() != model.digest()


def _docking_index(small_wall, n: int, dockings=None):
    """(a model with a docking calibration, the first ``n`` fragments with patches and a boundary
    profile, an index of them with their outlines and profiles): stage 3 with paint. ``dockings``: the
    store the index keeps its dockings in."""
    from dataclasses import replace

    wall, tables, cues, poses = small_wall
    model = replace(_model(small_wall), docking=(0.05, -2.0))
    ids = [f for f in cues if len(cues[f]) >= 3 and tables[f].boundary_profile is not None][:n]
    index = MatchIndex(dockings=dockings)
    for f in ids:
        index.add(cues[f], tables[f].contour_mm, tables[f].boundary_profile)
    return model, ids, index


def test_the_first_answer_of_a_docking_station_is_recalibrated_and_keeps_its_order(small_wall):
    """A station that docks next answers first from stages 1–2½, whose probabilities over-state (the same-fresco
    ratio most): propose(dock=False) gives the fast stages' order with each probability Platt-recalibrated by
    FIRST_CALIBRATION (σ(a logit p + b)), on the docked answer's scale; a model without docking keeps its own."""
    from dataclasses import replace

    from common.matching.index import FIRST_CALIBRATION

    model, ids, index = _docking_index(small_wall, 8)
    q = index.cues[ids[0]]
    raw = index.rank(q, index.candidates(q, model, 100), model, dock_candidates=0)[:5]
    first = index.propose(q, model, top=5, check=0, dock=False)
    assert [c.other for c in first] == [c.other for c in raw]
    a, b = FIRST_CALIBRATION["slope"], FIRST_CALIBRATION["intercept"]
    for c, r in zip(first, raw):
        want = 1.0 / (1.0 + np.exp(-(a * np.log(r.probability / (1.0 - r.probability)) + b)))
        assert c.probability == pytest.approx(want, rel=1e-9)
    assert max(c.probability for c in first) < max(r.probability for r in raw)
    plain = replace(model, docking=None)
    assert [c.probability for c in index.propose(q, plain, top=5, check=0, dock=False)] == \
        [c.probability for c in index.rank(q, index.candidates(q, plain, 100), plain, dock_candidates=0)[:5]]


def test_docking_stage_adds_the_pairs_paint_continuity(small_wall, monkeypatch):
    """Stage 3 with boundary profiles: each docked candidate's logit gains its paint continuity (best
    over the docking's candidate poses, computed independently here), cached per pair; without
    profiles (or with the paint switched off) the probabilities are the geometric ones."""
    import common.matching.index as index_mod
    from common.matching.paint import paint_field_from_profile, paint_pair_mm, with_paint

    wall, tables, cues, poses = small_wall
    model, ids, index = _docking_index(small_wall, 8)
    q, others = ids[0], ids[1:]
    monkeypatch.setattr(index_mod, "DOCK_USES_PAINT", False)
    geometric = {c.other: c.probability for c in index.rank(cues[q], others, model, dock_candidates=3)[:3]}
    monkeypatch.setattr(index_mod, "DOCK_USES_PAINT", True)
    ranked = index.rank(cues[q], others, model, dock_candidates=3)
    head = ranked[:3]
    assert {c.other for c in head} == set(geometric)
    fq = paint_field_from_profile(tables[q].contour_mm, tables[q].boundary_profile)
    for c in head:
        fo = paint_field_from_profile(tables[c.other].contour_mm, tables[c.other].boundary_profile)
        a, b = (fq, fo) if q < c.other else (fo, fq)
        ca, cb = (tables[q].contour_mm, tables[c.other].contour_mm)[:: 1 if q < c.other else -1]
        mm, _ = paint_pair_mm(a, b, ca, cb)
        assert np.isfinite(c.paint_mm) and c.paint_mm == __import__("pytest").approx(mm)
        # the paint is added to stage 3's logit before its recalibration (index.JOIN_CALIBRATION): undo it, add, redo
        a_, b_ = index_mod.JOIN_CALIBRATION["slope"], index_mod.JOIN_CALIBRATION["intercept"]
        lg = np.log(geometric[c.other] / (1 - geometric[c.other]))
        raw = 1 / (1 + np.exp(-(lg - b_) / a_))
        lp = np.log(float(with_paint(raw, mm, 0.05)) / (1 - float(with_paint(raw, mm, 0.05))))
        assert c.probability == __import__("pytest").approx(1 / (1 + np.exp(-(a_ * lp + b_))), rel=1e-5)
    assert [c.probability for c in head] == sorted((c.probability for c in head), reverse=True)
    assert len(index._paint_pairs) == 3                      # cached per pair
    assert index.paint_pair(head[0].other, q) == head[0].paint_mm


def test_stage_2_scores_missing_cues_as_the_model_imputes_them(small_wall):
    # colour-only fragments have no normal cues: NaN columns take the model's imputed value, as
    # model.probability does on the correspondence rows
    import dataclasses
    wall, tables, cues, poses = small_wall
    model = _model(small_wall)
    rng = np.random.default_rng(5)
    ids = [f for f in cues if len(cues[f]) >= 3][:10]
    holed = {}
    for k, f in enumerate(ids):
        patches, strips = cues[f].patches.copy(), [s.copy() for s in cues[f].strips]
        if k % 2:   # every other fragment lacks a few cues altogether, one patch lacks all
            patches[:, rng.choice(patches.shape[1], 6, replace=False)] = np.nan
        patches[0, :] = np.nan
        strips[0][1] = np.nan
        holed[f] = dataclasses.replace(cues[f], patches=patches, strips=strips)
    index = MatchIndex()
    for f in ids:
        index.add(holed[f], tables[f].contour_mm)
    q = holed[ids[1]]
    got = {c.other: c.patch_probability for c in index.score(q, ids, model)}
    assert len(got) == len(ids) - 1
    for other in ids:
        if other != q.fragment:
            p = np.sort(model.probability(pair_rows(q, holed[other])))[::-1][:model.top_m].mean()
            assert got[other] == pytest.approx(p, rel=1e-4)   # float32 grid, as above


def test_a_docked_candidate_offers_the_dockings_other_poses_in_its_frame(small_wall):
    """Stage 3 with paint proposes the learned chooser's best of the docking's 30 candidates and keeps the next-best
    distinct ones of its 30 + 70 (by the chooser's scores among all): the candidate's alignment carries them as
    ``other`` in the query's frame, and seen from the other fragment they are their inverses. The pair's paint
    evidence is the best over the first 30 only (the further candidates widen the offer, not the evidence).
    ``candidate_poses`` gives all 100, from either side."""
    from common.matching.alignment import pose_matrix
    from common.matching.docking import dock_outlines
    from common.matching.index import DOCK_MORE_POSES, DOCK_PAINT_PER_ANGLE, DOCK_PAINT_POSES
    from common.matching.paint import paint_continuity, paint_field_from_profile
    from common.matching.pose import ALTERNATIVE_POSES, learned_pose_scores, pose_features, wrapped_deg

    wall, tables, cues, poses = small_wall
    model, ids, index = _docking_index(small_wall, 6)
    q = ids[0]
    head = index.rank(cues[q], ids[1:], model, dock_candidates=3)[:3]
    angles = []
    for c in head:
        a, b = sorted((q, c.other))
        docks = dock_outlines(tables[a].contour_mm, tables[b].contour_mm, n_poses=DOCK_PAINT_POSES,
                              per_angle=DOCK_PAINT_PER_ANGLE, more_poses=DOCK_MORE_POSES)
        assert len(docks) > DOCK_PAINT_POSES
        paint = paint_continuity(paint_field_from_profile(tables[a].contour_mm, tables[a].boundary_profile),
                                 paint_field_from_profile(tables[b].contour_mm, tables[b].boundary_profile),
                                 np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks]))
        features = pose_features(docks, paint, tables[a].contour_mm, tables[b].contour_mm)
        # the pose: the chooser's best of the first 30, scored among them (what it was fitted on)
        chosen = docks[int(np.argmax(learned_pose_scores(features[:DOCK_PAINT_POSES])))]
        assert index.pose(a, b) == chosen
        # every candidate the pair chose and offers among, as the search gives them (the evaluation's ceiling)
        every = index.candidate_poses(a, b)
        assert every == docks
        for g, h in zip(every, index.candidate_poses(b, a)):
            np.testing.assert_allclose(pose_matrix(g.angle_deg, g.tx_mm, g.ty_mm) @ pose_matrix(h.angle_deg, h.tx_mm, h.ty_mm),
                                       np.eye(3), atol=1e-6)
        # the alternatives: all the others by the chooser's scores among all 100, no near repeat of a better one
        scores = learned_pose_scores(features)
        want = []
        for i in np.argsort(-scores, kind="stable"):
            d = docks[int(i)]
            if d != chosen and not any(abs((d.angle_deg - k.angle_deg + 180) % 360 - 180) <= 3.0
                                       and np.hypot(d.tx_mm - k.tx_mm, d.ty_mm - k.ty_mm) <= 3.0 for k in [chosen] + want):
                want.append(d)
        want = want[:ALTERNATIVE_POSES]                                                      # b in a's frame
        assert index.paint_pair(a, b) == pytest.approx(float(np.max(paint[:DOCK_PAINT_POSES])))
        got = index.alternatives(a, b)
        assert 0 < len(got) <= ALTERNATIVE_POSES and len(got) == len(want)
        for g, w in zip(got, want):
            np.testing.assert_allclose((g.angle_deg, g.tx_mm, g.ty_mm), (w.angle_deg, w.tx_mm, w.ty_mm), atol=1e-6)
        for g, h in zip(got, index.alternatives(b, a)):
            np.testing.assert_allclose(pose_matrix(g.angle_deg, g.tx_mm, g.ty_mm) @ pose_matrix(h.angle_deg, h.tx_mm, h.ty_mm),
                                       np.eye(3), atol=1e-6)
        mine = index.alternatives(q, c.other)
        # the proposal shows the same poses with every angle in the one range the station uses, [-180, 180)
        # (the docking's own are in [0, 360): a pose read 249° beside a verdict's -111° is the same pose)
        assert [tuple(map(float, t)) for t in c.alignment.alternatives] == \
            [(wrapped_deg(m.angle_deg), m.tx_mm, m.ty_mm) for m in mine]
        p = index.pose(q, c.other)
        assert (c.alignment.angle_deg, c.alignment.tx_mm, c.alignment.ty_mm) == (wrapped_deg(p.angle_deg), p.tx_mm, p.ty_mm)
        angles.extend([c.alignment.angle_deg] + [t[0] for t in c.alignment.alternatives])
    assert all(-180.0 <= a < 180.0 for a in angles)
    assert any(abs(a) > 1.0 for a in angles)        # turned poses among them, so the range was tested


def _after_a_model_update(small_wall, n: int = 24, dock_candidates: int = 3, dockings=None):
    """(the old model, a new model — weights moved by 30 % —, the fragments, an index where every fragment
    was proposed and its best ``dock_candidates`` docked under the old model: a station's steady state;
    more than HUBNESS_MIN_OTHERS fragments, so each has a hubness). ``dockings``: the index's store."""
    from dataclasses import replace

    model, ids, index = _docking_index(small_wall, n, dockings)
    for f in ids:   # the arrivals
        index.propose(index.cues[f], model, dock_candidates=dock_candidates)
    rng = np.random.default_rng(4)
    model2 = replace(model, coef=model.coef * (1 + 0.3 * rng.standard_normal(model.coef.shape)),
                     version="0002-rank-all")
    return model, model2, ids, index


def test_rank_all_docks_no_pair_and_returns_each_best_heads_undocked_pairs(small_wall):
    """The full re-rank after a model update docks nothing; what it returns is, for each fragment, exactly
    the pairs among its best ``dock_candidates`` after stage 2½ under the new model that were never docked
    (computed here from stages 1–2½ alone)."""
    model, model2, ids, index = _after_a_model_update(small_wall)
    docked = set(index._dockings)
    undocked = index.rank_all(model2, dock_candidates=3)
    assert set(index._dockings) == docked                       # no new docking
    assert all(index.hubness[f][0] == model2.version for f in ids)
    expected = {}
    for f in ids:
        others = index.candidates(index.cues[f], model2)
        head = [c.other for c in index.rank(index.cues[f], others, model2, dock_candidates=0)[:3]]
        new = [o for o in head if tuple(sorted((f, o))) not in docked]
        if new:
            expected[f] = new
    assert undocked == expected
    assert 0 < len(undocked) < len(ids)                         # the fixture has both kinds
    assert set(index._dockings) == docked


def test_rank_all_ranks_a_fragment_whose_best_are_docked_as_propose_does(small_wall):
    """Each fragment's kept ranking is what :meth:`propose` would give at that point of the pass (on a copy
    of the index, docking what it needs) wherever its best were docked before; and the pass is
    :meth:`rank_again` of every fragment after every hubness under the new model."""
    import copy

    model, model2, ids, index = _after_a_model_update(small_wall)
    ref = copy.deepcopy(index)
    ref.refresh_hubness(ref._order, model2)
    proposed = {}
    for f in ids:
        probe = copy.deepcopy(ref)
        probe.propose(probe.cues[f], model2, dock_candidates=3)
        proposed[f] = probe.rankings[f]
        ref.rank_again([f], model2, dock_candidates=3)
    undocked = index.rank_all(model2, dock_candidates=3)
    assert {f: index.rankings[f] for f in ids} == {f: ref.rankings[f] for f in ids}
    whole = [f for f in ids if f not in undocked]
    assert whole
    for f in whole:
        assert index.rankings[f] == proposed[f]
    for f, new in undocked.items():   # a pair new to the best is left below the docked ones
        assert not set(new) & set(index.rankings[f][:3 - len(new)])


def test_docking_the_pairs_rank_all_returns_brings_every_ranking_to_proposes(small_wall):
    """The follow-up: :meth:`propose` for each fragment rank_all named docks exactly its returned pairs;
    then a second full re-rank returns nothing and every fragment's ranking is what :meth:`propose`
    gives."""
    model, model2, ids, index = _after_a_model_update(small_wall)
    undocked = index.rank_all(model2, dock_candidates=3)
    for f, new in undocked.items():
        before = set(index._dockings)
        index.propose(index.cues[f], model2, dock_candidates=3)
        assert set(index._dockings) - before == {tuple(sorted((f, o))) for o in new} - before
    assert index.rank_all(model2, dock_candidates=3) == {}
    docked = set(index._dockings)
    for f in ids:
        kept = index.rankings[f]
        index.propose(index.cues[f], model2, dock_candidates=3)
        assert index.rankings[f] == kept
    assert set(index._dockings) == docked


# -- the dockings kept in the proposal store (MatchIndex(dockings=...)) --------------------------------------

def _counted_dockings(monkeypatch) -> list:
    """Every docking search the index makes from now on (one per docked pair), as a list that grows."""
    import common.matching.index as index_mod

    calls, dock = [], index_mod.dock_frames

    def counted(*args, **kw):
        calls.append(kw.get("n_poses"))
        return dock(*args, **kw)

    monkeypatch.setattr(index_mod, "dock_frames", counted)
    return calls


def _same_index(small_wall, ids, dockings):
    """A fresh index of ``ids`` (outlines and profiles) over ``dockings``: another worker, or this one restarted."""
    wall, tables, cues, poses = small_wall
    index = MatchIndex(dockings=dockings)
    for f in ids:
        index.add(cues[f], tables[f].contour_mm, tables[f].boundary_profile)
    return index


def _poses_of(index, keys) -> dict:
    return {k: (index.docking(*k), index.pose(*k), index.alternatives(*k), index.paint_pair(*k)) for k in keys}


def test_a_second_index_over_the_same_store_docks_none_of_the_pairs_the_first_docked(tmp_path, small_wall, monkeypatch):
    """A worker that starts afresh (or a second one) over the proposal store reads the pairs another docked:
    after the same arrivals the full re-rank gives the same rankings and the same pairs to dock next, the
    same poses, paint and alternatives (exactly: the numbers go through SQLite unchanged), and docks
    nothing; nor does a worker restarted straight into the full re-rank, which ranks as the first did."""
    from common.matching.proposals import ProposalStore

    calls = _counted_dockings(monkeypatch)
    store = ProposalStore(tmp_path / "p.sqlite")
    model, model2, ids, first = _after_a_model_update(small_wall, dockings=store)
    undocked = first.rank_all(model2, dock_candidates=3)
    assert calls and len(calls) == len(first._dockings) == store.count_dockings()   # each pair docked once, kept

    calls.clear()
    second = _same_index(small_wall, ids, ProposalStore(tmp_path / "p.sqlite"))
    for f in ids:   # the same arrivals, in the same order (as _after_a_model_update)
        second.propose(second.cues[f], model, dock_candidates=3)
    assert second.rank_all(model2, dock_candidates=3) == undocked
    assert calls == []                                                  # not one docking
    assert {f: second.rankings[f] for f in ids} == {f: first.rankings[f] for f in ids}
    assert _poses_of(second, first._dockings) == _poses_of(first, first._dockings)

    # restarted straight into a full re-rank: nothing docked, the same pairs left to dock
    third = _same_index(small_wall, ids, ProposalStore(tmp_path / "p.sqlite"))
    assert third.rank_all(model2, dock_candidates=3) == undocked
    assert calls == []
    assert {f: third.rankings[f] for f in ids} == {f: first.rankings[f] for f in ids}   # in the same order
    assert third.dock_hubness == first.dock_hubness
    assert 0 < len(undocked) < len(ids)


def test_a_stored_docking_of_other_inputs_or_another_docking_version_is_docked_again(tmp_path, small_wall,
                                                                                      monkeypatch):
    """A stored docking is served only for both fragments' current outline and profile (docking_inputs) and
    this docking version: a re-extracted fragment's pairs, or every pair after the docking changed, are
    docked again (and the row replaced); the other pairs are read."""
    import common.matching.index as index_mod
    from common.matching.index import docking_inputs, docking_version
    from common.matching.proposals import ProposalStore

    wall, tables, cues, poses = small_wall
    calls = _counted_dockings(monkeypatch)
    store = ProposalStore(tmp_path / "p.sqlite")
    model, ids, first = _docking_index(small_wall, 10, store)
    q = ids[0]
    head = [c.other for c in first.rank(cues[q], ids[1:], model, dock_candidates=3)[:3]]
    assert len(calls) == 3 and store.count_dockings() == 3

    # the digest follows the outline and the profile, and only them
    c, p = tables[q].contour_mm, tables[q].boundary_profile
    assert docking_inputs(c, p) == docking_inputs(c.copy(), p.copy())
    assert len({docking_inputs(c, p), docking_inputs(c, None), docking_inputs(c + 0.01, p),
                docking_inputs(c, p * 1.01)}) == 4

    # one partner re-extracted (its outline moved by 10 µm): its pair only is docked again
    calls.clear()
    moved = head[1]
    second = _same_index(small_wall, ids, store)
    second.add(cues[moved], tables[moved].contour_mm + 0.01, tables[moved].boundary_profile)
    assert [c.other for c in second.rank(cues[q], ids[1:], model, dock_candidates=3)[:3]] == head
    assert len(calls) == 1
    a, b = sorted((q, moved))
    assert store.docking(a, b, second._inputs[a], second._inputs[b], docking_version()) is not None
    assert store.count_dockings() == 3                                 # replaced, not added

    # another docking version: every pair docked again
    calls.clear()
    monkeypatch.setattr(index_mod, "DOCKING_VERSION", "docking-test")
    third = _same_index(small_wall, ids, store)
    third.rank(cues[q], ids[1:], model, dock_candidates=3)
    assert len(calls) == 3 and store.count_dockings() == 3
    assert docking_version().startswith("docking-test/")
    # and a change of the settings a docking is made with is another version too
    monkeypatch.setattr(index_mod, "DOCK_USES_PAINT", False)
    assert "no-paint" in docking_version()


def test_a_damaged_or_missing_stored_docking_is_docked_again(tmp_path, small_wall, monkeypatch):
    """Rows that do not decode (a pose that is not JSON, a number that is text, a pose of the wrong length)
    or are gone are docked again without an error, and written back whole; the intact row is read."""
    import sqlite3

    from common.matching.proposals import ProposalStore

    wall, tables, cues, poses = small_wall
    calls = _counted_dockings(monkeypatch)
    store = ProposalStore(tmp_path / "p.sqlite")
    model, ids, first = _docking_index(small_wall, 10, store)
    q = ids[0]
    first.rank(cues[q], ids[1:], model, dock_candidates=5)
    keys = sorted(first._dockings)
    assert len(keys) == 5 and store.count_dockings() == 5
    raw = sqlite3.connect(tmp_path / "p.sqlite")
    with raw:
        where = "WHERE fragment_a=? AND fragment_b=?"
        raw.execute(f"UPDATE dockings SET pose='not json' {where}", keys[0])
        raw.execute(f"UPDATE dockings SET contact_mm='many' {where}", keys[1])
        raw.execute(f"UPDATE dockings SET alternatives='[[1, 2]]' {where}", keys[2])
        raw.execute(f"DELETE FROM dockings {where}", keys[3])
    raw.close()
    calls.clear()
    second = _same_index(small_wall, ids, store)
    second.rank(cues[q], ids[1:], model, dock_candidates=5)
    assert len(calls) == 4                                            # the fifth was read
    assert _poses_of(second, keys) == _poses_of(first, keys)
    assert store.count_dockings() == 5
    third = _same_index(small_wall, ids, store)
    calls.clear()
    third.rank(cues[q], ids[1:], model, dock_candidates=5)
    assert calls == []                                                # all written back whole


def test_docking_calibration_does_not_follow_string_hashing(tmp_path):
    # the bootstrap model's digest names its version on every worker: the fit must be the same numbers
    # whatever order Python's hash gives a set of fragment pairs
    import subprocess
    import sys

    code = ("from common.synth.wall import generate_wall\n"
            "from common.matching.online import docking_calibration\n"
            "w = generate_wall(10, seed=3, dpi=40)\n"
            "print(repr(docking_calibration(w, negatives_per_positive=1.0)))\n")
    runs = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                           env={**__import__("os").environ, "PYTHONHASHSEED": seed}).stdout
            for seed in ("1", "2", "3")}
    assert len(runs) == 1 and "None" not in runs.pop()


def test_an_evaluation_ranks_as_the_station_whatever_the_fragments_order(small_wall):
    """The station scores a pair once both fragments are ranked (docking hubness known for both); an evaluation
    that ranked one fragment after another corrected a pair by the median for every partner not ranked yet, so
    its figures depended on the fragments' order. Now every fragment's docking hubness is settled first."""
    from common.matching.docking import docking_contact_mm
    from common.matching.evaluation import rank_lists

    wall, tables, cues, poses = small_wall
    lists = []
    for order in (1, -1):
        model, ids, index = _docking_index(small_wall, 10)
        index._order = list(index._order)[::order]
        got, best = rank_lists(index, model)
        lists.append((got, best))
        # the hubness each pair was corrected by is each fragment's own, from its docked best among all
        for f in ids:
            head = [c.other for c in index.rank(cues[f], [o for o in ids if o != f], model, dock_candidates=0)][:12]
            contact = sorted(docking_contact_mm(index.docking(f, o)) for o in head if index.docked(f, o))
            assert index.dock_hubness[f] == pytest.approx(np.mean(contact[-3:]))
    assert lists[0][0] == lists[1][0]
    assert lists[0][1] == pytest.approx(lists[1][1])


def test_the_ribbon_ranks_stage_2s_best_with_the_same_fresco_ratio_added(monkeypatch):
    """The cut to the ribbon's candidates orders stage 2's list by its logit plus FRESCO_WEIGHT × the same-fresco
    ratio: a piece of another fresco that stage 2 likes is left out for one of the query's fresco that it
    likes less. Worked by hand: logits 2.20, 1.39, 0.85, 0.41 with ratios −4, 0, +4, 0 and weight 4 give
    −13.8, 1.39, 16.8, 0.41, so the best two are c then b (stage 2 alone: a then b). A list no longer than the
    cut, a query without a signature or the ratio switched off keep stage 2's choice."""
    from common.matching import fresco
    from common.matching.index import Candidate

    def cand(other, p):
        return Candidate("q", other, p, 0, 0, np.zeros((0, 2), int), np.zeros((0, 1)))

    found = [cand("a", 0.9), cand("b", 0.8), cand("c", 0.7), cand("d", 0.6)]
    ratio = {"a": -4.0, "b": 0.0, "c": 4.0, "d": 0.0}
    index = MatchIndex()
    monkeypatch.setattr(MatchIndex, "_fresco_signature", lambda self, f: f)
    monkeypatch.setattr(fresco, "fresco_llr", lambda a, b: ratio[b])
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 4.0)
    assert [c.other for c in index._ribbon_head("q", found, 2)] == ["c", "b"]
    assert [c.probability for c in found] == [0.9, 0.8, 0.7, 0.6]          # the probabilities are stage 2's
    assert [c.other for c in index._ribbon_head("q", found, 4)] == ["a", "b", "c", "d"]
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 0.0)
    assert [c.other for c in index._ribbon_head("q", found, 2)] == ["a", "b"]
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 4.0)
    monkeypatch.setattr(MatchIndex, "_fresco_signature", lambda self, f: None)
    assert [c.other for c in index._ribbon_head("q", found, 2)] == ["a", "b"]


def test_a_collection_of_one_fresco_keeps_the_ribbons_order_and_its_cut(monkeypatch):
    """Set for one fresco, the same-fresco ratio no longer re-orders the ribbon's candidates (ribbon probabilities
    0.6, 0.5 with ratios −1, +1 and weight 4: the ratio would put b first, as the default index does), while the cut
    to the ribbon's candidates still adds it (the reach: stage 2 likes a best, the ratio picks b)."""
    from common.matching import fresco
    from common.matching.index import Candidate

    def cand(other, p):
        return Candidate("q", other, p, 0, 0, np.zeros((0, 2), int), np.zeros((0, 1)))

    ratio = {"a": -1.0, "b": 1.0}
    monkeypatch.setattr(MatchIndex, "_fresco_signature", lambda self, f: f)
    monkeypatch.setattr(fresco, "fresco_llr", lambda a, b: ratio[b])
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 4.0)
    several, one = MatchIndex(), MatchIndex(single_fresco=True)
    assert [c.other for c in several._rank_by_fresco("q", [cand("a", 0.6), cand("b", 0.5)])] == ["b", "a"]
    kept = one._rank_by_fresco("q", [cand("a", 0.6), cand("b", 0.5)])
    assert [(c.other, c.probability) for c in kept] == [("a", 0.6), ("b", 0.5)]
    assert [c.other for c in one._ribbon_head("q", [cand("a", 0.6), cand("b", 0.5)], 1)] == ["b"]


def test_an_index_with_its_own_fresco_weight_ranks_as_that_default_would(monkeypatch):
    """``MatchIndex(fresco_weight=w)`` (a station's ``[services.matcher] fresco_weight``) weighs the same-fresco ratio
    as the module's default at w would, after stage 2½ and in the cut: ribbon probabilities 0.6, 0.5 with ratios −1, +1
    put b first at weight 4 (logit 0.405 − 4 < −0.405 + 4), keep a first at 0.1 (0.305 > 0.295); 0 is off (no
    signature taken, the order kept). A weight that is not a number >= 0 is refused."""
    from common.matching import fresco
    from common.matching.index import Candidate

    def cand(other, p):
        return Candidate("q", other, p, 0, 0, np.zeros((0, 2), int), np.zeros((0, 1)))

    def order(index):
        return ([c.other for c in index._rank_by_fresco("q", [cand("a", 0.6), cand("b", 0.5)])],
                [c.other for c in index._ribbon_head("q", [cand("a", 0.6), cand("b", 0.5)], 1)])

    ratio = {"a": -1.0, "b": 1.0}
    monkeypatch.setattr(MatchIndex, "_fresco_signature", lambda self, f: f)
    monkeypatch.setattr(fresco, "fresco_llr", lambda a, b: ratio[b])
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 4.0)
    assert order(MatchIndex()) == order(MatchIndex(fresco_weight=4)) == (["b", "a"], ["b"])
    assert order(MatchIndex(fresco_weight=0.1)) == (["a", "b"], ["a"])
    assert order(MatchIndex(fresco_weight=0)) == (["a", "b"], ["a"])
    probability = MatchIndex(fresco_weight=0.1)._rank_by_fresco("q", [cand("a", 0.6)])[0].probability
    assert probability == pytest.approx(fresco.with_fresco(0.6, -1.0, 0.1))
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 0.1)                 # the default followed when none is given
    assert order(MatchIndex()) == (["a", "b"], ["a"])
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fresco_weight must be a number >= 0"):
            MatchIndex(fresco_weight=bad)


def test_stage_1_takes_the_fragments_likeliest_of_the_querys_fresco_by_their_boundary_colours(monkeypatch):
    """With a signature, stage 1's candidates are the fragments whose a*b* histograms overlap the query's most
    (Bhattacharyya coefficient Σ √(h_q h_o), the same-fresco ratio's one cue). Histograms over two bins:
    the query (1, 0); a (1, 0), b (0.25, 0.75), c (0, 1), d (0.64, 0.36) overlap it by 1, 0.5, 0, 0.8, so the
    best three are a, d, b. A fragment whose profile changes is looked up afresh, a removed one is gone; without a
    signature (or with the ratio off) stage 1 is the KD-tree's (None here)."""
    from types import SimpleNamespace

    from common.matching import fresco

    hists = {"q": (1.0, 0.0), "a": (1.0, 0.0), "b": (0.25, 0.75), "c": (0.0, 1.0), "d": (0.64, 0.36)}
    index = MatchIndex()
    index.cues = {f: None for f in hists}   # what add() leaves for _chroma_rows: the fragments, marked
    index._chroma_stale = set(hists)
    sigs = {f: SimpleNamespace(chroma_hist=np.array([h], np.float32)) for f, h in hists.items()}
    monkeypatch.setattr(MatchIndex, "_fresco_signature", lambda self, f: sigs.get(f))
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 4.0)
    assert index._candidates_by_fresco("q", 3) == ["a", "d", "b"]
    sigs["c"] = SimpleNamespace(chroma_hist=np.array([(0.81, 0.19)], np.float32))   # c re-imported: overlap 0.9
    index._chroma_stale.add("c")
    assert index._candidates_by_fresco("q", 3) == ["a", "c", "d"]
    del index.cues["a"]                      # a removed: its row goes, the last row takes its place
    index._chroma_stale.add("a")
    assert index._candidates_by_fresco("q", 4) == ["c", "d", "b"]
    assert sorted(index._chroma_names) == ["b", "c", "d", "q"] and len(index._chroma_rows()[1]) == 4
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 0.0)
    assert index._candidates_by_fresco("q", 3) is None
    monkeypatch.setattr(fresco, "FRESCO_WEIGHT", 4.0)
    sigs["q"] = None
    assert index._candidates_by_fresco("q", 3) is None
