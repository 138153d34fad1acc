"""``tessera synth``: a synthetic fresco with ground truth, written to the store.

    tessera synth --fragments N --seed S [--store DIR | --config station.toml] [--dpi 300] [--as rgbn|scans]
                  [--mode recursive|voronoi] [--style aegean|roman] [--image PICTURE --image-width-mm W]
                  [--missing 0.2] [--spurious 0.05] [--scan-dpi D] [--colour-only] [--workers K]

Writes each fragment either as an RGBN artifact ``fragments/<id>/rgbn/front-<key>.h5`` or as the raw
scans of the simulated flatbed (four rotations per face) ``fragments/<id>/scans/scans-<key>.h5``,
plus the ground truth ``groundtruth/<wall id>.h5``. Same seed and options -> identical data.
Then ``tessera reconcile`` queues the fragments for the station's stages.

    tessera synth --dafne DIR --store DIR [--dafne-dpi 50]

imports a DAFNE fragment set (colour only) into the same form: RGBN artifacts and ground truth.

    tessera synth --preset pompeii --fragments 60 --seed 1 --dpi 150 --colour-only [--palette-seed P]
                  [--store DIR] [--collection DIR] [--compare ../shared/data/repair-dev]

a wall that looks like RePAIR's broken Pompeii frescoes (big pieces, plaster lost along the
cracks, plain plaster with sparse faded painting); ``--collection DIR`` also writes it in the
RePAIR layout (RGBA PNGs + truth.csv), ``--compare DIR`` measures it and a real collection with the
same code and prints the statistics side by side (without ``--store`` nothing else is written).
"""

from __future__ import annotations

import logging
import sys
import time

log = logging.getLogger("tessera.synth")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("synth", help="generate a synthetic broken fresco with ground truth",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--fragments", type=int, help="number of fragments delivered (incl. spurious)")
    p.add_argument("--dafne", metavar="DIR", help="instead of generating, import a DAFNE fragment set (colour only)")
    p.add_argument("--dafne-dpi", type=float, default=50.0, help="nominal dpi of the DAFNE images (default 50)")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed -> same data)")
    p.add_argument("--store", help="storage root to write into (default: the station config's storage root)")
    p.add_argument("--dpi", type=float, default=300.0, help="fragment sampling in dpi (default 300)")
    p.add_argument("--as", dest="output", choices=("rgbn", "scans"), default="rgbn",
                   help="write RGBN images (fast) or simulated flatbed scans (whole station)")
    p.add_argument("--mode", choices=("recursive", "voronoi"), default="recursive", help="breakage model")
    p.add_argument("--style", choices=("aegean", "roman", "pompeii"),
                   help="painting style (default aegean; pompeii with --preset pompeii)")
    p.add_argument("--image", help="use this picture as the painting instead")
    p.add_argument("--image-width-mm", type=float, help="physical width of --image on the wall")
    p.add_argument("--median-size-mm", type=float, help="median fragment size, sqrt of area (default 30; pompeii 90)")
    p.add_argument("--missing", type=float, help="fraction of pieces lost (default 0.2; pompeii 0.25)")
    p.add_argument("--spurious", type=float, help="fraction of fragments from another wall (default 0.05)")
    p.add_argument("--scan-dpi", type=float, help="scan resolution with --as scans (default: --dpi)")
    p.add_argument("--colour-only", action="store_true",
                   help="with --as rgbn: fragments without normals (colour and mask, like RePAIR); "
                        "with --as scans: one scan per face")
    p.add_argument("--preset", choices=("pompeii",), help="realistic preset (see docs/synth.md)")
    p.add_argument("--palette-seed", type=int, help="walls with one palette seed share their colours (pompeii)")
    p.add_argument("--collection", metavar="DIR", help="also write the fragments as a RePAIR-layout collection here")
    p.add_argument("--compare", metavar="DIR",
                   help="measure a real collection (e.g. ../shared/data/repair-dev) and this wall, print both")
    p.add_argument("--compare-dpi", type=float, default=7.369 * 25.4,
                   help="sampling of the --compare images (default 187.2: RePAIR's 7.369 px/mm)")
    p.add_argument("--workers", type=int, default=1, help="render fragments in this many processes (same data)")
    p.add_argument("--pictures", metavar="DIR",
                   help="also write wall.png, cracks.png, fragments.png, reassembly.png here")
    from common.config import add_config_arguments
    add_config_arguments(p)
    p.set_defaults(func=run)


def _store_root(args) -> str:
    if args.store:
        return args.store
    from common.config import config_from_arguments
    return str(config_from_arguments(args)["storage"]["root"])


def run(args) -> int:
    import numpy as np

    from common.rgbn.image import save_rgbn
    from common.store import Store, content_key
    from common.synth import generate_wall, save_groundtruth

    if args.dafne:
        return _import_dafne(args)
    if args.fragments is None or args.fragments < 1:
        print("tessera synth: --fragments must be at least 1", file=sys.stderr)
        return 2
    if args.dpi <= 0:
        print("tessera synth: --dpi must be positive", file=sys.stderr)
        return 2
    image = None
    if args.image:
        from common.imports.door import read_image_checked
        # read whole (OpenCV alone paints a truncated file's missing rows grey); a plain wall is allowed
        try:
            px = read_image_checked(args.image, channels=(1, 3, 4), allow_blank=True).pixels
        except ValueError as exc:
            print(f"tessera synth: --image: {exc}", file=sys.stderr)
            return 2
        image = np.repeat(px[..., None], 3, axis=2) if px.ndim == 2 else px[..., :3]
    real = None
    if args.compare:
        from common.synth.stats import read_collection
        try:
            real = read_collection(args.compare)
        except ValueError as exc:
            print(f"tessera synth: --compare: {exc}", file=sys.stderr)
            return 2
    # with --compare / --collection the store is written only when --store is given
    store = Store(_store_root(args)) if args.store or not (args.compare or args.collection) else None
    pieces = []  # the wall as a collection, for --compare
    rows = []  # truth.csv rows for --collection
    written = []
    keep = []  # fragments kept for the pictures
    failed = []  # fragments the simulated bench could not capture
    t0 = time.monotonic()

    if args.output == "scans":
        from common.acquisition.capture import CaptureError, capture_fragment, simulated_operator, write_scans
        from common.acquisition.flatbed_sim import SimulatedFlatbed
        scan_dpi = args.scan_dpi or args.dpi

    def on_fragment(frag):
        prov = {"generator": "tessera synth", "seed": args.seed, "spurious": frag.spurious}
        wall_id = frag.id.rsplit("-", 1)[0]
        if args.collection:
            from common.synth.realistic import write_fragment_png
            rows.append(write_fragment_png(frag, args.collection, wall_id))
        if real is not None:
            from common.synth.stats import fragment_piece
            pieces.append(fragment_piece(frag, wall_id))
        if store is None:
            pass
        elif args.output == "rgbn":
            digest = content_key(_digest(frag.rgbn), "synth")
            ref = save_rgbn(store, f"fragments/{frag.id}/rgbn/front-{digest}.h5", frag.rgbn, provenance=prov)
        else:
            # one simulated bench per fragment, seeded from the fragment id: reproducible scans
            sim = SimulatedFlatbed(seed=int(content_key(frag.id, str(args.seed), length=8), 16) % (2 ** 31))
            sim.place(frag.surface)
            try:
                result = capture_fragment(sim, frag.id, operator=simulated_operator(sim), dpi=scan_dpi,
                                          colour_only=args.colour_only)
            except CaptureError as exc:
                # e.g. black paint the pre-scan cannot tell from the dark lid: the bench would
                # ask the operator; here the fragment is reported and left out
                failed.append(frag.id)
                print(f"fragment {frag.id} could not be captured: {getattr(exc, 'operator_message', '') or exc}",
                      file=sys.stderr)
                return
            ref = write_scans(store, frag.id, result)
        if store is not None:
            written.append(ref)
        if args.pictures:
            from dataclasses import replace

            from common.synth.figures import thumbnail
            keep.append(replace(frag) if len(keep) < 8 else thumbnail(frag, 0.5))

    def progress(fraction, text):
        print(f"[{fraction * 100:5.1f}%] {text} {time.monotonic() - t0:6.1f}s", file=sys.stderr, flush=True)

    try:
        wall = generate_wall(args.fragments, args.seed, args.dpi, mode=args.mode, style=args.style, image=image,
                             image_width_mm=args.image_width_mm, median_size_mm=args.median_size_mm,
                             missing_fraction=args.missing, spurious_fraction=args.spurious, keep_images=False,
                             workers=max(1, args.workers), surfaces=args.output == "scans",
                             on_fragment=on_fragment, progress=progress, preset=args.preset,
                             palette_seed=args.palette_seed,
                             colour_only=bool(args.colour_only and args.output == "rgbn"))
    except ValueError as exc:
        print(f"tessera synth: {exc}", file=sys.stderr)
        return 2
    gt = save_groundtruth(store, wall) if store is not None else None
    if args.collection:
        from common.synth.realistic import write_truth_csv
        folder = write_truth_csv(args.collection, wall.id, [r for r in rows if r is not None])
        print(f"collection written to {folder} (RGBA PNGs and truth.csv; spurious fragments in {folder}-spurious)")
    if real is not None:
        from common.synth.stats import collection_statistics, comparison_table
        print(f"measuring {args.compare} and the synthetic wall ...", file=sys.stderr, flush=True)
        table = comparison_table({f"{args.compare} ({args.compare_dpi:.0f} dpi)":
                                  collection_statistics(real, args.compare_dpi),
                                  f"{wall.id} ({args.dpi:g} dpi)": collection_statistics(pieces, args.dpi)})
        print(table)
    if args.pictures:
        from pathlib import Path

        from common.synth import figures
        out = Path(args.pictures)
        figures.save_png(out / "wall.png", figures.wall_picture(wall))
        figures.save_png(out / "cracks.png", figures.crack_picture(wall))
        figures.save_png(out / "fragments.png", figures.fragment_sheet(keep[:6], tile=130, columns=2))
        figures.save_png(out / "reassembly.png",
                         figures.reassembly_picture(wall, keep, mm_per_px=max(0.5, wall.width_mm / 1200)))
        print(f"pictures in {out}")
    areas = np.array([f.area_mm2 for f in wall.fragments])
    sizes = np.sqrt(areas) / 10.0
    print(f"wall {wall.id}: {wall.width_mm:.0f} x {wall.height_mm:.0f} mm, {len(wall.fragments)} fragments "
          f"({sum(f.spurious for f in wall.fragments)} spurious, {wall.n_missing} pieces missing), "
          f"{len(wall.adjacency)} neighbour pairs; size sqrt(area) median {np.median(sizes):.1f} cm "
          f"[{sizes.min():.1f}-{sizes.max():.1f}]")
    if store is not None:
        print(f"wrote {len(written)} {args.output} artifacts under {store.root}/fragments and {gt.path} "
              f"in {time.monotonic() - t0:.1f} s")
    if failed:
        print(f"{len(failed)} fragment(s) could not be captured (in the ground truth, not in the store): "
              f"{', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def _import_dafne(args) -> int:
    from common.rgbn.image import save_rgbn
    from common.store import Store, content_key
    from common.synth import save_groundtruth
    from common.synth.dafne import import_dafne

    try:
        wall = import_dafne(args.dafne, dpi=args.dafne_dpi)
    except ValueError as exc:
        print(f"tessera synth: {exc}", file=sys.stderr)
        return 2
    store = Store(_store_root(args))
    for k, frag in enumerate(wall.fragments):
        key = content_key(_digest(frag.rgbn), "dafne")
        save_rgbn(store, f"fragments/{frag.id}/rgbn/front-{key}.h5", frag.rgbn,
                  provenance={"source": "DAFNE", "path": str(args.dafne)})
        print(f"[{(k + 1) / len(wall.fragments) * 100:5.1f}%] fragment {frag.id}", file=sys.stderr, flush=True)
    gt = save_groundtruth(store, wall)
    placed = sum(f.pose is not None for f in wall.fragments)
    print(f"imported {wall.id}: {len(wall.fragments)} fragments ({placed} placed, {len(wall.fragments) - placed} "
          f"spurious), {len(wall.adjacency)} neighbour pairs at a nominal {wall.dpi:g} dpi; ground truth {gt.path}")
    return 0


def _digest(image) -> str:
    import hashlib
    h = hashlib.sha256()
    for arr in (image.albedo, image.mask, image.normals, image.height_mm):
        if arr is not None:
            h.update(arr.tobytes())
    return h.hexdigest()
