"""The per-match check: a 2-D analogue of the ribbon matcher (thesis §5.2.1, §5.3).

The thesis aligns two fragments by sliding thin 3-D "ribbons" of their fracture surfaces along each
other, scoring the gap between them and the volume where they interpenetrate. A flatbed sees each
fragment from above, so here the ribbon is the fragment's 2-D boundary strip: both contours are
resampled by arc length, every relative alignment of a window of one against a window of the other
is fitted in closed form (2-D Procrustes, all pairs at once as matrix products), and the best
candidates are scored by

* the **gap** (RMS distance between the two boundaries where they touch),
* the **contact length** (how much of the boundary lies within ``tolerance_mm`` of the other), and
* the **overlap** (the 2-D "volume intersection": area in mm² where the two rasterised outlines
  cover the same ground — real neighbours do not interpenetrate).

Coordinates are fragment-frame millimetres, ``x`` = column × pixel_mm (right) and ``y`` = row ×
pixel_mm (down), as in :mod:`common.features`. The returned pose maps fragment B's frame into
fragment A's: ``p_a = R(angle) @ p_b + t`` with ``R = [[cos, -sin], [sin, cos]]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class Alignment:
    """Relative pose of fragment B in fragment A's frame and how well the two fit.

    Attributes
    ----------
    angle_deg, tx_mm, ty_mm : float
        Pose mapping B's frame into A's: ``p_a = R(angle_deg) @ p_b + (tx_mm, ty_mm)``.
    gap_mm : float
        RMS distance between the boundaries over the contact (NaN without contact).
    contact_mm : float
        Length of B's boundary within ``tolerance_mm`` of A's after alignment.
    overlap_mm2 : float
        Area where the two aligned outlines overlap (the 2-D volume intersection).
    score : float
        ``contact_mm - overlap_mm2 / penetration_mm``: higher is better.
    alternatives : tuple of (angle_deg, tx_mm, ty_mm)
        Other candidate poses of B in A's frame, best first (stage 3's docking offers them; empty
        otherwise).
    """

    angle_deg: float
    tx_mm: float
    ty_mm: float
    gap_mm: float
    contact_mm: float
    overlap_mm2: float
    score: float
    alternatives: tuple = ()

    @property
    def matrix(self) -> np.ndarray:
        """3×3 homogeneous transform taking B's frame (mm) into A's."""
        return pose_matrix(self.angle_deg, self.tx_mm, self.ty_mm)

    def to_dict(self) -> dict:
        d = {k: float(getattr(self, k)) for k in
             ("angle_deg", "tx_mm", "ty_mm", "gap_mm", "contact_mm", "overlap_mm2", "score")}
        if self.alternatives:
            d["alternatives"] = [dict(zip(("angle_deg", "tx_mm", "ty_mm"), map(float, a))) for a in self.alternatives]
        return d


def pose_matrix(angle_deg: float, tx_mm: float, ty_mm: float) -> np.ndarray:
    """Homogeneous 3×3 matrix of ``p' = R(angle) @ p + t``, ``R = [[cos, -sin], [sin, cos]]``."""
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    return np.array([[c, -s, tx_mm], [s, c, ty_mm], [0.0, 0.0, 1.0]])


def apply_pose(points_mm: np.ndarray, angle_deg: float, tx_mm: float, ty_mm: float) -> np.ndarray:
    """Apply ``p' = R(angle) @ p + t`` to (K, 2) points."""
    m = pose_matrix(angle_deg, tx_mm, ty_mm)
    return np.asarray(points_mm, float) @ m[:2, :2].T + m[:2, 2]


def signed_area_mm2(contour_mm: np.ndarray) -> float:
    """Shoelace signed area of a closed polygon (positive when x→y turns counter-clockwise)."""
    x, y = contour_mm[:, 0], contour_mm[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def resample_contour(contour_mm: np.ndarray, step_mm: float, *, positive: bool = True) -> np.ndarray:
    """Resample a closed contour at equal arc-length steps.

    Parameters
    ----------
    contour_mm : (M, 2) array
        Closed polygon (the last vertex connects back to the first), mm.
    step_mm : float
        Arc-length spacing of the output samples.
    positive : bool
        Return the contour with positive signed area (one consistent orientation), reversing it
        if needed, so that two neighbours' shared boundary runs in opposite directions.

    Returns
    -------
    (K, 2) array of points, K = round(perimeter / step_mm) ≥ 3.
    """
    c = np.asarray(contour_mm, dtype=float)
    if c.ndim != 2 or c.shape[1] != 2 or len(c) < 3:
        raise ValueError(f"contour_mm must be (M ≥ 3, 2), got {c.shape}")
    if not step_mm > 0:
        raise ValueError(f"step_mm must be positive, got {step_mm}")
    if positive and signed_area_mm2(c) < 0:
        c = c[::-1]
    closed = np.vstack([c, c[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    perimeter = arc[-1]
    if perimeter <= 0:
        raise ValueError("contour_mm has zero length")
    k = max(3, int(round(perimeter / step_mm)))
    s = np.linspace(0.0, perimeter, k, endpoint=False)
    return np.column_stack([np.interp(s, arc, closed[:, 0]), np.interp(s, arc, closed[:, 1])])


def strip_windows(points: np.ndarray, width: int, *, reverse: bool = False) -> np.ndarray:
    """All windows of ``width`` consecutive samples of a closed resampled contour.

    Window ``i`` holds samples ``i, i+1, …`` (or ``i, i-1, …`` with ``reverse``), so the window's
    middle sample is ``i ± width // 2``. Returns (K, width, 2).
    """
    k = len(points)
    offs = np.arange(width)
    idx = (np.arange(k)[:, None] + (-offs if reverse else offs)[None, :]) % k
    return points[idx]


def procrustes_all_pairs(win_a: np.ndarray, win_b: np.ndarray):
    """Best rigid 2-D fit of every window of B onto every window of A, in closed form.

    For windows ``a`` (W,2) and ``b`` (W,2) the rotation minimising Σ|a_c − R b_c|² has
    ``tan θ = Σ(b_x a_y − b_y a_x) / Σ(b_x a_x + b_y a_y)`` over the centred points and the
    residual ``Σ|a_c|² + Σ|b_c|² − 2·sqrt(C² + S²)``; with all windows stacked both sums are
    matrix products, so (Ka × Kb) fits cost four GEMMs.

    Returns
    -------
    rms_mm : (Ka, Kb) RMS residual, angle_rad : (Ka, Kb) rotation of B onto A.
    """
    ca = win_a - win_a.mean(axis=1, keepdims=True)
    cb = win_b - win_b.mean(axis=1, keepdims=True)
    w = win_a.shape[1]
    c = ca[:, :, 0] @ cb[:, :, 0].T + ca[:, :, 1] @ cb[:, :, 1].T
    s = ca[:, :, 1] @ cb[:, :, 0].T - ca[:, :, 0] @ cb[:, :, 1].T
    na = (ca ** 2).sum(axis=(1, 2))
    nb = (cb ** 2).sum(axis=(1, 2))
    res = na[:, None] + nb[None, :] - 2.0 * np.hypot(c, s)
    return np.sqrt(np.maximum(res, 0.0) / w), np.arctan2(s, c)


def _rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray]:
    """Rotation angle (rad) and translation of the rigid fit a ≈ R b + t."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    ca, cb = a - ma, b - mb
    theta = np.arctan2(np.sum(cb[:, 0] * ca[:, 1] - cb[:, 1] * ca[:, 0]), np.sum(cb[:, 0] * ca[:, 0] + cb[:, 1] * ca[:, 1]))
    r = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    return float(theta), ma - r @ mb


def overlap_area_mm2(contour_a_mm: np.ndarray, contour_b_mm: np.ndarray, cell_mm: float = 0.5) -> float:
    """Area (mm²) covered by both closed outlines, by rasterising them on a common grid.

    This is the 2-D counterpart of the ribbon matcher's volume intersection (§5.3): true
    neighbours touch along their break but do not cover the same ground.
    """
    lo = np.minimum(contour_a_mm.min(axis=0), contour_b_mm.min(axis=0)) - 2 * cell_mm
    hi = np.maximum(contour_a_mm.max(axis=0), contour_b_mm.max(axis=0)) + 2 * cell_mm
    lo_i = np.maximum(contour_a_mm.min(axis=0), contour_b_mm.min(axis=0))
    hi_i = np.minimum(contour_a_mm.max(axis=0), contour_b_mm.max(axis=0))
    if np.any(hi_i <= lo_i):
        return 0.0  # bounding boxes do not even intersect
    shape = np.ceil((hi - lo) / cell_mm).astype(int)[::-1] + 1
    shift = 4  # sub-pixel polygon coordinates for cv2.fillPoly
    masks = []
    for c in (contour_a_mm, contour_b_mm):
        m = np.zeros(shape, np.uint8)
        pts = np.round((c - lo) / cell_mm * (1 << shift)).astype(np.int32)
        cv2.fillPoly(m, [pts], 1, lineType=cv2.LINE_8, shift=shift)
        # fillPoly paints every cell the outline touches, so two outlines that merely share an
        # edge would overlap by a cell-wide band; one cell of erosion removes that band
        masks.append(cv2.erode(m, np.ones((3, 3), np.uint8)))
    return float(np.count_nonzero(masks[0] & masks[1])) * cell_mm ** 2


def _evaluate(a_pts, tree_a, b_pts, contour_a, contour_b, theta, t, step_mm, tolerance_mm, cell_mm):
    r = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    bt = b_pts @ r.T + t
    d, _ = tree_a.query(bt, distance_upper_bound=4 * tolerance_mm)
    near = d <= tolerance_mm
    contact = float(near.sum()) * step_mm
    gap = float(np.sqrt(np.mean(d[near] ** 2))) if near.any() else float("nan")
    overlap = overlap_area_mm2(contour_a, contour_b @ r.T + t, cell_mm)
    return bt, d, contact, gap, overlap


def align_hypotheses(contour_a_mm: np.ndarray, contour_b_mm: np.ndarray, *, step_mm: float = 1.0,
                    window_mm: float = 24.0, tolerance_mm: float = 1.5, penetration_mm: float = 1.0,
                    n_candidates: int = 24, icp_iterations: int = 8, cell_mm: float = 0.5,
                    anchors: tuple[np.ndarray, np.ndarray] | None = None) -> list[Alignment]:
    """Candidate alignments of fragment B to fragment A along their boundaries, best first (§5.3).

    Distinct poses (one per refined window pair, duplicates merged) sorted by score; see
    :func:`align_fragments` for the method and parameters. The matcher re-scores these
    hypotheses with the patch classifier (the patches each pose puts face to face).
    """
    return _align(contour_a_mm, contour_b_mm, step_mm=step_mm, window_mm=window_mm, tolerance_mm=tolerance_mm,
                  penetration_mm=penetration_mm, n_candidates=n_candidates, icp_iterations=icp_iterations,
                  cell_mm=cell_mm, anchors=anchors)


def align_fragments(contour_a_mm: np.ndarray, contour_b_mm: np.ndarray, *, step_mm: float = 1.0,
                    window_mm: float = 24.0, tolerance_mm: float = 1.5, penetration_mm: float = 1.0,
                    n_candidates: int = 24, icp_iterations: int = 8, cell_mm: float = 0.5,
                    anchors: tuple[np.ndarray, np.ndarray] | None = None) -> Alignment:
    """Align fragment B to fragment A along their boundaries (2-D ribbon matcher, §5.2.1/§5.3).

    Both boundaries are resampled every ``step_mm`` with one orientation, so a shared break runs
    forwards on A and backwards on B. Every window of ``window_mm`` on A is fitted to every
    reversed window on B by 2-D Procrustes (exhaustive, vectorised: :func:`procrustes_all_pairs`);
    the ``n_candidates`` best fits (one per A window neighbourhood) are refined by a few
    iterations of closest-point fitting on the points in contact and scored by contact length,
    gap and overlap area. The best score wins.

    Parameters
    ----------
    contour_a_mm, contour_b_mm : (M, 2), (N, 2) arrays
        Closed outlines in each fragment's own frame, mm (x right, y down).
    step_mm : float
        Arc-length sampling of the strips.
    window_mm : float
        Length of the strip pieces compared in the exhaustive search.
    tolerance_mm : float
        Distance under which two boundary points count as in contact (erosion and scan noise).
    penetration_mm : float
        Converts overlap area into a length penalty: ``score = contact − overlap / penetration``.
    n_candidates : int
        Window pairs refined and scored in full.
    icp_iterations : int
        Closest-point refinement steps per candidate.
    cell_mm : float
        Raster cell for the overlap area.
    anchors : pair of (Ka,), (Kb,) arc positions in mm, optional
        Restrict the search to windows centred within ``window_mm / 2`` of these arc positions on
        each contour (e.g. the best patch pairs of the classifier), arc measured from the first
        vertex of the contour as given, along its given direction.

    Returns
    -------
    Alignment
        Pose of B in A's frame with its gap, contact, overlap and score.

    References
    ----------
    Toler-Franklin, thesis §5.2.1 (staged matching) and §5.3 (ribbon matcher: exhaustive
    alignment search, gap and volume-intersection scores); Brown et al., SIGGRAPH 2008.

    Examples
    --------
    >>> t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    >>> a = np.column_stack([20 * np.cos(t), 20 * np.sin(t)])
    >>> al = align_fragments(a, a + 50.0)   # two discs: they can touch at one point only
    >>> al.contact_mm < 15
    True
    """
    return _align(contour_a_mm, contour_b_mm, step_mm=step_mm, window_mm=window_mm, tolerance_mm=tolerance_mm,
                  penetration_mm=penetration_mm, n_candidates=n_candidates, icp_iterations=icp_iterations,
                  cell_mm=cell_mm, anchors=anchors)[0]


def _align(contour_a_mm, contour_b_mm, *, step_mm, window_mm, tolerance_mm, penetration_mm, n_candidates,
           icp_iterations, cell_mm, anchors):
    a_raw = np.asarray(contour_a_mm, float)
    b_raw = np.asarray(contour_b_mm, float)
    for name, c in (("contour_a_mm", a_raw), ("contour_b_mm", b_raw)):
        if c.ndim != 2 or c.shape[1] != 2 or len(c) < 3 or not np.all(np.isfinite(c)):
            raise ValueError(f"{name} must be a finite (M ≥ 3, 2) array, got shape {c.shape}")
    if not window_mm > 2 * step_mm:
        raise ValueError(f"window_mm ({window_mm}) must exceed two steps ({2 * step_mm})")
    if not tolerance_mm > 0 or not penetration_mm > 0:
        raise ValueError("tolerance_mm and penetration_mm must be positive")
    a = resample_contour(a_raw, step_mm)
    b = resample_contour(b_raw, step_mm)
    # polygons with the same orientation as the samples, for the overlap raster
    a_poly = a_raw if signed_area_mm2(a_raw) >= 0 else a_raw[::-1]
    b_poly = b_raw if signed_area_mm2(b_raw) >= 0 else b_raw[::-1]
    width = max(3, int(round(window_mm / step_mm)))
    width = min(width, len(a), len(b))
    win_a = strip_windows(a, width)
    win_b = strip_windows(b, width, reverse=True)
    rows = np.arange(len(a))
    cols = np.arange(len(b))
    if anchors is not None:
        rows = _anchor_windows(a_raw, anchors[0], len(a), width, step_mm, reverse=False)
        cols = _anchor_windows(b_raw, anchors[1], len(b), width, step_mm, reverse=True)
    rms, ang = procrustes_all_pairs(win_a[rows], win_b[cols])
    # best B window per A window, then the n best A windows spread along A (non-maximum suppression)
    best_j = np.argmin(rms, axis=1)
    best = rms[np.arange(len(rows)), best_j]
    order = np.argsort(best)
    chosen: list[int] = []
    taken = np.zeros(len(a), bool)
    for o in order:
        ia = rows[o]
        if taken[ia]:
            continue
        chosen.append(o)
        taken[(ia + np.arange(-width // 4, width // 4 + 1)) % len(a)] = True
        if len(chosen) >= n_candidates:
            break
    tree_a = cKDTree(a)
    results: list[Alignment] = []
    for o in chosen:
        wa, wb = win_a[rows[o]], win_b[cols[best_j[o]]]
        theta, t = _rigid_fit(wa, wb)
        # closest-point refinement on the points in contact: extends the fit from the window to
        # the whole shared break
        for it in range(icp_iterations):
            r = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
            bt = b @ r.T + t
            # capture radius shrinks from 2 to 0.5 tolerances: wide to pull in, tight to settle
            bound = tolerance_mm * (2.0 - 1.5 * it / max(icp_iterations - 1, 1))
            d, j = tree_a.query(bt, distance_upper_bound=bound)
            near = np.isfinite(d)
            if near.sum() < 3:
                break
            theta, t = _rigid_fit(a[j[near]], b[near])
        _, _, contact, gap, overlap = _evaluate(a, tree_a, b, a_poly, b_poly, theta, t, step_mm,
                                                tolerance_mm, cell_mm)
        score = contact - overlap / penetration_mm
        results.append(Alignment(float(np.degrees(theta)), float(t[0]), float(t[1]), gap, contact, overlap, score))
    results.sort(key=lambda r: -r.score)
    distinct: list[Alignment] = []
    for r in results:  # refinement often brings several windows to the same pose
        if not any(abs((r.angle_deg - d.angle_deg + 180) % 360 - 180) < 2.0
                   and np.hypot(r.tx_mm - d.tx_mm, r.ty_mm - d.ty_mm) < 2.0 for d in distinct):
            distinct.append(r)
    return distinct


def _anchor_windows(contour, arcs_mm, k, width, step_mm, *, reverse):
    """Window start indices whose middle sample lies within half a window of an anchor arc."""
    arcs_mm = np.atleast_1d(np.asarray(arcs_mm, float))
    closed = np.vstack([contour, contour[:1]])
    perimeter = float(np.hypot(*np.diff(closed, axis=0).T).sum())
    if signed_area_mm2(contour) < 0:  # resampling reversed the contour
        arcs_mm = perimeter - arcs_mm
    centre = np.round(arcs_mm / perimeter * k).astype(int)
    half = width // 2
    mids = (centre[:, None] + np.arange(-half, half + 1)[None, :]).ravel() % k
    starts = (mids + half) % k if reverse else (mids - half) % k
    return np.unique(starts)
