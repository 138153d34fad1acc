"""The sampling resolution (dpi) a scan or picture file declares in its metadata.

A scanner writes the resolution it scanned at into the file: PNG's ``pHYs`` chunk (pixels per
metre, unit 1), TIFF's ``XResolution``/``YResolution`` with ``ResolutionUnit`` (2 = inch,
3 = centimetre; TIFF 6.0 §Section 8) and JPEG's JFIF APP0 density (units 1 = dots per inch,
2 = dots per cm; JFIF 1.02). A file without a unit (PNG unit 0, TIFF unit 1, JFIF unit 0: an
aspect ratio only) declares no resolution. The 72 or 96 dpi an image editor writes when it knows
nothing is a declaration like any other: the importer warns when a file's dpi and ``--dpi``
disagree, and uses ``--dpi``.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

__all__ = ["file_dpi", "resolve_dpi"]

_INCH_M = 0.0254


def _png_dpi(path: Path) -> tuple[float, float] | None:
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89PNG\r\n\x1a\n":
            return None
        while True:
            head = fh.read(8)
            if len(head) < 8:
                return None
            length, kind = struct.unpack(">I4s", head)
            if kind == b"pHYs":
                data = fh.read(length)
                if len(data) < 9:
                    return None
                x, y, unit = struct.unpack(">IIB", data[:9])
                if unit != 1 or x == 0 or y == 0:     # unit 0: aspect ratio only
                    return None
                return x * _INCH_M, y * _INCH_M
            if kind in (b"IDAT", b"IEND"):           # pHYs must come before the image data
                return None
            fh.seek(length + 4, 1)


def _tiff_dpi(path: Path) -> tuple[float, float] | None:
    import tifffile
    with tifffile.TiffFile(path) as tf:
        tags = tf.pages[0].tags
        xr, yr, unit = tags.get("XResolution"), tags.get("YResolution"), tags.get("ResolutionUnit")
        if xr is None:
            return None
        u = int(unit.value) if unit is not None else 2      # TIFF's default unit is the inch
        if u not in (2, 3):
            return None

        def val(tag):
            v = tag.value
            return v[0] / v[1] if isinstance(v, tuple) else float(v)
        x = val(xr)
        y = val(yr) if yr is not None else x
        if x <= 0 or y <= 0:
            return None
        f = 2.54 if u == 3 else 1.0
        return x * f, y * f


def _jpeg_dpi(path: Path) -> tuple[float, float] | None:
    from PIL import Image
    with Image.open(path) as im:
        unit = im.info.get("jfif_unit")
        density = im.info.get("jfif_density")
        if unit in (1, 2) and density and density[0] > 0 and density[1] > 0:
            f = 2.54 if unit == 2 else 1.0
            return float(density[0]) * f, float(density[1]) * f
        dpi = im.info.get("dpi")          # EXIF resolution, when there is no JFIF density
        if unit is None and dpi and dpi[0] > 0 and dpi[1] > 0:
            return float(dpi[0]), float(dpi[1])
    return None


def file_dpi(path) -> float | None:
    """The resolution a PNG, TIFF or JPEG file declares, in dots per inch, or None.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    float or None
        The horizontal resolution in dpi. None when the file declares none (no ``pHYs`` chunk or
        a unitless one, no TIFF resolution tags or ``ResolutionUnit`` 1, no JFIF density or a
        unitless one), or for another format.

    Raises
    ------
    ValueError
        When the horizontal and vertical resolutions differ by more than 1 % (non-square pixels:
        the scan would need resampling first).
    """
    path = Path(path)
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic.startswith(b"\x89PNG"):
        found = _png_dpi(path)
    elif magic[:2] in (b"II", b"MM"):
        found = _tiff_dpi(path)
    elif magic[:2] == b"\xff\xd8":
        found = _jpeg_dpi(path)
    else:
        return None
    if found is None:
        return None
    x, y = found
    if abs(x - y) > 0.01 * max(x, y):
        raise ValueError(f"{path}: declares non-square pixels ({x:.4g} x {y:.4g} dpi); resample it to square "
                         "pixels first")
    return float(x)


def resolve_dpi(paths, given=None, *, where: str = "files", hint: str = "give --dpi") -> tuple[float, list[str]]:
    """The dpi of a set of scans: ``given`` if not None, else the one the files declare.

    One policy for every command that reads scans (``tessera import scans``, ``tessera calibrate
    --from-files``): a given dpi wins, with a warning for each file declaring another (by more than
    1 %); without one, the files must declare it, and agree within 1 %.

    Parameters
    ----------
    paths : sequence of path-like
        The scan files; files that do not exist are skipped (the door refuses them later).
    given : float or None
        The dpi the user gave (``--dpi``, a manifest column), or None.
    where : str
        Names the set of scans in messages.
    hint : str
        What the user can do when no dpi can be found, appended to that message.

    Returns
    -------
    dpi : float
        ``given``, or the median of the declared resolutions.
    warnings : list of str
        A file contradicting ``given``, or a file declaring nothing beside others that do.

    Raises
    ------
    ValueError
        No dpi given and none declared, files declaring different resolutions (no dpi given), or a
        file declaring non-square pixels.
    """
    paths = [Path(p) for p in paths]
    declared = {}
    for p in paths:
        try:
            d = file_dpi(p) if p.is_file() else None
        except (ValueError, OSError) as exc:
            raise ValueError(f"{where}: {exc}") from None
        if d is not None:
            declared[str(p)] = d
    if given is not None:
        given = float(given)
        return given, [f"{p} declares {d:.4g} dpi but {given:g} dpi was given; using {given:g}"
                       for p, d in declared.items() if abs(d - given) > 0.01 * given]
    if not declared:
        raise ValueError(f"{where}: no dpi: the files declare none (no PNG pHYs, TIFF resolution or JPEG density); "
                         f"{hint}")
    values = sorted(declared.values())
    if values[-1] - values[0] > 0.01 * values[-1]:
        raise ValueError(f"{where}: the files declare different resolutions ({values[0]:.4g} to "
                         f"{values[-1]:.4g} dpi); give --dpi")
    missing = [str(p) for p in paths if str(p) not in declared]
    warnings = [f"{missing[0]} declares no dpi; using {values[0]:.4g} dpi declared by the others"] if missing else []
    return float(np.median(values)), warnings
