"""Rendering of any size in bounded memory: overlapping tiles that share one exposure.

A recipe is drawn tile by tile. Each tile is read with a *halo* — a margin wide enough for every
filter of the recipe (4 sigma of the widest Gaussian — 3 sigma of exaggerated shading's base
level, whose weight in the picture is small — plus line lengths and widths, shadow lengths) — drawn, and only its core is kept, so neighbouring tiles agree where they meet. Before
the tiles, the recipe is drawn once on a *calibration window* (the centred crop of at most
:data:`CALIBRATION_MPX`, the whole image when it is smaller), and the values its ``"auto"``
parameters take there (exposure, noise scale, gains, thresholds, palette) are imposed on every
tile: without that each tile would pick its own exposure and the seams would show. An image that
fits the calibration window is therefore drawn with exactly the values a whole-image drawing
picks. A recipe with a ``[segmentation]`` section is segmented first, over the whole image but
window by window (:func:`common.rgbn.segmentation.segment_source`: SLIC superpixels per window,
merged across the windows' seams on one graph; 4 bytes a pixel of labels kept), and every tile
(and the calibration window) is drawn with its window of those labels, so a segment is one
segment across tiles.

The output is kept as 8/16-bit integers (the recipe's ``bits``): 200 Mpx of 8-bit RGB + alpha is
800 MB; the input is read window by window from an :class:`RGBNImage` in memory or, for faces
larger than memory, from an HDF5 RGBN artifact (:class:`H5Source`).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Callable

import numpy as np

from common.rgbn.image import RGBNImage

log = logging.getLogger(__name__)

#: Largest tile, halo included, megapixels: about 100-150 bytes a pixel at the heaviest style
#: keeps one tile's work within ~2.5 GB.
TILE_MPX = 16.0
#: Largest calibration window, megapixels.
CALIBRATION_MPX = 4.0


class MemorySource:
    """Windows of an :class:`RGBNImage` held in memory."""

    def __init__(self, image: RGBNImage):
        self.image = image
        self.shape = image.shape
        self.dpi = image.dpi

    def window(self, r0: int, r1: int, c0: int, c1: int) -> RGBNImage:
        """Rows ``r0:r1``, columns ``c0:c1`` (views, not copies); ``attrs["tile_origin"]`` is their
        position in the whole image (the image's own origin added, when it is itself a window)."""
        out = self.image.window(r0, r1, c0, c1)
        o = out.attrs.get("tile_origin", (0, 0))
        out.attrs["tile_origin"] = (int(o[0]) + r0, int(o[1]) + c0)
        return out


class H5Source:
    """Windows of an RGBN artifact read from its (chunked) HDF5 datasets, so that a face larger
    than memory can be drawn: only one tile with its halo is ever in memory."""

    def __init__(self, group):
        from common.rgbn.image import _OPTIONAL

        self.group = group
        self.shape = tuple(group["mask"].shape)
        self.dpi = float(group.attrs["dpi"])
        self._optional = [name for name in _OPTIONAL if name in group]

    def window(self, r0: int, r1: int, c0: int, c1: int) -> RGBNImage:
        g = self.group
        kw = {name: g[name][r0:r1, c0:c1] for name in self._optional}
        return RGBNImage(albedo=g["albedo"][r0:r1, c0:c1], mask=g["mask"][r0:r1, c0:c1], dpi=self.dpi,
                         attrs={"tile_origin": (r0, c0)}, **kw)


def halo_px(recipe, dpi: float, resolved: list | None = None, whole_levels=()) -> int:
    """Margin (pixels) a tile needs so that every layer of ``recipe`` sees all it reads: 4 sigma
    of its widest Gaussian plus its line lengths, widths and shadow lengths (``resolved``: the
    values of "auto" parameters, see :class:`common.render.Layer`). ``whole_levels``: levelling
    scales whose coarse field the tiles are given from the whole image (they need no halo)."""
    from common.render.recipes import _LAYER_KEYS

    mm = dpi / 25.4
    reach = 0.0
    pre = recipe.preprocess or {}
    reach += 4.0 * float(pre.get("smooth_mm", 0.0)) * mm
    if pre.get("bilateral"):
        reach += 3.0 * float(dict(pre["bilateral"]).get("sigma_x", 3.0)) + 2
    worst = 0.0
    for i, layer in enumerate(recipe.layers):
        from common.render.recipes import STYLES

        params = dict(STYLES[layer["style"]].parameters())
        params.update({k: v for k, v in layer.items() if k not in _LAYER_KEYS})
        if resolved is not None and i < len(resolved):
            params.update(resolved[i])
        num = {k: float(v) for k, v in params.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        sigma = max([v for k, v in num.items() if k.startswith("sigma") and k.endswith("_px")] + [0.0])
        sigma = max([sigma] + [v * mm for k, v in num.items() if k.startswith("sigma") and k.endswith("_mm")])
        level = num.get("level", 0.0)
        sigma = max(sigma, num.get("sigma_x", 0.0), num.get("fine_px", 0.0),
                    0.0 if level in whole_levels else level)
        style = layer["style"]
        reach_sigmas = 4.0
        if style == "exaggerated":
            sigma = num.get("sigma0_px", 2.0) * num.get("sigma_ratio", 2.0) ** num.get("scales", 6)
            # its widest Gaussian is the base lighting's, weighted base_weight / (1 + base_weight)
            # / 2 <= 0.115 in the picture: beyond 3 sigma lies 0.135 % of the kernel, which moves
            # the base normal by <= 0.0027 and the picture by <= 10 x 0.0027 x 0.115 = 0.0031 <
            # 1/255 even at the default contrast 10 (test_tiles: 6 scales tiled == whole)
            reach_sigmas = 3.0
        elif style == "multiscale_mean_curvature":
            sigma = num.get("sigma0_mm", 0.1) * mm * num.get("sigma_ratio", 2.0) ** (num.get("scales", 5) - 1)
        elif style in ("colour_relief", "normal_unsharp"):
            sigma = max(sigma, num.get("sigma_mm", 1.0) * mm, 2.0 * num.get("fine_px", 0.0) + 1.0)
        extra = sum(num.get(k, 0.0) for k in ("width_px", "min_length_px", "length_px", "radius_px", "edge_px"))
        if style == "watercolour":
            extra += 3 * 2.0 + 2  # edge darkening blur and gradient
        worst = max(worst, reach_sigmas * sigma + extra + 4.0)
    return int(np.ceil(reach + worst))


def needs_tiles(image: RGBNImage, recipe, tile: int | None = None) -> bool:
    """Whether :func:`common.render.render` should draw ``image`` in tiles."""
    h, w = image.shape
    if tile is not None:
        return max(h, w) > tile
    return h * w > TILE_MPX * 1e6


def calibration_window(shape: tuple[int, int], mpx: float = CALIBRATION_MPX) -> tuple[int, int, int, int]:
    """The centred crop ``(r0, r1, c0, c1)`` of at most ``mpx`` megapixels of an image of ``shape``
    (the whole image when it is smaller), on which "auto" values are chosen for a large image."""
    h, w = int(shape[0]), int(shape[1])
    side_h = min(h, int(np.sqrt(mpx * 1e6 * h / w)))
    side_w = min(w, int(mpx * 1e6 / max(side_h, 1)))
    r0, c0 = (h - side_h) // 2, (w - side_w) // 2
    return r0, r0 + side_h, c0, c0 + side_w


def shown_windows(shown: np.ndarray, margin: int, *, block: int = 32, band: int = 256) -> list:
    """Windows that together hold every True pixel of ``shown`` ((H, W) bool) with ``margin``
    pixels around it: ``[(core, window)]``, each ``(r0, r1, c0, c1)``. The image is cut into
    bands of rows (``band`` px, at least 4 margins) and each band's ``block`` x ``block`` px
    blocks holding a True pixel into runs of columns (a gap of more than two margins splits a
    run); a core is the bounding box of one run's blocks, its window the core grown by
    ``margin``, both clipped to the image. None True: no windows."""
    shown = np.asarray(shown, bool)
    h, w = shown.shape
    hb, wb = -(-h // block), -(-w // block)
    padded = np.zeros((hb * block, wb * block), bool)
    padded[:h, :w] = shown
    blocks = padded.reshape(hb, block, wb * block).any(axis=1).reshape(hb, wb, block).any(axis=2)
    del padded
    rows_per_band = -(-max(band, 4 * margin) // block)
    gap = -(-2 * margin // block) + 1   # blocks apart whose windows would not meet
    out = []
    for i0 in range(0, hb, rows_per_band):
        part = blocks[i0:i0 + rows_per_band]
        cols = np.flatnonzero(part.any(axis=0))
        for run in np.split(cols, np.flatnonzero(np.diff(cols) > gap) + 1) if cols.size else []:
            j0, j1 = int(run[0]), int(run[-1]) + 1
            rows = np.flatnonzero(part[:, j0:j1].any(axis=1))
            r0, r1 = (i0 + int(rows[0])) * block, min(h, (i0 + int(rows[-1]) + 1) * block)
            c0, c1 = j0 * block, min(w, j1 * block)
            out.append(((r0, r1, c0, c1), (max(0, r0 - margin), min(h, r1 + margin),
                                           max(0, c0 - margin), min(w, c1 + margin))))
    return out


def _spans(length: int, core: int) -> list[tuple[int, int]]:
    n = max(1, int(np.ceil(length / core)))
    edges = np.linspace(0, length, n + 1).round().astype(int)
    return list(zip(edges[:-1], edges[1:]))


def render_tiled(source, recipe, *, tile: int | None = None, progress: Callable[[float, str], None] | None = None,
                 calibration_mpx: float = CALIBRATION_MPX):
    """Draw ``source`` (an :class:`RGBNImage`, :class:`MemorySource` or :class:`H5Source`) with a
    recipe in overlapping tiles; see the module docstring.

    Parameters
    ----------
    source : RGBNImage or a window source
    recipe : Recipe or str
    tile : int, optional
        Side of a tile's core, pixels; None chooses it so a tile with its halo stays within
        :data:`TILE_MPX`.
    calibration_mpx : float
        Size of the calibration window, megapixels.

    Returns
    -------
    Rendering
        ``rgb`` (H, W, 3) and ``alpha`` (H, W) as uint8 / uint16 (the recipe's ``bits``); ``skipped``, the
        styles left out for want of normals, is not logged here (the caller says it once, for the image).
    """
    from common.render._heap import reuse_freed_memory
    from common.render.recipes import STYLES, Rendering, _render_whole, layers_without, load_recipe, style_recipe

    if isinstance(recipe, str):
        recipe = style_recipe(recipe) if recipe in STYLES else load_recipe(recipe)
    if isinstance(source, RGBNImage):
        source = MemorySource(source)
    h, w = source.shape
    labels = None
    if recipe.segmentation is not None and any(
            "segments" in layer or "exclude_segments" in layer or "segments" in STYLES[layer["style"]].needs
            for layer in recipe.layers):
        from common.rgbn.segmentation import segment_source

        if progress:
            progress(0.0, f"segmenting {w}x{h} px")
        with reuse_freed_memory():
            labels = segment_source(source, **recipe.segmentation)
    cut = lambda r0, r1, c0, c1: None if labels is None else labels[r0:r1, c0:c1]  # noqa: E731
    # 1. calibration on the centred window
    r0, r1, c0, c1 = calibration_window((h, w), calibration_mpx)
    side_h, side_w = r1 - r0, c1 - c0
    if progress:
        progress(0.0, f"calibrating exposure on {side_w}x{side_h} px")
    # the calibration drawing hands its heap back when it ends (the tiles below share one heap)
    with reuse_freed_memory():
        calib = _render_whole(source.window(r0, r1, c0, c1), recipe, None, None, cut(r0, r1, c0, c1))
    resolved = calib.resolved
    skipped = calib.skipped
    del calib
    layers_drawn = layers_without(recipe.layers, skipped)
    drawn_recipe = replace(recipe, layers=layers_drawn) if skipped else recipe
    log.info("exposure and scales from the %dx%d calibration window: %s", side_w, side_h, resolved)
    # 2. the coarse normal fields that levelling lights the surface by, for the whole image at
    # once (a few thousand cells): a tile gets its window of them, so their 4-sigma reach (384 px
    # at the usual 96 px) is not drawn again around every tile, and tiles and a whole drawing agree
    # (not after a [preprocess], which changes the normals tile by tile)
    whole = {}
    for r in ([] if drawn_recipe.preprocess else resolved):
        sigma = r.get("level")
        if isinstance(sigma, (int, float)) and sigma > 0 and float(sigma) not in whole:
            from common.render.enhance import whole_coarse_normals

            field = whole_coarse_normals(source, float(sigma))
            if field is not None:
                whole[float(sigma)] = field
    # 3. tiles
    halo = halo_px(drawn_recipe, source.dpi, resolved, whole_levels=set(whole))
    if tile is None:
        tile = max(256, int(np.sqrt(TILE_MPX * 1e6)) - 2 * halo)
    bits = recipe.bits
    dtype = np.uint8 if bits == 8 else np.uint16
    rgb = np.empty((h, w, 3), dtype)
    alpha = np.empty((h, w), dtype)
    spans = [(rs, cs) for rs in _spans(h, tile) for cs in _spans(w, tile)]
    log.info("drawing %dx%d px in %d tiles (core <= %d px, halo %d px)", w, h, len(spans), tile, halo)
    from common.render.enhance import coarse_window

    # the tiles, one after the other, reuse each other's freed arrays (_heap, none trimmed between
    # them): a tile's arrays have the sizes of the one before, so the heap stays about one tile's
    # drawing, and the next tile is not page-faulted in afresh (at 51 Mpx a quarter of the CPU time
    # was the kernel's, mapping and zeroing each tile's memory again)
    with reuse_freed_memory():
        for i, ((a, b), (c, d)) in enumerate(spans):
            if progress:
                progress(0.05 + 0.95 * i / len(spans), f"tile {i + 1}/{len(spans)}")
            ra, rb, ca, cb = max(0, a - halo), min(h, b + halo), max(0, c - halo), min(w, d + halo)
            seeds = {sigma: coarse_window(field, ra, rb, ca, cb) for sigma, field in whole.items()}
            part = _render_whole(source.window(ra, rb, ca, cb), drawn_recipe, None, resolved, cut(ra, rb, ca, cb),
                                 seeds, core=(a - ra, b - ra, c - ca, d - ca))
            core = (slice(a - ra, b - ra), slice(c - ca, d - ca))
            rgb[a:b, c:d] = _quantized(part.rgb[core], bits)
            alpha[a:b, c:d] = _quantized(part.alpha[core], bits)
            del part
    if progress:
        progress(1.0, "done")
    return Rendering(rgb, alpha, recipe, skipped, resolved)


def _quantized(values: np.ndarray, bits: int) -> np.ndarray:
    """Values in [0, 1] (a drawing: :func:`common.render.recipes.render` clips its colour and
    coverage) as ``bits``-bit integers, rounded to nearest (half to even), clipped: for 8 bits in
    one pass of OpenCV's ``convertScaleAbs`` (7x numpy's clip, scale, round and cast; the same
    integers), for 16 bits by numpy."""
    if bits == 8:
        import cv2

        return cv2.convertScaleAbs(np.ascontiguousarray(values), alpha=255.0)
    return np.round(np.clip(values, 0.0, 1.0) * np.float32(65535.0)).astype(np.uint16)


def render_h5(group, recipe, *, progress: Callable[[float, str], None] | None = None):
    """Draw an RGBN image stored in an open HDF5 group (an artifact): read whole when it is small,
    else window by window (:class:`H5Source`), so a face larger than memory draws within the tile
    budget (a recipe that segments keeps 4 bytes a pixel of labels besides).
    Returns ``(Rendering, dpi)``. Styles skipped for want of normals are listed in ``Rendering.skipped``,
    not logged: the caller reports them, naming the face (the renderer service)."""
    from common.render.recipes import STYLES, load_recipe, render, style_recipe
    from common.rgbn.image import read_rgbn

    if isinstance(recipe, str):
        recipe = style_recipe(recipe) if recipe in STYLES else load_recipe(recipe)
    for name in ("albedo", "mask"):   # the same refusal read_rgbn gives, before a shape is asked for
        if name not in group:
            from common.store import ArtifactError
            raise ArtifactError(f"RGBN data in {group.file.filename} lacks '{name}'")
    h, w = group["mask"].shape
    if h * w > TILE_MPX * 1e6:
        source = H5Source(group)
        return render_tiled(source, recipe, progress=progress), source.dpi
    image = read_rgbn(group)
    return render(image, recipe, progress=progress, warn_skipped=False), image.dpi
