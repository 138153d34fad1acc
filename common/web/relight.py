"""The fields a browser needs to relight an RGBN face in WebGL, cut into a tile pyramid.

A relighting shader can only do per-pixel work: everything that needs a neighbourhood (the
Gaussian-smoothed normals of the noise scale, of normal unsharp masking and of every scale of
exaggerated shading; the mean curvature) does not depend on the light, so it is computed here once,
with the same functions as the offline renderer (:func:`common.rgbn.smoothing.smooth_normals`,
:func:`common.rgbn.curvature.mean_curvature`), and the shader does the rest — exactly the
light-dependent part of the offline style's formula (``services/web/static/viewer/*.frag``).

A face is cut into a pyramid of :data:`common.web.tiles.TILE_PX`-pixel tiles with the levels of
the archive's pyramid (:func:`common.web.tiles.pyramid_levels`): level 0 is the face at full
resolution, level ``L`` the face area-averaged over ``2**L`` cells (masked; normals renormalised),
down to a level that fits :data:`TOP_PX` pixels (two levels below one tile: the first picture is a
small download). Unlike the archive's 8-bit albedo / normal-map tiles (cut in
one pass for IIIF and deep zoom), these carry float16 fields, and each tile is computed on its first
request from a level-0 window with its halo (so the first picture of a face does not wait for
all of level 0). A tile's fields are computed on its window plus a halo of 4 sigma of the
widest Gaussian, so neighbouring tiles agree where they meet and a level-0 tile holds exactly what a
whole-image computation gives there. Sigmas are in level-0 pixels and divided by ``2**L`` on level
``L`` (the dpi too), so a zoomed-out view shows the same shading at a coarser grain.

Tile format (one file per tile, ``h x w`` pixels, little-endian, gzip-compressed), in this order:

* ``float16 (3, h, w, 4)``: three RGBA textures of (x, y) pairs of unit normals (z = sqrt(1 - x² - y²),
  x right, y up, z towards the viewer): ``n, n0 | n1, n2 | n3, nu`` — ``n`` the normals as solved,
  ``n_i`` smoothed at ``sigma_px * 2**i`` (``n0`` is the noise scale the lit styles use, ``n0..n3``
  the scales of exaggerated shading), ``nu`` smoothed at normal unsharp masking's ``sigma_mm``;
* ``float16 (h, w)``: mean curvature ``H`` (1/mm, eq. 7.7) of the normals smoothed at
  ``curvature_sigma_px``;
* ``uint8 (h, w, 4)``: the albedo as display sRGB and the mask (255 on the fragment).

The parameters (the noise scale from the face's normals, the sigmas, dpi, the pyramid's sizes)
are chosen once per face on the centred calibration window, as the tiled offline renderer does
(:mod:`common.render.tiles`), and kept in ``params.json`` beside the tiles.
"""

from __future__ import annotations

import gzip
import json
import math
import threading
from pathlib import Path

import cv2
import numpy as np

from common.render.tiles import calibration_window
from common.rgbn.curvature import mean_curvature
from common.rgbn.io import linear_to_srgb
from common.rgbn.smoothing import smooth_normals
from common.web.tiles import TILE_PX, halve_sums, pyramid_levels

#: Scales of exaggerated shading the fields carry (``n0`` .. ``n3``: the viewer's ``scales = 3``).
EXAGGERATED_SCALES = 3
#: Version of the tile format and of the fields' formulas (part of the cache key).
FIELDS_VERSION = 1
#: Channels of the float16 part of a tile, in order.
NORMAL_FIELDS = ("n", "n0", "n1", "n2", "n3", "nu")
#: The pyramid goes on halving until the face fits this many pixels: the top tile, the viewer's
#: first picture, is then ~90 kB instead of ~1.5 MB for a full 256-px tile of float16 fields.
TOP_PX = 64
#: Levels of at most this many megapixels are cut whole by :meth:`RelightCache.cut` (about 0.5 GB
#: of fields and sums at 4 Mpx).
WHOLE_MPX = 4.0
#: Level-0 rows read at a time when a coarse level is area-averaged from the face.
_BAND_PX = 1024


def relight_params(normals: np.ndarray | None, mask: np.ndarray, dpi: float, shape: tuple[int, int], *,
                   unsharp_sigma_mm: float = 1.0) -> dict:
    """The light-independent scales of a face's relighting fields.

    Parameters
    ----------
    normals : (h, w, 3) float or None
        Unit normals of the calibration window (the centred crop of at most
        :data:`common.render.tiles.CALIBRATION_MPX`); None for a colour-only face.
    mask : (h, w) bool
        Its mask.
    dpi : float
        Sampling density of the face.
    shape : (H, W)
        Size of the whole face (level 0), pixels.
    unsharp_sigma_mm : float
        Normal unsharp masking's ``sigma_mm`` (the offline style's default 1 mm).

    Returns
    -------
    dict
        ``sigma_px`` (the noise scale, :func:`common.render.enhance.relief_scale_px`: what the
        offline styles' ``sigma_px = "auto"`` and ``sigma0_px = "auto"`` resolve to),
        ``exaggerated_sigmas_px``, ``unsharp_sigma_mm``, ``unsharp_sigma_px``
        (``max(sigma_mm * dpi / 25.4, 1)`` as :func:`common.render.recipes.draw_normal_unsharp`),
        ``curvature_sigma_mm`` / ``curvature_sigma_px`` (twice the noise scale, as
        :func:`common.render.recipes.draw_mean_curvature`'s "auto"), ``halo_px``, ``dpi``,
        ``width``, ``height``, ``tile_px``, ``levels`` (sizes ``[w, h]`` per level),
        ``has_normals``, ``version``, ``surface_normal`` (the way a near-flat face faces as a whole,
        :func:`common.render.enhance.surface_normal`, x right, y up: the lit styles light it relative to
        that, :func:`offline_arguments`; None for a curved object or a colour-only face).
    """
    from common.render.enhance import relief_scale_px, surface_normal

    if not np.isfinite(dpi) or dpi <= 0:
        raise ValueError(f"dpi must be a positive number, got {dpi}")
    if not unsharp_sigma_mm > 0:
        raise ValueError(f"unsharp_sigma_mm must be > 0, got {unsharp_sigma_mm}")
    h, w = int(shape[0]), int(shape[1])
    if h < 1 or w < 1:
        raise ValueError(f"shape must be positive, got {shape}")
    has_normals = normals is not None
    sigma = relief_scale_px(normals, dpi, mask)[0] if has_normals else 1.0
    facing = surface_normal(normals, mask) if has_normals else None
    ex = [sigma * 2.0 ** i for i in range(EXAGGERATED_SCALES + 1)]
    unsharp = max(unsharp_sigma_mm * dpi / 25.4, 1.0)
    curv = 2.0 * sigma
    # the archive's pyramid (common.web.tiles), continued down to TOP_PX for a small first picture
    levels = [[lw, lh] for lh, lw in pyramid_levels(h, w, TILE_PX, top_px=TOP_PX)]
    return {"version": FIELDS_VERSION, "dpi": float(dpi), "width": w, "height": h, "tile_px": TILE_PX,
            "levels": levels, "has_normals": has_normals,
            "sigma_px": round(float(sigma), 4), "exaggerated_sigmas_px": [round(float(s), 4) for s in ex],
            "unsharp_sigma_mm": float(unsharp_sigma_mm), "unsharp_sigma_px": round(float(unsharp), 4),
            "curvature_sigma_px": round(float(curv), 4), "curvature_sigma_mm": round(float(curv) * 25.4 / dpi, 6),
            "surface_normal": None if facing is None else [round(float(v), 6) for v in facing],
            "halo_px": int(math.ceil(4.0 * max(ex[-1], unsharp, curv))) + 2}


def relight_fields(normals: np.ndarray | None, albedo: np.ndarray, mask: np.ndarray, params: dict, *,
                   level: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The relighting fields of a window of level ``level`` (see the module docstring).

    Parameters
    ----------
    normals : (h, w, 3) float or None
        Unit normals of the window (None: colour-only, every normal (0, 0, 1)).
    albedo : (h, w, 3) float
        Linear albedo in [0, 1].
    mask : (h, w) bool
    params : dict
        :func:`relight_params` of the face.
    level : int
        Pyramid level of the window: sigmas and dpi are divided by ``2**level``.

    Returns
    -------
    normal_xy : (h, w, 12) float32
        The (x, y) of ``n, n0, n1, n2, n3, nu``.
    curvature : (h, w) float32
        Mean curvature H, 1/mm.
    colour : (h, w, 4) uint8
        Display sRGB albedo and the mask (0 / 255).
    """
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    if albedo.shape != (h, w, 3):
        raise ValueError(f"albedo must be {(h, w, 3)}, got {albedo.shape}")
    f = 2.0 ** int(level)
    xy = np.zeros((h, w, 12), np.float32)
    H = np.zeros((h, w), np.float32)
    if normals is not None and params["has_normals"]:
        if normals.shape != (h, w, 3):
            raise ValueError(f"normals must be {(h, w, 3)}, got {normals.shape}")
        normals = np.asarray(normals, np.float32)
        sigmas = [0.0] + [s / f for s in params["exaggerated_sigmas_px"]] + [params["unsharp_sigma_px"] / f]
        for k, s in enumerate(sigmas):
            # below a tenth of a pixel a Gaussian is the identity (coarse levels of small sigmas)
            n = smooth_normals(normals, s, mask=mask) if s >= 0.1 else normals
            xy[..., 2 * k:2 * k + 2] = n[..., :2]
        s = params["curvature_sigma_px"] / f
        H = mean_curvature(normals, params["dpi"] / f, mask=mask, sigma_px=s if s >= 0.1 else 0.0)
    else:
        xy[:] = 0.0
    colour = np.empty((h, w, 4), np.uint8)
    colour[..., :3] = np.round(np.clip(linear_to_srgb(np.clip(albedo, 0.0, 1.0)), 0.0, 1.0) * 255.0)
    colour[..., 3] = np.where(mask, 255, 0)
    return xy, H.astype(np.float32), colour


def pack_tile(normal_xy: np.ndarray, curvature: np.ndarray, colour: np.ndarray) -> bytes:
    """The gzip-compressed bytes of one tile (the format of the module docstring)."""
    h, w = curvature.shape
    planes = np.asarray(normal_xy, np.float32).reshape(h, w, 3, 4).transpose(2, 0, 1, 3)
    body = (np.ascontiguousarray(planes, dtype="<f2").tobytes()
            + np.ascontiguousarray(curvature, dtype="<f2").tobytes()
            + np.ascontiguousarray(colour, dtype=np.uint8).tobytes())
    return gzip.compress(body, compresslevel=3, mtime=0)


def unpack_tile(data: bytes, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`pack_tile` (the reader a test or another tool uses)."""
    raw = gzip.decompress(data)
    n1, n2 = h * w * 12 * 2, h * w * 2
    if len(raw) != n1 + n2 + h * w * 4:
        raise ValueError(f"a {w}x{h} tile has {n1 + n2 + h * w * 4} bytes, got {len(raw)}")
    xy = np.frombuffer(raw[:n1], "<f2").reshape(3, h, w, 4).transpose(1, 2, 0, 3).reshape(h, w, 12).astype(np.float32)
    H = np.frombuffer(raw[n1:n1 + n2], "<f2").reshape(h, w).astype(np.float32)
    colour = np.frombuffer(raw[n1 + n2:], np.uint8).reshape(h, w, 4)
    return xy, H, colour


def read_level_window(group, level: int, r0: int, r1: int, c0: int, c1: int):
    """Albedo, normals (or None) and mask of rows ``r0:r1``, columns ``c0:c1`` of pyramid level
    ``level`` of an RGBN HDF5 group, area-averaged from level 0 band by band (bounded memory).

    The average is masked (pixels off the fragment do not darken its border); normals are
    renormalised; a level pixel is on the fragment when at least half of its area is.
    """
    if int(level) == 0:
        H0, W0 = group["mask"].shape
        r1, c1 = min(r1, H0), min(c1, W0)
        albedo = group["albedo"][r0:r1, c0:c1].astype(np.float32)
        normals = group["normals"][r0:r1, c0:c1].astype(np.float32) if "normals" in group else None
        return albedo, normals, group["mask"][r0:r1, c0:c1].astype(bool)
    return level_from_sums(level_sums(group, level, r0, r1, c0, c1), level, "normals" in group)


#: Channels of the level sums: albedo x mask (3), normals x mask (3), normals (3), mask (1).
_SUMS = 10


def level_sums(group, level: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """``(h, w, 10)`` float32 sums over the ``2**level`` cells of rows ``r0:r1``, columns ``c0:c1`` of
    level ``level`` (>= 1): albedo x mask, normals x mask, normals, mask — read band by band.

    Sums, not means: summing 2 x 2 cells of level L gives level L + 1 exactly
    (:func:`common.web.tiles.halve_sums`), so every level comes from one read of the face."""
    f = 2 ** int(level)
    if f < 2:
        raise ValueError(f"level must be >= 1 for sums, got {level}")
    H0, W0 = group["mask"].shape
    has_n = "normals" in group
    R0, R1, C0, C1 = r0 * f, min(r1 * f, H0), c0 * f, min(c1 * f, W0)
    out = np.zeros((r1 - r0, c1 - c0, _SUMS), np.float32)
    band = max(f, (_BAND_PX // f) * f)
    for b0 in range(R0, R1, band):
        b1 = min(b0 + band, R1)
        m = group["mask"][b0:b1, C0:C1].astype(np.float32)
        stack = np.zeros(m.shape + (_SUMS,), np.float32)
        a = group["albedo"][b0:b1, C0:C1].astype(np.float32)
        stack[..., 0:3] = a * m[..., None]
        if has_n:
            n = group["normals"][b0:b1, C0:C1].astype(np.float32)
            stack[..., 3:6] = n * m[..., None]
            stack[..., 6:9] = n
        stack[..., 9] = m
        # pad the band to whole cells (the image's last row/column of cells may be partial)
        ph, pw = -(b1 - b0) % f, -(C1 - C0) % f
        if ph or pw:
            stack = np.pad(stack, ((0, ph), (0, pw), (0, 0)))
        rh, rw = stack.shape[0] // f, stack.shape[1] // f
        i = (b0 - R0) // f
        out[i:i + rh, :rw] = stack.reshape(rh, f, rw, f, _SUMS).sum(axis=(1, 3))
    return out


def level_from_sums(sums: np.ndarray, level: int, has_normals: bool = True):
    """Albedo, normals (None without them) and mask of level ``level`` from its :func:`level_sums`."""
    cm = sums[..., 9]
    alb = sums[..., 0:3] / np.maximum(cm, 1e-12)[..., None]
    nrm = None
    if has_normals:
        s = sums[..., 3:6].copy()
        off = cm <= 0   # no fragment in the cell: plain average, so the field stays defined
        s[off] = sums[..., 6:9][off]
        s /= np.maximum(np.linalg.norm(s, axis=2, keepdims=True), 1e-12)
        s[np.linalg.norm(s, axis=2) < 0.5] = (0.0, 0.0, 1.0)
        nrm = s.astype(np.float32)
    return alb.astype(np.float32), nrm, cm / float(4 ** int(level)) >= 0.5


def face_params(group, *, unsharp_sigma_mm: float = 1.0) -> dict:
    """:func:`relight_params` of an RGBN HDF5 group, measured on its calibration window; ``dpi_nominal``:
    True when the face's provenance says its dpi is a guess (a hand-held or RTI capture has no scale of its own,
    docs/handheld.md), which the page says beside every length it shows; ``piece_px``: the mask's bounding box
    ``[x0, y0, x1, y1]`` (pixels, end exclusive; None for an empty mask), the size the page gives the piece."""
    mask = group["mask"][:]
    shape = mask.shape
    r0, r1, c0, c1 = calibration_window(shape)
    normals = group["normals"][r0:r1, c0:c1] if "normals" in group else None
    params = relight_params(normals, mask[r0:r1, c0:c1], float(group.attrs["dpi"]), shape,
                            unsharp_sigma_mm=unsharp_sigma_mm)
    try:
        provenance = json.loads(group.attrs.get("provenance", "{}"))
    except (TypeError, ValueError):
        provenance = {}
    params["dpi_nominal"] = bool(isinstance(provenance, dict) and provenance.get("dpi_nominal"))
    # the piece's own extent: a scan cropped to everything that turned also holds the lamp's shadow around it
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    params["piece_px"] = ([int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1] if len(rows) else None)
    return params


def tile_from_group(group, params: dict, level: int, row: int, col: int) -> bytes:
    """The packed tile (``level``, ``row``, ``col``) of an RGBN HDF5 group."""
    levels = params["levels"]
    if not 0 <= level < len(levels):
        raise ValueError(f"level must be in [0, {len(levels) - 1}], got {level}")
    lw, lh = levels[level]
    t = params["tile_px"]
    if not (0 <= row < -(-lh // t) and 0 <= col < -(-lw // t)):
        raise ValueError(f"tile ({row}, {col}) is outside level {level} ({lw}x{lh} px)")
    halo = int(math.ceil(params["halo_px"] / 2 ** level))
    r0, r1 = row * t, min((row + 1) * t, lh)
    c0, c1 = col * t, min((col + 1) * t, lw)
    R0, R1, C0, C1 = max(r0 - halo, 0), min(r1 + halo, lh), max(c0 - halo, 0), min(c1 + halo, lw)
    alb, nrm, mask = read_level_window(group, level, R0, R1, C0, C1)
    xy, H, colour = relight_fields(nrm, alb, mask, params, level=level)
    core = (slice(r0 - R0, r1 - R0), slice(c0 - C0, c1 - C0))
    return pack_tile(xy[core], H[core], colour[core])


_locks: dict[str, threading.Lock] = {}
_locks_guard = threading.Lock()


def _lock(key: str) -> threading.Lock:
    """One lock per cache file in this process: concurrent requests for the same tile or
    parameters compute them once (the others wait and read the file)."""
    with _locks_guard:
        return _locks.setdefault(key, threading.Lock())


class RelightCache:
    """Tiles and parameters of one face, computed on first request and kept on storage.

    Parameters
    ----------
    store : common.store.Store
    rgbn_relpath : str
        The face's ``tessera.rgbn`` artifact, ``fragments/<id>/rgbn/<face>-<key>.h5``.

    The cache folder is ``fragments/<id>/viewer/<face>-<key>-v<FIELDS_VERSION>/``: keyed by the
    artifact's own content key (artifacts are immutable), so a new solve gets new tiles and an
    old folder is never wrong. Files are written atomically (temporary name, then rename).
    """

    def __init__(self, store, rgbn_relpath: str):
        p = Path(rgbn_relpath)
        if len(p.parts) != 4 or p.parts[0] != "fragments" or p.parts[2] != "rgbn" or p.suffix != ".h5":
            raise ValueError(f"not an RGBN artifact path: {rgbn_relpath!r}")
        self.store = store
        self.rgbn_relpath = rgbn_relpath
        self.folder = f"fragments/{p.parts[1]}/viewer/{p.stem}-v{FIELDS_VERSION}"

    def open_artifact(self):
        """The face's RGBN artifact, open for reading."""
        from common.rgbn.image import SCHEMA, SCHEMA_VERSION

        return self.store.open(self.rgbn_relpath, schema=SCHEMA, version=SCHEMA_VERSION)

    def _put(self, relpath: str, data: bytes) -> None:
        from common.store import write_file  # the project's one atomic write

        write_file(self.store.path(relpath), data)

    def params(self) -> dict:
        """The face's :func:`face_params` (computed once, then read from ``params.json``)."""
        rel = f"{self.folder}/params.json"
        path = self.store.path(rel)
        with _lock(str(path)):
            if path.is_file():
                params = json.loads(path.read_text())
                # written before the viewer lit a face relative to its surface_normal and said when its dpi is
                # nominal: measured again (the tiles stay, they depend on neither)
                if all(k in params for k in ("surface_normal", "dpi_nominal", "piece_px")):
                    return params
            with self.open_artifact() as f:
                params = face_params(f)
            params["rgbn"] = self.rgbn_relpath
            self._put(rel, json.dumps(params, sort_keys=True).encode())
            return params

    def tiles_of(self, level: int) -> list[tuple[int, int]]:
        """``[(row, col)]`` of every tile of ``level``."""
        params = self.params()
        lw, lh = params["levels"][level]
        t = params["tile_px"]
        return [(r, c) for r in range(-(-lh // t)) for c in range(-(-lw // t))]

    def tile_relpath(self, level: int, row: int, col: int) -> str:
        """Where tile (``level``, ``row``, ``col``) is kept, relative to the storage root."""
        return f"{self.folder}/{int(level)}/{int(row)}_{int(col)}.bin.gz"

    def tile_path(self, level: int, row: int, col: int) -> Path:
        """Path of the tile on storage, computing and writing it first if it is not there."""
        rel = self.tile_relpath(level, row, col)
        path = self.store.path(rel)
        if path.is_file():
            return path
        params = self.params()
        with _lock(str(path)):
            if not path.is_file():
                with self.open_artifact() as f:
                    data = tile_from_group(f, params, int(level), int(row), int(col))
                self._put(rel, data)
        return path

    def level_image(self, level: int):
        """Level ``level`` as an :class:`RGBNImage` assembled from its tiles (cut if missing): the
        normals as solved (float16, z from x and y), the albedo from its 8-bit sRGB, the mask — what
        "auto" contrast measures, without reading the face again."""
        from common.rgbn.image import RGBNImage
        from common.rgbn.io import srgb_to_linear

        params = self.params()
        lw, lh = params["levels"][level]
        t = params["tile_px"]
        normals = np.zeros((lh, lw, 3), np.float32)
        colour = np.zeros((lh, lw, 4), np.uint8)
        for r, c in self.tiles_of(level):
            h, w = min(t, lh - r * t), min(t, lw - c * t)
            xy, _, col = unpack_tile(self.tile_path(level, r, c).read_bytes(), h, w)
            core = (slice(r * t, r * t + h), slice(c * t, c * t + w))
            normals[core + (slice(0, 2),)] = xy[..., :2]
            colour[core] = col
        normals[..., 2] = np.sqrt(np.maximum(1.0 - normals[..., 0] ** 2 - normals[..., 1] ** 2, 0.0))
        return RGBNImage(albedo=srgb_to_linear(colour[..., :3] / np.float32(255.0)), mask=colour[..., 3] > 127,
                         dpi=params["dpi"] / 2 ** level, normals=normals if params["has_normals"] else None)

    def whole_from(self, whole_mpx: float = WHOLE_MPX) -> int | None:
        """The finest level >= 1 of at most ``whole_mpx`` megapixels: it and every coarser level are
        cut whole by :meth:`cut` (None when the face has no level >= 1)."""
        levels = self.params()["levels"]
        return next((L for L in range(1, len(levels)) if levels[L][0] * levels[L][1] <= whole_mpx * 1e6), None)

    def cut(self, *, min_level: int = 1, progress=None, whole_mpx: float = None) -> int:
        """Cut every tile of the levels ``min_level`` and coarser now (what a first view would
        otherwise wait for); tiles already there are kept. Returns the number of tiles.

        Levels of at most ``whole_mpx`` megapixels are computed whole, from one band-by-band read
        of the face (:func:`level_sums`, each coarser level summed from the finer one); finer
        levels tile by tile. ``progress(done, total)`` is called after each tile (a
        :class:`common.imports.progress.ProgressBar` made with ``total`` can show it)."""
        params = self.params()
        t, levels = params["tile_px"], params["levels"]
        grid = {L: self.tiles_of(L) for L in range(min_level, len(levels))}
        total, done = sum(len(v) for v in grid.values()), 0

        def tick():
            nonlocal done
            done += 1
            if progress is not None:
                progress(done, total)

        whole_mpx = WHOLE_MPX if whole_mpx is None else whole_mpx
        whole = [L for L in grid if L >= 1 and levels[L][0] * levels[L][1] <= whole_mpx * 1e6]
        k0 = min(whole) if whole else None
        if k0 is not None and any(not self.store.path(self.tile_relpath(L, r, c)).is_file() for L in whole for r, c in grid[L]):
            lw, lh = levels[k0]
            with self.open_artifact() as f:
                sums = level_sums(f, k0, 0, lh, 0, lw)
                has_n = "normals" in f
            # every coarser level summed from the finer, then drawn coarsest first: the one-tile
            # top level (what a first view shows while the rest arrives) is written first
            sums = {k0: sums}
            for L in range(k0 + 1, len(levels)):
                sums[L] = halve_sums(sums[L - 1])
            for L in range(len(levels) - 1, k0 - 1, -1):
                alb, nrm, mask = level_from_sums(sums.pop(L), L, has_n)
                xy, H, colour = relight_fields(nrm, alb, mask, params, level=L)
                for r, c in grid[L]:
                    path = self.store.path(self.tile_relpath(L, r, c))
                    with _lock(str(path)):
                        if not path.is_file():
                            core = (slice(r * t, (r + 1) * t), slice(c * t, (c + 1) * t))
                            self._put(self.tile_relpath(L, r, c), pack_tile(xy[core], H[core], colour[core]))
                    tick()
        for L in sorted(grid, reverse=True):
            if k0 is not None and L >= k0:
                continue
            for r, c in grid[L]:
                self.tile_path(L, r, c)
                tick()
        return total


def cut_archive_tiles(store, source_relpath: str, *, progress=None) -> int:
    """Cut everything the archive pages show of one artifact, once, so no first view waits for it.

    For an RGBN face: the 8-bit albedo / normal-map pyramid (IIIF, deep zoom,
    :meth:`common.web.tiles.TileCache.pyramid`) and the relight tiles of every level but full
    resolution (:meth:`RelightCache.cut`; level-0 tiles are cut on demand, 0.1 s CPU each); for a
    render artifact: its pyramid. Existing tiles are kept (cached by the artifact's content key),
    so calling it again costs a directory look-up. Returns the number of tiles there are.
    Used by the renderer stage when a face arrives and by ``tessera web --cut-tiles``.
    """
    from common.web.tiles import TileCache

    tiles = int(TileCache(store).pyramid(source_relpath)["tiles"])
    if "/rgbn/" in source_relpath:
        tiles += RelightCache(store, source_relpath).cut(min_level=1, progress=progress)
    return tiles


# ---- the viewer's styles as offline styles ------------------------------------------------------

#: The styles the viewer's shaders draw (``services/web/static/viewer/<style>.frag``) and, per style,
#: its contrast parameters (what "auto" contrast resolves).
VIEWER_STYLES = {"albedo": ("exposure",), "lambertian": ("exposure",), "raking": ("exposure",),
                 "specular": ("exposure",), "normal_unsharp": ("exposure",), "exaggerated": ("tones",),
                 "mean_curvature": ("radius_mm",)}


def offline_arguments(style: str, values: dict, params: dict, *, level: int = 0) -> dict:
    """The keyword arguments of :data:`common.render.recipes.STYLES` ``[style].draw`` that draw what
    the viewer's shader draws with ``values`` (the style's parameters, same names) on a face with
    fields ``params`` (:func:`relight_params`), on pyramid level ``level``.

    The scales the fields were computed at are passed explicitly, whatever ``values`` says
    (``sigma_px`` / ``sigma0_px`` the noise scale, ``scales = 3`` and ``sigma_ratio = 2``, normal
    unsharp masking's ``sigma_mm``, the curvature's ``sigma_mm``), the surface is not levelled region by region
    (``level = False``) but, for the lit styles, lit relative to the way the whole face faces (``params``'
    ``surface_normal``: the light turned as the viewer turns it, :func:`common.render.enhance.levelled_light`),
    and every parameter the viewer does not have keeps the offline default.
    """
    from common.render.recipes import STYLES

    if style not in VIEWER_STYLES:
        raise ValueError(f"style must be one of {sorted(VIEWER_STYLES)}, got {style!r}")
    allowed = STYLES[style].parameters()
    unknown = sorted(set(values) - set(allowed))
    if unknown:
        raise ValueError(f"{style} has no parameter {', '.join(unknown)} (it has {', '.join(sorted(allowed))})")
    kw = dict(values)
    f = 2.0 ** int(level)
    if style in ("lambertian", "raking", "specular"):
        kw.update(sigma_px=params["sigma_px"] / f, level=False)
        if params.get("surface_normal"):
            kw.update(_levelled_angles(style, kw, params["surface_normal"]))
    elif style == "exaggerated":
        kw.update(sigma0_px=params["sigma_px"] / f, scales=EXAGGERATED_SCALES, sigma_ratio=2.0)
    elif style == "normal_unsharp":
        kw.update(sigma_mm=params["unsharp_sigma_mm"])
    elif style == "mean_curvature":
        kw.update(sigma_mm=params["curvature_sigma_mm"])
    for key in ("light", "exposure", "tones", "colour_exposure"):
        if isinstance(kw.get(key), list):
            kw[key] = tuple(kw[key])
    return kw


def _levelled_angles(style: str, kw: dict, facing) -> dict:
    """The lit style's light (``light`` or raking's ``azimuth_deg`` / ``elevation_deg``) turned to a face facing
    ``facing`` as the viewer turns it, as angles again."""
    from common.render.enhance import Coarse, levelled_light
    from common.render.recipes import STYLES

    default = STYLES[style].parameters()
    if style == "raking":
        light = (kw.get("azimuth_deg", default["azimuth_deg"]), kw.get("elevation_deg", default["elevation_deg"]))
    else:
        light = kw.get("light", default["light"])
    c = np.asarray(facing, np.float32).reshape(1, 1, 3)
    l = levelled_light(light, Coarse(c, 1, (0, 0))).values[0, 0].astype(float)
    l /= np.linalg.norm(l)
    az, el = math.degrees(math.atan2(l[1], l[0])), math.degrees(math.asin(float(np.clip(l[2], -1.0, 1.0))))
    return {"azimuth_deg": az, "elevation_deg": el} if style == "raking" else {"light": (az, el)}


def auto_contrast(image, style: str, values: dict, params: dict, *, level: int = 0) -> dict:
    """The values the offline style's "auto" contrast takes (robust percentiles of its signal,
    :mod:`common.render.recipes`) for the viewer's ``values`` on ``image`` (level ``level`` of the
    face): ``{"exposure": [lo, hi]}``, ``{"tones": [lo, hi]}`` or ``{"radius_mm": r}``."""
    from common.render.recipes import STYLES

    kw = offline_arguments(style, values, params, level=level)
    for key in VIEWER_STYLES[style]:
        kw[key] = "auto"
    resolved = STYLES[style].draw(image, **kw).resolved
    return {key: resolved[key] for key in VIEWER_STYLES[style]}


def overview_level(params: dict, max_mpx: float = 0.5) -> int:
    """The finest pyramid level of at most ``max_mpx`` megapixels (where "auto" contrast is measured)."""
    for level, (w, h) in enumerate(params["levels"]):
        if w * h <= max_mpx * 1e6:
            return level
    return len(params["levels"]) - 1

