"""Colour-only fragments from photographs or scans: alpha, or a plain background removed.

A lab's fragment collection is often a folder of pictures: RGBA cut-outs (the alpha channel is
the fragment, possibly with a soft edge), or photographs and scans of each piece on a plain
background. :func:`fragment_from_image` turns one such picture into a colour-only
:class:`~common.rgbn.image.RGBNImage` (linear albedo + mask, no normals), the form every later
stage reads; implausible pictures are refused with the reason instead of giving a wrong mask.
"""

from __future__ import annotations

import cv2
import numpy as np

from common.imports.driver import ImportRefused
from common.rgbn._filters import normalized_blur
from common.rgbn.image import RGBNImage
from common.rgbn.io import linear_to_srgb, srgb_to_linear

BACKGROUNDS = ("auto", "alpha", "plain")


def _full_scale(arr: np.ndarray) -> float:
    if arr.dtype == np.uint8:
        return 255.0
    if arr.dtype == np.uint16:
        return 65535.0
    if np.issubdtype(arr.dtype, np.floating):
        return 1.0
    raise ValueError(f"image must be uint8, uint16 or float, got {arr.dtype}")


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """Holes of a mask filled: background is what the image border reaches."""
    flood = np.pad((~mask).astype(np.uint8), 1, constant_values=1)
    cv2.floodFill(flood, None, (0, 0), 2)
    return flood[1:-1, 1:-1] != 2


def _largest_component(fg: np.ndarray) -> np.ndarray:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fg.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros(fg.shape, bool)
    return labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))


def _border(a: np.ndarray, width: int) -> np.ndarray:
    """Pixels (..., C) of the border strip of ``width`` pixels, as rows."""
    h, w = a.shape[:2]
    keep = np.zeros((h, w), bool)
    keep[:width] = keep[-width:] = True
    keep[:, :width] = keep[:, -width:] = True
    return keep


def background_mask(rgb: np.ndarray, *, margin: float = 6.0, min_contrast: float = 0.06,
                    border_px: int | None = None, srgb: bool = True, edge_px: int = 3) -> tuple[np.ndarray, dict]:
    """Fragment mask of a picture on a plain background, by its distance from the background colour.

    Parameters
    ----------
    rgb : (H, W, 3) float array
        Colour in [0, 1] as stored (sRGB-encoded for photographs: roughly perceptual steps).
    margin : float
        The threshold is the background's robust spread (1.4826 MAD of the border pixels'
        distance from the background model) times ``margin``...
    min_contrast : float
        ...but never below this distance in [0, 1] colour units (a perfectly flat synthetic
        background has zero spread).
    border_px : int, optional
        Width of the border strip that samples the background (default 2 % of the smaller side,
        at least 2 pixels).
    srgb : bool
        The values are sRGB-encoded (photographs, scans): the edge's mix of piece and background
        is modelled in linear light. False for linear data.
    edge_px : int
        Depth of the piece's soft edge in pixels (partial coverage, the optics' blur): the colour
        of the piece is taken from twice this far inside the first edge (:func:`edge_coverage`).

    Returns
    -------
    mask : (H, W) bool
        The largest connected region that differs from the background, holes filled, its edge
        placed where the piece covers half a pixel.
    info : dict
        ``background`` (mean colour), ``threshold``, ``spread`` (units of [0, 1] colour);
        ``coverage`` (H, W) float32, the share of each pixel covered by the piece (1 inside, 0 on
        the background, the estimate on the edge, NaN where the edge's contrast is too low to
        tell, :func:`edge_coverage`); ``background_rgb`` (H, W, 3) float32, the background model
        in the input's units; ``edge_placed``, the share of the edge pixels whose side was
        decided by their coverage rather than by the threshold.

    Notes
    -----
    The background is modelled per channel as a plane ``c0 + c1 x + c2 y`` fitted to the border
    strip by least squares, so a lamp gradient or vignetting across a scan or photograph does not
    read as fragment. The first fit takes the half of the strip nearest its per-channel median
    colour (background while parts of the fragment reaching the border, dust, cover less than half
    of it), and leaves out the border pixels it would call fragment (farther than ``margin`` MAD);
    the plane is fitted to the rest, then refitted once without the border pixels farther than
    3 MAD from that fit. A fit to the whole strip first was dragged by a piece reaching the border
    along a sixth of it or more (its colour mixed into the background's, the spread grown past full
    scale): the picture was refused as holding no fragment, where it is found now and refused for
    touching the border (:func:`fragment_from_image`). With no piece on the border nothing is left
    out and the fit is the whole strip's, as before.

    A threshold a few noise levels above the background finds the piece, but on a contrasting
    background it puts the edge where the piece covers a few per cent of a pixel: 2.4 px outside
    the half-coverage edge on RePAIR's pieces composited on black (1 px blur), 1.3 px on white,
    against 0 for a cut-out's alpha split at half. The outline then depends on the background,
    and a dark or pale fringe of mixed pixels lines the piece. So the edge is placed again by
    each pixel's coverage (:func:`edge_coverage`), where the contrast allows.
    """
    rgb = np.asarray(rgb, np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3), got shape {rgb.shape}")
    h, w = rgb.shape[:2]
    if min(h, w) < 8:
        raise ValueError(f"rgb is {w}x{h} px: too small to tell a fragment from its background")
    b = border_px or max(2, int(round(0.02 * min(h, w))))
    strip = _border(rgb, b)
    yy, xx = np.nonzero(strip)
    design = np.stack([np.ones(len(xx)), xx / w - 0.5, yy / h - 0.5], axis=1)
    samples = rgb[strip].astype(np.float64)

    def spread_of(coef, among):
        dist = np.linalg.norm(samples - design @ coef, axis=1)
        med = float(np.median(dist[among]))
        return dist, med, 1.4826 * float(np.median(np.abs(dist[among] - med))) + 1e-6

    # first fit: the half of the strip nearest its per-channel median colour, background while the piece (or dust)
    # covers less than half of the strip; a fit to the whole strip was dragged by a piece reaching the border
    near = np.linalg.norm(samples - np.median(samples, axis=0), axis=1)
    first = near <= np.median(near)
    coef, *_ = np.linalg.lstsq(design[first], samples[first], rcond=None)
    dist, med, mad = spread_of(coef, slice(None))
    keep = dist <= med + max(margin, 3.0) * mad    # what this fit would call fragment left out
    for _ in range(2):
        coef, *_ = np.linalg.lstsq(design[keep], samples[keep], rcond=None)
        dist, med, mad = spread_of(coef, keep)
        keep = dist <= med + 3.0 * mad
    spread = med + mad
    threshold = max(float(min_contrast), med + margin * mad)
    c = coef.astype(np.float32)
    gx = (np.arange(w, dtype=np.float32) / w - 0.5)[None, :, None]
    gy = (np.arange(h, dtype=np.float32) / h - 0.5)[:, None, None]
    diff = rgb - c[0]
    diff -= gx * c[1]
    diff -= gy * c[2]
    dist = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    fg = (dist > threshold).astype(np.uint8)
    k = max(1, int(round(min(h, w) / 300)))  # specks of noise and dust out, thin necks kept
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((2 * k + 1, 2 * k + 1), np.uint8)) > 0
    found = _fill_holes(_largest_component(fg))
    back = rgb - diff     # the background model at every pixel
    # half coverage is decidable where piece and background differ by twice the threshold
    coverage = edge_coverage(rgb, found, back, srgb=srgb, edge_px=edge_px, min_contrast=2.0 * threshold)
    band = found & ~cv2.erode(found.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    mask = np.where(np.isnan(coverage), found, coverage >= 0.5)
    if mask.any():
        mask = _fill_holes(_largest_component(mask))
    placed = float((band & np.isfinite(coverage)).sum() / max(int(band.sum()), 1))
    return mask, {"background": [float(v) for v in coef[0]], "threshold": float(threshold), "spread": float(spread),
                  "coverage": coverage, "background_rgb": back, "edge_placed": placed}


def edge_coverage(rgb: np.ndarray, mask: np.ndarray, background: np.ndarray, *, srgb: bool = True,
                  edge_px: int = 3, min_contrast: float = 0.1) -> np.ndarray:
    """Share of each pixel along a piece's edge that the piece covers, from its colour as a mix (linear light).

    A pixel the edge crosses, or one the optics blur across it, records ``c = α f + (1 − α) b`` in
    linear light, with ``f`` the piece's colour next to it and ``b`` the background's. So
    ``α = (c − b)·(f − b) / |f − b|²`` (the least-squares mixing share, as in the "alpha matting"
    of a known background; Smith & Blinn 1996, "Blue screen matting"), clipped to [0, 1]. ``f`` is
    the mean colour of the piece at least 2 ``edge_px`` inside the first edge, carried outward by a
    normalised Gaussian convolution (σ = ``edge_px``), so a painted band reaching the edge gives
    its own colour, not the piece's average.

    Parameters
    ----------
    rgb : (H, W, 3) float array
        Colour in [0, 1] as stored.
    mask : (H, W) bool
        The piece as first found (its edge a little outside half coverage, as a low threshold
        puts it).
    background : (H, W, 3) float array
        The background's colour at every pixel, same units as ``rgb``.
    srgb : bool
        ``rgb`` and ``background`` are sRGB-encoded: mixed after decoding to linear light.
    edge_px : int
        Depth of the soft edge in pixels (the first edge's distance outside half coverage, and
        the blur's reach inside it, are each about this).
    min_contrast : float
        Where ``|f − b|`` (encoded units, as ``rgb``) is below this, the share cannot be told from
        noise: NaN there.

    Returns
    -------
    (H, W) float32
        1 on the piece deeper than 2 ``edge_px`` inside ``mask``, 0 more than 1 px outside it,
        α between, NaN where the contrast is too low.
    """
    rgb = np.asarray(rgb, np.float32)
    background = np.asarray(background, np.float32)
    if rgb.shape != background.shape or rgb.ndim != 3 or rgb.shape[:2] != np.shape(mask):
        raise ValueError(f"rgb {rgb.shape}, background {background.shape} and mask {np.shape(mask)} must agree")
    if edge_px < 1:
        raise ValueError(f"edge_px must be >= 1, got {edge_px}")
    m = np.asarray(mask, np.uint8)
    # the first edge lies up to ~edge_px outside half coverage and the blur reaches edge_px inside it
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (4 * edge_px + 1, 4 * edge_px + 1))
    inner = cv2.erode(m, kernel)
    reach = cv2.dilate(m, np.ones((3, 3), np.uint8)).astype(bool) & ~inner.astype(bool)
    out = np.where(inner > 0, np.float32(1.0), np.float32(0.0))
    if not reach.any():
        return out
    # the piece's colour next to each edge pixel: normalised convolution of the inner part
    near, weight = normalized_blur(rgb, inner.astype(np.float32), edge_px)
    ok = reach & (weight > 1e-3)
    f = near[ok]
    c, b = rgb[ok], background[ok]
    contrast = np.linalg.norm(f - b, axis=1)
    if srgb:
        f, c, b = srgb_to_linear(f), srgb_to_linear(c), srgb_to_linear(b)
    d = f - b
    alpha = np.einsum("ij,ij->i", c - b, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12)
    alpha = np.clip(alpha, 0.0, 1.0).astype(np.float32)
    alpha[contrast < min_contrast] = np.nan
    out[ok] = alpha
    out[reach & ~ok] = np.nan
    return out


def cut_from_background(rgb: np.ndarray, *, margin: float = 6.0, srgb: bool = True) -> tuple[np.ndarray, np.ndarray, dict]:
    """A piece on a plain background, cut out: ``(colour, mask, info)``.

    The mask and ``info`` are :func:`background_mask`'s (the edge at half coverage); ``colour`` is ``rgb``
    (float, [0, 1], as stored) with the background's share taken out of the edge pixels kept
    (:func:`unmix_edge`), so no fringe of the background's colour lines the piece. What
    ``tessera import images`` and ``tessera evaluate --collection`` make of an RGB picture.
    """
    mask, info = background_mask(rgb, margin=margin, srgb=srgb)
    return unmix_edge(rgb, info["coverage"], info["background_rgb"], srgb=srgb), mask, info


def unmix_edge(rgb: np.ndarray, coverage: np.ndarray, background: np.ndarray, *, srgb: bool = True) -> np.ndarray:
    """The piece's own colour at its edge: the background's share taken out of each mixed pixel.

    Inverts ``c = α f + (1 − α) b`` (linear light) for ``f`` where ``0.5 ≤ α < 1`` (the edge pixels
    kept in the mask; dividing by α at most doubles their noise). Elsewhere ``rgb`` is returned
    unchanged. Without this the mask's outermost pixel ring carries a fringe of the background's
    colour (dark on black, pale on white) that reads as paint at the edge.

    Parameters
    ----------
    rgb, background : (H, W, 3) float arrays in [0, 1], as stored (sRGB-encoded when ``srgb``).
    coverage : (H, W) float array
        From :func:`edge_coverage` (NaN: left as is).

    Returns
    -------
    (H, W, 3) float32, same encoding as ``rgb``.
    """
    out = np.array(rgb, np.float32)
    a = np.nan_to_num(np.asarray(coverage, np.float32), nan=1.0)
    sel = (a >= 0.5) & (a < 1.0)
    if not sel.any():
        return out
    c, b = out[sel], np.asarray(background, np.float32)[sel]
    if srgb:
        c, b = srgb_to_linear(c), srgb_to_linear(b)
    f = np.clip(b + (c - b) / a[sel][:, None], 0.0, 1.0)
    out[sel] = linear_to_srgb(f) if srgb else f
    return out


def fragment_from_image(image: np.ndarray, *, dpi: float, background: str = "auto", alpha_threshold: float = 0.5,
                        srgb: bool = True, margin: float = 6.0, min_area_fraction: float = 0.001,
                        max_cover: float = 0.9, max_border_touch: float = 0.1) -> RGBNImage:
    """A colour-only RGBN image of one fragment from a picture with alpha or on a plain background.

    Parameters
    ----------
    image : (H, W), (H, W, 2), (H, W, 3) or (H, W, 4) array
        Grey, grey + alpha, RGB or RGBA samples, uint8, uint16 or float in [0, 1] (channel order
        RGB, as :func:`common.imports.door.read_image_checked` returns).
    dpi : float
        Sampling density of the picture, dots per inch (pixel = 25.4 / dpi mm).
    background : {'auto', 'alpha', 'plain'}
        Where the mask comes from. ``alpha``: alpha above ``alpha_threshold`` of full scale (the
        soft edge of a cut-out split at half coverage). ``plain``: the picture's background is
        estimated from its border and removed (:func:`background_mask`). ``auto``: alpha when the
        image has an alpha channel at or below ``alpha_threshold`` somewhere (it cuts something out),
        else plain.
    alpha_threshold : float
        Fraction of full scale in (0, 1).
    srgb : bool
        Decode the sRGB transfer curve to linear albedo (photographs, 8/16-bit scans). False for
        data that is linear already.
    margin : float
        Background threshold in robust spreads (see :func:`background_mask`).
    min_area_fraction, max_cover : float
        The fragment must cover at least / at most this fraction of the picture.
    max_border_touch : float
        At most this fraction of the picture's border may be fragment (more: the piece is cut
        off by the frame, or the background is not plain). This and ``max_cover`` apply to a
        plain background only: a cut-out's alpha may be cropped tight to the piece.

    Returns
    -------
    RGBNImage
        ``albedo`` linear RGB (0 outside the mask), ``mask``, ``dpi``; no normals.
        ``attrs['mask_from']`` is ``"alpha"`` or ``"plain background"``; from a plain background,
        ``attrs['edge_placed']`` is the share of the edge placed at half coverage
        (:func:`background_mask`; low: the background is too close to the piece's colour).

    Raises
    ------
    ValueError
        A bad argument (named). :class:`~common.imports.driver.ImportRefused` (a ValueError) for a
        picture that gives no plausible fragment: none found, too much of the picture, or cut by
        the border; the message gives the measured figure.

    Examples
    --------
    >>> img = np.full((60, 80, 3), 30, np.uint8); img[15:45, 20:60] = (200, 150, 90)
    >>> frag = fragment_from_image(img, dpi=300)
    >>> int(frag.mask.sum()), frag.has_normals
    (1200, False)
    """
    if background not in BACKGROUNDS:
        raise ValueError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    if not 0.0 < alpha_threshold < 1.0:
        raise ValueError(f"alpha_threshold must be in (0, 1), got {alpha_threshold}")
    if not (np.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi must be a positive number, got {dpi}")
    arr = np.asarray(image)
    full = _full_scale(arr)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4):
        raise ValueError(f"image must be (H, W[, 1|2|3|4]), got shape {np.asarray(image).shape}")
    has_alpha = arr.shape[2] in (2, 4)
    colour = arr[..., :-1] if has_alpha else arr
    if colour.shape[2] == 1:
        colour = np.repeat(colour, 3, axis=2)
    rgb = colour.astype(np.float32) / np.float32(full)
    alpha = arr[..., -1].astype(np.float32) / np.float32(full) if has_alpha else None
    if background == "alpha" and alpha is None:
        raise ValueError("background='alpha' but the image has no alpha channel")
    use_alpha = background == "alpha" or (background == "auto" and alpha is not None
                                          and bool((alpha <= alpha_threshold).any()))
    if use_alpha:
        mask = alpha > alpha_threshold
        how = "alpha"
    else:
        rgb, mask, info = cut_from_background(rgb, margin=margin, srgb=srgb)
        how = "plain background"
    area = float(mask.mean())
    if area < min_area_fraction or not mask.any():
        why = ("alpha is below the threshold everywhere" if use_alpha else
               "nothing differs from the background colour "
               f"{np.round(np.array(info['background']) * 255).astype(int).tolist()} "
               f"by more than {info['threshold'] * 255:.0f}/255")
        raise ImportRefused(f"no fragment found ({area * 100:.2f} % of the picture; {why})")
    if not use_alpha:
        _check_plausible(mask, area, max_cover, max_border_touch)
    albedo = srgb_to_linear(rgb) if srgb else np.clip(rgb, 0.0, 1.0)
    albedo[~mask] = 0.0
    attrs = {"mask_from": how}
    if not use_alpha:
        attrs["edge_placed"] = round(info["edge_placed"], 3)
    return RGBNImage(albedo=albedo, mask=mask, dpi=float(dpi), attrs=attrs)


def crop_to_mask(image: RGBNImage, *, margin_mm: float = 2.0) -> tuple[RGBNImage, tuple[int, int]]:
    """``image`` cut to its mask's bounding box and ``margin_mm`` of background round it (inside the picture).

    A picture of a fragment is often mostly background (RePAIR's pieces fill 10–25 % of their 2000 px
    canvas): every later stage would carry it, and the review page's pictures, shrunk to a few hundred
    pixels, would show the piece at ~1 mm per pixel. Returns the cropped image (a window of ``image``,
    :meth:`~common.rgbn.image.RGBNImage.window`; ``attrs['crop_px']`` = ``[x0, y0]``, the crop's top-left
    corner in the picture's pixels) and ``(x0, y0)``.

    >>> m = np.zeros((100, 200), bool); m[40:50, 60:90] = True
    >>> img = RGBNImage(albedo=np.zeros((100, 200, 3), np.float32), mask=m, dpi=254.0)   # 0.1 mm per pixel
    >>> out, (x0, y0) = crop_to_mask(img, margin_mm=1.0)
    >>> out.mask.shape, (x0, y0), int(out.mask.sum())
    ((30, 50), (50, 30), 300)
    """
    if not (np.isfinite(margin_mm) and margin_mm >= 0):
        raise ValueError(f"margin_mm must be >= 0, got {margin_mm}")
    rows, cols = np.flatnonzero(image.mask.any(axis=1)), np.flatnonzero(image.mask.any(axis=0))
    if not len(rows):
        raise ImportRefused("no fragment found (the mask is empty)")
    pad = int(np.ceil(margin_mm / image.pixel_mm))
    h, w = image.mask.shape
    y0, x0 = max(int(rows[0]) - pad, 0), max(int(cols[0]) - pad, 0)
    out = image.window(y0, min(int(rows[-1]) + pad + 1, h), x0, min(int(cols[-1]) + pad + 1, w))
    out.attrs["crop_px"] = [x0, y0]
    return out, (x0, y0)


def _check_plausible(mask, area, max_cover, max_border_touch) -> None:
    """A mask cut from a plain background must leave background all round (a cut-out's alpha may be cropped tight)."""
    if area > max_cover:
        raise ImportRefused(f"the fragment would cover {area * 100:.0f} % of the picture (more than "
                            f"{max_cover * 100:.0f} %): the background is not plain or the piece fills the frame")
    edge = _border(mask, 1)
    touch = float(mask[edge].mean())
    if touch > max_border_touch:
        raise ImportRefused(f"the fragment touches the picture's border along {touch * 100:.0f} % of it (more than "
                            f"{max_border_touch * 100:.0f} %): the piece is cut off by the frame or the background "
                            "is not plain")


def mask_picture(rgb: np.ndarray, mask: np.ndarray, *, max_side: int = 800) -> np.ndarray:
    """A picture for checking a mask by eye: the background dimmed, the outline in magenta.

    Parameters
    ----------
    rgb : (H, W, 3) array
        The picture as shown (display values: uint8, uint16 or float in [0, 1]).
    mask : (H, W) bool
    max_side : int
        The result is scaled down so its longer side is at most this (pixels).

    Returns
    -------
    (h, w, 3) uint8 RGB
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[:2] != np.shape(mask):
        raise ValueError(f"rgb must be (H, W, 3) matching mask {np.shape(mask)}, got {rgb.shape}")
    img = np.clip(rgb.astype(np.float32) / np.float32(_full_scale(rgb)) * 255.0, 0, 255).astype(np.uint8)
    m = np.asarray(mask, bool)
    scale = min(1.0, max_side / max(m.shape))
    if scale < 1.0:
        size = (max(1, round(m.shape[1] * scale)), max(1, round(m.shape[0] * scale)))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        m = cv2.resize(m.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    out = img.copy()
    out[~m] = (out[~m] * 0.35).astype(np.uint8)
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, (255, 0, 255), max(1, round(max(out.shape) / 400)))
    return out
