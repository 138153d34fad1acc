"""``tessera import rti``: flash / RTI captures on disk -> RGBN faces + ``rgbn.ready`` (thesis §3.2).

    tessera import rti CAPTURE_DIR... [--dome-radius PX|auto] [--store DIR]
    tessera import rti COLLECTION_DIR [--spheres auto [auto]] [--store DIR]

A *capture* is a folder of flash images of one view (JPEG, 8/16-bit PNG/TIFF) with its lights:

* an ``.lp`` light file (RTIBuilder / relight: count, then ``file x y z``; images matched by
  name), or a plain direction file (``dirs.txt``, ``lights.txt``, ``light_directions.txt``:
  ``x y z`` per line, images matched in natural order), optionally ``light_intensities.txt``;
* or no light file: the lights come from the spheres in the frame (``--spheres auto`` finds a
  mirror and, if present, a diffuse sphere; or ``cx,cy,r`` circles in pixels);
* optionally ``mask.png`` (or ``<name>.mask.png``); without it the automatic mask is used
  (light modulation: a frame-filling object keeps the whole frame).

A folder holding no images but sub-folders is a collection: every sub-folder is a capture. The
fragment id is the capture folder's name. Each capture goes through the same code path as
``tessera ps`` (:func:`services.cli.ps.solve_capture`: door checks, mask, near lights, solve,
re-render residual) and becomes ``fragments/<id>/rgbn/<face>-<key>.h5`` + ``rgbn.ready`` (extra
fields ``source: rti``, ``method``) through the import driver (progress, resume, summary,
``--store`` or the bus). A capture any of whose images was already imported as another fragment is
refused naming it (``--allow-duplicates`` imports it anyway), and one imported for the same fragment at
another ``--dpi`` naming both (``--replace``); the light file, intensities and mask are a rig's, often the
same file for every capture, and are not compared. See ``docs/handheld.md`` and ``docs/import.md``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from common.imports import ImportItem, ImportRefused, Output

log = logging.getLogger("tessera.import.rti")

#: algorithm version of this importer: part of every content key (the solver's own is in the provenance)
VERSION = "rti-1"

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
DIRECTION_FILES = ("dirs.txt", "lights.txt", "light_directions.txt", "directions.txt")
INTENSITY_FILES = ("light_intensities.txt", "intensities.txt")


def add_parser(subparsers) -> None:
    from services.cli.imports import add_sink_arguments
    p = subparsers.add_parser("rti", help="flash / RTI captures (.lp or direction files, or spheres in the frame)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", metavar="DIR", help="capture folders, or folders of capture folders")
    p.add_argument("--spheres", nargs="+", metavar="SPEC",
                   help="without a light file: MIRROR [DIFFUSE] spheres in the frame (cx,cy,r in pixels, or auto)")
    p.add_argument("--dome-radius", metavar="PX|auto",
                   help="near lights on a dome of this radius in pixels, or 'auto' (default: distant lights)")
    p.add_argument("--light-positions", type=float, metavar="PX_PER_UNIT",
                   help="the light files give positions (near lights) from the image centre; pixels per unit")
    p.add_argument("--method", choices=("robust", "least_squares"), default="robust")
    p.add_argument("--srgb", choices=("auto", "yes", "no"), default="auto",
                   help="images are sRGB-encoded: auto = JPEGs yes, PNG/TIFF no (default)")
    p.add_argument("--bit-depth", type=int, choices=(8, 16), help="declared bit depth: other files are refused")
    p.add_argument("--dpi", type=float, default=96.0, help="sampling density (nominal if unknown; default 96)")
    p.add_argument("--face", choices=("front", "back"), default="front")
    p.add_argument("--min-mask-share", type=float, default=None, metavar="F",
                   help="refuse an automatic mask keeping less than this share of the frame (default 0.05)")
    p.add_argument("--no-discontinuities", action="store_true", help="skip the depth-discontinuity map")
    add_sink_arguments(p)
    p.set_defaults(func=run)


def _images_in(folder: Path) -> list[Path]:
    from common.acquisition.lightfile import natural_key

    return sorted((c for c in folder.iterdir() if c.is_file() and c.suffix.lower() in IMAGE_SUFFIXES
                   and "mask" not in c.name.lower() and not c.name.startswith(".")), key=natural_key)


def find_captures(paths) -> list[Path]:
    """Capture folders named, or the capture sub-folders of collection folders (natural order)."""
    from common.acquisition.lightfile import natural_key

    out = []
    for p in map(Path, paths):
        if not p.is_dir():
            raise ValueError(f"{p}: not a folder (give capture folders: images + a light file)")
        if _images_in(p):
            out.append(p)
            continue
        subs = sorted((c for c in p.iterdir() if c.is_dir() and not c.name.startswith(".")), key=natural_key)
        caps = [c for c in subs if _images_in(c)]
        if not caps:
            raise ValueError(f"{p}: no images, and no sub-folder with images")
        out += caps
    return out


def describe_capture(folder: Path) -> dict:
    """The files of one capture: images, light file (or None), intensities, mask."""
    lp = sorted(folder.glob("*.lp")) + sorted(folder.glob("*.LP"))
    if len(lp) > 1:
        raise ImportRefused(f"{folder}: {len(lp)} .lp files ({', '.join(p.name for p in lp)}): keep one")
    lights = lp[0] if lp else next((folder / n for n in DIRECTION_FILES if (folder / n).is_file()), None)
    images = _images_in(folder)
    if lights is not None and lp:
        from common.acquisition.lightfile import _basename, read_lp
        try:
            names = read_lp(lights).filenames
        except ValueError as exc:
            raise ImportRefused(str(exc)) from None
        by_name = {p.name.lower(): p for p in images}
        missing = [n for n in names if _basename(n).lower() not in by_name]
        if missing:
            raise ImportRefused(f"{lights}: lists {len(missing)} image(s) not in {folder} (first: {missing[0]})")
        images = [by_name[_basename(n).lower()] for n in names]
    intens = next((folder / n for n in INTENSITY_FILES if (folder / n).is_file()), None)
    masks = sorted(p for p in folder.iterdir() if p.is_file() and "mask" in p.name.lower()
                   and p.suffix.lower() in IMAGE_SUFFIXES)
    if len(masks) > 1:
        raise ImportRefused(f"{folder}: {len(masks)} mask images ({', '.join(p.name for p in masks)}): keep one")
    return {"images": images, "lights": lights, "intensities": intens, "mask": masks[0] if masks else None}


def _items(args) -> list[ImportItem]:
    from common.imports.manifest import fragment_id

    if args.spheres and len(args.spheres) > 2:   # as tessera ps: a third sphere would be silently ignored
        raise ValueError(f"--spheres takes MIRROR [DIFFUSE], got {len(args.spheres)} specs")
    items, used = [], {}
    for folder in find_captures(args.paths):
        fid = fragment_id(folder.name)
        if fid in used:
            raise ValueError(f"{folder}: fragment id {fid} is also the id of {used[fid]}; rename one folder")
        used[fid] = folder
        try:
            files = describe_capture(folder)
            if files["lights"] is None and not args.spheres:
                raise ImportRefused(f"{folder}: no light file (.lp, {', '.join(DIRECTION_FILES)}) and no --spheres: "
                                    "give the spheres in the frame (--spheres auto) or add the light file")
        except ImportRefused as exc:  # refused in the summary, the other captures go on
            items.append(ImportItem(name=folder.name, sources=_images_in(folder), fragment=fid, face=args.face,
                                    options={"refused": str(exc)}))
            continue
        rig = [f for f in (files["lights"], files["intensities"], files["mask"]) if f]
        sources = files["images"] + rig
        srgb = {"yes": True, "no": False}.get(args.srgb)
        if srgb is None:
            srgb = all(p.suffix.lower() in (".jpg", ".jpeg") for p in files["images"])
        # the rig's files (one light file for every capture of a dome) do not say which fragment it is
        items.append(ImportItem(name=folder.name, sources=sources, fragment=fid, face=args.face, shared=rig, options={
            "n_images": len(files["images"]), "lights": files["lights"].name if files["lights"] else None,
            "intensities": files["intensities"].name if files["intensities"] else None,
            "mask": files["mask"].name if files["mask"] else None, "spheres": args.spheres,
            "dome_radius": args.dome_radius, "light_positions": args.light_positions, "method": args.method,
            "srgb": srgb, "dpi": args.dpi, "bit_depth": args.bit_depth,
            "min_mask_share": args.min_mask_share, "discontinuities": not args.no_discontinuities}))
    return items


def convert(item: ImportItem, store) -> list[Output]:
    """One capture folder -> one RGBN face through :func:`services.cli.ps.solve_capture`."""
    from common.rgbn.image import save_rgbn
    from services.cli.ps import solve_capture

    o = item.options
    if "refused" in o:
        raise ImportRefused(o["refused"])
    n = o["n_images"]
    images = [str(p) for p in item.sources[:n]]
    folder = Path(images[0]).parent
    spheres = o["spheres"] or []
    try:
        done = solve_capture(images, lights=str(folder / o["lights"]) if o["lights"] else None,
                             intensities=str(folder / o["intensities"]) if o["intensities"] else None,
                             chrome=spheres[0] if not o["lights"] and spheres else None,
                             diffuse=spheres[1] if not o["lights"] and len(spheres) > 1 else None,
                             mask=str(folder / o["mask"]) if o["mask"] else None, method=o["method"],
                             srgb=o["srgb"], dpi=o["dpi"], bit_depth=o.get("bit_depth"),
                             min_mask_share=o["min_mask_share"],
                             dome_radius=o["dome_radius"], light_positions=o.get("light_positions"),
                             discontinuities=o["discontinuities"])
    except ImportRefused:
        raise
    except ValueError as exc:
        msg = str(exc)
        raise ImportRefused(msg if str(folder) in msg else f"{folder}: {msg}") from None
    for w in done.warnings:
        log.warning("%s: %s", folder, w)
    done.rgbn.attrs.update({"source": "tessera import rti", "face": item.face})
    # the images say which fragment this is, the rig's files do not (common.imports.sources)
    prov = dict(done.provenance, importer="tessera import rti", importer_version=VERSION, capture=str(folder),
                **item.source_provenance())
    ref = save_rgbn(store, f"fragments/{item.fragment}/rgbn/{item.face}-{item.key}.h5", done.rgbn, provenance=prov)
    log.info("%s: re-render residual per image median %.3f, max %.3f", folder.name,
             float(sorted(done.residual)[len(done.residual) // 2]), float(max(done.residual)))
    return [Output("rgbn.ready", ref, {"face": item.face, "source": "rti", "method": o["method"]})]


def run(args) -> int:
    from services.cli.imports import run_items
    try:
        items = _items(args)
    except (ValueError, ImportRefused) as exc:
        print(f"tessera import rti: {exc}", file=sys.stderr)
        return 2
    return run_items(args, items, convert, kind="rti", version=VERSION, out=sys.stdout)  # the stdout of now (tests swap it)
