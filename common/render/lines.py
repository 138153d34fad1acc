"""Line styles from RGBN images (§7.3.3-7.3.4): discontinuity lines, suggestive contours
(image space and object space) and ridges and valleys.

Every function returns a line *strength* map in [0, 1] (H, W): 1 = full ink. Directions and
normals follow the Tessera convention (x right, y up, z towards the viewer).
"""

from __future__ import annotations

import cv2
import numpy as np

from common.render._util import check_dpi, smoothstep
from common.rgbn._filters import check_mask, check_normals, gaussian_blur
from common.rgbn.curvature import NZ_MIN, _fundamental_forms, curvature, normal_derivatives
from common.rgbn.smoothing import smooth_normals


def discontinuity_lines(normals: np.ndarray | None = None, *, mask: np.ndarray | None = None,
                        discontinuity: np.ndarray | None = None, threshold_deg: float = 20.0,
                        softness_deg: float = 10.0, outline: bool = True, width_px: float = 1.0,
                        flash_gain: float = 2.5, min_length_px: int = 0) -> np.ndarray:
    """Lines along depth and orientation discontinuities (§7.3.3).

    Sources, combined by maximum:

    * the normal map: the angle between the normals of neighbouring pixels (central differences),
      ``smoothstep(threshold - softness, threshold + softness, angle)`` — creases, steps, cracks;
    * the flash capture's discontinuity map (:attr:`RGBNImage.discontinuity`, Raskar et al. 2004):
      its magnitude times ``flash_gain``, clipped to 1;
    * the fragment outline (the mask boundary) when ``outline``.

    Parameters
    ----------
    normals : (H, W, 3) float, optional
        Unit normals.
    mask : (H, W) bool, optional
        The fragment.
    discontinuity : (H, W, 2) float, optional
        Depth-discontinuity vectors (direction towards the occluder, length = strength).
    threshold_deg, softness_deg : float
        Normal change per pixel (degrees) at which a line is half-strength, and the ramp half-width.
    outline : bool
        Draw the mask boundary.
    width_px : float
        Line width in pixels (lines are thickened by a grey dilation and softened).
    flash_gain : float
        Scale of the flash discontinuity strength before clipping (its values rarely reach 1).
    min_length_px : int
        Line pieces (normal and flash lines at more than half strength, 8-connected) shorter
        than this are dropped: noise in measured normals and flash maps makes many short ones.

    Returns
    -------
    (H, W) float32 in [0, 1]

    References
    ----------
    Toler-Franklin 2011, §7.3.3; R. Raskar, K.-H. Tan, R. Feris, J. Yu, M. Turk, "Non-photorealistic
    camera: depth edge detection and stylized rendering using multi-flash imaging", SIGGRAPH 2004.
    """
    if normals is None and discontinuity is None and mask is None:
        raise ValueError("discontinuity_lines needs normals, a discontinuity map or a mask")
    shape = None
    for arr in (normals, discontinuity, mask):
        if arr is not None:
            shape = np.shape(arr)[:2]
            break
    mask = check_mask(mask, shape)
    lines = np.zeros(shape, np.float32)
    if normals is not None:
        normals = check_normals(normals)
        # angle between p-1 and p+1 halved: the turn per pixel
        dx = cv2.Sobel(normals, cv2.CV_32F, 1, 0, ksize=1, scale=0.5, borderType=cv2.BORDER_REFLECT)
        dy = cv2.Sobel(normals, cv2.CV_32F, 0, 1, ksize=1, scale=0.5, borderType=cv2.BORDER_REFLECT)
        ones = np.ones(3, np.float32)
        q = np.multiply(dx, dx) @ ones             # |dx|^2, one matrix-vector product
        del dx
        np.maximum(q, np.multiply(dy, dy) @ ones, out=q)
        del dy
        inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0
        # the angle grows with the turn: only a pixel whose turn reaches the ramp's foot (a few per
        # cent of them) gets its angle and step made; the others are 0, as the step is below its foot
        low = max(threshold_deg - softness_deg, 0.0)
        foot = np.float32((2.0 * np.sin(np.radians(low) / 2.0)) ** 2 * (1.0 - 1e-4)) if low < 180.0 else np.inf
        at = np.flatnonzero((q > foot) & inner)
        turn = np.sqrt(q.ravel()[at])
        angle = np.degrees(2.0 * np.arcsin(np.clip(turn * 0.5, 0.0, 1.0)))
        lines.ravel()[at] = smoothstep(threshold_deg - softness_deg, threshold_deg + softness_deg, angle)
        del q, at, turn, angle
    if discontinuity is not None:
        d = np.asarray(discontinuity, np.float32)
        if d.shape != tuple(shape) + (2,):
            raise ValueError(f"discontinuity must be {tuple(shape) + (2,)}, got {d.shape}")
        lines = np.maximum(lines, np.clip(np.float32(flash_gain) * np.hypot(d[..., 0], d[..., 1]), 0.0, 1.0))
    if min_length_px > 1 and lines.any():
        keep = prune_short_lines(lines > 0.5, min_length_px)
        keep = cv2.dilate(keep.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        lines = np.where(keep, lines, 0.0).astype(np.float32)
    if outline and not mask.all():
        m = mask.astype(np.uint8)
        edge = (m - cv2.erode(m, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)) > 0
        lines = np.maximum(lines, edge.astype(np.float32))
    return _thicken(lines, width_px)


def suggestive_contours(normals: np.ndarray, *, mask: np.ndarray | None = None, radius_px: float = 4.0,
                        fraction: float = 0.2, depth: float = 0.04, min_length_px: int = 12,
                        sigma_px: float = 1.0, width_px: float = 1.0, fade_deg: float = 0.0) -> np.ndarray:
    """Image-space suggestive contours with length pruning (DeCarlo et al. 2003, §4; §7.3.4).

    Suggestive contours are the valleys of the image lit from the viewer, ``I = n . v = nz``. A
    pixel p is marked when, within a disc of ``radius_px``, fewer than ``fraction`` of the pixels
    are darker than p and the brightest is brighter than p by at least ``depth``. Connected line
    pieces shorter than ``min_length_px`` pixels are pruned (noise in measured normals makes many
    short ones).

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    mask : (H, W) bool, optional
        The fragment; no lines outside it.
    radius_px : float
        Radius of the valley test, pixels (about the line width an artist would use x 2).
    fraction : float
        The paper's ``s``: maximum fraction of darker neighbours.
    depth : float
        The paper's ``d``: minimum intensity depth of the valley (in nz units).
    min_length_px : int
        Pruning: minimum pixel count of a connected line piece.
    sigma_px : float
        Foreshortening-corrected smoothing of the normals first.
    width_px : float
        Drawn line width.
    fade_deg : float
        Lines fade where the surface faces the viewer: full strength where the smoothed normal
        turns at least ``fade_deg`` degrees from the view, falling linearly in ``1 - nz`` to 0
        facing it (a painting seen head-on draws almost none); 0 = no fading.

    Returns
    -------
    (H, W) float32 in [0, 1]

    References
    ----------
    D. DeCarlo, A. Finkelstein, S. Rusinkiewicz, A. Santella, "Suggestive contours for conveying
    shape", SIGGRAPH 2003, §4 (image-space algorithm); Toler-Franklin 2011, §7.3.4.
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if not radius_px >= 1:
        raise ValueError(f"radius_px must be >= 1, got {radius_px}")
    if not 0 < fraction < 1:
        raise ValueError(f"fraction must be in (0, 1), got {fraction}")
    if min_length_px < 0:
        raise ValueError(f"min_length_px must be >= 0, got {min_length_px}")
    n = smooth_normals(normals, sigma_px, mask=mask) if sigma_px > 0 else normals
    intensity = np.ascontiguousarray(n[..., 2])
    r = int(np.ceil(radius_px))
    offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)
               if 0 < dy * dy + dx * dx <= radius_px * radius_px]
    darker = _count_darker(intensity, offsets)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    brightest = cv2.dilate(intensity, disc, borderType=cv2.BORDER_REFLECT)
    line = (darker < fraction * len(offsets)) & (brightest - intensity > depth)
    inner = cv2.erode(mask.astype(np.uint8), disc, borderType=cv2.BORDER_REPLICATE) > 0
    line &= inner
    line = prune_short_lines(line, min_length_px)
    return _thicken(line.astype(np.float32), width_px) * facing_fade(n, fade_deg, width_px)


def suggestive_contours_object(normals: np.ndarray, dpi: float, *, mask: np.ndarray | None = None,
                               sigma_px: float = 2.0, threshold: float = 0.05,
                               min_length_px: int = 12, width_px: float = 1.0,
                               fade_deg: float = 0.0) -> np.ndarray:
    """Object-space suggestive contours from curvature derivatives (DeCarlo et al. 2003, §3).

    With the view ``v = (0, 0, 1)`` projected into the tangent plane, ``w ∝ -(nx, ny)`` in the
    image, the radial curvature is ``kr = II(w, w) / I(w, w)`` (from the fundamental forms of
    eq. 7.6). Suggestive contours are the zeros of ``kr`` where its derivative along w is
    positive, ``D_w kr > threshold * |grad kr|`` (a relative threshold makes the test independent
    of the scale of the relief). Line pieces shorter than ``min_length_px`` are pruned.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    dpi : float
        Sampling density (curvature in 1/mm).
    mask : (H, W) bool, optional
        The fragment.
    sigma_px : float
        Foreshortening-corrected smoothing (derivatives of curvature need it).
    threshold : float
        Minimum cosine between w and grad kr at a zero crossing, in [0, 1).
    min_length_px : int
        Pruning length.
    width_px : float
        Drawn line width.
    fade_deg : float
        Fading where the surface faces the viewer, as in :func:`suggestive_contours`.

    Returns
    -------
    (H, W) float32 in [0, 1]

    References
    ----------
    DeCarlo et al. 2003, §3 (definition: kr = 0, D_w kr > 0); Toler-Franklin 2011, §7.3.4.
    """
    normals = check_normals(normals)
    dpi = check_dpi(dpi)
    mask = check_mask(mask, normals.shape[:2])
    if not 0 <= threshold < 1:
        raise ValueError(f"threshold must be in [0, 1), got {threshold}")
    n = smooth_normals(normals, sigma_px, mask=mask) if sigma_px > 0 else normals
    dx, dy = normal_derivatives(n, dpi)
    nz, E, F, G, e, f, g = _fundamental_forms(n, dx, dy)
    wx, wy = -n[..., 0], -n[..., 1]
    num = e * wx * wx + 2.0 * f * wx * wy + g * wy * wy
    den = E * wx * wx + 2.0 * F * wx * wy + G * wy * wy
    # kr = nz * II_s(w, w) / I_s(w, w) (scaled forms, see common.rgbn.curvature)
    kr = np.where(den > 1e-10, nz * num / np.maximum(den, 1e-10), 0.0).astype(np.float32)
    gx = cv2.Sobel(kr, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    gy = -cv2.Sobel(kr, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
    wn = np.sqrt(wx * wx + wy * wy)
    gn = np.sqrt(gx * gx + gy * gy)
    dw = (gx * wx + gy * wy) / np.maximum(wn * gn, 1e-12)
    crossing = _zero_crossings(kr)
    line = crossing & (dw > threshold) & (wn > 1e-3) & (n[..., 2] > NZ_MIN)
    disc = np.ones((3, 3), np.uint8)
    line &= cv2.erode(mask.astype(np.uint8), disc, iterations=max(1, int(np.ceil(2 * sigma_px))),
                      borderType=cv2.BORDER_REPLICATE) > 0
    line = prune_short_lines(line, min_length_px)
    return _thicken(line.astype(np.float32), width_px) * facing_fade(n, fade_deg, width_px)


def facing_fade(normals: np.ndarray, fade_deg: float, width_px: float = 1.0) -> np.ndarray:
    """Line strength factor: 1 where the normal turns >= ``fade_deg`` from the view (0, 0, 1),
    linear in ``1 - nz`` down to 0 facing the viewer; all ones when ``fade_deg`` is 0."""
    if not 0 <= fade_deg < 90:
        raise ValueError(f"fade_deg must be in [0, 90), got {fade_deg}")
    if fade_deg == 0:
        return np.ones(normals.shape[:2], np.float32)
    f = np.clip((1.0 - normals[..., 2]) / np.float32(1.0 - np.cos(np.radians(fade_deg))), 0.0, 1.0)
    # the lines were thickened: spread the factor as far (a line keeps one strength across)
    k = 2 * int(np.ceil(max(width_px, 1.0))) + 1
    return cv2.dilate(f.astype(np.float32), np.ones((k, k), np.uint8))


def ridges_valleys(normals: np.ndarray, dpi: float, *, mask: np.ndarray | None = None, sigma_px: float = 1.5,
                   threshold: float | None = None, percentile: float = 90.0, min_length_px: int = 8,
                   width_px: float = 1.0, return_threshold: bool = False):
    """Ridge and valley lines: local extrema of principal curvature along its direction (§7.3.4).

    A ridge pixel has ``k1 > threshold``, a dominant curvature (``k1 - k2 > k1 / 4``: no lines at
    umbilics such as a sphere) and is a maximum of k1 along its principal direction
    ``dir1`` (non-maximum suppression at the two neighbours along ``±dir1``, as in Canny's edge
    thinning); a valley pixel has ``k2 < -threshold`` and is a minimum of k2 along ``dir2``.
    Ridges are convex crests (towards the viewer), valleys concave troughs (incisions, string
    impressions).

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    dpi : float
        Sampling density (curvature in 1/mm).
    mask : (H, W) bool, optional
        The fragment.
    sigma_px : float
        Curvature scale: foreshortening-corrected smoothing in pixels.
    threshold : float, optional
        Minimum |principal curvature| in 1/mm; default: the ``percentile`` of |k| on the fragment.
    percentile : float
        Used when ``threshold`` is None.
    min_length_px : int
        Pruning length in pixels.
    width_px : float
        Drawn line width.

    Returns
    -------
    ridges, valleys : (H, W) float32 in [0, 1]
    threshold : float
        Only with ``return_threshold``: the threshold used (1/mm).

    References
    ----------
    Y. Ohtake, A. Belyaev, H.-P. Seidel, "Ridge-valley lines on meshes via implicit surface
    fitting", SIGGRAPH 2004; Toler-Franklin 2011, §7.3.4.
    """
    normals = check_normals(normals)
    dpi = check_dpi(dpi)
    mask = check_mask(mask, normals.shape[:2])
    if not 0 < percentile < 100:
        raise ValueError(f"percentile must be in (0, 100), got {percentile}")
    c = curvature(normals, dpi, mask=mask, sigma_px=sigma_px)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=max(1, int(np.ceil(sigma_px))),
                      borderType=cv2.BORDER_REPLICATE) > 0
    if threshold is None:
        vals = np.concatenate([c.k1[inner & (c.k1 > 0)], -c.k2[inner & (c.k2 < 0)]])
        threshold = float(np.percentile(vals, percentile)) if vals.size else np.inf
    if threshold < 0:
        raise ValueError(f"threshold must be >= 0, got {threshold}")
    # near silhouettes (small nz) curvature from normals is unreliable; at umbilics (k1 = k2,
    # e.g. a sphere) the lines of curvature are undefined: require a dominant curvature
    inner &= normals[..., 2] > 0.25
    aniso = c.k1 - c.k2
    ridge = (c.k1 > threshold) & (aniso > 0.25 * np.abs(c.k1)) & _extremum_along(c.k1, c.dir1, maximum=True) & inner
    valley = (c.k2 < -threshold) & (aniso > 0.25 * np.abs(c.k2)) & _extremum_along(c.k2, c.dir2, maximum=False) \
        & inner
    ridge = prune_short_lines(ridge, min_length_px)
    valley = prune_short_lines(valley, min_length_px)
    out = _thicken(ridge.astype(np.float32), width_px), _thicken(valley.astype(np.float32), width_px)
    return out + (float(threshold),) if return_threshold else out


def prune_short_lines(lines: np.ndarray, min_length_px: int) -> np.ndarray:
    """Remove 8-connected pieces of a binary line map with fewer than ``min_length_px`` pixels."""
    lines = np.asarray(lines, bool)
    if min_length_px <= 1 or not lines.any():
        return lines
    count, labels, stats, _ = cv2.connectedComponentsWithStats(lines.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_length_px
    keep[0] = False
    return keep[labels]


def _count_darker(intensity: np.ndarray, offsets) -> np.ndarray:
    """Per pixel, how many of the neighbours at ``offsets`` are darker (the heavy loop)."""
    h, w = intensity.shape
    r = max(max(abs(dy), abs(dx)) for dy, dx in offsets)
    pad = np.pad(intensity, r, mode="reflect")
    count = np.zeros((h, w), np.uint16)
    for dy, dx in offsets:
        count += pad[r + dy:r + dy + h, r + dx:r + dx + w] < intensity
    return count


def _zero_crossings(values: np.ndarray) -> np.ndarray:
    """Pixels next to a sign change (right or down neighbour) that are the closer one to zero."""
    z = np.zeros(values.shape, bool)
    a, b = values[:, :-1], values[:, 1:]
    cross = (a * b) < 0
    z[:, :-1] |= cross & (np.abs(a) <= np.abs(b))
    z[:, 1:] |= cross & (np.abs(b) < np.abs(a))
    a, b = values[:-1], values[1:]
    cross = (a * b) < 0
    z[:-1] |= cross & (np.abs(a) <= np.abs(b))
    z[1:] |= cross & (np.abs(b) < np.abs(a))
    return z


def _extremum_along(values: np.ndarray, direction: np.ndarray, *, maximum: bool) -> np.ndarray:
    """Non-maximum suppression along a per-pixel direction quantized to 4 neighbour axes."""
    # direction is (x right, y up); rows go down
    angle = np.mod(np.degrees(np.arctan2(direction[..., 1], direction[..., 0])), 180.0)
    sector = (np.floor((angle + 22.5) / 45.0).astype(np.int8)) % 4
    pad = np.pad(values, 1, mode="edge")
    h, w = values.shape
    result = np.zeros(values.shape, bool)
    # sector: 0 -> x axis, 1 -> 45 deg (up-right), 2 -> y axis, 3 -> 135 deg (up-left)
    for s, (dr, dc) in enumerate(((0, 1), (-1, 1), (-1, 0), (-1, -1))):
        fwd = pad[1 + dr:1 + dr + h, 1 + dc:1 + dc + w]
        bwd = pad[1 - dr:1 - dr + h, 1 - dc:1 - dc + w]
        ok = (values >= fwd) & (values >= bwd) if maximum else (values <= fwd) & (values <= bwd)
        result |= (sector == s) & ok
    return result


def _thicken(lines: np.ndarray, width_px: float) -> np.ndarray:
    """Binary or soft line pixels drawn as anti-aliased strokes about ``width_px`` wide: dilated to
    the width, then softened by a Gaussian of 0.3 x width (>= 0.5 px) and renormalised so a
    stroke's centre keeps full strength (its flanks are partial coverage, not jagged steps)."""
    if width_px < 0:
        raise ValueError(f"width_px must be >= 0, got {width_px}")
    lines = np.asarray(lines, np.float32)
    if width_px == 0 or not lines.any():
        return np.clip(lines, 0.0, 1.0)
    if width_px > 1.0:
        k = int(np.ceil(width_px))
        lines = cv2.dilate(lines, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    sigma = max(0.3 * width_px, 0.5)
    soft = gaussian_blur(lines, sigma)
    # a one-pixel line blurred at sigma keeps 1 / (sqrt(2 pi) sigma) of its peak: give it back
    peak = 1.0 / min(1.0, max(width_px, 1.0) / (np.sqrt(2 * np.pi) * sigma))
    # the stroke's own pixels keep their strength; the blur adds the partial coverage around them
    return np.clip(np.maximum(soft * np.float32(peak), lines), 0.0, 1.0)
