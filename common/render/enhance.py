"""Readable-by-default tone and relief enhancement: robust exposure, the noise scale of a normal
map, relief applied to lightness only (the colour is kept), and the two enhancements of
RTIViewer — normal unsharp masking and specular enhancement.

Every function is arrays in, arrays out; :mod:`common.render.recipes` turns them into styles.
Display values are in [0, 1]; normals are x right, y up, z towards the viewer.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from common.render._util import as_light, dot_light, scale_colour
from common.rgbn._filters import check_mask, check_normals
from common.rgbn.smoothing import smooth_normals, smoothed_cosines, strips, unit_rows, weighted_stack

#: Share of the pixels a robust stretch may clip at each end, percent (so at most 2 x this in all).
CLIP_PERCENT = 0.5
#: At most this many pixels are sampled (on a regular stride) for a percentile.
_SAMPLE = 1 << 20


def _sample(values: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Values on the mask (all pixels when None), subsampled on a regular stride to <= _SAMPLE."""
    values = np.asarray(values)
    if mask is None:
        v = values.ravel()
    elif values.ndim == 2:
        v = masked_stride(values, mask, _SAMPLE)
    else:
        v = values[np.asarray(mask, bool)].ravel()
    if v.size > _SAMPLE:
        v = v[:: int(np.ceil(v.size / _SAMPLE))]
    return v[np.isfinite(v)]


def masked_stride(values: np.ndarray, mask: np.ndarray, limit: int = _SAMPLE) -> np.ndarray:
    """``values[mask][::step]`` with ``step = ceil(count / limit)`` (count = mask pixels), without
    gathering every mask pixel first: rows of ~1 Mpx at a time, each keeping the mask pixels whose
    rank among all of them is a multiple of ``step``. (N,) for (H, W) values, (N, C) for (H, W, C)."""
    values = np.asarray(values)
    mask = np.asarray(mask, bool)
    count = int(np.count_nonzero(mask))
    step = max(1, int(np.ceil(count / limit))) if count else 1
    if step == 1:
        return values[mask]
    h, w = mask.shape
    rows = max(1, (1 << 20) // max(w, 1))
    parts, seen = [], 0
    for r0 in range(0, h, rows):
        at = np.flatnonzero(mask[r0:r0 + rows])   # this block's mask pixels, ranks seen, seen + 1, …
        flat = values[r0:r0 + rows].reshape((-1,) + values.shape[2:])
        parts.append(flat[at[(-seen) % step::step]])
        seen += at.size
    return np.concatenate(parts) if parts else values[mask]


def robust_range(values: np.ndarray, mask: np.ndarray | None = None, *,
                 clip_percent: float = CLIP_PERCENT) -> tuple[float, float]:
    """The ``clip_percent`` and ``100 - clip_percent`` percentiles of ``values`` on ``mask``.

    Parameters
    ----------
    values : (H, W) float
        Any scalar image (shading, curvature, lightness).
    mask : (H, W) bool, optional
        Pixels to measure; None = all.
    clip_percent : float
        Percent of the pixels allowed below the low and above the high end, in [0, 25).

    Returns
    -------
    (low, high) : floats; ``low == high`` for a constant image.

    Examples
    --------
    >>> robust_range(np.arange(101.0), clip_percent=10.0)
    (10.0, 90.0)
    """
    if not 0 <= clip_percent < 25:
        raise ValueError(f"clip_percent must be in [0, 25), got {clip_percent}")
    v = _sample(np.asarray(values, np.float32), mask)
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [clip_percent, 100.0 - clip_percent])
    return float(lo), float(hi)


def stretch(values: np.ndarray, low: float, high: float, *, out_low: float = 0.0,
            out_high: float = 1.0) -> np.ndarray:
    """Linear map of ``[low, high]`` to ``[out_low, out_high]``, clipped (float32).

    With ``low == high`` (a constant image) the output is the middle of the output range.
    """
    values = np.asarray(values, np.float32)
    if not high > low:
        return np.full(values.shape, 0.5 * (out_low + out_high), np.float32)
    scale = np.float32((out_high - out_low) / (high - low))
    out = (values - np.float32(low)) * scale + np.float32(out_low)
    return np.clip(out, min(out_low, out_high), max(out_low, out_high)).astype(np.float32)


def symmetric_scale(values: np.ndarray, mask: np.ndarray | None = None, *,
                    clip_percent: float = CLIP_PERCENT) -> float:
    """The ``100 - clip_percent`` percentile of ``|values|``: maps a zero-centred signal (curvature,
    detail shading) to [-1, 1] with at most ``clip_percent`` % of the pixels clipped (1.0 if zero)."""
    v = np.abs(_sample(np.asarray(values, np.float32), mask))
    ref = float(np.percentile(v, 100.0 - clip_percent)) if v.size else 0.0
    return ref if ref > 1e-12 else 1.0


#: Where a tone curve puts the 5th and 95th percentiles of its input (so the default pictures use
#: 60 % of the tone range between them).
TONE_SPAN = (0.2, 0.8)


def tone_curve(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """S-shaped tone curve: ``0.5 + 0.5 tanh(k (2 v - low - high) / (high - low))`` with
    ``k = atanh(0.6)``, so ``low -> 0.2``, ``high -> 0.8``, and the tails roll off instead of
    clipping: a value saturates (> 254.5/255) only beyond ~4.5 half-ranges from the middle.

    Give ``low``, ``high`` as the 5th and 95th percentiles (:func:`robust_range` with
    ``clip_percent=5``) and the picture uses 60 % of the tone range between them.

    Examples
    --------
    >>> [round(float(x), 3) for x in tone_curve(np.array([0.0, 1.0, 2.0]), 0.0, 2.0)]
    [0.2, 0.5, 0.8]
    """
    values = np.asarray(values, np.float32)
    if not high > low:
        return np.full(values.shape, 0.5, np.float32)
    k = np.float32(np.arctanh(TONE_SPAN[1] * 2 - 1) / (0.5 * (high - low)))
    out = values - np.float32(0.5 * (low + high))   # the only array made: the rest is in place
    # 0.5 + 0.5 tanh(u) = 1 / (1 + exp(-2u)): OpenCV's vectorised exp, half numpy's tanh's time
    # (within 1.2e-7 of it); exp overflowing to inf for a far dark value gives 0, as tanh's -1 does
    out *= np.float32(-2.0) * k
    flat = out.reshape(-1, 1)   # a view (out is contiguous): OpenCV takes it as one column
    cv2.exp(flat, dst=flat)
    out += np.float32(1.0)
    np.reciprocal(out, out=out)
    return out


def shoulder(values: np.ndarray, knee: float = 0.8, *, out: np.ndarray | None = None) -> np.ndarray:
    """Highlight roll-off: identity below ``knee``, then ``knee + (1 - knee) tanh((v - knee) /
    (1 - knee))`` — values above 1 approach white instead of clipping (slope 1 at the knee).
    ``out``: the array to write to (may be ``values`` itself); None makes a copy."""
    if out is None:
        v = np.array(values, np.float32)
    else:
        v = out
        if out is not values:
            np.copyto(v, values)
    room, k = np.float32(1.0 - knee), np.float32(knee)
    # usually a small share of the pixels: found by one comparison, then only they are gathered
    flat = v.reshape(-1)
    over = np.flatnonzero(flat > k)
    flat[over] = k + room * np.tanh((flat[over] - k) / room)
    return v


# ---- noise of a normal map ----------------------------------------------------------------------

def normal_noise(normals: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Standard deviation of the pixel-scale noise of a normal map (in units of the normal's
    components), by the robust Laplacian-residual estimator of Immerkær (1996).

    Each component is filtered with ``[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``, which removes
    planes and ramps; for white noise of std s its response has std 6 s, so
    ``s = 1.4826 * median(|response|) / 6`` (the median makes edges and lines count little).
    8-bit quantisation alone gives about 0.002; a JPEG-sourced photometric-stereo map 0.01-0.05.

    References
    ----------
    J. Immerkær, "Fast noise variance estimation", CVIU 64(2), 1996.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> n = np.zeros((200, 200, 3), np.float32); n[..., 2] = 1
    >>> n[..., 0] = rng.normal(0, 0.02, (200, 200))
    >>> round(normal_noise(n), 2)
    0.02
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    res = [[], []]
    for win in _windows(normals.shape[:2]):
        m = cv2.erode(mask[win].astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                      borderValue=0) > 0
        for c in range(2):  # nx, ny carry the relief; nz is second order for near-flat surfaces
            r = cv2.filter2D(np.ascontiguousarray(normals[win][..., c]), cv2.CV_32F, kernel,
                             borderType=cv2.BORDER_REFLECT)
            res[c].append(np.abs(r[m]))
    if not sum(a.size for a in res[0]):
        return 0.0
    return float(max(1.4826 * float(median(np.concatenate(a))) / 6.0 for a in res))


def median(values: np.ndarray):
    """``np.median`` of a 1-D array, the same value, by a partition at one rank (and, for an even
    count, the largest value below it): numpy's median partitions at both middle ranks at once,
    4x slower on the 5 million residuals of :func:`normal_noise`. NaN if any value is NaN.

    Examples
    --------
    >>> float(median(np.array([3.0, 1.0, 4.0, 1.5], np.float32)))
    2.25
    """
    values = np.asarray(values).ravel()
    n = values.size
    if n == 0:
        return np.float64(np.nan)
    k = n // 2
    part = np.partition(values, k)   # NaNs are put last
    if np.isnan(part[-1]):
        return part[-1]
    if n % 2:
        return part[k]
    # numpy's mean of the two middle values, in the array's own precision
    return np.mean(np.array([part[:k].max(), part[k]], part.dtype))


def _windows(shape, side: int = 1024, count: int = 5) -> list:
    """Up to ``count`` windows of ``side`` pixels spread over an image (centre and four quarters;
    the whole image when it is small): where the noise of a large image is measured."""
    h, w = shape
    if h * w <= count * side * side:
        return [(slice(0, h), slice(0, w))]
    out = []
    for fy, fx in ((0.5, 0.5), (0.25, 0.25), (0.25, 0.75), (0.75, 0.25), (0.75, 0.75))[:count]:
        r0 = int(np.clip(fy * h - side / 2, 0, max(h - side, 0)))
        c0 = int(np.clip(fx * w - side / 2, 0, max(w - side, 0)))
        out.append((slice(r0, r0 + side), slice(c0, c0 + side)))
    return out


def block_artefacts(normals: np.ndarray, mask: np.ndarray | None = None, *, block: int = 8) -> float:
    """How much stronger the jumps across ``block``-pixel boundaries are than elsewhere (JPEG
    blocks of the source images survive photometric stereo): the ratio of the mean absolute
    difference between columns/rows ``k*block - 1`` and ``k*block`` to the mean of all others.
    About 1 for a clean map; > 1.3 means visible 8x8 blocks."""
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    ratios = []
    h, w = normals.shape[:2]
    for axis in (0, 1):
        # the profile across the blocks needs only a sample of the lines along them (<= 512)
        step = max(1, (w if axis == 0 else h) // 512)
        sub = normals[:, ::step, :2] if axis == 0 else normals[::step, :, :2]
        msub = mask[:, ::step] if axis == 0 else mask[::step]
        d = np.abs(np.diff(sub, axis=axis)).sum(axis=2)
        m = msub[1:] & msub[:-1] if axis == 0 else msub[:, 1:] & msub[:, :-1]
        d = np.where(m, d, np.nan)
        valid = m.any(axis=1 - axis)
        prof = np.full(d.shape[axis], np.nan)
        prof[valid] = np.nanmean(d[valid] if axis == 0 else d[:, valid], axis=1 - axis)
        if prof.size < 4 * block:
            continue
        idx = np.arange(prof.size)
        on = (idx % block) == block - 1
        a, b = np.nanmean(prof[on]), np.nanmean(prof[~on])
        if np.isfinite(a) and np.isfinite(b) and b > 0:
            ratios.append(a / b)
    return float(max(ratios)) if ratios else 1.0


def relief_scale_px(normals: np.ndarray, dpi: float, mask: np.ndarray | None = None, *,
                    min_mm: float = 0.0, target_noise: float = 0.004) -> tuple[float, dict]:
    """Smoothing scale (Gaussian sigma, pixels) that brings a normal map's pixel noise down to
    ``target_noise``, with a floor for JPEG blocks and a physical floor ``min_mm``.

    A Gaussian of sigma s divides white noise by ``2 sqrt(pi) s``, so
    ``s_noise = noise / (2 sqrt(pi) target_noise)``; 8x8 JPEG blocks (:func:`block_artefacts`
    > 1.3) need at least 2 px; ``min_mm * dpi / 25.4`` is the scale below which relief is not of
    interest. The result is clipped to [0.7, 16] px.

    Returns
    -------
    sigma_px : float
    evidence : dict
        ``noise``, ``blocks``, ``sigma_noise_px``, ``sigma_dpi_px`` (what decided it).
    """
    normals = check_normals(normals)
    if not np.isfinite(dpi) or dpi <= 0:
        raise ValueError(f"dpi must be a positive number, got {dpi}")
    if min_mm < 0:
        raise ValueError(f"min_mm must be >= 0, got {min_mm}")
    if not target_noise > 0:
        raise ValueError(f"target_noise must be > 0, got {target_noise}")
    noise = normal_noise(normals, mask)
    blocks = block_artefacts(normals, mask)
    s_noise = noise / (2.0 * np.sqrt(np.pi) * target_noise)
    s_dpi = min_mm * dpi / 25.4
    sigma = max(s_noise, s_dpi, 2.0 if blocks > 1.3 else 0.0)
    sigma = float(np.clip(sigma, 0.7, 16.0))
    return sigma, {"noise": round(float(noise), 5), "blocks": round(float(blocks), 3),
                   "sigma_noise_px": round(float(s_noise), 3), "sigma_dpi_px": round(float(s_dpi), 3)}


class Coarse(NamedTuple):
    """A smooth field on a grid downsampled by ``factor``: sample (i, j) covers the pixels
    ``offset + factor * (i, j) ... + factor - 1`` of the full grid."""

    values: np.ndarray
    factor: int
    offset: tuple

    def full(self, shape, rows=None) -> np.ndarray:
        """Bilinear interpolation to the full grid ``shape`` (edges replicated); ``rows`` =
        (r0, r1): only those rows of it (the same values).

        Pixel ``y`` of the full grid lies at ``(y - offset + 0.5) / factor - 0.5`` cells, which is
        where ``cv2.resize`` of the cells to ``factor`` times their size puts its row
        ``y - offset``; beyond the cells the value is the edge cell's, that resize's edge row. So
        for a factor of 2, 4, 8 or 16 the rows asked for are that resize of the cells they read
        (one more on each side, so no edge is replicated inside;
        :func:`common.rgbn._filters.upsampled_rows`), shifted by the offset and edge-replicated
        to the shape: the values of ``cv2.warpAffine`` of the same map (whose 1/32-px positions
        are exact there), at 1.5-2.5x its speed. Any other factor (levelling's 24) is that
        warpAffine, which is as fast there."""
        h, w = shape
        r0, r1 = (0, h) if rows is None else (int(rows[0]), int(rows[1]))
        if self.factor == 1 and self.values.shape[:2] == (h, w):
            return self.values[r0:r1]
        if r1 <= r0 or w <= 0:
            return np.zeros((max(r1 - r0, 0), max(w, 0)) + self.values.shape[2:], np.float32)
        f = int(self.factor)
        if f not in (2, 4, 8, 16):
            m = np.array([[1 / f, 0.0, (0.5 - self.offset[1]) / f - 0.5],
                          [0.0, 1 / f, (0.5 + r0 - self.offset[0]) / f - 0.5]], np.float64)
            return cv2.warpAffine(self.values, m, (w, r1 - r0), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                  borderMode=cv2.BORDER_REPLICATE)
        hh, ww = self.values.shape[:2]
        (y0, y1, top, bottom), (x0, x1, left, right) = (_resize_span(r0, r1, int(self.offset[0]), hh * f),
                                                        _resize_span(0, w, int(self.offset[1]), ww * f))
        i0, i1 = max(0, (y0 - f) // f), min(hh, (y1 + f) // f + 1)   # the cells rows y0:y1 read, and one more
        part = cv2.resize(np.ascontiguousarray(self.values[i0:i1]), (ww * f, (i1 - i0) * f),
                          interpolation=cv2.INTER_LINEAR)
        part = part.reshape(part.shape[:2] + self.values.shape[2:])[y0 - i0 * f:y1 - i0 * f, x0:x1]
        if top or bottom or left or right:
            part = cv2.copyMakeBorder(np.ascontiguousarray(part), top, bottom, left, right, cv2.BORDER_REPLICATE)
            part = part.reshape(part.shape[:2] + self.values.shape[2:])
        return part


def _resize_span(a: int, b: int, offset: int, n: int) -> tuple[int, int, int, int]:
    """Pixels ``a:b`` of :meth:`Coarse.full` along one axis as ``(s, e, before, after)``: the rows
    (or columns) ``s:e`` of the resize of ``n`` pixels, then ``before`` and ``after`` copies of its
    first and last (pixel ``p`` is the resize's ``p - offset``, clipped to it)."""
    s, e = min(max(a - offset, 0), n), min(max(b - offset, 0), n)
    if e > s:
        before = max(0, min(offset, b) - a)
        return s, e, before, (b - a) - before - (e - s)
    if b - offset <= 0:      # wholly before the cells: the first pixel's value throughout
        return 0, 1, b - a - 1, 0
    return n - 1, n, 0, b - a - 1   # wholly after: the last's


def coarse_normals(normals: np.ndarray, sigma_px: float, *, mask: np.ndarray | None = None,
                   full_size: bool = True, origin=(0, 0)):
    """The normal field smoothed at a large ``sigma_px`` (masked, 1/nz-weighted as
    :func:`common.rgbn.smoothing.smooth_normals`), computed on a grid downsampled by
    ``max(1, sigma_px // 4)`` — a field that smooth costs almost nothing at a quarter of its
    sigma per sample — and, with ``full_size``, interpolated back (else a :class:`Coarse`).

    ``origin`` (row, column) is the position of this window in a larger image: the coarse grid
    is aligned to the whole image's, so overlapping tiles compute the same field.
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    h, w = normals.shape[:2]
    f = coarse_grid(sigma_px, (h, w))
    if f == 1:
        c = smooth_normals(normals, sigma_px, mask=mask)
        return c if full_size else Coarse(c, 1, (0, 0))
    o = (int(-origin[0]) % f, int(-origin[1]) % f)  # first full cell of the global grid
    hh, ww = (h - o[0]) // f, (w - o[1]) // f
    if hh < 2 or ww < 2:
        c = smooth_normals(normals, sigma_px, mask=mask)
        return c if full_size else Coarse(c, 1, (0, 0))
    small = np.empty((hh, ww, 4), np.float32)
    area_stack(normals, mask, f, o, out=small)
    small_n, small_w = unit_cells(small)
    del small
    coarse = Coarse(smooth_normals(small_n, sigma_px / f, mask=small_w > 0), f, o)
    if not full_size:
        return coarse
    out = coarse.full((h, w))
    return out / np.maximum(np.sqrt(np.einsum("...i,...i->...", out, out)), 1e-12)[..., None]


def coarse_grid(sigma_px: float, shape) -> int:
    """Grid step of :func:`coarse_normals` for ``sigma_px`` on an image of ``shape``."""
    return int(max(1, min(sigma_px // 4, min(shape[:2]) // 8)))


def area_stack(normals: np.ndarray, mask: np.ndarray, f: int, offset=(0, 0), *, out: np.ndarray) -> np.ndarray:
    """The 1/nz-weighted stack (w n, w) (:func:`common.rgbn.smoothing.weighted_stack`, nz >= 0.05)
    area-averaged onto the cells of ``f`` x ``f`` pixels whose first starts at ``offset`` (row,
    column): ``out`` (hh, ww, 4) float32, filled strip by strip (no full-resolution temporary)."""
    hh, ww = out.shape[:2]
    cols = slice(offset[1], offset[1] + ww * f)
    for i0, i1, _, _ in strips((hh, ww * f), 0, pixels=max(1 << 20, ww * f) // f):
        rows = slice(offset[0] + i0 * f, offset[0] + i1 * f)
        st = weighted_stack(normals[rows, cols], mask[rows, cols], nz_min=0.05)
        out[i0:i1] = cv2.resize(st, (ww, i1 - i0), interpolation=cv2.INTER_AREA).reshape(i1 - i0, ww, 4)
    return out


def unit_cells(small: np.ndarray):
    """(unit normals (hh, ww, 3), weights (hh, ww)) of an area-averaged stack (:func:`area_stack`)."""
    small_w = np.ascontiguousarray(small[..., 3])
    small_n = np.ascontiguousarray(small[..., :3])
    small_n /= np.maximum(small_w, 1e-12)[..., None]
    small_n /= np.maximum(np.linalg.norm(small_n, axis=2, keepdims=True), 1e-12)
    return small_n, small_w


def whole_coarse_normals(source, sigma_px: float):
    """:func:`coarse_normals` of a whole image (``full_size=False``, origin (0, 0)) read window
    by window from ``source`` (``shape`` and ``window(r0, r1, c0, c1) -> RGBNImage``): the cells
    are area-averaged a strip of rows at a time, so only the coarse grid is held. None when the
    field is not taken on a coarser grid (f = 1)."""
    h, w = source.shape
    f = coarse_grid(sigma_px, (h, w))
    hh, ww = h // f, w // f
    if f == 1 or hh < 2 or ww < 2:
        return None
    small = np.empty((hh, ww, 4), np.float32)
    rows = max(1, (1 << 24) // max(ww * f * f, 1))   # ~16 Mpx read at a time
    for i0 in range(0, hh, rows):
        i1 = min(hh, i0 + rows)
        win = source.window(i0 * f, i1 * f, 0, ww * f)
        area_stack(win.normals, win.mask, f, (0, 0), out=small[i0:i1])
    small_n, small_w = unit_cells(small)
    return Coarse(smooth_normals(small_n, sigma_px / f, mask=small_w > 0), f, (0, 0))


def coarse_window(coarse: Coarse, r0: int, r1: int, c0: int, c1: int) -> Coarse:
    """The cells of an image's :class:`Coarse` field that the window rows ``r0:r1``, columns
    ``c0:c1`` of that image interpolate from — those over the window and one more ring — as a
    :class:`Coarse` of the window: its :meth:`Coarse.full` on the window is the field's on those
    pixels. The field may itself be a window's (a tile's, any ``offset``)."""
    f = coarse.factor
    hh, ww = coarse.values.shape[:2]
    (o0, o1) = coarse.offset
    i0, i1 = max(0, (r0 - o0) // f - 1), min(hh, -(-(r1 - o0) // f) + 1)
    j0, j1 = max(0, (c0 - o1) // f - 1), min(ww, -(-(c1 - o1) // f) + 1)
    return Coarse(coarse.values[i0:i1, j0:j1], f, (o0 + i0 * f - r0, o1 + j0 * f - c0))


#: a surface whose coarse normals' mean is at least this long is near-flat (a painting, a relief, even when near
#: lights tilted the whole solve) and is levelled; a curved object (a ball: about 0.7) is not
NEAR_FLAT = 0.95


def levelling_sigma_px(shape) -> float:
    """The scale (px) of the slow undulation levelling removes from an image of ``shape``: a sixteenth of its
    shorter side, within 8–96 px."""
    return float(np.clip(min(shape[:2]) / 16.0, 8.0, 96.0))


def near_flat_facing(coarse: np.ndarray) -> np.ndarray | None:
    """The unit mean of a coarse normal field (its values, any shape (..., 3)) when it is longer than
    :data:`NEAR_FLAT` — the surface is near-flat and faces that way —, else None (a curved object)."""
    mean = np.asarray(coarse).reshape(-1, 3).astype(np.float64).mean(axis=0)
    length = float(np.linalg.norm(mean))
    return (mean / length).astype(np.float32) if length > NEAR_FLAT else None


def surface_normal(normals: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray | None:
    """The way a near-flat surface faces as a whole: :func:`near_flat_facing` of its normals smoothed at
    :func:`levelling_sigma_px` (:func:`coarse_normals`), or None for a curved object (which has no one direction)
    or no surface.

    A viewer lights a painting whose solve is tilted as a whole (a panel not square to the camera,
    a light file's small bias) relative to this direction: the light turned by the rotation that takes
    it to the view axis (:func:`levelled_light` of a constant field), as levelling does per region.

    Examples
    --------
    >>> n = np.zeros((64, 64, 3), np.float32); n[...] = (0.5, 0.0, np.sqrt(0.75))   # tilted 30° towards +x
    >>> [round(float(v), 4) for v in surface_normal(n)]
    [0.5, 0.0, 0.866]
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if not mask.any():
        return None
    return near_flat_facing(coarse_normals(normals, levelling_sigma_px(normals.shape), mask=mask, full_size=False).values)


def level_normals(normals: np.ndarray, sigma_px: float, *, mask: np.ndarray | None = None,
                  origin=(0, 0), coarse: Coarse | None = None) -> np.ndarray:
    """Normals relative to the surface's own slow undulation: every normal is rotated by the
    rotation that takes the normal field smoothed at ``sigma_px`` to the view axis (0, 0, 1).

    A raking light then rakes the *surface* (a painting whose solved normals carry the slow tilt
    of near lights, a warped panel) instead of putting half of it in shadow. Detail finer than
    ``sigma_px`` is unchanged; a plane becomes (0, 0, 1).

    ``coarse``: the smoothed field, when given (a tile's window of the whole image's).

    Examples
    --------
    >>> n = np.zeros((8, 8, 3), np.float32); n[...] = (0.6, 0.0, 0.8)
    >>> [round(float(v), 6) + 0.0 for v in level_normals(n, 2.0)[4, 4]]
    [0.0, 0.0, 1.0]
    """
    normals = check_normals(normals)
    if coarse is None:
        c = coarse_normals(normals, sigma_px, mask=mask, origin=origin)
    else:   # the field given (a tile's window of the whole image's, :func:`coarse_window`)
        c = unit_rows(coarse.full(normals.shape[:2]))
    cz = np.maximum(c[..., 2], 1e-3)
    # Rodrigues for the rotation taking c to z: axis v = c x z = (cy, -cx, 0), cos = cz
    vx, vy = c[..., 1], -c[..., 0]
    nx, ny, nz = normals[..., 0], normals[..., 1], normals[..., 2]
    vdotn = vx * nx + vy * ny
    k = vdotn / (1.0 + cz)
    out = np.empty_like(normals)
    # v x n = (vy nz, -vx nz, vx ny - vy nx)
    out[..., 0] = nx * cz + vy * nz + vx * k
    out[..., 1] = ny * cz - vx * nz + vy * k
    out[..., 2] = nz * cz + (vx * ny - vy * nx)
    out /= np.maximum(np.sqrt(np.einsum("...i,...i->...", out, out)), 1e-12)[..., None]
    return out


def level_light(light, coarse, shape) -> np.ndarray:
    """The per-pixel light that lights the normals as :func:`level_normals` would: instead of
    rotating every normal n by R (which takes the coarse normal c to the view axis), the light is
    rotated back, ``n . (R^T l) = (R n) . l``. R^T l varies as slowly as c, so it is computed on
    ``coarse`` (the coarse field: full size, or a :class:`Coarse` from :func:`coarse_normals`;
    :func:`levelled_light`) and interpolated to ``shape`` — much cheaper than rotating every normal.

    Returns
    -------
    (H, W, 3) float32 unit light directions.
    """
    return unit_rows(levelled_light(light, coarse).full(shape))


def levelled_light(light, coarse) -> Coarse:
    """:func:`level_light` on the coarse field's own grid, before interpolation: a :class:`Coarse`
    whose ``full(shape, rows=...)``, made unit, is the per-pixel light of any rows."""
    l = as_light(light).astype(np.float32)
    grid = coarse if isinstance(coarse, Coarse) else Coarse(np.asarray(coarse, np.float32), 1, (0, 0))
    c = grid.values
    cz = np.maximum(c[..., 2], 1e-3)
    # R^T rotates z to c: axis u = z x c = (-cy, cx, 0), cos = cz (Rodrigues)
    ux, uy = -c[..., 1], c[..., 0]
    k = (ux * l[0] + uy * l[1]) / (1.0 + cz)
    out = np.empty(c.shape, np.float32)
    # u x l = (uy lz, -ux lz, ux ly - uy lx)
    out[..., 0] = l[0] * cz + uy * l[2] + ux * k
    out[..., 1] = l[1] * cz - ux * l[2] + uy * k
    out[..., 2] = l[2] * cz + (ux * l[1] - uy * l[0])
    return Coarse(out, grid.factor, grid.offset)


# ---- colour plus relief -------------------------------------------------------------------------

def lightness_relief(albedo: np.ndarray, relief: np.ndarray | None, *, strength: float = 0.6,
                     exposure: tuple[float, float] | None = None, encoded: bool = False) -> np.ndarray:
    """Relief drawn on the lightness of the colour only (CIELAB L*), so the paint keeps its hue
    and chroma.

    With ``r`` the relief in [-1, 1] (0 = no relief), ``L' = L + strength * r * (100 - L)`` where
    ``r > 0`` and ``L' = L + strength * r * L`` where ``r < 0``: a soft-light on L* that can
    never push a pixel out of [0, 100] (no relief pixel saturates). ``exposure = (lo, hi)``
    first maps L* through :func:`tone_curve` so that ``lo -> 20`` and ``hi -> 80`` (give the 5th
    and 95th percentiles, :func:`lightness_range`), scaling a* and b* with L* (the hue is kept).
    A colour that sRGB cannot show after all is pulled towards the grey of its lightness
    (:func:`gamut_map_lab`: chroma reduced, hue and lightness kept) instead of having a channel
    clipped.

    Parameters
    ----------
    albedo : (H, W, 3) float
        Linear RGB colour in [0, 1] (``encoded``: display, sRGB-encoded colour, decoded a strip of
        rows at a time by :func:`common.rgbn.io.srgb_to_linear`, never as a whole).
    relief : (H, W) float or None
        Relief signal in [-1, 1]; None: none (exposure only).
    strength : float
        Share of the room to black/white that the strongest relief uses, in [0, 1].
    exposure : (float, float), optional
        L* values mapped to 20 and 80.

    Returns
    -------
    (H, W, 3) float32
        Display (sRGB-encoded) colour in [0, 1].

    References
    ----------
    W3C Compositing and Blending Level 1, "soft-light"; CIE 15:2004 (CIELAB).
    """
    if not 0 <= strength <= 1:
        raise ValueError(f"strength must be in [0, 1], got {strength}")
    albedo = np.asarray(albedo, np.float32)
    if albedo.ndim != 3 or albedo.shape[2] != 3:
        raise ValueError(f"albedo must be (H, W, 3), got shape {albedo.shape}")
    if relief is not None:
        relief = np.asarray(relief, np.float32)
        if relief.shape != albedo.shape[:2]:
            raise ValueError(f"relief must be {albedo.shape[:2]}, got {relief.shape}")
    if relief is None:
        strength = 0.0
    # per pixel, so drawn a strip of rows at a time: the Lab copy and the temporaries are a strip's
    # (memory already mapped and in cache), only the result has the image's size
    from common.rgbn.io import srgb_to_linear

    out = np.empty(albedo.shape, np.float32)
    for r0, r1, _, _ in strips(albedo.shape, 0):
        rows = srgb_to_linear(albedo[r0:r1]) if encoded else albedo[r0:r1]
        _lightness_relief_rows(rows, None if relief is None else relief[r0:r1], np.float32(strength), exposure,
                               out[r0:r1], inside=encoded)
    return out


def _lightness_relief_rows(albedo: np.ndarray, relief: np.ndarray, strength, exposure, out: np.ndarray, *,
                           inside: bool = False) -> None:
    """:func:`lightness_relief` of some rows (checked arguments), written to ``out`` (contiguous);
    ``inside``: the colours are known to lie in [0, 1] (decoded ones), not looked at for that."""
    # OpenCV's float LRGB2Lab takes linear RGB in [0, 1] and gives L* in [0, 100]; Lab2RGB gives
    # sRGB-encoded values back (its own gamma tables: no per-pixel power here)
    inside = inside or (albedo.size and float(albedo.min()) >= 0.0 and float(albedo.max()) <= 1.0)
    lab = cv2.cvtColor(np.ascontiguousarray(albedo if inside else np.clip(albedo, 0.0, 1.0)), cv2.COLOR_LRGB2Lab)
    # L*, a*, b* as contiguous planes (numpy is slow on every third value of an interleaved array),
    # put back together by one merge before the conversion back
    L, a, b = cv2.split(lab)
    if exposure is not None:
        lo, hi = float(exposure[0]), float(exposure[1])
        if hi > lo:
            L2 = tone_curve(L, lo, hi)
            L2 *= np.float32(100.0)
            # an exposure change scales chroma with lightness (a darker print of the same paint),
            # so a saturated colour made darker stays a colour sRGB can show
            k = np.maximum(L, np.float32(1.0))
            np.divide(L2, k, out=k)
            np.clip(k, 0.0, 2.0, out=k)
            a *= k
            b *= k
            del k
            L = L2
    if strength > 0:
        r = np.clip(relief, -1.0, 1.0) * strength
        L = L + r * np.where(r > 0, 100.0 - L, L)
    cv2.merge([np.asarray(L, np.float32), a, b], dst=lab)
    # OpenCV's Lab2RGB clips each channel: the colours it clipped are mapped again, chroma only
    _into_gamut(cv2.cvtColor(lab, cv2.COLOR_Lab2RGB, dst=out), lab)


#: CIE XYZ -> linear sRGB and the D65 white, with OpenCV's constants (``COLOR_Lab2RGB``), so the
#: colours this module computes itself agree with OpenCV's where both are in gamut.
_XYZ_TO_RGB = np.array([[3.240479, -1.537150, -0.498535],
                        [-0.969256, 1.875991, 0.041556],
                        [0.055648, -0.204043, 1.057311]], np.float32)
_WHITE_X, _WHITE_Z = 0.950456, 1.088754
#: Bisection steps of the gamut mapping: the chroma kept is within 2^-16 of its largest in-gamut value.
GAMUT_STEPS = 16
#: A linear channel this far outside [0, 1] is float rounding, not a colour outside the gamut.
_GAMUT_EPS = 1e-5


def lab_to_linear_rgb(L: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """CIELAB (D65) to linear sRGB **without clipping**: a colour sRGB cannot show has a channel
    below 0 or above 1 (OpenCV's float ``COLOR_Lab2RGB`` / ``Lab2LRGB`` clip each channel, which is
    why :func:`lightness_relief` does not use them for such colours).

    Parameters
    ----------
    L, a, b : (N,) float
        L* in [0, 100], a* and b*.

    Returns
    -------
    (N, 3) float32
        Linear RGB, unbounded.

    References
    ----------
    CIE 15:2004, eqs. 8.6-8.8 (inverse CIELAB); IEC 61966-2-1 (sRGB primaries, D65).
    """
    L = np.asarray(L, np.float32)
    low = L <= 7.9996  # OpenCV's split: Y = L / 903.3 below, ((L + 16) / 116)^3 above
    fy = np.where(low, 7.787 * (L / 903.3) + 16.0 / 116.0, (L + 16.0) / 116.0).astype(np.float32)
    Y = np.where(low, L / 903.3, fy * fy * fy)

    def finv(f):
        return np.where(f > 0.206893, f * f * f, (f - 16.0 / 116.0) / 7.787)

    X = finv(fy + np.asarray(a, np.float32) / 500.0) * _WHITE_X
    Z = finv(fy - np.asarray(b, np.float32) / 200.0) * _WHITE_Z
    return (np.stack([X, Y, Z], axis=-1) @ _XYZ_TO_RGB.T).astype(np.float32)


def gamut_map_lab(L: np.ndarray, a: np.ndarray, b: np.ndarray, *, steps: int = GAMUT_STEPS) -> np.ndarray:
    """Colours given in CIELAB brought into the sRGB gamut by reducing their chroma only: L* and
    the hue angle ``atan2(b*, a*)`` are kept, and (a*, b*) are scaled by the largest ``s`` in
    [0, 1] for which the colour fits (found by bisection; ``s = 0``, the grey of that lightness,
    always fits). A colour already inside is returned unchanged.

    Parameters
    ----------
    L, a, b : (N,) float
        L* in [0, 100], a* and b*.
    steps : int
        Bisection steps: ``s`` is within ``2**-steps`` below its largest in-gamut value.

    Returns
    -------
    (N, 3) float32
        Linear RGB in [0, 1].

    References
    ----------
    Morovič, *Color Gamut Mapping* (Wiley 2008), §10.2: lightness- and hue-preserving chroma
    clipping towards the lightness axis.
    """
    L = np.clip(np.asarray(L, np.float32), 0.0, 100.0)
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    rgb = lab_to_linear_rgb(L, a, b)
    out = ~((rgb >= -_GAMUT_EPS) & (rgb <= 1.0 + _GAMUT_EPS)).all(axis=-1)
    if out.any():
        Lo, ao, bo = L[out], a[out], b[out]
        lo = np.zeros(Lo.shape, np.float32)   # always inside (the grey)
        hi = np.ones(Lo.shape, np.float32)    # outside
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            c = lab_to_linear_rgb(Lo, mid * ao, mid * bo)
            fits = ((c >= 0.0) & (c <= 1.0)).all(axis=-1)
            lo = np.where(fits, mid, lo)
            hi = np.where(fits, hi, mid)
        rgb[out] = lab_to_linear_rgb(Lo, lo * ao, lo * bo)
    return np.clip(rgb, 0.0, 1.0)


def _into_gamut(rgb: np.ndarray, lab: np.ndarray) -> np.ndarray:
    """The display colours of ``lab`` (``rgb``: OpenCV's ``Lab2RGB`` of it, each channel clipped),
    with every colour sRGB cannot show replaced by :func:`gamut_map_lab` (hue and lightness kept,
    chroma reduced) instead of having a channel clipped, which would shift the hue and flatten the
    relief. Only a colour OpenCV left with a channel at 0 or 1 can be one, so only those are
    recomputed."""
    from common.rgbn.io import linear_to_srgb

    rgb = np.ascontiguousarray(rgb, np.float32)   # written through a flat view below
    # one pass (cv2.inRange: every channel strictly inside) instead of reductions over the 3-channel
    # axis, which numpy runs slowly on large images
    edge = cv2.inRange(rgb, (1e-6, 1e-6, 1e-6), (1.0 - 1e-6, 1.0 - 1e-6, 1.0 - 1e-6)) == 0
    if not edge.any():
        return rgb
    lab_e = np.asarray(lab, np.float32)[edge]
    exact = lab_to_linear_rgb(lab_e[:, 0], lab_e[:, 1], lab_e[:, 2])
    outside = ~((exact >= -_GAMUT_EPS) & (exact <= 1.0 + _GAMUT_EPS)).all(axis=1)
    if outside.any():
        idx = np.flatnonzero(edge.ravel())[outside]
        mapped = gamut_map_lab(lab_e[outside, 0], lab_e[outside, 1], lab_e[outside, 2])
        rgb = rgb if rgb.flags.writeable else rgb.copy()
        rgb.reshape(-1, 3)[idx] = linear_to_srgb(mapped)
    return rgb


#: The narrowest lightness range (L* units) that an exposure stretches to L* 20-80: a colour
#: varying less is drawn with a range this wide (the tone curve's gain stays <= 60 / 6 = 10) ...
MIN_LIGHTNESS_RANGE = 6.0
#: ... and at least this many times the pixel noise of its lightness, so the capture's noise is
#: drawn at most 60 / 10 = 6 L* strong ...
NOISE_RANGES = 10.0
#: ... but never wider than this (L*): a colour that varies this much is stretched as it is.
MAX_LIGHTNESS_FLOOR = 15.0


def lightness_range(albedo: np.ndarray, mask: np.ndarray | None = None, *,
                    encoded: bool = False) -> tuple[float, float]:
    """The 5th and 95th percentiles of CIELAB L* (0-100) of a linear albedo: the ``exposure`` of
    :func:`lightness_relief`, which puts them at L* 20 and 80. A range already wider than 20-80
    is kept. A nearly uniform colour (one metal, one plaster: less than 15 L* between the
    percentiles) is stretched as it is when its spread is at least :data:`MIN_LIGHTNESS_RANGE`
    and :data:`NOISE_RANGES` times its pixel noise (:func:`lightness_noise`), else widened to
    that (so a colour that is mostly noise is not turned into amplified noise). ``encoded``: the
    colour is display (sRGB-encoded) colour; only the pixels measured are decoded."""
    from common.rgbn.io import srgb_to_linear

    albedo = np.asarray(albedo, np.float32)
    m = check_mask(mask, albedo.shape[:2])
    flat = masked_stride(albedo, m, _SAMPLE)
    if flat.shape[0] == 0:
        return 5.0, 95.0
    if encoded:
        flat = srgb_to_linear(flat)
    L = cv2.cvtColor(np.ascontiguousarray(np.clip(flat, 0.0, 1.0)[None]), cv2.COLOR_LRGB2Lab)[0, :, 0]
    lo, hi = robust_range(L, clip_percent=5.0)
    if lo <= 20.0 and hi >= 80.0:
        return 20.0, 80.0
    mid = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    if 2.0 * half < MAX_LIGHTNESS_FLOOR:
        floor = min(MAX_LIGHTNESS_FLOOR,
                    max(MIN_LIGHTNESS_RANGE, NOISE_RANGES * lightness_noise(albedo, m, encoded=encoded)))
        half = max(half, 0.5 * floor)
    return float(mid - half), float(mid + half)


def lightness_noise(albedo: np.ndarray, mask: np.ndarray | None = None, *, encoded: bool = False) -> float:
    """Standard deviation of the pixel-scale noise of CIELAB L* (0-100) of a linear albedo, by
    Immerkær's Laplacian-residual estimator (as :func:`normal_noise`) on up to five 1024-px
    windows: about 0.1 for clean 8-bit sRGB, 0.3-1 for a scan or a JPEG photograph. ``encoded``: the
    colour is display (sRGB-encoded) colour, each window decoded."""
    from common.rgbn.io import srgb_to_linear

    albedo = np.asarray(albedo, np.float32)
    mask = check_mask(mask, albedo.shape[:2])
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    res = []
    for win in _windows(albedo.shape[:2]):
        m = cv2.erode(mask[win].astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                      borderValue=0) > 0
        colour = srgb_to_linear(albedo[win]) if encoded else albedo[win]
        L = cv2.cvtColor(np.ascontiguousarray(np.clip(colour, 0.0, 1.0)), cv2.COLOR_LRGB2Lab)[..., 0]
        res.append(np.abs(cv2.filter2D(np.ascontiguousarray(L), cv2.CV_32F, kernel,
                                       borderType=cv2.BORDER_REFLECT)[m]))
    v = np.concatenate(res) if res else np.zeros(0, np.float32)
    return 1.4826 * float(median(v)) / 6.0 if v.size else 0.0


def lightness_spread(albedo: np.ndarray, mask: np.ndarray | None = None) -> float:
    """The 5th-95th percentile span of CIELAB L* (0-100) of a linear albedo: how much the colour
    itself varies (a painting 40-70, one metal or one plaster 5-15)."""
    albedo = np.asarray(albedo, np.float32)
    m = check_mask(mask, albedo.shape[:2])
    flat = masked_stride(albedo, m, _SAMPLE)
    if flat.shape[0] == 0:
        return 0.0
    L = cv2.cvtColor(np.ascontiguousarray(np.clip(flat, 0.0, 1.0)[None]), cv2.COLOR_LRGB2Lab)[0, :, 0]
    lo, hi = robust_range(L, clip_percent=5.0)
    return float(hi - lo)


def detail_shading(normals: np.ndarray, light=(135.0, 45.0), *, mask: np.ndarray | None = None,
                   sigma_px: float = 4.0, fine_px: float = 1.0) -> np.ndarray:
    """The shading of the relief finer than ``sigma_px``: ``(n_f - n_s) . l`` with ``n_f`` and
    ``n_s`` the normals smoothed at ``fine_px`` (noise) and ``sigma_px`` (the shape).

    It is the change of Lambertian shading that normal unsharp masking adds (Malzbender et al.
    2006), without the shading of the overall shape (which, on a painting, is mostly the bias of
    near lights). Zero on a plane and on any shape smoother than ``sigma_px``.

    Returns
    -------
    (H, W) float32, about [-1, 1] (usually within +-0.1).
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if not sigma_px > fine_px >= 0:
        raise ValueError(f"sigma_px must exceed fine_px >= 0, got sigma_px={sigma_px}, fine_px={fine_px}")
    l = as_light(light)
    d = smoothed_cosines(normals, fine_px, [l], mask=mask)[0]
    d -= smoothed_cosines(normals, sigma_px, [l], mask=mask)[0]
    return d


def normal_unsharp_masking(normals: np.ndarray, light=(135.0, 45.0), *, mask: np.ndarray | None = None,
                           sigma_px: float = 4.0, gain: float = 3.0, fine_px: float = 0.0) -> np.ndarray:
    """RTIViewer's normal unsharp masking: the normals' detail is amplified,
    ``n_e = normalize(n + gain * (n - G_sigma * n))``, and ``n_e`` is lit (Lambert, ``n_e . l``
    clamped at 0).

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    light : 3-vector or (azimuth_deg, elevation_deg)
    mask : (H, W) bool, optional
    sigma_px : float
        Width of the Gaussian whose residual is the detail, pixels.
    gain : float
        The enhancement gain (RTIViewer's slider), >= 0.
    fine_px : float
        Smoothing of the noise first (0 = none, as RTIViewer).

    Returns
    -------
    (H, W) float32 in [0, 1]: the shading (multiply with the colour to get RTIViewer's picture).

    References
    ----------
    T. Malzbender, B. Wilburn, D. Gelb, B. Ambrisco, "Surface enhancement using real-time
    photometric stereo and reflectance transformation", EGSR 2006 (normal unsharp masking);
    Cultural Heritage Imaging, "Guide to RTIViewer" v1.1 (2013).
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if gain < 0:
        raise ValueError(f"gain must be >= 0, got {gain}")
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    n = smooth_normals(normals, fine_px, mask=mask) if fine_px > 0 else normals
    smooth = smooth_normals(normals, sigma_px, mask=mask)
    e = n + np.float32(gain) * (n - smooth)
    del smooth
    e /= np.maximum(np.sqrt(np.einsum("...i,...i->...", e, e)), 1e-12)[..., None]
    return np.maximum(dot_light(e, as_light(light)), 0.0)


def specular_enhancement(normals: np.ndarray, light=(135.0, 45.0), *, albedo: np.ndarray | None = None,
                         kd: float = 0.6, ks: float = 0.7, exponent: float = 40.0, clip: bool = True) -> np.ndarray:
    """Specular enhancement (Malzbender et al. 2001): the surface drawn as a shiny material,
    ``I = kd * albedo * max(n . l, 0) + ks * max(n . h, 0)^exponent`` with ``h`` the half vector
    between the light and the view ``v = (0, 0, 1)``. The highlight follows the slope of the
    surface much more sharply than diffuse shading, so small relief shows.

    Parameters
    ----------
    normals : (H, W, 3) float
    light : 3-vector or (azimuth_deg, elevation_deg)
    albedo : (H, W, 3) float, optional
        Display colour (the diffuse term's); None = 0.75 grey.
    kd, ks : float
        Diffuse and specular weights (RTIViewer's kd, ks), >= 0.
    exponent : float
        The specular exponent (RTIViewer's n), > 0: larger = tighter highlights.
    clip : bool
        Clip to [0, 1] (False: leave highlights above 1 for a tone curve).

    Returns
    -------
    (H, W, 3) float32 in [0, 1] (>= 0 when not clipped)

    References
    ----------
    T. Malzbender, D. Gelb, H. Wolters, "Polynomial texture maps", SIGGRAPH 2001, §5.2
    (specular enhancement).
    """
    normals = check_normals(normals)
    l = as_light(light)
    return specular_of_cosines(dot_light(normals, l), dot_light(normals, half_vector(l)), albedo=albedo,
                               kd=kd, ks=ks, exponent=exponent, clip=clip)


def half_vector(light: np.ndarray) -> np.ndarray:
    """The unit half vector between a light (a 3-vector or an (H, W, 3) field of unit vectors) and
    the view ``v = (0, 0, 1)``: ``(l + v) / |l + v|``, float32."""
    h = np.asarray(light, np.float32) + np.array([0.0, 0.0, 1.0], np.float32)
    if h.ndim == 1:
        return h / np.float32(max(float(np.linalg.norm(h)), 1e-12))
    return unit_rows(h)


def specular_of_cosines(cos_nl: np.ndarray, cos_nh: np.ndarray, *, albedo: np.ndarray | None = None,
                        kd: float = 0.6, ks: float = 0.7, exponent: float = 40.0, clip: bool = True) -> np.ndarray:
    """:func:`specular_enhancement` of the cosines ``n . l`` and ``n . h`` per pixel ((H, W) float
    each; :func:`half_vector`)."""
    from common.rgbn.io import _power

    for name, v in (("kd", kd), ("ks", ks)):
        if v < 0:
            raise ValueError(f"{name} must be >= 0, got {v}")
    if not exponent > 0:
        raise ValueError(f"exponent must be > 0, got {exponent}")
    cos_nl = np.asarray(cos_nl, np.float32)
    base = np.float32(0.75) if albedo is None else np.asarray(albedo, np.float32)
    if albedo is not None and base.shape != cos_nl.shape + (3,):
        raise ValueError(f"albedo must be {cos_nl.shape + (3,)}, got {base.shape}")
    # each term made in place: one colour array and two planes in all
    diffuse = np.maximum(cos_nl, np.float32(0.0))
    diffuse *= np.float32(kd)
    spec = np.maximum(np.asarray(cos_nh, np.float32), np.float32(0.0))
    _power(spec, exponent)   # OpenCV's power, 3x numpy's (within 2e-7 of it)
    spec *= np.float32(ks)
    if albedo is not None:
        out = scale_colour(base, diffuse)
    else:
        diffuse *= base
        out = cv2.merge([diffuse, diffuse, diffuse])
    del diffuse
    cv2.add(out, cv2.merge([spec, spec, spec]), dst=out)
    return np.clip(out, 0.0, 1.0, out=out) if clip else out
