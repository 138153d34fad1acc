"""How two fragment outlines face each other at a candidate pose: the facing stretch and its gap.

The docking (:mod:`common.matching.docking`) scores a pose by one number, the length of outline in the
other's lost-material band. On eroded real outlines that number is as high at many wrong poses as at the
true one (docs/matching.md, "Why the true pose scores low"), but *how* the two outlines face each other
still differs. :func:`facing_geometry` measures it at many poses at once, from each outline resampled at
an even step and looked up in the other's signed distance map: how much of each outline faces the other
and in one run, the gap across the facing stretch (its quantiles and its roughness along the run), how
much is pushed into the other piece, whether the two outlines' curvature profiles follow each other along
the run (κ_A = −κ_B where one bulges into the other's hollow, both traversed the same way), and how far
apart the two facing runs end. They are the cues of the learned pose chooser
(:func:`common.matching.pose.learned_pose_scores`). Measured on the docking's candidates (docs/matching.md,
"A learned pose chooser"): at the true pose the gap is *wider at its narrowest* and narrower at its widest
(material lost evenly along a crack, not a tight fit here and a wide one there) and steadier; the
curvature profiles follow each other *less* than at the wrong candidates — the docking's wrong poses are
where two outlines run parallel, while a true crack ends where both outlines turn away from it (convex
corners on both sides: κ_A and κ_B of one sign). :func:`probe_poses` gives the poses a small move along,
across and about a candidate's facing stretch (to probe whether a cue peaks at the candidate).

Curvature profiles along fragment boundaries are the classical puzzle-assembly cue (Freeman & Garder
1964; Kong & Kimia 2001, curvature-based boundary matching); the gap statistics follow the gap-tolerant
scores of the ribbon matcher (Toler-Franklin, thesis §5.3).

The pose convention is the docking's: fragment-frame millimetres (x right, y down) and
``p_a = R(angle_deg) @ p_b + (tx_mm, ty_mm)``.
"""

from __future__ import annotations

import cv2
import numpy as np

from common.matching.alignment import resample_contour
from common.matching.docking import _rotation

#: resampling step of the outlines, mm
FACING_STEP_MM = 1.0
#: a point of one outline faces the other where it lies between this far inside it ...
FACING_INSIDE_MM = 1.5
#: ... and this far outside it (the widest lost material expected, with margin)
FACING_OUTSIDE_MM = 8.0
#: a point is in tight contact within this distance of the other outline, mm
FACING_TIGHT_MM = 2.0
#: cell of the signed distance maps the outlines are looked up in, mm
SIGNED_CELL_MM = 0.5
#: curvature scale: the outline's turn over ± this arc length, mm
FACING_CURVATURE_MM = 4.0
#: the paint is probed this far along and across the facing stretch, and turned this much about it
PROBE_ALONG_MM, PROBE_ACROSS_MM, PROBE_TURN_DEG = 3.0, 1.5, 2.0

#: the columns of :func:`facing_geometry`'s rows
FACING_COLUMNS = ("face_mm", "run_mm", "tight_mm", "gap_q10_mm", "gap_median_mm", "gap_q90_mm", "gap_rough_mm",
                  "inside_mm", "depth_mm", "curvature_mismatch", "curvature_correlation", "end_mismatch_mm")


def turning_curvature(points: np.ndarray, half_mm: float = FACING_CURVATURE_MM,
                      step_mm: float = FACING_STEP_MM) -> np.ndarray:
    """Signed curvature (1/mm) of an evenly resampled closed outline at the scale ``half_mm``: the turn
    from the chord ``i − k → i`` to the chord ``i → i + k`` over the arc ``k × step_mm`` between the
    chords' midpoints (``k = half_mm / step_mm``); positive where it turns anticlockwise with x right and
    y up (clockwise on screen, y down); the sign flips with the direction of traversal.

    Examples
    --------
    >>> t = np.linspace(0, 2 * np.pi, 63, endpoint=False)
    >>> circle = np.stack([10 * np.cos(t), 10 * np.sin(t)], 1)          # radius 10 mm, step ≈ 1 mm
    >>> bool(np.allclose(turning_curvature(circle, 4.0, 2 * np.pi * 10 / 63), 0.1, atol=0.005))
    True
    """
    p = np.asarray(points, float)
    k = max(1, int(round(half_mm / step_mm)))
    d1 = p - np.roll(p, k, axis=0)
    d2 = np.roll(p, -k, axis=0) - p
    turn = np.arctan2(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0], (d1 * d2).sum(1))
    return turn / (k * step_mm)


def signed_distance_map(contour_mm: np.ndarray, cell_mm: float, margin_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (mm) to a closed outline on a grid of ``cell_mm`` cells reaching ``margin_mm``
    beyond it: positive outside, negative inside (the outline filled at 1/16-cell precision, OpenCV's
    5x5 distance transform both ways).

    Returns
    -------
    distance_mm : (H, W) float32
    origin_mm : (2,) float
        ``(x, y)`` of cell ``[0, 0]``; :func:`sample_map` looks points up in it.
    """
    c = np.asarray(contour_mm, float)
    origin = c.min(0) - margin_mm
    hi = c.max(0) + margin_mm
    shape = (int(np.ceil((hi[1] - origin[1]) / cell_mm)) + 1, int(np.ceil((hi[0] - origin[0]) / cell_mm)) + 1)
    m = np.zeros(shape, np.uint8)
    cv2.fillPoly(m, [np.round((c - origin) / cell_mm * 16).astype(np.int32)], 1, shift=4)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, 5)
    return ((outside - inside) * cell_mm).astype(np.float32), origin


def sample_map(values: np.ndarray, origin_mm: np.ndarray, cell_mm: float, points_mm: np.ndarray,
               off_grid: float) -> np.ndarray:
    """``values`` (a map of :func:`signed_distance_map`'s grid) at the nearest cell of each point
    (``(..., 2)`` mm), ``off_grid`` where a point falls outside the grid."""
    ij = np.round((points_mm - origin_mm) / cell_mm).astype(int)
    h, w = values.shape
    ok = (ij[..., 0] >= 0) & (ij[..., 0] < w) & (ij[..., 1] >= 0) & (ij[..., 1] < h)
    return np.where(ok, values[np.clip(ij[..., 1], 0, h - 1), np.clip(ij[..., 0], 0, w - 1)], off_grid)


def _longest_runs(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start index and length of each row's longest circular run of True, (N,) each: the first longest
    counted from the row's first False (a row all True: 0 and its length; none True: 0 and 0)."""
    masks = np.asarray(masks, bool)
    n_rows, n = masks.shape
    starts, lengths = np.zeros(n_rows, np.int64), np.zeros(n_rows, np.int64)
    full = masks.all(axis=1)
    lengths[full] = n
    rows = np.nonzero(~full & masks.any(axis=1))[0]
    if not len(rows):
        return starts, lengths
    shift = np.argmin(masks[rows], axis=1)       # start each row at a False so no run wraps
    rolled = np.take_along_axis(masks[rows], (shift[:, None] + np.arange(n)) % n, axis=1).astype(np.int8)
    d = np.diff(np.pad(rolled, ((0, 0), (1, 1))), axis=1)
    row_on, col_on = np.nonzero(d == 1)           # row-major: each row's runs in order, ends paired with starts
    _, col_off = np.nonzero(d == -1)
    run = col_off - col_on
    # each row's first longest run: stable order by row, then longest first
    order = np.lexsort((-run, row_on))
    first = order[np.r_[0, np.nonzero(np.diff(row_on[order]))[0] + 1]]
    starts[rows] = (col_on[first] + shift) % n
    lengths[rows] = run[first]
    return starts, lengths


def _facing_percentiles(distance_mm: np.ndarray, facing: np.ndarray, q, empty: float) -> np.ndarray:
    """Per row, percentiles ``q`` (numpy's linear interpolation) of the facing points' gaps (distances clipped at
    0, where ``facing``); ``empty`` where a row has none. (N, len(q))."""
    n = facing.sum(1)
    gaps = np.sort(np.where(facing, np.clip(distance_mm, 0, None), np.inf), axis=1)
    out = np.full((len(n), len(q)), float(empty))
    ok = n > 0
    if not ok.any():
        return out
    rows = np.nonzero(ok)[0]
    last = (n[ok] - 1)[:, None]
    virtual = last * (np.asarray(q, float) / 100.0)[None]
    below = np.floor(virtual).astype(int)
    above = np.minimum(below + 1, last)
    gamma = virtual - below
    a = np.take_along_axis(gaps[rows], below, 1)
    b = np.take_along_axis(gaps[rows], above, 1)
    diff = b - a
    # numpy's lerp: from below for gamma < 0.5, from above otherwise (the same numbers as np.percentile)
    out[rows] = np.where(gamma >= 0.5, b - diff * (1 - gamma), a + diff * gamma)
    return out


def facing_geometry(contour_a_mm: np.ndarray, contour_b_mm: np.ndarray, poses, *, step_mm: float = FACING_STEP_MM,
                    inside_mm: float = FACING_INSIDE_MM, outside_mm: float = FACING_OUTSIDE_MM,
                    tight_mm: float = FACING_TIGHT_MM, curvature_mm: float = FACING_CURVATURE_MM):
    """The facing geometry of fragment B posed against fragment A, at each of N poses.

    Both outlines are resampled every ``step_mm``; at a pose each point of B's is looked up in A's signed
    distance map and each point of A's in B's (0.5 mm grid). A point *faces* the other outline where it
    lies between ``inside_mm`` inside and ``outside_mm`` outside it; the *facing run* of an outline is its
    longest contiguous stretch of facing points.

    Parameters
    ----------
    contour_a_mm, contour_b_mm : (M, 2), (K, 2) arrays
        Closed outlines in each fragment's frame, mm, traversed the same way (as the features stage
        stores them).
    poses : (N, 3) array_like
        ``(angle_deg, tx_mm, ty_mm)`` of B in A's frame.
    step_mm, inside_mm, outside_mm, tight_mm, curvature_mm : float
        Resampling step; the facing band; the tight-contact distance; the curvature scale
        (:func:`turning_curvature`).

    Returns
    -------
    rows : (N, 12) float
        :data:`FACING_COLUMNS`: facing length (mean of the two outlines, mm); facing run length (mean,
        mm); length in tight contact (mm); 10th / 50th / 90th percentile of the gap over the facing
        points (mm, inside counted 0); the gap's roughness along B's facing run (standard deviation
        about its 10 mm running mean, mm); length pushed more than ``inside_mm`` into the other piece
        (mean, mm) and the deepest point (mm); the curvature mismatch along B's facing run (mean
        ``|κ_A + κ_B|`` at nearest points, 1/mm: 0 for complementary outlines) and the correlation of
        ``κ_A`` with ``−κ_B`` there (0 where either is constant); the distance between the ends of the
        two facing runs (mean over the two ends, the runs paired end to end, mm; 30 where a run is
        shorter than 6 points): large where one outline leaves the crack and the other runs on in the band.
    directions : (N, 2) float
        Unit direction of B's facing run in A's frame (its principal axis; (1, 0) for a short run).
    centres : (N, 2) float
        Centre of B's facing run in A's frame, mm.

    Notes
    -----
    Cost: O(N · (M + K)) lookups and the facing runs, done for all poses at once, plus a few small
    reductions per pose along B's facing run; ≈ 10 ms CPU for a pair's 30 docking candidates and 25 ms for
    the station's 100 (docs/matching.md, "More candidate poses to offer").
    """
    from scipy.spatial import cKDTree

    p = np.asarray(poses, float).reshape(-1, 3)
    if not np.all(np.isfinite(p)):
        raise ValueError("poses must be finite (angle_deg, tx_mm, ty_mm)")
    for name, c in (("contour_a_mm", contour_a_mm), ("contour_b_mm", contour_b_mm)):
        c = np.asarray(c, float)
        if c.ndim != 2 or c.shape[1] != 2 or len(c) < 3 or not np.all(np.isfinite(c)):
            raise ValueError(f"{name} must be a finite (N >= 3, 2) outline, got shape {c.shape}")
    pa = resample_contour(contour_a_mm, step_mm, positive=False)
    pb = resample_contour(contour_b_mm, step_mm, positive=False)
    ka, kb_all = turning_curvature(pa, curvature_mm, step_mm), turning_curvature(pb, curvature_mm, step_mm)
    # far (1000 mm) off the grids
    (sdf_a, lo_a), (sdf_b, lo_b) = (signed_distance_map(c, SIGNED_CELL_MM, outside_mm + 4.0)
                                    for c in (contour_a_mm, contour_b_mm))
    tree_a = cKDTree(pa)
    # every pose at once: B's points in A's frame and A's in B's, and each looked up in the other's map
    rot = np.stack([_rotation(a) for a in p[:, 0]]) if len(p) else np.zeros((0, 2, 2))
    t = p[:, None, 1:3]
    qb_all = np.matmul(pb[None], rot.transpose(0, 2, 1)) + t              # (N, K_b, 2)
    db_all = sample_map(sdf_a, lo_a, SIGNED_CELL_MM, qb_all, 1e3)
    da_all = sample_map(sdf_b, lo_b, SIGNED_CELL_MM, np.matmul(pa[None] - t, rot), 1e3)
    fb_all = (db_all > -inside_mm) & (db_all < outside_mm)
    fa_all = (da_all > -inside_mm) & (da_all < outside_mm)
    face = (fa_all.sum(1) + fb_all.sum(1)) / 2 * step_mm
    inside = ((da_all < -inside_mm).sum(1) + (db_all < -inside_mm).sum(1)) / 2 * step_mm
    depth = np.maximum(0.0, -np.minimum(da_all.min(1, initial=np.inf), db_all.min(1, initial=np.inf)))
    tight = ((np.abs(da_all) < tight_mm).sum(1) + (np.abs(db_all) < tight_mm).sum(1)) / 2 * step_mm
    gap_q = _facing_percentiles(np.concatenate([da_all, db_all], 1), np.concatenate([fa_all, fb_all], 1),
                                (10, 50, 90), outside_mm)
    rows = np.empty((len(p), len(FACING_COLUMNS)))
    directions = np.tile([1.0, 0.0], (len(p), 1))
    centres = qb_all.mean(1)
    (run_b, len_b), (run_a, len_a) = _longest_runs(fb_all), _longest_runs(fa_all)
    # A's outline point nearest each point of B's facing run, for every pose in one query
    runs_b = [(run_b[i] + np.arange(len_b[i])) % len(pb) for i in range(len(p))]
    long_b = [i for i in range(len(p)) if len_b[i] >= 6]
    nearest = {}
    if long_b:
        _, nn_all = tree_a.query(np.concatenate([qb_all[i][runs_b[i]] for i in long_b]))
        nearest = dict(zip(long_b, np.split(nn_all, np.cumsum([len_b[i] for i in long_b])[:-1])))
    for i in range(len(p)):
        qb, db = qb_all[i], db_all[i]
        sa0, na, nb, idx_b = int(run_a[i]), int(len_a[i]), int(len_b[i]), runs_b[i]
        rough, mismatch, corr, end = 0.0, 0.0, 0.0, 30.0
        if nb >= 6:
            g = db[idx_b]
            w = min(10, nb)
            smooth = np.convolve(np.pad(g, w // 2, mode="edge"), np.ones(w) / w, mode="same")[w // 2:w // 2 + nb]
            rough = float(np.std(g - smooth))
            kb, kan = kb_all[idx_b], ka[nearest[i]]
            mismatch = float(np.mean(np.abs(kan + kb)))       # complementary outlines: κ_A = −κ_B
            if np.std(kan) > 1e-9 and np.std(kb) > 1e-9:
                corr = float(np.corrcoef(kan, -kb)[0, 1])
            seg = qb[idx_b]
            centres[i] = seg.mean(0)
            directions[i] = np.linalg.svd(seg - centres[i], full_matrices=False)[2][0]
            if na >= 6:
                idx_a = (sa0 + np.arange(na)) % len(pa)
                a0, a1 = pa[idx_a[0]], pa[idx_a[-1]]
                b0, b1 = qb[idx_b[0]], qb[idx_b[-1]]
                # two outlines traversed the same way run in opposite directions along a shared crack
                end = float(min(np.linalg.norm(b0 - a1) + np.linalg.norm(b1 - a0),
                                np.linalg.norm(b0 - a0) + np.linalg.norm(b1 - a1)) / 2)
        rows[i] = (face[i], (nb + na) / 2 * step_mm, tight[i], *gap_q[i], rough, inside[i], depth[i], mismatch, corr,
                   end)
    return rows, directions, centres


def probe_poses(poses, directions, centres, *, along_mm: float = PROBE_ALONG_MM, across_mm: float = PROBE_ACROSS_MM,
                turn_deg: float = PROBE_TURN_DEG) -> np.ndarray:
    """Each pose moved a little: B slid ∓/± ``along_mm`` along its facing run, moved ∓/± ``across_mm``
    across it, and turned ∓/± ``turn_deg`` about the run's centre (A's frame).

    Returns
    -------
    (N, 6, 3) float
        Per pose: along −, along +, across −, across +, turned −, turned + (``angle_deg, tx_mm, ty_mm``).

    Examples
    --------
    >>> probe_poses([[0, 0, 0]], [[1, 0]], [[0, 0]])[0].round(6).tolist()
    [[0.0, -3.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, -1.5], [0.0, 0.0, 1.5], [-2.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
    """
    p = np.asarray(poses, float).reshape(-1, 3)
    u = np.asarray(directions, float).reshape(-1, 2)
    c = np.asarray(centres, float).reshape(-1, 2)
    if not (len(p) == len(u) == len(c)):
        raise ValueError("poses, directions and centres must have one row each per pose, got "
                         f"{len(p)}, {len(u)}, {len(c)}")
    out = np.empty((len(p), 6, 3))
    for i, ((a, tx, ty), d, centre) in enumerate(zip(p, u, c)):
        n = np.array([-d[1], d[0]])
        rows = [(a, tx + s * d[0], ty + s * d[1]) for s in (-along_mm, along_mm)]
        rows += [(a, tx + s * n[0], ty + s * n[1]) for s in (-across_mm, across_mm)]
        for turn in (-turn_deg, turn_deg):
            t = _rotation(turn) @ (np.array([tx, ty]) - centre) + centre      # B turned about the run's centre
            rows.append((a + turn, t[0], t[1]))
        out[i] = rows
    return out
