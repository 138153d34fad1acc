"""The relative pose of a proposed join: the docking's candidate poses re-ranked by geometry and paint.

Stage 3 docks two fragment outlines (:func:`common.matching.docking.dock_outlines`) and keeps the
best few local maxima of the correlation as *candidate poses*. On real broken frescoes the
geometric score alone prefers a wrong candidate: material lost along the crack erodes the
outlines smooth, so two pieces face each other along *more* outline at a wrong pose than at the
true one (17 of 21 RePAIR pairs, 73 of 80 synthetic pairs; docs/matching.md, "Why the true pose
scores low"). Paint that continues across the crack (:func:`common.matching.paint.paint_continuity`)
is evidence the geometry does not have, so the pose of a pair is the candidate with the best

    score_mm = contact_mm + weight × paint_mm

``contact_mm`` the docking's geometric score as millimetres of shared crack
(:func:`~common.matching.docking.docking_contact_mm`) and ``paint_mm`` the paint evidence at that
candidate (millimetres of crack with paint continuing; ≈ 0 for plain plaster, so a plain crack
keeps the geometric choice). This is the hybrid (geometric + pictorial) pairwise alignment of
Shahar, Elkin & Ben-Shahar (2025) restricted to the docking's candidates. The weight
(:data:`POSE_PAINT_WEIGHT`) was chosen on realistic synthetic walls that the figures are not
measured on (``tests/bench/bench_pose.py``), never on the real collections.

**The station's chooser since session 13 is learned** (:func:`learned_pose_scores` of
:func:`pose_features`): a linear ranker over the contact, the paint and the facing geometry of the two
outlines at each candidate (:func:`common.matching.facing.facing_geometry`: facing length, the gap's
quantiles and roughness along the facing stretch, length pushed inside the other piece, curvature
agreement, how far apart the facing runs end), each as its raw value and its z-score among the pair's
candidates, fitted pairwise (right − wrong candidates of one pair; :func:`fit_pose_ranker`) on 50
realistic synthetic walls. Pose accuracy (within 5° and 5 mm) on held-out synthetic walls 0.199 → 0.278,
on RePAIR 0.143 → 0.190, for ≈ 20 ms CPU more per pair (docs/matching.md, "A learned pose chooser").
:func:`pose_scores` (``contact + 6 × paint``) stays as the hand-weighted rule and the default of
:func:`choose_pose` / :func:`ranked_poses` when no ``scores`` are given.

What was tried and measured not to help (docs/matching.md, "Poses that fit"): a gap-tolerant
point-to-curve refinement of the chosen candidate (it slides the piece along the crack: geometry
prefers wrong poses locally too), a local search of the paint alone around it, and choosing each
pair's pose so that no stretch of outline faces two partners within an object (even among true
pairs only).

The pose convention is the docking's: fragment-frame millimetres (x right, y down) and
``p_a = R(angle_deg) @ p_b + (tx_mm, ty_mm)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from common.matching.docking import DOCK_CELL_MM, Docking, _rotation, docking_contact_mm
# a pose seen from the other fragment, and the one range of angles: defined beside invert_docking, offered here with
# the other pose helpers
from common.matching.docking import inverse_pose, wrapped_deg  # noqa: F401

#: weight of a candidate's paint evidence (mm of crack with continuing paint) against its geometric
#: contact (mm of shared crack) when choosing a pair's pose among the docking's candidates; chosen on
#: realistic synthetic walls (``generate_wall(16, seed 31–36, preset="pompeii")``, pose accuracy within
#: 5° and 5 mm of their true pairs' 30 candidates: ``python tests/bench/bench_pose.py``), not on the
#: walls or collections the figures in docs/matching.md are measured on
POSE_PAINT_WEIGHT = 6.0
#: candidate poses a proposal offers beside its chosen one (``alignment.alternatives``), best first by the
#: learned chooser among the docking's 100 (index.DOCK_PAINT_POSES + DOCK_MORE_POSES): the review page steps
#: through them when the chosen pose is not the join. The chosen pose is right for about a fifth of RePAIR's
#: true pairs; with 19 alternatives a right pose is offered for a third (docs/matching.md, "More candidate
#: poses to offer")
ALTERNATIVE_POSES = 19


def pose_scores(dockings: Sequence[Docking], paint_mm, *, weight: float = POSE_PAINT_WEIGHT,
                cell_mm: float = DOCK_CELL_MM) -> np.ndarray:
    """Score of each candidate pose of a pair: geometric contact plus weighted paint evidence, mm.

    Parameters
    ----------
    dockings : sequence of Docking
        The pair's candidate poses (B in A's frame), e.g. ``dock_outlines(..., n_poses=30, per_angle=3)``.
    paint_mm : (N,) array_like
        Paint evidence at each candidate, mm of crack
        (:func:`common.matching.paint.paint_continuity` of the two fragments' paint fields at the
        candidates' ``(angle_deg, tx_mm, ty_mm)``); NaN counts as no evidence (0).
    weight : float
        Millimetres of contact one millimetre of continuing paint is worth (>= 0; 0: geometry alone).
    cell_mm : float
        Cell of the docking that produced the candidates (its score is in cells).

    Returns
    -------
    (N,) float
        ``contact_mm + weight × paint_mm`` for each candidate.

    Examples
    --------
    >>> from common.matching.docking import Docking
    >>> d = [Docking(0, 0, 0, 60.0, 45, 0), Docking(90, 5, 0, 50.0, 37.5, 0)]
    >>> pose_scores(d, [0.0, 4.0], weight=2.0).round(1).tolist()      # 45 mm; 37.5 + 2 × 4 mm
    [45.0, 45.5]
    """
    docks = list(dockings)
    paint = np.asarray(paint_mm, float).reshape(-1)
    if not docks:
        raise ValueError("dockings is empty: a pair needs at least one candidate pose")
    if len(paint) != len(docks):
        raise ValueError(f"paint_mm has {len(paint)} values for {len(docks)} candidate poses")
    if not (np.isfinite(weight) and weight >= 0):
        raise ValueError(f"weight must be finite and >= 0, got {weight}")
    if not cell_mm > 0:
        raise ValueError(f"cell_mm must be positive, got {cell_mm}")
    contact = np.array([docking_contact_mm(d, cell_mm) for d in docks], float)
    return contact + weight * np.nan_to_num(paint, nan=0.0, posinf=0.0, neginf=0.0)


def choose_pose(dockings: Sequence[Docking], paint_mm, *, weight: float = POSE_PAINT_WEIGHT,
                cell_mm: float = DOCK_CELL_MM, scores=None) -> Docking:
    """The pair's pose: the candidate with the best score (the first on a tie) — ``scores`` where given
    (the station's: :func:`learned_pose_scores` of :func:`pose_features`), else :func:`pose_scores`.

    The returned :class:`~common.matching.docking.Docking` is the candidate itself (its own
    geometric score, contact and overlap), so a ranking that uses the docking's best contact as a
    pair's evidence is unchanged by which pose is proposed.

    Examples
    --------
    >>> from common.matching.docking import Docking
    >>> d = [Docking(0, 0, 0, 60.0, 45, 0), Docking(90, 5, 0, 50.0, 37.5, 0)]
    >>> choose_pose(d, [0.0, 4.0], weight=2.0).angle_deg                  # paint tips it
    90
    >>> choose_pose(d, [0.0, 4.0], weight=0.0).angle_deg                  # geometry alone
    0
    >>> choose_pose(d, [0.0, 4.0], scores=[1.0, 0.5]).angle_deg           # scores given
    0
    """
    return ranked_poses(dockings, paint_mm, weight=weight, cell_mm=cell_mm, scores=scores)[0]


def ranked_poses(dockings: Sequence[Docking], paint_mm, *, weight: float = POSE_PAINT_WEIGHT,
                 cell_mm: float = DOCK_CELL_MM, distinct_deg: float = 3.0, distinct_mm: float = 3.0,
                 scores=None) -> list[Docking]:
    """The pair's candidate poses best first by ``scores`` (default :func:`pose_scores`), without near
    repeats: a candidate whose angle is within ``distinct_deg`` and translation within ``distinct_mm``
    of a better one's is left out (the docking keeps several maxima per rotation). The first is
    :func:`choose_pose`'s.

    Examples
    --------
    >>> from common.matching.docking import Docking
    >>> d = [Docking(0, 0, 0, 60.0, 45, 0), Docking(90, 5, 0, 50.0, 37.5, 0), Docking(1, 1, 0, 58.0, 44, 0)]
    >>> [p.angle_deg for p in ranked_poses(d, [0.0, 4.0, 0.0], weight=2.0)]   # (1, 1) repeats (0, 0)
    [90, 0]
    """
    docks = list(dockings)
    if not docks:
        raise ValueError("dockings is empty: a pair needs at least one candidate pose")
    if scores is None:
        scores = pose_scores(docks, paint_mm, weight=weight, cell_mm=cell_mm)
    scores = np.asarray(scores, float).reshape(-1)
    if len(scores) != len(docks):
        raise ValueError(f"scores has {len(scores)} values for {len(docks)} candidate poses")
    if not np.all(np.isfinite(scores)):
        raise ValueError("scores must be finite")
    order = np.argsort(-scores, kind="stable")
    kept: list[Docking] = []
    for i in order:
        d = docks[int(i)]
        if not any(abs(wrapped_deg(d.angle_deg - k.angle_deg)) <= distinct_deg
                   and np.hypot(d.tx_mm - k.tx_mm, d.ty_mm - k.ty_mm) <= distinct_mm for k in kept):
            kept.append(d)
    return kept


def offered_poses(dockings: Sequence[Docking], paint_mm, features, *, choose_among: int, weights=None) -> list[Docking]:
    """The pair's proposed pose, then the other candidate poses a person may step through, best first.

    The proposed pose is the learned chooser's best among the first ``choose_among`` candidates, scored among
    those (the docking's search the chooser was fitted on: ``dock_frames(n_poses=30, per_angle=3)``); the rest
    follow in the order of its scores among all candidates (the further ones of ``more_poses`` too), without
    near repeats (:func:`ranked_poses`). So the proposed pose is what it was without the further candidates,
    and they only widen what is offered.

    Parameters
    ----------
    dockings, paint_mm : as for :func:`ranked_poses`
    features : (N, F) array
        :func:`pose_features` of the candidates.
    choose_among : int
        How many of the first candidates the proposed pose is chosen from.
    weights : optional
        As :func:`learned_pose_scores`.

    Examples
    --------
    >>> from common.matching.docking import Docking
    >>> d = [Docking(0, 0, 0, 60.0, 45, 0), Docking(90, 5, 0, 50.0, 37.5, 0), Docking(45, 9, 0, 20.0, 15, 0)]
    >>> x = np.array([[1.0], [2.0], [9.0]])                        # one feature; the third candidate is best
    >>> [p.angle_deg for p in offered_poses(d, [0, 0, 0], x, choose_among=2, weights=([1.0], [0.0]))]
    [90, 45, 0]
    """
    docks = list(dockings)
    x = np.asarray(features, float)
    if not 1 <= choose_among or len(x) != len(docks):
        raise ValueError(f"need choose_among >= 1 and one feature row per candidate, got {choose_among} and "
                         f"{len(x)} rows for {len(docks)} candidates")
    first = int(np.argmax(learned_pose_scores(x[:choose_among], weights)))
    scores = learned_pose_scores(x, weights)
    scores[first] = scores.max() + 1.0          # the proposed pose leads; the rest by the scores among all
    return ranked_poses(docks, paint_mm, scores=scores)


def adjusted_pose(pose, centre_b_mm, *, turn_deg: float = 0.0, shift_mm=(0.0, 0.0)) -> tuple[float, float, float]:
    """A pose corrected by a person: fragment B turned by ``turn_deg`` about its own centre, then moved
    by ``shift_mm`` (both in A's frame, as the review page draws the join).

    Parameters
    ----------
    pose : (3,) angle_deg, tx_mm, ty_mm
        B in A's frame, ``p_a = R(angle_deg) p_b + t``.
    centre_b_mm : (2,)
        B's centre in B's own frame, mm (the point it turns about).
    turn_deg : float
        Turn added, degrees (the pose convention's sense: clockwise on screen, y down).
    shift_mm : (2,)
        Move of B's centre in A's frame, mm (x right, y down).

    Returns
    -------
    (angle_deg, tx_mm, ty_mm) with ``R(angle + turn) c_b + t' = R(angle) c_b + t + shift``: B's centre
    lands where it was, moved by ``shift_mm``, and B is turned by ``turn_deg`` about it.
    """
    values = np.array([*np.ravel(pose), *np.ravel(centre_b_mm), turn_deg, *np.ravel(shift_mm)], float)
    if values.shape != (8,) or not np.all(np.isfinite(values)):
        raise ValueError("pose (3), centre_b_mm (2), turn_deg and shift_mm (2) must be finite numbers, got "
                         f"{pose!r}, {centre_b_mm!r}, {turn_deg!r}, {shift_mm!r}")
    angle, tx, ty, cx, cy, turn, sx, sy = values
    centre_a = _rotation(angle) @ (cx, cy) + (tx, ty) + (sx, sy)
    t = centre_a - _rotation(angle + turn) @ (cx, cy)
    return wrapped_deg(angle + turn), float(t[0]), float(t[1])


def adjustment_between(pose, other, centre_b_mm) -> tuple[float, float, float]:
    """The correction that turns ``pose`` into ``other`` (both B in A's frame): the inverse of
    :func:`adjusted_pose`, so ``adjusted_pose(pose, c, turn_deg=t, shift_mm=(sx, sy)) == other``.

    Returns
    -------
    (turn_deg, shift_x_mm, shift_y_mm)
        B turned about its centre (degrees in (-180, 180]) and its centre moved in A's frame (mm).

    Examples
    --------
    >>> turn, sx, sy = adjustment_between((0, 0, 0), (90, 0, 0), (10, 0))   # B's centre (10, 0) -> (0, 10)
    >>> round(turn), round(sx, 6), round(sy, 6)
    (90, -10.0, 10.0)
    """
    values = np.array([*np.ravel(pose), *np.ravel(other), *np.ravel(centre_b_mm)], float)
    if values.shape != (8,) or not np.all(np.isfinite(values)):
        raise ValueError(f"pose (3), other (3) and centre_b_mm (2) must be finite numbers, got {pose!r}, {other!r}, "
                         f"{centre_b_mm!r}")
    a0, tx0, ty0, a1, tx1, ty1, cx, cy = values
    shift = _rotation(a1) @ (cx, cy) + (tx1, ty1) - _rotation(a0) @ (cx, cy) - (tx0, ty0)
    return -wrapped_deg(a0 - a1), float(shift[0]), float(shift[1])


# ------------------------------------------------------------------------------------------------------------
# the learned chooser (issue 15, session 13)

#: the per-candidate cues of the learned chooser (:func:`pose_features`), in order: the docking's contact
#: (mm of crack), the paint continuity (mm), and the facing geometry of the two outlines at the candidate
#: (:data:`common.matching.facing.FACING_COLUMNS`)
POSE_FEATURES = ("contact_mm", "paint_mm", "face_mm", "run_mm", "tight_mm", "gap_q10_mm", "gap_median_mm",
                 "gap_q90_mm", "gap_rough_mm", "inside_mm", "depth_mm", "curvature_mismatch",
                 "curvature_correlation", "end_mismatch_mm")

#: weights of the learned chooser (:func:`learned_pose_scores`): per feature of :data:`POSE_FEATURES`, the
#: weight of its raw value and of its z-score within the pair. Fitted by ``python tests/bench/bench_pose_learned.py
#: cache --cache DIR`` then ``... fit --cache DIR --train 31-80 --no-lines --drop paint_peak,band,overlap,rank,support
#: --emit`` (:func:`fit_pose_ranker`, pairwise, C = 0.1 chosen by 5-fold cross-validation grouped by wall): every
#: candidate of every true pair of 50 realistic synthetic walls, ``generate_wall(16, seed 31–80, dpi=40,
#: preset="pompeii", colour_only=True)``, 1 224 pairs, right = within 5° and 5 mm of the truth. Never fitted on
#: the test walls (21–23) or on a real collection (docs/matching.md, "A learned pose chooser").
POSE_MODEL_RAW = (0.0227795, 0.116682, 0.0432271, -0.0404096, 0.0963054, 2.25611, -2.13428, -1.03198, -27.2083,
                  -0.348418, -0.85388, 20.9498, -5.57915, -0.134783)
POSE_MODEL_Z = (1.72791, 3.03171, 1.46365, -1.60347, 0.114307, 1.06316, -0.679993, -0.669754, -1.91142, -0.50763,
                -1.09626, 0.894162, -1.29292, 1.75355)


def pose_features(dockings: Sequence[Docking], paint_mm, contour_a_mm, contour_b_mm, *,
                  cell_mm: float = DOCK_CELL_MM) -> np.ndarray:
    """The cues of a pair's candidate poses that the learned chooser weighs (:data:`POSE_FEATURES`).

    Parameters
    ----------
    dockings, paint_mm
        As for :func:`pose_scores`: the pair's candidate poses and the paint continuity at each.
    contour_a_mm, contour_b_mm : (M, 2), (K, 2) arrays
        The two outlines the candidates were docked from (each in its fragment's frame, mm).
    cell_mm : float
        Cell of the docking (its score is in cells).

    Returns
    -------
    (N, 14) float
        Per candidate: the docking's contact (mm), the paint (mm) and
        :func:`common.matching.facing.facing_geometry`'s 12 columns.
    """
    from common.matching.facing import facing_geometry

    docks = list(dockings)
    contact = pose_scores(docks, paint_mm, weight=0.0, cell_mm=cell_mm)
    paint = np.nan_to_num(np.asarray(paint_mm, float).reshape(-1), nan=0.0, posinf=0.0, neginf=0.0)
    geometry, _, _ = facing_geometry(contour_a_mm, contour_b_mm,
                                     np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks], float))
    return np.column_stack([contact, paint, geometry])


def pose_design(features) -> np.ndarray:
    """A pair's candidate features normalised within the pair: each raw value beside its z-score among the
    pair's candidates (0 where a feature does not vary), ``(N, 2F)``. The z-score is what lets one weight
    serve pairs of different sizes and paint (a long straight piece faces everything along more outline)."""
    x = np.asarray(features, float)
    if x.ndim != 2 or not np.all(np.isfinite(x)):
        raise ValueError(f"features must be a finite (N, F) array, got shape {x.shape}")
    sd = x.std(0, keepdims=True)
    z = np.where(sd > 1e-9, (x - x.mean(0, keepdims=True)) / np.where(sd > 1e-9, sd, 1.0), 0.0)
    return np.hstack([x, z])


def fit_pose_ranker(features: Sequence[np.ndarray], right: Sequence[np.ndarray], *, C: float = 1.0,
                    kind: str = "pairwise", seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fit the weights of a linear pose chooser on pairs whose right candidates are known.

    Parameters
    ----------
    features : sequence of (N_i, F) arrays
        Each pair's candidate features (:func:`pose_features`).
    right : sequence of (N_i,) bool arrays
        Which candidates are right (e.g. within 5° and 5 mm of the truth).
    C : float
        Inverse L2 regularisation of the logistic regression (on standardised :func:`pose_design` columns).
    kind : {"pairwise", "pointwise"}
        "pairwise": a logistic regression on the differences right − wrong within each pair (a linear
        RankNet / RankSVM; each pair weighs about the same, pairs with no right or no wrong candidate
        add nothing). "pointwise": a class-balanced logistic regression on the candidates themselves.
    seed : int
        The pairwise differences are given random signs (a balanced two-class problem); deterministic.

    Returns
    -------
    raw, z : (F,) arrays
        Weights of each feature's raw value and its within-pair z-score (:func:`learned_pose_scores`);
        the standardisation is folded into them, an intercept (it does not rank) dropped.

    References
    ----------
    R. Herbrich, T. Graepel, K. Obermayer, "Large margin rank boundaries for ordinal regression", 2000;
    T. Joachims, "Optimizing search engines using clickthrough data", KDD 2002 (pairwise ranking as
    classification of differences).
    """
    from sklearn.linear_model import LogisticRegression
    from sklearn.preprocessing import StandardScaler

    designs = [pose_design(x) for x in features]
    labels = [np.asarray(y, bool).reshape(-1) for y in right]
    if len(designs) != len(labels) or any(len(d) != len(y) for d, y in zip(designs, labels)):
        raise ValueError("features and right must give one label per candidate of each pair")
    if kind not in ("pairwise", "pointwise"):
        raise ValueError(f"kind must be 'pairwise' or 'pointwise', got {kind!r}")
    scaler = StandardScaler().fit(np.vstack(designs))
    scale = np.where(scaler.scale_ > 0, scaler.scale_, 1.0)
    designs = [(d - scaler.mean_) / scale for d in designs]
    if kind == "pointwise":
        x, y = np.vstack(designs), np.concatenate(labels)
        if y.all() or not y.any():
            raise ValueError("the pairs need both right and wrong candidates")
        coef = LogisticRegression(C=C, class_weight="balanced", max_iter=2000).fit(x, y).coef_[0]
    else:
        diffs = [((d[y][:, None] - d[~y][None]).reshape(-1, d.shape[1]) / np.sqrt(y.sum() * (~y).sum()))
                 for d, y in zip(designs, labels) if y.any() and not y.all()]
        if not diffs:
            raise ValueError("no pair has both a right and a wrong candidate")
        x = np.vstack(diffs)
        sign = np.random.default_rng(seed).choice([-1.0, 1.0], len(x))
        coef = LogisticRegression(C=C, fit_intercept=False, max_iter=4000).fit(x * sign[:, None],
                                                                              (sign > 0).astype(int)).coef_[0]
    w = coef / scale
    f = len(w) // 2
    return w[:f], w[f:]


def learned_pose_scores(features, weights=None) -> np.ndarray:
    """Score of each candidate pose of a pair by the learned chooser: ``Σ_f raw_f x_f + z_f ẑ_f``, ``ẑ`` the
    within-pair z-score (:func:`pose_design`); higher is better, comparable within a pair only.

    Parameters
    ----------
    features : (N, F) array
        :func:`pose_features` of the pair's candidates.
    weights : (raw, z) pair of (F,) arrays, optional
        Default the station's (:data:`POSE_MODEL_RAW`, :data:`POSE_MODEL_Z`), fitted on realistic synthetic
        walls by :func:`fit_pose_ranker`.

    Returns
    -------
    (N,) float

    Examples
    --------
    >>> x = np.array([[1.0, 0.0], [2.0, 5.0]])
    >>> learned_pose_scores(x, (np.array([1.0, 0.0]), np.array([0.0, 1.0]))).tolist()   # raw 1st + z of 2nd
    [0.0, 3.0]
    """
    raw, z = (POSE_MODEL_RAW, POSE_MODEL_Z) if weights is None else weights
    d = pose_design(features)
    w = np.concatenate([np.asarray(raw, float), np.asarray(z, float)])
    if len(w) != d.shape[1]:
        raise ValueError(f"{d.shape[1] // 2} features for weights of {len(w) // 2}")
    return d @ w
