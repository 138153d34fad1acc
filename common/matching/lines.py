"""Pose hypotheses from painted lines and bands that cross a fragment's edge (issue 15, session 9).

The docking (:mod:`common.matching.docking`) proposes candidate poses from the outlines' contact
alone, and on eroded real outlines that score leaves the true pose out for two thirds of true pairs
(docs/matching.md, "Poses that fit"). This module proposes poses from the paint instead: where a
painted line, band or colour zone is cut by a fragment's edge, its *boundary* crosses the outline
at a point, in a direction, with one colour on either side. Two such crossings, one on each
fragment, with the same two colours (in the opposite order: two outlines run in opposite
directions along their shared crack) give a pose hypothesis — B turned so that its boundary is
collinear with A's and placed on the other side of A's edge, a few millimetres of lost material
further along the line (Derech, Tal & Shimshoni 2021 continue the image across the gap in the
same spirit; here only the boundaries' geometry is continued).

* :func:`line_ends` — the crossings of one fragment: colour boundaries (the Di Zenzo structure
  tensor of the CIELAB image) where the colour along the outline changes;
* :func:`line_pose_hypotheses` — poses of B in A's frame from every colour-compatible pair of
  crossings, on a small grid of gap, turn and shift about the collinear pose;
* :func:`line_continuity` — at any poses, how many of A's crossings a crossing of B continues;
* :func:`outline_contact_mm` — the docking's contact sampled along the outlines, for many poses at
  once (to refine each hypothesis' grid).

Measured (docs/matching.md, "Pose hypotheses from painted lines"; ``tests/bench/bench_pose.py
--lines``): merged with the docking's 30 candidates the truth is among the candidates for 0.52 of
RePAIR's true pairs (0.33 before) and 0.41–0.50 of the test walls' (0.33–0.38), but the pose chosen
by contact, paint and continuity is right for 0.143 of RePAIR's pairs as before and 0.223 of the test
walls' (0.197), at 0.5–12 s CPU per pair; not used by the station.

The pose convention is the docking's: fragment-frame millimetres (x right, y down,
``x = col × pixel_mm``) and ``p_a = R(angle_deg) @ p_b + (tx_mm, ty_mm)``.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage as ndi

from common.matching.docking import DOCK_GAP_MM, DOCK_NEAR_WEIGHT, DOCK_OVERLAP_WEIGHT, DOCK_TAPER_MM
from common.matching.facing import sample_map, signed_distance_map
from common.matching.paint import _lab, checked_face

#: weight of CIELAB lightness against the chroma axes (fading and lighting change lightness most)
LINE_L_WEIGHT = 0.5
#: grid the image is analysed on, mm (painted lines on real frescoes are >= 1 mm wide)
LINE_CELL_MM = 0.4
#: least colour change along the outline (between ±side_mm) that counts as a crossing, ΔE
LINE_MIN_CONTRAST_DE = 2.5
#: least coherence of the structure tensor (0: no direction, 1: a straight boundary)
LINE_MIN_COHERENCE = 0.2
#: least angle between a boundary and the outline: a band running along the edge has no end there
LINE_MIN_SLANT_DEG = 25.0
#: colours of two crossings farther apart than this (either side, ΔE) are not one boundary
LINE_MAX_DE = 15.0
#: the same for :func:`line_continuity`, a little wider (a faded continuation still counts)
LINE_CONTINUITY_MAX_DE = 18.0

#: columns of :func:`line_ends`
END_COLUMNS = ("x_mm", "y_mm", "direction_deg", "coherence", "L_before", "a_before", "b_before",
               "L_after", "a_after", "b_after", "contrast_de")

_W = np.array([LINE_L_WEIGHT, 1.0, 1.0], np.float32)


def _outline(mask: np.ndarray):
    """The outer outline (cells, in findContours' order), or None when there is none of 20 points."""
    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not cs:
        return None
    c = max(cs, key=len)[:, 0].astype(float)
    if len(c) < 20:
        return None
    return c


def line_ends(albedo: np.ndarray, mask: np.ndarray, pixel_mm: float, *, cell_mm: float = LINE_CELL_MM,
              smooth_mm: float = 0.6, depths_mm=(1.0, 2.0, 3.0), side_mm: float = 2.0,
              min_contrast_de: float = LINE_MIN_CONTRAST_DE, tensor_mm: float = 2.5,
              min_coherence: float = LINE_MIN_COHERENCE, min_slant_deg: float = LINE_MIN_SLANT_DEG,
              spacing_mm: float = 2.0) -> np.ndarray:
    """Where the boundaries of painted lines, bands and colour zones cross a fragment's outline.

    The colour just inside the edge (CIELAB, lightness × :data:`LINE_L_WEIGHT`, mean over
    ``depths_mm`` along the inward normal, past the damaged rim) is followed along the outline; a
    crossing is a local maximum (at least ``spacing_mm`` apart) of the colour change
    ``ΔE(c(s + side_mm), c(s − side_mm))`` above ``min_contrast_de``. Its direction is that of the
    colour boundary at the middle depth: the eigenvector of the smaller eigenvalue of the Di Zenzo
    (1986) structure tensor ``J = G_σ * Σ_channels ∇c ∇cᵀ`` (σ = ``tensor_mm``; the outline's own step
    excluded), kept where its coherence ``(λ1 − λ2) / (λ1 + λ2)`` is at least ``min_coherence`` and the
    boundary meets the outline at ``min_slant_deg`` or more (a band running along the edge has no end
    there). A band gives two crossings (its two edges), a thin line two close ones, a colour zone one.

    Parameters
    ----------
    albedo : (H, W, 3) float
        Linear RGB albedo in [0, 1].
    mask : (H, W) bool
        The fragment (holes are filled: stains cut out are not edges).
    pixel_mm : float
        Pixel size, mm (the fragment frame is ``x = col × pixel_mm``, ``y = row × pixel_mm``).
    cell_mm : float
        The image is analysed on cells of ``max(cell_mm, pixel_mm)``.

    Returns
    -------
    (K, 11) float
        One row per crossing, columns :data:`END_COLUMNS`: its point on the outline (mm, fragment
        frame), the boundary's direction pointing into the fragment (degrees, ``atan2(dy, dx)`` in
        the y-down frame), its coherence, the colour (CIELAB) before and after it in the outline's
        order (``cv2.findContours``' order, the same for every fragment) and the colour change (ΔE).
        Empty (0, 11) for plain plaster.
    """
    alb, mask = checked_face(albedo, mask, pixel_mm)
    empty = np.zeros((0, len(END_COLUMNS)))
    cell = max(float(cell_mm), float(pixel_mm))
    s = pixel_mm / cell
    if s < 1:
        alb = cv2.resize(alb, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    m = cv2.resize(mask.astype(np.float32), (alb.shape[1], alb.shape[0]), interpolation=cv2.INTER_AREA) > 0.5
    m = ndi.binary_fill_holes(m)
    if m.sum() < 50:
        return empty
    # a resized cell j covers pixels [j/s, (j+1)/s): its centre in the original pixel grid
    to_mm = (lambda p: (p / s + 0.5 * (1 / s - 1)) * pixel_mm) if s < 1 else (lambda p: p * pixel_mm)
    lab = _lab(alb).astype(np.float32) * _W
    wm = m.astype(np.float32)
    sig = smooth_mm / cell
    # normalised smoothing inside the mask: the background does not bleed into the edge colour
    labs = (cv2.GaussianBlur(lab * wm[..., None], (0, 0), sig)
            / np.maximum(cv2.GaussianBlur(wm, (0, 0), sig), 1e-6)[..., None])
    gx = np.stack([cv2.Sobel(labs[..., k], cv2.CV_32F, 1, 0, ksize=3) / 8 for k in range(3)], -1)
    gy = np.stack([cv2.Sobel(labs[..., k], cv2.CV_32F, 0, 1, ksize=3) / 8 for k in range(3)], -1)
    core = ndi.binary_erosion(m, iterations=2).astype(np.float32)   # the outline's own step is not paint
    ts = tensor_mm / cell
    jxx = cv2.GaussianBlur((gx * gx).sum(-1) * core, (0, 0), ts)
    jxy = cv2.GaussianBlur((gx * gy).sum(-1) * core, (0, 0), ts)
    jyy = cv2.GaussianBlur((gy * gy).sum(-1) * core, (0, 0), ts)
    c = _outline(m)
    if c is None:
        return empty
    H, W = m.shape
    k = max(2, int(round(1.5 / cell)))
    tang = np.roll(c, -k, 0) - np.roll(c, k, 0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-9)
    nrm = np.stack([-tang[:, 1], tang[:, 0]], 1)

    def sample(img, pts):
        q = np.round(pts).astype(int)
        ok = (q[:, 0] >= 0) & (q[:, 0] < W) & (q[:, 1] >= 0) & (q[:, 1] < H)
        q[:, 0] = np.clip(q[:, 0], 0, W - 1)
        q[:, 1] = np.clip(q[:, 1], 0, H - 1)
        return img[q[:, 1], q[:, 0]], ok & m[q[:, 1], q[:, 0]]

    if sample(m.astype(np.float32), c + nrm * (2.0 / cell))[1].mean() < 0.5:
        nrm = -nrm   # the normal must point into the fragment
    cols, oks = [], []
    for d in depths_mm:
        v, ok = sample(labs, c + nrm * d / cell)
        cols.append(v * ok[:, None])
        oks.append(ok)
    col = np.sum(cols, 0) / np.maximum(np.sum(oks, 0), 1)[:, None]
    valid = np.sum(oks, 0) >= 2
    step = np.mean(np.linalg.norm(np.diff(c, axis=0), axis=1))
    ks = max(1, int(round(side_mm / cell / step)))
    before, after = np.roll(col, ks, 0), np.roll(col, -ks, 0)
    contrast = np.sqrt(((after - before) ** 2).sum(1)) * (valid & np.roll(valid, ks) & np.roll(valid, -ks))
    contrast = ndi.uniform_filter1d(contrast, 3, mode="wrap")
    ns = max(1, int(round(spacing_mm / cell / step)))
    peak = (contrast >= ndi.maximum_filter1d(contrast, 2 * ns + 1, mode="wrap")) & (contrast >= min_contrast_de)
    rows = []
    for i in np.nonzero(peak)[0]:
        q = np.clip(np.round(c[i] + nrm[i] * (depths_mm[len(depths_mm) // 2] / cell)).astype(int), 0, [W - 1, H - 1])
        a, b, d = float(jxx[q[1], q[0]]), float(jxy[q[1], q[0]]), float(jyy[q[1], q[0]])
        if a + d <= 1e-9:
            continue
        root = np.sqrt(max((a - d) ** 2 / 4 + b * b, 0.0))
        l1, l2 = (a + d) / 2 + root, (a + d) / 2 - root
        coherence = (l1 - l2) / (l1 + l2 + 1e-12)
        g = np.array([b, l1 - a]) if abs(b) > 1e-12 else (np.array([1.0, 0.0]) if a >= d else np.array([0.0, 1.0]))
        g /= np.linalg.norm(g) + 1e-12
        e = np.array([-g[1], g[0]])   # the boundary runs across the colour gradient
        if e @ nrm[i] < 0:
            e = -e
        slant = np.degrees(np.arccos(min(1.0, abs(float(e @ tang[i])))))
        if coherence < min_coherence or slant < min_slant_deg:
            continue
        x, y = to_mm(c[i])
        rows.append([x, y, np.degrees(np.arctan2(e[1], e[0])), coherence,
                     *(before[i] / _W), *(after[i] / _W), contrast[i]])
    return np.array(rows, float).reshape(-1, len(END_COLUMNS))


def _check_ends(ends, name):
    ends = np.asarray(ends, float)
    if ends.ndim != 2 or ends.shape[1] != len(END_COLUMNS):
        raise ValueError(f"{name} must be (K, {len(END_COLUMNS)}) rows of line_ends, got shape {ends.shape}")
    return ends


def _compatible(ends_a: np.ndarray, ends_b: np.ndarray, max_de: float):
    """Index pairs whose colours agree across the crack: A's before/after = B's after/before."""
    ia, ib = np.meshgrid(np.arange(len(ends_a)), np.arange(len(ends_b)), indexing="ij")
    ia, ib = ia.ravel(), ib.ravel()
    d1 = np.sqrt((((ends_a[ia, 4:7] - ends_b[ib, 7:10]) * _W) ** 2).sum(1))
    d2 = np.sqrt((((ends_a[ia, 7:10] - ends_b[ib, 4:7]) * _W) ** 2).sum(1))
    ok = np.maximum(d1, d2) <= max_de
    return ia[ok], ib[ok]


def line_pose_hypotheses(ends_a, ends_b, *, gaps_mm=(1.0, 2.5, 4.0, 5.5, 7.0, 8.5, 10.0),
                         turns_deg=(-6.0, -4.5, -3.0, -1.5, 0.0, 1.5, 3.0, 4.5, 6.0),
                         shifts_mm=(-2.0, -1.0, 0.0, 1.0, 2.0), max_de: float = LINE_MAX_DE):
    """Poses of B in A's frame that continue a boundary of A's paint into one of B's.

    For crossings ``a`` (point ``p_a``, inward direction ``α_a``) and ``b`` (``p_b``, ``α_b``) whose
    colours agree across the crack (A's colour before / after = B's after / before, each within
    ``max_de`` ΔE), the collinear pose turns B by ``θ = α_a + 180° − α_b`` (B's boundary, pointing
    into B, then points out of A along A's) and puts B's crossing ``g`` mm beyond A's along the line,
    ``R(θ) p_b + t = p_a − g·u_a + h·n_a`` (``u_a`` the unit direction, ``n_a`` its normal). Estimated
    directions are off by a few degrees and the lost material is unknown, so every pair yields a
    grid: ``g`` in ``gaps_mm``, ``θ + δ`` for ``δ`` in ``turns_deg``, ``h`` in ``shifts_mm``.

    Returns
    -------
    poses : (P, G, 3) float
        ``(angle_deg, tx_mm, ty_mm)`` for each of the P compatible pairs and G grid points
        (angles in [−180, 180)).
    pairs : (P, 2) int
        The rows of ``ends_a`` and ``ends_b`` each hypothesis comes from.
    """
    ea, eb = _check_ends(ends_a, "ends_a"), _check_ends(ends_b, "ends_b")
    gaps, turns, shifts = (np.asarray(v, float).reshape(-1) for v in (gaps_mm, turns_deg, shifts_mm))
    G = len(gaps) * len(turns) * len(shifts)
    if G == 0:
        raise ValueError("gaps_mm, turns_deg and shifts_mm must each hold at least one value")
    ia, ib = _compatible(ea, eb, max_de)
    if len(ia) == 0:
        return np.zeros((0, G, 3)), np.zeros((0, 2), int)
    ua = np.radians(ea[ia, 2])
    u = np.stack([np.cos(ua), np.sin(ua)], -1)                       # (P, 2) into A
    n = np.stack([-u[:, 1], u[:, 0]], -1)
    theta = (ea[ia, 2] + 180.0 - eb[ib, 2])[:, None] + turns[None]   # (P, T)
    r = np.radians(theta)
    pb = eb[ib, :2]
    rpb = np.stack([np.cos(r) * pb[:, :1] - np.sin(r) * pb[:, 1:], np.sin(r) * pb[:, :1] + np.cos(r) * pb[:, 1:]], -1)
    target = (ea[ia, None, None, :2] - gaps[None, :, None, None] * u[:, None, None, :]
              + shifts[None, None, :, None] * n[:, None, None, :])   # (P, g, h, 2)
    t = target[:, None] - rpb[:, :, None, None, :]                  # (P, T, g, h, 2)
    ang = np.broadcast_to(((theta + 180.0) % 360.0 - 180.0)[:, :, None, None], t.shape[:4])
    poses = np.concatenate([ang[..., None], t], -1).reshape(len(ia), G, 3)
    return poses, np.stack([ia, ib], 1)


def line_continuity(ends_a, ends_b, poses, *, max_gap_mm: float = 14.0, max_shift_mm: float = 3.0,
                    max_turn_deg: float = 20.0, max_de: float = LINE_CONTINUITY_MAX_DE) -> np.ndarray:
    """How many of A's crossings a crossing of B continues, at each pose.

    At a pose, B's crossing continues A's when their colours agree across the crack (as in
    :func:`line_pose_hypotheses`, within ``max_de``), it lies beyond A's crossing along A's boundary
    by less than ``max_gap_mm`` (the gap measured along a slanted line is longer than across the
    crack), within ``max_shift_mm`` of the line, and the two boundaries are collinear within
    ``max_turn_deg``.

    Returns
    -------
    (N,) float
        Count of A's crossings continued at each of the N poses (``p_a = R(angle) p_b + t``).
    """
    ea, eb = _check_ends(ends_a, "ends_a"), _check_ends(ends_b, "ends_b")
    poses = np.asarray(poses, float).reshape(-1, 3)
    out = np.zeros(len(poses))
    if len(ea) == 0 or len(eb) == 0 or len(poses) == 0:
        return out
    ia, ib = _compatible(ea, eb, max_de)
    if len(ia) == 0:
        return out
    r = np.radians(poses[:, 0])
    c, s = np.cos(r)[:, None], np.sin(r)[:, None]
    pb = eb[ib, :2]
    qb = np.stack([c * pb[:, 0] - s * pb[:, 1], s * pb[:, 0] + c * pb[:, 1]], -1) + poses[:, None, 1:3]
    ua = np.radians(ea[ia, 2])
    u = np.stack([np.cos(ua), np.sin(ua)], -1)
    v = qb - ea[ia, :2][None]
    along = -(v * u[None]).sum(-1)                                   # out of A along its boundary
    across = np.abs(v[..., 0] * u[None, :, 1] - v[..., 1] * u[None, :, 0])
    turn = np.abs((eb[ib, 2][None] + poses[:, :1] - ea[ia, 2][None]) % 360.0 - 180.0)
    good = (along > -1.0) & (along < max_gap_mm) & (across < max_shift_mm) & (turn < max_turn_deg)
    hit = np.zeros((len(poses), len(ea)), bool)
    rows, cols = np.nonzero(good)
    hit[rows, ia[cols]] = True
    return hit.sum(1).astype(float)


def outline_contact_mm(contour_a_mm, contour_b_mm, poses, *, cell_mm: float = 0.75, step_mm: float = 2.5,
                       gap_mm: float = DOCK_GAP_MM, taper_mm: float = DOCK_TAPER_MM,
                       near_weight: float = DOCK_NEAR_WEIGHT, overlap_weight: float = DOCK_OVERLAP_WEIGHT) -> np.ndarray:
    """The docking's contact score at many poses at once, from points sampled along the outlines.

    A point-sampled stand-in for :func:`common.matching.docking.docking_score_at` (same band: full
    weight up to ``gap_mm`` outside an outline, tapering to 0 over ``taper_mm``, ``near_weight`` times
    heavier at the outline), cheap enough to refine every line hypothesis' grid: each fragment's
    outline, resampled every ``step_mm``, is looked up in the other's band (rasterised once on
    ``cell_mm`` cells), and every sample that lies deeper than half a cell inside the other fragment
    costs ``overlap_weight`` × its depth (mm) instead of the docking's covered area.

    Returns
    -------
    (N,) float
        ``(contact_A + contact_B − overlap_weight × depth) / 2`` per pose, mm of crack (comparable with
        :func:`~common.matching.docking.docking_contact_mm`, not equal to it).
    """
    poses = np.asarray(poses, float).reshape(-1, 3)
    fields = []
    for name, c in (("contour_a_mm", contour_a_mm), ("contour_b_mm", contour_b_mm)):
        c = np.asarray(c, float)
        if c.ndim != 2 or c.shape[1] != 2 or len(c) < 3:
            raise ValueError(f"{name} must be (N >= 3, 2) outline points, got shape {c.shape}")
        signed, lo = signed_distance_map(c, cell_mm, gap_mm + taper_mm + 3.0)
        out, depth = np.maximum(signed, 0), np.maximum(-signed, 0)
        band = (np.clip((gap_mm + taper_mm - out) / taper_mm, 0, 1)
                * (near_weight + (1 - near_weight) * np.clip(out / gap_mm, 0, 1)))
        band[signed < 0] = 0
        closed = np.vstack([c, c[:1]])
        arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
        t = np.arange(0, arc[-1], step_mm)
        samples = np.stack([np.interp(t, arc, closed[:, 0]), np.interp(t, arc, closed[:, 1])], 1)
        fields.append((band, depth, lo, samples))

    def look(field, pts):
        band, depth, lo, _ = field
        return sample_map(band, lo, cell_mm, pts, 0.0), sample_map(depth, lo, cell_mm, pts, 0.0)

    r = np.radians(poses[:, 0])
    rot = np.stack([np.stack([np.cos(r), -np.sin(r)], -1), np.stack([np.sin(r), np.cos(r)], -1)], -2)
    b_in_a = np.einsum("nij,kj->nki", rot, fields[1][3]) + poses[:, None, 1:3]
    a_in_b = np.einsum("nji,nkj->nki", rot, fields[0][3][None] - poses[:, None, 1:3])
    band_b, depth_b = look(fields[0], b_in_a)
    band_a, depth_a = look(fields[1], a_in_b)
    contact = band_b.sum(1) * step_mm + band_a.sum(1) * step_mm
    over = (np.clip(depth_b - cell_mm, 0, None).sum(1) + np.clip(depth_a - cell_mm, 0, None).sum(1)) * step_mm
    return (contact - overlap_weight * over) / 2.0
