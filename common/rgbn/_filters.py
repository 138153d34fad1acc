"""Shared low-level filters for RGBN processing (private)."""

from __future__ import annotations

import cv2
import numpy as np

# Above this sigma (px) a Gaussian is applied on a downsampled copy: the kernel cost then stays
# constant per pixel, which keeps 8-scale exaggerated shading within its budget (§7.3).
_DIRECT_SIGMA = 6.0


def gaussian_blur(values: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur of an (H, W) or (H, W, C) float32 array, reflecting at the border.

    Large sigmas are applied on a power-of-two downsampled copy (area averaging) and bilinearly
    upsampled; the variances of the box and tent kernels are subtracted so the effective width
    stays ``sigma_px``.
    """
    values = np.ascontiguousarray(values, dtype=np.float32)
    if sigma_px <= 0:
        return values.copy()
    h, w = values.shape[:2]
    factor = decimation_factor(sigma_px, values.shape)
    if factor == 1:
        return _blur_direct(values, sigma_px)
    small_shape = (max(1, round(w / factor)), max(1, round(h / factor)))
    small = cv2.resize(values, small_shape, interpolation=cv2.INTER_AREA)
    if values.ndim == 3 and small.ndim == 2:
        small = small[..., None]
    small = _blur_direct(small, decimated_sigma(sigma_px, factor))
    out = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    if values.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out


def decimation_factor(sigma_px: float, shape) -> int:
    """The power-of-two step of the downsampled copy :func:`gaussian_blur` applies ``sigma_px`` on
    for an image of ``shape`` (1: at full resolution)."""
    h, w = shape[:2]
    factor = 1
    while sigma_px / (factor * 2) >= _DIRECT_SIGMA / 2 and min(h, w) // (factor * 2) >= 8:
        factor *= 2
    return factor


def upsampled_rows(small: np.ndarray, shape, rows) -> np.ndarray:
    """Rows ``r0:r1`` of ``cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR)`` (``shape`` =
    (H, W), a whole multiple ``f`` of ``small``'s) without making the whole: the small rows those
    rows interpolate from, with one more on each side (so no border is replicated inside),
    resized to ``f`` times their height, which puts every output row at the same source
    position as the whole resize does; the same values."""
    h, w = shape[:2]
    hh = small.shape[0]
    f = h // hh
    r0, r1 = int(rows[0]), int(rows[1])
    i0 = max(0, (r0 - f) // f)                     # a small row below the first one read ...
    i1 = min(hh, (r1 + f) // f + 1)                # ... and one past the last
    part = cv2.resize(np.ascontiguousarray(small[i0:i1]), (w, (i1 - i0) * f), interpolation=cv2.INTER_LINEAR)
    if small.ndim == 3 and part.ndim == 2:
        part = part[..., None]
    return part[r0 - i0 * f:r1 - i0 * f]


def decimated_sigma(sigma_px: float, factor: int) -> float:
    """The sigma, in steps of a grid ``factor`` times coarser, of the Gaussian that, applied to the
    grid's ``factor`` x ``factor`` area means and followed by bilinear interpolation back, makes a
    Gaussian of ``sigma_px`` (pixels): the variances of the box, ``(f^2 - 1) / 12``, and of the
    interpolation's tent, ``f^2 / 6``, are subtracted (at least half a grid step is kept)."""
    var = sigma_px ** 2 - (factor ** 2 - 1) / 12.0 - factor ** 2 / 6.0
    return max(np.sqrt(max(var, 0.25)) / factor, 0.5)


def blurs_directly(sigma_px: float, shape) -> bool:
    """Whether :func:`gaussian_blur` applies ``sigma_px`` at full resolution on an image of
    ``shape`` (else on a downsampled copy)."""
    h, w = shape[:2]
    return not (sigma_px / 2 >= _DIRECT_SIGMA / 2 and min(h, w) // 2 >= 8)


def gaussian_reach(sigma_px: float) -> int:
    """Rows (or columns) a full-resolution :func:`gaussian_blur` reads on each side: OpenCV's
    float Gaussian kernel has ``2 * round(4 sigma) + 1`` taps, so 4 sigma, plus one for rounding."""
    return int(np.ceil(4.0 * sigma_px)) + 1


def _blur_direct(values: np.ndarray, sigma_px: float) -> np.ndarray:
    # OpenCV filters at most 4 channels in one call efficiently for all builds; split larger stacks.
    if values.ndim == 3 and values.shape[2] > 4:
        return np.concatenate([_blur_direct(values[..., i:i + 4], sigma_px)
                               for i in range(0, values.shape[2], 4)], axis=2)
    out = cv2.GaussianBlur(values, (0, 0), sigmaX=float(sigma_px), sigmaY=float(sigma_px),
                           borderType=cv2.BORDER_REFLECT)
    if values.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out


def normalized_blur(values: np.ndarray, weight: np.ndarray, sigma_px: float, *,
                    ksize: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Gaussian mean of ``values`` around each pixel: ``G * (values · weight) / G * weight``.

    A normalised convolution (Knutsson & Westin 1993, "Normalized and differential convolution"):
    pixels of zero weight (outside a fragment, or not yet known) neither count nor pull the mean
    towards their values, so the edge of a region keeps the region's colour. ``values`` is (H, W) or
    (H, W, C), ``weight`` (H, W); ``ksize`` as OpenCV's, (0, 0) = from ``sigma_px``.

    Returns ``(mean, G * weight)``: the mean is ``num / max(den, 1e-6)``, so it tends to 0 where no
    weighted pixel is within reach (callers that need to tell use the second array).

    >>> v = np.zeros((9, 9, 3), np.float32); v[:, :5] = 0.5; w = np.zeros((9, 9), np.float32); w[:, :5] = 1
    >>> float(normalized_blur(v, w, 1.5)[0][4, 4, 0])   # the region's edge keeps its colour
    0.5
    """
    w = np.asarray(weight)
    wide = values.ndim == 3
    num = cv2.GaussianBlur(values * (w[..., None] if wide else w), ksize, sigma_px)
    den = cv2.GaussianBlur(w, ksize, sigma_px)
    floor = np.maximum(den, 1e-6)
    return num / (floor[..., None] if wide else floor), den


def normalize_vectors(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Unit vectors along the last axis (zero vectors stay zero)."""
    n = np.sqrt(np.einsum("...i,...i->...", v, v))
    return v / np.maximum(n, eps)[..., None]


def check_normals(normals, name: str = "normals") -> np.ndarray:
    """Validate an (H, W, 3) normal map and return it as float32."""
    arr = np.asarray(normals)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"{name} must be an (H, W, 3) array of unit normals, got shape {arr.shape}")
    return arr.astype(np.float32, copy=False)


def check_mask(mask, shape, name: str = "mask") -> np.ndarray:
    """Validate an optional (H, W) mask; None means every pixel."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask, dtype=bool)
    if m.shape != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {m.shape}")
    return m
