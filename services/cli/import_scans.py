"""``tessera import scans``: flatbed scans of fragments from files, as the scanner service would store them.

    tessera import scans S0.png S90.png S180.png S270.png --fragment F12 --device epson-v850 --dpi 600
                         [--back B0.png B90.png ...] [--turn cw|ccw|auto] [--crop] [--srgb] [--store DIR]
    tessera import scans --manifest scans.csv --device epson-v850 [--dpi 600] [--store DIR]

Each fragment becomes one ``tessera.scans`` artifact ``fragments/<id>/scans/scans-<key>.h5`` and
one ``fragment.ready`` event naming ``--device``: the solver registers the scans, takes the
newest calibration of that device (``tessera calibrate --from-files MANIFEST --device NAME``)
and solves the normals, exactly as for a capture at the bench.

The scans of a face are given in the order they were taken, the fragment turned by about 90°
between them; ``--turn`` says which way, clockwise or counter-clockwise as seen on the scan
image, or ``auto`` (default): both are tried in registration and the one that registers is kept
(and recorded). A given direction the scans contradict is refused with the direction to give.
``--crop`` is for whole-bed scans: the fragment's region is where the scans of a face differ
(the fragment turns, the bed, a frame or jig and rulers do not), cut with a margin from each.
Files: PNG or TIFF, 8 or 16-bit (float TIFF: linear, full scale 1), or JPEG, RGB, RGBA (alpha
dropped) or grey (three equal channels: grey albedo). JPEG is accepted with a one-line warning per
fragment: it is 8-bit and lossy, and its 8x8 compression blocks add noise to the photometric-stereo
normals (scan to 16-bit PNG or TIFF where you can). Values are taken as linear (what a scanner gives
with its gamma set to 1.0); ``--srgb`` decodes sRGB-encoded files first (a JPEG usually is). Without ``--crop`` the
scans must show the fragment with a ring of bed around it. Normals need at least 3 scans per face; one scan per
face is imported colour-only with ``--colour-only``.

The manifest is a CSV file with the columns ``file`` and ``fragment`` (or ``inventory``), and
optionally ``face`` (front/back, default front), ``dpi`` and ``turn``; rows of one face in scan
order. A fragment's ``dpi`` and ``turn`` count from whichever of its rows gives them (else ``--dpi``,
``--turn``); two of its rows giving different values are refused, naming the fragment, the values
and the lines, before anything is imported (exit 2). Every file is checked at the door (decodes fully, bit depth, not black or blank) and a
refused fragment names the file and the reason; nothing of it is written. A scan set any of whose files was already
imported as another fragment is refused naming that fragment and the file (``--allow-duplicates`` imports it anyway),
and one imported for the same fragment at another dpi naming both dpi values (``--replace``). See docs/flatbed.md
and docs/import.md.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from common.imports import ImportItem, ImportRefused, Output

#: algorithm version of this importer: part of every content key
VERSION = "scans-1"
log = logging.getLogger("tessera.import.scans")


def add_parser(subparsers) -> None:
    from services.cli.imports import add_sink_arguments
    p = subparsers.add_parser("scans", help="flatbed scans of fragments from files (4 turned scans per face)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="*", metavar="SCAN",
                   help="scans of the front face, in the order taken (PNG/TIFF 8/16-bit; JPEG with a warning)")
    p.add_argument("--back", nargs="+", default=[], metavar="SCAN", help="scans of the back face, in the order taken")
    p.add_argument("--fragment", help="fragment (inventory) id of the scans given as arguments")
    p.add_argument("--manifest", metavar="CSV", help="file, fragment[, face, dpi, turn] columns, one row per scan")
    p.add_argument("--device", required=True,
                   help="name of the scanner that made the scans: its calibration is used (tessera calibrate)")
    p.add_argument("--dpi", type=float, help="resolution of the scans (default: the manifest's dpi column, else "
                                             "what the files declare: PNG pHYs, TIFF XResolution, JPEG density)")
    p.add_argument("--turn", choices=("cw", "ccw", "auto"), default="auto",
                   help="way the fragment was turned between scans, as seen on the image (default auto: detected)")
    p.add_argument("--crop", action="store_true", help="whole-bed scans: find the fragment and keep its region")
    p.add_argument("--srgb", action="store_true", help="the 8/16-bit files are sRGB-encoded (decode to linear first)")
    p.add_argument("--colour-only", action="store_true", help="one scan per face, albedo only (no normals)")
    add_sink_arguments(p)
    p.set_defaults(func=run)


def _items(args) -> list[ImportItem]:
    from common.imports.manifest import fragment_id, read_manifest
    from common.limits import check_dpi
    from common.store import ArtifactError

    groups: dict = {}           # fragment -> {"front": [paths], "back": [paths], "dpi":, "turn":, "where":}
    if args.manifest:
        if args.paths or args.back:
            raise ValueError("give scans as arguments or --manifest, not both")
        for row in read_manifest(args.manifest):
            where = f"{args.manifest} line {row['line']}"
            if "inventory" not in row:
                raise ValueError(f"{where}: no fragment (a 'fragment' or 'inventory' column)")
            fid = fragment_id(row["inventory"])
            face = row.get("face", "front").lower()
            if face not in ("front", "back"):
                raise ValueError(f"{where}: face {face!r} must be front or back")
            g = groups.setdefault(fid, {"front": [], "back": [], "dpi": None, "dpi_line": None, "turn": None,
                                        "turn_line": None, "where": where})
            if row.get("turn") is not None:
                _fragment_value(g, "turn", row["turn"].lower(), repr, fid, args.manifest, row["line"],
                                why="a fragment's scans are turned one way: ")
            # the dpi column counts on whichever row of the fragment gives it (an empty first cell included)
            if row.get("dpi") is not None:
                try:
                    row_dpi = check_dpi(row["dpi"], where)
                except ArtifactError as exc:
                    raise ValueError(str(exc)) from None
                _fragment_value(g, "dpi", row_dpi, "{:g}".format, fid, args.manifest, row["line"])
            g[face].append(Path(row["file"]))
        for g in groups.values():   # --dpi and --turn for the fragments whose rows give none
            g["dpi"] = args.dpi if g["dpi"] is None else g["dpi"]
            g["turn"] = args.turn if g["turn"] is None else g["turn"]
    else:
        if not args.fragment:
            raise ValueError("--fragment ID is needed with scans given as arguments")
        groups[fragment_id(args.fragment)] = {"front": [Path(p) for p in args.paths],
                                              "back": [Path(p) for p in args.back], "dpi": args.dpi,
                                              "turn": args.turn, "where": "arguments"}
    items = []
    for fid, g in groups.items():
        g["dpi"] = _dpi_of(fid, g)
        _warn_if_jpeg(fid, g["front"] + g["back"], srgb=bool(args.srgb))
        try:
            dpi = check_dpi(g["dpi"], f"{fid} dpi")
        except ArtifactError as exc:
            raise ValueError(str(exc)) from None
        if g["turn"] not in ("cw", "ccw", "auto"):
            raise ValueError(f"{fid} ({g['where']}): turn {g['turn']!r} must be cw, ccw or auto")
        items.append(ImportItem(name=fid, sources=g["front"] + g["back"], fragment=fid, face="front",
                                options={"dpi": dpi, "turn": g["turn"], "device": args.device,
                                         "faces": {"front": len(g["front"]), "back": len(g["back"])},
                                         "crop": bool(args.crop), "srgb": bool(args.srgb),
                                         "colour_only": bool(args.colour_only)}))
    return items


def _fragment_value(g: dict, key: str, value, show, fid: str, manifest: str, line: int, *, why: str = "") -> None:
    """A fragment's ``key`` (its turn, its dpi) from whichever of its manifest rows gives it: ``g[key]`` and
    ``g[key + "_line"]``. Two rows that give different values are refused, naming the fragment, both values
    (``show``) and both lines."""
    if g[key] is not None and value != g[key]:
        raise ValueError(f"fragment {fid}: {key} {show(g[key])} ({manifest} line {g[key + '_line']}) differs from "
                         f"{key} {show(value)} (line {line}); {why}give the same {key} in all its rows")
    g[key], g[key + "_line"] = value, line


def _dpi_of(fid: str, g: dict) -> float:
    """The scans' dpi: given (``--dpi`` or the manifest), else declared by the files (PNG pHYs, TIFF, JFIF).

    A given dpi the files contradict (by more than 1 %) is used, with a warning naming the file;
    files of one fragment declaring different resolutions, or no dpi given or declared, are refused.
    """
    from common.imports.resolution import resolve_dpi

    dpi, warnings = resolve_dpi(g["front"] + g["back"], g["dpi"], where=f"{fid} ({g['where']})",
                                hint="give --dpi or a dpi column in the manifest")
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    if g["dpi"] is not None:
        return dpi
    log.info("%s: %.4g dpi, read from the files' metadata", fid, dpi)
    return dpi


def _warn_if_jpeg(fid: str, paths: list, *, srgb: bool) -> None:
    """One line on stderr when scans of a fragment are JPEG files (accepted, but they cost normals' accuracy)."""
    from common.imports.door import image_format

    jpegs = [Path(p).name for p in paths if image_format(p) == "jpeg"]
    if jpegs:
        shown = ", ".join(jpegs[:4]) + (f" and {len(jpegs) - 4} more" if len(jpegs) > 4 else "")
        print(f"warning: {fid}: {len(jpegs)} JPEG scan(s) ({shown}): JPEG is 8-bit and lossy, its 8x8 compression "
              f"blocks add noise to the photometric-stereo normals; scan to 16-bit PNG or TIFF where you can"
              + ("" if srgb else " (and pass --srgb unless the scanner wrote them with gamma 1.0)"),
              file=sys.stderr)


def _read_scan(path: Path, opts: dict) -> tuple[np.ndarray, tuple]:
    """One file -> (H, W, 3) uint8/uint16 linear scan and its area in mm, or ImportRefused naming the file."""
    from common.acquisition.capture import check_scan
    from common.acquisition.errors import CaptureError
    from common.acquisition.locate import crop_to_fragment
    from common.imports.door import read_image_checked
    from common.rgbn.io import srgb_to_linear

    img = read_image_checked(path, channels=(1, 3, 4))
    try:
        px = check_scan(img.pixels, str(path))
    except ValueError as exc:
        raise ImportRefused(str(exc)) from None
    if opts["srgb"] and img.bits != 32:   # a float scan is linear already, and check_scan made it 16-bit
        px = np.rint(srgb_to_linear(px.astype(np.float32) / img.full_scale) * 65535).astype(np.uint16)
    dpi = opts["dpi"]
    area = (0.0, 0.0, px.shape[1] * 25.4 / dpi, px.shape[0] * 25.4 / dpi)
    if opts["crop"] and opts.get("single", False):
        try:
            px, area = crop_to_fragment(px, dpi)
        except CaptureError as exc:
            raise ImportRefused(f"{path}: {exc}") from None
    return np.ascontiguousarray(px), area


def _crop_face(scans: list, paths: list, dpi: float) -> list:
    """Whole-bed scans of one face -> the region where they differ (the turned fragment), cut from each."""
    from common.acquisition.errors import CaptureError
    from common.acquisition.locate import locate_changing
    try:
        x0, y0, x1, y1 = locate_changing([s[0] for s in scans], dpi)
    except (CaptureError, ValueError) as exc:
        raise ImportRefused(f"{paths[0]} ... {Path(paths[-1]).name}: {exc}") from None
    p = 25.4 / dpi
    c0, r0, c1, r1 = int(np.floor(x0 / p)), int(np.floor(y0 / p)), int(np.ceil(x1 / p)), int(np.ceil(y1 / p))
    return [(np.ascontiguousarray(px[r0:r1, c0:c1]), (c0 * p, r0 * p, c1 * p, r1 * p)) for px, _ in scans]


def convert(item: ImportItem, store) -> list[Output]:
    """The scans of one fragment -> checked, turn direction found, one ``tessera.scans`` artifact."""
    from common.acquisition.capture import CaptureResult, Scan, check_capture, write_scans
    from common.acquisition.calibration import lamp_direction_from_shadows
    from common.acquisition.errors import RegistrationError
    from common.acquisition.flatbed_normals import register_face
    from common.acquisition.locate import focus_mask, fragment_mask
    from common.acquisition.registration import TurnDirectionError, turn_rotations

    opts = item.options
    n_front, n_back = opts["faces"]["front"], opts["faces"]["back"]
    files = {"front": list(item.sources[:n_front]), "back": list(item.sources[n_front:n_front + n_back])}
    result = CaptureResult(item.fragment, opts["device"], {}, colour_only=opts["colour_only"])
    turns = {}
    for face, paths in files.items():
        scans = [_read_scan(Path(p), {**opts, "single": len(paths) < 2}) for p in paths]
        if scans and len({s[0].dtype for s in scans}) > 1:
            raise ImportRefused(f"{paths[0]}: the {face} scans mix 8-bit and 16-bit files; export them alike")
        if opts["crop"] and len(scans) >= 2:
            if len({s[0].shape[:2] for s in scans}) > 1:
                raise ImportRefused(f"{paths[0]}: --crop needs the {face} scans to be whole-bed scans of one size")
            scans = _crop_face(scans, paths, opts["dpi"])
        if opts["colour_only"]:
            if len(scans) > 1:
                raise ImportRefused(f"{paths[1]}: --colour-only takes one scan per face, {len(scans)} given for "
                                    f"the {face}")
            rotations = [0.0] * len(scans)
        elif len(scans) >= 3:
            # colour masks, or focus masks where colour takes the shadow too (an object of the bed's grey)
            try:
                turn, regs, _, method = register_face([s[0] for s in scans], opts["dpi"], turn=opts["turn"])
            except TurnDirectionError as exc:
                raise ImportRefused(f"{paths[0]} ... {Path(paths[-1]).name} ({face}): {exc}; pass --turn {exc.turn}"
                                    ) from None
            except RegistrationError as exc:
                raise ImportRefused(f"{paths[0]} ... {Path(paths[-1]).name} ({face}): {exc}") from None
            turns[face] = {"turn": turn, "angles_deg": [round(r.angle_deg, 2) for r in regs],
                           "correlation_min": round(min(r.correlation for r in regs), 4), "mask": method}
            try:    # where the scanner's light comes from, for a nominal calibration (tessera calibrate --nominal)
                masks = [(focus_mask if method == "focus" else fragment_mask)(s[0], opts["dpi"]) for s in scans]
                lamp, agree = lamp_direction_from_shadows([s[0] for s in scans], masks, opts["dpi"])
                turns[face]["lamp_direction_deg"] = round(lamp, 1)
                turns[face]["lamp_direction_agreement"] = round(agree, 2)
            except ValueError:
                pass
            rotations = turn_rotations(len(scans), turn)
        else:
            rotations = [0.0] * len(scans)      # too few: check_capture says so below
        result.scans[face] = [Scan(px, opts["dpi"], int(round(rot)), area, 8 if px.dtype == np.uint8 else 16)
                              for (px, area), rot in zip(scans, rotations)]
    try:
        check_capture(result)
    except ValueError as exc:
        raise ImportRefused(f"{item.sources[0]}: {exc}") from None
    for face, t in turns.items():
        log.info("%s %s: turned %s, measured rotations %s, correlation >= %.2f, %s mask, shadows put the lamp at "
                 "%s deg (counter-clockwise from the image's +x)", item.fragment, face, t["turn"], t["angles_deg"],
                 t["correlation_min"], t["mask"], t.get("lamp_direction_deg", "?"))
    prov = {"importer": "tessera import scans", "version": VERSION,
            "source_files": [str(p) for p in item.sources], **item.source_provenance(),
            "turn": {f: t["turn"] for f, t in turns.items()}, "registration_check": turns}
    ref = write_scans(store, item.fragment, result, key=item.key, provenance=prov)
    return [Output("fragment.ready", ref, {"device": opts["device"], "colour_only": bool(opts["colour_only"])})]


def _warn_if_uncalibrated(args) -> None:
    """Say so when the device has no calibration where the solver will look (it would refuse the scans)."""
    from common.acquisition.calibration import newest_calibration
    from common.acquisition.errors import CalibrationError
    from common.store import Store
    try:
        if args.store:
            root = args.store
        else:
            from common.config import config_from_arguments
            root = config_from_arguments(args)["storage"]["root"]
        newest_calibration(Store(root), args.device)
    except CalibrationError:
        print(f"warning: no calibration of device {args.device!r} in {root}: the solver will refuse these scans "
              f"until you run `tessera calibrate --from-files MANIFEST --device {args.device}` (scans of a tilted "
              f"target), or, with no target scans, `tessera calibrate --nominal --lamp-direction-deg D --device "
              f"{args.device}` (D: the lamp side this import logs from the shadows)", file=sys.stderr)
    except Exception:  # storage unreachable: the bench spools; the solver checks later
        pass


def run(args) -> int:
    from services.cli.imports import run_items
    if not args.paths and not args.manifest:
        print("tessera import scans: give the scans of a face (in the order taken), or --manifest CSV",
              file=sys.stderr)
        return 2
    try:
        items = _items(args)
    except ValueError as exc:
        print(f"tessera import scans: {exc}", file=sys.stderr)
        return 2
    _warn_if_uncalibrated(args)
    return run_items(args, items, convert, kind="scans", version=VERSION)
