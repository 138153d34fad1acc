"""``tessera features``: describe an RGBN face (§5.4) and print or store its feature table.

    tessera features RGBN.h5 [--out FEATURES.h5] [--debug-dir D]
    tessera features --store ROOT --fragment ID [--face front] [--config STATION.toml] [--debug-dir D]

The first form reads an RGBN file anywhere; the second finds the fragment's newest RGBN artifact
of that face in the store, runs the feature stage exactly as the worker would (with the station
configuration's ``[services.features]`` settings; content-keyed output under
``fragments/<id>/features/``) and prints the ``features.ready`` event.

With ``--json`` the standard output is the JSON object of the fragment-level values and nothing
else (``tessera features ... --json | python3 -m json.tool`` works): the event, the "wrote" lines
and the errors go to the standard error.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import h5py
import numpy as np

from common.messages import to_json

log = logging.getLogger("tessera.features")


def add_parser(subparsers) -> None:
    from common.config import add_config_arguments

    p = subparsers.add_parser("features", help="compute the feature table of an RGBN face (§5.4)",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("rgbn", nargs="?", help="an RGBN HDF5 file (tessera.rgbn)")
    p.add_argument("--store", help="storage root (with --fragment)")
    p.add_argument("--fragment", help="fragment id in the store")
    p.add_argument("--face", default="front", help="face to describe (default: front)")
    p.add_argument("--out", help="write the table to this HDF5 file (RGBN-file form)")
    p.add_argument("--debug-dir", help="write debug pictures (patches, orientation, erosion) here")
    p.add_argument("--json", action="store_true",
                   help="print the fragment-level values as JSON: stdout is then only the JSON "
                        "(the features.ready event and the 'wrote' lines go to stderr)")
    add_config_arguments(p)   # the --store form reads [services.features] as the worker does
    p.set_defaults(func=run)


def _read_rgbn_file(path: Path, face: str):
    from common.rgbn.image import read_rgbn
    from common.store import ArtifactError
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ArtifactError(f"{path} is not a readable HDF5 file ({exc})") from exc
    with f:
        if "albedo" in f:
            return read_rgbn(f)
        if face in f and "albedo" in f[face]:
            return read_rgbn(f[face])
        raise ArtifactError(f"{path} holds no RGBN image (no albedo at / or /{face})")


def _print_table(table, as_json: bool) -> None:
    if as_json:
        print(to_json(table.values, indent=1))   # NaN and ±inf as null: stdout is for JSON readers
        return
    print(f"face {table.face}: {table.n_patches} patches "
          f"({int(np.sum(table.patch_coverage >= 0.6))} with coverage >= 0.6), "
          f"contour {len(table.contour_mm)} points, work grid {table.work_pixel_mm:.3f} mm, "
          f"missing data: {', '.join(table.missing_data) or 'none'}")
    for k, v in table.values.items():
        print(f"  {k:24s} {v: .5g}")


def run(args) -> int:
    from common.features import extract_features, load_features, save_features
    from common.store import ArtifactError, Store

    # with --json, stdout carries the JSON alone: every other line goes to stderr
    status = sys.stderr if args.json else sys.stdout

    def say(line: str) -> None:
        print(line, file=status)

    def fail(line: str) -> None:
        print(f"tessera features: {line}", file=sys.stderr)

    if bool(args.rgbn) == bool(args.store):
        fail("give either an RGBN file or --store ROOT --fragment ID")
        return 2
    try:
        if args.rgbn:
            image = _read_rgbn_file(Path(args.rgbn), args.face)
            table = extract_features(image, face=args.face)
            if args.out:
                out = Path(args.out).resolve()
                ref = save_features(Store(out.parent), out.name, table,
                                    provenance={"stage": "features", "input": str(args.rgbn)})
                say(f"wrote {out} ({ref.bytes} bytes)")
        else:
            if not args.fragment:
                fail("--store needs --fragment ID")
                return 2
            import services.features as stage
            from common.messages import new_message
            store = Store(args.store)
            rdir = store.path(f"fragments/{args.fragment}/rgbn")
            cands = sorted(rdir.glob(f"{args.face}-*.h5"), key=lambda p: p.stat().st_mtime) if rdir.is_dir() else []
            if not cands:
                fail(f"no RGBN artifact {args.face}-*.h5 under {rdir}")
                return 1
            rel = cands[-1].relative_to(store.root).as_posix()
            job = new_message("rgbn.ready", fragment=args.fragment, face=args.face, artifact=store.ref(rel))

            from common.config import config_from_arguments, service_config

            class _Ctx:
                config: dict = {}

            ctx = _Ctx()
            ctx.config = service_config(config_from_arguments(args), "features")
            ctx.store, ctx.log = store, log
            ctx.progress = lambda f, t: log.debug("%3.0f%% %s", 100 * f, t)
            events = stage.handle(job, ctx)
            say(to_json(events[0], indent=1))
            table = load_features(store, events[0]["artifact"], face=args.face)
            image = None
            if args.debug_dir:
                from common.rgbn.image import load_rgbn
                image = load_rgbn(store, rel)
    except (ArtifactError, ValueError) as exc:
        fail(str(exc))
        return 1
    _print_table(table, args.json)
    if args.debug_dir:
        from common.features.debug import save_debug_pictures
        for p in save_debug_pictures(image, table, args.debug_dir, prefix=f"{args.face}-"):
            say(f"wrote {p}")
    return 0
