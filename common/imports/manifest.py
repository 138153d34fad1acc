"""Which files to import and what a lab knows about each: paths, manifests, fragment ids.

A **manifest** is a CSV file (UTF-8, Excel's BOM accepted, comma, semicolon or tab separated) with a
header row. Column names are matched without regard to case, spaces, hyphens or underscores:

========================  ================================================================
``file``                  image path, relative to the manifest's folder (required)
``inventory``             inventory number (also ``inventory number``, ``inventory no``, ``inv``, ``id``);
                          the fragment id is made from it (:func:`fragment_id`)
``find_spot``             where it was found (also ``find-spot``, ``findspot``)
``context``               stratigraphic context / unit
``date``                  date of find or of the picture, as written
``notes``                 free text
``dpi``                   sampling of this picture (else the command's ``--dpi``)
``face``                  ``front`` (default) or ``back``
any other column          kept as metadata under its own (normalised) name
========================  ================================================================
"""

from __future__ import annotations

import csv
import os
import re
from pathlib import Path
from typing import Iterable, Sequence

from common.messages import FRAGMENT_PATTERN

#: suffixes of picture files picked up from a folder
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
METADATA_COLUMNS = ("inventory", "find_spot", "context", "date", "notes")
# keyed by the name without spaces, hyphens or underscores: "Inventory number", "InventoryNumber" and
# "inventory_number" are one column to a lab
_ALIASES = {"inventory": "inventory", "inventorynumber": "inventory", "inventoryno": "inventory", "inv": "inventory",
            "invno": "inventory", "fragment": "inventory", "id": "inventory", "findspot": "find_spot",
            "findplace": "find_spot", "filename": "file", "path": "file", "image": "file", "note": "notes",
            "comment": "notes", "comments": "notes"}


def natural_key(path: str | os.PathLike) -> list:
    """Sort key that orders ``img2`` before ``img10`` (numbers compared as numbers)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", os.fspath(path))]


def expand_paths(paths: Iterable[str | os.PathLike], suffixes: Sequence[str] = IMAGE_SUFFIXES) -> list[Path]:
    """Files named, and the picture files of folders named (not recursive), in natural order.

    A path that does not exist is kept (the door refuses it by name).
    """
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted((c for c in p.iterdir() if c.is_file() and c.suffix.lower() in suffixes
                           and not c.name.startswith(".")), key=natural_key)
        else:
            out.append(p)
    return out


#: folder names that are never a collection's or an object's (an archive unpacked on a Mac), lower case
NOT_FOLDERS_OF_PICTURES = {"__macosx"}


def subfolders(folder: str | os.PathLike) -> list[Path]:
    """The folders in ``folder`` that may hold pictures, by name: hidden ones (``.name``) and ``__MACOSX`` left out."""
    return sorted(p for p in Path(folder).iterdir()
                  if p.is_dir() and not p.name.startswith(".") and p.name.lower() not in NOT_FOLDERS_OF_PICTURES)


def picture_subfolders(folder: str | os.PathLike) -> list[Path]:
    """Those of its :func:`subfolders` that hold pictures directly (:func:`expand_paths`): a collection kept one
    folder per object, given where one of its objects was expected."""
    return [c for c in subfolders(folder) if expand_paths([c])]


def fragment_id(text: str) -> str:
    """A fragment id (storage directory name) from an inventory number or a file stem.

    Characters other than letters, digits, ``.``, ``_`` and ``-`` become ``-`` (``Inv. 1234/5`` ->
    ``Inv.-1234-5``); at most 64 characters. Raises ValueError if nothing usable is left.
    """
    fid = re.sub(r"[^A-Za-z0-9._-]+", "-", str(text).strip())
    fid = re.sub(r"^[._-]+", "", fid)[:64].rstrip("-")
    if not FRAGMENT_PATTERN.match(fid):
        raise ValueError(f"cannot make a fragment id from {text!r}: it needs letters or digits")
    return fid


def _column(name: str) -> str:
    key = re.sub(r"[\s\-]+", "_", name.strip().lower())
    return _ALIASES.get(key.replace("_", ""), key)


def read_manifest(path: str | os.PathLike) -> list[dict]:
    """Rows of a manifest CSV as dicts with normalised column names; ``file`` made absolute.

    Empty cells are dropped. Raises ValueError naming the manifest when it cannot be read, has
    no ``file`` column, or a row has no file.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"manifest {path} cannot be read: {exc}") from None
    try:
        dialect = csv.Sniffer().sniff(text.splitlines()[0] if text.strip() else ",", delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    reader = csv.reader(text.splitlines(), dialect)
    rows = [(reader.line_num, r) for r in reader if any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"manifest {path} is empty")
    header = [_column(h) for h in rows[0][1]]
    if "file" not in header:
        raise ValueError(f"manifest {path} has no 'file' column (columns: {', '.join(rows[0][1])})")
    out = []
    for n, r in rows[1:]:
        if len(r) > len(header):
            raise ValueError(f"manifest {path} line {n} has {len(r)} cells, the header has {len(header)}")
        row = {k: v.strip() for k, v in zip(header, r) if v.strip()}
        if "file" not in row:
            raise ValueError(f"manifest {path} line {n} names no file")
        row["file"] = str((path.parent / row["file"]).resolve())
        row["line"] = n
        out.append(row)
    return out
