"""Gaussian smoothing and scale space of RGBN images with the foreshortening correction (§7.2).

A pixel of a normal map covers a surface area proportional to ``1 / nz``: a patch tilted away
from the viewer is foreshortened into fewer pixels. Averaging normals with plain image-space
weights therefore under-represents steep surface; the thesis (§7.2.1) weights every sample by
``1 / nz`` so that the filter averages over surface area rather than over pixels.
"""

from __future__ import annotations

import numpy as np

from common.rgbn._filters import check_mask, check_normals, gaussian_blur

#: Smallest nz used in the 1/nz weight: silhouette pixels (nz -> 0) would otherwise dominate.
NZ_MIN = 0.05


def foreshortening_weights(normals: np.ndarray, mask: np.ndarray | None = None, *,
                           nz_min: float = NZ_MIN) -> np.ndarray:
    """Per-pixel surface-area weight ``1 / max(nz, nz_min)`` (0 outside ``mask``), §7.2.1."""
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if not 0 < nz_min <= 1:
        raise ValueError(f"nz_min must be in (0, 1], got {nz_min}")
    w = 1.0 / np.maximum(normals[..., 2], nz_min)
    return np.where(mask, w, 0.0).astype(np.float32)


def smooth_normals(normals: np.ndarray, sigma_px: float, *, mask: np.ndarray | None = None,
                   foreshortening: bool = True, nz_min: float = NZ_MIN) -> np.ndarray:
    """Gaussian smoothing of a normal map with the 1/nz foreshortening correction.

    Computes ``n'(p) = normalize( sum_q G_sigma(p - q) w(q) n(q) )`` with
    ``w(q) = mask(q) / nz(q)`` (thesis §7.2.1): a normalized convolution, so pixels outside the
    mask neither contribute nor darken the border.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals, x right, y up, z towards the viewer.
    sigma_px : float
        Standard deviation of the Gaussian in pixels (``sigma_mm * dpi / 25.4``). 0 returns a copy.
    mask : (H, W) bool, optional
        Pixels that carry a normal; others are ignored and filled from their neighbours.
    foreshortening : bool
        Weight samples by ``1 / nz`` (True, the thesis' choice) or uniformly.
    nz_min : float
        Lower bound of nz in the weight.

    Returns
    -------
    (H, W, 3) float32
        Unit normals. Inside the mask the smoothed normal; outside it the smoothed extrapolation
        where any mask pixel is within reach, else the input.

    References
    ----------
    Toler-Franklin 2011, §7.2.1 (RGBN smoothing, eq. 7.1); Toler-Franklin et al., "Illustration of
    complex real-world objects using images with normals", NPAR 2007, §3.1.

    Examples
    --------
    >>> n = np.zeros((32, 32, 3), np.float32); n[..., 2] = 1
    >>> bool(np.allclose(smooth_normals(n, 2.0), n))
    True
    """
    normals = check_normals(normals)
    if not np.isfinite(sigma_px) or sigma_px < 0:
        raise ValueError(f"sigma_px must be a finite number >= 0, got {sigma_px}")
    mask = check_mask(mask, normals.shape[:2])
    if sigma_px == 0:
        return normals.copy()
    return next(iter_scale_space(normals, [sigma_px], mask=mask, foreshortening=foreshortening, nz_min=nz_min))


def iter_scale_space(normals: np.ndarray, sigmas_px, *, mask: np.ndarray | None = None,
                     foreshortening: bool = True, nz_min: float = NZ_MIN):
    """Yield :func:`smooth_normals` at each sigma in turn, sharing the weighted stack (§7.2.1).

    Only one level is alive at a time unless the caller keeps it, which bounds the memory of
    many-scale styles on 16-Mpx images.
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    w = foreshortening_weights(normals, mask, nz_min=nz_min) if foreshortening else mask.astype(np.float32)
    stack = np.empty(normals.shape[:2] + (4,), np.float32)
    np.multiply(normals, w[..., None], out=stack[..., :3])
    stack[..., 3] = w
    floor = np.float32(1e-6 * max(float(w.max(initial=0.0)), 1e-12))
    for sigma in sigmas_px:
        if not np.isfinite(sigma) or sigma < 0:
            raise ValueError(f"sigma_px must be a finite number >= 0, got {sigma}")
        if sigma == 0:
            yield normals.copy()
            continue
        blurred = gaussian_blur(stack, float(sigma))
        v = blurred[..., :3]
        norm = np.sqrt(np.einsum("...i,...i->...", v, v))
        # where no mask pixel is in reach the weight sum vanishes: keep the input there
        empty = blurred[..., 3] <= floor
        np.maximum(norm, 1e-12, out=norm)
        out = v / norm[..., None]
        if empty.any():
            out[empty] = normals[empty]
        yield out


def smooth_albedo(albedo: np.ndarray, sigma_px: float, *, mask: np.ndarray | None = None) -> np.ndarray:
    """Masked (normalized-convolution) Gaussian smoothing of an (H, W, C) colour image."""
    albedo = np.asarray(albedo, dtype=np.float32)
    if albedo.ndim == 2:
        albedo = albedo[..., None]
    if albedo.ndim != 3:
        raise ValueError(f"albedo must be (H, W) or (H, W, C), got shape {albedo.shape}")
    if not np.isfinite(sigma_px) or sigma_px < 0:
        raise ValueError(f"sigma_px must be a finite number >= 0, got {sigma_px}")
    mask = check_mask(mask, albedo.shape[:2])
    if sigma_px == 0:
        return albedo.copy()
    w = mask.astype(np.float32)
    blurred = gaussian_blur(np.concatenate([albedo * w[..., None], w[..., None]], axis=2), sigma_px)
    den = blurred[..., -1:]
    out = np.where(den > 1e-6, blurred[..., :-1] / np.maximum(den, 1e-6), albedo)
    return out.astype(np.float32, copy=False)


def scale_space(normals: np.ndarray, sigmas_px, *, mask: np.ndarray | None = None,
                foreshortening: bool = True) -> list[np.ndarray]:
    """Normals smoothed at each of ``sigmas_px`` (a Gaussian scale space, §7.2.1).

    Each level is computed from the input (not cascaded), so level ``i`` is exactly
    :func:`smooth_normals` at ``sigmas_px[i]``; large sigmas run on a downsampled grid, so the
    cost per level is roughly constant.

    Returns
    -------
    list of (H, W, 3) float32
        One unit-normal map per sigma, in the given order.
    """
    sigmas = [float(s) for s in np.atleast_1d(sigmas_px)]
    if not sigmas:
        raise ValueError("sigmas_px must hold at least one sigma")
    return list(iter_scale_space(normals, sigmas, mask=mask, foreshortening=foreshortening))


def smooth_rgbn(image, sigma_mm: float, *, foreshortening: bool = True):
    """Smooth an :class:`~common.rgbn.image.RGBNImage`: albedo and normals at ``sigma_mm``.

    The pixel sigma is ``sigma_mm * dpi / 25.4``. Returns a new RGBNImage (other channels kept).
    """
    from dataclasses import replace

    if not np.isfinite(sigma_mm) or sigma_mm < 0:
        raise ValueError(f"sigma_mm must be a finite number >= 0, got {sigma_mm}")
    sigma_px = sigma_mm / image.pixel_mm
    albedo = smooth_albedo(image.albedo, sigma_px, mask=image.mask)
    normals = None
    if image.normals is not None:
        normals = smooth_normals(image.normals, sigma_px, mask=image.mask, foreshortening=foreshortening)
    return replace(image, albedo=albedo, normals=normals)
