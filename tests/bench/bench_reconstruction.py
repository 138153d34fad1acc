"""Reconstruction of a synthetic wall from its true joins confirmed: errors after the pose-graph solve, and time.

    python tests/bench/bench_reconstruction.py [--fragments 150] [--walls 3,5,7] [--draws 10] [--noise 0.3]
                                               [--composite-dpi 40]

For each wall (``generate_wall(N, seed, dpi=20)``, pose only) and each noise draw, every true join is
given the generator's relative pose with noise, solved by :func:`solve_pose_graph` with the fragments'
centres, and each piece's error is taken after the best rigid fit of its cluster to the truth:
its centre's distance (mm) and its angle (degrees). Noise models (per join):

* ``bounded``: B turned by U(−n, n)° about its centre and shifted by U(−n, n) mm per axis (each join
  off by at most n; the test's model);
* ``gauss``: the same with N(0, n) — a few joins per wall are then 2–3 n off;
* ``stored``: N(0, n) added to the stored (angle, tx, ty) — B turned about its frame origin (an image
  corner), so the shift at B's centre is larger.

Prints, per model: max and median over pieces (max over draws of the max; median of medians), the
share of draws with every piece within 1 mm and 1°, the spanning-tree start's max error, and the
solve's CPU time; then the same walls with one wrong join added (a non-neighbour pair at another
join's pose): how often a conflicting loop through it is flagged, and the others' errors. With
``--composite-dpi``, the first wall is also made with its images at that dpi, stored as a station's
fragments with every true join confirmed (bounded noise) in a proposal store, and ``tessera reconstruct``
is timed on it.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", ".."))

from common.matching.reconstruction import Join, closure_loops, relative_pose, solve_pose_graph  # noqa: E402
from common.synth.wall import generate_wall  # noqa: E402


def _apply(pose, p):
    a = math.radians(pose[0])
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return np.asarray(p, float) @ R.T + np.asarray(pose[1:], float)


def noisy_joins(wall, byid, centres, rng, n, model):
    draw = (lambda: rng.uniform(-n, n)) if model == "bounded" else (lambda: rng.normal(0.0, n))
    out = []
    for a, b, _ in wall.adjacency:
        z = relative_pose(byid[a].pose, byid[b].pose)
        if model == "stored":
            out.append(Join(a, b, z[0] + draw(), z[1] + draw(), z[2] + draw()))
            continue
        c = _apply(z, [centres[b]])[0]
        e = math.radians(draw())
        R = np.array([[math.cos(e), -math.sin(e)], [math.sin(e), math.cos(e)]])
        t = R @ (np.array(z[1:]) - c) + c + np.array([draw(), draw()])
        out.append(Join(a, b, z[0] + math.degrees(e), float(t[0]), float(t[1])))
    return out


def errors(clusters, byid, centres):
    mm, deg = [], []
    for c in clusters:
        root = byid[c.root]
        truth = {f: relative_pose(root.pose, byid[f].pose) for f in c.fragments}
        A = np.array([_apply(truth[f], [centres[f]])[0] for f in c.fragments])
        B = np.array([_apply(c.poses[f], [centres[f]])[0] for f in c.fragments])
        ma, mb = A.mean(axis=0), B.mean(axis=0)
        U, _, Vt = np.linalg.svd((B - mb).T @ (A - ma))
        R = (U @ Vt).T
        rot = math.degrees(math.atan2(R[1, 0], R[0, 0]))
        mm.append(np.linalg.norm((B - mb) @ R.T + ma - A, axis=1))
        deg.append(np.array([abs((c.poses[f][0] + rot - truth[f][0] + 180) % 360 - 180) for f in c.fragments]))
    return np.concatenate(mm), np.concatenate(deg)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fragments", type=int, default=150)
    ap.add_argument("--walls", default="3,5,7")
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument("--composite-dpi", type=float, default=0.0, help="also time `tessera reconstruct` at this dpi")
    args = ap.parse_args(argv)
    print(f"load average at start: {os.getloadavg()}")
    walls = []
    for s in (int(x) for x in args.walls.split(",")):
        w = generate_wall(args.fragments, seed=s, dpi=20, keep_images=False, surfaces=False, colour_only=True)
        byid = {f.id: f for f in w.fragments}
        centres = {f.id: tuple(f.contour_mm.mean(axis=0)) for f in w.fragments}
        placed = {f for a, b, _ in w.adjacency for f in (a, b)}
        walls.append((s, w, byid, centres))
        print(f"wall seed {s}: {len(w.fragments)} fragments delivered, {len(placed)} with a true neighbour, "
              f"{len(w.adjacency)} true joins, {w.width_mm:.0f} x {w.height_mm:.0f} mm")
    for model in ("bounded", "gauss", "stored"):
        maxmm, maxdeg, medmm, meddeg, ok, cpu, tree_mm, flagged = [], [], [], [], 0, [], [], 0
        for s, w, byid, centres in walls:
            for d in range(args.draws):
                joins = noisy_joins(w, byid, centres, np.random.default_rng(1000 * s + d), args.noise, model)
                t0 = time.process_time()
                clusters = solve_pose_graph(joins, centres_mm=centres)
                cpu.append(time.process_time() - t0)
                mm, deg = errors(clusters, byid, centres)
                tree_mm.append(errors(solve_pose_graph(joins, centres_mm=centres, refine=False), byid, centres)[0].max())
                maxmm.append(mm.max()); maxdeg.append(deg.max()); medmm.append(np.median(mm)); meddeg.append(np.median(deg))
                ok += bool(mm.max() <= 1.0 and deg.max() <= 1.0)
                flagged += sum(len(c.conflicting_loops) for c in clusters)
        n = len(maxmm)
        print(f"{model:8s} noise {args.noise}: max {max(maxmm):.2f} mm / {max(maxdeg):.2f} deg (median of draws' max "
              f"{np.median(maxmm):.2f} mm / {np.median(maxdeg):.2f} deg), median {np.median(medmm):.2f} mm / "
              f"{np.median(meddeg):.2f} deg; all pieces within 1 mm and 1 deg in {ok}/{n} draws; spanning-tree start "
              f"max {np.median(tree_mm):.2f} mm (median of draws); solve CPU {np.median(cpu) * 1000:.0f} ms median, "
              f"{max(cpu) * 1000:.0f} ms max; false conflicting loops {flagged}")
    # one wrong join per draw: confirmed last, or at a random moment among the true ones (joins carry
    # their confirmation order as time; blame_joins breaks ties by it)
    for when in ("last", "random"):
        caught, blamed_ok, rest_max, rest_med, cpu, total = 0, 0, [], [], [], 0
        for s, w, byid, centres in walls:
            ids = sorted({f for a, b, _ in w.adjacency for f in (a, b)})
            rng = np.random.default_rng(s)
            for d in range(args.draws):
                joins = noisy_joins(w, byid, centres, np.random.default_rng(1000 * s + d), args.noise, "bounded")
                while True:
                    a, b = (str(x) for x in sorted(rng.choice(ids, 2, replace=False)))
                    if not w.is_neighbour(a, b):
                        break
                k = int(rng.integers(len(joins)))
                wrong = Join(a, b, joins[k].angle_deg, joins[k].tx_mm, joins[k].ty_mm)
                at = len(joins) if when == "last" else int(rng.integers(len(joins) + 1))
                allj = joins[:at] + [wrong] + joins[at:]
                allj = [Join(j.fragment_a, j.fragment_b, j.angle_deg, j.tx_mm, j.ty_mm, time=float(i))
                        for i, j in enumerate(allj)]
                loops = closure_loops(allj, centres_mm=centres)
                total += 1
                caught += any(lp.conflicting and (a, b) in lp.joins for lp in loops)
                t0 = time.process_time()
                clusters = solve_pose_graph(allj, centres_mm=centres)
                cpu.append(time.process_time() - t0)
                blamed_ok += [p for c in clusters for p in c.blamed] == [(a, b)]
                mm, deg = errors(clusters, byid, centres)
                rest_max.append(mm.max()); rest_med.append(np.median(mm))
        worst = int(np.argmax(rest_max))
        print(f"one wrong join confirmed {when}: flagged in a conflicting loop {caught}/{total}; blamed alone "
              f"{blamed_ok}/{total}; pieces after the robust solve: median {np.median(rest_med):.2f} mm, max "
              f"{np.median(rest_max):.2f} mm (median of draws), draws with max <= 1 mm "
              f"{sum(m <= 1.0 for m in rest_max)}/{total}, worst draw {rest_max[worst]:.1f} mm; solve CPU "
              f"{np.median(cpu) * 1000:.0f} ms median, {max(cpu) * 1000:.0f} ms max")
    if args.composite_dpi:
        composite(walls[0][0], args)
    print(f"load average at end: {os.getloadavg()}")
    return 0


def composite(seed, args):
    import json
    import resource
    import tempfile
    from pathlib import Path

    from common.matching.proposals import Proposal, ProposalStore
    from common.rgbn.image import save_rgbn
    from common.store import Store
    from services.cli import main as cli

    t0, c0 = time.monotonic(), time.process_time()
    w = generate_wall(args.fragments, seed=seed, dpi=args.composite_dpi, surfaces=False)
    print(f"wall seed {seed} with images at {args.composite_dpi:g} dpi: {time.monotonic() - t0:.1f} s wall, "
          f"{time.process_time() - c0:.1f} s CPU")
    byid = {f.id: f for f in w.fragments}
    centres = {f.id: tuple(f.contour_mm.mean(axis=0)) for f in w.fragments}
    with tempfile.TemporaryDirectory() as tmp:
        store = Store(Path(tmp) / "store")
        for f in w.fragments:
            save_rgbn(store, f"fragments/{f.id}/rgbn/front-bench.h5", f.rgbn)
        joins = noisy_joins(w, byid, centres, np.random.default_rng(seed), args.noise, "bounded")
        with ProposalStore(Path(tmp) / "store" / "matches" / "proposals.sqlite") as db:
            db.upsert([Proposal(j.fragment_a, j.fragment_b, 0.9, "bench", angle_deg=j.angle_deg, tx_mm=j.tx_mm,
                                ty_mm=j.ty_mm) for j in joins])
            for j in joins:
                db.record_verdict(j.fragment_a, j.fragment_b, "confirmed")
        t0, c0 = time.monotonic(), time.process_time()
        status = cli(["reconstruct", "--store", str(Path(tmp) / "store"), "-o", str(Path(tmp) / "out")])
        wall_s, cpu_s = time.monotonic() - t0, time.process_time() - c0
        doc = json.loads((Path(tmp) / "out" / "reconstruction.json").read_text())
        sizes = [c["composite"]["size_px"] for c in doc["clusters"] if c["composite"]]
        print(f"tessera reconstruct ({len(doc['clusters'])} cluster(s), composites {sizes} px): exit {status}, "
              f"{wall_s:.1f} s wall, {cpu_s:.1f} s CPU, "
              f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
        # the page's JSON: first request (reads every face once), again (cached), after one more verdict
        from common.web.review import ReviewData
        from services import web
        app = web.create_app(token="x" * 32, store_root=Path(tmp) / "store",
                             review=ReviewData(Path(tmp) / "store" / "matches" / "proposals.sqlite", store))
        client = app.test_client()
        for what in ("first", "cached", "after a verdict"):
            if what == "after a verdict":
                with ProposalStore(Path(tmp) / "store" / "matches" / "proposals.sqlite") as db:
                    j = joins[0]
                    db.record_verdict(j.fragment_a, j.fragment_b, "confirmed")
            t0, c0 = time.monotonic(), time.process_time()
            r = client.get("/api/reconstruction")
            assert r.status_code == 200
            print(f"GET /api/reconstruction ({what}): {(time.monotonic() - t0) * 1000:.0f} ms wall, "
                  f"{(time.process_time() - c0) * 1000:.0f} ms CPU, {len(r.data) / 1024:.0f} KB")


if __name__ == "__main__":
    sys.exit(main())
