"""``tessera reconstruct``: the confirmed joins assembled into clusters — composites and JSON poses.

    tessera reconstruct -o OUT [--store DIR | --config station.toml] [--db PATH] [--dpi D] [--max-side PX]
                        [--sigma-mm 1.0] [--sigma-deg 1.0] [--json-only] [--no-dock]

Solves the pose graph of the station's confirmed joins (``common/matching/reconstruction.py``) and
writes ``OUT/reconstruction.json`` (schema ``tessera.reconstruction`` v1, ``docs/storage.md``) and,
per cluster, ``OUT/cluster-<root>.png`` (8-bit sRGB, alpha = coverage) and ``cluster-<root>.tif``
(16-bit). Each cluster's next joins carry the pose the newcomer would take (its proposal's) and, where
docked against the whole cluster it fits a corner (it faces two members there), that fit too
(docs/matching.md, "Docking against a confirmed cluster"; ``--no-dock``: no fits). Conflicting loops are
printed and listed in the JSON. Every file is written by ``common.store.write_file`` (free space checked
first, an older file replaced only by a whole new one); a full disk stops the command naming the file, and
``reconstruction.json``, written last, stays as it was. Exit 0, 1 when a loop conflicts, a fragment's image
is missing or the disk is full, 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("reconstruct", help="confirmed joins as clusters: PNG/TIFF composites + JSON poses",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--store", metavar="DIR", help="storage root (default: the station config's)")
    p.add_argument("--db", metavar="PATH",
                   help="proposal database (default: the config's, or STORE/matches/proposals.sqlite)")
    p.add_argument("--dpi", type=float, help="composite sampling (default: the lowest dpi among a cluster's fragments)")
    p.add_argument("--max-side", type=int, default=8192, metavar="PX", help="longest composite side (default 8192)")
    p.add_argument("--sigma-mm", type=float, default=1.0, help="a join's translation uncertainty, mm (default 1)")
    p.add_argument("--sigma-deg", type=float, default=1.0, help="a join's angle uncertainty, degrees (default 1)")
    p.add_argument("--json-only", action="store_true", help="write the JSON poses, no composites")
    p.add_argument("--no-dock", action="store_true",
                   help="do not dock the next joins' newcomers against their whole cluster for a fit in a corner "
                        "(which reads the feature tables, ~0.1-0.3 s CPU a newcomer)")
    from common.config import add_config_arguments
    add_config_arguments(p)
    p.set_defaults(func=run)


def storage_and_proposals(args) -> tuple[Path, Path]:
    """(storage root, proposal database) of a command taking ``--store``, ``--db`` and ``--config``: ``--store``
    replaces the config's root (and its matcher's ``db`` setting), ``--db`` any other
    (:func:`common.matching.proposals.proposals_path`)."""
    from common.matching.proposals import proposals_path

    if args.store:
        root, db = Path(args.store), None
    else:
        from common.config import config_from_arguments
        cfg = config_from_arguments(args)
        root, db = Path(cfg["storage"]["root"]), dict(cfg.get("services", {}).get("matcher", {})).get("db")
    return root, proposals_path(root, args.db or db)


def run(args) -> int:
    from common.imports import ProgressBar
    from common.matching import reconstruction as rc
    from common.messages import to_json
    from common.matching.proposals import ProposalStore
    from common.store import Store, write_file

    root, db_path = storage_and_proposals(args)
    if not root.is_dir():
        print(f"tessera reconstruct: storage root {root} does not exist", file=sys.stderr)
        return 2
    if not db_path.is_file():
        print(f"tessera reconstruct: no proposal database at {db_path} (has a matcher run?)", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        print(f"tessera reconstruct: {out} exists and is not a folder", file=sys.stderr)
        return 2
    store = Store(root, create=False)
    with ProposalStore(db_path) as db:
        fragments = sorted({f for j in rc.confirmed_joins(db)[0] for f in j.pair})
        images, missing = {}, {}
        bar = ProgressBar(len(fragments), "read faces")
        for i, f in enumerate(fragments):
            got, why = rc.front_images(store, [f])
            images.update(got)
            missing.update(why)
            bar.update(i + 1, f)
        bar.close()
        unread = {}   # fragments whose outline cannot be read: their next joins get no fit

        def pieces(wanted):
            got, why = rc.front_pieces(store, db.fragments(face="front"), wanted)
            unread.update(why)
            return got

        try:
            rec = rc.reconstruct(db, centres_mm={f: rc.mask_centre_mm(im) for f, im in images.items() if im.mask.any()},
                                 dpi={f: im.dpi for f, im in images.items()}, sigma_mm=args.sigma_mm,
                                 sigma_deg=args.sigma_deg, pieces=None if args.no_dock else pieces)
        except ValueError as exc:
            print(f"tessera reconstruct: {exc}", file=sys.stderr)
            return 2
    # every file through the project's atomic writer (common.store.write_file, as write_composite's pictures):
    # the free space checked first, an older file replaced only by a whole new one; a full disk stops the
    # command and leaves reconstruction.json as it was
    composites, bar = {}, None
    try:
        if not args.json_only:
            bar = ProgressBar(len(rec["clusters"]), "composite")
            for i, c in enumerate(rec["clusters"]):
                if any(f not in images for f in c.fragments):
                    bar.update(i + 1, f"{c.id}: skipped")
                    continue
                comp = rc.compose_cluster(c, images, dpi=args.dpi, max_side_px=args.max_side)
                stem = f"cluster-{c.root}"
                rc.write_composite(comp, out / f"{stem}.png", out / f"{stem}.tif")
                composites[c.id] = {"png": f"{stem}.png", "tiff": f"{stem}.tif", "dpi": comp["dpi"],
                                    "pixel_mm": comp["pixel_mm"], "origin_mm": list(comp["origin_mm"]),
                                    "size_px": [int(comp["alpha"].shape[1]), int(comp["alpha"].shape[0])]}
                bar.update(i + 1, c.id)
            bar.close()
        doc = rec["document"]
        for c in doc["clusters"]:
            c["composite"] = composites.get(c["id"])
        doc["missing_images"] = missing
        # strict JSON (NaN and ±inf as null, numpy scalars as their numbers) for every reader, as the web serves
        # the same document
        write_file(out / "reconstruction.json", (to_json(doc, indent=2) + "\n").encode("utf-8"), public=True)
    except OSError as exc:   # StorageFull / StorageReadOnly name the problem and the file
        if bar is not None:
            bar.close()      # the error on a line of its own
        print(f"tessera reconstruct: {exc}; stopped, {out / 'reconstruction.json'} not updated", file=sys.stderr)
        return 1
    conflicts = [(c.id, lp) for c in rec["clusters"] for lp in c.conflicting_loops]
    print(f"{len(rec['clusters'])} cluster(s), {sum(len(c.fragments) for c in rec['clusters'])} fragments, "
          f"{sum(len(c.joins) for c in rec['clusters'])} joins, {sum(len(c.loops) for c in rec['clusters'])} loops "
          f"({len(conflicts)} conflicting) -> {out}")
    for cid, lp in conflicts:
        print(f"  conflicting loop in {cid}: {' - '.join(lp.fragments)}: {lp.residual_mm:.1f} mm, "
              f"{lp.residual_deg:.1f} deg (chi2 {lp.chi2:.0f})", file=sys.stderr)
    for a, b in rec["unposed"]:
        print(f"  confirmed join {a} - {b} has no pose: not placed", file=sys.stderr)
    for f, why in missing.items():
        print(f"  {f}: {why}", file=sys.stderr)
    for f, why in unread.items():
        print(f"  {f}: not docked against its cluster, no fit offered ({why})", file=sys.stderr)
    return 1 if conflicts or missing else 0
