"""``tessera calibrate``: calibrate a flatbed's lamp model from a tilted diffuse target (§3.3.5).

    tessera calibrate                         # the simulated scanner (default [scanner] device)
    tessera calibrate --device sane --sane-device epson2:libusb:001:004
    tessera calibrate --show                  # print the newest valid calibration
    tessera calibrate --show --device epson-v850   # ... of a scanner calibrated --from-files or --nominal
    tessera calibrate --from-files targets.csv --device epson-v850 [--dpi 300]  # scans of a target made elsewhere
    tessera calibrate --nominal --lamp-direction-deg 170 --device old-flatbed  # no target scans at all

Scans the target at tilts 0–25° and eight rotations (a real scanner asks the operator to set up
each pose), fits I(n) = a·(nx, ny, nz, 1), prints the leave-one-out error of the first- and
second-order models and stores ``calibration/<scanner>/<UTC date>-<key>.h5`` under the storage
root. The solver uses the newest valid calibration of the device that made the scans.

``--from-files MANIFEST`` fits the same model to target scans already on disk (any scanner; PNG or
TIFF, 8/16-bit, grey or RGB). The manifest is a CSV file with a header and the columns

    file,tilt_deg,tilt_direction_deg
    flat.png,0,0
    t10_a0.png,10,0
    t10_a90.png,10,90

``file`` is relative to the manifest's folder; ``tilt_deg`` is the angle between the target's
normal and the glass's normal; ``tilt_direction_deg`` is the direction, on the scan image as it
is displayed, towards which the normal leans: 0 = towards the image's right edge (increasing
column), 90 = towards its top edge (decreasing row), counter-clockwise on screen — the target's
edge on that side is the one lifted off the glass, the opposite edge lies on it (the reading is
taken there, by a linear fit along the tilt direction: the light changes with the distance from
the glass, and fragments lie on it). Each scan shows the target with a ring of bed
around it, or is a crop of the target alone. Scans with more than ``--max-clipped`` of the target's
pixels clipped (saturated, or at 0) are dropped and listed; the report gives each file's reading,
clipped pixels and fit residual. Every file is checked at the door (decodes fully, not blank);
a refused file stops the calibration and nothing is stored.
The dpi (the mm scale of the fit along the tilt) is ``--dpi``, else what the files declare, as for
``tessera import scans``: files declaring none, or different ones, are refused (exit 2).

``--nominal --lamp-direction-deg D`` is for a scanner with no target scans: the simulator's
first-order model turned so that its light comes from D (counter-clockwise from the image's +x
axis, 0 = right, 90 = top; ``tessera import scans`` logs D from the shadows beside the fragment).
The relief it gives is right; its tilt angles are nominal (docs/flatbed.md).

``--show`` prints the newest valid calibration of one scanner: ``--name NAME``, else ``--device
NAME`` for a scanner calibrated ``--from-files`` or ``--nominal`` (stored under that name), else
the simulated scanner (``sim``) or, with ``--device sane``, the SANE device's name.
"""

from __future__ import annotations

import math
import sys

from common.config import add_config_arguments, config_from_arguments
from common.messages import to_json


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("calibrate", help="calibrate the scanner's lamp model (§3.3.5)",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--device", help="scanner backend, simulated | sane (default: [scanner] device); with "
                                    "--from-files or --nominal the device's name, under which the calibration is "
                                    "stored; with --show that name finds it")
    p.add_argument("--from-files", metavar="MANIFEST",
                   help="fit from target scans on disk listed in a CSV manifest (file,tilt_deg,tilt_direction_deg)")
    p.add_argument("--nominal", action="store_true",
                   help="no target scans: store the nominal lamp model (the simulator's) turned to "
                        "--lamp-direction-deg, under --device NAME; relief only, angles are not measured")
    p.add_argument("--lamp-direction-deg", type=float,
                   help="with --nominal: direction towards the lamp on the scan image, counter-clockwise from its "
                        "+x axis (0 right, 90 top); `tessera import scans` logs it from the shadows")
    p.add_argument("--face-depth-mm", type=float, default=0.75,
                   help="with --from-files: height above the glass at which tilted targets are read, where a "
                        "fragment's face lies on average (default 0.75 mm)")
    p.add_argument("--max-clipped", type=float, default=0.01,
                   help="drop target scans with more than this fraction of clipped pixels (default 0.01)")
    p.add_argument("--sane-device", help="SANE device name (default: [scanner] sane_device)")
    p.add_argument("--name", help="scanner name to store the calibration under (default: the device's name)")
    p.add_argument("--tilts", default="0,5,10,15,20,25", help="target tilts in degrees (comma-separated)")
    p.add_argument("--azimuths", default="0,45,90,135,180,225,270,315", help="target rotations in degrees")
    p.add_argument("--dpi", type=float,
                   help="scan resolution of the target (default 150; with --from-files, what the files declare: "
                        "PNG pHYs, TIFF XResolution, JPEG density)")
    p.add_argument("--target-albedo", type=float, default=0.8, help="diffuse reflectance of the target (default 0.8)")
    p.add_argument("--show", action="store_true",
                   help="print the newest valid calibration of --name NAME, else of --device (simulated, sane, or "
                        "the name given to --from-files / --nominal), and exit")
    add_config_arguments(p)
    p.set_defaults(func=run)


def _floats(text: str, name: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise SystemExit(f"tessera calibrate: --{name} must be comma-separated numbers, got {text!r}")


def _error(text) -> None:
    """An error on the standard error (the standard output is for results: a report, --show's JSON)."""
    print(f"tessera calibrate: {text}", file=sys.stderr)


def _scan_dpi(args) -> float:
    """The dpi to scan at (or record) when no files say it: ``--dpi``, else 150."""
    return 150.0 if args.dpi is None else args.dpi


def run(args) -> int:
    from common.acquisition.calibration import (calibrate_scanner, save_calibration, simulated_target_operator,
                                                target_poses)
    from common.acquisition.errors import CalibrationError, CaptureError
    from common.imports import ProgressBar
    from common.store import Store

    cfg = config_from_arguments(args)
    store = Store(cfg["storage"]["root"])
    if args.show:
        return _show(args, store, cfg)
    if args.from_files:
        return _from_files(args, store)
    if args.nominal:
        return _nominal(args, store)
    device = args.device or cfg["scanner"]["device"]
    if device not in ("simulated", "sane"):
        _error(f"--device must be simulated or sane (or a device name with --from-files, --nominal or --show), "
               f"got {device!r}")
        return 2
    # the target poses are checked before the scanner is opened and the operator asked to set anything up
    tilts, azimuths = _floats(args.tilts, "tilts"), _floats(args.azimuths, "azimuths")
    bad = [t for t in tilts if not 0 <= t < 90] + [a for a in azimuths if not math.isfinite(a)]
    if bad:
        _error(f"--tilts must be degrees in [0, 90) and --azimuths finite degrees, got {', '.join(map(str, bad))}")
        return 2
    try:
        n_poses = len(target_poses(tilts, azimuths))
    except ValueError as exc:   # too few poses to fit
        _error(exc)
        return 2
    if device == "simulated":
        from common.acquisition.flatbed_sim import SimulatedFlatbed
        scanner = SimulatedFlatbed(args.name or "sim", seed=int(cfg["scanner"]["seed"]))
        operator, area = simulated_target_operator(scanner), (50.0, 50.0, 70.0, 70.0)
    else:
        from common.acquisition.scanners import SaneScanner
        try:
            scanner = SaneScanner(args.sane_device or cfg["scanner"]["sane_device"])
        except CaptureError as exc:
            _error(exc.operator_message)
            return 1
        if args.name:
            scanner.name = args.name

        from services.scanner import ask

        def operator(tilt, azimuth):   # on the standard error with the progress: the standard output is the report
            ask(f"Set the calibration target at tilt {tilt:g}° turned to {azimuth:g}°, close the lid, "
                "and press Enter ", sys.stderr)
        area = None
    # progress on the standard error, as --from-files: the standard output is for the report
    bar = ProgressBar(n_poses, "target scans")
    try:
        cal = calibrate_scanner(scanner, operator, tilts=tilts, azimuths=azimuths, dpi=_scan_dpi(args), area_mm=area,
                                target_albedo=args.target_albedo,
                                progress=lambda f, t: bar.update(round(f * bar.total), t))
    except CaptureError as exc:
        bar.close()
        _error(exc.operator_message)
        return 1
    except CalibrationError as exc:
        bar.close()
        _error(f"calibration failed: {exc}")
        return 1
    except EOFError:   # the operator's input closed before every target pose was scanned: nothing is stored
        bar.close()
        _error(f"stopped: the operator's input closed before the {n_poses} target poses were scanned; "
               "no calibration stored")
        return 1
    bar.close()
    ref = save_calibration(store, cal)
    a = ", ".join(f"{v:+.4f}" for v in cal.a)
    print(f"scanner {cal.scanner}: a = ({a}) from {len(cal.intensities)} target scans")
    print(f"leave-one-out RMS error: first order {cal.cv_rmse['first']:.4f}, second order {cal.cv_rmse['second']:.4f} "
          f"(full scale 1) -> {'first' if cal.order == 1 else 'second'}-order model recommended"
          + ("" if cal.order == 1 else "; the solver still uses the first-order model of eq. 3.4"))
    print(f"stored {ref.path}")
    return 0


def _show(args, store, cfg) -> int:
    """``--show``: the newest valid calibration of ``--name``, else of ``--device`` (see the module doc)."""
    from common.acquisition.calibration import newest_calibration
    from common.acquisition.errors import CalibrationError

    if args.from_files or args.nominal:
        _error("--show prints a stored calibration; it does not go with --from-files or --nominal "
               "(calibrate first, then --show --device NAME)")
        return 2
    device = args.device or cfg["scanner"]["device"]
    if args.name:
        name = args.name
    elif device == "simulated":
        name = "sim"                                   # the simulated scanner's name (SimulatedFlatbed)
    elif device == "sane":
        name = args.sane_device or cfg["scanner"]["sane_device"]
    else:
        name = device                                  # a scanner calibrated --from-files or --nominal
    try:
        cal, ref = newest_calibration(store, name)
    except CalibrationError as exc:
        hint = "" if device in ("simulated", "sane") and not args.name else (
            f" (a scanner without a station device is calibrated by `tessera calibrate --from-files MANIFEST "
            f"--device {name}` or `--nominal --lamp-direction-deg D --device {name}`)")
        _error(f"{exc}{hint}")
        return 1
    print(to_json({"scanner": cal.scanner, "date": cal.date, "a": [float(v) for v in cal.a],
                      "cv_rmse": cal.cv_rmse, "order": cal.order, "path": ref.path}, indent=2))
    return 0


def _nominal(args, store) -> int:
    """``--nominal``: a scanner with no target scans gets the nominal lamp model turned to its lamp side."""
    import math
    from common.acquisition.calibration import nominal_calibration, save_calibration

    if not args.device or args.device in ("simulated", "sane"):
        _error("--nominal needs --device NAME: the name of the scanner that made the scans")
        return 2
    if args.lamp_direction_deg is None or not math.isfinite(args.lamp_direction_deg):
        _error("--nominal needs --lamp-direction-deg D: where the scanner's light comes from on its images, "
               "counter-clockwise from the +x axis (0 right, 90 top); `tessera import scans` logs it from the shadows")
        return 2
    cal = nominal_calibration(args.device, args.lamp_direction_deg, dpi=_scan_dpi(args))
    ref = save_calibration(store, cal)
    a = ", ".join(f"{v:+.4f}" for v in cal.a)
    print(f"scanner {cal.scanner}: NOMINAL model a = ({a}) (the simulator's lamp turned to "
          f"{args.lamp_direction_deg:g} deg; no target was measured: the relief is right, angles are nominal)")
    print(f"stored {ref.path}")
    return 0


def read_manifest(path) -> list[tuple]:
    """Rows ``(file path, tilt_deg, tilt_direction_deg)`` of a target manifest (see the module doc).

    Raises ValueError naming the manifest, the line and what is wrong.
    """
    import csv
    import math
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: manifest does not exist")
    with open(path, newline="", encoding="utf-8-sig") as fh:
        rows = list(csv.reader(fh))
    rows = [r for r in rows if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if not rows:
        raise ValueError(f"{path}: manifest is empty")
    header = [c.strip().lower() for c in rows[0]]
    need = ("file", "tilt_deg", "tilt_direction_deg")
    missing = [c for c in need if c not in header]
    if missing:
        raise ValueError(f"{path}: header must name the columns {', '.join(need)}; missing {', '.join(missing)} "
                         f"(got {', '.join(header)})")
    col = {c: header.index(c) for c in need}
    out = []
    for line, r in enumerate(rows[1:], start=2):
        try:
            name = r[col["file"]].strip()
            tilt, direction = float(r[col["tilt_deg"]]), float(r[col["tilt_direction_deg"]])
        except (IndexError, ValueError):
            raise ValueError(f"{path}, line {line}: expected a file name and two numbers, got {r}") from None
        if not name:
            raise ValueError(f"{path}, line {line}: empty file name")
        if not (math.isfinite(tilt) and 0 <= tilt < 60):
            raise ValueError(f"{path}, line {line}: tilt_deg must be in [0, 60), got {tilt}")
        if not math.isfinite(direction):
            raise ValueError(f"{path}, line {line}: tilt_direction_deg must be a number, got {direction}")
        out.append((path.parent / name, tilt, direction))
    return out


def _from_files(args, store) -> int:
    from common.acquisition.calibration import TargetReading, fit_target_readings, read_target, save_calibration
    from common.acquisition.errors import CalibrationError
    from common.imports import ImportRefused, ProgressBar
    from common.imports.door import BLACK_FRACTION, read_image_checked
    from common.imports.resolution import resolve_dpi
    from common.limits import check_dpi
    from common.store import ArtifactError

    if not args.device or args.device in ("simulated", "sane"):
        _error("--from-files needs --device NAME: the name of the scanner that made the target scans "
               "(the calibration is stored under it, and `tessera import scans --device NAME` uses it)")
        return 2
    if not 0 <= args.face_depth_mm <= 5:
        _error(f"--face-depth-mm must be in [0, 5], got {args.face_depth_mm}")
        return 2
    try:
        rows = read_manifest(args.from_files)
    except ValueError as exc:
        _error(f"calibration failed: {exc}")
        return 1
    # the dpi sets the mm scale of the lamp's change along the tilt: --dpi, else what the files
    # declare, as `tessera import scans` does; never a silent default
    try:
        dpi, warnings = resolve_dpi([r[0] for r in rows], args.dpi, where=str(args.from_files))
        dpi = check_dpi(dpi, "--dpi" if args.dpi is not None else f"{args.from_files}: the files' declared")
    except (ValueError, ArtifactError) as exc:
        _error(exc)
        return 2
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    readings: list[TargetReading] = []
    bar = ProgressBar(len(rows), "target scans")
    try:
        for i, (path, tilt, direction) in enumerate(rows):
            # a tight crop of a plain target may look "blank" to the door: check black here instead
            img = read_image_checked(path, channels=(1, 3, 4), allow_blank=True)
            px = img.pixels[..., :3] if img.pixels.ndim == 3 else img.pixels
            if float(px.max()) < BLACK_FRACTION * img.full_scale:
                raise ImportRefused(f"{path}: is all black: lamp off or lid open?")
            try:
                readings.append(read_target(px, dpi, tilt_deg=tilt, direction_deg=direction,
                                            depth_mm=args.face_depth_mm))
            except CalibrationError as exc:
                raise ImportRefused(f"{path}: {exc}") from exc
            bar.update(i + 1)
    except ImportRefused as exc:
        bar.close()
        _error(f"calibration failed, nothing stored: {exc}")
        return 1
    bar.close()
    try:
        cal = fit_target_readings(args.device, readings, [r[1] for r in rows], [r[2] for r in rows],
                                  names=[str(r[0].name) for r in rows], target_albedo=args.target_albedo,
                                  max_clipped=args.max_clipped, dpi=dpi,
                                  depth=16)
    except (CalibrationError, ValueError) as exc:
        _error(f"calibration failed, nothing stored: {exc}")
        return 1
    print(format_report(cal))
    ref = save_calibration(store, cal)
    print(f"stored {ref.path}")
    return 0


def format_report(cal) -> str:
    """The fit-quality report: one line per target scan, dropped ones with the reason, then the model."""
    lines = [f"{'file':<28} {'tilt':>5} {'dir':>6} {'reading':>8} {'clipped':>9} {'residual':>9}  status"]
    for e in cal.report:
        lines.append(f"{e['name'][:28]:<28} {e['tilt_deg']:5.1f} {e['direction_deg']:6.1f} {e['value']:8.4f} "
                     f"{e['clipped']:>4}/{e['pixels']:<4} {e.get('residual', float('nan')):+9.4f}  "
                     + ("used" + (" (whole image)" if e["whole_image"] else "") if e["used"]
                        else f"DROPPED: {e['reason']}"))
    dropped = sum(not e["used"] for e in cal.report)
    a = ", ".join(f"{v:+.4f}" for v in cal.a)
    lines.append(f"scanner {cal.scanner}: a = ({a}) from {len(cal.report) - dropped} target scans"
                 + (f", {dropped} dropped (clipped)" if dropped else ""))
    lines.append(f"fit RMS residual {cal.fit_rms:.4f}; leave-one-out RMS error: first order {cal.cv_rmse['first']:.4f}, "
                 f"second order {cal.cv_rmse['second']:.4f} (full scale 1, albedo 1)")
    if any(float(v) != 0 for v in cal.a_per_mm):
        lines.append(f"a read at {cal.a_depth_mm:g} mm from the glass; change per mm of distance: a_per_mm = ("
                     + ", ".join(f"{v:+.4f}" for v in cal.a_per_mm) + ")")
    return "\n".join(lines)
