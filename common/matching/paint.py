"""Paint that continues across a crack with lost material: a score of candidate relative poses.

Two fresco fragments that were one piece carry the same painting up to the crack between them; the
crack has lost 1–8 mm of plaster (RePAIR, Pompeii), so the paint just inside one edge is not the
paint just inside the other, and a painted line or band that crosses the crack reappears on the
other side a few millimetres further on. This module extrapolates each fragment's paint outward
across its edge (Derech, Tal & Shimshoni 2021 bridge the gap this way) and, for any number of
candidate poses at once, compares one fragment's real paint near its edge with the other's
extrapolation at the same place (Shahar, Elkin & Ben-Shahar 2025 score real RePAIR 2-D pairs by
such a hybrid geometric + colour compatibility; the docking stage, :mod:`common.matching.docking`,
gives the geometric part).

What the paint of real broken frescoes does across a crack was measured on RePAIR's 21 true pairs
at their true relative pose (docs/matching.md, "Paint across the crack"), and decided the design:

* most of a crack is plain plaster on both sides (≈ 70 % of the facing samples), so plain plaster
  must be *no evidence* — neither for nor against a pose: each sample's evidence is a log likelihood
  ratio against the chance of its colour among the other fragment's edge colours (its rarity), ≈ 0
  for plaster meeting the same plaster;
* where one side is painted, the facing point of the other side is painted too only 2–11 % of the
  time (lines end at the crack, cracks follow the edge of a band), so a sample's cost is bounded
  (the ratio is clipped at −1, against +3 for paint that continues);
* the colour of the facing edges at the true pose is closer than at random pairings (median ΔE 3.3
  against 4.2–4.6 at a depth of 1–3 mm), i.e. the plaster's own tone varies across a fresco and
  continues over the crack: absolute CIELAB colour is compared (lightness at half weight), which
  measured better than deviations from each piece's plaster on the synthetic walls;
* the damaged rim is thin (the colour of the outer 0.25 mm differs from the interior by ≈ 3.5 ΔE
  against ≈ 2 ΔE deeper): the outer ``rim_mm`` is replaced by the extrapolation, and the paint carried
  outward is the mean over 1–4 mm along the line to the edge, so a faded edge is outvoted;
* holes in a fragment's mask (stains cut out with the background) are not edges.

The pose convention is the docking's (:class:`common.matching.alignment.Alignment`): fragment-frame
millimetres (x right, y down, ``x = col × pixel_mm``) and ``p_a = R(angle_deg) @ p_b + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage as ndi

from common.rgbn._filters import normalized_blur

#: grid of the paint fields, mm (paint features on real frescoes are ≥ 1 mm wide)
PAINT_CELL_MM = 0.5
#: outer rim replaced by the extrapolation (damaged, discoloured, the soft alpha edge), mm
PAINT_RIM_MM = 1.0
#: depth of the band just inside the rim whose paint is extrapolated and compared, mm
PAINT_DEPTH_MM = 3.0
#: how far the paint is carried outward (widest lost material expected plus the band), mm
PAINT_REACH_MM = 12.0
#: Gaussian tolerance of the extrapolated field (oblique lines, imprecise placement), mm
PAINT_SMOOTH_MM = 0.5
#: width of the colour kernel that decides whether two paints are the same, CIELAB ΔE (lightness
#: scaled by ``PAINT_L_WEIGHT``): about the colour noise of a photographed plaster surface
PAINT_TAU_DE = 3.0
#: floor of the likelihoods: a paint that meets a different one costs at most log(chance / floor)
PAINT_FLOOR = 0.02
#: per-sample log likelihood ratio is clipped to this range (paint meeting plaster costs little)
PAINT_LLR_CLIP = (-1.0, 3.0)
#: the chance level is taken against at most this many of the other fragment's edge samples
PAINT_REFERENCE = 1000
#: weight of lightness relative to the chroma axes (fading and lighting change lightness most;
#: 0.5 and 1 measured alike on the synthetic walls)
PAINT_L_WEIGHT = 0.5


@dataclass(frozen=True)
class PaintField:
    """A fragment's paint near its edge and carried outward across it (:func:`paint_field`).

    Attributes
    ----------
    field : (H, W, 3) float32
        Paint colour carried across the edge, CIELAB with lightness × ``PAINT_L_WEIGHT``, on a grid
        of ``cell_mm``: over the rim and up to ``reach_mm`` outside the outline (0 elsewhere).
    weight : (H, W) float32
        Where ``field`` holds evidence: 1 outside up to ``reach_mm`` and over the ``rim_mm`` rim, 0
        deeper inside (a pose that covers a fragment's interior is not evidence of continuity) and
        beyond the reach.
    origin_mm : (2,) float
        Fragment-frame position (x, y) of cell (0, 0).
    cell_mm : (2,) float
        Grid cell along x and y, mm (``cell_mm`` of :func:`paint_field`, or the image's pixel if coarser).
    samples_mm : (K, 2) float
        Fragment-frame positions of the compared band's cells (``rim_mm`` … ``rim_mm + depth_mm``
        inside the outline).
    samples : (K, 3) float32
        The fragment's paint at ``samples_mm`` (CIELAB, lightness × ``PAINT_L_WEIGHT``).
    plaster_lab : (3,) float
        The fragment's plaster colour (median CIELAB over the fragment).
    sample_length_mm : float
        Length of outline each sample stands for (cell area / band depth for :func:`paint_field`;
        profile step / number of depths for :func:`paint_field_from_profile`): evidence × this = mm.
    """

    field: np.ndarray
    weight: np.ndarray
    origin_mm: np.ndarray
    cell_mm: np.ndarray
    samples_mm: np.ndarray
    samples: np.ndarray
    plaster_lab: np.ndarray
    sample_length_mm: float


def _lab(albedo_linear: np.ndarray) -> np.ndarray:
    """CIELAB (D65) of linear RGB albedo in [0, 1]."""
    a = np.clip(np.asarray(albedo_linear, np.float32), 0.0, 1.0)
    srgb = np.where(a <= 0.0031308, 12.92 * a, 1.055 * np.power(a, 1 / 2.4) - 0.055).astype(np.float32)
    return cv2.cvtColor(srgb, cv2.COLOR_RGB2Lab)


def _smooth(values: np.ndarray, weight: np.ndarray, sigma_cells: float) -> np.ndarray:
    """Normalised Gaussian convolution (:func:`common.rgbn._filters.normalized_blur`), the kernel cut at 3 σ:
    the weighted mean of ``values`` around each cell."""
    if sigma_cells <= 0:
        return values
    k = int(np.ceil(3 * sigma_cells)) * 2 + 1
    return normalized_blur(values, weight, sigma_cells, ksize=(k, k))[0]


def checked_face(albedo, mask, pixel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(albedo as float32 (H, W, 3), mask (H, W)) of a fragment's image, or ValueError naming what is
    wrong: the albedo's shape, the mask's, a pixel size that is not a positive number."""
    alb = np.asarray(albedo, np.float32)
    m = np.asarray(mask)
    if alb.ndim != 3 or alb.shape[2] != 3:
        raise ValueError(f"albedo must be (H, W, 3), got shape {alb.shape}")
    if m.shape != alb.shape[:2]:
        raise ValueError(f"mask must be {alb.shape[:2]} like albedo, got {m.shape}")
    if not (np.isfinite(pixel_mm) and pixel_mm > 0):
        raise ValueError(f"pixel_mm must be a positive number, got {pixel_mm}")
    return alb, m


def paint_field(albedo: np.ndarray, mask: np.ndarray, pixel_mm: float, *, cell_mm: float = PAINT_CELL_MM,
                rim_mm: float = PAINT_RIM_MM, depth_mm: float = PAINT_DEPTH_MM, reach_mm: float = PAINT_REACH_MM,
                smooth_mm: float = PAINT_SMOOTH_MM) -> PaintField:
    """Extrapolate a fragment's paint outward across its edge (from its image).

    Parameters
    ----------
    albedo : (H, W, 3) float
        Linear RGB albedo in [0, 1] of the fragment image (``RGBNImage.albedo``).
    mask : (H, W) bool
        True on the fragment (``RGBNImage.mask``).
    pixel_mm : float
        Pixel size of ``albedo`` and ``mask``, mm; the fragment frame is ``x = col × pixel_mm``,
        ``y = row × pixel_mm``.
    cell_mm : float
        Grid of the returned field (the image is area-averaged onto it).
    rim_mm : float
        Outer rim whose colour is not trusted (damaged, discoloured, the soft alpha edge): replaced
        by the extrapolation.
    depth_mm : float
        Depth of the band inside the rim whose paint is carried outward and compared.
    reach_mm : float
        How far outside the outline the paint is carried.
    smooth_mm : float
        Gaussian tolerance of the extrapolation along the edge: a line that crosses the crack
        obliquely, or a placement a millimetre off, still meets its continuation.
    Returns
    -------
    PaintField

    Notes
    -----
    Derech et al. extrapolate the image across the gap by inpainting along the image's structure;
    here each cell outside takes the paint of the nearest cell of the band inside the rim, and
    ``smooth_mm`` blurs it along the edge, which carries a band crossing the crack at up to ≈ 45°
    over a few millimetres of lost material (the gap on RePAIR: median 4.5 mm at 150 dpi).

    References
    ----------
    N. Derech, A. Tal, I. Shimshoni, "Solving archaeological puzzles", Pattern Recognition 119,
    108065, 2021 (extrapolation of each fragment's image across the gap before comparing).

    Examples
    --------
    >>> m = np.zeros((80, 80), bool); m[10:70, 10:40] = True
    >>> alb = np.full((80, 80, 3), 0.7, np.float32); alb[30:40, 10:40] = (0.6, 0.1, 0.1)  # a red band
    >>> pf = paint_field(alb, m, 0.5)
    >>> x, y = np.round((np.array([22.5, 17.5]) - pf.origin_mm) / pf.cell_mm).astype(int)
    >>> bool(np.linalg.norm(pf.field[y, x]) > 20)       # the band carried 2.5 mm past the right edge
    True
    """
    alb, m = checked_face(albedo, mask, pixel_mm)
    for name, v in (("cell_mm", cell_mm), ("depth_mm", depth_mm), ("reach_mm", reach_mm)):
        if not v > 0:
            raise ValueError(f"{name} must be positive, got {v}")
    if not (rim_mm >= 0 and smooth_mm >= 0):
        raise ValueError(f"rim_mm and smooth_mm must be >= 0, got {rim_mm}, {smooth_mm}")
    m = m.astype(bool)
    if m.sum() < 4:
        raise ValueError("the mask has no fragment (fewer than 4 pixels): cannot sample its paint")
    alb = np.nan_to_num(alb, nan=0.0, posinf=1.0, neginf=0.0)
    # onto the cell grid (area-averaged colour over the fragment only) with a margin for the reach;
    # an image coarser than the cell is used at its own pixel size
    scale = min(1.0, pixel_mm / cell_mm)
    h, w = m.shape
    stack = np.dstack([alb * m[..., None], m.astype(np.float32)])
    if scale < 1:
        stack = cv2.resize(stack, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    sx, sy = stack.shape[1] / w, stack.shape[0] / h
    pad = int(np.ceil((reach_mm + 3 * smooth_mm) * max(sx, sy) / pixel_mm)) + 2
    grid = cv2.copyMakeBorder(stack, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    # cell J's centre is image pixel (J − pad + ½) / s − ½, i.e. mm = J · cell + origin
    cell_xy = pixel_mm / np.array([sx, sy])
    origin = ((0.5 - pad) / np.array([sx, sy]) - 0.5) * pixel_mm
    cell_mm = float(np.mean(cell_xy))
    cover = grid[..., 3]
    covered = cover > 0.5
    # holes in a mask (dark stains cut out with the background) are not edges the other piece can meet
    inside = ndi.binary_fill_holes(covered)
    if inside.sum() < 4:
        raise ValueError(f"the fragment is smaller than a few {cell_mm} mm cells: no paint to sample")
    colour = grid[..., :3] / np.maximum(cover, 1e-6)[..., None]
    lab = _lab(colour)
    plaster = np.median(lab[covered], axis=0)
    # the paint as weighted CIELAB: lightness counts PAINT_L_WEIGHT of a chroma unit
    dev = lab * np.array([PAINT_L_WEIGHT, 1.0, 1.0], np.float32)
    depth = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, 5) * cell_mm
    outside = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, 5) * cell_mm
    band = covered & (depth > rim_mm) & (depth <= rim_mm + depth_mm)
    if not band.any():  # a sliver thinner than the rim: use what there is
        band = covered
    # the source: the band's paint, smoothed within the band; every cell takes its nearest band cell
    src = _smooth(dev, band.astype(np.float32), 0.5 / cell_mm)
    seeds = (~band).astype(np.uint8)
    _, labels = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    zy, zx = np.nonzero(band)
    lut = np.zeros(int(labels.max()) + 1, np.int64)
    lut[labels[zy, zx]] = np.arange(len(zy))
    near = lut[labels]
    # carry the band's paint outward along the line from each cell to its nearest band cell, as the
    # mean over the band's depth along that line: a line or band that crosses the edge keeps its
    # strength, a faded or damaged outer band is outvoted by the paint deeper in
    gy, gx = np.mgrid[0:depth.shape[0], 0:depth.shape[1]].astype(np.float32)
    uy, ux = zy[near] - gy, zx[near] - gx
    norm = np.hypot(uy, ux)
    uy, ux = uy / np.maximum(norm, 1e-6), ux / np.maximum(norm, 1e-6)
    steps = np.arange(0.0, depth_mm + 1e-6, cell_mm / 2) / cell_mm
    acc = np.zeros(dev.shape, np.float32)
    cnt = np.zeros(depth.shape, np.float32)
    bandf = band.astype(np.float32)
    stack = np.dstack([src * bandf[..., None], bandf])
    for k in steps:
        v = cv2.remap(stack, (zx[near] + ux * k).astype(np.float32), (zy[near] + uy * k).astype(np.float32),
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        acc += v[..., :3]
        cnt += v[..., 3]
    carried = acc / np.maximum(cnt, 1e-6)[..., None]
    ext = np.where(band[..., None], dev, carried).astype(np.float32)
    reach = ((~inside & (outside <= reach_mm)) | (inside & (depth <= rim_mm + depth_mm))).astype(np.float32)
    ext = _smooth(ext, reach, smooth_mm / cell_mm) * reach[..., None]
    # evidence only where the other fragment may lie: outside, and over the rim (pieces that touch)
    weight = ((~inside & (outside <= reach_mm)) | (inside & (depth <= rim_mm))).astype(np.float32)
    ext[weight == 0] = 0.0
    by, bx = np.nonzero(band)
    samples_mm = np.column_stack([bx * cell_xy[0], by * cell_xy[1]]) + origin
    return PaintField(ext, weight, origin.astype(float), cell_xy.astype(float), samples_mm,
                      dev[by, bx].astype(np.float32), np.asarray(plaster, float),
                      float(np.prod(cell_xy) / depth_mm))


def paint_field_from_profile(contour_mm: np.ndarray, profile: np.ndarray, step_mm: float | None = None, *,
                             names=None, cell_mm: float = PAINT_CELL_MM, rim_mm: float = PAINT_RIM_MM,
                             reach_mm: float = PAINT_REACH_MM) -> PaintField:
    """The paint field of a fragment from what the features stage stores: its outline and boundary profile.

    The matcher's index keeps each fragment's ``contour_mm`` and ``boundary_profile`` (√albedo at 0.8
    and 1.6 mm inside the outline, one sample every ``boundary_step_mm`` from the contour's first
    point; :func:`common.features.boundary.boundary_profile`), not its image. This builds the same
    :class:`PaintField` from them: the samples are the profile's, at their places inside the outline,
    and every cell outside (up to ``reach_mm``) or over the rim takes the mean colour of the two depths
    at the nearest arc position — the profile's paint carried straight out across the edge.

    Parameters
    ----------
    contour_mm : (M, 2) array
        Closed outline, fragment frame (mm, x right, y down), traversed as the features stage does
        (clockwise on screen, fragment on the right).
    profile : (K, C) array
        Boundary profile; its ``sqrt_{r,g,b}@{depth}`` columns are used.
    step_mm : float, optional
        Arc-length step of the profile (``FeatureTable.boundary_step_mm``); default the outline's
        perimeter over the number of samples, which is how the profile's step is made.
    names : list of str, optional
        Column names of ``profile`` (default :func:`~common.features.boundary.boundary_channel_names`).
    cell_mm, rim_mm, reach_mm : float
        As :func:`paint_field`.

    Returns
    -------
    PaintField

    Notes
    -----
    A coarser field than :func:`paint_field`'s (one sample per mm of outline and depth instead of a
    band of cells), and its depths (0.8, 1.6 mm) lie partly in the damaged rim; measured against it
    in docs/matching.md ("Paint across the crack").
    """
    from common.features.boundary import boundary_channel_names

    c = np.asarray(contour_mm, float)
    if c.ndim != 2 or c.shape[1] != 2 or len(c) < 3 or not np.all(np.isfinite(c)):
        raise ValueError(f"contour_mm must be a finite (M >= 3, 2) array, got shape {c.shape}")
    prof = np.asarray(profile, np.float32)
    names = list(boundary_channel_names() if names is None else names)
    if prof.ndim != 2 or len(prof) < 3 or prof.shape[1] != len(names):
        raise ValueError(f"profile must be a (K >= 3, {len(names)}) array matching names, got shape {prof.shape}")
    if step_mm is None:
        step_mm = float(np.hypot(*np.diff(np.vstack([c, c[:1]]), axis=0).T).sum()) / len(prof)
    if not (np.isfinite(step_mm) and step_mm > 0):
        raise ValueError(f"step_mm must be a positive number, got {step_mm}")
    depths = sorted({float(n.split("@")[1]) for n in names if n.startswith("sqrt_r@")})
    if not depths:
        raise ValueError("profile has no sqrt_r@<depth> column: no colour to carry")
    # the profile's places: arc k·step from the contour's first point, d inside along the inward normal
    closed = np.vstack([c, c[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    at = np.arange(len(prof)) * step_mm % arc[-1]
    on = np.column_stack([np.interp(at, arc, closed[:, 0]), np.interp(at, arc, closed[:, 1])])
    ahead = np.column_stack([np.interp((at + 0.5) % arc[-1], arc, closed[:, 0]),
                             np.interp((at + 0.5) % arc[-1], arc, closed[:, 1])])
    behind = np.column_stack([np.interp((at - 0.5) % arc[-1], arc, closed[:, 0]),
                              np.interp((at - 0.5) % arc[-1], arc, closed[:, 1])])
    tangent = ahead - behind
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    inward = np.column_stack([-tangent[:, 1], tangent[:, 0]])   # clockwise on screen (y down): right of travel
    lab_at = []
    for d in depths:
        rgb = prof[:, [names.index(f"sqrt_{ch}@{d:g}") for ch in "rgb"]]
        rgb = np.nan_to_num(rgb, nan=0.0) ** 2
        lab_at.append(_lab(rgb[None])[0] * np.array([PAINT_L_WEIGHT, 1.0, 1.0], np.float32))
    mean_lab = np.mean(lab_at, axis=0)
    # the grid: the outline rasterised with a margin for the reach
    pad = reach_mm + 2 * cell_mm
    lo = c.min(axis=0) - pad
    shape = (int(np.ceil((c[:, 1].max() + pad - lo[1]) / cell_mm)) + 1,
             int(np.ceil((c[:, 0].max() + pad - lo[0]) / cell_mm)) + 1)
    inside = np.zeros(shape, np.uint8)
    cv2.fillPoly(inside, [np.round((c - lo) / cell_mm * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    inside = inside.astype(bool)
    depth = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, 5) * cell_mm
    outside = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, 5) * cell_mm
    cells = np.clip(np.round((on - lo) / cell_mm).astype(int), 0, [shape[1] - 1, shape[0] - 1])
    seeds = np.ones(shape, np.uint8)
    seeds[cells[:, 1], cells[:, 0]] = 0
    _, labels = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    order = np.full(shape, -1, np.int64)
    order[cells[:, 1], cells[:, 0]] = np.arange(len(cells))
    zy, zx = np.nonzero(seeds == 0)
    lut = np.zeros(int(labels.max()) + 1, np.int64)
    lut[labels[zy, zx]] = order[zy, zx]
    weight = ((~inside & (outside <= reach_mm)) | (inside & (depth <= rim_mm))).astype(np.float32)
    field = (mean_lab[lut[labels]] * weight[..., None]).astype(np.float32)
    samples_mm = np.vstack([on + inward * d for d in depths])
    samples = np.vstack(lab_at).astype(np.float32)
    plaster = np.median(samples, axis=0) / np.array([PAINT_L_WEIGHT, 1.0, 1.0])
    return PaintField(field, weight, lo.astype(float), np.array([cell_mm, cell_mm], float), samples_mm, samples,
                      plaster.astype(float), float(step_mm / len(depths)))


def _lookup(pf: PaintField, pts_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear field and weight of ``pf`` at fragment-frame points (..., 2); 0 off the grid."""
    q = ((pts_mm - pf.origin_mm) / pf.cell_mm).astype(np.float32)
    shp = q.shape[:-1]
    q = q.reshape(-1, 2)
    n = len(q)
    width = 4096  # remap's output must stay below 32767 columns: fold the points into rows
    q = np.vstack([q, np.full((-n % width, 2), -1e6, np.float32)]).reshape(-1, width, 2)
    stack = np.dstack([pf.field, pf.weight])
    out = cv2.remap(stack, q[..., 0], q[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    out = out.reshape(-1, 4)[:n].reshape(*shp, 4)
    return out[..., :3], out[..., 3]


#: rows of the chance kernel computed at once (:func:`_likelihood_ratio`)
_CHANCE_ROWS = 128


def _likelihood_ratio(real: np.ndarray, carried: np.ndarray, weight: np.ndarray, reference: np.ndarray,
                      tau: float, floor: float, clip) -> np.ndarray:
    """Per-sample log likelihood ratio that ``real`` paint continues the ``carried`` paint (N, K).

    ``log((k(real − carried) + floor) / (mean_j k(real − reference_j) + floor))`` with a Gaussian
    kernel ``k`` of width ``tau``: how much better the colour carried across the gap at this pose
    predicts the real colour than the other fragment's edge colours at random do (its *rarity*).
    Plain plaster meeting the same plaster scores ≈ 0; a rare paint meeting its continuation scores
    high; clipped to ``clip`` so that paint meeting plaster (a line that ends at the crack) costs
    little. Only samples the other fragment's field reaches (``weight`` ≈ 1) count."""
    chance = np.empty(len(real), np.result_type(real, reference))
    for lo in range(0, len(real), _CHANCE_ROWS):   # in blocks: the (rows, R) kernel stays in cache
        r = real[lo:lo + _CHANCE_ROWS]
        d2 = (r[:, None, 0] - reference[None, :, 0]) ** 2
        for c in range(1, real.shape[1]):
            d2 += (r[:, None, c] - reference[None, :, c]) ** 2
        chance[lo:lo + len(r)] = np.exp(-d2 / (2 * tau * tau)).mean(axis=1)  # (K,)
    fit = np.exp(-((real[None] - carried) ** 2).sum(axis=-1) / (2 * tau * tau))  # (N, K)
    llr = np.clip(np.log((fit + floor) / (chance[None] + floor)), clip[0], clip[1])
    return llr * (weight > 0.99)


def paint_continuity(field_a: PaintField, field_b: PaintField, poses, *, tau_de: float = PAINT_TAU_DE,
                     floor: float = PAINT_FLOOR, clip=PAINT_LLR_CLIP, n_reference: int = PAINT_REFERENCE) -> np.ndarray:
    """Score candidate relative poses of two fragments by the paint that continues across their crack.

    Each fragment's paint just inside its rim (:attr:`PaintField.samples`) is compared with the
    other's paint carried across the gap to the same place (:attr:`PaintField.field`), sample by
    sample, as a log likelihood ratio: how much better the carried colour predicts the real one than
    the other fragment's edge colours do at random,

        ``llr = log((k(c_real − c_carried) + floor) / (mean_j k(c_real − c_ref,j) + floor))``,

    ``k`` a Gaussian of width ``tau_de`` (ΔE), clipped to ``clip``. Plain plaster meeting the same
    plaster is as likely at a wrong pose as at the true one (≈ 0: no evidence, not a match); a rare
    paint meeting its own continuation is strong evidence (the rarity is the denominator); paint
    meeting plaster — a line that ends at the crack, common on real frescoes — costs little. The
    score is the sum over both fragments' samples that the other's field reaches, in millimetres of
    crack (each sample stands for :attr:`PaintField.sample_length_mm` of outline), so it adds to the
    docking's contact in mm.

    Parameters
    ----------
    field_a, field_b : PaintField
        :func:`paint_field` of fragments A and B.
    poses : (N, 3) or (3,) array
        Candidate poses ``(angle_deg, tx_mm, ty_mm)`` of B in A's frame: ``p_a = R(angle) p_b + t``
        (the docking's convention, :class:`common.matching.docking.Docking`), e.g. the docking's
        top-N poses of the pair.
    tau_de : float
        Colour kernel width, ΔE (lightness scaled by ``PAINT_L_WEIGHT``).
    floor : float
        Added to both likelihoods (bounds the cost of a mismatch).
    clip : (float, float)
        Range of the per-sample log likelihood ratio.
    n_reference : int
        The chance level of a sample's colour is its mean kernel against at most this many of the
        other fragment's edge samples (a fixed, evenly spaced subset: deterministic).

    Returns
    -------
    (N,) float
        Paint evidence for each pose, mm of crack (0: no evidence either way; positive: paint that
        continues across the gap).

    Notes
    -----
    The per-sample ratio is the colour term of a naive-Bayes pose likelihood, with the rarity of the
    colour among the other fragment's edge colours in the denominator (the ribbon's rarity,
    :mod:`common.matching.ribbon`, plays the same part). Cost: O(N · K) for K edge samples (≈ 10
    samples per mm of outline at the default 0.5 mm cells), plus O(K · n_reference) once per call; ≈ 10 ms
    CPU for a RePAIR pair's 30 candidate poses and 15 ms for 100.

    References
    ----------
    N. Derech, A. Tal, I. Shimshoni, "Solving archaeological puzzles", Pattern Recognition 119,
    108065, 2021 (each fragment's image extrapolated across the gap, then compared);
    O. Shahar, Y. Elkin, O. Ben-Shahar, hybrid (geometric + colour) pairwise compatibility of
    RePAIR 2-D fragments, 2025 (the docking gives the geometry; this the colour).

    Examples
    --------
    >>> m = np.zeros((60, 60), bool); m[5:55, 5:30] = True
    >>> alb = np.full((60, 60, 3), 0.7, np.float32); alb[25:33] = (0.6, 0.1, 0.1)   # a red band
    >>> fa = paint_field(alb, m, 0.5)
    >>> fb = paint_field(alb[:, ::-1], m[:, ::-1], 0.5)                            # its mirror: the band continues
    >>> s = paint_continuity(fa, fb, [[0, 3.0, 0.0], [0, 3.0, 10.0]])              # 3 mm gap; then 10 mm off
    >>> bool(s[0] > 2 and s[0] > s[1])
    True
    """
    p = np.asarray(poses, float)
    if p.ndim == 1:
        p = p[None]
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise ValueError(f"poses must be a finite (N, 3) array of (angle_deg, tx_mm, ty_mm), got shape {p.shape}")
    for name, f in (("field_a", field_a), ("field_b", field_b)):
        if not isinstance(f, PaintField):
            raise ValueError(f"{name} must be a PaintField (paint_field), got {type(f).__name__}")
    if not tau_de > 0 or not floor > 0:
        raise ValueError(f"tau_de and floor must be positive, got {tau_de}, {floor}")
    if len(clip) != 2 or not clip[0] < clip[1]:
        raise ValueError(f"clip must be (low, high) with low < high, got {clip}")
    if n_reference < 1:
        raise ValueError(f"n_reference must be >= 1, got {n_reference}")
    a = np.radians(p[:, 0])
    c, s = np.cos(a)[:, None], np.sin(a)[:, None]                                # (N, 1)
    tx, ty = p[:, 1:2], p[:, 2:3]
    # B's samples in A's frame (p_a = R p_b + t), and A's samples in B's frame (p_b = Rᵀ (p_a − t)),
    # written out: a (N, K) product each, 20× faster than einsum's
    xb, yb = field_b.samples_mm[:, 0], field_b.samples_mm[:, 1]
    b_in_a = np.stack([c * xb - s * yb + tx, s * xb + c * yb + ty], axis=-1)
    xa, ya = field_a.samples_mm[:, 0] - tx, field_a.samples_mm[:, 1] - ty
    a_in_b = np.stack([c * xa + s * ya, c * ya - s * xa], axis=-1)
    total = np.zeros(len(p))
    for own, other, pts in ((field_b, field_a, b_in_a), (field_a, field_b, a_in_b)):
        carried, weight = _lookup(other, pts)                                       # (N, K, 3), (N, K)
        step = max(1, int(np.ceil(len(other.samples) / n_reference)))
        llr = _likelihood_ratio(own.samples.astype(np.float32), carried, weight, other.samples[::step],
                                float(tau_de), float(floor), clip)
        total += llr.sum(axis=1) * own.sample_length_mm
    return total / 2.0


#: weight of a pair's paint evidence (mm of crack) against the docking's contact (mm) in the join's
#: logit: chosen on the synthetic pompeii walls (within-wall @1/@3 of the station's ranking plus paint,
#: docs/matching.md "Paint across the crack"), never on the real collections it is measured on
PAINT_PAIR_WEIGHT = 8.0


def paint_pair_mm(field_a: PaintField, field_b: PaintField, contour_a_mm: np.ndarray, contour_b_mm: np.ndarray, *,
                  n_poses: int = 30, per_angle: int = 3, docks=None) -> tuple[float, tuple]:
    """A pair's paint evidence: the best :func:`paint_continuity` over the docking's candidate poses.

    Whether two fragments are neighbours at all (not which pose): on real frescoes the paint tells
    the true pose among the docking's candidates only weakly, but its best over them separates true
    neighbours from look-alikes of the same fresco (docs/matching.md, "Paint across the crack").

    Parameters
    ----------
    field_a, field_b : PaintField
        The two fragments' paint fields (:func:`paint_field_from_profile` or :func:`paint_field`).
    contour_a_mm, contour_b_mm : (M, 2) arrays
        Their outlines in the same frames (``FeatureTable.contour_mm``).
    n_poses, per_angle : int
        Candidate poses of :func:`common.matching.docking.dock_outlines`.
    docks : list of Docking, optional
        The pair's docking already done (B in A's frame, e.g. by the index's stage 3, whose best is the
        pair's pose): its poses are the candidates, and the contours are not docked again.

    Returns
    -------
    paint_mm : float
        The best paint evidence, mm of crack.
    pose : (angle_deg, tx_mm, ty_mm)
        The candidate pose (B in A's frame) where it was found.
    """
    from common.matching.docking import dock_outlines

    if docks is None:
        docks = dock_outlines(contour_a_mm, contour_b_mm, n_poses=n_poses, per_angle=per_angle)
    if not len(docks):
        raise ValueError("docks must hold at least one candidate pose")
    poses = np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks], float)
    scores = paint_continuity(field_a, field_b, poses)
    i = int(np.argmax(scores))
    return float(scores[i]), tuple(float(v) for v in poses[i])


def with_paint(probability, paint_mm, docking_slope: float, weight: float = PAINT_PAIR_WEIGHT) -> np.ndarray:
    """Join probabilities with a pair's paint evidence added to their logit (naive Bayes).

    ``σ(logit(p) + weight · docking_slope · paint_mm)``: a millimetre of crack with continuing paint
    counts ``weight`` millimetres of the docking's contact, whose calibration slope (per mm,
    ``MatchModel.docking[0]``) turns it into logit units. No paint evidence (0) leaves ``p`` as it is.
    """
    p = np.clip(np.asarray(probability, float), 1e-12, 1 - 1e-12)
    m = np.asarray(paint_mm, float)
    if not np.all(np.isfinite(m)):
        raise ValueError("paint_mm must be finite")
    if not (np.isfinite(docking_slope) and np.isfinite(weight)):
        raise ValueError(f"docking_slope and weight must be finite, got {docking_slope}, {weight}")
    logit = np.log(p) - np.log1p(-p) + weight * docking_slope * m
    return 1.0 / (1.0 + np.exp(-logit))
