"""The outline of a fragment face: sub-pixel contour with outward normals and arc length (§5.2.1).

Fragment-frame coordinates in millimetres: ``x = col * pixel_mm`` (right), ``y = row * pixel_mm``
(down), pixel centres at integer indices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from skimage import measure


@dataclass
class Contour:
    """A closed fragment outline sampled uniformly by arc length.

    Attributes
    ----------
    points_mm : (M, 2) float
        Contour points (x right, y down) in mm, traversed so the fragment lies on the right-hand
        side on screen (clockwise), starting at the point farthest from the fragment centroid.
    normals : (M, 2) float
        Outward unit normals (same frame).
    arc_mm : (M,) float
        Arc length of each point from the start, mm.
    length_mm : float
        Perimeter, mm.
    """

    points_mm: np.ndarray
    normals: np.ndarray
    arc_mm: np.ndarray
    length_mm: float

    def at(self, arc_mm) -> tuple[np.ndarray, np.ndarray]:
        """Points and outward normals at arc positions (mm, wrapped), linearly interpolated."""
        s = np.mod(np.asarray(arc_mm, dtype=float), self.length_mm)
        sp = np.append(self.arc_mm, self.length_mm)
        pts = np.vstack([self.points_mm, self.points_mm[:1]])
        nrm = np.vstack([self.normals, self.normals[:1]])
        p = np.stack([np.interp(s, sp, pts[:, k]) for k in range(2)], axis=-1)
        n = np.stack([np.interp(s, sp, nrm[:, k]) for k in range(2)], axis=-1)
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        return p, n


def fragment_contour(mask, pixel_mm, *, step_mm=0.25, smooth_mm=0.5, normal_smooth_mm=1.0,
                     start_mm=None) -> Contour:
    """Sub-pixel outline of the largest fragment region of a mask.

    Parameters
    ----------
    mask : (H, W) bool or float array
        True (or coverage 1) on the fragment, e.g. a boolean mask or an area-averaged one. It is
        blurred by a one-pixel Gaussian and the 0.5 iso-line is traced (sub-pixel).
    pixel_mm : float
        Pixel size in mm.
    step_mm : float
        Arc-length spacing of the returned samples, mm.
    smooth_mm : float
        Gaussian smoothing of the positions along the arc (removes the pixel staircase), mm.
    normal_smooth_mm : float
        Gaussian smoothing of the tangent used for the normals, mm.
    start_mm : (2,) float, optional
        Start the contour at the point nearest to this one (x, y mm) instead of the point
        farthest from the centroid (e.g. to sample a re-scan at the same places).

    Returns
    -------
    Contour

    References
    ----------
    Toler-Franklin 2011, §5.2.1 (patches are placed along the contour of the front face).

    Examples
    --------
    >>> yy, xx = np.mgrid[:64, :64]
    >>> c = fragment_contour((yy - 32) ** 2 + (xx - 32) ** 2 < 20 ** 2, 0.5)
    >>> round(c.length_mm / (2 * np.pi * 10), 2)
    1.0
    """
    m = np.asarray(mask)
    if m.ndim != 2:
        raise ValueError(f"mask must be 2-D (H, W), got shape {m.shape}")
    if not (np.isfinite(pixel_mm) and pixel_mm > 0):
        raise ValueError(f"pixel_mm must be a positive number, got {pixel_mm}")
    if not step_mm > 0:
        raise ValueError(f"step_mm must be positive, got {step_mm}")
    # a one-pixel Gaussian softens the pixel staircase of a binary mask (it cannot restore a
    # sagitta below one pixel: that needs an area-averaged mask); it moves the 0.5 iso-line of
    # a curve of radius R pixels by only ~1/(2R) pixel
    f = ndi.gaussian_filter(m.astype(np.float32), 1.0)
    # keep only the largest region so holes or crumbs don't give the outline
    lab, n = ndi.label(f > 0.5)
    if n == 0:
        raise ValueError("mask has no fragment pixels: cannot trace a contour")
    if n > 1:
        sizes = ndi.sum_labels(np.ones_like(lab), lab, index=np.arange(1, n + 1))
        keep = ndi.binary_dilation(lab == 1 + int(np.argmax(sizes)), iterations=2)
        f = np.where(keep, f, 0.0)
    f = np.pad(f, 1)  # closes contours touching the image border
    curves = measure.find_contours(f, 0.5)
    rc = max(curves, key=len) - 1.0
    if len(rc) < 8:
        raise ValueError("fragment region is too small to trace a contour (fewer than 8 points)")
    xy = rc[:, ::-1] * pixel_mm
    if not np.allclose(xy[0], xy[-1]):
        xy = np.vstack([xy, xy[:1]])
    # resample uniformly by arc length
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    length = float(cum[-1])
    m_pts = max(8, int(round(length / step_mm)))
    s = np.linspace(0.0, length, m_pts, endpoint=False)
    pts = np.stack([np.interp(s, cum, xy[:, 0]), np.interp(s, cum, xy[:, 1])], axis=-1)
    step = length / m_pts
    if smooth_mm > 0:
        pts = ndi.gaussian_filter1d(pts, smooth_mm / step, axis=0, mode="wrap")
        # smoothing moves the samples along the curve: resample to uniform arc length again
        loop = np.vstack([pts, pts[:1]])
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=1))])
        s = np.linspace(0.0, cum[-1], m_pts, endpoint=False)
        pts = np.stack([np.interp(s, cum, loop[:, 0]), np.interp(s, cum, loop[:, 1])], axis=-1)
        step = cum[-1] / m_pts
    tan = ndi.gaussian_filter1d(pts, max(normal_smooth_mm / step, 0.5), axis=0, order=1, mode="wrap")
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
    # traversal: clockwise on screen (shoelace > 0 with y down) -> fragment on the right
    area2 = np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1])
    if area2 < 0:
        pts, tan = pts[::-1], -tan[::-1]
    # walking clockwise on screen (y down), the outside is on the left-hand side: (ty, -tx)
    normals = np.stack([tan[:, 1], -tan[:, 0]], axis=-1)
    # canonical start: farthest point from the centroid (rotation-invariant up to ties)
    if start_mm is None:
        centroid = pts.mean(axis=0)
        start = int(np.argmax(np.sum((pts - centroid) ** 2, axis=1)))
    else:
        start = int(np.argmin(np.sum((pts - np.asarray(start_mm, float)) ** 2, axis=1)))
    pts, normals = np.roll(pts, -start, axis=0), np.roll(normals, -start, axis=0)
    seg = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    return Contour(points_mm=pts, normals=normals, arc_mm=arc, length_mm=float(seg.sum()))
