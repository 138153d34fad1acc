"""Pictures for the station's pages: pre-scan outline, two fragments joined at a proposed pose.

Pure numpy/OpenCV helpers; arrays follow the RGBN conventions of :mod:`common.rgbn.image`
(``[row, col]``, row 0 at the top). A *pose* ``(angle_deg, tx_mm, ty_mm)`` maps a point ``p`` of
fragment B's frame (mm, x right = col × pixel_mm, y down = row × pixel_mm) into fragment A's
frame by ``R(angle) @ p + t`` with ``R = [[cos, -sin], [sin, cos]]`` — the convention of
``Wall.fragments[i].pose`` in :mod:`common.synth`, with A's frame in the role of the wall.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# outline colours (RGB) that stay distinct on fresco colours and for the common colour deficiencies
COLOUR_A = (0, 158, 255)
COLOUR_B = (255, 140, 0)
COLOUR_DETECTED = (0, 230, 64)


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Encode linear RGB in [0, 1] as 8-bit sRGB for display (IEC 61966-2-1 transfer curve).

    Parameters
    ----------
    rgb : (H, W, 3) or (H, W) float array
        Linear reflectance; values outside [0, 1] are clipped.

    Returns
    -------
    (H, W, 3) or (H, W) uint8
    """
    x = np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0)
    y = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(y * 255.0).astype(np.uint8)


def to_rgb8(image: np.ndarray) -> np.ndarray:
    """Any scan-like array (uint8, uint16, or float in [0, 1], grey or RGB) as (H, W, 3) uint8.

    Integer scans are shown as they are (a scanner's output is already display-encoded); floats
    are taken as linear reflectance and sRGB-encoded.
    """
    a = np.asarray(image)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"image must be (H, W), (H, W, 3) or (H, W, 4), got {a.shape}")
    a = a[..., :3]
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if a.dtype == np.uint16:
        return (a >> 8).astype(np.uint8)
    if np.issubdtype(a.dtype, np.floating):
        return linear_to_srgb8(a)
    raise ValueError(f"image dtype {a.dtype} not supported (uint8, uint16 or float)")


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) uint8 RGB (or (H, W) grey) image."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8, got {a.dtype}")
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", a)
    if not ok:
        raise ValueError("could not encode the image as PNG")
    return buf.tobytes()


def fit_within(rgb: np.ndarray, max_side_px: int) -> np.ndarray:
    """Downscale (area averaging) so that neither side exceeds ``max_side_px``; never upscale."""
    if max_side_px < 1:
        raise ValueError(f"max_side_px must be >= 1, got {max_side_px}")
    h, w = rgb.shape[:2]
    s = max_side_px / max(h, w)
    if s >= 1.0:
        return rgb
    size = (max(1, int(round(w * s))), max(1, int(round(h * s))))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def outline_detected(prescan: np.ndarray, mask: np.ndarray | None = None, *,
                     bbox: tuple[int, int, int, int] | None = None,
                     colour: tuple[int, int, int] = COLOUR_DETECTED, thickness_px: int = 2) -> np.ndarray:
    """The pre-scan with the detected fragment outlined, for the operator (§3.3, pre-scan).

    Parameters
    ----------
    prescan : (H, W[, 3]) array
        Low-dpi scan of the platen.
    mask : (H, W) bool, optional
        Pixels of the detected fragment(s); every connected region is outlined.
    bbox : (row0, col0, row1, col1), optional
        Region that the full-dpi scan will cover (pixels, end exclusive); drawn dashed-free as a
        thin rectangle.
    colour : RGB triple
    thickness_px : int

    Returns
    -------
    (H, W, 3) uint8
    """
    out = to_rgb8(prescan).copy()
    h, w = out.shape[:2]
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (h, w):
            raise ValueError(f"mask must be {(h, w)} like the pre-scan, got {m.shape}")
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, colour, thickness_px, lineType=cv2.LINE_AA)
    if bbox is not None:
        r0, c0, r1, c1 = (int(round(v)) for v in bbox)
        if not (r1 > r0 and c1 > c0):
            raise ValueError(f"bbox must be (row0, col0, row1, col1) with row1 > row0 and col1 > col0, got {bbox}")
        cv2.rectangle(out, (c0, r0), (c1 - 1, r1 - 1), colour, 1)
    return out


def outline_mm(mask: np.ndarray, pixel_mm: float, *, tolerance_mm: float = 0.5) -> list:
    """A piece's outline (its largest region's outer boundary) as a polygon in its frame, mm (``x = col ×
    pixel_mm``), simplified to within ``tolerance_mm`` (Douglas–Peucker, ``cv2.approxPolyDP``): what the
    reconstruction page draws dashed round a next join's piece where it would go. [] for an empty mask.

    >>> m = np.zeros((20, 30), bool); m[5:15, 10:20] = True
    >>> outline_mm(m, 0.5)
    [[5.0, 2.5], [5.0, 7.0], [9.5, 7.0], [9.5, 2.5]]
    """
    contours, _ = cv2.findContours(np.ascontiguousarray(mask, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return []
    poly = cv2.approxPolyDP(max(contours, key=cv2.contourArea), tolerance_mm / pixel_mm, True)[:, 0, :]
    return [[round(float(x) * pixel_mm, 3), round(float(y) * pixel_mm, 3)] for x, y in poly]


def relative_pose(pose_a, pose_b) -> tuple[float, float, float]:
    """Pose of fragment B in fragment A's frame from both fragments' poses in a common frame.

    With ``wall = R(θa) p_a + t_a = R(θb) p_b + t_b``:
    ``p_a = R(θb − θa) p_b + R(θa)ᵀ (t_b − t_a)``.
    """
    ta, xa, ya = (float(v) for v in pose_a)
    tb, xb, yb = (float(v) for v in pose_b)
    c, s = math.cos(math.radians(ta)), math.sin(math.radians(ta))
    dx, dy = xb - xa, yb - ya
    return (tb - ta, c * dx + s * dy, -s * dx + c * dy)


def _mask_corners(mask: np.ndarray) -> np.ndarray:
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    r0, r1, c0, c1 = rows[0], rows[-1], cols[0], cols[-1]
    return np.array([[c0, r0], [c1, r0], [c0, r1], [c1, r1]], dtype=np.float64)


def _pose_matrix(pose, scale: float) -> np.ndarray:
    angle, tx, ty = (float(v) for v in pose)
    c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    return np.array([[c, -s, tx * scale], [s, c, ty * scale]], dtype=np.float64)


def join_at_pose(rgb_a: np.ndarray, mask_a: np.ndarray, rgb_b: np.ndarray, mask_b: np.ndarray,
                 pose, pixel_mm: float, *, pixel_mm_b: float | None = None, max_side_px: int = 1024, margin_px: int = 8,
                 outline: bool = True, background: tuple[int, int, int] = (40, 40, 40)) -> np.ndarray:
    """The two fragments joined at a proposed pose, in one picture, for the conservator.

    Fragment B is warped into A's frame by ``pose`` (see the module docstring); the picture is
    the bounding box of both, scaled down so that its longer side is at most ``max_side_px``.
    Where the two overlap they are blended half and half, so an overlap (a bad proposal) shows.

    Parameters
    ----------
    rgb_a, rgb_b : (H, W, 3) arrays
        Pictures of each fragment in its own frame (colour or a relief rendering).
    mask_a, mask_b : (H, W) bool
        Fragment pixels.
    pose : (angle_deg, tx_mm, ty_mm)
        B's frame → A's frame.
    pixel_mm : float
        Pixel size of A's picture (25.4 / dpi), and of B's unless ``pixel_mm_b`` is given.
    pixel_mm_b : float, optional
        Pixel size of B's picture when it was scanned at another dpi.
    max_side_px : int
    margin_px : int
    outline : bool
        Draw each fragment's outline (A blue, B orange).
    background : RGB triple

    Returns
    -------
    (h, w, 3) uint8
    """
    a, b = to_rgb8(rgb_a), to_rgb8(rgb_b)
    ma, mb = np.asarray(mask_a, dtype=bool), np.asarray(mask_b, dtype=bool)
    if ma.shape != a.shape[:2]:
        raise ValueError(f"mask_a must be {a.shape[:2]}, got {ma.shape}")
    if mb.shape != b.shape[:2]:
        raise ValueError(f"mask_b must be {b.shape[:2]}, got {mb.shape}")
    if not (np.isfinite(pixel_mm) and pixel_mm > 0):
        raise ValueError(f"pixel_mm must be a positive number, got {pixel_mm}")
    pixel_mm_b = pixel_mm if pixel_mm_b is None else float(pixel_mm_b)
    if not (np.isfinite(pixel_mm_b) and pixel_mm_b > 0):
        raise ValueError(f"pixel_mm_b must be a positive number, got {pixel_mm_b}")
    if len(pose) != 3 or not all(np.isfinite(float(v)) for v in pose):
        raise ValueError(f"pose must be finite (angle_deg, tx_mm, ty_mm), got {pose!r}")
    if max_side_px < 16:
        raise ValueError(f"max_side_px must be >= 16, got {max_side_px}")

    if not ma.any() or not mb.any():
        raise ValueError("mask_a and mask_b must each mark at least one fragment pixel")
    mab = _pose_matrix(pose, 1.0 / pixel_mm)  # rotation, translation in A pixels
    mab[:, :2] *= pixel_mm_b / pixel_mm        # B pixels (col, row) -> A pixels
    # the picture spans both fragments (their mask boxes), not their whole scan frames
    box_a = _mask_corners(ma)
    box_b = _mask_corners(mb) @ mab[:, :2].T + mab[:, 2]
    lo = np.minimum(box_a.min(axis=0), box_b.min(axis=0))
    hi = np.maximum(box_a.max(axis=0), box_b.max(axis=0))
    span = hi - lo + 1
    scale = min(1.0, (max_side_px - 2 * margin_px) / float(span.max()))
    size = (int(math.ceil(span[0] * scale)) + 2 * margin_px, int(math.ceil(span[1] * scale)) + 2 * margin_px)
    offset = -lo * scale + margin_px
    to_canvas_a = np.array([[scale, 0, offset[0]], [0, scale, offset[1]]])
    to_canvas_b = np.vstack([mab, [0, 0, 1]])
    to_canvas_b = (np.vstack([to_canvas_a, [0, 0, 1]]) @ to_canvas_b)[:2]

    def warp(img, m, interp):
        return cv2.warpAffine(img, m, size, flags=interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    ia = warp(a, to_canvas_a, cv2.INTER_LINEAR)
    ib = warp(b, to_canvas_b, cv2.INTER_LINEAR)
    wa_mask = warp(ma.astype(np.uint8), to_canvas_a, cv2.INTER_NEAREST).astype(bool)
    wb_mask = warp(mb.astype(np.uint8), to_canvas_b, cv2.INTER_NEAREST).astype(bool)

    canvas = np.empty((size[1], size[0], 3), dtype=np.uint8)
    canvas[:] = background
    canvas[wb_mask] = ib[wb_mask]
    canvas[wa_mask] = ia[wa_mask]
    both = wa_mask & wb_mask
    canvas[both] = ((ia[both].astype(np.uint16) + ib[both]) // 2).astype(np.uint8)
    if outline:
        for m, colour in ((wa_mask, COLOUR_A), (wb_mask, COLOUR_B)):
            contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(canvas, contours, -1, colour, 1, lineType=cv2.LINE_8)
    return canvas


def side_by_side(images, *, gap_px: int = 12, background: tuple[int, int, int] = (40, 40, 40),
                 height_px: int | None = None, pixel_mm=None) -> np.ndarray:
    """Pictures next to each other on one row: at one common scale, or each scaled to a common height.

    Parameters
    ----------
    images : sequence of (H, W[, 3]) arrays
    gap_px : int
    background : RGB triple
    height_px : int, optional
        Height of the row. Without ``pixel_mm`` every picture is scaled to it (default: the smallest
        input height). With ``pixel_mm`` the physically tallest picture is drawn this tall (default: its
        own height in pixels) and the others at the same mm a pixel, centred vertically.
    pixel_mm : sequence of float, optional
        Size of a pixel of each picture, mm (25.4 / dpi). Given, all pictures are drawn at one scale,
        so their sizes compare truthfully: a 105 mm fragment is drawn 105/149 as tall as a 149 mm one,
        whatever the dpi of each.

    Examples
    --------
    >>> a, b = np.zeros((20, 10, 3), np.uint8), np.zeros((40, 40, 3), np.uint8)
    >>> side_by_side([a, b], gap_px=0).shape                       # one height
    (20, 30, 3)
    >>> side_by_side([a, b], gap_px=0, pixel_mm=[0.1, 0.1]).shape  # one scale: a 2 mm tall, b 4 mm
    (40, 50, 3)
    """
    imgs = [to_rgb8(im) for im in images]
    if not imgs:
        raise ValueError("images must hold at least one picture")
    if pixel_mm is None:
        h = int(height_px or min(im.shape[0] for im in imgs))
        if h < 1:
            raise ValueError(f"height_px must be >= 1, got {height_px}")
        sizes = [(max(1, int(round(im.shape[1] * h / im.shape[0]))), h) for im in imgs]
    else:
        pmm = [float(p) for p in pixel_mm]
        if len(pmm) != len(imgs) or not all(np.isfinite(p) and p > 0 for p in pmm):
            raise ValueError(f"pixel_mm must hold one positive size (mm) per picture ({len(imgs)}), got {pixel_mm!r}")
        tall = max(range(len(imgs)), key=lambda i: imgs[i].shape[0] * pmm[i])
        h = int(height_px or imgs[tall].shape[0])
        if h < 1:
            raise ValueError(f"height_px must be >= 1, got {height_px}")
        out_mm = imgs[tall].shape[0] * pmm[tall] / h   # the common size of a pixel, mm
        sizes = [(max(1, int(round(im.shape[1] * p / out_mm))), max(1, min(h, int(round(im.shape[0] * p / out_mm)))))
                 for im, p in zip(imgs, pmm)]
    scaled = []
    for im, (w, hi) in zip(imgs, sizes):
        interp = cv2.INTER_AREA if hi < im.shape[0] else cv2.INTER_LINEAR
        scaled.append(cv2.resize(im, (w, hi), interpolation=interp))
    width = sum(im.shape[1] for im in scaled) + gap_px * (len(scaled) - 1)
    out = np.empty((h, width, 3), dtype=np.uint8)
    out[:] = background
    x = 0
    for im in scaled:
        y = (h - im.shape[0]) // 2
        out[y:y + im.shape[0], x:x + im.shape[1]] = im
        x += im.shape[1] + gap_px
    return out


def raking_light(normals: np.ndarray, mask: np.ndarray | None = None, *, azimuth_deg: float = 135.0,
                 elevation_deg: float = 25.0, albedo: np.ndarray | None = None) -> np.ndarray:
    """Lambertian shading of a normal map under one low (raking) light, as (H, W, 3) uint8.

    A fallback relief picture when :mod:`common.render` offers nothing better: ``I = max(0, n·l)``
    with ``l`` at ``azimuth_deg`` (counter-clockwise from +x, y up) and ``elevation_deg`` above the
    image plane; a low elevation exaggerates relief (§7.2). Off-mask pixels are black.
    """
    n = np.asarray(normals, dtype=np.float32)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {n.shape}")
    if not 0 < elevation_deg <= 90:
        raise ValueError(f"elevation_deg must be in (0, 90], got {elevation_deg}")
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    light = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)], dtype=np.float32)
    shade = np.clip(np.nan_to_num(n @ light), 0.0, 1.0)
    # normalise so a flat surface is mid-grey whatever the elevation: relief, not exposure, shows
    shade = np.clip(shade * (0.5 / max(light[2], 1e-3)), 0.0, 1.0)
    rgb = np.repeat(shade[..., None], 3, axis=2)
    if albedo is not None:
        rgb = rgb * np.clip(np.asarray(albedo, dtype=np.float32), 0, 1) ** 0.3
    out = np.round(rgb * 255).astype(np.uint8)
    if mask is not None:
        out[~np.asarray(mask, dtype=bool)] = 0
    return out
