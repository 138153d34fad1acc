"""``tessera calibrate``: calibrate a flatbed's lamp model from a tilted diffuse target (§3.3.5).

    tessera calibrate                         # the simulated scanner (default [scanner] device)
    tessera calibrate --device sane --sane-device epson2:libusb:001:004
    tessera calibrate --show                  # print the newest valid calibration

Scans the target at tilts 0–25° and eight rotations (a real scanner asks the operator to set up
each pose), fits I(n) = a·(nx, ny, nz, 1), prints the leave-one-out error of the first- and
second-order models and stores ``calibration/<scanner>/<UTC date>-<key>.h5`` under the storage
root. The solver uses the newest valid calibration of the device that made the scans.
"""

from __future__ import annotations

import json

from common.config import add_config_arguments, config_from_arguments


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("calibrate", help="calibrate the scanner's lamp model (§3.3.5)",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--device", choices=["simulated", "sane"], help="scanner backend (default: [scanner] device)")
    p.add_argument("--sane-device", help="SANE device name (default: [scanner] sane_device)")
    p.add_argument("--name", help="scanner name to store the calibration under (default: the device's name)")
    p.add_argument("--tilts", default="0,5,10,15,20,25", help="target tilts in degrees (comma-separated)")
    p.add_argument("--azimuths", default="0,45,90,135,180,225,270,315", help="target rotations in degrees")
    p.add_argument("--dpi", type=float, default=150.0, help="scan resolution of the target (default 150)")
    p.add_argument("--target-albedo", type=float, default=0.8, help="diffuse reflectance of the target (default 0.8)")
    p.add_argument("--show", action="store_true", help="print the newest valid calibration and exit")
    add_config_arguments(p)
    p.set_defaults(func=run)


def _floats(text: str, name: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise SystemExit(f"--{name} must be comma-separated numbers, got {text!r}")


def run(args) -> int:
    from common.acquisition.calibration import (calibrate_scanner, newest_calibration, save_calibration,
                                                simulated_target_operator)
    from common.acquisition.errors import CalibrationError, CaptureError
    from common.store import Store

    cfg = config_from_arguments(args)
    store = Store(cfg["storage"]["root"])
    device = args.device or cfg["scanner"]["device"]
    if device == "simulated":
        from common.acquisition.flatbed_sim import SimulatedFlatbed
        scanner = SimulatedFlatbed(args.name or "sim", seed=int(cfg["scanner"]["seed"]))
        operator, area = simulated_target_operator(scanner), (50.0, 50.0, 70.0, 70.0)
    else:
        if args.show:
            scanner = None
        else:
            from common.acquisition.scanners import SaneScanner
            try:
                scanner = SaneScanner(args.sane_device or cfg["scanner"]["sane_device"])
            except CaptureError as exc:
                print(exc.operator_message)
                return 1
            if args.name:
                scanner.name = args.name

            def operator(tilt, azimuth):
                input(f"Set the calibration target at tilt {tilt:g}° turned to {azimuth:g}°, close the lid, "
                      "and press Enter ")
        area = None
    name = args.name or (scanner.name if scanner is not None else args.sane_device or cfg["scanner"]["sane_device"])
    if args.show:
        try:
            cal, ref = newest_calibration(store, name)
        except CalibrationError as exc:
            print(exc)
            return 1
        print(json.dumps({"scanner": cal.scanner, "date": cal.date, "a": [float(v) for v in cal.a],
                          "cv_rmse": cal.cv_rmse, "order": cal.order, "path": ref.path}, indent=2))
        return 0
    try:
        cal = calibrate_scanner(scanner, operator, tilts=_floats(args.tilts, "tilts"),
                                azimuths=_floats(args.azimuths, "azimuths"), dpi=args.dpi, area_mm=area,
                                target_albedo=args.target_albedo,
                                progress=lambda f, t: print(f"[{f:4.0%}] {t}", flush=True))
    except CaptureError as exc:
        print(exc.operator_message)
        return 1
    except CalibrationError as exc:
        print(f"calibration failed: {exc}")
        return 1
    ref = save_calibration(store, cal)
    a = ", ".join(f"{v:+.4f}" for v in cal.a)
    print(f"scanner {cal.scanner}: a = ({a}) from {len(cal.intensities)} target scans")
    print(f"leave-one-out RMS error: first order {cal.cv_rmse['first']:.4f}, second order {cal.cv_rmse['second']:.4f} "
          f"(full scale 1) -> {'first' if cal.order == 1 else 'second'}-order model recommended"
          + ("" if cal.order == 1 else "; the solver still uses the first-order model of eq. 3.4"))
    print(f"stored {ref.path}")
    return 0
