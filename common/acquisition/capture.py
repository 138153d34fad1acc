"""The capture workflow at the bench (§3.3.4) and the scans artifact.

For each face: the operator places the fragment; a low-dpi pre-scan of the whole bed finds it by
background subtraction (:mod:`common.acquisition.locate`); only its region plus a margin is
scanned at full dpi; the operator turns it ~90° and the pre-scan/scan repeats until four
rotations are done; then the fragment is flipped and the back gets the same. Colour-only mode
takes one scan per face. The operator is told each step through ``operator(step)``.

:func:`write_scans` stores every raw scan of a fragment as one ``tessera.scans`` artifact;
:func:`read_scans` reads it back.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from common.acquisition.errors import (CaptureError, MultipleFragmentsError, NoFragmentError,  # noqa: F401
                                       ScannerError)
from common.acquisition.locate import locate_fragment
from common.limits import check_scans_file
from common.store import ArtifactError, ArtifactRef, Store, content_key

SCHEMA = "tessera.scans"
SCHEMA_VERSION = 1
FACES = ("front", "back")

__all__ = ["CaptureStep", "Scan", "CaptureResult", "capture_fragment", "write_scans", "read_scans",
           "simulated_operator", "CaptureError", "NoFragmentError", "MultipleFragmentsError", "ScannerError"]


@dataclass(frozen=True)
class CaptureStep:
    """One thing the operator must do before the next scan.

    Attributes
    ----------
    index, total : int
        1-based step number and number of steps of this capture.
    face : str
        ``front`` or ``back``.
    rotation : int
        Nominal rotation of this scan in degrees (0, 90, 180, 270).
    instruction : str
        Plain words: "Place the fragment face down ...", "Turn the fragment 90° clockwise",
        "Flip the fragment ...".
    action : str
        Machine-readable action: ``place``, ``rotate`` or ``flip`` (the simulated operator uses it).
    """

    index: int
    total: int
    face: str
    rotation: int
    instruction: str
    action: str


@dataclass
class Scan:
    """One raw scan."""

    image: np.ndarray             # (H, W, 3) uint8 | uint16
    dpi: float
    rotation: int                 # nominal, degrees clockwise
    area_mm: tuple                # (left, top, right, bottom) bed mm
    depth: int


@dataclass
class CaptureResult:
    """Every raw scan of one fragment."""

    fragment_id: str
    device: str
    scans: dict = field(default_factory=dict)      # face -> list[Scan]
    colour_only: bool = False
    calibration: str | None = None
    bed_mm: tuple | None = None


def _steps(colour_only: bool) -> list[tuple[str, int, str, str]]:
    rotations = (0,) if colour_only else (0, 90, 180, 270)
    out = []
    for face in FACES:
        for r in rotations:
            if face == "front" and r == 0:
                out.append((face, r, "place", "Place the fragment face down near the middle of the glass and close the lid"))
            elif r == 0:
                out.append((face, r, "flip", "Flip the fragment over (back face down on the glass) and close the lid"))
            else:
                out.append((face, r, "rotate", "Turn the fragment 90° clockwise where it lies and close the lid"))
    return out


def capture_fragment(scanner, fragment_id: str, *, operator: Callable[[CaptureStep], None], dpi: float = 600,
                     prescan_dpi: float = 50, depth: int = 16, colour_only: bool = False, margin_mm: float = 5.0,
                     background: np.ndarray | None = None, calibration: str | None = None,
                     progress: Callable[[float, str], None] | None = None) -> CaptureResult:
    """Capture one fragment: pre-scan, locate, full-dpi scans at four rotations per face (§3.3.4).

    Parameters
    ----------
    scanner : Scanner
        Any backend of :mod:`common.acquisition.scanners` (or the simulator).
    fragment_id : str
        The fragment's inventory id.
    operator : callable(CaptureStep)
        Called before each scan; returns when the operator has done the step.
    dpi : float
        Full resolution (600–1200 for normals).
    prescan_dpi : float
        Pre-scan resolution of the whole bed.
    depth : int
        8 or 16 bit.
    colour_only : bool
        One scan per face (no normals).
    margin_mm : float
        Margin around the located fragment.
    background : array or None
        Empty-bed pre-scan at ``prescan_dpi`` for background subtraction (None = estimate).
    calibration : str or None
        Id of the calibration in force, recorded with the scans.

    Raises
    ------
    NoFragmentError, MultipleFragmentsError, ScannerError
        With ``.operator_message`` for the person at the bench.
    """
    if not fragment_id or not isinstance(fragment_id, str):
        raise ValueError(f"fragment_id must be a non-empty string, got {fragment_id!r}")
    if depth not in (8, 16):
        raise ValueError(f"depth must be 8 or 16, got {depth}")
    if not (dpi > 0 and prescan_dpi > 0):
        raise ValueError("dpi and prescan_dpi must be positive")
    steps = _steps(colour_only)
    result = CaptureResult(fragment_id, getattr(scanner, "name", type(scanner).__name__), {f: [] for f in FACES},
                           colour_only=colour_only, calibration=calibration, bed_mm=tuple(scanner.bed_mm))
    for i, (face, rot, action, text) in enumerate(steps):
        operator(CaptureStep(i + 1, len(steps), face, rot, f"{text} ({face} face, scan {i + 1} of {len(steps)})", action))
        if progress:
            progress(i / len(steps), f"pre-scan for {face} {rot}°")
        pre = scanner.scan(None, prescan_dpi, depth)
        area = locate_fragment(pre, prescan_dpi, background=background, margin_mm=margin_mm, bed_mm=scanner.bed_mm)
        if progress:
            progress((i + 0.3) / len(steps), f"scanning {face} {rot}° at {dpi:g} dpi")
        img = scanner.scan(area, dpi, depth)
        result.scans[face].append(Scan(np.asarray(img), float(dpi), rot, tuple(float(v) for v in area), depth))
    if progress:
        progress(1.0, "capture complete")
    return result


def simulated_operator(sim) -> Callable[[CaptureStep], None]:
    """An operator for the simulated flatbed: does each step with realistic imprecision."""
    def act(step: CaptureStep) -> None:
        if step.action == "rotate":
            sim.rotate(90.0)
        elif step.action == "flip":
            sim.flip()
    return act


def write_scans(store: Store, fragment_id: str, result: CaptureResult) -> ArtifactRef:
    """Store every raw scan of a fragment as ``fragments/<id>/scans/scans-<key>.h5`` (``tessera.scans``).

    Layout: group per face, dataset ``scan_<k>`` (H, W, 3) uint8/uint16 with attributes ``dpi``,
    ``rotation_deg`` (nominal), ``area_mm`` (left, top, right, bottom), ``depth``; root attributes
    ``fragment``, ``device``, ``calibration``, ``colour_only``. The key is a digest of the pixels.
    """
    h = hashlib.sha256()
    for f in FACES:
        for s in result.scans.get(f, []):
            h.update(s.image.tobytes())
    digest = content_key(fragment_id, result.device, h.hexdigest())
    relpath = f"fragments/{fragment_id}/scans/scans-{digest}.h5"

    def fill(f):
        f.attrs["fragment"] = fragment_id
        f.attrs["device"] = result.device
        f.attrs["calibration"] = result.calibration or ""
        f.attrs["colour_only"] = bool(result.colour_only)
        if result.bed_mm:
            f.attrs["bed_mm"] = np.asarray(result.bed_mm, float)
        for face in FACES:
            g = f.create_group(face)
            for k, s in enumerate(result.scans.get(face, [])):
                d = g.create_dataset(f"scan_{k}", data=s.image, compression="gzip", compression_opts=1, shuffle=True)
                d.attrs["dpi"] = s.dpi
                d.attrs["rotation_deg"] = s.rotation
                d.attrs["area_mm"] = np.asarray(s.area_mm, float)
                d.attrs["depth"] = s.depth
    return store.write(relpath, SCHEMA, SCHEMA_VERSION, fill,
                       provenance={"device": result.device, "calibration": result.calibration, "fragment": fragment_id})


def read_scans(store: Store, ref, *, check_limits: bool = False) -> CaptureResult:
    """Read a ``tessera.scans`` artifact (digest-checked when given a pointer).

    ``check_limits``: first check every scan's declared dpi, size and area against the sane ranges
    of :mod:`common.limits` (as the solver does with its input), before a pixel is read.
    """
    with store.open(ref, schema=SCHEMA) as f:
        if check_limits:
            check_scans_file(f)
        try:
            res = CaptureResult(str(f.attrs["fragment"]), str(f.attrs["device"]), {},
                                colour_only=bool(f.attrs["colour_only"]),
                                calibration=str(f.attrs.get("calibration", "")) or None,
                                bed_mm=tuple(f.attrs["bed_mm"]) if "bed_mm" in f.attrs else None)
            for face in FACES:
                scans = []
                if face in f:
                    names = sorted(f[face], key=lambda n: int(n.split("_")[1]))
                    for n in names:
                        d = f[face][n]
                        scans.append(Scan(d[()], float(d.attrs["dpi"]), int(d.attrs["rotation_deg"]),
                                          tuple(float(v) for v in d.attrs["area_mm"]), int(d.attrs["depth"])))
                res.scans[face] = scans
        except KeyError as exc:
            raise ArtifactError(f"scans artifact {f.filename} lacks {exc}") from exc
    return res
