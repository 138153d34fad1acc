"""Finding the fragment on the glass: background subtraction on the pre-scan (§3.3.4).

:func:`locate_fragment` takes a low-dpi pre-scan of the whole bed and returns the fragment's
region in bed millimetres. The background is either an empty-bed pre-scan (best) or estimated
from the pre-scan itself by a median filter much larger than a fragment. Dust (specks below
``min_area_mm2``), bed texture (robust noise threshold from the median absolute deviation) and
the lamp's shadow (darker than the background, neutral, with no texture of its own — measured on
the dark pixels alone, so that the fragment's edge beside a narrow shadow band does not count)
are rejected. :func:`fragment_mask` segments the fragment in a full-dpi scan of its region, whose
outer ring is background.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from common.acquisition.errors import MultipleFragmentsError, NoFragmentError


@dataclass(frozen=True)
class Blob:
    """One object seen on the glass.

    Attributes
    ----------
    bbox_mm : (left, top, right, bottom) in bed mm
    centroid_mm : (x, y) in bed mm
    area_mm2 : float
    """

    bbox_mm: tuple[float, float, float, float]
    centroid_mm: tuple[float, float]
    area_mm2: float


def to_float(image: np.ndarray) -> np.ndarray:
    """Scanner image (uint8/uint16/float) as float32 in [0, 1], always (H, W, 3)."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None].repeat(3, axis=2)
    if image.ndim != 3 or image.shape[2] < 3:
        raise ValueError(f"image must be (H, W, 3), got {image.shape}")
    image = image[..., :3]
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    if image.dtype == np.uint16:
        return image.astype(np.float32) / 65535.0
    return image.astype(np.float32)


def _foreground(img: np.ndarray, bg: np.ndarray, pixel_mm: float, k: float,
                noise_region: np.ndarray | None = None) -> np.ndarray:
    """Pixels that differ from the background beyond its noise, minus shadow-like ones.

    The noise statistics come from ``noise_region`` (pixels known to be background), or from
    the whole image when the object is small in it (the pre-scan).
    """
    sm = cv2.GaussianBlur(img, (0, 0), max(0.6, 0.15 / pixel_mm))
    diff = sm - bg
    dist = np.sqrt((diff ** 2).sum(axis=2))
    ref = dist if noise_region is None else dist[noise_region]
    med = np.median(ref)
    mad = np.median(np.abs(ref - med)) + 1e-6
    thr = max(k * 1.4826 * mad + med, 0.02 * float(np.median(bg.sum(axis=2))) + 0.004)
    fg = dist > thr
    # the lamp's shadow: darker than the background in every channel, with the background's hue
    lum, blum = sm.mean(axis=2), bg.mean(axis=2) + 1e-6
    chroma = np.abs(sm / (lum[..., None] + 1e-6) - bg / blum[..., None]).sum(axis=2)
    dark = (lum < 0.85 * blum) & (chroma < 0.15)
    lap = np.abs(cv2.Laplacian(lum, cv2.CV_32F))
    s = max(1.0, 0.5 / pixel_mm)
    tex = cv2.GaussianBlur(lap, (0, 0), s)
    btex = np.median(tex)
    # the texture of the dark pixels themselves: the Laplacian only where its 3×3 stencil lies in
    # dark pixels, averaged over them (normalised convolution). Blurred over all pixels, the bright
    # fragment edge beside a shadow band a few pixels wide (a small, thick fragment at 100 dpi)
    # passes for texture and the shadow for fragment.
    inner = cv2.erode(dark.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
    den = cv2.GaussianBlur(inner, (0, 0), s)
    own = cv2.GaussianBlur(lap * inner, (0, 0), s) / np.maximum(den, 1e-6)
    tex = np.where(den > 0.1, own, tex)
    shadow = dark & (tex < 3 * btex + 1e-4)
    return fg & ~shadow


def locate_fragments(prescan: np.ndarray, dpi: float, *, background: np.ndarray | None = None,
                     min_area_mm2: float = 20.0, max_elongation: float = 6.0, min_solidity: float = 0.5,
                     k: float = 6.0, background_mm: float = 100.0, join_mm: float = 10.0) -> list[Blob]:
    """Every object on the glass in a pre-scan, by background subtraction.

    Parameters
    ----------
    prescan : (H, W, 3) array
        Whole-bed pre-scan (uint8/uint16/float), pixel (0, 0) at bed (0, 0).
    dpi : float
        Pre-scan resolution.
    background : (H, W, 3) array or None
        Pre-scan of the empty bed at the same dpi; None = estimate it (median filter over
        ``background_mm``, which must exceed twice the largest fragment).
    min_area_mm2 : float
        Smaller blobs are dust.
    max_elongation : float
        Blobs longer than this times their width are bed features (frames, rulers), not fragments.
    min_solidity : float
        Blobs filling less than this fraction of their convex hull (rings, frames) are rejected.
    k : float
        Threshold in robust standard deviations of the background difference.
    background_mm : float
        Window of the estimated background (more than twice the largest fragment).
    join_mm : float
        Parts closer than this are one object (dark paint as dark as the lid splits a fragment).

    Returns
    -------
    list of Blob, largest first.
    """
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    img = to_float(prescan)
    pixel_mm = 25.4 / dpi
    if background is not None:
        bg = to_float(background)
        if bg.shape != img.shape:
            raise ValueError(f"background must have the pre-scan's shape {img.shape}, got {bg.shape}")
        bg = cv2.GaussianBlur(bg, (0, 0), max(0.6, 0.15 / pixel_mm))
    else:
        # median filter over ``background_mm``, more than twice a fragment's size (else the median
        # at the fragment is the fragment), on a coarse copy (fast), then back to full size
        f = max(1, int(round(background_mm / 25 / pixel_mm)))      # 25 cells across the window
        small = cv2.resize(img, (max(1, img.shape[1] // f), max(1, img.shape[0] // f)), interpolation=cv2.INTER_AREA)
        ksz = int(round(background_mm / (pixel_mm * f))) | 1
        med = np.dstack([ndimage.median_filter(small[..., c], size=ksz, mode="reflect") for c in range(3)])
        bg = cv2.resize(med, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)
    fg = _foreground(img, bg, pixel_mm, k)
    r = max(1, int(round(0.5 / pixel_mm)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    # close first: an object close to the bed's colour is a speckle of foreground pixels (engraving,
    # relief); then open: isolated dust specks vanish
    fg = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (4 * r + 1, 4 * r + 1)))
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, kernel)
    labels, n = _group(fg, join_mm / pixel_mm, int(2.0 / pixel_mm ** 2))
    blobs = []
    areas = np.bincount(labels.ravel(), minlength=n + 1)
    yy, xx = np.indices(labels.shape)
    sx = np.bincount(labels.ravel(), weights=xx.ravel(), minlength=n + 1)
    sy = np.bincount(labels.ravel(), weights=yy.ravel(), minlength=n + 1)
    for i, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        y, x = sl[0].start, sl[1].start
        h, w = sl[0].stop - y, sl[1].stop - x
        area = int(areas[i])
        area_mm2 = area * pixel_mm ** 2
        if area_mm2 < min_area_mm2:
            continue
        if max(w, h) > max_elongation * max(1, min(w, h)) or area < 0.15 * w * h:
            continue      # long thin or sparse: a frame, ruler or the bed edge
        if area > 0.5 * img.shape[0] * img.shape[1]:
            continue
        comp = (labels[sl] == i).astype(np.uint8)
        contours, _ = cv2.findContours(comp, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        hull = cv2.contourArea(cv2.convexHull(np.vstack(contours)))
        if area < min_solidity * max(hull, 1.0):
            continue      # a ring or frame around the bed, not a fragment
        blobs.append(Blob((x * pixel_mm, y * pixel_mm, (x + w) * pixel_mm, (y + h) * pixel_mm),
                          ((sx[i] / area + 0.5) * pixel_mm, (sy[i] / area + 0.5) * pixel_mm), float(area_mm2)))
    blobs.sort(key=lambda b: -b.area_mm2)
    return blobs


def locate_fragment(prescan: np.ndarray, dpi: float, *, background: np.ndarray | None = None,
                    margin_mm: float = 5.0, bed_mm: tuple[float, float] | None = None, **kw) -> tuple[float, float, float, float]:
    """The one fragment's region (left, top, right, bottom) in bed mm, plus ``margin_mm``.

    Raises
    ------
    NoFragmentError
        Nothing larger than dust on the glass.
    MultipleFragmentsError
        More than one object; the message says how many and where.
    """
    blobs = locate_fragments(prescan, dpi, background=background, **kw)
    if not blobs:
        raise NoFragmentError("pre-scan shows no fragment on the glass",
                              "No fragment found on the glass. Place the fragment face down near the middle of the glass and press Scan.")
    # a second object counts only if it is not negligible next to the first (e.g. a crumb)
    others = [b for b in blobs[1:] if b.area_mm2 > 0.1 * blobs[0].area_mm2]
    if others:
        where = "; ".join(f"{b.area_mm2:.0f} mm² at x={b.centroid_mm[0]:.0f} mm, y={b.centroid_mm[1]:.0f} mm"
                          for b in [blobs[0]] + others)
        raise MultipleFragmentsError(f"pre-scan shows {1 + len(others)} objects: {where}",
                                     f"{1 + len(others)} objects are on the glass ({where}). Leave only one fragment on the glass and press Scan.")
    x0, y0, x1, y1 = blobs[0].bbox_mm
    x0, y0, x1, y1 = x0 - margin_mm, y0 - margin_mm, x1 + margin_mm, y1 + margin_mm
    if bed_mm is None:
        bed_mm = (prescan.shape[1] * 25.4 / dpi, prescan.shape[0] * 25.4 / dpi)
    return (max(0.0, x0), max(0.0, y0), min(bed_mm[0], x1), min(bed_mm[1], y1))


def _group(fg: np.ndarray, join_px: float, min_part_px: int = 0, min_part_fraction: float = 0.0,
           drop_edge: bool = False) -> tuple[np.ndarray, int]:
    """Label foreground pixels so that parts closer than ``join_px`` share a label.

    Parts smaller than ``min_part_px`` (noise speckles in a shadow, dust) are dropped first so
    they do not join anything; with ``min_part_fraction`` > 0 the limit is at most that fraction
    of the largest part (a small fragment's own pieces, cut off by paint as dark as the lid, are
    not dust). With ``drop_edge``, parts touching the image's edge other than the largest are
    dropped too (in a scan of the fragment's region plus a margin they are the bed: a patch of
    lid texture or shadow).
    """
    if min_part_px > 0 or drop_edge:
        n, lab, stats, _ = cv2.connectedComponentsWithStats(fg.astype(np.uint8), connectivity=8)
        area = stats[1:, cv2.CC_STAT_AREA]
        if min_part_fraction > 0 and len(area):
            min_part_px = min(min_part_px, max(1.0, min_part_fraction * float(area.max())))
        keep = np.zeros(n, bool)
        keep[1:] = area >= min_part_px
        if drop_edge and n > 2:
            x, y, w, h = (stats[1:, k] for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
            edge = (x == 0) | (y == 0) | (x + w == fg.shape[1]) | (y + h == fg.shape[0])
            edge[int(np.argmax(area))] = False
            keep[1:] &= ~edge
        fg = keep[lab]
    r = max(0, int(round(join_px / 2)))
    grown = cv2.dilate(fg.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)) if r else fg
    n, labels = cv2.connectedComponents(np.ascontiguousarray(grown, dtype=np.uint8), connectivity=8)
    labels[fg == 0] = 0
    return labels, n - 1


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill enclosed holes (flood the background from a padded border; faster than scipy)."""
    m = np.pad(mask.astype(np.uint8), 1)
    flood = m.copy()
    cv2.floodFill(flood, np.zeros((m.shape[0] + 2, m.shape[1] + 2), np.uint8), (0, 0), 1)
    return (m | (flood == 0))[1:-1, 1:-1].astype(bool)


def fragment_mask(scan: np.ndarray, dpi: float, *, ring_fraction: float = 0.04, k: float = 6.0,
                  close_mm: float = 0.0, work_mm: float = 0.2, join_mm: float = 10.0) -> np.ndarray:
    """Mask of the fragment in a full-dpi scan of its region (the outer ring is background).

    The background colour is the median of the outer ring; pixels differing beyond ``k`` robust
    standard deviations are foreground, the lamp's shadow is excluded, gaps up to ``close_mm`` are
    closed (for objects of the bed's own colour, e.g. a coin on grey), holes are filled, and the
    largest object is kept with the parts within ``join_mm`` of it (gaps up to 6 mm closed; wider
    ones, e.g. a broad band of paint as dark as the lid, stay out of the mask). Parts under 2 mm²
    (or, for a small fragment, under 2 % of its largest part) are dust; parts other than the
    largest that reach the region's edge are the bed. Computed on a copy reduced to about
    ``work_mm`` per pixel and brought back to full size (the outline to a fraction of that).
    """
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    scan = np.asarray(scan)
    H0, W0 = scan.shape[:2]
    pixel_mm = 25.4 / dpi
    f = max(1, int(work_mm / pixel_mm))
    # reduce first (in the scan's own integer type: cheaper), then convert
    img = to_float(scan if f == 1 else cv2.resize(np.ascontiguousarray(scan[..., :3]), (max(8, W0 // f), max(8, H0 // f)),
                                                  interpolation=cv2.INTER_AREA))
    H, W = img.shape[:2]
    pixel_mm = pixel_mm * W0 / W
    b = max(2, int(round(ring_fraction * min(H, W))))
    ring = np.ones((H, W), bool)
    ring[b:-b, b:-b] = False
    bgc = np.median(img[ring], axis=0).astype(np.float32)
    bg = np.broadcast_to(bgc, img.shape)
    fg = _foreground(img, bg, pixel_mm, k, noise_region=ring).astype(np.uint8)
    # close gaps of up to ``close_mm`` (an object of the bed's own grey shows only its outline and
    # engraving), fill the enclosed holes, then open away dust
    if close_mm > 0:
        rc = max(1, int(round(close_mm / pixel_mm)))
        fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rc + 1,) * 2))
        fg = _fill_holes(fg).astype(np.uint8)
    r = max(1, int(round(0.3 / pixel_mm)))
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2))
    # parts under 2 mm² are dust or speckle, but under 2 % of the fragment only for a small one
    # (at 100 dpi, 2 mm² is 31 pixels: the tip of a 60 mm² piece beyond a black band); parts
    # reaching the region's edge are bed, not fragment
    labels, n = _group(fg, join_mm / pixel_mm, int(2.0 / pixel_mm ** 2), min_part_fraction=0.02, drop_edge=True)
    if n < 1:
        return np.zeros((H0, W0), bool)
    best = 1 + int(np.argmax(np.bincount(labels.ravel(), minlength=n + 1)[1:]))
    mask = (labels == best).astype(np.uint8)
    if join_mm > 0:      # bridge narrow gaps between its parts (e.g. a band of black paint)
        rj = max(1, int(round(min(join_mm / 2, 3.0) / pixel_mm)))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rj + 1,) * 2))
    mask = _fill_holes(mask)
    if f == 1:
        return mask
    up = cv2.resize(mask.astype(np.float32), (W0, H0), interpolation=cv2.INTER_LINEAR)
    return up > 0.5


def crop_to_fragment(scan: np.ndarray, dpi: float, *, margin_mm: float = 5.0, prescan_dpi: float = 50.0,
                     **kw) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The fragment's region of a whole-bed scan, as the capture would have scanned it (§3.3.4).

    The scan is reduced to ``prescan_dpi`` (a pre-scan), :func:`locate_fragment` finds the one
    fragment on it, and that region plus ``margin_mm`` is cut from the full-resolution scan.

    Parameters
    ----------
    scan : (H, W, 3) array
        A scan of the whole bed (or a large part of it) at ``dpi``.
    dpi : float
    margin_mm : float
        Margin around the fragment (its outer ring is the background :func:`fragment_mask` needs).
    prescan_dpi : float
        Resolution the fragment is located at.
    **kw
        Passed to :func:`locate_fragments` (e.g. ``background_mm``).

    Returns
    -------
    crop : array
        The region, same dtype as ``scan``.
    area_mm : (left, top, right, bottom)
        The region in the scan's millimetres (origin at its top-left corner).

    Raises
    ------
    NoFragmentError, MultipleFragmentsError
        As :func:`locate_fragment`.
    """
    if not dpi > 0 or not prescan_dpi > 0:
        raise ValueError(f"dpi and prescan_dpi must be positive, got {dpi} and {prescan_dpi}")
    scan = np.asarray(scan)
    H, W = scan.shape[:2]
    f = max(1.0, dpi / prescan_dpi)
    pre = cv2.resize(np.ascontiguousarray(scan), (max(8, int(round(W / f))), max(8, int(round(H / f)))),
                     interpolation=cv2.INTER_AREA) if f > 1 else scan
    pre_dpi = dpi * pre.shape[1] / W
    x0, y0, x1, y1 = locate_fragment(pre, pre_dpi, margin_mm=margin_mm, **kw)
    p = 25.4 / dpi
    c0, r0 = max(0, int(np.floor(x0 / p))), max(0, int(np.floor(y0 / p)))
    c1, r1 = min(W, int(np.ceil(x1 / p))), min(H, int(np.ceil(y1 / p)))
    return scan[r0:r1, c0:c1], (c0 * p, r0 * p, c1 * p, r1 * p)


def locate_changing(scans: list, dpi: float, *, margin_mm: float = 5.0, prescan_dpi: float = 25.0, k: float = 8.0,
                    min_area_mm2: float = 20.0) -> tuple[float, float, float, float]:
    """The region of a fragment turned between whole-bed scans: where the scans differ (§3.3.4).

    Scans of one face, the fragment turned between them, share everything else: the bed, the lid,
    a frame or jig, rulers, their shadows. Where the scans differ beyond their noise is the
    fragment (its paint and relief turn with it) and its changing shadow, whatever the background
    looks like — where a background estimate fails (a frame of dark bars, a two-coloured lid).
    The per-pixel range of the scans' luminance, reduced to ``prescan_dpi``, is thresholded at
    ``k`` robust standard deviations (median absolute deviation over the image), closed, and the
    largest compact part (with parts within 5 mm) taken; its box plus ``margin_mm`` is returned.

    Parameters
    ----------
    scans : list of (H, W, 3) arrays
        At least 2 whole-bed scans of the same size and resolution.
    dpi : float
    margin_mm : float
    prescan_dpi : float
    k : float
    min_area_mm2 : float
        Smaller changing parts (dust moved by the hand) are ignored.

    Returns
    -------
    (left, top, right, bottom) in mm from the scans' top-left corner.

    Raises
    ------
    ValueError
        Fewer than 2 scans or different sizes.
    NoFragmentError
        Nothing changes between the scans.
    """
    if len(scans) < 2:
        raise ValueError(f"scans must hold at least 2 scans, got {len(scans)}")
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    shape = np.asarray(scans[0]).shape[:2]
    if any(np.asarray(s).shape[:2] != shape for s in scans):
        raise ValueError("scans must all have the same size to find what changes between them")
    H, W = shape
    f = max(1.0, dpi / prescan_dpi)
    size = (max(8, int(round(W / f))), max(8, int(round(H / f))))
    lum = np.stack([to_float(cv2.resize(np.ascontiguousarray(np.asarray(s)[..., :3] if np.asarray(s).ndim == 3 else s),
                                        size, interpolation=cv2.INTER_AREA)).mean(axis=2) for s in scans])
    pixel_mm = 25.4 / dpi * W / size[0]
    rng = lum.max(axis=0) - lum.min(axis=0)
    med = float(np.median(rng))
    mad = float(np.median(np.abs(rng - med))) + 1e-6
    fg = (rng > med + k * 1.4826 * mad).astype(np.uint8)
    r = max(1, int(round(1.0 / pixel_mm)))
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3)))
    fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2))
    labels, n = _group(fg, 5.0 / pixel_mm, int(min_area_mm2 / pixel_mm ** 2))
    if n < 1:
        raise NoFragmentError("the scans do not differ anywhere: no turned fragment found",
                              "The scans are the same everywhere: was the fragment turned between them?")
    areas = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    best = 1 + int(np.argmax(areas))
    ys, xs = np.nonzero(labels == best)
    x0, y0 = xs.min() * pixel_mm - margin_mm, ys.min() * pixel_mm - margin_mm
    x1, y1 = (xs.max() + 1) * pixel_mm + margin_mm, (ys.max() + 1) * pixel_mm + margin_mm
    return (max(0.0, x0), max(0.0, y0), min(W * 25.4 / dpi, x1), min(H * 25.4 / dpi, y1))


def focus_mask(scan: np.ndarray, dpi: float, *, work_mm: float = 0.25, open_mm: float = 1.0) -> np.ndarray:
    """Mask of what lies sharp on the glass in a scan of a fragment's region: its face, not its shadow.

    A flatbed's depth of field is a few tenths of a millimetre (§3.3.1): the fragment's face, which
    rests on the glass, is in focus; the lamp's shadow on the lid, the shade beside a thick piece and
    anything lifted off the glass (the rim of a tilted coin) are blurred. Where the fragment is the
    bed's own grey — a coin on a grey lid — colour cannot separate it from its shadow, but focus can.
    The measure is the share of fine detail in the local contrast, a ratio of band-pass energies
    (a focus measure in the sense of Nayar & Nakagawa 1994): with L the luminance on a copy reduced
    to about ``work_mm`` per pixel and G_s a Gaussian of s mm,

        f = G_0.4 ∗ |L − G_0.5 ∗ L|,  c = G_0.4 ∗ |G_0.5 ∗ L − G_1 ∗ L|,  r = f / (c + median f).

    A blurred edge has c ≫ f, engraving, paint texture and the fragment's own crisp outline have
    f ≳ c. Pixels with r above Otsu's threshold of log r and f above the bed's noise (6 robust
    standard deviations over the median) are in focus; gaps up to ``open_mm`` are closed, holes
    filled, parts thinner than ``open_mm`` opened away and the largest region kept.

    Parameters
    ----------
    scan : (H, W, 3) array
        Region scan (uint8, uint16 or float in [0, 1]), the fragment with a ring of bed around it.
    dpi : float
    work_mm : float
        Working resolution, mm per pixel.
    open_mm : float
        Closing and opening radius, mm.

    Returns
    -------
    (H, W) bool
    """
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    scan = np.asarray(scan)
    H0, W0 = scan.shape[:2]
    f = max(1, int(work_mm / (25.4 / dpi)))
    img = scan if scan.ndim == 2 else scan[..., :3]
    if f > 1:
        img = cv2.resize(np.ascontiguousarray(img), (max(8, W0 // f), max(8, H0 // f)), interpolation=cv2.INTER_AREA)
    lum = to_float(img).mean(axis=2)
    pixel_mm = 25.4 / dpi * W0 / lum.shape[1]
    g1 = cv2.GaussianBlur(lum, (0, 0), 0.5 / pixel_mm)
    g2 = cv2.GaussianBlur(lum, (0, 0), 1.0 / pixel_mm)
    s = 0.4 / pixel_mm
    fine = cv2.GaussianBlur(np.abs(lum - g1), (0, 0), s)
    coarse = cv2.GaussianBlur(np.abs(g1 - g2), (0, 0), s)
    med = float(np.median(fine))
    mad = float(np.median(np.abs(fine - med))) + 1e-7
    lr = np.log(fine / (coarse + med + 1e-7) + 1e-7)
    lo, hi = float(lr.min()), float(lr.max())
    t, _ = cv2.threshold(np.uint8(np.clip((lr - lo) / max(hi - lo, 1e-7) * 255, 0, 255)), 0, 255,
                         cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    fg = ((lr > lo + t / 255 * (hi - lo)) & (fine > med + 6 * 1.4826 * mad)).astype(np.uint8)
    r = max(1, int(round(open_mm / pixel_mm)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)
    fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, disc)
    fg = _fill_holes(fg).astype(np.uint8)
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, disc)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    if n < 2:
        return np.zeros((H0, W0), bool)
    mask = (lab == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.float32)
    if f == 1 and mask.shape == (H0, W0):
        return mask > 0.5
    return cv2.resize(mask, (W0, H0), interpolation=cv2.INTER_LINEAR) > 0.5


def area_spread(masks: list) -> float:
    """Largest over smallest area of a list of masks (1 = all alike; inf when one is empty)."""
    areas = [int(np.count_nonzero(m)) for m in masks]
    return float("inf") if min(areas, default=0) == 0 else max(areas) / min(areas)


def face_masks(scans: list, dpi: float, *, max_spread: float = 1.15) -> tuple[list, str]:
    """Fragment masks of the turned scans of one face, by colour or, where colour fails, by focus.

    A fragment turned on the glass keeps its area, so its masks in the scans of a face must have
    about the same area. The colour mask (:func:`fragment_mask`) is used when they do (largest
    over smallest area at most ``max_spread``); when they do not — an object of the bed's own
    grey, whose colour mask takes its outline plus the lamp's shadow — the focus mask
    (:func:`focus_mask`) is used if its areas agree better.

    Returns
    -------
    masks : list of (H, W) bool
    method : {"colour", "focus"}
    """
    colour = [fragment_mask(s, dpi) for s in scans]
    spread = area_spread(colour)
    if len(scans) < 2 or spread <= max_spread:
        return colour, "colour"
    focus = [focus_mask(s, dpi) for s in scans]
    if area_spread(focus) < spread:
        return focus, "focus"
    return colour, "colour"
