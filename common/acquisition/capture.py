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
#: Scans of a face needed for normals (three unknowns per pixel, eq. 3.6); fewer is colour only.
MIN_SCANS_FOR_NORMALS = 3
#: A scan whose brightest sample is below this fraction of full scale is "all black".
BLACK_FRACTION = 2.0 / 255.0

__all__ = ["CaptureStep", "Scan", "CaptureResult", "capture_fragment", "write_scans", "read_scans", "check_scan",
           "check_capture", "MIN_SCANS_FOR_NORMALS",
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


def check_scan(image: np.ndarray, what: str = "scan", *, depth: int | None = None) -> np.ndarray:
    """A scan as the station stores it, (H, W, 3) uint8 or uint16, or ValueError naming ``what`` and why.

    Grey scans (H, W) or (H, W, 1) become three equal channels; an alpha channel is dropped; float
    scans (full scale 1) become 16-bit. Refused: other sample types, NaN or values outside [0, 1] in
    a float scan, a declared ``depth`` the samples do not have, 8-bit values stored in a 16-bit scan
    (the largest sample under 256 of 65535: the scan would read as nearly black), all-black and
    blank (uniform) scans.
    """
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or min(image.shape[:2]) < 1:
        raise ValueError(f"{what}: shape {image.shape} is not a grey, RGB or RGBA image")
    image = image[..., :3]
    if image.dtype.kind == "f":
        if not np.isfinite(image).all():
            raise ValueError(f"{what}: float samples include NaN or infinity")
        lo, hi = float(image.min()), float(image.max())
        if lo < 0 or hi > 1.0 + 1e-6:
            raise ValueError(f"{what}: float samples span {lo:g}..{hi:g}; a float scan must be linear with full "
                             "scale 1")
        image = np.rint(np.clip(image, 0, 1) * 65535).astype(np.uint16)
    elif image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{what}: samples of type {image.dtype}; scans must be 8/16-bit integers or float")
    bits = 8 if image.dtype == np.uint8 else 16
    if depth is not None and depth != bits:
        raise ValueError(f"{what}: {bits}-bit samples but {depth}-bit was declared")
    full = 255 if bits == 8 else 65535
    hi, lo = int(image.max()), int(image.min())
    if bits == 16 and 0 < hi < 256:
        raise ValueError(f"{what}: a 16-bit scan holding 8-bit values (largest sample {hi} of 65535); save it "
                         "again at 16 bits, or as 8-bit")
    if hi < BLACK_FRACTION * full:
        raise ValueError(f"{what}: all black (no sample above {BLACK_FRACTION:.1%} of full scale): lamp off or "
                         "lid open?")
    if hi - lo < BLACK_FRACTION * full:
        raise ValueError(f"{what}: blank (every sample within {BLACK_FRACTION:.1%} of full scale of {lo / full:.3f})")
    return np.ascontiguousarray(image)


def check_capture(result: "CaptureResult") -> "CaptureResult":
    """Every scan of a capture checked (:func:`check_scan`) and enough of them per face, or ValueError.

    Scans are named ``<face> scan <k>`` with ``k`` counted from 0 as stored. A face of a capture
    that is not colour-only needs :data:`MIN_SCANS_FOR_NORMALS` scans (or none: a missing back);
    a colour-only capture's faces use their first scan. Returns the capture with the checked
    (converted) scans.
    """
    faces = {f: list(result.scans.get(f) or []) for f in FACES}
    if not any(faces.values()):
        raise ValueError(f"capture of {result.fragment_id} holds no scans")
    for face, scans in faces.items():
        if scans and not result.colour_only and len(scans) < MIN_SCANS_FOR_NORMALS:
            raise ValueError(f"{face} face has {len(scans)} scan(s): normals need at least {MIN_SCANS_FOR_NORMALS} "
                             "scans turned about 90° apart (4 in the thesis); add scans or import it colour-only")
        for k, s in enumerate(scans):
            img = check_scan(s.image, f"{face} scan {k}", depth=s.depth)
            if not (np.isfinite(s.dpi) and s.dpi > 0):
                raise ValueError(f"{face} scan {k}: dpi must be positive, got {s.dpi}")
            if scans[0].dpi != s.dpi:
                raise ValueError(f"{face} scan {k}: {s.dpi:g} dpi but {face} scan 0 is {scans[0].dpi:g} dpi; "
                                 "every scan of a face must have the same resolution")
            scans[k] = Scan(img, s.dpi, s.rotation, s.area_mm, 8 if img.dtype == np.uint8 else 16)
    result.scans = faces
    return result


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
        k = len(result.scans[face])
        try:   # a backend in grey mode, at another depth, or giving a black frame: said now, not at the solver
            img = check_scan(img, f"{face} scan {k}", depth=depth)
        except ValueError as exc:
            raise ScannerError(f"the scanner returned an unusable scan: {exc}",
                               f"The scanner returned an unusable scan ({exc}). Check the scanner's colour "
                               f"mode ({depth}-bit colour), the lamp and the lid, then press Scan again.",
                               status="bad_scan") from exc
        result.scans[face].append(Scan(img, float(dpi), rot, tuple(float(v) for v in area), depth))
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


def write_scans(store: Store, fragment_id: str, result: CaptureResult, *, key: str | None = None,
                provenance: dict | None = None) -> ArtifactRef:
    """Store every raw scan of a fragment as ``fragments/<id>/scans/scans-<key>.h5`` (``tessera.scans``).

    Layout: group per face, dataset ``scan_<k>`` (H, W, 3) uint8/uint16 with attributes ``dpi``,
    ``rotation_deg`` (nominal), ``area_mm`` (left, top, right, bottom), ``depth``; root attributes
    ``fragment``, ``device``, ``calibration``, ``colour_only``. The key is a digest of the pixels,
    or ``key`` when given (an importer's content key of its source files); ``provenance`` adds
    entries to the artifact's provenance (e.g. the source files, a detected turn direction).
    """
    if key is None:
        h = hashlib.sha256()
        for f in FACES:
            for s in result.scans.get(f, []):
                h.update(s.image.tobytes())
        digest = content_key(fragment_id, result.device, h.hexdigest())
    else:
        digest = key
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
                       provenance={"device": result.device, "calibration": result.calibration, "fragment": fragment_id,
                                   **(provenance or {})})


def read_scans(store: Store, ref, *, check_limits: bool = False) -> CaptureResult:
    """Read a ``tessera.scans`` artifact (digest-checked when given a pointer).

    ``check_limits``: first check every scan's declared dpi, size and area against the sane ranges
    of :mod:`common.limits` (as the solver does with its input), before a pixel is read.
    """
    with store.open(ref, schema=SCHEMA, version=SCHEMA_VERSION) as f:
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
