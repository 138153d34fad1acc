"""Gap-tolerant shape docking of two fragment outlines by FFT correlation (stage 3 of the matcher).

Real broken frescoes lose material along their cracks: on RePAIR's Pompeii frescoes the outlines of
true neighbours, placed where the archaeologists put them, run 1–8 mm apart (median ≈ 4.5 mm at a
nominal 150 dpi; ../shared/data/README.md), so a contact test at 1.5 mm (:mod:`alignment`) finds no
contact at the true pose. Here the two outlines are compared the way protein docking compares two
molecules (Katchalski-Katzir et al. 1992): fragment A is fixed; for every rotation of fragment B,
one FFT correlation scores *every* translation at once by

    score(t) = Σ band_A · edge_B(· − t) + Σ edge_A · band_B(· − t) − λ Σ inner_A · mask_B(· − t)

where ``edge`` is an outline one cell wide, ``band`` the ring of width ``gap_mm`` outside a
fragment (the material the crack may have lost: weight ``near_weight`` at the outline falling to 1
at ``gap_mm``, then to 0 over ``taper_mm``, so a tighter fit of the same length wins) and ``inner``
the fragment eroded by one cell (real neighbours never cover the same ground, λ
``overlap_weight``). The score is symmetric in A and B and counts, in cells, how much of each
outline runs within the lost-material band of the other; ``contact_mm`` is half of it times the
cell size, i.e. the length of shared crack. With the paint along both outlines, a paint term carried
across the gap joins the same correlation (:func:`dock_outlines`), so pose search is over geometry
and paint jointly. Search is exhaustive (every ``step_deg`` and every cell), so it needs no anchor
and cannot be trapped by a local optimum; the best angle is refined once at a third of the step.

Defaults (6 mm band, near weight 3, 1.5 mm cells, 4° steps) were chosen on realistic synthetic walls
(``generate_wall(..., preset="pompeii")``, two walls of 16 fragments: within-wall hit rate @1 0.37
against 0.23 for a flat 8 mm band; docs/matching.md), not on the real collections they are
evaluated on.

The pose convention is the one of :class:`common.matching.alignment.Alignment`: fragment-frame
millimetres (x right, y down) and ``p_a = R(angle_deg) @ p_b + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy import fft as _fft

#: defaults, measured on real fresco cracks (see module docstring and docs/matching.md)
DOCK_CELL_MM = 1.5
DOCK_GAP_MM = 6.0
DOCK_TAPER_MM = 2.0
DOCK_STEP_DEG = 4.0
DOCK_OVERLAP_WEIGHT = 3.0
#: the band weighs this much more at an outline than at its outer edge: closer fits count more
DOCK_NEAR_WEIGHT = 3.0
DOCK_PAINT_WEIGHT = 0.0
#: coarse to fine: rotations docked again on the fine grid after a pass on a grid of twice the cell
DOCK_COARSE_ANGLES = 3
#: a paint deviation of one unit: this much √albedo away from the fragment's plain plaster
PAINT_SCALE = 0.04


@dataclass(frozen=True)
class Docking:
    """One docked pose of fragment B against fragment A.

    Attributes
    ----------
    angle_deg, tx_mm, ty_mm : float
        Pose mapping B's frame into A's: ``p_a = R(angle_deg) @ p_b + (tx_mm, ty_mm)``.
    score : float
        Correlation score in cells (band contact of both outlines minus weighted overlap).
    contact_mm : float
        Length of outline within the other fragment's lost-material band (mean of the two sides).
    overlap_mm2 : float
        Area where B covers A's interior (eroded by one cell).
    """

    angle_deg: float
    tx_mm: float
    ty_mm: float
    score: float
    contact_mm: float
    overlap_mm2: float


def _raster(points_mm: np.ndarray, cell_mm: float, margin: int) -> tuple[np.ndarray, np.ndarray]:
    """Filled polygon on a grid of ``cell_mm`` cells; returns (mask uint8, origin in mm of cell (0,0))."""
    lo = points_mm.min(axis=0) - margin * cell_mm
    hi = points_mm.max(axis=0) + margin * cell_mm
    shape = (int(np.ceil((hi[1] - lo[1]) / cell_mm)) + 1, int(np.ceil((hi[0] - lo[0]) / cell_mm)) + 1)
    mask = np.zeros(shape, np.uint8)
    shift = 4
    pts = np.round((points_mm - lo) / cell_mm * (1 << shift)).astype(np.int32)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=shift)
    return mask, lo


def _maps(mask: np.ndarray, gap_cells: float, taper_cells: float, near_weight: float = 1.0):
    """Outline (1 cell), interior eroded by one cell, and the lost-material band outside."""
    k = np.ones((3, 3), np.uint8)
    inner = cv2.erode(mask, k)
    edge = (mask - inner).astype(np.float32)
    dist = cv2.distanceTransform((1 - mask).astype(np.uint8), cv2.DIST_L2, 3)
    band = np.clip((gap_cells + taper_cells - dist) / max(taper_cells, 1e-6), 0.0, 1.0)
    if near_weight != 1.0:  # closer fits count more: weight near_weight at contact, 1 at the band's edge
        band *= near_weight + (1.0 - near_weight) * np.clip(dist / max(gap_cells, 1e-6), 0.0, 1.0)
    band[mask > 0] = 0.0
    return edge, inner.astype(np.float32), band.astype(np.float32), mask.astype(np.float32)


def _paint_band(points_mm: np.ndarray, paint: np.ndarray, origin: np.ndarray, shape, cell_mm: float,
                band: np.ndarray, mask: np.ndarray, rim_cells: float) -> np.ndarray:
    """Paint carried across a fragment's outline: over its band outside and a rim of ``rim_cells``
    inside (so two fragments that touch, with no lost material, still compare their paint), each
    cell takes the paint of the nearest of the outline's ``K`` samples (at even arc steps along
    ``points_mm``), weighted by the band (outside) or 1 (the rim)."""
    closed = np.vstack([points_mm, points_mm[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(closed, axis=0).T))])
    at = np.arange(len(paint)) * arc[-1] / len(paint)
    xy = np.column_stack([np.interp(at, arc, closed[:, 0]), np.interp(at, arc, closed[:, 1])])
    cells = np.clip(np.round((xy - origin) / cell_mm).astype(int), 0, [shape[1] - 1, shape[0] - 1])
    seeds = np.ones(shape, np.uint8)
    seeds[cells[:, 1], cells[:, 0]] = 0
    _, labels = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL)
    # labels number the zero pixels in raster order: map each back to its sample
    order = np.full(shape, -1, np.int64)
    order[cells[:, 1], cells[:, 0]] = np.arange(len(cells))
    lut = np.zeros(int(labels.max()) + 1, np.int64)
    zy, zx = np.nonzero(seeds == 0)
    lut[labels[zy, zx]] = order[zy, zx]
    inside = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)
    weight = np.where(mask > 0, (inside <= rim_cells).astype(np.float32), band).astype(np.float32)
    return paint[lut[labels]] * weight[..., None], weight


def paint_deviation(paint: np.ndarray, scale: float = None) -> np.ndarray:
    """Paint samples as deviations from the fragment's plain plaster, for :func:`dock_outlines`.

    ``(p − median over the samples) / scale``, clipped to ±3: plaster gives ~0, a painted band or
    line a few units. ``paint`` is (K, C), e.g. √albedo along the outline (the boundary profile's
    ``sqrt_*`` channels, :mod:`common.features.boundary`).
    """
    p = np.asarray(paint, np.float32)
    if p.ndim != 2 or len(p) < 3:
        raise ValueError(f"paint must be a (K >= 3, C) array, got shape {p.shape}")
    scale = PAINT_SCALE if scale is None else float(scale)
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    p = np.where(np.isfinite(p), p, np.nanmedian(p, axis=0))
    return np.clip((p - np.median(p, axis=0)) / scale, -3.0, 3.0)


def paint_from_profile(profile: np.ndarray) -> np.ndarray | None:
    """Paint deviations along an outline from a boundary profile (:mod:`common.features.boundary`:
    its √albedo at 0.8 mm inside, one sample per arc step from the contour's first point, in the
    contour's order); None when the profile is absent or malformed."""
    from common.features.boundary import boundary_channel_names

    names = boundary_channel_names()
    p = None if profile is None else np.asarray(profile, np.float32)
    if p is None or p.ndim != 2 or len(p) < 3 or p.shape[1] != len(names):
        return None
    return paint_deviation(p[:, [names.index(f"sqrt_{c}@0.8") for c in "rgb"]])


#: square FFT sizes of the correlation: 1, 9/8, 5/4, 3/2 and 7/4 of a power of two (steps <= 25 %), so
#: one fragment's turned spectra (:class:`DockingFrame`) serve every partner of a similar size
_FFT_SIZES = tuple(sorted({m << k for m in (8, 9, 10, 12, 14) for k in range(10)}))


def _fft_size(n: int) -> int:
    """The smallest size of :data:`_FFT_SIZES` that holds ``n`` cells."""
    for s in _FFT_SIZES:
        if s >= n:
            return s
    return int(cv2.getOptimalDFTSize(n))


def _spectra(maps, size: int) -> np.ndarray:
    """Real 2-D FFTs of same-sized maps zero-padded to ``size × size``, (len(maps), size, size // 2 + 1)
    complex64, pruned: the padding rows are zero, so the row transforms run on the maps' own rows only
    (then the column transforms on all); the same numbers as ``rfft2`` of the padded maps."""
    stack = np.asarray(maps, np.float32)
    rows = _fft.rfft(stack, n=size, axis=-1, workers=1)
    return _fft.fft(rows, n=size, axis=-2, workers=1)


def _rotation(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def _window_max(values: np.ndarray, radius: int) -> np.ndarray:
    """Maximum over the ``(2 radius + 1)²`` window of every cell, wrapping around the edges (as
    ``scipy.ndimage.maximum_filter(mode="wrap")``, 20× faster as a dilation)."""
    padded = np.pad(values, radius, mode="wrap")
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.dilate(padded, kernel)[radius:radius + values.shape[0], radius:radius + values.shape[1]]


class DockingFrame:
    """One fragment's outline prepared for :func:`dock_frames`: what does not depend on the partner,
    computed once and kept.

    As fragment A (held) it gives its band, outline and eroded interior and their spectra; as fragment
    B (turned) it gives, for every rotation, the turned outline, band and mask and their (conjugate)
    spectra. The turned spectra are kept for the last ``sizes_kept`` FFT sizes — square sizes of a ladder
    ≤ 25 % apart (:func:`_fft_size`), so partners of similar size share them; dock a fragment's partners
    in order of size (:meth:`fft_size`) to compute them once per size — at ``3 × size × (size // 2 + 1) × 8``
    bytes per rotation: 0.8 MB at size 256 (a 20 cm fragment against another at the 1.5 mm cell), 71 MB
    for its 90 rotations. :attr:`nbytes` tells what a frame holds; :meth:`clear` frees it.

    Parameters
    ----------
    contour_mm : (M, 2) array
        Closed outline in the fragment's own frame, mm (x right, y down).
    cell_mm, gap_mm, taper_mm, near_weight : float
        The grid and the lost-material band, as in :func:`dock_outlines`.
    sizes_kept : int
        FFT sizes whose turned spectra are kept (the least recently used size goes first).
    """

    def __init__(self, contour_mm: np.ndarray, *, cell_mm: float = DOCK_CELL_MM, gap_mm: float = DOCK_GAP_MM,
                 taper_mm: float = DOCK_TAPER_MM, near_weight: float = DOCK_NEAR_WEIGHT, sizes_kept: int = 1,
                 name: str = "contour_mm"):
        c = np.asarray(contour_mm, float)
        if c.ndim != 2 or c.shape[1] != 2 or len(c) < 3 or not np.all(np.isfinite(c)):
            raise ValueError(f"{name} must be a finite (M >= 3, 2) array, got shape {c.shape}")
        if not cell_mm > 0:
            raise ValueError(f"cell_mm must be positive, got {cell_mm}")
        if not gap_mm >= 0 or not taper_mm >= 0:
            raise ValueError(f"gap_mm and taper_mm must be >= 0, got {gap_mm}, {taper_mm}")
        if sizes_kept < 1:
            raise ValueError(f"sizes_kept must be >= 1, got {sizes_kept}")
        self.sizes_kept = int(sizes_kept)
        self.contour_mm = c
        self.params = (float(cell_mm), float(gap_mm), float(taper_mm), float(near_weight))
        self.cell_mm = float(cell_mm)
        self.gap_cells, self.taper_cells = gap_mm / cell_mm, taper_mm / cell_mm
        self.margin = int(np.ceil(self.gap_cells + self.taper_cells)) + 2
        self.mask, self.origin = _raster(c, cell_mm, self.margin)
        self.edge, self.inner, self.band, _ = _maps(self.mask, self.gap_cells, self.taper_cells, near_weight)
        self.centre = c.mean(axis=0)
        radius = float(np.max(np.hypot(*(c - self.centre).T)))
        #: side of the square that holds the turned outline's maps at any rotation, cells
        self.side = int(np.ceil(2 * radius / cell_mm)) + 2 * self.margin + 3
        self._held: dict[int, np.ndarray] = {}
        self._turned: dict[float, tuple] = {}
        self._turned_spectra: dict[int, dict[float, np.ndarray]] = {}
        self._coarser = None

    def coarser(self) -> "DockingFrame":
        """The same outline on a grid of twice the cell (the coarse pass of coarse to fine), kept."""
        if self._coarser is None:
            cell, gap, taper, near = self.params
            self._coarser = DockingFrame(self.contour_mm, cell_mm=2 * cell, gap_mm=gap, taper_mm=taper,
                                         near_weight=near)
        return self._coarser

    def fft_size(self, turned: "DockingFrame") -> int:
        """FFT size of the correlation with ``turned`` turned against this fragment (no wrap-around)."""
        return _fft_size(max(self.mask.shape) + turned.side)

    def held_spectra(self, size: int) -> np.ndarray:
        """Spectra of this fragment held: (band, outline, eroded interior), (3, size, size // 2 + 1)."""
        f = self._held.get(size)
        if f is None:
            f = self._held[size] = _spectra([self.band, self.edge, self.inner], size)
        return f

    def turned(self, angle_deg: float) -> tuple:
        """The outline turned by ``angle_deg`` about its centre: (points mm about the centre, origin mm of
        cell (0, 0), outline, band, mask) on the grid."""
        key = round(float(angle_deg) % 360.0, 9)
        t = self._turned.get(key)
        if t is None:
            q = (self.contour_mm - self.centre) @ _rotation(key).T
            mask, origin = _raster(q, self.cell_mm, self.margin)
            edge, _, band, full = _maps(mask, self.gap_cells, self.taper_cells, self.params[3])
            t = self._turned[key] = (q, origin, edge.astype(np.uint8), band, mask)
        return t

    def turned_spectra(self, angle_deg: float, size: int) -> np.ndarray:
        """Conjugate spectra of the turned (outline, band, mask), (3, size, size // 2 + 1), kept."""
        key = round(float(angle_deg) % 360.0, 9)
        per = self._turned_spectra.pop(size, None)
        if per is None:
            per = {}
            while len(self._turned_spectra) >= self.sizes_kept:   # the least recently used size goes
                del self._turned_spectra[next(iter(self._turned_spectra))]
        self._turned_spectra[size] = per    # most recently used last
        f = per.get(key)
        if f is None:
            _, _, edge, band, mask = self.turned(key)
            f = _spectra([edge, band, mask], size)
            per[key] = np.conjugate(f, out=f)
        return f

    @property
    def nbytes(self) -> int:
        """Bytes held by the kept maps and spectra (this grid and the coarser one)."""
        n = sum(f.nbytes for f in self._held.values())
        n += sum(sum(a.nbytes for a in t[2:]) for t in self._turned.values())
        n += sum(f.nbytes for per in self._turned_spectra.values() for f in per.values())
        return n + (self._coarser.nbytes if self._coarser is not None else 0)

    def clear(self) -> None:
        """Forget the kept spectra and turned maps (they are recomputed when needed)."""
        self._held.clear()
        self._turned.clear()
        self._turned_spectra.clear()
        self._coarser = None


@dataclass
class _Peak:
    """A correlation peak before it is reported: score, rotation, B's translation and its shift in cells."""

    score: float
    angle_deg: float
    t: np.ndarray
    sy: int
    sx: int
    mask_b: np.ndarray
    rank: int = 0          # its place among its rotation's local maxima (0: the best)


def dock_outlines(contour_a_mm: np.ndarray, contour_b_mm: np.ndarray, *, cell_mm: float = DOCK_CELL_MM,
                  gap_mm: float = DOCK_GAP_MM, taper_mm: float = DOCK_TAPER_MM, step_deg: float = DOCK_STEP_DEG,
                  overlap_weight: float = DOCK_OVERLAP_WEIGHT, near_weight: float = DOCK_NEAR_WEIGHT,
                  paint_a: np.ndarray | None = None, paint_b: np.ndarray | None = None,
                  paint_weight: float = DOCK_PAINT_WEIGHT, n_poses: int = 3, per_angle: int = 1,
                  min_shift_mm: float = 6.0, rescore=None, rescore_weight: float = 1.0,
                  coarse_angles: int = None, more_poses: int = 0, more_per_angle: int = 10) -> list[Docking]:
    """Dock fragment B against fragment A over every rotation and translation, tolerating lost material.

    Parameters
    ----------
    contour_a_mm, contour_b_mm : (M, 2), (N, 2) arrays
        Closed outlines in each fragment's own frame, mm (x right, y down).
    cell_mm : float
        Grid cell of the correlation (1.5 mm: outlines' fine jaggedness is lost along real cracks anyway).
    gap_mm : float
        Width of the band outside each outline in which the other's outline counts as facing it: the
        widest crack (lost material) expected between true neighbours.
    taper_mm : float
        The band's weight falls linearly from 1 at ``gap_mm`` to 0 at ``gap_mm + taper_mm``.
    step_deg : float
        Rotation step of the exhaustive search (the best angle is refined at ``step_deg / 3``).
    overlap_weight : float
        λ: cells of overlap cost this many cells of contact.
    near_weight : float
        Weight of the band right at an outline relative to its outer edge (1: flat; > 1 favours
        close fits, so of two poses with the same length of crack in the band the tighter wins).
    paint_a, paint_b : (K, C) arrays, optional
        Paint just inside each outline, sampled at ``K`` even arc-length steps from the outline's
        first point in its given order, as deviations from the fragment's plain plaster
        (:func:`paint_deviation`). With both, the paint is carried outward across the lost
        material (each band cell takes the paint of the nearest outline sample) and the score
        gains ``paint_weight × Σ_band∩band (p_A·p_B − ¼|p_A|² − ¼|p_B|²)``: positive where the same
        paint meets across the gap (a band or line crossing the crack), negative where paint meets
        plain plaster or other paint, nothing for plaster meeting plaster.
    paint_weight : float
        Weight of the paint term (per cell of overlapping band, deviations in units of
        :data:`PAINT_SCALE`).
    n_poses : int
        Distinct poses returned, best first: at least ``2 * step_deg`` apart in angle, or, with
        ``per_angle`` > 1, at least ``min_shift_mm`` apart in translation (at B's centre).
    per_angle : int
        Local maxima of the correlation kept per rotation (1: its best translation only). More give
        the candidate poses a finer score can re-rank (e.g. paint continuity across the gap, or
        loops of poses that must agree): on RePAIR the true pose is the best pose of a true pair
        for 3 of 21, among the best 100 candidates (10 per rotation) for 13 (docs/matching.md).
    min_shift_mm : float
        With ``per_angle`` > 1: two poses within ``2 * step_deg`` are distinct when B's centre
        lies this far apart (local maxima closer than this within one rotation are merged).
    rescore : callable, optional
        ``rescore(poses)`` → (N,) extra evidence in mm of crack for (N, 3) candidate poses
        ``(angle_deg, tx_mm, ty_mm)`` (e.g. :func:`common.matching.paint.paint_continuity` of the two
        fragments' paint fields). The ``n_poses`` candidates are re-ranked by the geometric score plus
        ``rescore_weight`` × that (converted to the score's cells), and the best is then refined at a
        quarter of ``step_deg`` within ``min_shift_mm / 2`` of its translation, re-scored the same way.
    rescore_weight : float
        Weight of ``rescore``'s millimetres against the geometric contact's.
    coarse_angles : int
        0: every rotation on the ``cell_mm`` grid. N > 0 (with ``per_angle`` 1 and no paint): coarse to
        fine — every rotation is first docked on a grid of twice the cell (a quarter of the cells),
        and only the best N distinct rotations, each with its two neighbours ``step_deg`` away, are
        docked again on the ``cell_mm`` grid. Default :data:`DOCK_COARSE_ANGLES` (3): 1.5–1.9× less
        CPU, the same best score for 74–84 % of pairs, the same within-object ranking and pose
        accuracy on RePAIR and on three synthetic walls (docs/matching.md).
    more_poses, more_per_angle : int
        With ``more_poses`` > 0 (and ``per_angle`` > 1), up to that many further distinct candidates
        follow the ``n_poses`` ones, from up to ``more_per_angle`` local maxima per rotation, best first:
        the wider set of poses a person can step through (a right pose is among 30 + 70 candidates for
        0.45–0.52 of synthetic and 0.38 of RePAIR's true pairs, among the 30 alone for 0.33–0.40;
        docs/matching.md "More candidate poses to offer"). The first ``n_poses`` are exactly
        those returned without them, and the further ones come only when those are all found (so
        ``result[:n_poses]`` is always the search of ``n_poses`` and ``per_angle``). Not with ``rescore``.

    Returns
    -------
    list of Docking, best first (the ``n_poses`` candidates, then the ``more_poses``, each best first).

    See Also
    --------
    dock_frames : the same with the two outlines prepared once (:class:`DockingFrame`): to dock one
        fragment against many, keep its frame (the index's stage 3 does).

    References
    ----------
    E. Katchalski-Katzir et al., "Molecular surface recognition: determination of geometric fit
    between proteins and their ligands by correlation techniques", PNAS 89, 1992 (FFT docking);
    N. Derech, A. Tal, I. Shimshoni, "Solving archaeological puzzles", Pattern Recognition 119,
    2021 (paint extrapolated across the gap before comparing);
    Toler-Franklin, thesis §5.3 (gap and volume-intersection scores of the ribbon matcher).

    Examples
    --------
    >>> sq = np.array([[0, 0], [40, 0], [40, 40], [0, 40]], float)
    >>> best = dock_outlines(sq, sq)[0]     # two squares dock side by side
    >>> bool(best.contact_mm > 30)
    True
    """
    frames = [DockingFrame(c, cell_mm=cell_mm, gap_mm=gap_mm, taper_mm=taper_mm, near_weight=near_weight, name=name)
              for c, name in ((contour_a_mm, "contour_a_mm"), (contour_b_mm, "contour_b_mm"))]
    return dock_frames(*frames, step_deg=step_deg, overlap_weight=overlap_weight, paint_a=paint_a, paint_b=paint_b,
                       paint_weight=paint_weight, n_poses=n_poses, per_angle=per_angle, min_shift_mm=min_shift_mm,
                       rescore=rescore, rescore_weight=rescore_weight, coarse_angles=coarse_angles,
                       more_poses=more_poses, more_per_angle=more_per_angle)


def dock_frames(frame_a: DockingFrame, frame_b: DockingFrame, *, step_deg: float = DOCK_STEP_DEG,
                overlap_weight: float = DOCK_OVERLAP_WEIGHT, paint_a: np.ndarray | None = None,
                paint_b: np.ndarray | None = None, paint_weight: float = DOCK_PAINT_WEIGHT, n_poses: int = 3,
                per_angle: int = 1, min_shift_mm: float = 6.0, rescore=None, rescore_weight: float = 1.0,
                coarse_angles: int = None, coarse_poses: int = 0, more_poses: int = 0,
                more_per_angle: int = 10) -> list[Docking]:
    """:func:`dock_outlines` of two prepared outlines (:class:`DockingFrame`, same grid and band), reusing
    what they keep: A's spectra and B's turned maps and spectra are computed once per fragment (and FFT
    size) and serve every partner, so docking one fragment against many costs one inverse transform per
    rotation and partner. The same poses as :func:`dock_outlines` (which builds the two frames and calls
    this); parameters as there, and

    coarse_poses : int
        0: with ``per_angle`` > 1 every rotation is searched on the fine grid. N > 0: the candidate search
        is coarse to fine too — every rotation on the grid of twice the cell (``per_angle`` maxima each),
        then only the rotations of its best N distinct candidates on the fine grid (so fewer than
        ``n_poses`` candidates may come back when N rotations hold fewer distinct maxima).

    Examples
    --------
    >>> sq = np.array([[0, 0], [40, 0], [40, 40], [0, 40]], float)
    >>> turned = DockingFrame(sq)                       # kept: serves every partner
    >>> [dock_frames(DockingFrame(sq * s), turned)[0] == dock_outlines(sq * s, sq)[0] for s in (1.0, 1.5)]
    [True, True]
    """
    if frame_a.params != frame_b.params:
        raise ValueError(f"the two frames must share the grid and band (cell, gap, taper, near weight), "
                         f"got {frame_a.params} and {frame_b.params}")
    if not 0 < step_deg <= 90:
        raise ValueError(f"step_deg must be in (0, 90], got {step_deg}")
    coarse_angles = DOCK_COARSE_ANGLES if coarse_angles is None else int(coarse_angles)
    if coarse_angles < 0:
        raise ValueError(f"coarse_angles must be >= 0, got {coarse_angles}")
    if n_poses < 1 or per_angle < 1:
        raise ValueError(f"n_poses and per_angle must be >= 1, got {n_poses}, {per_angle}")
    if not min_shift_mm >= 0:
        raise ValueError(f"min_shift_mm must be >= 0, got {min_shift_mm}")
    if more_poses < 0 or (more_poses and (per_angle < 2 or more_per_angle < per_angle or rescore is not None)):
        raise ValueError(f"more_poses needs per_angle >= 2, more_per_angle >= per_angle and no rescore, got "
                         f"more_poses={more_poses}, per_angle={per_angle}, more_per_angle={more_per_angle}")
    cell_mm = frame_a.cell_mm
    a, origin_a, inner_a, centre_b = frame_a.contour_mm, frame_a.origin, frame_a.inner, frame_b.centre
    size = frame_a.fft_size(frame_b)
    shape = (size, size)
    use_paint = paint_a is not None and paint_b is not None and paint_weight > 0
    if use_paint:
        paint_a, paint_b = np.asarray(paint_a, np.float32), np.asarray(paint_b, np.float32)
        if paint_a.ndim != 2 or paint_b.ndim != 2 or paint_a.shape[1] != paint_b.shape[1] or \
                min(len(paint_a), len(paint_b)) < 3:
            raise ValueError(f"paint_a and paint_b must be (K, C) arrays with the same C and K >= 3, "
                             f"got {paint_a.shape} and {paint_b.shape}")
        ext_a, field_a = _paint_band(a, paint_a, origin_a, frame_a.mask.shape, cell_mm, frame_a.band, frame_a.mask,
                                     frame_a.gap_cells)
        n_c = ext_a.shape[2]
        fa_paint = _spectra([ext_a[..., c] for c in range(n_c)] + [(ext_a ** 2).sum(axis=2), field_a], size)
    # single precision: the correlation sums are small integers-ish (cells), far inside float32's
    # precision; A's three spectra weighted once (band·outline_B + outline·band_B − λ inner·mask_B)
    fa = frame_a.held_spectra(size) * np.array([1.0, 1.0, -overlap_weight], np.float32)[:, None, None]

    def correlate(angle):
        q, origin_b, _, band_b, mask_b = frame_b.turned(angle)
        fb = frame_b.turned_spectra(angle, size)
        spec = fa[0] * fb[0] + fa[1] * fb[1] + fa[2] * fb[2]
        if use_paint:
            ext_b, field_b = _paint_band(q, paint_b, origin_b, mask_b.shape, cell_mm, band_b, mask_b, frame_b.gap_cells)
            fp = np.conj(_spectra([ext_b[..., c] for c in range(n_c)] + [field_b, (ext_b ** 2).sum(axis=2)], size))
            cross = sum(fa_paint[c] * fp[c] for c in range(n_c))
            # |p_A|² counts where B's paint field lies and |p_B|² where A's does
            sq = fa_paint[n_c] * fp[n_c] + fa_paint[n_c + 1] * fp[n_c + 1]
            spec = spec + paint_weight * (cross - 0.25 * sq)
        return _fft.irfft2(spec, shape, workers=1), origin_b, mask_b

    radius = max(1, int(round(min_shift_mm / cell_mm)))

    kept_per_angle = more_per_angle if more_poses else per_angle

    def at(angle):
        corr, origin_b, mask_b = correlate(angle)
        if kept_per_angle == 1:
            peaks = [int(np.argmax(corr))]
        else:  # local maxima at least min_shift_mm apart, best first
            top = (corr == _window_max(corr, radius)) & (corr > 0)
            idx = np.flatnonzero(top)
            peaks = idx[np.argsort(-corr.flat[idx])][:kept_per_angle] if len(idx) else [int(np.argmax(corr))]
        return peaks_at(angle, corr, peaks, origin_b, mask_b)

    def near(angle, d, radius_mm):
        """The best pose at ``angle`` whose B centre lies within ``radius_mm`` of docking ``d``'s."""
        corr, origin_b, mask_b = correlate(angle)
        c = _rotation(d.angle_deg) @ centre_b + (d.tx_mm, d.ty_mm)
        sx, sy = np.round((c - origin_a + origin_b) / cell_mm).astype(int)
        r = max(1, int(np.ceil(radius_mm / cell_mm)))
        ys, xs = np.arange(sy - r, sy + r + 1) % shape[0], np.arange(sx - r, sx + r + 1) % shape[1]
        win = corr[np.ix_(ys, xs)]
        iy, ix = np.unravel_index(int(np.argmax(win)), win.shape)
        return docking(peaks_at(angle, corr, [int(ys[iy] * shape[1] + xs[ix])], origin_b, mask_b)[0])

    turned_centre = {}   # angle -> R c_b, the same for every peak of a rotation

    def peaks_at(angle, corr, cells, origin_b, mask_b):
        """The peaks at flat indices ``cells`` of one rotation's correlation, in that order (their rank)."""
        cells = np.asarray(cells, np.int64)
        sy, sx = np.unravel_index(cells, shape)
        # the shifts where the two grids meet run from −(B's extent) to A's extent, and the FFT holds
        # both (size ≥ A's + B's): those at or past A's extent are the negative ones, wrapped around
        sy = np.where(sy >= inner_a.shape[0], sy - shape[0], sy)
        sx = np.where(sx >= inner_a.shape[1], sx - shape[1], sx)
        rc = turned_centre.get(angle)
        if rc is None:
            rc = turned_centre[angle] = _rotation(angle) @ centre_b
        # A cell = B cell + shift  =>  p_a = R (p_b − c_b) + origin_a − origin_b + cell · shift
        t = (origin_a - origin_b) + cell_mm * np.stack([sx, sy], axis=1).astype(float) - rc
        scores = corr.flat[cells]
        return [_Peak(float(scores[k]), float(angle), t[k], int(sy[k]), int(sx[k]), mask_b, k)
                for k in range(len(cells))]

    def docking(p):
        """The peak as a Docking, with the overlap and contact at its shift (for reporting)."""
        h, w = p.mask_b.shape
        ys = slice(max(p.sy, 0), min(p.sy + h, inner_a.shape[0]))
        xs = slice(max(p.sx, 0), min(p.sx + w, inner_a.shape[1]))
        overlap = 0.0   # cells of A's interior under B's mask (0/1 maps: an exact count)
        if ys.start < ys.stop and xs.start < xs.stop:
            overlap = float((inner_a[ys, xs] * p.mask_b[ys.start - p.sy:ys.stop - p.sy,
                                                        xs.start - p.sx:xs.stop - p.sx]).sum())
        overlap *= cell_mm ** 2
        contact = (p.score + overlap_weight * overlap / cell_mm ** 2) * cell_mm / 2
        return Docking(p.angle_deg, float(p.t[0]), float(p.t[1]), p.score, float(contact), overlap)

    angles = np.arange(0.0, 360.0, step_deg)
    if coarse_angles > 0 and per_angle == 1 and not use_paint:
        coarse = dock_frames(frame_a.coarser(), frame_b.coarser(), step_deg=step_deg, overlap_weight=overlap_weight,
                             n_poses=coarse_angles, coarse_angles=0)
        angles = sorted({round((c.angle_deg + k * step_deg) % 360.0, 9) for c in coarse for k in (-1, 0, 1)})
    elif coarse_poses > 0 and per_angle > 1 and not use_paint:
        coarse = dock_frames(frame_a.coarser(), frame_b.coarser(), step_deg=step_deg, overlap_weight=overlap_weight,
                             n_poses=coarse_poses, per_angle=per_angle, min_shift_mm=min_shift_mm, coarse_angles=0)
        angles = sorted({round(c.angle_deg % 360.0, 9) for c in coarse})
    found = [p for angle in angles for p in at(angle)]
    found.sort(key=lambda p: -p.score)
    best = found[0]
    for angle in (best.angle_deg - step_deg / 3, best.angle_deg + step_deg / 3):
        p = at(angle % 360.0)[0]
        if p.score > found[0].score:
            found[0] = p

    def centre(p):
        """B's centre at peak ``p`` (A's frame, mm)."""
        return turned_centre[p.angle_deg] + p.t

    # the poses taken so far: their rotations and B's centres, to test a new one against all at once
    taken_angle, taken_centre = np.empty(n_poses + more_poses), np.empty((n_poses + more_poses, 2))

    def apart(p, n_taken):
        """Whether ``p`` is another rotation (≥ 2 steps) or, with ``per_angle`` > 1, ≥ ``min_shift_mm`` away
        from each of the first ``n_taken`` poses taken."""
        turn = np.abs((p.angle_deg - taken_angle[:n_taken] + 180) % 360 - 180) >= 2 * step_deg - 1e-9
        if per_angle > 1:
            c = centre(p)
            turn |= np.hypot(c[0] - taken_centre[:n_taken, 0], c[1] - taken_centre[:n_taken, 1]) >= min_shift_mm
        return bool(turn.all())

    distinct: list[_Peak] = []

    def take(p):
        taken_angle[len(distinct)], taken_centre[len(distinct)] = p.angle_deg, centre(p)
        distinct.append(p)

    for p in found:
        if p.rank < per_angle and apart(p, len(distinct)):   # the search of n_poses and per_angle, as without more
            take(p)
        if len(distinct) >= n_poses:
            break
    if more_poses and len(distinct) == n_poses:
        chosen = {id(p) for p in distinct}
        for p in found:
            if len(distinct) >= n_poses + more_poses:
                break
            if id(p) not in chosen and apart(p, len(distinct)):
                take(p)
    distinct = [docking(p) for p in distinct]
    if rescore is None:
        return distinct

    def rescored(ds):
        extra = np.asarray(rescore(np.array([[d.angle_deg, d.tx_mm, d.ty_mm] for d in ds], float)), float)
        if extra.shape != (len(ds),) or not np.all(np.isfinite(extra)):
            raise ValueError(f"rescore must return {len(ds)} finite scores, got shape {extra.shape}")
        # mm of crack -> cells of outline (the score counts both outlines: 2 cells per cell_mm of crack)
        return [replace(d, score=d.score + rescore_weight * x * 2.0 / cell_mm) for d, x in zip(ds, extra)]

    distinct = sorted(rescored(distinct), key=lambda d: -d.score)
    # the winner refined on a finer angle grid near its translation (the candidates are 4° and a cell apart)
    local = [near((distinct[0].angle_deg + k * step_deg / 4) % 360.0, distinct[0], min_shift_mm / 2)
             for k in (-2, -1, 1, 2)]
    top = max(rescored(local), key=lambda d: d.score)
    if top.score > distinct[0].score:
        distinct[0] = top
    return distinct


#: gaps between a cluster's pieces up to twice this wide are closed when their outline is made one
#: (:func:`cluster_outline`): the lost material of real cracks is 1-8 mm (median ≈ 4.5 mm at 150 dpi)
CLUSTER_CLOSE_MM = 4.0


def cluster_outline(contours_mm, poses, *, close_mm: float = CLUSTER_CLOSE_MM, cell_mm: float = 0.25) -> np.ndarray:
    """The outer outline of several fragments placed together, the lost material between them closed.

    A confirmed cluster docks a newcomer as one piece (:func:`common.matching.reconstruction.dock_newcomer`):
    each outline is placed at its pose, the filled pieces are merged on a ``cell_mm`` grid and closed
    morphologically with a disc of radius ``close_mm``, so a crack up to ``2 close_mm`` wide between two
    members is bridged and a corner where they meet becomes one notch the newcomer can fit into.

    Parameters
    ----------
    contours_mm : sequence of (M_i, 2) arrays
        Closed outlines, each in its fragment's frame (mm, x right, y down).
    poses : sequence of (angle_deg, tx_mm, ty_mm)
        Each fragment's frame in the common frame, ``p = R(angle) p_i + t``.
    close_mm, cell_mm : float

    Returns
    -------
    (K, 2) float
        The merged outline in the common frame, mm (the largest piece if they do not come together).

    Examples
    --------
    Two 10 mm squares 2 mm apart close into one 10 x 22 mm piece:

    >>> sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    >>> c = cluster_outline([sq, sq], [(0, 0, 0), (0, 12, 0)])
    >>> [round(float(v)) for v in np.ptp(c, axis=0)]
    [22, 10]
    """
    contours, poses = [np.asarray(c, float) for c in contours_mm], list(poses)
    if not contours or len(contours) != len(poses):
        raise ValueError(f"one pose per outline is needed, got {len(contours)} outlines and {len(poses)} poses")
    placed = []
    for c, (angle, tx, ty) in zip(contours, poses):
        if c.ndim != 2 or c.shape[1] != 2 or len(c) < 3:
            raise ValueError(f"an outline must be (M >= 3, 2) mm, got shape {c.shape}")
        placed.append(c @ _rotation(angle).T + (tx, ty))
    if not (close_mm >= 0 and cell_mm > 0):
        raise ValueError(f"close_mm must be >= 0 and cell_mm > 0, got {close_mm}, {cell_mm}")
    allp = np.vstack(placed)
    origin = allp.min(0) - 2 * close_mm - 2 * cell_mm
    hi = allp.max(0) + 2 * close_mm + 2 * cell_mm
    mask = np.zeros((int(np.ceil((hi[1] - origin[1]) / cell_mm)) + 1, int(np.ceil((hi[0] - origin[0]) / cell_mm)) + 1),
                    np.uint8)
    for c in placed:
        cv2.fillPoly(mask, [np.round((c - origin) / cell_mm * 16).astype(np.int32)], 1, shift=4)
    r = int(round(close_mm / cell_mm))
    if r:
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    found, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return max(found, key=cv2.contourArea)[:, 0, :].astype(float) * cell_mm + origin


def docking_score_at(contour_a_mm: np.ndarray, contour_b_mm: np.ndarray, pose, *, cell_mm: float = DOCK_CELL_MM,
                     gap_mm: float = DOCK_GAP_MM, taper_mm: float = DOCK_TAPER_MM,
                     overlap_weight: float = DOCK_OVERLAP_WEIGHT, near_weight: float = DOCK_NEAR_WEIGHT) -> float:
    """The geometric score :func:`dock_outlines` gives B at a given ``pose`` (``angle_deg, tx_mm,
    ty_mm``, B into A's frame) — e.g. at the true pose, to see whether the search or the score is
    what misses it. Both outlines are rasterised on one grid with the same maps."""
    a = np.asarray(contour_a_mm, float)
    r = _rotation(pose[0])
    b = np.asarray(contour_b_mm, float) @ r.T + np.array(pose[1:3], float)
    margin = int(np.ceil((gap_mm + taper_mm) / cell_mm)) + 2
    both, origin = _raster(np.vstack([a, b]), cell_mm, margin)
    masks = []
    for pts in (a, b):
        m = np.zeros_like(both)
        cv2.fillPoly(m, [np.round((pts - origin) / cell_mm * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
        masks.append(m)
    edge_a, inner_a, band_a, _ = _maps(masks[0], gap_mm / cell_mm, taper_mm / cell_mm, near_weight)
    edge_b, _, band_b, full_b = _maps(masks[1], gap_mm / cell_mm, taper_mm / cell_mm, near_weight)
    return float((band_a * edge_b).sum() + (edge_a * band_b).sum() - overlap_weight * (inner_a * full_b).sum())


def docking_contact_mm(docking: Docking, cell_mm: float = DOCK_CELL_MM) -> float:
    """The docking's score as millimetres of shared crack (contact less the overlap's cost)."""
    return float(docking.score) * cell_mm / 2.0


def wrapped_deg(angle_deg: float) -> float:
    """An angle in degrees in [-180, 180): the one range every pose the station shows or stores uses.

    >>> wrapped_deg(249.5), wrapped_deg(-190.0), wrapped_deg(180.0)
    (-110.5, 170.0, -180.0)
    """
    return float((float(angle_deg) + 180.0) % 360.0 - 180.0)


def inverse_pose(angle_deg: float, tx_mm: float, ty_mm: float) -> tuple[float, float, float]:
    """The same relative pose seen from the other fragment: A in B's frame, ``p_b = Rᵀ (p_a − t)``, its angle in
    [-180, 180) (:func:`wrapped_deg`: -180 would otherwise invert to +180, outside the range poses are stated in).

    >>> inverse_pose(-180.0, 10.0, 0.0)[0], inverse_pose(30.0, 0.0, 0.0)[0]
    (-180.0, -30.0)
    """
    t = -_rotation(angle_deg).T @ np.array([tx_mm, ty_mm], float)
    return wrapped_deg(-angle_deg), float(t[0]), float(t[1])


def invert_docking(docking: Docking) -> Docking:
    """The same docking seen from B: pose of A in B's frame (:func:`inverse_pose`)."""
    return Docking(*inverse_pose(docking.angle_deg, docking.tx_mm, docking.ty_mm), docking.score,
                   docking.contact_mm, docking.overlap_mm2)


def hub_corrected(contact_mm, hub_query: float, hub_others, centre: float) -> np.ndarray:
    """Docking contact less the two fragments' *hubness* (mean contact of their best dockings).

    Large fragments with long straight or convex sides dock along something with almost any other
    fragment, so their raw contact is high against everything. As for the patch classifier
    (:mod:`common.matching.index`, CSLS: Conneau et al., ICLR 2018), each pair's contact becomes
    ``c − ½(μ_a − μ̄) − ½(μ_b − μ̄)``, ``μ`` the mean contact of a fragment's best
    :data:`DOCK_HUB_TOP` dockings and ``μ̄`` the median over the collection.
    """
    c = np.asarray(contact_mm, float)
    return c - 0.5 * (float(hub_query) - centre) - 0.5 * (np.asarray(hub_others, float) - centre)


#: a fragment's docking hubness is the mean contact of its best this many dockings
DOCK_HUB_TOP = 3
