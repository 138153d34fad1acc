"""``tessera import normals``: normal maps + albedo made by other tools (RTIBuilder, Relight, ...) -> RGBN faces.

    tessera import normals CAPTURE_FOLDERS_OR_MAPS... --dpi 600 [--convention opengl|directx|auto] [--store DIR]
    tessera import normals piece_normals.png --albedo piece_albedo.png --fragment F0042 --dpi 600
    tessera import normals --manifest maps.csv [--store DIR]

A normal map (8/16-bit PNG/TIFF, or float TIFF/.npy holding the vectors) becomes one RGBN face
``fragments/<id>/rgbn/<face>-<key>.h5`` and one ``rgbn.ready`` event. Pairing: a folder holding
``normals.png`` (any name containing "normal") and ``albedo.png`` (the same name with "albedo"
instead) is one fragment named after the folder; a file ``X_normals.png`` pairs with
``X_albedo.png`` and names fragment ``X``. The manifest has ``file`` (the normal map),
``albedo``, ``inventory``, ``dpi``, ``face``, ``convention`` and metadata columns (docs/import.md).

Checked at the door: a map must decode to unit vectors facing the viewer (a photograph passed as
a normal map is refused), and its green channel must match the declared convention (the normals
of a real surface are integrable only one way); ``--convention auto`` picks it from the data.
A map or albedo already imported as another fragment is refused naming it (``--allow-duplicates``
imports it anyway), and one imported for the same fragment at another dpi naming both dpi values
(``--replace``); see docs/import.md.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from common.imports import ImportItem, ImportRefused, Output

#: algorithm version of this importer: part of every content key
VERSION = "normals-1"
_NORMAL = re.compile(r"normals?", re.IGNORECASE)


def add_parser(subparsers) -> None:
    from services.cli.imports import add_sink_arguments
    p = subparsers.add_parser("normals", help="normal maps + albedo made by other tools (OpenGL or DirectX)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="*", metavar="PATH", help="normal-map files, or folders holding normals + albedo")
    p.add_argument("--albedo", metavar="FILE", help="albedo of the one normal map given")
    p.add_argument("--fragment", metavar="ID", help="fragment id of the one normal map given")
    p.add_argument("--manifest", metavar="CSV", help="file, albedo, inventory, dpi, face, convention, metadata columns")
    p.add_argument("--dpi", type=float, help="sampling of the maps (unless the manifest has a dpi column)")
    p.add_argument("--face", default="front", choices=("front", "back"))
    p.add_argument("--convention", choices=("opengl", "directx", "auto"), default="opengl",
                   help="green = y up (opengl, default), y down (directx), or told from the data (auto)")
    p.add_argument("--linear", action="store_true", help="albedo holds linear values (no sRGB decoding)")
    add_sink_arguments(p)
    p.set_defaults(func=run)


def _albedo_for(normal_map: Path) -> Path | None:
    from common.imports.manifest import IMAGE_SUFFIXES
    base = _NORMAL.sub("albedo", normal_map.stem)
    if base == normal_map.stem:
        return None
    for suffix in (normal_map.suffix,) + IMAGE_SUFFIXES:
        for name in (base + suffix, base.lower() + suffix):
            cand = normal_map.with_name(name)
            if cand.is_file():
                return cand
    return None


def _pairs(paths) -> list[tuple[Path, Path | None, str, str | None]]:
    """(normal map, albedo or None, default id, face or None) for files and folders named.

    In a folder, a map named ``front-normals.png`` / ``back_normal.tif`` (what ``tessera export``
    writes) is that face of the fragment named after the folder.
    """
    from common.imports.manifest import IMAGE_SUFFIXES, expand_paths
    out = []
    for p in map(Path, paths):
        if p.is_dir():
            maps = [c for c in expand_paths([p], IMAGE_SUFFIXES + (".npy",)) if _NORMAL.search(c.stem)]
            if not maps:
                raise ValueError(f"folder {p} holds no file whose name contains 'normal'")
            for m in maps:
                rest = _rest(m)
                face = rest.lower() if rest.lower() in ("front", "back") else None
                fid = p.resolve().name if len(maps) == 1 or face else (rest or p.resolve().name)
                out.append((m, _albedo_for(m), fid, face))
        else:
            rest = _rest(p)
            out.append((p, _albedo_for(p), rest or p.parent.resolve().name, None))
    return out


def _rest(normal_map: Path) -> str:
    """A map's stem without the word 'normal(s)' and the separators around it."""
    return _NORMAL.sub("", normal_map.stem).strip("_-. ")


def _items(args) -> list[ImportItem]:
    from common.imports.manifest import fragment_id, read_manifest
    from common.limits import check_dpi
    from common.store import ArtifactError

    if args.manifest:
        rows = read_manifest(args.manifest)
        base = Path(args.manifest).parent
        triples = [(Path(r["file"]), (base / r["albedo"]).resolve() if r.get("albedo") else None,
                    r.get("inventory") or Path(r["file"]).stem, r) for r in rows]
    else:
        triples = [(m, a, i, {"face": f} if f else {}) for m, a, i, f in _pairs(args.paths)]
    if (args.albedo or args.fragment) and len(triples) != 1:
        raise ValueError("--albedo and --fragment name the albedo and id of one normal map; "
                         f"{len(triples)} were given (use a manifest for several)")
    items, used = [], {}
    for nmap, albedo, fid, row in triples:
        where = f"{args.manifest} line {row['line']}" if "line" in row else str(nmap)
        albedo = Path(args.albedo) if args.albedo else albedo
        fid = fragment_id(args.fragment or fid)
        face = row.get("face", args.face).lower()
        convention = row.get("convention", args.convention).lower()
        if face not in ("front", "back"):
            raise ValueError(f"{where}: face {face!r} must be front or back")
        if convention not in ("opengl", "directx", "auto"):
            raise ValueError(f"{where}: convention {convention!r} must be opengl, directx or auto")
        if (fid, face) in used:
            raise ValueError(f"{where}: fragment {fid} ({face}) is also given by {used[fid, face]}")
        used[fid, face] = where
        exported = {} if args.manifest else _exported_face(nmap.parent, face)
        raw_dpi = row.get("dpi", args.dpi if args.dpi is not None else exported.get("dpi"))
        if raw_dpi is None:
            raise ValueError(f"{where}: no dpi: give --dpi or a dpi column in the manifest")
        try:
            dpi = check_dpi(raw_dpi, where)
        except ArtifactError as exc:
            raise ValueError(str(exc)) from None
        metadata = {k: v for k, v in row.items() if k not in ("file", "line", "dpi", "face", "albedo", "convention")}
        metadata.update(exported.get("metadata") or {})
        metadata["source_file"] = nmap.name
        sources = [nmap] + ([albedo] if albedo else [])
        items.append(ImportItem(name=nmap.name if not nmap.stem.lower().startswith("normal") else
                                f"{nmap.parent.name}/{nmap.name}", sources=sources, fragment=fid, face=face,
                                options={"dpi": dpi, "convention": convention, "linear": bool(args.linear),
                                         "metadata": metadata}))
    return items


def _exported_face(folder: Path, face: str) -> dict:
    """A face's entry in the ``metadata.json`` of a folder ``tessera export`` wrote (else {})."""
    try:
        meta = json.loads((folder / "metadata.json").read_text(encoding="utf-8"))
        return dict(meta["faces"][face])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def convert(item: ImportItem, store) -> list[Output]:
    """A normal map (+ albedo) -> one RGBN face, checked at the door."""
    import numpy as np

    from common.imports.door import read_image_checked
    from common.imports.fragments import fragment_from_image
    from common.imports.normals import normals_from_map
    from common.rgbn.image import RGBNImage, save_rgbn
    from common.rgbn.io import srgb_to_linear

    opts = item.options
    nmap = Path(item.sources[0])
    raw = read_image_checked(nmap, channels=(3, 4))
    albedo, alpha, albedo_img = None, None, None
    if len(item.sources) > 1:
        apath = Path(item.sources[1])
        albedo_img = read_image_checked(apath)
        if albedo_img.pixels.shape[:2] != raw.pixels.shape[:2]:
            h, w = raw.pixels.shape[:2]
            ah, aw = albedo_img.pixels.shape[:2]
            raise ImportRefused(f"{apath}: is {aw}x{ah} px but the normal map {nmap.name} is {w}x{h}: "
                                "they must share a pixel grid")
        a = albedo_img.as_float()
        if a.ndim == 2:
            a = a[..., None]
        if a.shape[2] in (2, 4):
            alpha = a[..., -1] > 0
            a = a[..., :-1]
        a = np.repeat(a, 3, axis=2) if a.shape[2] == 1 else a
        albedo = a if opts["linear"] or albedo_img.bits == 32 else srgb_to_linear(a)
    try:
        normals, mask, info = normals_from_map(raw.pixels, raw.full_scale, convention=opts["convention"], mask=alpha)
    except ImportRefused as exc:
        raise ImportRefused(f"{nmap}: {exc}") from None
    mask_from = "normal map" if raw.channels == 3 else "normal map alpha"
    if alpha is not None:
        mask_from += " + albedo alpha"
    elif mask.mean() > 0.98 and albedo_img is not None:
        # nothing outside the object in the map itself: cut the fragment from the albedo's plain background
        try:
            cut = fragment_from_image(albedo_img.pixels, dpi=opts["dpi"], background="plain")
            mask &= cut.mask
            mask_from = "albedo background"
        except ImportRefused:
            mask_from = "whole frame"
    if albedo is None:
        albedo = np.full(normals.shape, 0.8, np.float32)   # no albedo given: a uniform light grey
    albedo = np.where(mask[..., None], albedo, 0.0).astype(np.float32)
    normals[~mask] = (0.0, 0.0, 1.0)
    rgbn = RGBNImage(albedo=albedo, mask=mask, dpi=opts["dpi"], normals=normals,
                     attrs={"source": "tessera import normals", "face": item.face, "mask_from": mask_from,
                            "source_convention": info["convention"],
                            "metadata": json.dumps(opts["metadata"], sort_keys=True, ensure_ascii=False)})
    prov = {"importer": "tessera import normals", "version": VERSION,
            "source_files": [str(p) for p in item.sources], **item.source_provenance(),
            "convention": info["convention"], "curl_opengl": info["curl_opengl"], "curl_directx": info["curl_directx"],
            "albedo": "given" if len(item.sources) > 1 else "none (uniform 0.8)"}
    ref = save_rgbn(store, f"fragments/{item.fragment}/rgbn/{item.face}-{item.key}.h5", rgbn, provenance=prov)
    return [Output("rgbn.ready", ref, {"face": item.face, "metadata": opts["metadata"]})]


def run(args) -> int:
    from services.cli.imports import run_items
    if not args.paths and not args.manifest:
        print("tessera import normals: give normal maps or folders, or --manifest CSV", file=sys.stderr)
        return 2
    try:
        items = _items(args)
    except ValueError as exc:
        print(f"tessera import normals: {exc}", file=sys.stderr)
        return 2
    return run_items(args, items, convert, kind="normals", version=VERSION)
