"""Benchmark: the realistic synthetic walls measured against real broken Pompeii frescoes (issue 15).

    python tests/bench/bench_synth_stats.py [--collection ../shared/data/repair-dev] [--walls 3]
        [--fragments 30] [--dpi 187.2] [--palette-seed 7] [--pictures docs/synth]

Measures the RePAIR collection and ``--walls`` synthetic walls of the ``pompeii`` preset (and one
wall of the original generator, for reference) with the same code (:mod:`common.synth.stats`),
at RePAIR's sampling by default so that pixel-scale figures compare, and prints the markdown
table of docs/synth.md with the generation times (wall clock and CPU: the machine is shared).
With ``--pictures`` it also writes ``repair_vs_synthetic.png``: real objects assembled at their
true places beside a synthetic wall at the same scale.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.synth import generate_wall  # noqa: E402
from common.synth.figures import collection_picture, save_png  # noqa: E402
from common.synth.stats import (REPAIR_DPI, collection_statistics, comparison_table, read_collection,  # noqa: E402
                                wall_collection)

ROOT = Path(__file__).resolve().parents[2]


def _timed(fn, *a, **kw):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*a, **kw)
    return out, time.perf_counter() - t0, time.process_time() - c0


def picture(real, out: Path, dpi: float, palette_seed: int, mm_per_px: float = 0.8) -> Path:
    """RePAIR's g12 and g13 assembled at their true places beside a 12-fragment pompeii wall."""
    pics = [collection_picture([p for p in real if p.object == o], REPAIR_DPI, mm_per_px=mm_per_px,
                               title=f"RePAIR {o.split('_')[1]} (real)")
            for o in ("RPobj_g12_o0012", "RPobj_g13_o0013")]
    small = generate_wall(12, 3, dpi, preset="pompeii", colour_only=True, palette_seed=palette_seed)
    pics.append(collection_picture([p for p in wall_collection(small) if p.matrix is not None], dpi,
                                   mm_per_px=mm_per_px, title="synthetic, pompeii (12 fragments)"))
    h = max(p.shape[0] for p in pics)
    row = np.hstack([np.pad(p, ((0, h - p.shape[0]), (0, 8), (0, 0)), constant_values=255) for p in pics])
    save_png(out / "repair_vs_synthetic.png", row)
    return out / "repair_vs_synthetic.png"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--collection", default=str(ROOT / ".." / "shared" / "data" / "repair-dev"))
    ap.add_argument("--walls", type=int, default=3)
    ap.add_argument("--fragments", type=int, default=30)
    ap.add_argument("--dpi", type=float, default=REPAIR_DPI)
    ap.add_argument("--palette-seed", type=int, default=7)
    ap.add_argument("--pictures", help="write repair_vs_synthetic.png here")
    args = ap.parse_args()
    if not Path(args.collection).is_dir():
        print(f"RePAIR collection not found at {args.collection}: nothing to compare against (skipped)")
        return 0
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (shared)")
    real, t, c = _timed(read_collection, args.collection)
    st_real, t2, c2 = _timed(collection_statistics, real, REPAIR_DPI)
    print(f"read {len(real)} real fragments: {t:.1f} s ({c:.1f} s CPU); measured in {t2:.1f} s ({c2:.1f} s CPU)")

    pieces, walls = [], []
    for k in range(args.walls):
        wall, t, c = _timed(generate_wall, args.fragments, k + 1, args.dpi, preset="pompeii", colour_only=True,
                            palette_seed=args.palette_seed)
        walls.append(wall)
        pieces += wall_collection(wall)
        print(f"pompeii wall {wall.id}: {len(wall.fragments)} fragments, {len(wall.adjacency)} true pairs, "
              f"{wall.width_mm:.0f} x {wall.height_mm:.0f} mm; generated in {t:.1f} s ({c:.1f} s CPU)")
        for f in wall.fragments:
            f.rgbn = None  # measured from the pieces; free the images
    st_syn, t, c = _timed(collection_statistics, pieces, args.dpi)
    print(f"measured {len(pieces)} synthetic fragments in {t:.1f} s ({c:.1f} s CPU)")
    legacy, t, c = _timed(generate_wall, args.fragments, 1, args.dpi, surfaces=False)
    print(f"original generator wall {legacy.id}: generated in {t:.1f} s ({c:.1f} s CPU)")
    st_old = collection_statistics(wall_collection(legacy), args.dpi)

    print()
    print(comparison_table({"RePAIR repair-dev": st_real,
                            f"pompeii preset ({args.walls} walls x {args.fragments})": st_syn,
                            "original generator (1 wall)": st_old}))
    if args.pictures:
        print(f"wrote {picture(real, Path(args.pictures), args.dpi, args.palette_seed)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
