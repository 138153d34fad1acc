"""Training, online learning from verdicts, and re-ranking (thesis §5.8; §5.2.2).

* :func:`wall_cues` — feature tables and matcher cues of a synthetic (or imported) wall.
* :func:`train_model` — fit the default logistic regression on a training set and extract it as a
  pickle-free :class:`~common.matching.models.MatchModel` (its training rows go with it, so later
  refits can start from them).
* :func:`verdict_rows` / :func:`refit_with_verdicts` — **online learning**: every verdict adds the
  evidence rows the classifier saw for that proposal (its ``top_m`` best patch pairs), labelled 1
  (confirmed) or 0 (rejected), with a larger sample weight than the bootstrap rows (a person's
  decision on a real fragment outweighs a synthetic example); the logistic regression is re-fitted
  on the union and becomes the next model version.
* :func:`rerank` — new probabilities for stored proposals under the new model.
* :func:`stage_combination` / :func:`with_combination` — stage 3's weighing of every stage's score
  (patch classifier, ribbon, docking, paint), learned by a logistic regression on the docked candidates
  of a synthetic wall with ground truth.

The ribbon calibration (:func:`common.matching.ribbon.fit_ribbon_calibration`) is fitted once, on
the bootstrap wall's fragment pairs, and carried over by every refit: verdicts teach the patch
classifier, which chooses the candidates the ribbon ranks.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from common.matching.classifiers import make_classifier
from common.matching.docking import paint_from_profile
from common.matching.models import MatchModel, model_from_pipeline
from common.matching.pairs import FragmentCues, TrainingSet, correspondence_columns, fragment_cues, training_set
from common.matching.ribbon import RIBBON_DEFINITION, fit_ribbon_calibration, pair_ribbon_scores

#: sample weight of one verdict row relative to one bootstrap row
VERDICT_WEIGHT = 5.0
#: the bootstrap model (and ``tessera evaluate``'s models) use stage 3's learned combination of the stage
#: scores (:func:`stage_combination`); off: stage 3 combines them by fixed rules. Off since 2026-11-25:
#: it lifts pooled top-5 on the synthetic wall and DAFNE but the bootstrap's fit lowers RePAIR's
#: within-object @3 from 1.000 to 0.750 (docs/matching.md, "Stage 3's learned combination")
STAGE_COMBINATION = False


def wall_cues(wall, *, progress=None, work_pixel_mm: float = 0.1):
    """Extract features of every fragment of a wall with images.

    Returns
    -------
    tables : dict id → FeatureTable, cues : dict id → FragmentCues, poses : dict id → pose (None
    for spurious fragments)
    """
    from common.features import extract_features

    tables, cues, poses = {}, {}, {}
    n = len(wall.fragments)
    for i, f in enumerate(wall.fragments):
        if f.rgbn is None:
            raise ValueError(f"fragment {f.id} of wall {wall.id} has no image (generate with keep_images=True)")
        tables[f.id] = extract_features(f.rgbn, work_pixel_mm=work_pixel_mm)
        cues[f.id] = fragment_cues(tables[f.id], f.id)
        poses[f.id] = f.pose
        if progress:
            progress((i + 1) / n, f"features of fragment {i + 1}/{n}")
    return tables, cues, poses


def train_model(ts: TrainingSet, *, sequence: int = 1, C: float = 1.0, sample_weight=None, top_m: int = 3,
                info: dict | None = None, ribbon: tuple | None = None,
                docking: tuple | None = None) -> tuple[MatchModel, object]:
    """Fit the logistic regression (balanced class weights) and return (model, fitted pipeline);
    ``ribbon`` is the ribbon calibration stored with it (:func:`ribbon_calibration`)."""
    if len(np.unique(ts.y)) < 2:
        raise ValueError("the training set needs both matches and non-matches")
    pipe = make_classifier("logistic", C=C)
    kw = {"clf__sample_weight": np.asarray(sample_weight, float)} if sample_weight is not None else {}
    pipe.fit(ts.x, ts.y, **kw)
    meta = {"n_train": int(len(ts)), "n_match": int(ts.y.sum()), "class_weight": "balanced",
            "negatives_per_positive": float(ts.negatives_per_positive), "C": C}
    meta.update(info or {})
    if ribbon is not None and "ribbon_definition" not in (info or {}):   # a refit keeps the previous model's
        meta["ribbon_definition"] = RIBBON_DEFINITION
    model = model_from_pipeline(pipe, ts.columns, sequence=sequence, top_m=top_m, info=meta, ribbon=ribbon,
                                docking=docking)
    model.training = (ts.x, ts.y, np.ones(len(ts.y)) if sample_weight is None else np.asarray(sample_weight, float))
    return model, pipe


def ribbon_calibration(tables: dict, adjacency) -> tuple[float, float] | None:
    """Ribbon calibration from a wall's feature tables (their boundary profiles) and its true
    neighbour pairs: every fragment pair scored, joined = shares a crack. None when the tables
    have no boundary profiles."""
    from common.features.boundary import boundary_channel_names

    profiles = {f: t.boundary_profile for f, t in tables.items() if len(t.boundary_profile)}
    if len(profiles) < 3:
        return None
    scores = pair_ribbon_scores(profiles, boundary_channel_names())
    joined = {frozenset(p[:2]) for p in adjacency}
    keys = list(scores)
    y = np.array([frozenset(k) in joined for k in keys])
    if y.all() or not y.any():
        return None
    return fit_ribbon_calibration([scores[k] for k in keys], y)


def docking_calibration(wall, *, contours: dict | None = None, paint: dict | None = None,
                        negatives_per_positive: float = 3.0, seed: int = 0, progress=None) -> tuple[float, float] | None:
    """Calibration of the docking contact (stage 3) from a wall with ground truth.

    Every true neighbour pair and ``negatives_per_positive`` random other pairs per fragment pair
    are docked (:func:`common.matching.docking.dock_outlines`); each fragment's docking hubness is
    the mean contact of its best dockings among those, and the hub-corrected contact of every pair
    is fitted against joined/separate (:func:`common.matching.ribbon.fit_ribbon_calibration`, the
    same 1-D logistic calibration as the ribbon's). ``contours``: id → outline in mm (default: the
    wall's fragments' ``contour_mm``); ``paint``: id → paint along it
    (:func:`common.matching.docking.paint_deviation`), as the index docks them. None when the wall
    has too few pairs of either kind.
    """
    from common.matching.docking import DOCK_HUB_TOP, dock_outlines, docking_contact_mm, hub_corrected

    outlines = contours or {f.id: f.contour_mm for f in wall.fragments if f.contour_mm is not None}
    ids = sorted(outlines)
    joined = {frozenset(p[:2]) for p in wall.adjacency if p[0] in outlines and p[1] in outlines}
    rng = np.random.default_rng(seed)
    pairs = sorted(tuple(sorted(p)) for p in joined)   # sorted: the fit, and so the model's digest, must not follow string hashing
    n_neg = int(round(negatives_per_positive * len(pairs)))
    tries = 0
    negatives = set()
    while len(negatives) < n_neg and tries < 50 * max(n_neg, 1) and len(ids) > 2:
        a, b = rng.choice(len(ids), 2, replace=False)
        key = tuple(sorted((ids[a], ids[b])))
        if frozenset(key) not in joined:
            negatives.add(key)
        tries += 1
    pairs += sorted(negatives)
    if len(joined) < 3 or len(negatives) < 3:
        return None
    contact = {}
    for i, (a, b) in enumerate(pairs):
        paint = paint or {}
        contact[(a, b)] = docking_contact_mm(dock_outlines(outlines[a], outlines[b], paint_a=paint.get(a),
                                                           paint_b=paint.get(b), n_poses=1)[0])
        if progress and (i % 20 == 0 or i == len(pairs) - 1):
            progress((i + 1) / len(pairs), f"docked {i + 1}/{len(pairs)} pairs")
    per: dict = {}
    for (a, b), c in contact.items():
        per.setdefault(a, []).append(c)
        per.setdefault(b, []).append(c)
    hub = {f: float(np.mean(sorted(v)[-DOCK_HUB_TOP:])) for f, v in per.items()}
    centre = float(np.median(list(hub.values())))
    scores = [float(hub_corrected(c, hub[a], hub[b], centre)) for (a, b), c in contact.items()]
    y = [frozenset(k) in joined for k in contact]
    return fit_ribbon_calibration(scores, y)


def stage_combination(tables: dict, cues: dict, adjacency, model: MatchModel, *, C: float = 1.0,
                      progress=None) -> tuple | None:
    """Stage 3's combination of the stage scores, learned on a wall with ground truth.

    Every fragment of the wall is ranked against all others by the staged matcher under ``model``
    (:func:`common.matching.evaluation.trace_stages`, stages 2–3 as the station ranks), and each
    *docked* candidate becomes a row of its :meth:`~common.matching.models.MatchModel.stage_terms`
    (stage 2's hubness-corrected logit, the ribbon's, the docking's, the paint's; a missing term takes
    the mean of the others), labelled 1 for a true neighbour. A logistic regression on those rows
    (unweighted, so its probability is the share of true joins among docked candidates, comparable
    between queries) gives the weights: stacking the stages' calibrated scores (Wolpert 1992, *Stacked
    generalization*) instead of adding their logits as if independent.

    Parameters
    ----------
    tables, cues : dict id → FeatureTable / FragmentCues of the wall
    adjacency : true neighbour pairs ``(a, b, ...)``
    model : the model (with ribbon and docking calibrations) whose stages are combined
    C : inverse L2 regularisation of the logistic regression

    Returns
    -------
    The :attr:`~common.matching.models.MatchModel.combination` (weights, intercept, fill values), or
    None when the wall gives too few docked true or false candidates (fewer than 5 of either).
    """
    from sklearn.linear_model import LogisticRegression

    from common.matching.evaluation import trace_stages
    from common.matching.index import MatchIndex

    if model.docking is None:
        raise ValueError("the stage combination needs a model with a docking calibration")
    index = MatchIndex()
    for f in sorted(cues):
        index.add(cues[f], tables[f].contour_mm, tables[f].boundary_profile)
    ids = list(index._order)
    index.refresh_hubness(ids, replace(model, combination=None), n_candidates=100)
    truth: dict = {}
    for a, b, *_ in adjacency:
        truth.setdefault(a, set()).add(b)
        truth.setdefault(b, set()).add(a)
    terms, labels = [], []
    for i, f in enumerate(ids):
        t = trace_stages(index, replace(model, combination=None), f, ids)
        docked = [o for o in t.order["dock"] if np.isfinite(t.evidence[o]["contact_mm"])]
        ev = [t.evidence[o] for o in docked]
        terms.append(model.stage_terms([e["patch_logit"] for e in ev], [e["ribbon"] for e in ev],
                                       [e["contact_mm"] for e in ev], [e["paint_mm"] for e in ev]))
        labels += [o in truth.get(f, ()) for o in docked]
        if progress and (i % 10 == 0 or i == len(ids) - 1):
            progress((i + 1) / len(ids), f"stage combination: ranked {i + 1}/{len(ids)} fragments")
    x, y = np.vstack(terms) if terms else np.zeros((0, 4)), np.asarray(labels, bool)
    if y.sum() < 5 or (~y).sum() < 5:
        return None
    with np.errstate(invalid="ignore"):
        fill = np.nanmean(np.where(np.isfinite(x), x, np.nan), axis=0)
    fill = np.where(np.isfinite(fill), fill, 0.0)
    lr = LogisticRegression(C=C, max_iter=1000).fit(np.where(np.isfinite(x), x, fill), y)
    return (*lr.coef_[0].tolist(), float(lr.intercept_[0]), *fill.tolist())


def with_combination(model: MatchModel, combination: tuple | None) -> MatchModel:
    """The model with stage 3's learned combination (:func:`stage_combination`), re-versioned."""
    m = replace(model, combination=combination)
    m.version = f"{m.sequence:04d}-{m.digest()}"
    return m


def bootstrap_wall(*, n_fragments: int = 60, seed: int = 0, dpi: float = 100.0, progress=None):
    """The synthetic wall the bootstrap model's patch classifier and ribbon calibration are fitted on, with its
    feature tables and cues: ``(wall, tables, cues)``."""
    from common.synth.wall import generate_wall

    wall = generate_wall(n_fragments, seed=seed, dpi=dpi)
    tables, cues, _ = wall_cues(wall, progress=progress)
    return wall, tables, cues


def with_current_ribbon(model: MatchModel, *, n_fragments: int = 60, seed: int = 0, dpi: float = 100.0,
                        progress=None) -> MatchModel:
    """``model`` itself when its ribbon calibration is for today's ribbon score
    (:data:`~common.matching.ribbon.RIBBON_DEFINITION`, recorded in ``info["ribbon_definition"]``) or it has none;
    otherwise the model with its ribbon calibrated again on the bootstrap wall (``n_fragments``, ``seed``, ``dpi``:
    the station's bootstrap settings), as the next model version. Everything else — the patch classifier and what
    the verdicts taught it, the docking, the combination — is kept."""
    if model.ribbon is None or model.info.get("ribbon_definition") == RIBBON_DEFINITION:
        return model
    wall, tables, _ = bootstrap_wall(n_fragments=n_fragments, seed=seed, dpi=dpi, progress=progress)
    info = dict(model.info, ribbon_definition=RIBBON_DEFINITION, previous=model.version,
                ribbon_recalibrated=f"was {model.info.get('ribbon_definition', 'one run of 20 mm')}: {model.ribbon}")
    m = replace(model, ribbon=ribbon_calibration(tables, wall.adjacency), info=info)
    m.version = f"{m.sequence + 1:04d}-{m.digest()}"
    return m


def bootstrap_model(*, n_fragments: int = 60, seed: int = 0, dpi: float = 100.0, progress=None) -> MatchModel:
    """A first model trained on a synthetic wall, for a station that has no verdicts yet."""
    from common.synth.wall import generate_wall

    wall, tables, cues = bootstrap_wall(n_fragments=n_fragments, seed=seed, dpi=dpi, progress=progress)
    ts = training_set(cues, {f.id: f.pose for f in wall.fragments}, wall.adjacency, seed=seed)
    # the docking is calibrated on a realistic wall (plaster lost along the cracks, 2-20 cm pieces),
    # the kind of collection it has to work on; colour-only, since only the outlines are used
    real = generate_wall(max(12, n_fragments // 4), seed=seed + 1, dpi=min(dpi, 40.0), preset="pompeii",
                         colour_only=True)
    real_tables, real_cues, _ = wall_cues(real)
    docking = docking_calibration(real, contours={f: t.contour_mm for f, t in real_tables.items()},
                                  paint={f: paint_from_profile(t.boundary_profile) for f, t in real_tables.items()},
                                  seed=seed, negatives_per_positive=2.0)
    model, _ = train_model(ts, sequence=1, ribbon=ribbon_calibration(tables, wall.adjacency), docking=docking,
                           info={"docking_trained_on": f"synthetic wall {real.id} (preset pompeii, seed {seed + 1})",
                                 "trained_on": f"synthetic wall {wall.id} ({n_fragments} fragments, seed {seed}, {dpi:g} dpi)"})
    if docking is not None and STAGE_COMBINATION:
        # stage 3's weighing of the stage scores, learned on the realistic wall's staged ranking (lost material
        # along the cracks, where the docking and the paint carry evidence), as the docking's calibration is
        model = with_combination(model, stage_combination(real_tables, real_cues, real.adjacency, model))
    return model


def verdict_rows(evidence: dict, verdict: str, columns: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Rows and labels a verdict teaches: the proposal's evidence rows, 1 if confirmed else 0."""
    if verdict not in ("confirmed", "rejected"):
        raise ValueError(f"verdict must be 'confirmed' or 'rejected', got {verdict!r}")
    if not evidence or "rows" not in evidence:
        return np.zeros((0, len(columns))), np.zeros(0, int)
    cols = list(evidence.get("columns", columns))
    rows = np.array(evidence["rows"], dtype=float).reshape(-1, len(cols))
    x = np.full((len(rows), len(columns)), np.nan)
    pos = {c: i for i, c in enumerate(cols)}
    for j, c in enumerate(columns):
        if c in pos:
            x[:, j] = rows[:, pos[c]]
    return x, np.full(len(rows), 1 if verdict == "confirmed" else 0)


def refit_with_verdicts(base_x: np.ndarray, base_y: np.ndarray, verdicts: list[tuple[np.ndarray, np.ndarray]], *,
                        previous: MatchModel, verdict_weight: float = VERDICT_WEIGHT, C: float | None = None) -> MatchModel:
    """Re-fit the logistic regression on the bootstrap rows plus every verdict's rows.

    Parameters
    ----------
    base_x, base_y : bootstrap training rows (stored with the model)
    verdicts : list of (rows, labels) from :func:`verdict_rows`, all verdicts so far (latest per pair)
    previous : MatchModel
        The current model; the new one gets the next sequence number.
    verdict_weight : float
        Sample weight of a verdict row relative to a bootstrap row.
    """
    xs = [np.asarray(base_x, float)] + [v[0] for v in verdicts if len(v[0])]
    ys = [np.asarray(base_y, int)] + [v[1] for v in verdicts if len(v[1])]
    ws = [np.ones(len(base_y))] + [np.full(len(v[1]), float(verdict_weight)) for v in verdicts if len(v[1])]
    x, y, w = np.vstack(xs), np.concatenate(ys), np.concatenate(ws)
    ts = TrainingSet(x, y, np.zeros(len(y), int), np.zeros((len(y), 2), str), np.zeros((len(y), 2), int),
                     list(previous.columns), float(previous.info.get("negatives_per_positive", np.nan)))
    n_v = int(sum(len(v[1]) for v in verdicts))
    info = dict(previous.info)
    info.update({"verdict_rows": n_v, "verdict_weight": float(verdict_weight), "previous": previous.version})
    model, _ = train_model(ts, sequence=previous.sequence + 1, C=float(C if C is not None else previous.info.get("C", 1.0)),
                           sample_weight=w, top_m=previous.top_m, info=info, ribbon=previous.ribbon,
                           docking=previous.docking)
    model = with_combination(model, previous.combination)
    model.training = (np.asarray(base_x, float), np.asarray(base_y, int), np.ones(len(base_y)))
    return model


def rerank(index, model: MatchModel, pairs: list[tuple[str, str]]) -> dict:
    """New probabilities of fragment pairs under ``model`` (pairs whose fragments are indexed).

    Pairs are grouped by their first fragment so each fragment's patches are scored against all
    its partners in one batch. Returns ``{(a, b): Candidate}``.
    """
    by_a: dict = {}
    for a, b in pairs:
        if a in index and b in index:
            by_a.setdefault(a, []).append(b)
    # hubness under the new model for every fragment involved (index.py: the ranking correction)
    index.refresh_hubness(sorted({f for a, others in by_a.items() for f in [a, *others]}), model)
    out = {}
    for a, others in by_a.items():
        # the probability a proposal would get now: stage 2, then the ribbon where it applies
        for c in index.rank(index.cues[a], others, model, ribbon_candidates=len(others), evidence_for=0):
            out[(a, c.other)] = c
    return out


def evidence_dict(candidate, columns: list[str] | None = None) -> dict:
    """JSON-able evidence of a candidate: its top patch pairs and their correspondence rows."""
    rows = np.asarray(candidate.evidence, float)
    return {"columns": list(columns or correspondence_columns()),
            "patches": np.asarray(candidate.top_pairs, int).tolist(),
            "rows": [[None if not np.isfinite(v) else float(v) for v in r] for r in rows]}
