"""Image pyramids of a face cut once into 256-pixel PNG tiles and cached on storage.

What deep-zoom viewers (OpenSeadragon), IIIF clients and WebGL relighting (Relight/openlime-style
normal maps) read. Each source artifact gets one pyramid:

* a ``tessera.rgbn`` face gives the layers ``albedo`` (display sRGB, 8-bit RGBA, alpha = the
  fragment's coverage) and, when it has normals, ``normals`` (8-bit RGBA, ``R, G, B =
  round((n + 1) / 2 * 255)``, **OpenGL convention**: x right, y up — green grows towards the top
  row —, z towards the viewer; RGB = 128 off the fragment, which decodes to the zero vector, "no
  normal", as Relight/openlime read normal maps; alpha = coverage);
* a ``tessera.render`` illustration gives the layer ``render`` (its display values, 8-bit RGBA,
  alpha = the render's alpha).

Level 0 is the image at full resolution; level ``L`` is it area-averaged over ``2**L x 2**L``
cells (partial cells at the right and bottom edges average the pixels they hold), down to the
first level that fits one tile. The average is weighted by the mask (pixels off the fragment do
not darken its border), colour is averaged in linear reflectance before the sRGB encoding, and
normals are averaged then renormalised; where the coverage is 0, RGB is 0 (normals: 128).

The face is read band by band (:data:`TILE_PX` rows of level 0 at a time) and every level is
built from the one below as the bands stream through, so memory stays at about two bands of
eight float32 channels whatever the size of the face (a 50 Mpx face of width 8000 px: ~130 MB),
and the face is read once.

Cache: ``fragments/<id>/tiles/<kind>-<source stem>-t<TILES_VERSION>/`` (``kind`` = ``rgbn`` or
``render``; the stem ``<face>-<key>`` is the source artifact's content key, and artifacts are
immutable, so a new solve or render gets a new folder and an old one is never wrong), holding
``<layer>/<level>/<col>_<row>.png`` and ``pyramid.json``. Each file is written with the store's
atomic write (temporary name, fsync, rename); ``pyramid.json`` is written last and marks the
pyramid complete — a folder without it is an interrupted cut and is cut again (same bytes).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import threading
import time
from pathlib import Path, PurePosixPath
from typing import Callable, Iterator

import cv2
import numpy as np

from common.rgbn.io import linear_to_srgb
from common.store import ArtifactError, Store, write_file

log = logging.getLogger("tessera.web")

#: Side of a tile, pixels.
TILE_PX = 256
#: Version of the pyramid's layout and formulas (part of the cache folder's name).
TILES_VERSION = 1
#: Layers a pyramid may hold.
LAYERS = ("albedo", "normals", "render")
#: How each layer encodes its pixels (also in ``pyramid.json``).
ENCODING = {
    "albedo": "8-bit RGBA PNG: display sRGB of the area-averaged linear reflectance; alpha = coverage of the fragment",
    "normals": "8-bit RGBA PNG, OpenGL convention: RGB = round((n + 1) / 2 * 255), x right, y up (green grows towards "
               "the top row), z towards the viewer; area-averaged normals renormalised; off the fragment RGB = 128 "
               "(decodes to the zero vector: 'no normal', as openlime's BRDF shader reads it); alpha = coverage of the "
               "fragment",
    "render": "8-bit RGBA PNG: the illustration's display values area-averaged over its alpha; alpha = the render's alpha",
}


# --------------------------------------------------------------------------------------------
# the algorithm
# --------------------------------------------------------------------------------------------
def pyramid_levels(height: int, width: int, tile_px: int = TILE_PX, top_px: int | None = None) -> list[tuple[int, int]]:
    """Sizes ``(height, width)`` of the levels of a pyramid, level 0 (full resolution) first.

    Level ``L + 1`` is level ``L`` halved, rounding up, down to the first level whose sides both
    fit in ``top_px`` pixels (default: one ``tile_px`` tile).

    Examples
    --------
    >>> pyramid_levels(600, 1000)
    [(600, 1000), (300, 500), (150, 250)]
    >>> pyramid_levels(600, 1000, top_px=64)
    [(600, 1000), (300, 500), (150, 250), (75, 125), (38, 63)]
    """
    if int(height) < 1 or int(width) < 1:
        raise ValueError(f"height and width must be >= 1 pixel, got {height} x {width}")
    if int(tile_px) < 1:
        raise ValueError(f"tile_px must be >= 1, got {tile_px}")
    top = int(tile_px if top_px is None else top_px)
    if not 1 <= top <= int(tile_px):
        raise ValueError(f"top_px must be in [1, tile_px = {tile_px}], got {top_px}")
    h, w = int(height), int(width)
    levels = [(h, w)]
    while h > top or w > top:
        h, w = -(-h // 2), -(-w // 2)
        levels.append((h, w))
    return levels


def halve_sums(sums: np.ndarray) -> np.ndarray:
    """Sum-pool an ``(H, W, C)`` array over 2 x 2 cells (zero-padded to even sides).

    The pyramid carries sums, not means (weighted values, weights and pixel counts), so every
    level is an exact area average of level 0 however the cells are grouped.
    """
    s = np.asarray(sums, dtype=np.float32)
    if s.ndim != 3:
        raise ValueError(f"sums must be (H, W, C), got shape {s.shape}")
    ph, pw = s.shape[0] % 2, s.shape[1] % 2
    if ph or pw:
        s = np.pad(s, ((0, ph), (0, pw), (0, 0)))
    h, w, c = s.shape
    return s.reshape(h // 2, 2, w // 2, 2, c).sum(axis=(1, 3), dtype=np.float32)


def weighted_sums(values: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The level-0 sums of a band: ``values * weight`` (k channels), ``weight``, and a pixel count of 1."""
    v = np.asarray(values, dtype=np.float32)
    m = np.asarray(weight, dtype=np.float32)
    if v.ndim == 2:
        v = v[..., None]
    if v.shape[:2] != m.shape:
        raise ValueError(f"values {v.shape[:2]} and weight {m.shape} must have the same rows and columns")
    out = np.empty(v.shape[:2] + (v.shape[2] + 2,), np.float32)
    np.multiply(v, m[..., None], out=out[..., :-2])
    out[..., -2] = m
    out[..., -1] = 1.0
    return out


def encode_tile(sums: np.ndarray, layer: str, *, offset: int = 0) -> np.ndarray:
    """The 8-bit RGBA pixels of a layer from pyramid sums (see the module docstring).

    Parameters
    ----------
    sums : (h, w, C) float32
        Sums of a level's cells; channels ``offset:offset + 3`` are the layer's weighted values,
        ``C - 2`` the weight, ``C - 1`` the pixel count.
    layer : {"albedo", "normals", "render"}
    offset : int
        First channel of the layer's weighted values.

    Returns
    -------
    (h, w, 4) uint8
        RGBA, RGB as in :data:`ENCODING`, A = round(255 * weight / count).
    """
    if layer not in LAYERS:
        raise ValueError(f"layer must be one of {LAYERS}, got {layer!r}")
    weight, count = sums[..., -2], sums[..., -1]
    vals = sums[..., offset:offset + 3]
    on = weight > 0
    out = np.zeros(sums.shape[:2] + (4,), np.uint8)
    if layer == "normals":
        length = np.linalg.norm(vals, axis=2)
        on &= length > 1e-12
        n = vals / np.maximum(length, 1e-12)[..., None]
        rgb = (n + 1.0) * 0.5
    else:
        rgb = vals / np.maximum(weight, 1e-12)[..., None]
        if layer == "albedo":
            rgb = linear_to_srgb(rgb)
    off = 128 if layer == "normals" else 0   # a normal map's "no normal" is (0.5, 0.5, 0.5): 2c - 1 = 0
    out[..., :3] = np.where(on[..., None], np.round(np.clip(rgb, 0.0, 1.0) * 255.0), off).astype(np.uint8)
    out[..., 3] = np.round(np.clip(weight / np.maximum(count, 1e-12), 0.0, 1.0) * 255.0).astype(np.uint8)
    return out


def encode_png(rgba: np.ndarray) -> bytes:
    """PNG bytes of an RGBA (or RGB) uint8/uint16 image (channel order RGB(A))."""
    code = cv2.COLOR_RGBA2BGRA if rgba.shape[2] == 4 else cv2.COLOR_RGB2BGR
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgba), code))
    if not ok:
        raise ValueError(f"could not encode a {rgba.shape} {rgba.dtype} image as PNG")
    return buf.tobytes()


def decode_png(data: bytes) -> np.ndarray:
    """RGBA uint8 pixels of PNG bytes written by :func:`encode_png`."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 3:
        raise ValueError("not an RGB(A) PNG tile")
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA if img.shape[2] == 4 else cv2.COLOR_BGR2RGBA)


def cut_pyramid(bands: Iterator[np.ndarray], height: int, width: int, layers: dict[str, int],
                put: Callable[[str, int, int, int, np.ndarray], None], *, tile_px: int = TILE_PX,
                progress: Callable[[int], None] | None = None) -> list[tuple[int, int]]:
    """Cut a pyramid from level-0 bands of sums streamed top to bottom.

    Parameters
    ----------
    bands : iterator of (rows, width, C) float32
        :func:`weighted_sums` of consecutive bands of level 0, top to bottom, ``tile_px`` rows each
        (the last may be shorter).
    height, width : int
        Size of level 0, pixels.
    layers : dict
        ``{layer: offset}``: the layers to encode and where their values start in the sums.
    put : callable
        ``put(layer, level, col, row, rgba)`` receives every tile (:func:`encode_tile`'s pixels).
    tile_px : int
    progress : callable, optional
        Called with the number of level-0 rows done after each band.

    Returns
    -------
    list of (height, width)
        :func:`pyramid_levels`.
    """
    levels = pyramid_levels(height, width, tile_px)
    pending: list[list[np.ndarray]] = [[] for _ in levels]   # rows of each level not cut yet
    done = [0] * len(levels)                                  # rows of each level cut so far

    def cut(level: int, band: np.ndarray) -> None:
        row = done[level] // tile_px
        for col in range(-(-band.shape[1] // tile_px)):
            core = band[:, col * tile_px:(col + 1) * tile_px]
            for layer, offset in layers.items():
                put(layer, level, col, row, encode_tile(core, layer, offset=offset))
        done[level] += band.shape[0]
        if level + 1 < len(levels):
            feed(level + 1, halve_sums(band))

    def feed(level: int, rows: np.ndarray) -> None:
        pending[level].append(rows)
        have = sum(r.shape[0] for r in pending[level])
        while have >= tile_px:
            block = np.concatenate(pending[level], axis=0) if len(pending[level]) > 1 else pending[level][0]
            pending[level] = [block[tile_px:]] if block.shape[0] > tile_px else []
            have -= tile_px
            cut(level, block[:tile_px])

    seen = 0
    for band in bands:
        if band.ndim != 3 or band.shape[1] != width:
            raise ValueError(f"bands must be (rows, {width}, C), got {band.shape}")
        seen += band.shape[0]
        feed(0, band)
        if progress is not None:
            progress(seen)
    if seen != height:
        raise ValueError(f"the bands held {seen} rows, expected {height}")
    for level in range(len(levels)):   # the last, shorter band of each level, top level last
        if pending[level]:
            block = np.concatenate(pending[level], axis=0)
            pending[level] = []
            cut(level, block)
    for level, (h, _) in enumerate(levels):
        if done[level] != h:
            raise AssertionError(f"level {level}: cut {done[level]} rows of {h}")
    return levels


def read_region(tile: Callable[[int, int], np.ndarray | None], level_size: tuple[int, int],
                y0: int, y1: int, x0: int, x1: int, *, tile_px: int = TILE_PX) -> np.ndarray:
    """Pixels ``[y0:y1, x0:x1]`` of one level assembled from its tiles.

    ``tile(col, row)`` returns the RGBA tile (or None: transparent). Returns ``(y1 - y0, x1 - x0, 4)`` uint8.
    """
    h, w = level_size
    if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
        raise ValueError(f"region rows {y0}:{y1}, columns {x0}:{x1} is not inside the {w} x {h} level")
    out = np.zeros((y1 - y0, x1 - x0, 4), np.uint8)
    for row in range(y0 // tile_px, (y1 - 1) // tile_px + 1):
        for col in range(x0 // tile_px, (x1 - 1) // tile_px + 1):
            t = tile(col, row)
            if t is None:
                continue
            ty, tx = row * tile_px, col * tile_px
            a0, a1 = max(y0, ty), min(y1, ty + t.shape[0])
            b0, b1 = max(x0, tx), min(x1, tx + t.shape[1])
            out[a0 - y0:a1 - y0, b0 - x0:b1 - x0] = t[a0 - ty:a1 - ty, b0 - tx:b1 - tx]
    return out


# --------------------------------------------------------------------------------------------
# the cache on storage
# --------------------------------------------------------------------------------------------
def _put_file(store: Store, relpath: str, data: bytes) -> None:
    write_file(store.path(relpath), data)


def pyramid_folder(source_relpath: str) -> str:
    """Cache folder of the pyramid of ``fragments/<id>/(rgbn|renders)/<face>-<key>.h5``."""
    p = PurePosixPath(source_relpath)
    if len(p.parts) != 4 or p.parts[0] != "fragments" or p.parts[2] not in ("rgbn", "renders") or p.suffix != ".h5":
        raise ValueError(f"not an RGBN or render artifact path: {source_relpath!r}")
    kind = "rgbn" if p.parts[2] == "rgbn" else "render"
    return f"fragments/{p.parts[1]}/tiles/{kind}-{p.stem}-t{TILES_VERSION}"


def _bands(f, names: list[str], weight: str, scale: float, scaled_weight: bool, band_px: int):
    h = f[weight].shape[0]
    for r0 in range(0, h, band_px):
        r1 = min(r0 + band_px, h)
        vals = np.concatenate([f[n][r0:r1].astype(np.float32) / scale for n in names], axis=2)
        w = f[weight][r0:r1].astype(np.float32)
        if scaled_weight:
            w /= scale
        yield weighted_sums(vals, w)


def cut_source(store: Store, source_relpath: str, *, tile_px: int = TILE_PX,
               progress: Callable[[int, int], None] | None = None) -> dict:
    """Cut the pyramid of an RGBN face or a render artifact into its cache folder; return its
    ``pyramid.json`` (written last). An existing complete pyramid is returned as it is.

    ``progress(rows_done, rows)`` is called after each band of level 0.
    """
    from common.render.artifact import SCHEMA as RENDER, SCHEMA_VERSION as RENDER_VERSION
    from common.rgbn.image import SCHEMA as RGBN, SCHEMA_VERSION as RGBN_VERSION

    folder = pyramid_folder(source_relpath)
    info_path = store.path(f"{folder}/pyramid.json")
    if info_path.is_file():
        return json.loads(info_path.read_text())
    t0, c0 = time.perf_counter(), time.process_time()
    ref = store.ref(source_relpath)
    kind = folder.rsplit("/", 1)[1].split("-", 1)[0]
    with store.open(ref, schema=RGBN if kind == "rgbn" else RENDER,
                    version=RGBN_VERSION if kind == "rgbn" else RENDER_VERSION) as f:
        try:
            if kind == "rgbn":
                names = ["albedo"] + (["normals"] if "normals" in f else [])
                layers = {"albedo": 0, **({"normals": 3} if "normals" in f else {})}
                weight, scale, dpi = "mask", 1.0, float(f.attrs["dpi"])
                meta = f.attrs.get("metadata", "")
            else:
                names, layers, weight = ["image"], {"render": 0}, "alpha"
                scale, dpi, meta = (255.0 if int(f.attrs["bits"]) == 8 else 65535.0), float(f.attrs["dpi"]), ""
            height, width = f[weight].shape
        except KeyError as exc:
            raise ArtifactError(f"artifact {source_relpath} lacks {exc}") from exc
        written = []

        def put(layer, level, col, row, rgba):
            rel = f"{folder}/{layer}/{level}/{col}_{row}.png"
            _put_file(store, rel, encode_png(rgba))
            written.append(rel)

        levels = cut_pyramid(_bands(f, names, weight, scale, kind == "render", tile_px), height, width, layers, put,
                             tile_px=tile_px, progress=None if progress is None else lambda r: progress(r, height))
    info = {
        "version": TILES_VERSION, "source": ref.to_dict(), "kind": kind, "tile_px": tile_px,
        "format": "png", "layers": {name: ENCODING[name] for name in layers},
        "levels": [{"level": i, "width": w, "height": h, "cols": -(-w // tile_px), "rows": -(-h // tile_px)}
                   for i, (h, w) in enumerate(levels)],
        "width": width, "height": height, "dpi": dpi, "pixel_mm": 25.4 / dpi,
        "tile_path": "{layer}/{level}/{col}_{row}.png", "level_0": "full resolution; level L is 2**L times smaller",
        "metadata": json.loads(meta) if isinstance(meta, (str, bytes)) and meta else {},
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(), "tiles": len(written),
        "cut_s": {"wall": round(time.perf_counter() - t0, 3), "cpu": round(time.process_time() - c0, 3)},
    }
    _put_file(store, f"{folder}/pyramid.json", json.dumps(info, indent=1, sort_keys=True).encode())
    return info


class TileCache:
    """The pyramids of a storage root, cut on first use (once per source, one cut at a time per
    source in this process) and read from storage afterwards.

    Parameters
    ----------
    store : common.store.Store
    tile_px : int
        Side of the tiles of the pyramids it cuts (a pyramid on storage keeps its own, in
        ``pyramid.json``).
    """

    def __init__(self, store: Store, tile_px: int = TILE_PX):
        self.store = store
        self.tile_px = int(tile_px)
        self._locks: dict[str, threading.Lock] = {}
        self._guard = threading.Lock()

    def pyramid(self, source_relpath: str) -> dict:
        """``pyramid.json`` of a source artifact, cutting the pyramid first if needed."""
        folder = pyramid_folder(source_relpath)
        path = self.store.path(f"{folder}/pyramid.json")
        if path.is_file():
            return json.loads(path.read_text())
        with self._guard:
            lock = self._locks.setdefault(folder, threading.Lock())
        with lock:
            return cut_source(self.store, source_relpath, tile_px=self.tile_px)

    def tile_path(self, source_relpath: str, layer: str, level: int, col: int, row: int) -> Path:
        """Path of one tile on storage (the pyramid is cut first if needed).

        Raises LookupError naming what is outside the pyramid (layer, level, column or row).
        """
        info = self.pyramid(source_relpath)
        if layer not in info["layers"]:
            raise LookupError(f"no layer {layer!r} here (layers: {', '.join(info['layers'])})")
        if not 0 <= level < len(info["levels"]):
            raise LookupError(f"level must be 0..{len(info['levels']) - 1}, got {level}")
        lv = info["levels"][level]
        if not (0 <= col < lv["cols"] and 0 <= row < lv["rows"]):
            raise LookupError(f"tile {col}_{row} is outside level {level} ({lv['cols']} x {lv['rows']} tiles)")
        return self.store.path(f"{pyramid_folder(source_relpath)}/{layer}/{level}/{col}_{row}.png")

    def region(self, source_relpath: str, layer: str, level: int, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        """RGBA pixels ``[y0:y1, x0:x1]`` of a level (:func:`read_region` over the cached tiles)."""
        info = self.pyramid(source_relpath)
        lv = info["levels"][level]

        def tile(col, row):
            return decode_png(self.tile_path(source_relpath, layer, level, col, row).read_bytes())

        return read_region(tile, (lv["height"], lv["width"]), y0, y1, x0, x1, tile_px=info["tile_px"])


def face_sources(store: Store, fragment: str) -> dict[str, dict]:
    """``{face: {"rgbn": relpath, "normals": bool, "renders": {recipe: relpath}}}`` — the newest RGBN
    artifact of each face (:func:`common.imports.export.latest_faces`), whether it has normals (a
    colour-only face, an imported picture, has none: no ``normals`` layer), and the renders made from it.

    Each file is opened with its schema and the highest version this reader understands: a face it cannot
    read (not HDF5, not an RGBN image, written by a newer Tessera) is listed without normals, a render it
    cannot read is left out, and the log says why."""
    from common.imports.export import latest_faces
    from common.render.artifact import SCHEMA as RENDER, SCHEMA_VERSION as RENDER_VERSION
    from common.rgbn.image import SCHEMA as RGBN, SCHEMA_VERSION as RGBN_VERSION

    out: dict[str, dict] = {}
    renders = store.path(f"fragments/{fragment}/renders")
    for face, rel in latest_faces(store, fragment).items():
        try:
            with store.open(rel, schema=RGBN, version=RGBN_VERSION) as f:
                normals = "normals" in f
        except (ArtifactError, OSError) as exc:   # unreadable: listed as it is, its pyramid request says what is wrong
            log.warning("tiles: face %s listed without normals: %s", rel, exc)
            normals = False
        entry = {"rgbn": rel, "normals": normals, "renders": {}}
        for rp in sorted(renders.glob(f"{face}-*.h5")) if renders.is_dir() else []:
            rrel = rp.relative_to(store.root).as_posix()
            try:
                with store.open(rrel, schema=RENDER, version=RENDER_VERSION) as f:
                    inputs = json.loads(f.attrs.get("provenance", "{}")).get("inputs") or [{}]
                    recipe = f.attrs.get("recipe", "render")
            except (ArtifactError, OSError, ValueError) as exc:
                log.warning("tiles: render %s of face %s not offered: %s", rrel, rel, exc)
                continue
            recipe = recipe.decode() if isinstance(recipe, bytes) else str(recipe)
            if inputs[0].get("path") not in (None, rel):
                continue   # a render of an older solve of this face
            entry["renders"][recipe] = rrel
        out[face] = entry
    return out


def face_thumbnail(store: Store, rgbn_relpath: str, max_px: int = 128) -> np.ndarray:
    """The albedo of an RGBN face area-averaged to at most ``max_px`` on its longest side.

    The top level of a pyramid with ``max_px`` tiles, computed the same way (band by band, bounded
    memory) without writing any tile. Returns ``(h, w, 4)`` uint8 RGBA (display sRGB, alpha = coverage).
    """
    from common.rgbn.image import SCHEMA as RGBN, SCHEMA_VERSION as RGBN_VERSION

    if int(max_px) < 1:
        raise ValueError(f"max_px must be >= 1, got {max_px}")
    top: dict[str, np.ndarray] = {}
    with store.open(rgbn_relpath, schema=RGBN, version=RGBN_VERSION) as f:
        try:
            height, width = f["mask"].shape
            levels = pyramid_levels(height, width, max_px)

            def put(layer, level, col, row, rgba):
                if level == len(levels) - 1:
                    top["rgba"] = rgba

            cut_pyramid(_bands(f, ["albedo"], "mask", 1.0, False, max_px), height, width, {"albedo": 0}, put,
                        tile_px=max_px)
        except KeyError as exc:
            raise ArtifactError(f"artifact {rgbn_relpath} lacks {exc}") from exc
    return top["rgba"]


# --------------------------------------------------------------------------------------------
# Deep Zoom (DZI): what OpenSeadragon and openlime's "deepzoom" layout read
# --------------------------------------------------------------------------------------------
def dzi_xml(info: dict, fmt: str = "png") -> str:
    """The ``.dzi`` descriptor of a pyramid (Deep Zoom: tile size 256, overlap 0)."""
    return ('<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<Image xmlns="http://schemas.microsoft.com/deepzoom/2008" Format="{fmt}" Overlap="0" '
            f'TileSize="{info["tile_px"]}"><Size Width="{info["width"]}" Height="{info["height"]}"/></Image>\n')


def dzi_max_level(width: int, height: int) -> int:
    """Deep Zoom's full-resolution level: ``ceil(log2(max(width, height)))`` (level 0 is 1 x 1)."""
    return int(max(width, height) - 1).bit_length()


def dzi_tile(cache: "TileCache", source_relpath: str, layer: str, dzi_level: int, col: int, row: int) -> np.ndarray:
    """RGBA pixels of Deep Zoom tile ``dzi_level/col_row``: pyramid level ``max - dzi_level``, and
    below the pyramid's top (levels smaller than one tile) the top level area-resampled.

    Raises LookupError outside the image.
    """
    info = cache.pyramid(source_relpath)
    top = dzi_max_level(info["width"], info["height"])
    if not 0 <= dzi_level <= top:
        raise LookupError(f"Deep Zoom level must be 0..{top}, got {dzi_level}")
    level = top - dzi_level
    last = len(info["levels"]) - 1
    if level <= last:
        return decode_png(cache.tile_path(source_relpath, layer, level, col, row).read_bytes())
    if (col, row) != (0, 0):
        raise LookupError(f"Deep Zoom level {dzi_level} has one tile")
    t = decode_png(cache.tile_path(source_relpath, layer, last, 0, 0).read_bytes())
    f = 2 ** (level - last)
    h, w = -(-info["height"] // 2 ** level), -(-info["width"] // 2 ** level)
    return cv2.resize(t, (w, h), interpolation=cv2.INTER_AREA) if (h, w) != t.shape[:2] and f > 1 else t
