"""Feature extractor benchmarks (issue 6).

    python tests/bench/bench_features.py            # speed and the Table 5.1-like table
    python tests/bench/bench_features.py --speed    # speed only
    python tests/bench/bench_features.py --table [--fragments 30 --seed 1 --dpi 200]
    python tests/bench/bench_features.py --pictures docs/features   # the debug pictures of docs/

Speed: all per-fragment and per-patch descriptors of a 10 cm fragment at 600 dpi (about
2400 x 2400 pixels), target <= 1.5 s on the 2-core station machine.

Table: on a synthetic fresco (common.synth.generate_wall) the correspondence (registry rule:
|a - b|, |a + b| for signed curvature, wrapped angle) of every descriptor for matching and
non-matching pairs, like Table 5.1 of the thesis: min / mean / max / stdev, and the AUC
(probability that a matching pair corresponds better than a non-matching one; 0.5 = useless).
Matching patch pairs: 10 mm patches of two adjacent fragments whose contour points both lie
within --match-mm (1 mm) of one ground-truth pair of corresponding contour points (patches are
sampled every 5 mm on each fragment independently, so only some of them face a patch of the
neighbour that closely). Non-matching:
patch pairs drawn at random from fragments that are not adjacent. Fragment level: adjacent vs
non-adjacent fragment pairs.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.features import (correspondence, extract_features,  # noqa: E402
                             fragment_descriptors, patch_descriptors)


def bench_speed(repeats: int = 3) -> None:
    from tests.features._fragments import textured_fragment
    img = textured_fragment(dpi=600.0, size_mm=100.0, canvas=1.02, seed=0)
    print(f"speed: 10 cm fragment at 600 dpi, image {img.shape[1]} x {img.shape[0]} px, "
          f"{int(img.mask.sum())} fragment pixels, normals + height")
    extract_features(img)  # warm-up (imports, FFT plans)
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        t = extract_features(img)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    print(f"  {t.n_patches} patches x {len(t.patch_names)} descriptors + {len(t.values)} fragment descriptors")
    print(f"  extract_features wall time: best {min(times):.3f} s, median {np.median(times):.3f} s over "
          f"{repeats} (target <= 1.5 s); CPU time (all threads) best {min(cpu):.3f} s; "
          f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")


def _auc(match: np.ndarray, non: np.ndarray) -> float:
    """P(match correspondence < non-match correspondence), ties count half."""
    if not len(match) or not len(non):
        return float("nan")
    allv = np.concatenate([match, non])
    order = np.argsort(allv, kind="mergesort")
    ranks = np.empty(len(allv))
    ranks[order] = np.arange(1, len(allv) + 1)
    # average ranks for ties
    _, inv, counts = np.unique(allv, return_inverse=True, return_counts=True)
    sums = np.bincount(inv, weights=ranks)
    ranks = (sums / counts)[inv]
    r_match = ranks[: len(match)].sum()
    u = r_match - len(match) * (len(match) + 1) / 2
    return 1.0 - u / (len(match) * len(non))


def bench_table(n_fragments: int, seed: int, dpi: float, out: Path | None, match_mm: float = 1.0,
                erosion_mm: float | None = None) -> None:
    from common.synth import generate_wall
    t0 = time.perf_counter()
    kw = {} if erosion_mm is None else {"erosion_mm": erosion_mm}
    wall = generate_wall(n_fragments, seed=seed, dpi=dpi, **kw)
    frags = {f.id: f for f in wall.fragments}
    print(f"table: synthetic fresco generate_wall({n_fragments}, seed={seed}, dpi={dpi:g}{', erosion_mm=%g' % erosion_mm if kw else ''}): "
          f"{len(frags)} fragments, {len(wall.adjacency)} adjacent pairs ({time.perf_counter() - t0:.0f} s)")
    tables = {}
    for fid, f in frags.items():
        tables[fid] = extract_features(f.rgbn)
    rng = np.random.default_rng(seed)

    # matching patch pairs from the ground-truth contour correspondences
    match_pairs = set()
    for (a, b), (pa, pb) in wall.correspondences.items():
        ta, tb = tables[a], tables[b]
        ia, ib = ta.patch_indices("p10"), tb.patch_indices("p10")
        if not len(ia) or not len(ib):
            continue
        for qa, qb in zip(pa, pb):
            da = np.linalg.norm(ta.patch_contour_mm[ia] - qa, axis=1)
            db = np.linalg.norm(tb.patch_contour_mm[ib] - qb, axis=1)
            if da.min() <= match_mm and db.min() <= match_mm:
                match_pairs.add((a, int(ia[np.argmin(da)]), b, int(ib[np.argmin(db)])))
    adjacent = {frozenset((a, b)) for a, b, _ in wall.adjacency}
    ids = sorted(frags)
    non_pairs = []
    tries = 0
    while len(non_pairs) < max(10 * len(match_pairs), 500) and tries < 100000:
        tries += 1
        a, b = rng.choice(ids, 2, replace=False)
        if frozenset((a, b)) in adjacent:
            continue
        ia, ib = tables[a].patch_indices("p10"), tables[b].patch_indices("p10")
        if len(ia) and len(ib):
            non_pairs.append((a, int(rng.choice(ia)), b, int(rng.choice(ib))))
    frag_match = [(a, b) for a, b, _ in wall.adjacency]
    frag_non = [(a, b) for i, a in enumerate(ids) for b in ids[i + 1:] if frozenset((a, b)) not in adjacent]

    lines = [f"| level | descriptor | rule | matches: min / mean / max / stdev | non-matches: min / mean / max / stdev | AUC |",
             "|---|---|---|---|---|---|"]

    def row(d, m, n):
        m, n = m[np.isfinite(m)], n[np.isfinite(n)]
        fmt = lambda v: (f"{v.min():.3g} / {v.mean():.3g} / {v.max():.3g} / {v.std():.3g}" if len(v) else "–")  # noqa: E731
        lines.append(f"| {d.level} | {d.name} | {d.rule} | {fmt(m)} (n={len(m)}) | {fmt(n)} (n={len(n)}) | {_auc(m, n):.2f} |")

    for d in fragment_descriptors():
        m = np.array([correspondence(d, tables[a].values[d.name], tables[b].values[d.name]) for a, b in frag_match])
        n = np.array([correspondence(d, tables[a].values[d.name], tables[b].values[d.name]) for a, b in frag_non])
        row(d, m, n)
    for d in patch_descriptors():
        def corr(pairs):
            return np.array([correspondence(d, tables[a].patch_column(d.name)[i], tables[b].patch_column(d.name)[j])
                             for a, i, b, j in pairs], float)
        row(d, corr(sorted(match_pairs)), corr(non_pairs))
    print(f"  {len(match_pairs)} matching / {len(non_pairs)} non-matching 10 mm patch pairs; "
          f"{len(frag_match)} / {len(frag_non)} fragment pairs")
    text = "\n".join(lines)
    print(text)
    if out:
        out.write_text(text + "\n")
        print(f"wrote {out}")


def make_pictures(out_dir: Path) -> None:
    """Debug pictures (patches, Fig. 5.5-like orientation, Fig. 5.6-like erosion) of the largest
    fragment of a small synthetic wall."""
    from common.features.debug import save_debug_pictures
    from common.synth import generate_wall
    wall = generate_wall(6, seed=4, dpi=300, median_size_mm=40)
    frag = max(wall.fragments, key=lambda f: f.rgbn.mask.sum())
    table = extract_features(frag.rgbn)
    for p in save_debug_pictures(frag.rgbn, table, out_dir, prefix="synth-"):
        print(f"wrote {p} (fragment {frag.id})")
    # the erosion map of the test fragment with a crack and pits (the synthetic wall has few)
    from tests.features._fragments import textured_fragment
    img = textured_fragment(dpi=300.0, size_mm=60.0, canvas=1.1, seed=0)
    paths = save_debug_pictures(img, extract_features(img), out_dir, prefix="generated-")
    for p in paths:
        if p.name != "generated-erosion.png":
            p.unlink()
        else:
            print(f"wrote {p} (tests/features/_fragments.py textured_fragment, seed 0, 300 dpi)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--speed", action="store_true")
    p.add_argument("--table", action="store_true")
    p.add_argument("--fragments", type=int, default=30)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--dpi", type=float, default=200.0)
    p.add_argument("--match-mm", type=float, default=1.0,
                   help="how close both patches' contour points must be to a corresponding pair")
    p.add_argument("--erosion-mm", type=float, help="edge erosion of the synthetic fresco (default: its own)")
    p.add_argument("--out", type=Path, help="also write the markdown table here")
    p.add_argument("--pictures", type=Path, help="write the debug pictures of docs/features.md here")
    a = p.parse_args(argv)
    if a.pictures:
        make_pictures(a.pictures)
        if not (a.speed or a.table):
            return 0
    both = not (a.speed or a.table)
    if a.speed or both:
        bench_speed()
    if a.table or both:
        bench_table(a.fragments, a.seed, a.dpi, a.out, a.match_mm, a.erosion_mm)
    return 0


if __name__ == "__main__":
    sys.exit(main())
