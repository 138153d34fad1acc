"""Why the docking misses true poses: the true pairs of a placed collection measured at their true pose
and at the docking's best pose (issue 15).

    python tests/bench/bench_docking_truth.py [--collection ../shared/data/repair-dev] [--dpi 150]
                                              [--synthetic 3] [--candidates 100] [--picture F.png]

For every true neighbour pair (the collection's, and those of ``--synthetic`` realistic walls,
``generate_wall(16, seed, preset="pompeii")``, the generator's ground truth) it prints:

- the overlap of the two outlines at the true pose (mm²: a large one would mean the truth is wrong
  or the overlap penalty kills it);
- the gap between the outlines along the shared crack (median mm of B's outline within 12 mm of A);
- the *facing length* (mm of outline within 10 mm of the other, mean of both sides) at the true
  pose and at the docking's best pose;
- the docking score at both, and the rank of the true pose among the docking's best
  ``--candidates`` poses (10 local maxima per rotation; a candidate counts as the true pose within
  6° and 7.5 mm, the search's grid: 4° and 1.5 mm cells).

It ends with the share of true poses among the best 1/5/20/100 candidates. Figures in
docs/matching.md ("Why the true pose scores low").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.alignment import pose_matrix  # noqa: E402
from common.matching.collection import relative_pose_error  # noqa: E402
from common.matching.docking import dock_outlines, docking_score_at  # noqa: E402


def resample(c: np.ndarray, step: float = 0.5) -> np.ndarray:
    closed = np.vstack([c, c[:1]])
    s = np.r_[0.0, np.cumsum(np.hypot(*np.diff(closed, axis=0).T))]
    at = np.arange(0.0, s[-1], step)
    return np.c_[np.interp(at, s, closed[:, 0]), np.interp(at, s, closed[:, 1])]


def overlap_mm2(ca: np.ndarray, cb: np.ndarray, cell: float = 0.25) -> float:
    import cv2

    lo = np.minimum(ca.min(0), cb.min(0))
    hi = np.maximum(ca.max(0), cb.max(0))
    shape = (int((hi[1] - lo[1]) / cell) + 2, int((hi[0] - lo[0]) / cell) + 2)
    masks = []
    for c in (ca, cb):
        m = np.zeros(shape, np.uint8)
        cv2.fillPoly(m, [np.round((c - lo) / cell * 16).astype(np.int32)], 1, shift=4)
        masks.append(m)
    return float((masks[0] & masks[1]).sum() * cell * cell)


def facing(ca: np.ndarray, cb: np.ndarray, reach: float = 10.0, step: float = 0.5) -> tuple[float, float]:
    """(facing length mm, mean of both sides; median gap mm of B's outline within 12 mm of A)."""
    ra, rb = resample(ca, step), resample(cb, step)
    db, _ = cKDTree(ra).query(rb)
    da, _ = cKDTree(rb).query(ra)
    near = db[db < 12.0]
    return 0.5 * step * ((db < reach).sum() + (da < reach).sum()), float(np.median(near)) if len(near) else float("nan")


def short(fid: str) -> str:
    return fid.replace("_intact_mesh", "").replace("RPf_", "")[-13:]


def placed(ca, cb, pose):
    m = pose_matrix(*pose)
    return cb @ m[:2, :2].T + m[:2, 2]


def truth_pose(poses, a, b):
    rel = np.linalg.inv(pose_matrix(*poses[a])) @ pose_matrix(*poses[b])
    return float(np.degrees(np.arctan2(rel[1, 0], rel[0, 0]))), float(rel[0, 2]), float(rel[1, 2])


def measure(name: str, contours: dict, poses: dict, adjacency, n_candidates: int) -> list[int]:
    print(f"\n{name}: {len(adjacency)} true pairs")
    print(f"{'pair':27s} {'ovl mm²':>7s} {'gap mm':>6s} {'face@truth':>10s} {'face@best':>9s} "
          f"{'score@truth':>11s} {'score@best':>10s} {'rank':>5s}")
    ranks = []
    for a, b, *_ in adjacency:
        ca, cb = contours[a], contours[b]
        tp = truth_pose(poses, a, b)
        cands = dock_outlines(ca, cb, n_poses=n_candidates, per_angle=10)
        best = cands[0]
        ft, gap = facing(ca, placed(ca, cb, tp))
        fb, _ = facing(ca, placed(ca, cb, (best.angle_deg, best.tx_mm, best.ty_mm)))
        rank = next((i for i, d in enumerate(cands)
                     if (lambda e: e[0] <= 6 and e[1] <= 7.5)(
                         relative_pose_error(poses[a], poses[b], (d.angle_deg, d.tx_mm, d.ty_mm), cb.mean(0)))), None)
        ranks.append(n_candidates if rank is None else rank)
        print(f"{short(a):>13s}-{short(b):13s} {overlap_mm2(ca, placed(ca, cb, tp)):7.1f} {gap:6.1f} {ft:10.0f} {fb:9.0f} "
              f"{docking_score_at(ca, cb, tp):11.0f} {best.score:10.0f} {'-' if rank is None else rank:>5}")
    r = np.array(ranks)
    print("true pose among the best k candidates: " +
          ", ".join(f"k={k}: {(r < k).mean():.2f}" for k in (1, 5, 20, 100) if k <= n_candidates))
    return ranks


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--collection", default="../shared/data/repair-dev")
    p.add_argument("--dpi", type=float, default=150.0)
    p.add_argument("--synthetic", type=int, default=3, help="realistic synthetic walls of 16 fragments (0: none)")
    p.add_argument("--candidates", type=int, default=100)
    args = p.parse_args(argv)
    from common.matching.online import wall_cues

    t0, c0 = time.time(), time.process_time()
    if args.collection and Path(args.collection).is_dir():
        from common.matching.collection import collection_wall

        wall = collection_wall(args.collection, dpi=args.dpi)
        tables, _, poses = wall_cues(wall)
        measure(f"{args.collection} at {args.dpi:g} dpi", {k: t.contour_mm for k, t in tables.items()}, poses,
                wall.adjacency, args.candidates)
    elif args.collection:
        print(f"{args.collection}: no such directory, skipped")
    from common.synth.wall import generate_wall

    for seed in range(21, 21 + args.synthetic):
        wall = generate_wall(16, seed=seed, dpi=40, preset="pompeii", colour_only=True)
        tables, _, poses = wall_cues(wall)
        ok = {k for k, t in tables.items() if poses[k] is not None and len(t.contour_mm) > 3}
        measure(f"synthetic pompeii wall, seed {seed}", {k: tables[k].contour_mm for k in ok}, poses,
                [p for p in wall.adjacency if p[0] in ok and p[1] in ok], args.candidates)
    print(f"\n{time.time() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
