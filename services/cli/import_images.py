"""``tessera import images``: colour-only fragments from pictures (cut-outs with alpha, or a plain background).

    tessera import images PHOTOS_OR_FOLDERS... --dpi 300 [--store DIR]
    tessera import images --manifest finds.csv [--dpi 300] [--store DIR]

Each picture (PNG/TIFF 8/16-bit, JPEG; RGB, RGBA or grey) becomes one colour-only RGBN face
``fragments/<id>/rgbn/<face>-<key>.h5`` and one ``rgbn.ready`` event, as a capture would give.
The fragment id is the file's stem, or the manifest's inventory number; the manifest's metadata
(inventory, find-spot, context, date, notes, other columns) is kept in the artifact
(``attrs['metadata']``, JSON) and in the event. A picture whose content was already imported as
another fragment is refused naming it (``--allow-duplicates`` imports it anyway), and one imported
for the same fragment at another dpi naming both (``--replace``). See ``docs/import.md``.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

from common.imports import ImportItem, ImportRefused, Output

#: algorithm version of this importer: part of every content key
VERSION = "images-3"   # 2: the face cut to the fragment and 2 mm round it (attrs crop_px); 3: plain-background
                       # edges at half coverage, unmixed (common.imports.fragments.edge_coverage)
#: below this share of a plain-background piece's edge placed at half coverage, the import warns
EDGE_PLACED_WARN = 0.5


def add_parser(subparsers) -> None:
    from services.cli.imports import add_sink_arguments
    p = subparsers.add_parser("images", help="colour-only fragment pictures (alpha cut-outs or plain background)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="*", metavar="PATH", help="picture files or folders of them")
    p.add_argument("--manifest", metavar="CSV", help="file, inventory, find_spot, context, date, notes[, dpi, face] "
                                                     "columns (docs/import.md)")
    p.add_argument("--dpi", type=float, help="sampling of the pictures (unless the manifest has a dpi column)")
    p.add_argument("--face", default="front", choices=("front", "back"), help="face shown (default front)")
    p.add_argument("--background", choices=("auto", "alpha", "plain"), default="auto",
                   help="mask from the alpha channel, from a plain background, or auto (default)")
    p.add_argument("--linear", action="store_true", help="the pictures hold linear values (no sRGB decoding)")
    p.add_argument("--pictures", metavar="DIR", help="also write each imported mask over its picture, <id>-<face>.png")
    add_sink_arguments(p)
    p.set_defaults(func=run)


def _items(args) -> list[ImportItem]:
    from common.imports.manifest import expand_paths, fragment_id, read_manifest
    from common.limits import check_dpi
    from common.store import ArtifactError

    rows = read_manifest(args.manifest) if args.manifest else []
    by_file = {Path(r["file"]).resolve(): r for r in rows}
    files = expand_paths(args.paths) if args.paths else [Path(r["file"]) for r in rows]
    items, used = [], {}
    for f in files:
        row = by_file.get(f.resolve(), {})
        where = f"{args.manifest} line {row['line']}" if row else str(f)
        fid = fragment_id(row.get("inventory") or f.stem)
        face = row.get("face", args.face).lower()
        if face not in ("front", "back"):
            raise ValueError(f"{where}: face {face!r} must be front or back")
        if (fid, face) in used:
            raise ValueError(f"{where}: fragment {fid} ({face}) is also given by {used[fid, face]}; "
                             "give each picture its own inventory number")
        used[fid, face] = where
        raw_dpi = row.get("dpi", args.dpi)
        if raw_dpi is None:
            raise ValueError(f"{where}: no dpi: give --dpi or a dpi column in the manifest")
        try:
            dpi = check_dpi(raw_dpi, where)
        except ArtifactError as exc:
            raise ValueError(str(exc)) from None
        metadata = {k: v for k, v in row.items() if k not in ("file", "line", "dpi", "face")}
        metadata["source_file"] = f.name
        items.append(ImportItem(name=f.name, sources=[f], fragment=fid, face=face,
                                options={"dpi": dpi, "background": args.background, "linear": bool(args.linear),
                                         "metadata": metadata}))
    return items


def convert(item: ImportItem, store, *, pictures: str | None = None) -> list[Output]:
    """One picture -> one colour-only RGBN face (door checks, mask, metadata); ``pictures``: a
    folder for the mask drawn over the picture."""
    from common.imports.door import read_image_checked
    from common.imports.fragments import crop_to_mask, fragment_from_image
    from common.rgbn.image import save_rgbn

    import numpy as np

    src = Path(item.sources[0])
    image = read_image_checked(src)
    opts = item.options
    try:
        rgbn = fragment_from_image(image.pixels, dpi=opts["dpi"], background=opts["background"],
                                   srgb=not opts["linear"] and image.bits != 32)
    except ImportRefused as exc:
        raise ImportRefused(f"{src}: {exc}") from None
    except ValueError as exc:  # e.g. --background alpha on a picture without alpha
        raise ImportRefused(f"{src}: {exc}") from None
    placed = rgbn.attrs.get("edge_placed")
    if placed is not None and placed < EDGE_PLACED_WARN:
        print(f"warning: {item.fragment} ({src.name}): the piece's edge could be placed at half coverage along only "
              f"{placed * 100:.0f} % of it: the background is too close to the piece's colour, so the outline may be "
              "off by a pixel or two and parts as pale or dark as the background lost; scan or photograph it on a "
              "background that differs from the plaster (docs/import.md)", file=sys.stderr)
    rgbn, (x0, y0) = crop_to_mask(rgbn)   # the piece, not the picture's background round it
    rgbn.attrs.update({"source": "tessera import images", "face": item.face,
                       "metadata": json.dumps(opts["metadata"], sort_keys=True, ensure_ascii=False)})
    prov = {"importer": "tessera import images", "version": VERSION, "source_file": str(src),
            **item.source_provenance(), "mask_from": rgbn.attrs["mask_from"],
            "crop_px": [x0, y0]}
    if placed is not None:
        prov["edge_placed"] = placed
    ref = save_rgbn(store, f"fragments/{item.fragment}/rgbn/{item.face}-{item.key}.h5", rgbn, provenance=prov)
    if pictures:
        from common.imports.fragments import mask_picture
        from common.synth.figures import save_png
        colour = image.pixels if image.pixels.ndim == 3 else image.pixels[..., None]
        colour = colour[..., :3] if colour.shape[2] >= 3 else np.repeat(colour[..., :1], 3, axis=2)
        h, w = rgbn.mask.shape
        save_png(Path(pictures) / f"{item.fragment}-{item.face}.png",
                 mask_picture(colour[y0:y0 + h, x0:x0 + w], rgbn.mask))
    return [Output("rgbn.ready", ref, {"face": item.face, "colour_only": True, "metadata": opts["metadata"]})]


def _pictures_in_subfolders(paths) -> str:
    """Why folders named gave no picture, when their pictures are one level down (a collection kept one
    folder per object, as RePAIR's): the folders and their subfolders that hold pictures, or ""."""
    from common.imports.manifest import expand_paths, picture_subfolders

    notes = []
    for folder in (Path(p) for p in paths):
        if not folder.is_dir() or expand_paths([folder]):
            continue
        subs = [(c, len(expand_paths([c]))) for c in picture_subfolders(folder)]
        if subs:
            shown = ", ".join(f"{c.name} ({n} picture{'s' if n > 1 else ''})" for c, n in subs[:8])
            more = f" and {len(subs) - 8} more" if len(subs) > 8 else ""
            notes.append(f"{folder} holds no picture itself, and subfolders are not searched; its subfolders "
                         f"{shown}{more} do: name them (e.g. {folder}/*/) or list them in a --manifest")
    return "; ".join(notes)


def run(args) -> int:
    from services.cli.imports import run_items
    if not args.paths and not args.manifest:
        print("tessera import images: give picture files or folders, or --manifest CSV", file=sys.stderr)
        return 2
    try:
        items = _items(args)
    except ValueError as exc:
        print(f"tessera import images: {exc}", file=sys.stderr)
        return 2
    if args.pictures and Path(args.pictures).exists() and not Path(args.pictures).is_dir():
        print(f"tessera import images: --pictures {args.pictures} is a file, not a folder", file=sys.stderr)
        return 2
    if not items and args.paths:
        hint = _pictures_in_subfolders(args.paths)
        if hint:
            print(f"tessera import images: nothing to import: {hint}", file=sys.stderr)
            return 2
    return run_items(args, items, functools.partial(convert, pictures=args.pictures), kind="images",
                     version=VERSION)
