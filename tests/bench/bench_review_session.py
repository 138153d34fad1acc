"""A conservator's review session, simulated: how many confirmed joins keep a right pose (issue 15, session 17).

    python tests/bench/bench_review_session.py [--collection ../shared/data/repair-dev] [--dpi 150]
                                               [--walls 21-23] [--orders 5] [--json FILE]

The review page shows each proposal's joined picture at a pose and a confirmation stores the pose shown
(docs/web.md). Where a proposal's newcomer fits a corner of a cluster already confirmed
(:func:`~common.matching.reconstruction.next_joins` with the outlines: docked against the whole cluster, it faces
two members there, the proposal's among them), which pose should the page show first? This bench walks every
true pair of a placed collection (RePAIR) or realistic synthetic wall (``generate_wall(16, seed, dpi=40, preset="pompeii", colour_only=True)``, as
``bench_cluster_docking.py``) in a random order (``--orders`` seeds: the review queue's order does not know which
pairs are corners), confirms each at the pose the page would show, and counts the confirmed joins whose stored
pose is right (within 5° and 5 mm at B's centre, as ``tessera evaluate`` counts) — shown at the pair's own pose
(stage 3's choice, what the page shows first) or at the cluster's fit where there is one. The clusters are solved
from the joins confirmed so far (:func:`~common.matching.reconstruction.solve_pose_graph`), as the web app does.
False proposals are left out (a person rejects them; they change no cluster). Without ``--corrected`` no pose
is corrected by hand, so wrong poses build the clusters the next newcomers are fitted into; with it the
conservator sets every wrong pose right before confirming (the clusters are true), and the count is of the
confirmations that needed no correction.

Prints per source: joins confirmed right at first sight, with and without the fit, and how many were shown the
fit. Figures in docs/matching.md ("Docking against a confirmed cluster").
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.collection import relative_pose_error  # noqa: E402
from common.matching.online import wall_cues  # noqa: E402
from common.matching.paint import paint_field_from_profile  # noqa: E402
from common.matching.reconstruction import (Join, fit_as_proposal_pose, next_joins, relative_pose,  # noqa: E402
                                            solve_pose_graph)
from tests.bench.bench_cluster_docking import pair_pose  # noqa: E402
from tests.bench.bench_pose import seeds  # noqa: E402


def session(order: list, truth: dict, pieces: dict, proposed: dict, *, corrected: bool = False) -> list[dict]:
    """Confirm the true pairs ``order`` one by one at the pose the review page shows (``corrected``: at the true
    pose, as a conservator who sets every wrong pose right by hand); each step's record."""
    joins, out = [], []
    for a, b in order:
        z = proposed[(a, b)]
        shown, source = z, "proposal"
        clusters = solve_pose_graph(joins) if joins else []
        home = {f: c for c in clusters for f in c.fragments}
        member = a if a in home else b if b in home else None
        if member is not None and not (a in home and b in home and home[a] is home[b]):
            proposal = SimpleNamespace(id=0, fragment_a=a, fragment_b=b, probability=0.5, mutual=0.5,
                                       status="pending", angle_deg=z[0], tx_mm=z[1], ty_mm=z[2])
            got = next_joins(home[member], [proposal], clusters, pieces=pieces)[0]
            if got["fit"] is not None:
                shown = fit_as_proposal_pose(home[member].poses[member], got["fit"], member, a)
                source = "cluster"
        centre = pieces[b][0].mean(axis=0)
        out.append({"pair": (a, b), "source": source,
                    "right": max(relative_pose_error(truth[a], truth[b], shown, centre)) <= 5.0,
                    "pair_right": max(relative_pose_error(truth[a], truth[b], z, centre)) <= 5.0})
        joins.append(Join(a, b, *(relative_pose(truth[a], truth[b]) if corrected else shown)))
    return out


def run(wall, orders: int, corrected: bool = False) -> dict:
    """Every true pair's stage-3 pose, then ``orders`` simulated sessions; totals over them."""
    tables, _, truth = wall_cues(wall)
    pairs = sorted({tuple(sorted((a, b))) for a, b, *_ in wall.adjacency})
    used = {f for p in pairs for f in p}
    pieces = {f: (t.contour_mm, paint_field_from_profile(t.contour_mm, t.boundary_profile))
              for f, t in tables.items() if f in used}
    proposed = {(a, b): pair_pose(pieces[a], pieces[b]) for a, b in pairs}
    res = {"joins": 0, "right_pair": 0, "right_shown": 0, "shown_fit": 0, "fit_right": 0, "fit_pair_right": 0}
    t0 = time.process_time()
    for seed in range(orders):
        order = pairs[:]
        random.Random(seed).shuffle(order)
        for r in session(order, truth, pieces, proposed, corrected=corrected):
            res["joins"] += 1
            res["right_pair"] += r["pair_right"]
            res["right_shown"] += r["right"]
            if r["source"] == "cluster":
                res["shown_fit"] += 1
                res["fit_right"] += r["right"]
                res["fit_pair_right"] += r["pair_right"]
    res["cpu_s"] = time.process_time() - t0
    return res


def report(name: str, r: dict) -> None:
    n = max(r["joins"], 1)
    print(f"{name}: {r['joins']} confirmations; right at the pair's pose {r['right_pair']} ({r['right_pair'] / n:.3f}), "
          f"as shown with the cluster's fit {r['right_shown']} ({r['right_shown'] / n:.3f}); the fit shown for "
          f"{r['shown_fit']} (right {r['fit_right']}, their pair's pose right {r['fit_pair_right']}); "
          f"{r['cpu_s']:.0f} s CPU")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--collection", default="../shared/data/repair-dev")
    ap.add_argument("--dpi", type=float, default=150.0)
    ap.add_argument("--walls", default="21-23")
    ap.add_argument("--orders", type=int, default=5, help="random review orders per source (default 5)")
    ap.add_argument("--corrected", action="store_true",
                    help="the conservator sets every wrong pose right before confirming (the joins stored are true)")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    from common.synth.wall import generate_wall

    results = {}
    if args.collection and Path(args.collection).is_dir():
        from common.matching.collection import collection_wall
        results["collection"] = run(collection_wall(args.collection, dpi=args.dpi), args.orders,
                                     args.corrected)
        report(f"{args.collection} at {args.dpi:g} dpi", results["collection"])
    for s in seeds(args.walls):
        results[f"wall{s}"] = run(generate_wall(16, seed=s, dpi=40, preset="pompeii", colour_only=True), args.orders,
                                   args.corrected)
        report(f"wall {s}", results[f"wall{s}"])
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
