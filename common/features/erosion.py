"""Cracking and erosion (§5.4.6, Fig. 5.6).

Cracks and eroded pits are small dark dents: dark in colour and tilted in the normal map. A pixel
is *eroded* where both the black top-hat of the luminance (dark details smaller than the
structuring element) and the white top-hat of the normal tilt 1 − nz (steep details) exceed 0.3
of their range on the fragment; the structuring element is a disk of radius 3 pixels. The
descriptors are the density of eroded pixels and the mean area of the eroded components; per
fragment they are taken at ten structuring-element sizes (the disk of radius 3 on the image
area-averaged by a further 2^(1/3) per size).
"""

from __future__ import annotations

import cv2
import numpy as np

#: threshold on the normalised top-hats (§5.4.6)
EROSION_THRESHOLD = 0.3
#: structuring-element radius, pixels (§5.4.6)
EROSION_RADIUS_PX = 3
# lower bounds of the normalising ranges, so a smooth fragment's noise is not blown up to 1
_COLOUR_FLOOR = 0.15
_TILT_FLOOR = 0.1


def _disk(radius_px: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))


def _robust_max(v: np.ndarray) -> float:
    """99.9th percentile (of a regular subsample when there are many values: same statistic)."""
    if v.size > 200_000:
        v = v[:: v.size // 100_000]
    k = min(v.size - 1, int(0.999 * v.size))
    return float(np.partition(v, k)[k]) if v.size else 0.0


def erosion_map(grey, nz, mask, *, radius_px=EROSION_RADIUS_PX, threshold=EROSION_THRESHOLD):
    """Pixels marked as cracked or eroded (§5.4.6).

    Parameters
    ----------
    grey : (H, W) float
        Luminance of the albedo.
    nz : (H, W) float
        z component of the unit normals.
    mask : (H, W) bool
        Fragment pixels. Pixels closer than ``radius_px`` to the outline are never marked (the
        top-hats see the background there).
    radius_px : int
        Radius of the disk structuring element, pixels.
    threshold : float
        Threshold on each top-hat divided by its 99.9th percentile on the fragment.

    Returns
    -------
    eroded : (H, W) bool
    black_tophat : (H, W) float32
        Normalised black top-hat of the luminance.
    white_tophat : (H, W) float32
        Normalised white top-hat of the tilt 1 − nz.

    References
    ----------
    Toler-Franklin 2011, §5.4.6 and Fig. 5.6.

    Examples
    --------
    >>> g = np.full((40, 40), 0.6, np.float32); nz = np.ones((40, 40), np.float32)
    >>> g[20, 5:35] = 0.1; nz[20, 5:35] = 0.7          # a dark, steep crack
    >>> int(erosion_map(g, nz, np.ones((40, 40), bool))[0].sum())
    30
    """
    g = np.asarray(grey, dtype=np.float32)
    z = np.asarray(nz, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    if g.ndim != 2:
        raise ValueError(f"grey must be 2-D, got shape {g.shape}")
    if z.shape != g.shape or m.shape != g.shape:
        raise ValueError(f"grey {g.shape}, nz {z.shape} and mask {m.shape} must share one shape")
    if int(radius_px) < 1:
        raise ValueError(f"radius_px must be >= 1, got {radius_px}")
    if not m.any():
        empty = np.zeros_like(g)
        return np.zeros(g.shape, bool), empty, empty
    se = _disk(int(radius_px))
    # fill the background with neutral values: median luminance, flat normal
    g = np.where(m, g, np.median(g[m])).astype(np.float32)
    tilt = np.where(m, 1.0 - z, 0.0).astype(np.float32)
    bt = cv2.morphologyEx(g, cv2.MORPH_BLACKHAT, se)
    wt = cv2.morphologyEx(tilt, cv2.MORPH_TOPHAT, se)
    interior = cv2.erode(m.astype(np.uint8), se, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    sel = interior if interior.any() else m
    bt /= max(_robust_max(bt[sel]), _COLOUR_FLOOR)
    wt /= max(_robust_max(wt[sel]), _TILT_FLOOR)
    eroded = (bt > threshold) & (wt > threshold)
    # bridge one-pixel gaps so a crack stays one component however the scan was sampled
    eroded = cv2.morphologyEx(eroded.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)
    return eroded & interior, bt, wt


def erosion_statistics(eroded, region, pixel_mm):
    """Density of eroded pixels in a region and the mean area of the eroded components in it.

    Parameters
    ----------
    eroded : (H, W) bool
        Output of :func:`erosion_map`.
    region : (H, W) bool
        Region to describe (fragment or patch).
    pixel_mm : float
        Pixel size, mm.

    Returns
    -------
    (density, mean_area_mm2) : (float, float)
        ``density`` = eroded fraction of the region; ``mean_area_mm2`` = area-weighted mean area
        of the 8-connected components of eroded ∩ region (0 when there are none). NaN for an
        empty region.

    References
    ----------
    Toler-Franklin 2011, §5.4.6.

    Notes
    -----
    Components are cut to the region and their mean is weighted by area (sum a² / sum a: the
    size of the component an eroded pixel belongs to). A crack that only grazes a patch then adds
    a small piece with a small weight, and specks that come and go with noise barely move it;
    a plain per-component mean jumps in both cases.

    Examples
    --------
    >>> e = np.zeros((10, 10), bool); e[2, 2:6] = True; e[7, 7] = True
    >>> erosion_statistics(e, np.ones((10, 10), bool), 0.5)
    (0.05, 0.85)
    """
    e = np.asarray(eroded, dtype=bool)
    r = np.asarray(region, dtype=bool)
    if r.shape != e.shape:
        raise ValueError(f"region must be {e.shape}, got {r.shape}")
    n = int(r.sum())
    if n == 0:
        return np.nan, np.nan
    er = e & r
    k = int(np.count_nonzero(er))
    if k == 0:
        return 0.0, 0.0
    _, _, stats, _ = cv2.connectedComponentsWithStats(er.astype(np.uint8), connectivity=8)
    a = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    return k / n, float(np.sum(a * a) / np.sum(a)) * pixel_mm ** 2


def multiscale_erosion(grey, nz, mask, pixel_mm, *, n_scales=10, radius_px=EROSION_RADIUS_PX,
                       threshold=EROSION_THRESHOLD) -> dict[str, float]:
    """Erosion density and mean component area at ``n_scales`` structuring-element sizes.

    Size k applies the radius-3 disk to the image area-averaged to a pixel of
    ``pixel_mm * 2 ** (k / 3)``, i.e. a disk of ``3 * pixel_mm * 2 ** (k / 3)`` mm: on the
    0.1 mm working grid, radii 0.3 mm to 2.4 mm over the ten sizes (three per octave).

    Returns
    -------
    dict
        ``erosion_density_s<k>`` and ``erosion_size_s<k>`` (mm²) for k = 0 .. n_scales − 1;
        NaN once the downsampled fragment is smaller than the structuring element.

    References
    ----------
    Toler-Franklin 2011, §5.4.6 (multi-scale erosion, ten sizes per fragment).
    """
    return _multiscale_erosion(grey, nz, mask, pixel_mm, n_scales=n_scales, radius_px=radius_px,
                               threshold=threshold)[0]


def _multiscale_erosion(grey, nz, mask, pixel_mm, *, n_scales=10, radius_px=EROSION_RADIUS_PX,
                        threshold=EROSION_THRESHOLD) -> tuple[dict[str, float], np.ndarray]:
    # as multiscale_erosion, also returning the eroded map of size 0
    g = np.asarray(grey, dtype=np.float32)
    z = np.asarray(nz, dtype=np.float32)
    m = np.asarray(mask, dtype=np.float32)
    if not pixel_mm > 0:
        raise ValueError(f"pixel_mm must be positive, got {pixel_mm}")
    out = {}
    first = np.zeros(g.shape, bool)
    stack = cv2.merge([g * m, z * m, m])
    for k in range(int(n_scales)):
        f = 2.0 ** (k / 3.0)
        h, w = max(1, int(round(g.shape[0] / f))), max(1, int(round(g.shape[1] / f)))
        if k == 0:
            gk, zk, mk = g, z, m
        else:
            # area-average value*mask and mask so the background does not bleed into the edge
            small = cv2.resize(stack, (w, h), interpolation=cv2.INTER_AREA)
            mk = small[..., 2]
            safe = np.maximum(mk, 1e-6)
            gk, zk = small[..., 0] / safe, small[..., 1] / safe
        region = mk > 0.5
        if region.sum() < (2 * radius_px + 1) ** 2:
            out[f"erosion_density_s{k}"], out[f"erosion_size_s{k}"] = np.nan, np.nan
            continue
        eroded, _, _ = erosion_map(gk, zk, region, radius_px=radius_px, threshold=threshold)
        if k == 0:
            first = eroded
        d, s = erosion_statistics(eroded, region, pixel_mm * g.shape[1] / w)
        out[f"erosion_density_s{k}"], out[f"erosion_size_s{k}"] = d, s
    return out, first
