"""Evaluation of the matcher (thesis §5.8, Table 5.3, §5.8.5).

* :func:`grouped_cross_validation` — k-fold cross-validation with scikit-learn ``GroupKFold`` on the
  fragment-pair groups, so the patch pairs of one fragment pair never sit in both the training and
  the test fold; returns out-of-fold scores and predictions.
* :func:`confusion_rates` — true/false positive/negative rates (the numbers of Table 5.3).
* :func:`precision_recall` — precision–recall curve and average precision.
* :func:`rank_all_pairs` and :func:`top_k_recall` — the conservator's view: for each fragment, the
  share of its true neighbours among its ``k`` most probable proposals (:func:`top_k_counts`: the
  same counted per fragment).
* :func:`bootstrap_interval` — how far such a share may move on another collection of the same kind:
  a percentile bootstrap over the fragments (or pairs) it was counted on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sklearn.metrics import average_precision_score, precision_recall_curve
from sklearn.model_selection import GroupKFold

from common.matching.classifiers import make_classifier, match_scores, subset_columns


def confusion_rates(y_true: np.ndarray, y_pred: np.ndarray) -> dict:
    """True-positive, true-negative, false-positive and false-negative rates.

    ``tpr`` = matches recognised / matches, ``tnr`` = non-matches rejected / non-matches; the
    rates (not counts) are what Table 5.3 reports, so they do not depend on the sampling ratio.
    """
    y_true = np.asarray(y_true).astype(bool)
    y_pred = np.asarray(y_pred).astype(bool)
    if y_true.shape != y_pred.shape:
        raise ValueError(f"y_true {y_true.shape} and y_pred {y_pred.shape} differ in shape")
    pos, neg = y_true.sum(), (~y_true).sum()
    tp, tn = (y_true & y_pred).sum(), (~y_true & ~y_pred).sum()
    tpr = tp / pos if pos else np.nan
    tnr = tn / neg if neg else np.nan
    return {"tpr": float(tpr), "tnr": float(tnr), "fnr": float(1 - tpr), "fpr": float(1 - tnr),
            "positives": int(pos), "negatives": int(neg)}


def precision_recall(y_true: np.ndarray, scores: np.ndarray) -> dict:
    """Precision–recall curve and average precision (scikit-learn) of ranking scores."""
    y_true = np.asarray(y_true).astype(int)
    p, r, _ = precision_recall_curve(y_true, scores)
    return {"precision": p, "recall": r, "ap": float(average_precision_score(y_true, scores)),
            "prevalence": float(y_true.mean())}


@dataclass
class CVResult:
    """Out-of-fold results of one classifier on one feature subset."""

    kind: str
    subset: str
    scores: np.ndarray      # out-of-fold ranking score per row
    predicted: np.ndarray   # out-of-fold 0/1 prediction per row
    y: np.ndarray
    rates: dict
    ap: float
    folds: int


def grouped_cross_validation(x: np.ndarray, y: np.ndarray, groups: np.ndarray, columns: list[str], *,
                             kind: str = "logistic", subset: str | list[str] = "all", n_splits: int = 10,
                             progress=None) -> CVResult:
    """k-fold cross-validation grouped by fragment pair (thesis §5.8).

    Parameters
    ----------
    x : (K, D) correspondence rows; y : (K,) labels; groups : (K,) fragment-pair ids
    columns : list of str
        Column names of ``x`` (for the subset).
    kind : str
        Classifier (:data:`~common.matching.classifiers.CLASSIFIERS`).
    subset : str or list of str
        Feature subset name(s) (:data:`~common.matching.classifiers.SUBSETS`).
    n_splits : int
        Folds (10 in the thesis); reduced to the number of groups if there are fewer.
    progress : callable(fraction, text), optional

    Returns
    -------
    CVResult
    """
    x = np.asarray(x, float)
    y = np.asarray(y, int)
    groups = np.asarray(groups)
    if x.ndim != 2 or len(x) != len(y) or len(y) != len(groups):
        raise ValueError(f"x {x.shape}, y {y.shape} and groups {groups.shape} must have matching rows")
    if set(np.unique(y)) != {0, 1}:
        raise ValueError("y must contain both classes (0 = non-match, 1 = match)")
    cols = subset_columns(columns, subset)
    xs = x[:, cols]
    n_groups = len(np.unique(groups))
    folds = min(n_splits, n_groups)
    if folds < 2:
        raise ValueError(f"need at least two fragment pairs (groups) for cross-validation, got {n_groups}")
    scores = np.zeros(len(y))
    pred = np.zeros(len(y), int)
    for f, (tr, te) in enumerate(GroupKFold(n_splits=folds).split(xs, y, groups)):
        if len(np.unique(y[tr])) < 2:
            raise ValueError("a training fold lacks one class; use fewer folds or more fragment pairs")
        clf = make_classifier(kind).fit(xs[tr], y[tr])
        scores[te] = match_scores(clf, xs[te])
        pred[te] = clf.predict(xs[te])
        if progress:
            progress((f + 1) / folds, f"{kind}/{subset}: fold {f + 1}/{folds}")
    rates = confusion_rates(y, pred)
    ap = float(average_precision_score(y, scores))
    return CVResult(kind, subset if isinstance(subset, str) else "+".join(subset), scores, pred, y, rates, ap, folds)


def rank_all_pairs(index, model, *, n_candidates: int | None = None, pooling: str = "mutual",
                   progress=None) -> dict:
    """Score of every (candidate) fragment pair of an index under a model, pooled over both sides.

    Every fragment's hubness is estimated first, as the matcher service does when it proposes the
    fragment (:meth:`~common.matching.index.MatchIndex.refresh_hubness`, 100 pruned candidates), and its
    stage-3 docking hubness settled (:func:`settle_docking_hubness`), so no pair depends on the order.
    Each fragment's candidates (all other fragments, or its ``n_candidates`` pruned ones) are
    ranked as :meth:`~common.matching.index.MatchIndex.propose` ranks them: stage 2, then the
    colour ribbon on the best :data:`~common.matching.index.RIBBON_CANDIDATES` when the fragment
    has a boundary profile and the model a ribbon calibration
    (:meth:`~common.matching.index.MatchIndex.rank`; pairs it drops are not proposed).

    ``pooling``: how a pair's two rankings become one score — ``"mutual"`` (the station's:
    :func:`~common.matching.mutual.mutual_pair_scores` of both fragments' lists) or ``"max"`` (the
    larger of the two sides' probabilities; before mutual proximity). Returns ``{(a, b): score}``
    with ``a < b``.
    """
    from common.matching.mutual import mutual_pair_scores

    if pooling not in ("mutual", "max"):
        raise ValueError(f"pooling is 'mutual' or 'max', got {pooling!r}")
    lists, best = rank_lists(index, model, n_candidates=n_candidates, progress=progress)
    return mutual_pair_scores(lists) if pooling == "mutual" else best


def rank_lists(index, model, *, n_candidates: int | None = None, progress=None) -> tuple[dict, dict]:
    """Every fragment's ranking (:func:`rank_all_pairs`): ``(lists, best)`` with ``lists`` fragment →
    its candidates best first and ``best`` ``{(a, b): the larger of the two sides' probabilities}``."""
    order = list(index._order)
    # each fragment's hubness as the matcher service has it: from its own proposal (pruned candidates)
    index.refresh_hubness(order, model, n_candidates=100 if n_candidates is None else n_candidates)

    def others_of(f):
        return [o for o in order if o != f] if n_candidates is None else index.candidates(index.cues[f], model,
                                                                                        n_candidates)
    settle_docking_hubness(index, model, order, others_of)
    best: dict = {}
    lists: dict = {}
    for i, f in enumerate(order):
        ranked = index.rank(index.cues[f], others_of(f), model)
        lists[f] = [c.other for c in ranked]
        for c in ranked:
            key = tuple(sorted((c.fragment, c.other)))
            best[key] = max(best.get(key, 0.0), c.probability)
        if progress and (i % 10 == 0 or i == len(order) - 1):
            progress((i + 1) / len(order), f"ranked {i + 1}/{len(order)} fragments")
    return lists, best


def settle_docking_hubness(index, model, fragments, others_of) -> dict:
    """Every fragment's stage-3 docking hubness from its own docked best, before any ranking is kept; returns
    them (fragment → mm).

    The station scores a pair only once both fragments have been ranked, and its full re-rank sets every
    fragment's docking hubness before stage 3 (:meth:`~common.matching.index.MatchIndex.rank_again`). An
    evaluation that ranked the fragments one after another would correct a pair by the median instead of the
    hubness of every partner not ranked yet, an order-dependent mix the station never ranks by (on RePAIR it
    read pooled top-5 0.833 where the station gives 0.762; docs/matching.md, "Ranked as the station ranks").
    So each fragment is ranked once against ``others_of(fragment)`` (its best docked, its hubness set) first.
    """
    for f in fragments:
        index.rank(index.cues[f], others_of(f), model)
    return dict(index.dock_hubness)


def top_k_counts(pair_scores: dict, neighbours, ks=(1, 3, 5, 10), fragments=None) -> dict:
    """Per fragment, how many of its true neighbours are among its top-k ranked proposals.

    Parameters as :func:`top_k_recall`.

    Returns
    -------
    dict k → (hits, links): two integer arrays over the evaluated fragments (every fragment with a
    neighbour, in the order of ``fragments`` or of the neighbour list), the true neighbours in the
    fragment's top k and its true neighbours.
    """
    ranked: dict = {}
    for (a, b), s in pair_scores.items():
        ranked.setdefault(a, []).append((s, b))
        ranked.setdefault(b, []).append((s, a))
    for f in ranked:
        ranked[f].sort(key=lambda t: -t[0])
    truth: dict = {}
    for a, b, *_ in neighbours:
        truth.setdefault(str(a), set()).add(str(b))
        truth.setdefault(str(b), set()).add(str(a))
    frags = [f for f in (fragments or truth) if f in truth]
    links = np.array([len(truth[f]) for f in frags], int)
    return {int(k): (np.array([len(truth[f] & {o for _, o in ranked.get(f, [])[:k]}) for f in frags], int), links)
            for k in ks}


def top_k_recall(pair_scores: dict, neighbours, ks=(1, 3, 5, 10), fragments=None) -> dict:
    """Share of true neighbours that appear in their fragment's top-k ranked proposals.

    Parameters
    ----------
    pair_scores : dict (a, b) → score (unordered pairs; unscored pairs count as never proposed)
    neighbours : iterable of (a, b, ...) true neighbour pairs
    ks : k values
    fragments : ids to evaluate (default: every fragment with a neighbour)

    Returns
    -------
    dict k → recall, averaged over all (fragment, true neighbour) incidences, i.e. each true pair
    counted once from each side.
    """
    return {k: float(hits.sum() / links.sum()) if links.sum() else float("nan")
            for k, (hits, links) in top_k_counts(pair_scores, neighbours, ks, fragments).items()}


def bootstrap_interval(hits, totals=None, *, level: float = 0.9, draws: int = 4000,
                       seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of a share ``sum(hits) / sum(totals)`` counted over units.

    The units (fragments, or pairs) are drawn with replacement ``draws`` times and the share
    recomputed each time; the interval is the central ``level`` of those shares (Efron & Tibshirani,
    *An Introduction to the Bootstrap*, 1993, §13.3). It says how far a figure counted on a few
    dozen fragments may move on another collection of the same kind; the fragments of one object are
    not independent, so on a collection of few objects it is, if anything, too narrow. A share of
    exactly 0 or 1 has nothing to resample; there the exact binomial bound over the ``n`` units
    is given instead (Clopper & Pearson, Biometrika 26, 1934: ``((1 − level) / 2) ** (1 / n)`` below
    1, its complement above 0), so 24 hits of 24 read 0.88–1.00 at 90 %, not 1.00–1.00.

    Parameters
    ----------
    hits : per unit, what was found (1/0 for a hit rate, a count for links)
    totals : per unit, what could be found (default 1 each: a hit rate)
    level : coverage of the interval, in (0, 1)
    draws : bootstrap resamples
    seed : of the resampling, so a report is reproducible

    Returns
    -------
    (low, high); (nan, nan) without units.
    """
    hits = np.asarray(hits, float).ravel()
    totals = np.ones_like(hits) if totals is None else np.asarray(totals, float).ravel()
    if hits.shape != totals.shape:
        raise ValueError(f"hits and totals must have one value per unit, got {hits.size} and {totals.size}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if hits.size == 0 or totals.sum() <= 0:
        return float("nan"), float("nan")
    tail = (1.0 - level) / 2.0
    if np.all(hits >= totals):
        return float(tail ** (1.0 / hits.size)), 1.0
    if np.all(hits <= 0):
        return 0.0, float(1.0 - tail ** (1.0 / hits.size))
    pick = np.random.default_rng(seed).integers(0, hits.size, (int(draws), hits.size))
    found, possible = hits[pick].sum(axis=1), totals[pick].sum(axis=1)
    shares = found[possible > 0] / possible[possible > 0]
    low, high = np.quantile(shares, [tail, 1.0 - tail])
    return float(low), float(high)


def pair_precision_recall(pair_scores: dict, neighbours) -> dict:
    """Precision–recall over fragment pairs (a proposal is right when the pair are true neighbours)."""
    truth = {tuple(sorted((str(a), str(b)))) for a, b, *_ in neighbours}
    keys = list(pair_scores)
    y = np.array([k in truth for k in keys], int)
    s = np.array([pair_scores[k] for k in keys])
    if y.sum() == 0:
        raise ValueError("no true neighbour pair among the scored pairs")
    res = precision_recall(y, s)
    res["missing_truth"] = len(truth - set(keys))
    # recall is relative to all true pairs, including those never scored (pruned away)
    res["recall"] = res["recall"] * y.sum() / len(truth)
    return res


@dataclass
class StageTrace:
    """One fragment's candidates as each stage of :meth:`~common.matching.index.MatchIndex.rank` leaves them.

    ``order[stage]`` lists the other fragments best first after that stage, for the stages
    ``"prune"`` (the KD-tree's ``n_candidates`` nearest, stage 1), ``"patch"`` (stage 2, every
    other fragment it scores), ``"ribbon"`` (stage 2½: what stage 2 passed on, re-ranked) and
    ``"dock"`` (stage 3 and the final order of the query's own list). ``probability`` holds the final
    join probability of each other fragment in the list; ``evidence`` each candidate's stage scores:
    ``patch_logit`` (stage 2, hubness-corrected), ``ribbon`` (the ribbon score), ``contact_mm`` (the
    docking contact less both hubnesses) and ``paint_mm`` (paint continuity); NaN where a stage did not
    score it.
    """

    fragment: str
    order: dict
    probability: dict
    evidence: dict


def trace_stages(index, model, fragment: str, others, *, n_candidates: int = 100, **rank_options) -> StageTrace:
    """Rank ``fragment`` against ``others`` with :meth:`~common.matching.index.MatchIndex.rank`,
    recording every stage's order (:class:`StageTrace`): where true partners are lost.

    Stage 1 (the KD-tree's ``n_candidates``, which :func:`rank_all_pairs` skips by ranking every other
    fragment) is recorded beside; ``rank_options`` go to ``rank``.
    """
    cues = index.cues[fragment]
    others = [o for o in others if o != fragment]
    order = {"prune": index.candidates(cues, model, n_candidates)}
    stages: dict = {}
    final = index.rank(cues, others, model, evidence_for=0, trace=stages, **rank_options)
    for stage, found in stages.items():
        order[stage] = [c.other for c in found]
    order.setdefault("ribbon", order["patch"])
    order.setdefault("dock", order["ribbon"])
    evidence = {c.other: {"patch_logit": c.patch_logit, "ribbon": c.ribbon_score, "contact_mm": c.docking_contact_mm,
                          "paint_mm": c.paint_mm} for c in stages["patch"] + final}
    return StageTrace(fragment, order, {c.other: c.probability for c in final}, evidence)


def stage_recall(traces, neighbours, ks=(1, 5, 10)) -> dict:
    """Where the true neighbours are lost: for each stage of :func:`trace_stages`, the share of true
    neighbour links (each pair counted from both sides, as :func:`top_k_recall`) still in the
    fragment's list, and in its top ``k``; ``"final"`` is the pooled ranking in the station's order
    (mutual proximity of the traced fragments' final rankings, :func:`rank_all_pairs`).

    Returns
    -------
    dict stage → {"kept": share in the list, k: share in the top k}, plus ``"ranks"``: stage →
    the rank (0 = first) of each link, None where the stage dropped it.
    """
    truth: dict = {}
    for a, b, *_ in neighbours:
        truth.setdefault(str(a), set()).add(str(b))
        truth.setdefault(str(b), set()).add(str(a))
    traces = {t.fragment: t for t in traces}
    links = [(f, o) for f in traces for o in sorted(truth.get(f, ()))]
    out: dict = {"ranks": {}}
    from common.matching.mutual import mutual_pair_scores

    pooled = mutual_pair_scores({t.fragment: sorted(t.probability, key=lambda o: -t.probability[o])
                                 for t in traces.values()})
    final: dict = {}
    for (a, b), s in pooled.items():
        final.setdefault(a, []).append((s, b))
        final.setdefault(b, []).append((s, a))
    final = {f: [o for _, o in sorted(v, key=lambda x: -x[0])] for f, v in final.items()}
    for stage in ("prune", "patch", "ribbon", "dock", "final"):
        ranks = []
        for f, o in links:
            lst = final.get(f, []) if stage == "final" else traces[f].order[stage]
            ranks.append(lst.index(o) if o in lst else None)
        n = max(len(ranks), 1)
        row = {"kept": sum(r is not None for r in ranks) / n}
        for k in ks:
            row[int(k)] = sum(r is not None and r < k for r in ranks) / n
        out[stage] = row
        out["ranks"][stage] = ranks
    out["links"] = links
    return out
