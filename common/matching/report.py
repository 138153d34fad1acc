"""The matcher's evaluation report: Table 5.3-style rates, PR curves, top-k recall, cross-wall test.

:func:`evaluate_matching` runs the whole evaluation of thesis §5.8 on a training wall (grouped
10-fold cross-validation per classifier and feature subset), a second wall (train on one, test on
the other, §5.8.5) and optionally a colour-only real set (DAFNE), and writes CSV numbers and PNG
plots into one directory. ``tessera evaluate`` is its command-line shell.
"""

from __future__ import annotations

import csv
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from common.features.boundary import boundary_channel_names
from common.matching.evaluation import (bootstrap_interval, confusion_rates, grouped_cross_validation,
                                        pair_precision_recall, precision_recall, rank_all_pairs,
                                        settle_docking_hubness, top_k_counts, top_k_recall)
from common.matching.index import MatchIndex
from common.matching import online
from common.matching.online import (docking_calibration, ribbon_calibration, stage_combination, train_model, wall_cues,
                                    with_combination)
from common.matching.pairs import training_set
from common.matching.mutual import mutual_pair_scores
from common.matching.ribbon import ribbon_rankings

log = logging.getLogger("tessera.matching.report")

TABLE_SUBSETS = ("colour", "curvature", "normal", "erosion", "thickness", "per-match", "all")
KS = (1, 3, 5, 10, 20)
#: Coverage of the bootstrap intervals ``evaluate_collection`` gives beside its figures.
INTERVAL_LEVEL = 0.9


def write_csv(rows: list[dict], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = list(rows[0]) if rows else []
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})


def _plot_pr(curves: dict, path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.2, 4.2), dpi=90)
    for label, (p, r, ap) in curves.items():
        ax.plot(r, p, lw=1.3, label=f"{label} (AP {ap:.2f})")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _plot_topk(series: dict, path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.2, 4.0), dpi=90)
    for label, rec in series.items():
        ks = sorted(rec)
        ax.plot(ks, [rec[k] for k in ks], marker="o", lw=1.3, label=label)
    ax.set_xlabel("k (proposals shown per fragment)")
    ax.set_ylabel("share of true neighbours in top k")
    ax.set_ylim(0, 1.02)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _run_points(contour_mm: np.ndarray, centre_mm: float, half_mm: float) -> np.ndarray:
    """Contour points within ``half_mm`` of arc ``centre_mm`` (wrapped), in contour order."""
    closed = np.vstack([contour_mm, contour_mm[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(closed, axis=0).T))])[:-1]
    length = arc[-1] + np.hypot(*(contour_mm[0] - contour_mm[-1]))
    off = (arc - centre_mm + length / 2) % length - length / 2
    sel = np.flatnonzero(np.abs(off) <= half_mm)
    return contour_mm[sel[np.argsort(off[sel])]]


def _plot_ribbon_examples(wall, tables, index, model, path: Path, n: int = 4) -> None:
    """The fragments of the test wall whose first proposal is a true neighbour (longest shared
    crack first), each beside that neighbour, with the ribbon's best 20 mm run drawn on both."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common.matching.ribbon import RIBBON_WINDOW_MM

    shared = {frozenset(p[:2]): p[2] for p in wall.adjacency}
    images = {f.id: f.rgbn for f in wall.fragments}
    hits, seen = [], set()
    for f in index._order:
        if not index.uses_ribbon(f, model):
            continue
        best = index.rank(index.cues[f], [o for o in index._order if o != f], model)[:1]
        pair = frozenset((f, best[0].other)) if best else None
        if pair in shared and pair not in seen:   # each pair once, from the side that found it first
            seen.add(pair)
            hits.append((shared[pair], f, best[0]))
    hits = sorted(hits, key=lambda h: -h[0])[:n]
    if not hits:
        return
    fig, axes = plt.subplots(len(hits), 2, figsize=(6.4, 2.9 * len(hits)), dpi=80, squeeze=False)
    for row, (length, f, c) in enumerate(hits):
        for ax, fid, centre in ((axes[row, 0], f, c.ribbon_arc_mm[0]), (axes[row, 1], c.other, c.ribbon_arc_mm[1])):
            img = images[fid]
            px = img.pixel_mm
            rgb = np.clip(img.albedo, 0, 1) ** (1 / 2.2)
            ax.imshow(np.where(img.mask[..., None], rgb, 1.0), extent=(0, img.shape[1] * px, img.shape[0] * px, 0))
            run = _run_points(tables[fid].contour_mm, centre, RIBBON_WINDOW_MM / 2)
            ax.plot(run[:, 0], run[:, 1], color="#e6007e", lw=3)
            ax.set_title(f"{fid}" + (f"\nproposal 1: p = {c.probability:.2f}, shares {length:.0f} mm" if fid == c.other
                                      else "\nquery"), fontsize=7)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("Colour ribbon: best 20 mm run (magenta) of true neighbours ranked first", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _index_of(tables, cues, *, single_fresco: bool = False, fresco_weight: float | None = None):
    idx = MatchIndex(single_fresco=single_fresco, fresco_weight=fresco_weight)
    for fid, c in cues.items():
        idx.add(c, tables[fid].contour_mm, tables[fid].boundary_profile)
    return idx


def evaluate_matching(out_dir, *, n_fragments: int = 150, seed: int = 11, test_seed: int = 12, dpi: float = 100.0,
                      folds: int = 10, classifiers=("logistic", "tree", "forest", "svm"), subsets=TABLE_SUBSETS,
                      negatives_per_positive: float = 10.0, dafne: str | None = None, progress=None) -> dict:
    """Run the evaluation of §5.8 and write its CSV and PNG files into ``out_dir``.

    Parameters
    ----------
    out_dir : path
        Where ``table_5_3.csv``, ``pr_subsets.png``, ``pr_classifiers.png``, ``crosswall.csv``,
        ``topk.csv``, ``topk.png``, ``pr_pairs.png``, ``ribbon_examples.png`` (and ``dafne_*.csv|png``) go.
    n_fragments, seed, test_seed, dpi : synthetic walls (training wall ``seed``, test wall ``test_seed``)
    folds : cross-validation folds, grouped by fragment pair
    classifiers : classifier kinds compared on all features (logistic also on every subset)
    subsets : feature subsets for the logistic regression (Table 5.3 rows)
    negatives_per_positive : sampled non-matches per match (class weights balance the rest)
    dafne : path of a DAFNE set (colour and contour only), optional

    Returns
    -------
    dict with the numbers written (``table``, ``crosswall``, ``topk``, ``dafne``).
    """
    from common.synth.wall import generate_wall

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda f, t: None)
    t0 = time.time()
    say(0.0, f"training wall: {n_fragments} fragments, seed {seed}")
    wall = generate_wall(n_fragments, seed=seed, dpi=dpi)
    tables, cues, poses = wall_cues(wall, progress=lambda f, t: say(0.1 * f, t))
    ts = training_set(cues, poses, wall.adjacency, negatives_per_positive=negatives_per_positive, seed=seed)
    log.info("training set: %d rows, %d matches, ratio %.1f", len(ts), ts.y.sum(), ts.negatives_per_positive)

    # Table 5.3: rates per subset (logistic) and per classifier (all features)
    table, pr_sub, pr_clf = [], {}, {}
    runs = [("logistic", s) for s in subsets] + [(k, "all") for k in classifiers if k != "logistic"]
    for i, (kind, subset) in enumerate(runs):
        say(0.15 + 0.45 * i / len(runs), f"cross-validation {kind} / {subset}")
        r = grouped_cross_validation(ts.x, ts.y, ts.groups, ts.columns, kind=kind, subset=subset, n_splits=folds)
        table.append({"wall": wall.id, "classifier": kind, "subset": subset, "tpr": r.rates["tpr"],
                      "tnr": r.rates["tnr"], "fpr": r.rates["fpr"], "fnr": r.rates["fnr"], "ap": r.ap,
                      "matches": r.rates["positives"], "non_matches": r.rates["negatives"], "folds": r.folds})
        pr = precision_recall(r.y, r.scores)
        (pr_sub if kind == "logistic" else pr_clf)[subset if kind == "logistic" else kind] = (pr["precision"], pr["recall"], r.ap)
        if kind == "logistic" and subset == "all":
            pr_clf["logistic"] = (pr["precision"], pr["recall"], r.ap)
    write_csv(table, out / "table_5_3.csv")
    _plot_pr(pr_sub, out / "pr_subsets.png", f"Patch pairs, logistic regression by feature subset\n{wall.id}, {folds}-fold grouped CV")
    _plot_pr(pr_clf, out / "pr_classifiers.png", f"Patch pairs, all features, by classifier\n{wall.id}, {folds}-fold grouped CV")

    # train on one wall, test on another (§5.8.5)
    say(0.6, f"test wall: {n_fragments} fragments, seed {test_seed}")
    wall2 = generate_wall(n_fragments, seed=test_seed, dpi=dpi)
    tables2, cues2, poses2 = wall_cues(wall2, progress=lambda f, t: say(0.6 + 0.1 * f, t))
    ts2 = training_set(cues2, poses2, wall2.adjacency, negatives_per_positive=negatives_per_positive, seed=test_seed)
    # the station's staged ranking, docking included: its calibration fitted on the training wall
    say(0.66, "docking calibration on the training wall")
    model, pipe = train_model(ts, info={"trained_on": wall.id}, ribbon=ribbon_calibration(tables, wall.adjacency),
                              docking=_docking_of(wall, tables, seed))
    # stage 3's combination of the stage scores, learned on the training wall's own ranking: the station's
    # stage 3 when online.STAGE_COMBINATION is set, else measured beside the fixed rules
    say(0.68, "stage combination on the training wall")
    combination = stage_combination(tables, cues, wall.adjacency, model)
    model = with_combination(model, combination if online.STAGE_COMBINATION else None)
    pred = pipe.predict(ts2.x)
    rates = confusion_rates(ts2.y, pred)
    ap2 = precision_recall(ts2.y, model.probability(ts2.x))["ap"]
    crosswall = [{"train_wall": wall.id, "test_wall": wall2.id, "classifier": "logistic", "subset": "all",
                  "tpr": rates["tpr"], "tnr": rates["tnr"], "ap": ap2, "matches": rates["positives"],
                  "non_matches": rates["negatives"]}]
    write_csv(crosswall, out / "crosswall.csv")

    # top-k recall: every fragment pair of the test wall ranked as the staged matcher ranks them
    say(0.72, "ranking every fragment pair of the test wall")
    idx2 = _index_of(tables2, cues2)
    scores = rank_all_pairs(idx2, model, progress=lambda f, t: say(0.72 + 0.15 * f, t))
    topk = {"synthetic (train seed %d, test seed %d)" % (seed, test_seed): top_k_recall(scores, wall2.adjacency, KS)}
    # for comparison: stage 3 by the other combination (the same index, so the same dockings)
    other, name = _other_combination(model, combination)
    if other is not None:
        topk[f"synthetic, stage 3 by {name}"] = top_k_recall(rank_all_pairs(idx2, other), wall2.adjacency, KS)
    # for comparison: without the docking (stages 2 + 2½), stage 2 alone, and the ribbon alone on every pair
    undocked = rank_all_pairs(_index_of(tables2, cues2), replace(model, docking=None, combination=None))
    topk["synthetic, without docking (stages 2 + ribbon)"] = top_k_recall(undocked, wall2.adjacency, KS)
    plain = rank_all_pairs(_index_of(tables2, cues2), replace(model, ribbon=None, docking=None, combination=None))
    topk["synthetic, stage 2 only (patch classifier)"] = top_k_recall(plain, wall2.adjacency, KS)
    # each fragment's own ribbon list, pooled as the station pools (scores from two sides differ in scale)
    alone = mutual_pair_scores(ribbon_rankings({f: t.boundary_profile for f, t in tables2.items()},
                                               boundary_channel_names()))
    topk["synthetic, colour ribbon alone (every pair)"] = top_k_recall(alone, wall2.adjacency, KS)
    _plot_ribbon_examples(wall2, tables2, idx2, model, out / "ribbon_examples.png")
    ppr = pair_precision_recall(scores, wall2.adjacency)
    pair_curves = {"synthetic test wall": (ppr["precision"], ppr["recall"], ppr["ap"])}
    n_random = len(idx2) - 1
    topk["random ranking (expected)"] = {k: min(1.0, k / max(n_random, 1)) for k in KS}

    result = {"table": table, "crosswall": crosswall, "topk": topk, "pair_ap": {"synthetic": ppr["ap"]}}
    if dafne:
        say(0.88, "DAFNE (colour and contour only)")
        result["dafne"] = _evaluate_dafne(dafne, out, folds=folds, negatives_per_positive=negatives_per_positive,
                                          topk=topk, pair_curves=pair_curves, combination=combination)
        result["pair_ap"]["dafne"] = result["dafne"]["pair_ap"]
    write_csv([{"ranking": name, **{f"top{k}": v for k, v in rec.items()}} for name, rec in topk.items()],
              out / "topk.csv")
    _plot_topk(topk, out / "topk.png", "Top-k recall of true neighbours")
    _plot_pr(pair_curves, out / "pr_pairs.png", "Fragment pairs ranked by the matcher")
    log.info("evaluation done in %.0f s", time.time() - t0)
    say(1.0, "done")
    return result


def _other_combination(model, combination):
    """The model with stage 3's other combination (learned ↔ fixed rules) and its name, for a row beside;
    (None, "") when there is no learned one."""
    if model.combination is not None:
        return replace(model, combination=None), "fixed rules (no learned combination)"
    if combination is None or model.docking is None:
        return None, ""
    return with_combination(model, combination), "the learned combination (fitted on the synthetic training wall)"


def _docking_of(wall, tables, seed):
    """The docking calibration (stage 3) of a model trained on ``wall``: fitted on its own true pairs
    and random others (:func:`~common.matching.online.docking_calibration`, as the bootstrap model
    fits it on a realistic wall), with the outlines the features give."""
    return docking_calibration(wall, contours={f: t.contour_mm for f, t in tables.items()
                                               if t.contour_mm is not None and len(t.contour_mm) >= 3},
                               negatives_per_positive=2.0, seed=seed)


def _evaluate_dafne(path, out: Path, *, folds, negatives_per_positive, topk, pair_curves, combination=None) -> dict:
    """DAFNE: grouped CV on colour+curvature cues; top-k by training on one half of the fresco and
    ranking the other half (the halves split by the fragments' x position), both ways. ``combination``:
    stage 3's learned combination (fitted on the synthetic training wall; its terms are calibrated
    logits, so it carries over to each half's model), used as the main ranking when
    ``online.STAGE_COMBINATION`` is set and beside it otherwise."""
    from common.synth.dafne import import_dafne
    from common.synth.wall import Wall

    wall = import_dafne(path)
    tables, cues, poses = wall_cues(wall)
    placed = {f.id: f.pose for f in wall.fragments if f.pose is not None}
    ts = training_set(cues, placed, wall.adjacency, negatives_per_positive=negatives_per_positive, seed=0)
    rows = []
    for subset in ("colour", "curvature", "per-match", "all"):
        r = grouped_cross_validation(ts.x, ts.y, ts.groups, ts.columns, subset=subset, n_splits=folds)
        rows.append({"wall": wall.id, "classifier": "logistic", "subset": subset, "tpr": r.rates["tpr"],
                     "tnr": r.rates["tnr"], "ap": r.ap, "matches": r.rates["positives"],
                     "non_matches": r.rates["negatives"]})
    write_csv(rows, out / "dafne_table.csv")
    xs = {fid: p[1] for fid, p in placed.items()}
    cut = float(np.median(list(xs.values())))
    halves = [{f for f in xs if xs[f] < cut}, {f for f in xs if xs[f] >= cut}]
    spurious = {f.id for f in wall.fragments if f.pose is None}
    all_scores, other_scores, undocked_scores, plain_scores, alone_scores = {}, {}, {}, {}, {}
    other_name = ""
    for h in range(2):
        # sorted: the rarity reference and the fits follow the fragments' order, which must not follow string hashing
        train_ids, test_ids = sorted(halves[h]), sorted(halves[1 - h] | spurious)
        adj_tr = [p for p in wall.adjacency if p[0] in halves[h] and p[1] in halves[h]]
        ts_h = training_set({f: cues[f] for f in train_ids}, placed, adj_tr,
                            negatives_per_positive=negatives_per_positive, seed=h)
        half = Wall(f"{wall.id}-half{h}", [f for f in wall.fragments if f.id in halves[h]], adj_tr, {}, 0.0, 0.0,
                    wall.dpi)
        model, _ = train_model(ts_h, ribbon=ribbon_calibration({f: tables[f] for f in train_ids}, adj_tr),
                               docking=_docking_of(half, {f: tables[f] for f in train_ids}, h))
        if online.STAGE_COMBINATION and model.docking is not None:
            model = with_combination(model, combination)
        idx = _index_of({f: tables[f] for f in test_ids}, {f: cues[f] for f in test_ids})
        all_scores.update(rank_all_pairs(idx, model))
        other, other_name = _other_combination(model, combination)
        if other is not None:
            other_scores.update(rank_all_pairs(idx, other))
        undocked_scores.update(rank_all_pairs(_index_of({f: tables[f] for f in test_ids},
                                                        {f: cues[f] for f in test_ids}),
                                              replace(model, docking=None, combination=None)))
        plain_scores.update(rank_all_pairs(_index_of({f: tables[f] for f in test_ids}, {f: cues[f] for f in test_ids}),
                                           replace(model, ribbon=None, docking=None, combination=None)))
        alone_scores.update(mutual_pair_scores(ribbon_rankings({f: tables[f].boundary_profile for f in test_ids},
                                                               boundary_channel_names())))
    adj_te = [p for p in wall.adjacency if (p[0] in halves[0]) == (p[1] in halves[0])]
    rec = top_k_recall(all_scores, adj_te, KS)
    topk["DAFNE (train one half, rank the other)"] = rec
    if other_scores:
        topk[f"DAFNE, stage 3 by {other_name}"] = top_k_recall(other_scores, adj_te, KS)
    topk["DAFNE, without docking (stages 2 + ribbon)"] = top_k_recall(undocked_scores, adj_te, KS)
    topk["DAFNE, stage 2 only"] = top_k_recall(plain_scores, adj_te, KS)
    topk["DAFNE, colour ribbon alone"] = top_k_recall(alone_scores, adj_te, KS)
    ppr = pair_precision_recall(all_scores, adj_te)
    pair_curves["DAFNE halves"] = (ppr["precision"], ppr["recall"], ppr["ap"])
    return {"table": rows, "topk": rec, "pair_ap": ppr["ap"]}


def evaluate_collection(path, *, dpi: float = 150.0, model=None, out_dir=None, near_px: float = 48.0,
                        min_run_px: float = 100.0, adjacency=None, single_fresco: bool = False,
                        fresco_weight: float | None = None, progress=None) -> dict:
    """Evaluate the matcher on a real, placed collection (``repair-dev`` layout) with a given model.

    Nothing is fitted on the collection: the fragments are imported as colour-only fragments
    (:func:`common.matching.collection.collection_wall`), their features extracted as the station
    does, and every fragment ranked by the station's staged matcher
    (:meth:`~common.matching.index.MatchIndex.rank`, stages 2, 2½ and 3) — once against every other
    fragment of the collection (pooled) and once against the other fragments of its own object.
    Neighbours: placed outlines within ``near_px`` along ``min_run_px`` image pixels
    (:func:`~common.matching.collection.collection_wall`; the defaults are RePAIR's), or the pairs
    ``adjacency`` gives (``[(a, b, shared length), ...]`` as ``Wall.adjacency``: a variant of a collection
    — the same pieces scanned otherwise, their masks a pixel different — counted against the original's
    pairs, so that only the matcher's inputs differ; ``tests/bench/bench_scan_variants.py``).
    ``single_fresco``: rank as a station set for a collection of one fresco does (:class:`MatchIndex`);
    ``fresco_weight``: the same-fresco ratio's weight as a station set with ``fresco_weight`` (None: the default).

    A fragment's list is in the station's order: its pairs by mutual proximity of the two
    fragments' rankings (:mod:`common.matching.mutual`; the station's proposal store orders them so).

    Returns
    -------
    dict
        ``pooled_topk`` {1, 5, 10} (share of true neighbour links among a fragment's top k, pooled),
        ``within_object_recall`` {1, 3} (hit rate, ../shared/data/README.md) with
        ``within_object_random`` and ``within_object_incidence`` beside it, ``pair_ap`` (pooled
        pairs ranked by mutual proximity); the same by each query's own order and probability
        (before mutual proximity: ``within_object_recall_by_query``, ``pooled_topk_by_probability``
        — a pair's larger probability —, ``pair_ap_by_probability``), ``pose_accuracy`` (share of all true neighbour pairs whose
        proposed relative pose is within 5° and 5 mm), ``pose_offered`` (the same, counting a pair
        right when its proposed pose or one of its alternatives is: what a person stepping through the
        review page's candidate poses finds), ``pose_reachable`` (the same, counting a pair right when any of
        the docking's candidates is, :meth:`~common.matching.index.MatchIndex.candidate_poses`: the ceiling of
        any chooser among them, so a shortfall below it is the chooser's and above it the search's),
        ``pose_errors`` (each with ``right_candidate``, the first right candidate's place in the search's
        order, or None), ``n_fragments``,
        ``n_true_pairs``, ``skipped`` (what reading the collection left out, and why:
        :func:`~common.matching.collection.collection_wall`'s ``params['skipped']``), ``intervals`` (90 % bootstrap intervals of the pooled top-k, the within-object
        recall and the three pose shares, :func:`~common.matching.evaluation.bootstrap_interval` over the
        fragments or pairs counted), ``dpi``, ``model``, ``single_fresco``, ``seconds`` (wall) and ``cpu_seconds``.
    """
    from common.matching.alignment import pose_matrix
    from common.matching.collection import collection_wall, relative_pose_error, within_object_recall
    from common.matching.docking import docking_score_at
    from common.matching.online import bootstrap_model

    say = progress or (lambda f, t: None)
    t0, c0 = time.time(), time.process_time()
    say(0.0, f"importing {path}")
    wall = collection_wall(path, dpi=dpi, near_px=near_px, min_run_px=min_run_px)
    if adjacency is not None:
        known = {f.id for f in wall.fragments}
        unknown = sorted({x for a, b, *_ in adjacency for x in (a, b)} - known)
        if unknown:
            raise ValueError(f"adjacency names fragments not in {path}: {', '.join(unknown[:5])}")
        wall = replace(wall, adjacency=list(adjacency))
    if model is None:
        say(0.05, "training the default bootstrap model (synthetic walls only)")
        model = bootstrap_model()
    tables, cues, poses = wall_cues(wall, progress=lambda f, t: say(0.1 + 0.3 * f, t))
    index = _index_of(tables, cues, single_fresco=single_fresco, fresco_weight=fresco_weight)
    obj = {f.id: f.notes.get("object") for f in wall.fragments}
    ids = list(index._order)
    index.refresh_hubness(ids, model, n_candidates=100)
    say(0.4, "docking every fragment's best (its docking hubness, as the station has it)")
    settled = settle_docking_hubness(index, model, ids, lambda f: [o for o in ids if o != f])
    pooled_max, pooled_lists, within_query, proposed = {}, {}, {}, {}
    for i, f in enumerate(ids):
        ranked = index.rank(index.cues[f], [o for o in ids if o != f], model)
        pooled_lists[f] = [c.other for c in ranked]
        for c in ranked:
            key = tuple(sorted((f, c.other)))
            pooled_max[key] = max(pooled_max.get(key, 0.0), c.probability)
        mates = [o for o in ids if o != f and obj[o] == obj[f]]
        if mates:
            ranked_w = index.rank(index.cues[f], mates, model, dock_candidates=len(mates))
            # ranking among its mates set the fragment's docking hubness from them: the later queries are
            # corrected by the one the station has (its docked best among all)
            if f in settled:
                index.dock_hubness[f] = settled[f]
            within_query[f] = [c.other for c in ranked_w]
            for c in ranked_w:
                if c.alignment is not None:
                    proposed[(f, c.other)] = c.alignment
        say(0.4 + 0.55 * (i + 1) / len(ids), f"ranked {i + 1}/{len(ids)} fragments")
    # the station's order of a fragment's proposals: mutual proximity of both fragments' rankings
    pooled = mutual_pair_scores(pooled_lists)
    mp_within = mutual_pair_scores(within_query)
    within = {f: sorted(order, key=lambda o: -mp_within[tuple(sorted((f, o)))]) for f, order in within_query.items()}
    truth: dict = {}
    for a, b, *_ in wall.adjacency:
        truth.setdefault(a, set()).add(b)
        truth.setdefault(b, set()).add(a)
    wo = within_object_recall(within, truth, ks=(1, 3))
    wo_query = within_object_recall(within_query, truth, ks=(1, 3))
    errors = []
    for a, b, *_ in wall.adjacency:
        al = proposed.get((a, b))
        # the docking's geometric score at the true pose: below the best pose's means the score, not
        # the search, misses the true pose
        rel = np.linalg.inv(pose_matrix(*poses[a])) @ pose_matrix(*poses[b])
        at_truth = docking_score_at(tables[a].contour_mm, tables[b].contour_mm,
                                    (float(np.degrees(np.arctan2(rel[1, 0], rel[0, 0]))), rel[0, 2], rel[1, 2]))
        centre = tables[b].contour_mm.mean(axis=0)

        def error(q):   # (angle deg, shift mm) of pose q of b in a's frame from the truth
            return relative_pose_error(poses[a], poses[b], q, centre)

        # the ceiling of any chooser: the first of the docking's candidates (in its search order) that is right
        reachable = next((k for k, d in enumerate(index.candidate_poses(a, b))
                          if max(error((d.angle_deg, d.tx_mm, d.ty_mm))) <= 5), None)
        if al is None:
            errors.append({"a": a, "b": b, "angle_deg": None, "shift_mm": None, "score_at_truth": at_truth,
                           "right_candidate": reachable})
            continue

        # the proposed pose and its alternatives (what the review page steps through); right_pose_offered
        # is the first within 5 deg and 5 mm: 0 = the proposed pose, None = none of them
        offered = [error(q) for q in [(al.angle_deg, al.tx_mm, al.ty_mm), *al.alternatives]]
        right = [k for k, err in enumerate(offered) if max(err) <= 5]
        e = offered[0]
        best, best_right = float("nan"), None
        if index.docked(a, b):
            d = index.docking(a, b)    # the geometric search's best pose
            best, best_right = d.score, max(error((d.angle_deg, d.tx_mm, d.ty_mm))) <= 5
        errors.append({"a": a, "b": b, "angle_deg": e[0], "shift_mm": e[1], "score_at_truth": at_truth,
                       "score_best": best, "best_right": best_right, "right_pose_offered": right[0] if right else None,
                       "right_candidate": reachable})
    pose_right = [int(e["angle_deg"] is not None and e["angle_deg"] <= 5 and e["shift_mm"] <= 5) for e in errors]
    pose_offered = [int(e.get("right_pose_offered") is not None) for e in errors]
    pose_reachable = [int(e["right_candidate"] is not None) for e in errors]
    ok, offered_ok = sum(pose_right), sum(pose_offered)
    ppr = pair_precision_recall(pooled, wall.adjacency)
    ppr_max = pair_precision_recall(pooled_max, wall.adjacency)
    result = {
        "collection": str(path), "dpi": float(dpi), "model": model.version, "single_fresco": bool(single_fresco),
        "fresco_weight": float(index._ratio_weight()),
        "pooled_topk": top_k_recall(pooled, wall.adjacency, (1, 5, 10)),
        "pooled_topk_by_probability": top_k_recall(pooled_max, wall.adjacency, (1, 5, 10)),
        "within_object_recall": wo["recall"], "within_object_random": wo["random"],
        "within_object_recall_by_query": wo_query["recall"],
        "within_object_incidence": wo["incidence"], "within_object_fragments": wo["n"],
        "pair_ap": float(ppr["ap"]), "pair_ap_by_probability": float(ppr_max["ap"]), "pose_accuracy": ok / len(errors) if errors else float("nan"),
        "pose_offered": offered_ok / len(errors) if errors else float("nan"),
        "pose_reachable": sum(pose_reachable) / len(errors) if errors else float("nan"),
        # the search's best pose always scores at least the truth's (up to its grid): what says the
        # score, not the search, misses the truth is a wrong best pose scoring above the truth
        "wrong_pose_scores_above_truth": sum(1 for e in errors if e.get("best_right") is False
                                             and e["score_best"] > e["score_at_truth"]),
        "pose_errors": errors, "n_fragments": len(wall.fragments), "n_true_pairs": len(wall.adjacency),
        "skipped": list(wall.params.get("skipped", [])),   # what the reading left out, and why
        # how far each figure may move on another collection of this kind: resampling the fragments
        # (pairs for the poses) it was counted on
        "intervals": {
            "level": INTERVAL_LEVEL,
            "pooled_topk": {k: bootstrap_interval(h, n, level=INTERVAL_LEVEL)
                            for k, (h, n) in top_k_counts(pooled, wall.adjacency, (1, 5, 10)).items()},
            "within_object_recall": {k: bootstrap_interval(h, level=INTERVAL_LEVEL) for k, h in wo["hits"].items()},
            "pose_accuracy": bootstrap_interval(pose_right, level=INTERVAL_LEVEL),
            "pose_offered": bootstrap_interval(pose_offered, level=INTERVAL_LEVEL),
            "pose_reachable": bootstrap_interval(pose_reachable, level=INTERVAL_LEVEL),
        },
        "seconds": time.time() - t0, "cpu_seconds": time.process_time() - c0,
    }
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        _plot_collection_examples(wall, tables, within, truth, proposed, out / "collection_examples.png")
    say(1.0, "done")
    return result


def _plot_collection_examples(wall, tables, within, truth, proposed, path: Path, n: int = 6) -> None:
    """Each fragment's first proposal within its object drawn docked at the proposed pose: hits
    (a true neighbour) in green, misses in red, the true neighbour's outline at its true pose dashed."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    poses = {f.id: f.pose for f in wall.fragments}
    items = [(f, r[0]) for f, r in sorted(within.items()) if r and truth.get(f)]
    hits = [x for x in items if x[1] in truth[x[0]]][: n // 2]
    misses = [x for x in items if x[1] not in truth[x[0]]][: n - len(hits)]
    chosen = hits + misses
    if not chosen:
        return
    cols = 3
    rows = int(np.ceil(len(chosen) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.3 * cols, 3.3 * rows), dpi=80, squeeze=False)

    from common.matching.alignment import pose_matrix

    for ax, (f, o) in zip(axes.ravel(), chosen):
        ca = tables[f].contour_mm
        ax.fill(ca[:, 0], ca[:, 1], color="#bbbbbb")
        al = proposed.get((f, o))
        hit = o in truth[f]
        if al is not None:
            cb = tables[o].contour_mm @ al.matrix[:2, :2].T + al.matrix[:2, 2]
            ax.fill(cb[:, 0], cb[:, 1], color="#2ca02c" if hit else "#d62728", alpha=0.6)
        for nb in sorted(truth[f])[:2]:
            rel = np.linalg.inv(pose_matrix(*poses[f])) @ pose_matrix(*poses[nb])
            ct = tables[nb].contour_mm @ rel[:2, :2].T + rel[:2, 2]
            ax.plot(np.r_[ct[:, 0], ct[:1, 0]], np.r_[ct[:, 1], ct[:1, 1]], "k--", lw=0.8)
        ax.set_title(f"{f[:9]}: 1st = {o[:9]}\n{'true neighbour' if hit else 'miss'}", fontsize=7)
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[len(chosen):]:
        ax.axis("off")
    fig.suptitle("Within-object first proposals, docked (filled) vs a true neighbour at its true pose (dashed)",
                 fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
