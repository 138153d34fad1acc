"""``tessera export``: fragments' faces as files other tools read (normal map, albedo, renders, metadata).

    tessera export FRAGMENT... -o OUT [--store DIR | --config station.toml] [--albedo-bits 8|16] [--force]
    tessera export --all -o OUT                  # the whole collection, one folder per fragment

Writes ``OUT/<id>/<face>-normals.png`` (16-bit RGBA, OpenGL convention: green = y up),
``<face>-albedo.png`` (sRGB), ``<face>-render-<recipe>-<key>.png`` and ``metadata.json``; with
several fragments also ``OUT/collection.json`` listing them. Where the station has a proposal database
(``--db``, default the config's or STORE/matches/proposals.sqlite), the confirmed joins go with them: each
fragment's ``metadata.json`` lists its own (the other fragment's pose in its frame), ``collection.json``
those between the fragments it lists. See ``docs/import.md``.

Free space: each fragment's files are encoded in memory and their total size (plus a margin) is
checked against the free space of OUT's file system before any of them is written. A fragment
that does not fit stops the export (exit 1) with the bytes needed and available; the fragments
exported before it are complete, the ones after it are not tried. Nothing is written for it.
With --all the whole export is sized first (every fragment's files encoded; up to 128 MiB of them
kept in memory for the writing, the rest encoded again) and refused (exit 1) before any fragment is
written when it does not fit; the check per fragment stays, for a disk another writer fills meanwhile.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("export", help="a fragment's faces as PNG normal map, albedo, renders + JSON metadata",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("fragments", nargs="*", metavar="FRAGMENT", help="fragment ids")
    p.add_argument("--all", action="store_true", help="every fragment with an RGBN face on storage")
    p.add_argument("-o", "--out", required=True, metavar="DIR", help="output folder (one sub-folder per fragment)")
    p.add_argument("--store", metavar="DIR", help="storage root (default: the station config's)")
    p.add_argument("--db", metavar="PATH", help="proposal database whose confirmed joins go with the export "
                                               "(default: the config's, or STORE/matches/proposals.sqlite)")
    p.add_argument("--albedo-bits", type=int, choices=(8, 16), default=16, help="albedo PNG depth (default 16)")
    p.add_argument("--force", action="store_true", help="replace fragment folders that exist in OUT")
    from common.config import add_config_arguments
    add_config_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from common.imports import ProgressBar
    from common.imports.export import export_fragment, fragment_ids, join_record, size_export, write_fragment
    from common.store import Store, StorageFull, check_free_space, write_file
    from services.cli.reconstruct import storage_and_proposals

    root, db_path = storage_and_proposals(args)
    if not root.is_dir():
        print(f"tessera export: storage root {root} does not exist", file=sys.stderr)
        return 2
    store = Store(root, create=False)
    try:
        joins = _confirmed_joins(db_path, named=bool(args.db))
    except ValueError as exc:
        print(f"tessera export: {exc}", file=sys.stderr)
        return 2
    ids = fragment_ids(store) if args.all else list(dict.fromkeys(args.fragments))
    if not ids:
        print("tessera export: name fragments or --all" if not args.all else
              f"tessera export: no fragment with an RGBN face under {root}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        print(f"tessera export: {out} exists and is not a folder", file=sys.stderr)
        return 2
    done, failed, full, kept = [], [], None, {}
    several = args.all or len(ids) > 1     # --all lists the collection even when it holds one fragment
    if args.all:   # the whole collection sized first: a disk too small refuses it before any fragment is written
        bar = ProgressBar(len(ids), "export: sizing")
        try:
            sized = size_export(store, ids, out, albedo_bits=args.albedo_bits, overwrite=args.force,
                                progress=bar.update, joins=joins)
        except KeyboardInterrupt:
            bar.close()
            print("interrupted while sizing the export; nothing was written", file=sys.stderr)
            return 130
        bar.close()
        failed, kept = sized.failed, sized.kept
        ids = [fid for fid in ids if fid in sized.sizes]
        try:
            if ids:
                check_free_space(out, sized.total, f"the export of {len(ids)} fragment(s)")
        except StorageFull as exc:
            print(f"tessera export: not enough free space for --all: {exc}; nothing was written", file=sys.stderr)
            for fid, why in failed:
                print(f"  not exported {fid}: {why}", file=sys.stderr)
            return 1
    bar = ProgressBar(len(ids), "export")
    try:
        for i, fid in enumerate(ids):
            try:
                if fid in kept:   # encoded while sizing: written as they are (the free space checked again)
                    write_fragment(out, fid, kept.pop(fid), overwrite=args.force)
                else:
                    export_fragment(store, fid, out, albedo_bits=args.albedo_bits, overwrite=args.force, joins=joins)
                done.append(fid)
            except StorageFull as exc:      # checked before writing: the next ones would not fit either
                full = (fid, str(exc))
                break
            except (ValueError, OSError) as exc:
                failed.append((fid, str(exc)))
            bar.update(i + 1, fid)
    except KeyboardInterrupt:
        bar.close()
        print(f"interrupted after {len(done)} fragment(s); each folder written is complete", file=sys.stderr)
        return 130
    bar.close()
    index_written = True
    if several and done:
        index = out / "collection.json"
        listed = json.loads(index.read_text()) if index.is_file() else {"fragments": []}
        listed["fragments"] = sorted(set(listed.get("fragments", [])) | set(done))
        listed["storage_root"] = str(Path(root).resolve())
        if joins is not None:   # the station's confirmed joins between the fragments listed, B in A's frame
            inside = set(listed["fragments"])
            listed["joins"] = [{"fragment": j.fragment_a, **join_record(j, j.fragment_a)}
                               for j in joins if j.fragment_a in inside and j.fragment_b in inside]
        try:    # the project's atomic write, free space checked; an export's index is for everyone the umask allows
            write_file(index, (json.dumps(listed, indent=2) + "\n").encode("utf-8"), public=True)
        except OSError as exc:
            print(f"tessera export: {index} not updated: {exc}", file=sys.stderr)
            index_written = False
    print(f"exported {len(done)} fragment(s) to {out}" + (f"; {len(failed)} failed" if failed else ""))
    for fid, why in failed:
        print(f"  not exported {fid}: {why}", file=sys.stderr)
    if full:
        left = len(ids) - ids.index(full[0])   # the one that did not fit and those after it
        print(f"tessera export: not enough free space, stopped at {full[0]}: {full[1]}; nothing of it was written"
              + (f", {left - 1} more fragment(s) not tried" if left > 1 else "")
              + (f"; the {len(done)} exported before it are complete" if done else ""), file=sys.stderr)
    return 1 if failed or full or not index_written else 0


def _confirmed_joins(db_path: Path, *, named: bool):
    """The confirmed joins of the proposal database at ``db_path``
    (:func:`common.matching.reconstruction.confirmed_joins`); None where there is none (a store no matcher has
    run on; ValueError when it was ``named`` by --db) or it cannot be read (said on stderr: the faces are
    exported all the same, without joins)."""
    import sqlite3

    from common.matching.proposals import ProposalStore
    from common.matching.reconstruction import confirmed_joins

    if not db_path.is_file():
        if named:
            raise ValueError(f"no proposal database at {db_path}")
        return None
    try:
        with ProposalStore(db_path) as db:
            joins, unposed = confirmed_joins(db)
    except (sqlite3.Error, OSError) as exc:
        print(f"tessera export: proposal database {db_path} cannot be read ({exc}); the fragments are exported "
              "without their joins", file=sys.stderr)
        return None
    for a, b in unposed:
        print(f"tessera export: the confirmed join {a} - {b} has no pose (recorded before poses were kept); "
              "not listed", file=sys.stderr)
    return joins
