"""Benchmark: a 120-fragment synthetic wall as RGBN at 300 dpi (issue 5: target <= 60 s).

    python tests/bench/bench_synth.py [--fragments 120] [--dpi 300] [--seed 1] [--store DIR] [--mode recursive]
    python tests/bench/bench_synth.py --preset pompeii --fragments 60 --dpi 150 --colour-only --no-write

Prints the generation time (in memory, fragments streamed and dropped), optionally the time to
write everything to a store (RGBN artifacts + ground truth), and the statistics of the wall it
produced: fragment count, size distribution, adjacency.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.rgbn.image import save_rgbn  # noqa: E402
from common.store import Store, content_key  # noqa: E402
from common.synth import generate_wall, save_groundtruth  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fragments", type=int, default=120)
    ap.add_argument("--dpi", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--mode", default="recursive", choices=("recursive", "voronoi"))
    ap.add_argument("--store", help="also write to this store (default: a temporary one)")
    ap.add_argument("--no-write", action="store_true", help="only the in-memory generation")
    ap.add_argument("--workers", type=int, default=1, help="fragment rendering processes")
    ap.add_argument("--preset", choices=("pompeii",), help="realistic preset (issue 15)")
    ap.add_argument("--colour-only", action="store_true", help="fragments without normals (like RePAIR)")
    args = ap.parse_args()
    kw = dict(preset=args.preset, colour_only=args.colour_only)

    pixels = []
    load0 = os.getloadavg()[0]
    c0 = time.process_time()
    t0 = time.perf_counter()
    wall = generate_wall(args.fragments, args.seed, args.dpi, mode=args.mode, keep_images=False, surfaces=False,
                         workers=args.workers, **kw,
                         on_fragment=lambda f: pixels.append((f.rgbn.mask.size, int(f.rgbn.mask.sum()))))
    t_gen = time.perf_counter() - t0
    c_gen = time.process_time() - c0
    print(f"load average at start/end: {load0:.1f}/{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (shared)")
    print(f"generate_wall({args.fragments}, seed={args.seed}, dpi={args.dpi:g}, mode={args.mode}, "
          f"preset={args.preset}, colour_only={args.colour_only}, "
          f"workers={args.workers}): {t_gen:.1f} s wall clock, {c_gen:.1f} s CPU of this process "
          f"[target <= 60 s]" + ("" if args.workers == 1 else " (CPU excludes the workers)"))
    frame_px = sum(p for p, _ in pixels)
    frag_px = sum(m for _, m in pixels)
    print(f"  pixels: {frame_px / 1e6:.1f} M in fragment frames, {frag_px / 1e6:.1f} M on fragments, "
          f"{frame_px / t_gen / 1e6:.2f} M frame px/s")

    if not args.no_write:
        root = args.store or tempfile.mkdtemp(prefix="bench-synth-")
        store = Store(root)
        t0 = time.perf_counter()

        def write(f):
            save_rgbn(store, f"fragments/{f.id}/rgbn/front-{content_key(f.id, 'bench')}.h5", f.rgbn)
        wall2 = generate_wall(args.fragments, args.seed, args.dpi, mode=args.mode, keep_images=False, surfaces=False,
                              on_fragment=write,
                              workers=args.workers, **kw)
        save_groundtruth(store, wall2)
        t_all = time.perf_counter() - t0
        size = sum(p.stat().st_size for p in Path(root).rglob("*.h5"))
        print(f"generate + write RGBN + ground truth to {root}: {t_all:.1f} s, {size / 1e6:.0f} MB")

    sizes_cm = np.sqrt([f.area_mm2 for f in wall.fragments]) / 10.0
    n_spur = sum(f.spurious for f in wall.fragments)
    pieces = len(wall.fragments) - n_spur + wall.n_missing
    print(f"wall {wall.id}: {wall.width_mm:.0f} x {wall.height_mm:.0f} mm; {len(wall.fragments)} fragments "
          f"({n_spur} spurious), {wall.n_missing} of {pieces} pieces missing ({wall.n_missing / pieces:.0%})")
    q = np.percentile(sizes_cm, [0, 5, 25, 50, 75, 95, 100])
    print("  size sqrt(area) cm: min {:.1f}  p5 {:.1f}  p25 {:.1f}  median {:.1f}  p75 {:.1f}  p95 {:.1f}  max {:.1f}"
          .format(*q))
    logs = np.log(sizes_cm)
    print(f"  log-size mean {logs.mean():.2f} sd {logs.std():.2f} "
          f"(log-normal fit: median {np.exp(logs.mean()):.1f} cm)")
    hist, edges = np.histogram(sizes_cm, bins=[0, 1, 2, 3, 4, 6, 8, 12, 20, 100])
    print("  histogram (cm): " + ", ".join(f"{a:g}-{b:g}: {h}" for a, b, h in zip(edges[:-1], edges[1:], hist)))
    deg = {}
    for a, b, _ in wall.adjacency:
        deg[a] = deg.get(a, 0) + 1
        deg[b] = deg.get(b, 0) + 1
    present = [f.id for f in wall.fragments if not f.spurious]
    degrees = np.array([deg.get(i, 0) for i in present])
    lengths = np.array([l for *_, l in wall.adjacency])
    ncorr = np.array([len(wall.correspondences[(a, b)][0]) for a, b, _ in wall.adjacency])
    print(f"  adjacency: {len(wall.adjacency)} neighbour pairs among {len(present)} present fragments; degree "
          f"mean {degrees.mean():.2f}, max {degrees.max()}, isolated {int((degrees == 0).sum())}")
    print(f"  shared crack length mm: median {np.median(lengths):.1f}, p5 {np.percentile(lengths, 5):.1f}, "
          f"p95 {np.percentile(lengths, 95):.1f}, total {lengths.sum() / 1000:.2f} m")
    print(f"  correspondences per pair: median {np.median(ncorr):.0f}, total {ncorr.sum()}")
    print(f"  deteriorated: {sum('fade' in f.notes for f in wall.fragments)} faded, "
          f"{sum('discolour' in f.notes for f in wall.fragments)} discoloured")
    return 0


if __name__ == "__main__":
    sys.exit(main())
