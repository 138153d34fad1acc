"""Docking a newcomer against a confirmed cluster instead of one member (issue 15, session 16).

    python tests/bench/bench_cluster_docking.py [--collection ../shared/data/repair-dev] [--dpi 150]
                                                [--walls 21-23] [--json FILE]

For every fragment A of a placed collection (RePAIR) or realistic synthetic wall (``generate_wall(16, seed,
dpi=40, preset="pompeii", colour_only=True)``, as ``bench_pose.py``), every true neighbour B of A confirmed with
it (a cluster {A, B} at their true poses) and every other true neighbour C of A (the newcomer): C's pose in the
cluster frame

* as the station proposes it today: the pair A-C docked and its pose chosen as stage 3 chooses
  (:func:`~common.matching.docking.dock_outlines`, paint continuity, the learned chooser), composed with A's pose
  (what :func:`~common.matching.reconstruction.next_joins` gives without outlines);
* docked against the whole cluster (:func:`~common.matching.reconstruction.dock_newcomer`);
* by ``next_joins`` with the outlines: the fit it offers where C faces two members or more there (A among
  them), else the pair's.

Right: within 5° and 5 mm of the truth at C's centre (as ``tessera evaluate`` counts a pose). The cases are
split by whether C is a true neighbour of B too (it fits a corner of the cluster). Prints a table per source and
the CPU time of a cluster docking. Figures in docs/matching.md ("Docking against a confirmed cluster").
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.collection import relative_pose_error  # noqa: E402
from common.matching.docking import dock_outlines  # noqa: E402
from common.matching.index import DOCK_PAINT_PER_ANGLE, DOCK_PAINT_POSES  # noqa: E402
from common.matching.online import wall_cues  # noqa: E402
from common.matching.paint import paint_continuity, paint_field_from_profile  # noqa: E402
from common.matching.pose import learned_pose_scores, pose_features  # noqa: E402
from common.matching.reconstruction import Cluster, Join, next_joins  # noqa: E402
from common.web.compose import relative_pose  # noqa: E402
from tests.bench.bench_pose import seeds  # noqa: E402


def pair_pose(piece_a, piece_b) -> tuple[float, float, float]:
    """B's pose in A's frame as stage 3 proposes it (30 candidates, paint, the learned chooser)."""
    (ca, fa), (cb, fb) = piece_a, piece_b
    docks = dock_outlines(ca, cb, n_poses=DOCK_PAINT_POSES, per_angle=DOCK_PAINT_PER_ANGLE)
    poses = np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks], float)
    paint = paint_continuity(fa, fb, poses) if fa is not None and fb is not None else np.zeros(len(docks))
    return tuple(poses[int(np.argmax(learned_pose_scores(pose_features(docks, paint, ca, cb))))])


def cases(wall) -> tuple[list[dict], float]:
    """Every (A, B confirmed; C new) case of a wall: the three poses' errors; and the CPU of the cluster dockings."""
    tables, _, poses = wall_cues(wall)
    neighbours: dict = {}
    for a, b, *_ in wall.adjacency:
        neighbours.setdefault(a, set()).add(b)
        neighbours.setdefault(b, set()).add(a)
    pieces = {f: (t.contour_mm, paint_field_from_profile(t.contour_mm, t.boundary_profile))
              for f, t in tables.items() if f in neighbours}
    pairs: dict = {}
    out, cpu = [], 0.0
    for a in sorted(neighbours):
        for b in sorted(neighbours[a]):
            cluster = Cluster(id=f"C:{a}", root=a, fragments=sorted((a, b)),
                              poses={a: (0.0, 0.0, 0.0), b: relative_pose(poses[a], poses[b])},
                              joins=[Join(a, b, *relative_pose(poses[a], poses[b]))])
            for c in sorted(neighbours[a] - {b}):
                if (a, c) not in pairs:
                    pairs[(a, c)] = pair_pose(pieces[a], pieces[c])
                z = pairs[(a, c)]
                proposal = SimpleNamespace(id=0, fragment_a=a, fragment_b=c, probability=0.5, mutual=0.5,
                                           status="pending", angle_deg=z[0], tx_mm=z[1], ty_mm=z[2])
                c0 = time.process_time()
                got = next_joins(cluster, [proposal], [cluster], pieces=pieces)[0]
                cpu += time.process_time() - c0
                centre = pieces[c][0].mean(axis=0)

                def right(pose):
                    return max(relative_pose_error(poses[a], poses[c], pose, centre)) <= 5.0

                fit = got["fit"] is not None   # the fit where next_joins offers one, else the pair's pose
                out.append({"a": a, "b": b, "c": c, "corner": c in neighbours[b], "pair": right(z),
                            "station": right(got["fit"] if fit else got["pose"]),
                            "from": "cluster" if fit else "proposal"})
    return out, cpu


def table(name: str, rows: list[dict], cpu: float) -> dict:
    def share(sel, key):
        sel = [r for r in rows if sel(r)]
        return (sum(r[key] for r in sel), len(sel))

    res = {}
    for label, sel in (("corner", lambda r: r["corner"]), ("one member", lambda r: not r["corner"]),
                       ("all", lambda r: True)):
        res[label] = {"pair": share(sel, "pair"), "next_joins": share(sel, "station"),
                      "from_cluster": sum(1 for r in rows if sel(r) and r["from"] == "cluster")}
    print(f"{name}: {len(rows)} cases, cluster docking {cpu / max(len(rows), 1) * 1e3:.0f} ms CPU each")
    for label, r in res.items():
        (h0, n), (h1, _) = r["pair"], r["next_joins"]
        print(f"  {label:10s} n={n:4d}  pair's pose {h0 / max(n, 1):.3f} ({h0})  next_joins with outlines "
              f"{h1 / max(n, 1):.3f} ({h1}), docked against the cluster for {r['from_cluster']}")
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--collection", default="../shared/data/repair-dev")
    ap.add_argument("--dpi", type=float, default=150.0)
    ap.add_argument("--walls", default="21-23")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    from common.synth.wall import generate_wall

    results = {}
    if args.collection and Path(args.collection).is_dir():
        from common.matching.collection import collection_wall
        rows, cpu = cases(collection_wall(args.collection, dpi=args.dpi))
        results["collection"] = table(f"{args.collection} at {args.dpi:g} dpi", rows, cpu)
    for s in seeds(args.walls):
        rows, cpu = cases(generate_wall(16, seed=s, dpi=40, preset="pompeii", colour_only=True))
        results[f"wall{s}"] = table(f"wall {s}", rows, cpu)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
