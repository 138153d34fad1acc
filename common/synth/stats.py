"""Statistics of a broken-fresco collection, real or synthetic, measured the same way on both.

A *collection* is a list of pieces -- each an RGBA image (8-bit sRGB colour, alpha = the
fragment) with, where known, its placement on its object's canvas. :func:`read_collection`
reads one laid out as ``../shared/data/repair-dev`` (RePAIR: one folder per object, ``truth.csv``
``rpf,x,y,rot``); :func:`wall_collection` turns a synthetic :class:`~common.synth.wall.Wall` into
the same form. :func:`collection_statistics` then measures what makes real joins hard:

- **gaps between true neighbours** -- neighbours are pieces whose placed outlines come within
  ``near_px`` (48 px at 187 dpi, 6.5 mm) of each other along at least ``min_run_px`` (100 px,
  13.6 mm); for each pair the smallest distance between the placed masks (alpha >= 128), and the
  median distance along the close run (how much material is lost along the crack);
- **fragment size** -- square root of the area, and the largest diameter (mm);
- **contour roughness** -- turning angles of the outline (smoothed by 1 px) resampled every 0.5 mm, at chord
  lengths 1, 3 and 10 mm (mean absolute angle, degrees), and the rms distance (mm) between the
  outline and the outline smoothed by a 2 mm Gaussian along its arc;
- **plain edge** -- the share of outline length whose band 0.5-3 mm inside the edge is plain
  plaster: CIELAB chroma ``C* < plain_chroma`` (8) and lightness ``L* > 45``;
- **colour** -- CIELAB lightness and chroma of the fragment faces (median, 90th percentile), the
  share of face area with ``C* >= 15`` ("painted");
- **soft alpha edge** -- width (px) of the band where 0 < alpha < 255: partial pixels / outline.

Pixel figures are given at the collection's own sampling; mm figures use its dpi (RePAIR:
7.369 px/mm, about 187 dpi, the conversion of RePAIR's own evaluation code).
"""

from __future__ import annotations

import codecs
import csv
import io
import logging
import os
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

REPAIR_DPI = 7.369 * 25.4  # RePAIR's evaluation code: 7.369 px/mm


log = logging.getLogger("tessera.collection")

TRUTH_COLUMNS = ("rpf", "x", "y", "rot")
@dataclass
class Piece:
    """One fragment of a collection.

    Attributes
    ----------
    id : str
    object : str
        The object (fresco) it belongs to.
    rgba : (H, W, 4) uint8
        sRGB colour and alpha (0 outside, 255 inside, a soft ramp at the edge), cropped.
    matrix : (2, 3) float array or None
        Crop pixel (col, row, 1) -> object canvas pixel; None when its place is unknown
        (a distractor).
    file : str or None
        The picture it was read from (None for a synthetic piece).
    """

    id: str
    object: str
    rgba: np.ndarray
    matrix: np.ndarray | None = None
    file: str | None = None


def read_fragment_rgba(path) -> np.ndarray:
    """A fragment image as (H, W, 4) uint8 RGBA, the piece in its alpha channel, read completely
    through the import door (:func:`common.imports.door.read_image_checked`: a truncated or corrupt
    file or a fully transparent one is refused, naming the file and the reason; OpenCV alone would
    return a truncated PNG's missing rows as grey). 16-bit files are reduced to 8 bits; grey pictures
    (with or without alpha) read as grey RGB(A).

    An RGB image without alpha (the piece photographed or scanned on a plain background, black or
    any other) is cut out by :func:`common.imports.fragments.cut_from_background` (the edge where the
    piece covers half a pixel, the background's share taken out of the edge pixels), as ``tessera import
    images --background auto`` does; one where no piece stands out from the background is refused. So is
    an RGBA image whose alpha hides nothing (255 everywhere: a picture on its background saved with an
    opaque alpha channel), which would otherwise be read as a piece the size of the whole picture."""
    from common.imports.door import read_image_checked
    from common.imports.fragments import cut_from_background

    img = read_image_checked(path, channels=(1, 2, 3, 4))
    px = img.pixels if img.bits == 8 else (np.clip(img.as_float(), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if px.ndim == 2:
        px = px[..., None]
    if px.shape[2] in (1, 2):   # grey, grey + alpha
        px = np.concatenate([np.repeat(px[..., :1], 3, axis=2), px[..., 1:]], axis=2)
    if px.shape[2] == 4 and not (px[..., 3] < 255).any():
        px = px[..., :3]        # an alpha channel that hides nothing: the piece is on its background
    if px.shape[2] == 4:
        return np.ascontiguousarray(px)
    rgb, mask, _ = cut_from_background(px.astype(np.float32) / 255.0)
    if not mask.any():
        raise ValueError(f"{path}: RGB image without alpha, and no piece stands out from its plain background")
    return np.dstack([(rgb * 255.0 + 0.5).astype(np.uint8), np.where(mask, 255, 0).astype(np.uint8)])


def _crop(rgba: np.ndarray, pad: int = 2):
    ys, xs = np.nonzero(rgba[..., 3] > 0)
    if not ys.size:
        raise ValueError("the image has no opaque pixel (alpha is 0 everywhere)")
    r0, c0 = max(int(ys.min()) - pad, 0), max(int(xs.min()) - pad, 0)
    r1, c1 = int(ys.max()) + pad + 1, int(xs.max()) + pad + 1
    return rgba[r0:r1, c0:c1].copy(), c0, r0


def _truth_file(obj: Path) -> Path | None:
    """An object folder's ``truth.csv``, its name in any case (``Truth.CSV`` from another system)."""
    found = sorted(c for c in obj.iterdir() if c.name.lower() == "truth.csv" and c.is_file())
    if len(found) > 1:
        raise ValueError(f"{obj}: {' and '.join(c.name for c in found)} are two truth files: keep one")
    return found[0] if found else None


def _truth_text(path: Path) -> str:
    """A truth file's text as spreadsheets save it: UTF-8 with or without BOM, UTF-16 with BOM
    (Excel's "Unicode text"), else Windows-1252 (Excel's plain "CSV" on Windows)."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if raw.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            return raw.decode("utf-16")
        except UnicodeDecodeError as exc:
            raise ValueError(f"{path}: starts as UTF-16 text but cannot be decoded ({exc.reason} at byte "
                             f"{exc.start}): save it as CSV (UTF-8)") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        pass
    try:
        return raw.decode("cp1252")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: is not text (UTF-8, UTF-16 or Windows-1252: byte {raw[exc.start]:#04x} at "
                         f"{exc.start} cannot be decoded): save it as CSV (UTF-8)") from None


def _pictures_named(name: str, pictures: set) -> list:
    """The pictures of a folder a ``truth.csv`` name may mean, best first: the file name itself, given
    with a folder path another tool wrote (its last part), in another case, or as a stem, or with another
    picture suffix than the file has (a collection converted from PNG to JPEG keeps its truth.csv)."""
    from common.imports.manifest import IMAGE_SUFFIXES

    base = PureWindowsPath(name).name if ("/" in name or "\\" in name) else name   # both separators
    if base in pictures:
        return [base]
    same = sorted(p for p in pictures if p.lower() == base.lower())
    if same:
        return same
    stem = Path(base).stem if Path(base).suffix.lower() in IMAGE_SUFFIXES else base
    return sorted(p for p in pictures if Path(p).stem.lower() == stem.lower())


def _number(cell: str, delimiter: str) -> float:
    text = cell.strip()
    if delimiter != "," and re.fullmatch(r"[-+]?\d*,\d+", text):   # a decimal comma (semicolon-separated files)
        text = text.replace(",", ".")
    return float(text)


def _read_truth(path: Path, images: set, row_problem=None) -> dict:
    """``truth.csv`` of one object: ``{image file name: (x, y, rot)}``.

    Read as spreadsheets write it: any of the encodings :func:`_truth_text` reads, separated by commas,
    semicolons (then a decimal comma is read as a point) or tabs as its header line is, column names in
    any case and order with spaces around them, extra columns, blank rows and rows of empty cells
    ignored. A fragment may be named by its file name (RePAIR's ``RPf_00072_intact_mesh.png``), its stem,
    and as :func:`_pictures_named` finds it.

    A file without the four columns is refused (ValueError naming it). A row is refused naming the file,
    line and problem -- a value that is not a finite number, a name given twice, one that matches no image
    of the folder (a typo would otherwise leave a placed piece silently unplaced) or several; with
    ``row_problem`` (a callable taking that message) the row is ignored instead and reading goes on
    (a picture whose rows are ignored has no place).
    """
    text = _truth_text(path)
    first = next((line for line in text.splitlines() if line.strip()), "")
    if not first:
        raise ValueError(f"{path}: is empty (expected the header line {','.join(TRUTH_COLUMNS)} and a row per "
                         "placed picture)")
    delimiter = next((d for d in (",", ";", "\t") if d in first), ",")
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
    header = None
    truth, lines, bad = {}, {}, set()

    def problem(message):
        if row_problem is None:
            raise ValueError(message)
        row_problem(message + ": row ignored")

    for row in reader:
        if not any(cell.strip() for cell in row):
            continue
        if header is None:
            names = [cell.strip().lower() for cell in row]
            missing = [c for c in TRUTH_COLUMNS if c not in names]
            if missing:
                found = ", ".join(cell.strip() for cell in row if cell.strip())
                raise ValueError(f"{path}: missing column(s) {', '.join(missing)} (expected "
                                 f"{','.join(TRUTH_COLUMNS)}; found: {found})")
            header = {c: names.index(c) for c in TRUTH_COLUMNS}
            continue
        line = reader.line_num
        cells = {c: (row[i] if i < len(row) else "") for c, i in header.items()}
        name = cells["rpf"].strip()
        where = f"{path}, line {line}"
        matches = _pictures_named(name, images) if name else []
        if len(matches) > 1:
            problem(f"{where}: {name!r} could be any of {', '.join(matches)}: name the file")
            continue
        if not matches:
            problem(f"{where}: {name!r} names no fragment image in {path.parent}" if name else
                    f"{where}: the rpf cell is empty")
            continue
        pic = matches[0]
        if pic in lines:
            bad.add(pic)
            problem(f"{where}: {pic} is placed twice (lines {lines[pic]} and {line})")
            continue
        lines[pic] = line
        try:
            values = tuple(_number(cells[c], delimiter) for c in ("x", "y", "rot"))
        except ValueError:
            bad.add(pic)
            problem(f"{where}: {pic}: x, y and rot must be numbers, got "
                    f"{cells['x']!r}, {cells['y']!r}, {cells['rot']!r}")
            continue
        if not all(np.isfinite(values)):
            bad.add(pic)
            problem(f"{where}: {pic}: x, y and rot must be finite, got {values}")
            continue
        truth[pic] = values
    if header is None:
        raise ValueError(f"{path}: is empty (expected the header line {','.join(TRUTH_COLUMNS)})")
    return {k: v for k, v in truth.items() if k not in bad}


def collection_layout(path: str | os.PathLike) -> dict:
    """What a collection's object folders hold, read without decoding a picture (a check before a long run).

    Returns
    -------
    dict
        object folder name -> ``{"pictures": n, "placed": n of them a truth.csv row places (None without a
        truth file), "problem": why its truth file is unusable, or None, "deeper": its subfolders that hold
        pictures (not read)}``; folders as :func:`read_collection` reads them (hidden ones left out).
    """
    from common.imports.manifest import expand_paths, picture_subfolders, subfolders

    root = Path(path)
    out = {}
    for obj in subfolders(root):
        pictures = expand_paths([obj])
        deeper = [c.name for c in picture_subfolders(obj)]
        entry = {"pictures": len(pictures), "placed": None, "problem": None, "deeper": deeper}
        try:
            tf = _truth_file(obj)
            if tf is not None:
                entry["placed"] = len(_read_truth(tf, {p.name for p in pictures}, row_problem=lambda m: None))
        except ValueError as exc:
            entry["problem"] = str(exc)
        out[obj.name] = entry
    return out


def read_collection(path: str | os.PathLike, *, skipped: list | None = None) -> list[Piece]:
    """Read a collection laid out as ``repair-dev``: one folder per object with fragment pictures (PNG, TIFF or
    JPEG as ``tessera import images`` reads them; RGBA, or RGB or grey on a plain background:
    :func:`read_fragment_rgba`) and, where the placement is known, ``truth.csv`` (``rpf,x,y,rot``: rotate the
    image counter-clockwise by ``rot`` degrees about its centre, canvas kept, then put its top-left corner at
    ``(x, y)``, in the picture's own pixels; the file as spreadsheets write it, :func:`_read_truth`).
    Folders without ``truth.csv``, or whose ``truth.csv`` has no rows, give distractors (``matrix`` None);
    so does a picture no row places (:func:`common.matching.collection.collection_wall` leaves those out).

    Pictures are the files with a picture suffix directly in an object folder (hidden files, such as macOS's
    ``._name.png``, and other files left out); hidden folders and ``__MACOSX`` are no objects. A piece's id is
    its file's stem, or its file name where two pictures of the folder share the stem.

    Parameters
    ----------
    path : path
        The collection directory.
    skipped : list, optional
        Given, a damaged picture, an unusable ``truth.csv`` row (its picture then has no place) or an unusable
        ``truth.csv`` (its object left out) is left out, described here with its file and reason, and reading
        goes on. What the layout leaves out (an object folder without pictures, pictures outside any object
        folder) is described here too. Each is logged as a warning (logger ``tessera.collection``).

    Returns
    -------
    list of Piece

    Raises
    ------
    ValueError
        Without ``skipped``: a bad ``truth.csv`` (naming the file and line), or damaged fragment images: every
        one is named with its reason (:func:`read_fragment_rgba`), so one run lists all there are to fix.
        Always: ``path`` not a directory, or no fragment picture read, saying where the pictures were found
        (directly in ``path``, or a level deeper) and what to give instead.
    """
    from common.imports.manifest import IMAGE_SUFFIXES, expand_paths, picture_subfolders, subfolders

    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"path {root} is not a directory" if root.exists() else f"path {root} does not exist")
    lenient = skipped is not None
    notes = []

    def leave_out(message):
        log.warning(message)
        notes.append(message)
        if lenient:
            skipped.append(message)

    pieces, refused, folders = [], [], []
    for obj in subfolders(root):
        pictures = sorted(expand_paths([obj]))   # as import images lists a folder (hidden files left out)
        if not pictures:
            subs = [c.name for c in subfolders(obj)]
            leave_out(f"{obj}: holds no fragment picture ({', '.join(IMAGE_SUFFIXES)} directly in it"
                      + (f"; subfolders such as {', '.join(subs[:3])} are not read" if subs else "") + "): left out")
            continue
        folders.append(obj)
        names = {p.name for p in pictures}
        ignored = []

        def row_ignored(message):
            ignored.append(message)
            leave_out(message)

        try:
            tf = _truth_file(obj)
            truth = _read_truth(tf, names, row_problem=row_ignored if lenient else None) if tf else {}
        except ValueError as exc:
            if not lenient:
                raise
            leave_out(f"{exc}: object {obj.name} left out ({len(pictures)} pictures)")
            continue
        if tf is not None and not truth and ignored:   # its pieces are each other's joins: not distractors
            leave_out(f"{tf}: none of its rows is usable: object {obj.name} left out ({len(pictures)} pictures)")
            continue
        if tf is not None and not truth:
            leave_out(f"{tf} places none of the {len(pictures)} pictures of {obj.name}: read as unplaced "
                      "(distractors), as a folder without truth.csv")
        stems = Counter(p.stem for p in pictures)
        for pic in pictures:
            try:
                rgba = read_fragment_rgba(pic)
                crop, c0, r0 = _crop(rgba)
            except Exception as exc:   # noqa: BLE001 -- every damaged image is named, not one per run
                text = str(exc) if isinstance(exc, ValueError) else f"could not be read ({type(exc).__name__}: {exc})"
                text = text if text.startswith(str(pic)) else f"{pic}: {text}"
                if lenient:
                    leave_out(f"{text}: left out")
                else:
                    refused.append(text)
                continue
            h, w = rgba.shape[:2]
            M = None
            if pic.name in truth:
                x, y, rot = truth[pic.name]
                R = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), rot, 1.0)
                R[:, 2] += (x, y)
                M = R.copy()
                M[:, 2] = R[:, :2] @ (c0, r0) + R[:, 2]  # crop pixel -> canvas
            pieces.append(Piece(pic.stem if stems[pic.stem] == 1 else pic.name, obj.name, crop, M, str(pic)))
    if refused:
        shown = "; ".join(refused[:10]) + (f"; and {len(refused) - 10} more" if len(refused) > 10 else "")
        raise ValueError(f"{len(refused)} fragment image(s) refused: {shown}")
    stray = expand_paths([root])
    layout = f"a collection is one folder per object, {root}/<object>/<picture> with the object's truth.csv beside"
    if stray and folders:
        leave_out(f"{root}: {len(stray)} fragment picture(s) directly in it ({', '.join(p.name for p in stray[:3])}"
                  f"{', ...' if len(stray) > 3 else ''}) belong to no object folder: left out")
    if folders and _truth_file(root) is not None:
        leave_out(f"{_truth_file(root)}: a truth file at the top of the collection is not read (each object's "
                  "truth.csv goes in its folder)")
    if pieces:
        return pieces
    if stray and not folders:
        raise ValueError(f"path {root} holds {len(stray)} fragment pictures directly and no object folder: {layout} "
                         f"its pictures; put them in a folder of their own inside {root}")
    for obj in subfolders(root):
        deeper = picture_subfolders(obj)
        if deeper and _truth_file(obj) is None:
            raise ValueError(f"path {root} holds no fragment picture one level down, but {obj} holds object folders "
                             f"with pictures ({', '.join(c.name for c in deeper[:3])}): give {obj} as the collection "
                             f"({layout} its pictures)")
        if deeper:
            raise ValueError(f"{obj}: its truth.csv is beside no picture; the pictures are in its subfolder "
                             f"{deeper[0].name}: put them directly in {obj}")
    if notes:
        raise ValueError(f"no fragment picture of {root} could be read: " + "; ".join(notes[:5])
                         + (f"; and {len(notes) - 5} more" if len(notes) > 5 else ""))
    raise ValueError(f"path {root} holds no fragment images (expected <object>/<fragment>.png; "
                     f"{', '.join(IMAGE_SUFFIXES)} are read)")


def wall_collection(wall, fragments=None, *, alpha_px: float | None = None) -> list[Piece]:
    """A synthetic (or imported) wall as a collection: each fragment with an image as RGBA
    (:func:`fragment_rgba`), placed by its pose on a canvas at the wall's dpi.

    Parameters
    ----------
    wall : Wall
    fragments : list of Fragment, optional
        Fragments with images (default: ``wall.fragments``).
    alpha_px : float, optional
        Soft alpha edge width (px) given to the RGBA images (default: what the fragment has).
    """
    return [fragment_piece(f, wall.id, alpha_px=alpha_px)
            for f in (wall.fragments if fragments is None else fragments) if f.rgbn is not None]


def fragment_piece(fragment, object_name: str, *, alpha_px: float | None = None) -> Piece:
    """One fragment with an image as a :class:`Piece` (RGBA with a soft edge, placed by its pose
    on a canvas at its own dpi; spurious fragments unplaced)."""
    from common.synth.realistic import fragment_rgba

    f = fragment
    if f.rgbn is None:
        raise ValueError(f"fragment {f.id} has no image")
    rgba = fragment_rgba(f.rgbn, edge_px=alpha_px)
    pad = (rgba.shape[0] - f.rgbn.shape[0]) // 2  # fragment_rgba pads evenly
    crop, c0, r0 = _crop(rgba)
    M = None
    if f.pose is not None:
        pm = f.rgbn.pixel_mm
        a = np.deg2rad(f.pose[0])
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        # canvas px = wall mm / pm = R @ (col, row) + t / pm, (col, row) = crop px + offset - pad
        M = np.hstack([R, (np.asarray(f.pose[1:]) / pm)[:, None]])
        M[:, 2] = R @ (c0 - pad, r0 - pad) + M[:, 2]
    return Piece(f.id, object_name, crop, M)


# ------------------------------------------------------------------------------------------ gaps
def _placed(piece: Piece):
    """Placed mask (alpha >= 128) in a canvas window, its offset, and its outline (canvas px)."""
    a = piece.rgba[..., 3]
    h, w = a.shape
    corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) @ piece.matrix.T
    x0, y0 = np.floor(corners.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 2
    M = piece.matrix.copy()
    M[:, 2] -= (x0, y0)
    warped = cv2.warpAffine(a, M, (int(x1 - x0), int(y1 - y0)), flags=cv2.INTER_LINEAR)
    mask = warped >= 128
    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = max(cs, key=len).reshape(-1, 2).astype(float) + (x0, y0) if cs else np.zeros((0, 2))
    return mask, (int(x0), int(y0)), outline


def _step_lengths(outline: np.ndarray) -> np.ndarray:
    """Length of outline attributed to each point (half the steps to both neighbours)."""
    d = np.hypot(*(np.roll(outline, -1, axis=0) - outline).T)
    return 0.5 * (d + np.roll(d, 1))


def neighbour_gaps(pieces: list[Piece], *, near_px: float = 48.0, min_run_px: float = 100.0) -> list[dict]:
    """True neighbours of a placed collection and the gaps between them.

    Two pieces of one object are neighbours when each one's placed outline comes within
    ``near_px`` of the other's along at least ``min_run_px`` (outline length, mean of the two).

    Parameters
    ----------
    pieces : list of Piece
        Pieces with a placement (others are ignored).
    near_px, min_run_px : float
        Neighbour definition, canvas pixels.

    Returns
    -------
    list of dict
        One per neighbour pair: ``a``, ``b``, ``object``, ``run_px`` (close outline length),
        ``min_gap_px`` (smallest distance between the placed masks; 0 where they touch or overlap),
        ``median_gap_px`` (median distance of the close run to the other outline), ``within3``
        (share of the close run within 3 px).
    """
    if near_px <= 0 or min_run_px <= 0:
        raise ValueError(f"near_px and min_run_px must be positive, got {near_px}, {min_run_px}")
    placed = {}
    for p in pieces:
        if p.matrix is not None:
            placed[(p.object, p.id)] = _placed(p)
    keys = sorted(placed)
    trees = {k: cKDTree(v[2]) for k, v in placed.items() if len(v[2])}
    out = []
    for i, ka in enumerate(keys):
        ma, (xa, ya), oa = placed[ka]
        for kb in keys[i + 1:]:
            if kb[0] != ka[0] or ka not in trees or kb not in trees:
                continue
            mb, (xb, yb), ob = placed[kb]
            if (xb > xa + ma.shape[1] + near_px or xa > xb + mb.shape[1] + near_px
                    or yb > ya + ma.shape[0] + near_px or ya > yb + mb.shape[0] + near_px):
                continue
            da, _ = trees[kb].query(oa, distance_upper_bound=near_px + 1)
            db, _ = trees[ka].query(ob, distance_upper_bound=near_px + 1)
            close_a, close_b = da <= near_px, db <= near_px
            run = 0.5 * (_step_lengths(oa)[close_a].sum() + _step_lengths(ob)[close_b].sum())
            if run < min_run_px:
                continue
            # masks overlapping or touching -> gap 0; else outline-to-outline distance
            x0, y0 = max(xa, xb), max(ya, yb)
            x1, y1 = min(xa + ma.shape[1], xb + mb.shape[1]), min(ya + ma.shape[0], yb + mb.shape[0])
            overlap = x1 > x0 and y1 > y0 and bool(np.any(
                ma[y0 - ya:y1 - ya, x0 - xa:x1 - xa] & mb[y0 - yb:y1 - yb, x0 - xb:x1 - xb]))
            gap = 0.0 if overlap else max(0.0, float(min(da.min(), db.min())) - 1.0)
            dd = np.concatenate([da[close_a], db[close_b]])
            out.append(dict(object=ka[0], a=ka[1], b=kb[1], run_px=float(run), min_gap_px=gap,
                            median_gap_px=float(max(0.0, np.median(dd) - 1.0)),
                            within3=float(np.mean(dd - 1.0 <= 3.0))))
    return out


# -------------------------------------------------------------------------------- per piece
def _lab(rgb8: np.ndarray) -> np.ndarray:
    """8-bit sRGB (N, 3) -> CIELAB (N, 3) with L in 0-100 (D65)."""
    lab = cv2.cvtColor(rgb8.reshape(-1, 1, 3).astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)
    return lab.reshape(-1, 3)


def _turning(outline_mm: np.ndarray, chord_mm: float, step_mm: float) -> float:
    k = max(1, int(round(chord_mm / step_mm)))
    if len(outline_mm) < 2 * k + 3:
        return float("nan")
    u = np.roll(outline_mm, -k, axis=0) - outline_mm
    v = outline_mm - np.roll(outline_mm, k, axis=0)
    ang = np.arctan2(v[:, 0] * u[:, 1] - v[:, 1] * u[:, 0], (u * v).sum(axis=1))
    return float(np.degrees(np.mean(np.abs(ang))))


def _resample(outline: np.ndarray, step: float) -> np.ndarray:
    closed = np.vstack([outline, outline[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    s = np.concatenate([[0], np.cumsum(seg)])
    t = np.arange(0.0, s[-1], step)
    return np.column_stack([np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])])


def piece_statistics(rgba: np.ndarray, dpi: float, *, plain_chroma: float = 8.0) -> dict:
    """Size, outline roughness, plain-edge share, colour and alpha-edge width of one fragment.

    Parameters
    ----------
    rgba : (H, W, 4) uint8
        sRGB colour and alpha.
    dpi : float
        Sampling (pixel = 25.4 / dpi mm).
    plain_chroma : float
        CIELAB chroma below which the edge band counts as plain plaster (with L* > 45).

    Returns
    -------
    dict
        ``size_mm`` (sqrt area), ``diameter_mm``, ``turn1_deg``, ``turn3_deg``, ``turn10_deg``,
        ``rough_mm``, ``plain_edge``, ``L_median``, ``C_median``, ``C_p90``, ``painted``,
        ``alpha_edge_px``, ``perimeter_mm``.
    """
    rgba = np.asarray(rgba)
    if rgba.ndim != 3 or rgba.shape[2] != 4 or rgba.dtype != np.uint8:
        raise ValueError(f"rgba must be an (H, W, 4) uint8 image, got {rgba.shape} {rgba.dtype}")
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    pm = 25.4 / dpi
    alpha = rgba[..., 3]
    mask = alpha >= 128
    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not cs:
        raise ValueError("rgba has no pixel with alpha >= 128")
    outline = max(cs, key=len).reshape(-1, 2).astype(float)
    perim_px = float(_step_lengths(outline).sum())
    hull = cv2.convexHull(outline.astype(np.float32)).reshape(-1, 2)
    diam = float(np.max(np.hypot(*(hull[:, None] - hull[None]).transpose(2, 0, 1)))) if len(hull) > 1 else 0.0
    step = 0.5
    # the pixel staircase, lightly smoothed (1 px), resampled every 0.5 mm
    o_mm = _resample(gaussian_filter1d(outline, 1.0, axis=0, mode="wrap") * pm, step)
    # roughness: distance to the outline smoothed along its arc (2 mm Gaussian: shapes with radii
    # of curvature of centimetres barely shrink, jags below a few mm are what remains)
    sm = gaussian_filter1d(o_mm, 2.0 / step, axis=0, mode="wrap")
    rough = float(np.sqrt(np.mean(np.sum((o_mm - sm) ** 2, axis=1))))
    # edge band 0.5-3 mm inside; each band pixel belongs to its nearest outline sample
    dist = cv2.distanceTransform(np.pad(mask.astype(np.uint8), 1), cv2.DIST_L2, 5)[1:-1, 1:-1] * pm
    band = mask & (dist >= 0.5) & (dist <= 3.0)
    rgb = rgba[..., :3]
    lab_face = _lab(rgb[mask & (alpha == 255)] if np.any(mask & (alpha == 255)) else rgb[mask])
    chroma = np.hypot(lab_face[:, 1], lab_face[:, 2])
    plain = float("nan")
    yy, xx = np.nonzero(band)
    if yy.size:
        samples = _resample(outline, 1.0 / pm)  # one per mm, px
        _, nearest = cKDTree(samples).query(np.column_stack([xx, yy]))
        lab_b = _lab(rgb[yy, xx])
        n = len(samples)
        cnt = np.bincount(nearest, minlength=n)
        mean = np.stack([np.bincount(nearest, lab_b[:, j], minlength=n) for j in range(3)], 1) / np.maximum(cnt, 1)[:, None]
        ok = cnt > 0
        c_b = np.hypot(mean[ok, 1], mean[ok, 2])
        plain = float(np.mean((c_b < plain_chroma) & (mean[ok, 0] > 45)))
    partial = int(np.count_nonzero((alpha > 0) & (alpha < 255)))
    return dict(size_mm=float(np.sqrt(mask.sum()) * pm), diameter_mm=diam * pm, perimeter_mm=perim_px * pm,
                turn1_deg=_turning(o_mm, 1.0, step), turn3_deg=_turning(o_mm, 3.0, step),
                turn10_deg=_turning(o_mm, 10.0, step), rough_mm=rough, plain_edge=plain,
                L_median=float(np.median(lab_face[:, 0])), C_median=float(np.median(chroma)),
                C_p90=float(np.percentile(chroma, 90)), painted=float(np.mean(chroma >= 15.0)),
                alpha_edge_px=partial / max(perim_px, 1.0))


# ------------------------------------------------------------------------------ whole collection
def _q(values, qs=(25, 50, 75)):
    v = np.asarray([x for x in values if np.isfinite(x)], float)
    return [float(np.percentile(v, q)) for q in qs] if v.size else [float("nan")] * len(qs)


def collection_statistics(pieces: list[Piece], dpi: float, *, near_mm: float = 48 / 7.369,
                          min_run_mm: float = 100 / 7.369, plain_chroma: float = 8.0,
                          min_size_mm: float = 10.0) -> dict:
    """Summary statistics of a collection (see the module notes for the definitions).

    Parameters
    ----------
    pieces : list of Piece
    dpi : float
        Sampling of the images.
    near_mm, min_run_mm : float
        Neighbour definition in mm (default: RePAIR's 48 px and 100 px at 7.369 px/mm).
    plain_chroma : float
        Chroma threshold of a plain edge.
    min_size_mm : float
        Pieces smaller than this (sqrt area) are crumbs: counted, left out of the per-piece figures.

    Returns
    -------
    dict
        ``n_pieces``, ``n_crumbs``, ``n_pairs``, ``pieces`` (per-piece dicts), ``pairs`` (from
        :func:`neighbour_gaps`), and quartiles ``[q25, median, q75]`` of ``min_gap_mm``,
        ``median_gap_mm``, ``size_mm``, ``diameter_mm``, ``turn1_deg``, ``turn3_deg``,
        ``turn10_deg``, ``rough_mm``, ``plain_edge``, ``L_median``, ``C_median``, ``C_p90``,
        ``painted``, ``alpha_edge_px``; ``min_gap_within3px`` (share of pairs whose smallest gap is
        at most 3 px at 187 dpi, 0.41 mm), ``run_within3px`` (share of the close runs within it),
        ``plain_edge_all`` (outline-length-weighted plain share).
    """
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    pm = 25.4 / dpi
    per = []
    crumbs = 0
    for p in pieces:
        s = piece_statistics(p.rgba, dpi, plain_chroma=plain_chroma)
        s.update(id=p.id, object=p.object)
        if s["size_mm"] < min_size_mm:
            crumbs += 1
            continue
        per.append(s)
    pairs = neighbour_gaps(pieces, near_px=near_mm / pm, min_run_px=min_run_mm / pm)
    for q in pairs:
        q["min_gap_mm"] = q["min_gap_px"] * pm
        q["median_gap_mm"] = q["median_gap_px"] * pm
    out = dict(n_pieces=len(pieces), n_crumbs=crumbs, n_pairs=len(pairs), pieces=per, pairs=pairs, dpi=float(dpi))
    out["min_gap_mm"] = _q([q["min_gap_mm"] for q in pairs])
    out["median_gap_mm"] = _q([q["median_gap_mm"] for q in pairs])
    tol = 3.0 / 7.369
    out["min_gap_within3px"] = float(np.mean([q["min_gap_mm"] <= tol for q in pairs])) if pairs else float("nan")
    out["run_within3px"] = float(np.average([q["within3"] for q in pairs], weights=[q["run_px"] for q in pairs])) \
        if pairs else float("nan")
    for k in ("size_mm", "diameter_mm", "turn1_deg", "turn3_deg", "turn10_deg", "rough_mm", "plain_edge",
              "L_median", "C_median", "C_p90", "painted", "alpha_edge_px"):
        out[k] = _q([s[k] for s in per])
    w = np.array([s["perimeter_mm"] for s in per])
    pe = np.array([s["plain_edge"] for s in per])
    ok = np.isfinite(pe)
    out["plain_edge_all"] = float(np.average(pe[ok], weights=w[ok])) if ok.any() else float("nan")
    return out


_ROWS = [
    ("neighbour pairs (48 px / 100 px rule)", "n_pairs", None),
    ("smallest gap per pair, mm: median [IQR]", "min_gap_mm", "q"),
    ("smallest gap per pair, px at 187 dpi: median [IQR]", "min_gap_mm", "px"),
    ("pairs whose smallest gap is <= 3 px (0.41 mm)", "min_gap_within3px", "share"),
    ("median gap along the crack, mm: median [IQR]", "median_gap_mm", "q"),
    ("close crack length within 3 px", "run_within3px", "share"),
    ("fragment size sqrt(area), mm", "size_mm", "q"),
    ("largest diameter, mm", "diameter_mm", "q"),
    ("outline turning angle at 1 mm, deg", "turn1_deg", "q"),
    ("outline turning angle at 3 mm, deg", "turn3_deg", "q"),
    ("outline turning angle at 10 mm, deg", "turn10_deg", "q"),
    ("outline roughness (rms to 2 mm-smoothed), mm", "rough_mm", "q"),
    ("plain edge share per fragment (C* < 8, L* > 45, 0.5-3 mm inside)", "plain_edge", "q"),
    ("plain edge share, all outline", "plain_edge_all", "share"),
    ("face lightness L*, per-fragment median", "L_median", "q"),
    ("face chroma C*, per-fragment median", "C_median", "q"),
    ("face chroma C*, per-fragment 90th percentile", "C_p90", "q"),
    ("painted share of the face (C* >= 15)", "painted", "q"),
    ("soft alpha edge, partial px per px of outline", "alpha_edge_px", "q"),
]


def comparison_table(columns: dict) -> str:
    """A markdown table of :func:`collection_statistics` results side by side.

    Parameters
    ----------
    columns : dict
        Column title -> statistics dict.

    Returns
    -------
    str
    """
    names = list(columns)
    lines = ["| statistic | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]

    def cell(st, key, kind):
        v = st.get(key)
        if v is None:
            return ""
        if kind is None:
            return f"{v}"
        if kind == "share":
            return f"{v:.2f}"
        q = np.asarray(v, float)
        if kind == "px":
            q = q * 7.369
        fmt = "{:.2f}" if np.nanmax(np.abs(q)) < 10 else "{:.1f}"
        return f"{fmt.format(q[1])} [{fmt.format(q[0])}-{fmt.format(q[2])}]"

    for title, key, kind in _ROWS:
        lines.append(f"| {title} | " + " | ".join(cell(columns[n], key, kind) for n in names) + " |")
    lines.append("| fragments measured (crumbs < 1 cm left out) | " + " | ".join(
        f"{columns[n]['n_pieces'] - columns[n]['n_crumbs']} ({columns[n]['n_crumbs']})" for n in names) + " |")
    return "\n".join(lines)
