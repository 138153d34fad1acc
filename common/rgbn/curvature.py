"""Curvature of the surface seen in a normal map (§7.2.3, eqs. 7.3-7.7).

The surface is treated as a height field z(x, y) seen orthographically. With the normal
n = (nx, ny, nz) the (scaled) tangent vectors of eq. 7.6 are

    a = (nz, 0, -nx) = nz * dX/dx,      b = (0, nz, -ny) = nz * dX/dy,

the first fundamental form (scaled by nz^2) is I = [[a.a, a.b], [a.b, b.b]] and the second
(scaled by nz) is II = [[dn/dx . a, dn/dy . a], [dn/dx . b, dn/dy . b]] (symmetrized). The shape
operator is S = I^-1 II = adj(I) II / nz, so

    H = (G e - 2 F f + E g) / (2 nz),     K = e g - f^2,    k1,2 = H +- sqrt(H^2 - K).

Sign convention: **positive = convex towards the viewer** (a bump, a sphere seen from outside).
Derivatives are in mm (pixel size 25.4 / dpi), so curvatures are in 1/mm; a sphere of radius r mm
has H = 1/r, K = 1/r^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.rgbn._filters import check_mask, check_normals
from common.rgbn.smoothing import smooth_normals

#: nz below this is treated as a silhouette: curvature there is not measurable from the image.
NZ_MIN = 0.05


@dataclass
class Curvature:
    """Curvature maps of a normal map, all in 1/mm (0 outside the mask).

    Attributes
    ----------
    mean, gaussian : (H, W) float32
        Mean curvature H (1/mm, convex positive) and Gaussian curvature K (1/mm^2).
    k1, k2 : (H, W) float32
        Principal curvatures, k1 >= k2.
    dir1, dir2 : (H, W, 2) float32
        Principal directions of k1 and k2 as unit vectors in the image plane (x right, y up);
        the sign of a direction is arbitrary.
    """

    mean: np.ndarray
    gaussian: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    dir1: np.ndarray
    dir2: np.ndarray


def normal_derivatives(normals: np.ndarray, dpi: float, *, method: str = "central"):
    """dn/dx and dn/dy in 1/mm (x right = columns, y up = towards row 0).

    ``method`` 'central' uses (n[c+1] - n[c-1]) / 2; 'sobel' the 3x3 Sobel operator / 8, which
    also smooths across the derivative direction. Borders are reflected.
    """
    normals = check_normals(normals)
    if not np.isfinite(dpi) or dpi <= 0:
        raise ValueError(f"dpi must be a positive number, got {dpi}")
    if method not in ("central", "sobel"):
        raise ValueError(f"method must be 'central' or 'sobel', got {method!r}")
    pixel_mm = 25.4 / float(dpi)
    ksize, norm = (1, 0.5) if method == "central" else (3, 0.125)
    scale = norm / pixel_mm
    dx = cv2.Sobel(normals, cv2.CV_32F, 1, 0, ksize=ksize, scale=scale, borderType=cv2.BORDER_REFLECT)
    # y is up while rows go down
    dy = cv2.Sobel(normals, cv2.CV_32F, 0, 1, ksize=ksize, scale=-scale, borderType=cv2.BORDER_REFLECT)
    return dx, dy


def _fundamental_forms(normals, dx, dy):
    # the channels as contiguous planes (OpenCV's split): numpy is several times slower on the
    # strided channels of an interleaved array
    nx, ny, nz = cv2.split(np.ascontiguousarray(normals))
    np.maximum(nz, NZ_MIN, out=nz)
    (dx0, dx1, dx2), (dy0, dy1, dy2) = cv2.split(dx), cv2.split(dy)
    # first fundamental form of the scaled tangents a, b (eq. 7.6)
    E = nz * nz + nx * nx
    F = nx * ny
    G = nz * nz + ny * ny
    # second fundamental form: derivative of n along x / y dotted with a / b
    e = nz * dx0 - nx * dx2
    g = nz * dy1 - ny * dy2
    f = 0.5 * ((nz * dx1 - ny * dx2) + (nz * dy0 - nx * dy2))
    return nz, E, F, G, e, f, g


def mean_curvature(normals: np.ndarray, dpi: float, *, mask: np.ndarray | None = None,
                   method: str = "central", sigma_px: float = 0.0) -> np.ndarray:
    """Mean curvature H (1/mm, convex towards the viewer positive) of a normal map, eq. 7.7.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals, x right, y up, z towards the viewer.
    dpi : float
        Sampling density; the pixel is 25.4 / dpi mm.
    mask : (H, W) bool, optional
        Output is 0 outside it.
    method : {'central', 'sobel'}
        Derivative operator.
    sigma_px : float
        Optional foreshortening-corrected pre-smoothing (pixels).

    Returns
    -------
    (H, W) float32
        H = (G e - 2 F f + E g) / (2 nz) in 1/mm.

    References
    ----------
    Toler-Franklin 2011, §7.2.3, eqs. 7.6-7.7; do Carmo, *Differential Geometry of Curves and
    Surfaces*, §3-3.

    Examples
    --------
    >>> n = np.zeros((8, 8, 3), np.float32); n[..., 2] = 1
    >>> float(np.abs(mean_curvature(n, dpi=600)).max())
    0.0
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if sigma_px > 0:
        normals = smooth_normals(normals, sigma_px, mask=mask)
    if not np.isfinite(dpi) or dpi <= 0:
        raise ValueError(f"dpi must be a positive number, got {dpi}")
    H = np.empty(normals.shape[:2], np.float32)
    for rows, block, inner in _blocks(normals):
        H[rows] = _mean_curvature_block(block, dpi, method)[inner]
    H[~mask] = 0.0
    return H


def _mean_curvature_block(normals: np.ndarray, dpi: float, method: str) -> np.ndarray:
    """Eq. 7.7 on the normals' channels as contiguous planes, the products grouped as
    ``(G e + E g - 2 F f) / (2 nz)`` in place (the fundamental forms of :func:`_fundamental_forms`
    without making each): central differences on the planes themselves (:func:`normal_derivatives`'
    'central', borders reflected; a third of its passes over memory), the Sobel operator through
    :func:`normal_derivatives`."""
    nx, ny, nz = cv2.split(np.ascontiguousarray(normals, np.float32))
    if method == "central":
        (dx0, dx1, dx2), (dy0, dy1, dy2) = _central_differences((nx, ny, nz), dpi)
    else:
        dx, dy = normal_derivatives(normals, dpi, method=method)
        (dx0, dx1, dx2), (dy0, dy1, dy2) = cv2.split(dx), cv2.split(dy)
    np.maximum(nz, NZ_MIN, out=nz)    # after the derivatives, as in _fundamental_forms
    nz2 = nz * nz
    out = nz * dx0                    # e
    out -= nx * dx2
    out *= nz2 + ny * ny              # G e
    g = nz * dy1
    g -= ny * dy2
    g *= nz2 + nx * nx                # E g
    out += g
    f2 = nz * dx1                     # 2 f
    f2 -= ny * dx2
    f2 += nz * dy0
    f2 -= nx * dy2
    f2 *= nx * ny                     # 2 F f
    out -= f2
    nz *= np.float32(2.0)
    out /= nz
    return out


def _central_differences(planes, dpi: float):
    """``(d/dx, d/dy)`` of each (H, W) plane in 1/mm, as :func:`normal_derivatives`' 'central'
    (``(p[c+1] - p[c-1]) / 2``, borders reflected, y up), on contiguous planes."""
    scale = np.float32(0.5 * dpi / 25.4)

    def along_x(p):
        d = np.empty_like(p)
        np.subtract(p[:, 2:], p[:, :-2], out=d[:, 1:-1])
        d[:, 0] = p[:, min(1, p.shape[1] - 1)] - p[:, 0]        # reflected: n[-1] = n[0]
        d[:, -1] = p[:, -1] - p[:, max(p.shape[1] - 2, 0)]
        d *= scale
        return d

    def along_y(p):   # y is up while rows go down
        d = np.empty_like(p)
        np.subtract(p[:-2], p[2:], out=d[1:-1])
        d[0] = p[0] - p[min(1, p.shape[0] - 1)]
        d[-1] = p[max(p.shape[0] - 2, 0)] - p[-1]
        d *= scale
        return d

    return [along_x(p) for p in planes], [along_y(p) for p in planes]


def curvature(normals: np.ndarray, dpi: float, *, mask: np.ndarray | None = None,
              method: str = "central", sigma_px: float = 0.0) -> Curvature:
    """Mean, Gaussian and principal curvatures and principal directions of a normal map.

    The shape operator S = I^-1 II is built from the first and second fundamental forms with the
    tangent vectors of eq. 7.6 (see the module docstring); its eigenvalues are the principal
    curvatures and its eigenvectors, expressed in the image plane, the principal directions.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals, x right, y up, z towards the viewer.
    dpi : float
        Sampling density; curvatures come out in 1/mm.
    mask : (H, W) bool, optional
        Output is 0 outside it.
    method : {'central', 'sobel'}
        Derivative operator (central differences or Sobel).
    sigma_px : float
        Optional foreshortening-corrected Gaussian pre-smoothing in pixels (a curvature scale).

    Returns
    -------
    Curvature
        ``mean``, ``gaussian``, ``k1 >= k2`` (1/mm, 1/mm^2) and unit directions ``dir1``, ``dir2``.

    References
    ----------
    Toler-Franklin 2011, §7.2.3, eqs. 7.3-7.7; Toler-Franklin et al., NPAR 2007, §3.2.

    Examples
    --------
    >>> n = np.zeros((8, 8, 3), np.float32); n[..., 2] = 1
    >>> c = curvature(n, dpi=600)
    >>> float(np.abs(c.gaussian).max()), float(np.abs(c.k1).max())
    (0.0, 0.0)
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if sigma_px > 0:
        normals = smooth_normals(normals, sigma_px, mask=mask)
    shape = normals.shape[:2]
    H, K, k1, k2 = (np.empty(shape, np.float32) for _ in range(4))
    dir1, dir2 = np.empty(shape + (2,), np.float32), np.empty(shape + (2,), np.float32)
    # row blocks keep the dozen per-pixel temporaries small on 16-Mpx images
    for rows, block, inner in _blocks(normals):
        dx, dy = normal_derivatives(block, dpi, method=method)
        nz, E, F, G, e, f, g = (a[inner] for a in _fundamental_forms(block, dx, dy))
        inv = 1.0 / nz
        # S = adj(I) II / nz
        s11 = (G * e - F * f) * inv
        s12 = (G * f - F * g) * inv
        s21 = (E * f - F * e) * inv
        s22 = (E * g - F * f) * inv
        h = 0.5 * (s11 + s22)
        k = e * g - f * f
        disc = np.sqrt(np.maximum(h * h - k, 0.0))
        H[rows], K[rows], k1[rows], k2[rows] = h, k, h + disc, h - disc
        dir1[rows] = _eigvec(s11, s12, s21, s22, h + disc)
        # the directions are I-orthogonal, not image-orthogonal; compute the second one the same way
        dir2[rows] = _eigvec(s11, s12, s21, s22, h - disc)
    if not mask.all():
        outside = ~mask
        for arr in (H, K, k1, k2, dir1, dir2):
            arr[outside] = 0.0
    return Curvature(mean=H, gaussian=K, k1=k1, k2=k2, dir1=dir1, dir2=dir2)


_BLOCK_ROWS = 256


def _blocks(normals: np.ndarray, rows: int | None = None):
    """Row blocks with a 2-row halo: yields (output row slice, block with halo, slice of the block's
    own rows). Derivatives inside a block then see their true neighbours; only the image border
    is reflected."""
    h = normals.shape[0]
    rows = rows or _BLOCK_ROWS
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        a0, a1 = max(0, r0 - 2), min(h, r1 + 2)
        yield slice(r0, r1), normals[a0:a1], slice(r0 - a0, r0 - a0 + (r1 - r0))


def _eigvec(s11, s12, s21, s22, k):
    # (S - k) v = 0: take the better-conditioned of the two row-derived solutions
    ax, ay = s12, k - s11
    bx, by = k - s22, s21
    na = ax * ax + ay * ay
    nb = bx * bx + by * by
    use_a = na >= nb
    vx = np.where(use_a, ax, bx)
    vy = np.where(use_a, ay, by)
    n = np.sqrt(np.maximum(na, nb))
    # umbilic (S = k I): every direction is principal; report x
    small = n < 1e-12
    inv = 1.0 / np.where(small, 1.0, n)
    vx = np.where(small, 1.0, vx * inv)
    vy = np.where(small, 0.0, vy * inv)
    return np.stack([vx, vy], axis=-1)
