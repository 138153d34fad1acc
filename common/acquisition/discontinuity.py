"""Depth discontinuities from flash images (multi-flash imaging; thesis §3.2).

A flash beside the camera casts a thin shadow behind every depth edge, on the side away from
the flash. Raskar et al. (2004) find the edges from several flashes: divide each image by the
per-pixel maximum over all images (the *ratio image* cancels albedo and shading: ≈ 1 where the
pixel is lit, ≈ 0 in that flash's shadow), then walk each ratio image along its epipolar lines —
away from the flash's image-space position — and mark the *negative steps*, where a lit pixel
meets the shadow. The occluding (nearer) side of the edge is the lit side, towards the flash.

With distant flashes and the orthographic camera of the solver, every epipolar line of light
*i* runs parallel to the light's image-plane direction ``u_i = (l_x, l_y) / |(l_x, l_y)|``
(x right, y up), so the walk becomes a directional derivative of the ratio image along
``−u_i``, followed by non-maximum suppression along the same line.

The result is a directional map (H, W, 2): at an edge pixel the unit vector (x right, y up)
towards the occluding side, scaled by the edge strength in [0, 1] (the ratio drop across the
step, 1 for lit → black); zero elsewhere. It is stored as ``RGBNImage.discontinuity``.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np


def _ratio_step_response(ratio, t_col, t_row, sigma):
    """Directional derivative of the smoothed ratio image along (t_col, t_row) per pixel."""
    r = cv2.GaussianBlur(ratio, (0, 0), sigma) if sigma > 0 else ratio
    gx = cv2.Sobel(r, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE) / 8.0
    gy = cv2.Sobel(r, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE) / 8.0
    return gx * t_col + gy * t_row


@functools.lru_cache(maxsize=8)
def _unit_step_peak(sigma: float) -> float:
    """Peak response of the derivative chain to a unit step (normalises strength to [0, 1])."""
    step = np.ones((9, 64), np.float32)
    step[:, 32:] = 0.0
    return float(-_ratio_step_response(step, 1.0, 0.0, sigma)[4].min())


def depth_discontinuities(images, directions, *, mask=None, sigma: float = 1.0, min_step: float = 0.3,
                          min_tilt: float = 0.1, dark_fraction: float = 0.05) -> np.ndarray:
    """Directional depth-discontinuity map from flash images (Raskar et al. 2004).

    Parameters
    ----------
    images : (N, H, W) or (N, H, W, 3) float array
        Linear flash images of one view (any intensity scale).
    directions : (N, 3) array
        Light directions (x right, y up, z towards the camera).
    mask : (H, W) bool, optional
        Where to report edges (default everywhere the max composite is not dark).
    sigma : float ≥ 0
        Gaussian smoothing of the ratio images in pixels before differentiation.
    min_step : float in (0, 1)
        Smallest ratio drop (lit → shadow) that counts as an edge.
    min_tilt : float in [0, 1)
        Flashes with ``|(l_x, l_y)| < min_tilt`` (almost on the view axis) cast no usable
        shadow and are skipped.
    dark_fraction : float
        Pixels whose max composite is below this fraction of its 99th percentile are
        background/never lit; no ratio is formed there.

    Returns
    -------
    (H, W, 2) float32
        Unit direction (x right, y up) towards the occluding side × strength in [0, 1];
        zero where there is no edge.

    Notes
    -----
    The paper walks epipolar rays from each flash's epipole; with distant flashes those rays
    are parallel, so the walk is a directional derivative (here: Sobel on the smoothed ratio
    image) with non-maximum suppression along the ray. Each flash votes its image-plane
    direction ``u_i`` (towards the flash = towards the occluder) weighted by its step; the map
    keeps the strongest step and the direction of the vote sum, pooled over a Gaussian
    window of 1.5 px.

    References
    ----------
    R. Raskar, K.-H. Tan, R. Feris, J. Yu, M. Turk, "Non-photorealistic camera: depth edge
    detection and stylized rendering using multi-flash imaging", ACM SIGGRAPH 2004, §3
    (ratio images, negative transitions along epipolar lines). Thesis §3.2.

    Examples
    --------
    >>> import numpy as np
    >>> lit = np.ones((4, 32, 32), np.float32)
    >>> L = np.array([[1, 0, 1], [-1, 0, 1], [0, 1, 1], [0, -1, 1]], float)
    >>> lit[0, :, 10:14] = 0.0  # the flash on the right: shadow left of an edge at column 14
    >>> d = depth_discontinuities(lit, L)
    >>> np.round(d[16, 12:16, 0], 2).tolist()  # x component: occluder to the right, strength 1
    [0.0, 0.0, 1.0, 0.0]
    """
    imgs = np.asarray(images)
    if imgs.ndim == 4:
        if imgs.shape[3] != 3:
            raise ValueError(f"images must be (N, H, W) or (N, H, W, 3), got {imgs.shape}")
        imgs = imgs.astype(np.float32) @ np.array([0.2989, 0.5870, 0.1140], np.float32)
    if imgs.ndim != 3:
        raise ValueError(f"images must be (N, H, W) or (N, H, W, 3), got {imgs.shape}")
    imgs = imgs.astype(np.float32, copy=False)
    n, h, w = imgs.shape
    d = np.asarray(directions, dtype=np.float64)
    if d.shape != (n, 3) or not np.all(np.isfinite(d)):
        raise ValueError(f"directions must be finite ({n}, 3), got {d.shape}")
    if sigma < 0:
        raise ValueError(f"sigma must be >= 0, got {sigma}")
    if not 0.0 < min_step < 1.0:
        raise ValueError(f"min_step must be in (0, 1), got {min_step}")
    if not 0.0 <= min_tilt < 1.0:
        raise ValueError(f"min_tilt must be in [0, 1), got {min_tilt}")
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != (h, w):
            raise ValueError(f"mask must be {(h, w)}, got {mask.shape}")
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)

    composite = imgs.max(axis=0)
    lit_level = float(np.percentile(composite, 99)) if composite.size else 0.0
    lit = composite > dark_fraction * max(lit_level, 1e-12)
    region = lit if mask is None else lit & mask
    # erode the valid region a little so that the region's own border is no 'edge'
    inside = cv2.erode(lit.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    peak = _unit_step_peak(float(sigma))

    strength = np.zeros((h, w), np.float32)
    votes = np.zeros((h, w, 2), np.float32)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    safe = np.where(lit, composite, 1.0)
    for i in range(n):
        tilt = float(np.hypot(d[i, 0], d[i, 1]))
        if tilt < min_tilt:
            continue
        ux, uy = float(d[i, 0]) / tilt, float(d[i, 1]) / tilt  # towards the flash, x right / y up
        t_col, t_row = -ux, uy  # walking away from the flash, in (column, row) steps
        ratio = np.where(lit, imgs[i] / safe, 1.0).astype(np.float32)
        drop = -_ratio_step_response(ratio, t_col, t_row, sigma) / peak
        # non-maximum suppression along the epipolar line (bilinear neighbours ±1 px)
        ahead = cv2.remap(drop, cols + t_col, rows + t_row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        behind = cv2.remap(drop, cols - t_col, rows - t_row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        edge = (drop >= min_step) & (drop >= ahead) & (drop > behind) & inside
        s = np.where(edge, np.clip(drop, 0.0, 1.0), 0.0).astype(np.float32)
        strength = np.maximum(strength, s)
        votes[..., 0] += s * ux
        votes[..., 1] += s * uy
    # neighbouring edge pixels often hold the votes of different flashes (each flash's step is
    # thinned to one pixel): pool the votes over a small window before taking the direction
    votes = cv2.GaussianBlur(votes, (0, 0), 1.5)
    norm = np.linalg.norm(votes, axis=2)
    keep = (strength > 0) & (norm > 1e-6) & region
    out = np.zeros((h, w, 2), np.float32)
    out[keep] = votes[keep] / norm[keep, None] * strength[keep, None]
    return out
