"""Contour curvature at several scales: area-based (eq. 5.1) and three-point (eq. 5.2), §5.4.2.

Both are signed, convex > 0 (a disc of radius R gives +1/R), in 1/mm. The correspondence of two
fragments' curvatures is |a + b| (registry rule ``abs_sum``): where two fragments join, a convex
stretch of one meets an equally concave stretch of the other.
"""

from __future__ import annotations

import numpy as np

from common.features.contour import Contour
from common.features.patches import disk_window

# largest disc radius, in pixels, measured at full resolution by area_curvature
_DISC_PX = 40


def area_curvature(coverage_map, pixel_mm, points_mm, radius_mm):
    """Signed contour curvature from the area of a disc centred on the contour (eq. 5.1).

    The disc of radius r centred on a boundary point with curvature κ covers
    A(r) = π r² / 2 − κ r³ / 3 + O(r⁴) of the fragment (the area integral invariant), so

        κ = 3 (π r² / 2 − A) / r³.

    Parameters
    ----------
    coverage_map : (H, W) float or bool
        Fraction of each pixel on the fragment (an area-averaged mask gives sub-pixel accuracy).
    pixel_mm : float
        Pixel size of ``coverage_map``, mm.
    points_mm : (N, 2) float
        Contour points (x right, y down) in mm.
    radius_mm : float
        Disc radius r, mm (the thesis uses 2.5, 5, 8, 10 and 15 mm).

    Returns
    -------
    (N,) float
        Curvature in 1/mm, convex > 0 (the image is taken to be background beyond its border).

    References
    ----------
    Toler-Franklin 2011, §5.4.2, eq. 5.1; Manay et al., "Integral invariants for shape matching",
    PAMI 2006.

    Examples
    --------
    >>> from common.features.contour import fragment_contour
    >>> yy, xx = np.mgrid[:240, :240]
    >>> disc = (yy - 120) ** 2 + (xx - 120) ** 2 < 80 ** 2     # radius 20 mm at 0.25 mm/px
    >>> c = fragment_contour(disc, 0.25)
    >>> k = area_curvature(disc, 0.25, c.points_mm[::50], 10.0)
    >>> bool(np.all(np.abs(k * 20 - 1) < 0.1))
    True
    """
    cov = np.asarray(coverage_map, dtype=np.float32)
    if cov.ndim != 2:
        raise ValueError(f"coverage_map must be 2-D, got shape {cov.shape}")
    if not radius_mm > 0:
        raise ValueError(f"radius_mm must be positive, got {radius_mm}")
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 2)
    out = np.full(len(pts), np.nan)
    # a disc more than _DISC_PX pixels in radius is measured on a coarser area-averaged grid:
    # the anti-aliased disc and the coverage map keep the area exact, at a fraction of the cost
    f = int(radius_mm / pixel_mm // _DISC_PX)
    if f > 1:
        h, w = -(-cov.shape[0] // f), -(-cov.shape[1] // f)
        pad = np.zeros((h * f, w * f), np.float32)
        pad[:cov.shape[0], :cov.shape[1]] = cov
        cov = pad.reshape(h, f, w, f).mean(axis=(1, 3))
        # coarse cell (i, j) covers fine pixels i*f .. i*f+f-1: its centre sits at i*f + (f-1)/2
        pts = pts - (f - 1) / 2 * pixel_mm
        pixel_mm = pixel_mm * f
    r_px = radius_mm / pixel_mm
    # beyond the image border is background: pad so every disc lies wholly on the grid
    pad = int(np.ceil(r_px)) + 3
    cov = np.pad(cov, pad)
    shift = pad * pixel_mm
    for i, p in enumerate(pts):
        rows, cols, w, full = disk_window(p + shift, radius_mm, pixel_mm, cov.shape)
        if w.size == 0 or abs(w.sum() - full) > 0.02 * full:
            continue  # contour point far outside the image
        # area in px², normalised by the discretised disc so the estimate is unbiased
        a = float(np.sum(w * cov[rows, cols])) * (np.pi * r_px * r_px / float(w.sum()))
        out[i] = 3.0 * (np.pi * r_px * r_px / 2.0 - a) / r_px ** 3 / pixel_mm
    return out


def three_point_curvature(contour: Contour, arc_mm, span_mm):
    """Signed curvature of the circle through three contour points (eq. 5.2).

    For the contour points a = c(s − d), b = c(s), c = c(s + d) the circumcircle has curvature

        κ = 4 K / (|a − b| |b − c| |c − a|),   K = area of triangle abc,

    signed positive where the fragment is convex (the chord midpoint lies inside).

    Parameters
    ----------
    contour : Contour
    arc_mm : (N,) float
        Arc positions s of the middle points, mm.
    span_mm : float
        Arc distance d to the outer points, mm (the thesis uses 2.5, 5, 8, 10 and 15 mm).

    Returns
    -------
    (N,) float
        Curvature in 1/mm, convex > 0.

    References
    ----------
    Toler-Franklin 2011, §5.4.2, eq. 5.2.

    Examples
    --------
    >>> from common.features.contour import fragment_contour
    >>> yy, xx = np.mgrid[:200, :200]
    >>> c = fragment_contour((yy - 100) ** 2 + (xx - 100) ** 2 < 80 ** 2, 0.25)
    >>> k = three_point_curvature(c, c.arc_mm[::50], 10.0)
    >>> bool(np.all(np.abs(k * 20 - 1) < 0.05))
    True
    """
    if not span_mm > 0:
        raise ValueError(f"span_mm must be positive, got {span_mm}")
    if 2 * span_mm >= contour.length_mm:
        raise ValueError(f"span_mm {span_mm} is too long for a contour of {contour.length_mm:.1f} mm")
    s = np.asarray(arc_mm, dtype=float).ravel()
    a, _ = contour.at(s - span_mm)
    b, nb = contour.at(s)
    c, _ = contour.at(s + span_mm)
    ab, bc, ca = b - a, c - b, a - c
    cross = ab[:, 0] * (c - a)[:, 1] - ab[:, 1] * (c - a)[:, 0]
    denom = np.linalg.norm(ab, axis=1) * np.linalg.norm(bc, axis=1) * np.linalg.norm(ca, axis=1)
    k = 2.0 * np.abs(cross) / np.maximum(denom, 1e-12)
    bulge = np.sum(nb * ((a + c) / 2 - b), axis=1)  # < 0: chord inside, convex
    return np.where(bulge <= 0, k, -k)
