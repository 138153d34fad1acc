"""Sane physical ranges of the artifacts that enter a stage (scans, RGBN faces).

A flatbed scans between 25 and 4800 dpi; a fresco fragment is at most a metre across; one image
of a face stays within a few hundred megapixels. An artifact outside these ranges (a corrupted
``dpi`` attribute, a declared 200000 × 200000 dataset) would make a stage resample into terabytes
or run for hours, so each stage checks the *declared* shapes and attributes of its input before
reading a pixel (:func:`check_scans_file`, :func:`check_rgbn_file`; stages call them through
``read_scans(..., check_limits=True)`` and ``load_rgbn(..., check_limits=True)``). A violation raises
:class:`~common.store.ArtifactError` naming the value, which the worker reports as rejected: the
broker parks the job at once with an ``input.rejected`` event.

The ranges live here only; :class:`~common.rgbn.image.RGBNImage` itself accepts any positive dpi
(unit tests use tiny images at a few dpi).
"""

from __future__ import annotations

import math

import h5py

from common.store import ArtifactError

#: Scan and face resolution accepted at stage entry, dots per inch (flatbed range, §3.3.4).
DPI_RANGE = (25.0, 4800.0)
#: Largest image (rows × cols) of one scan or face, pixels: an A4 bed at 1600 dpi is 254 Mpx.
MAX_IMAGE_PIXELS = 300_000_000
#: Largest extent of a fragment face (either side of the image or scan area), millimetres.
MAX_EXTENT_MM = 1000.0


def check_dpi(dpi, what: str) -> float:
    """Return ``dpi`` as a float, or raise :class:`ArtifactError` naming ``what`` and the value."""
    try:
        value = float(dpi)
    except (TypeError, ValueError):
        raise ArtifactError(f"{what}: dpi {dpi!r} is not a number") from None
    lo, hi = DPI_RANGE
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ArtifactError(f"{what}: dpi {value:g} is outside the sane range {lo:g}…{hi:g} dpi")
    return value


def check_image_size(shape, dpi: float, what: str) -> None:
    """Raise :class:`ArtifactError` if an image of ``shape`` (rows, cols, ...) at ``dpi`` is absurd.

    Absurd: an empty side, more than :data:`MAX_IMAGE_PIXELS` pixels, or a side longer than
    :data:`MAX_EXTENT_MM` (pixel size 25.4 / dpi mm).
    """
    if len(shape) < 2:
        raise ArtifactError(f"{what}: shape {tuple(shape)} is not an image (rows, cols[, channels])")
    rows, cols = int(shape[0]), int(shape[1])
    if rows < 1 or cols < 1:
        raise ArtifactError(f"{what}: image of {rows}×{cols} pixels is empty")
    if rows * cols > MAX_IMAGE_PIXELS:
        raise ArtifactError(f"{what}: image of {rows}×{cols} pixels ({rows * cols / 1e6:.0f} Mpx) exceeds "
                            f"the limit of {MAX_IMAGE_PIXELS / 1e6:.0f} Mpx")
    side_mm = max(rows, cols) * 25.4 / dpi
    if side_mm > MAX_EXTENT_MM:
        raise ArtifactError(f"{what}: image of {rows}×{cols} pixels at {dpi:g} dpi is {side_mm:.0f} mm across, "
                            f"more than the {MAX_EXTENT_MM:g} mm a fragment can be")


def check_rgbn_file(group: h5py.Group) -> None:
    """Check the declared dpi and image size of an open ``tessera.rgbn`` artifact before reading it.

    Raises :class:`ArtifactError` naming the bad value (a missing ``dpi`` or ``albedo`` is left
    to :func:`common.rgbn.image.read_rgbn`, which names it).
    """
    what = f"RGBN face {group.file.filename}"
    if "dpi" not in group.attrs or "albedo" not in group:
        return
    dpi = check_dpi(group.attrs["dpi"], what)
    for name in ("albedo", "mask", "normals", "confidence", "discontinuity", "height_mm"):
        if name in group:
            if not isinstance(group[name], h5py.Dataset):
                raise ArtifactError(f"{what}: {name} is not a dataset")
            check_image_size(group[name].shape, dpi, f"{what} {name}")


def check_scans_file(f: h5py.File) -> None:
    """Check every scan of an open ``tessera.scans`` artifact (dpi, size, scan area) before reading it.

    Raises :class:`ArtifactError` naming the face, scan and bad value.
    """
    for face in ("front", "back"):
        if face not in f:
            continue
        for name, d in f[face].items():
            what = f"scans {f.filename} {face}/{name}"
            if not isinstance(d, h5py.Dataset):
                raise ArtifactError(f"{what} is not a dataset")
            if "dpi" not in d.attrs:
                raise ArtifactError(f"{what} lacks its dpi")
            dpi = check_dpi(d.attrs["dpi"], what)
            check_image_size(d.shape, dpi, what)
            area = d.attrs.get("area_mm")
            if area is not None:
                try:
                    x0, y0, x1, y1 = (float(v) for v in area)
                except (TypeError, ValueError):
                    raise ArtifactError(f"{what}: scan area {area!r} is not (x0, y0, x1, y1) mm") from None
                if not all(map(math.isfinite, (x0, y0, x1, y1))) or max(abs(x1 - x0), abs(y1 - y0)) > MAX_EXTENT_MM:
                    raise ArtifactError(f"{what}: scan area {(x0, y0, x1, y1)} mm is larger than "
                                        f"{MAX_EXTENT_MM:g} mm or not finite")
