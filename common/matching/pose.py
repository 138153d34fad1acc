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
# a pose seen from the other fragment: defined beside invert_docking, offered here with the other pose helpers
from common.matching.docking import inverse_pose  # noqa: F401

#: weight of a candidate's paint evidence (mm of crack with continuing paint) against its geometric
#: contact (mm of shared crack) when choosing a pair's pose among the docking's candidates; chosen on
#: realistic synthetic walls (``generate_wall(16, seed 31–36, preset="pompeii")``, pose accuracy within
#: 5° and 5 mm of their true pairs' 30 candidates: ``python tests/bench/bench_pose.py``), not on the
#: walls or collections the figures in docs/matching.md are measured on
POSE_PAINT_WEIGHT = 6.0
#: candidate poses a proposal offers beside its chosen one (``alignment.alternatives``), best first:
#: the review page steps through them when the chosen pose is not the join (the true pose is among
#: the docking's 30 candidates for about a third of RePAIR's true pairs, chosen for a seventh)
ALTERNATIVE_POSES = 9


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
                cell_mm: float = DOCK_CELL_MM) -> Docking:
    """The pair's pose: the candidate with the best :func:`pose_scores` (the first on a tie).

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
    """
    return ranked_poses(dockings, paint_mm, weight=weight, cell_mm=cell_mm)[0]


def ranked_poses(dockings: Sequence[Docking], paint_mm, *, weight: float = POSE_PAINT_WEIGHT,
                 cell_mm: float = DOCK_CELL_MM, distinct_deg: float = 3.0, distinct_mm: float = 3.0) -> list[Docking]:
    """The pair's candidate poses best first by :func:`pose_scores`, without near repeats: a candidate
    whose angle is within ``distinct_deg`` and translation within ``distinct_mm`` of a better one's is
    left out (the docking keeps several maxima per rotation). The first is :func:`choose_pose`'s.

    Examples
    --------
    >>> from common.matching.docking import Docking
    >>> d = [Docking(0, 0, 0, 60.0, 45, 0), Docking(90, 5, 0, 50.0, 37.5, 0), Docking(1, 1, 0, 58.0, 44, 0)]
    >>> [p.angle_deg for p in ranked_poses(d, [0.0, 4.0, 0.0], weight=2.0)]   # (1, 1) repeats (0, 0)
    [90, 0]
    """
    docks = list(dockings)
    order = np.argsort(-pose_scores(docks, paint_mm, weight=weight, cell_mm=cell_mm), kind="stable")
    kept: list[Docking] = []
    for i in order:
        d = docks[int(i)]
        if not any(abs((d.angle_deg - k.angle_deg + 180.0) % 360.0 - 180.0) <= distinct_deg
                   and np.hypot(d.tx_mm - k.tx_mm, d.ty_mm - k.ty_mm) <= distinct_mm for k in kept):
            kept.append(d)
    return kept


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
    return float((angle + turn + 180.0) % 360.0 - 180.0), float(t[0]), float(t[1])


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
    return float(-((a0 - a1 + 180.0) % 360.0 - 180.0)), float(shift[0]), float(shift[1])
