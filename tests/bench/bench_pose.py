"""Pose accuracy of the proposed joins: the docking's candidate poses chosen by geometry and paint (issue 15).

    python tests/bench/bench_pose.py [--collection ../shared/data/repair-dev] [--dpi 150]
                                     [--train 31-36] [--test 21-23] [--weights 0,0.5,1,2,3,4,6,8]
                                     [--picture docs/matching/pose_repair.png]
                                     [--lines [--line-weight 20]]

For every true neighbour pair of realistic synthetic walls (``generate_wall(16, seed, dpi=40,
preset="pompeii")``, the generator's ground truth) and of a placed collection (RePAIR), the pair is
docked as the station's stage 3 docks it (``dock_outlines(..., n_poses=30, per_angle=3)``: the
candidate poses of ``index.DOCK_PAINT_POSES``), the paint continuity of each candidate is scored from
the stored outline and boundary profile (``paint_field_from_profile``, ``paint_continuity``), and the
pose is chosen by :func:`common.matching.pose.choose_pose` at each ``--weights`` value. It prints the
pose accuracy (share of true pairs whose chosen pose is within 5° and 5 mm of the truth, at B's centre)
per weight on the training walls (the weight is chosen there: best mean, ties to the smaller
weight), the test walls and the collection; that of the station's chooser since session 13, the
learned one (:func:`common.matching.pose.learned_pose_scores` of :func:`~common.matching.pose.pose_features`:
contact, paint and the outlines' facing geometry; fitted by ``tests/bench/bench_pose_learned.py``); the
ceiling (a candidate within 5°/5 mm exists), and
the CPU per pair of the docking and of the paint scores. ``--picture`` draws the collection's true pairs:
A's outline, B at its true pose (green), at the geometric docking's choice (grey) and at the
station's (learned) choice (red). Figures in docs/matching.md ("Poses that fit").

``--lines`` merges the pose hypotheses from painted lines (:mod:`common.matching.lines`: every
colour-compatible pair of boundary crossings, its grid of gap / turn / shift refined by
:func:`~common.matching.lines.outline_contact_mm`, the best 150 hypotheses kept and scored by
``docking_score_at`` and the paint) with the docking's 30, and chooses among all of them by
``contact + weight × paint + line_weight × line_continuity`` (continued crossings; ``--line-weight``).
Figures in docs/matching.md ("Pose hypotheses from painted lines"); slow (1–12 s CPU per pair).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.alignment import pose_matrix  # noqa: E402
from common.matching.collection import relative_pose_error  # noqa: E402
from common.matching.docking import DOCK_CELL_MM, Docking, dock_outlines, docking_score_at  # noqa: E402
from common.matching.lines import line_continuity, line_ends, line_pose_hypotheses, outline_contact_mm  # noqa: E402
from common.matching.paint import paint_continuity, paint_field_from_profile  # noqa: E402
from common.matching.pose import (POSE_PAINT_WEIGHT, choose_pose, learned_pose_scores, pose_features,  # noqa: E402
                                  pose_scores)

N_POSES, PER_ANGLE = 30, 3
#: line hypotheses kept per pair (the best by the sampled contact), as in docs/matching.md
N_LINE_POSES = 150


def seeds(text: str) -> list[int]:
    """Wall seeds from ``"31-36"``, ``"21,23"`` or both (``"21-23,31"``)."""
    out: list[int] = []
    for part in filter(None, text.split(",")):
        if "-" in part:
            lo, hi = (int(v) for v in part.split("-"))
            out += list(range(lo, hi + 1))
        else:
            out.append(int(part))
    return out


def line_candidates(ends_a, ends_b, ca, cb) -> list[Docking]:
    """The line hypotheses of a pair as docking candidates: each compatible pair of crossings' grid
    point with the best sampled contact, the best ``N_LINE_POSES`` of those, scored by the docking."""
    grid, _ = line_pose_hypotheses(ends_a, ends_b)
    if not len(grid):
        return []
    contact = outline_contact_mm(ca, cb, grid.reshape(-1, 3)).reshape(grid.shape[:2])
    best = contact.argmax(1)
    poses = grid[np.arange(len(grid)), best]
    keep = np.argsort(-contact[np.arange(len(grid)), best], kind="stable")[:N_LINE_POSES]
    out = []
    for a, tx, ty in poses[keep]:
        score = docking_score_at(ca, cb, (a, tx, ty))
        out.append(Docking(float(a), float(tx), float(ty), score, score * DOCK_CELL_MM / 2, 0.0))
    return out


def true_pairs(wall) -> tuple[dict, dict, dict, list[tuple[str, str]]]:
    """(cue tables, RGBN images, true poses, true neighbour pairs) of a synthetic wall, by fragment id; the pairs
    are those whose two fragments have a true pose and an outline of more than 3 points."""
    from common.matching.online import wall_cues

    tables, _, poses = wall_cues(wall)
    ok = {k for k, t in tables.items() if poses.get(k) is not None and len(t.contour_mm) > 3}
    images = {f.id: f.rgbn for f in wall.fragments}
    return tables, images, poses, [(a, b) for a, b, *_ in wall.adjacency if a in ok and b in ok]


def wall_pairs(wall, lines: bool = False) -> tuple[list[dict], float, float, float]:
    """Every true pair's candidates, paint scores, learned scores and pose errors; (pairs, docking CPU s, paint
    CPU s, learned chooser's CPU s: the facing geometry and the model).
    With ``lines`` the line hypotheses are added to each pair's candidates (CPU counted as docking's)."""
    tables, images, poses, pairs = true_pairs(wall)
    ends: dict = {}
    fields, out, cpu_dock, cpu_paint, cpu_learned = {}, [], 0.0, 0.0, 0.0
    for a, b in pairs:
        ca, cb = tables[a].contour_mm, tables[b].contour_mm
        c0 = time.process_time()
        docks = dock_outlines(ca, cb, n_poses=N_POSES, per_angle=PER_ANGLE)
        continuity = np.zeros(len(docks))
        if lines:
            for f in (a, b):
                if f not in ends:
                    ends[f] = line_ends(images[f].albedo, images[f].mask, 25.4 / images[f].dpi)
            docks = docks + line_candidates(ends[a], ends[b], ca, cb)
            continuity = line_continuity(ends[a], ends[b], [(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks])
        c1 = time.process_time()
        for f in (a, b):
            if f not in fields:
                fields[f] = paint_field_from_profile(tables[f].contour_mm, tables[f].boundary_profile)
        paint = paint_continuity(fields[a], fields[b], np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks]))
        c2 = time.process_time()
        learned = learned_pose_scores(pose_features(docks, paint, ca, cb))
        c3 = time.process_time()
        cpu_dock, cpu_paint, cpu_learned = cpu_dock + c1 - c0, cpu_paint + c2 - c1, cpu_learned + c3 - c2
        err = np.array([relative_pose_error(poses[a], poses[b], (d.angle_deg, d.tx_mm, d.ty_mm), cb.mean(axis=0))
                        for d in docks])
        out.append({"docks": docks, "paint": paint, "err": err, "contours": (ca, cb), "names": (a, b),
                    "continuity": continuity, "n_docked": N_POSES, "learned": learned,
                    "truth": _relative(poses[a], poses[b])})
    return out, cpu_dock, cpu_paint, cpu_learned


def _relative(pose_a, pose_b) -> tuple[float, float, float]:
    m = np.linalg.inv(pose_matrix(*pose_a)) @ pose_matrix(*pose_b)
    return float(np.degrees(np.arctan2(m[1, 0], m[0, 0]))), float(m[0, 2]), float(m[1, 2])


def picture(pairs: list[dict], path: str, weight: float | None = None) -> None:
    """One panel per pair: A (black), B at the truth (green), the geometric choice (grey), the chosen pose (red):
    the learned chooser's (``weight`` None) or ``contact + weight × paint``'s."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(pairs)
    cols = min(6, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3 * cols, 3 * rows), squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    for ax, p in zip(axes.flat, pairs):
        ca, cb = p["contours"]
        geometric = choose_pose(p["docks"], p["paint"], weight=0.0)
        chosen = choose_pose(p["docks"], p["paint"], scores=p["learned"]) if weight is None else \
            choose_pose(p["docks"], p["paint"], weight=weight)
        e = p["err"][p["docks"].index(chosen)]
        ax.fill(*np.vstack([ca, ca[:1]]).T, color="0.85", lw=0)
        ax.plot(*np.vstack([ca, ca[:1]]).T, color="k", lw=0.8)
        drawn = ((p["truth"], "tab:green", 1.6),
                 ((geometric.angle_deg, geometric.tx_mm, geometric.ty_mm), "0.55", 0.8),
                 ((chosen.angle_deg, chosen.tx_mm, chosen.ty_mm), "tab:red", 1.0))
        for pose, colour, lw in drawn:
            m = pose_matrix(*pose)
            q = np.vstack([cb, cb[:1]]) @ m[:2, :2].T + m[:2, 2]
            ax.plot(*q.T, color=colour, lw=lw)
        ax.set_aspect("equal")
        ax.invert_yaxis()   # y down, as the images
        right = e[0] <= 5 and e[1] <= 5
        a, b = (n.replace("_intact_mesh", "").replace("RPf_", "")[-6:] for n in p["names"])
        ax.set_title(f"{a}–{b}: {e[0]:.0f}°, {e[1]:.0f} mm"
                     + (" ✓" if right else ""), fontsize=8)
    chooser = "the learned chooser" if weight is None else f"contact + {weight:g} × paint"
    fig.suptitle(f"A filled; B at the truth (green), the docking's choice (grey), {chooser} (red)", fontsize=9)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    print(f"picture: {path}")


def accuracy(pairs: list[dict], weight: float, line_weight: float = 0.0) -> float:
    hits = 0
    for p in pairs:
        score = pose_scores(p["docks"], p["paint"], weight=weight) + line_weight * p["continuity"]
        e = p["err"][int(np.argmax(score))]
        hits += bool(e[0] <= 5 and e[1] <= 5)
    return hits / len(pairs) if pairs else float("nan")


def learned_accuracy(pairs: list[dict]) -> float:
    hits = [bool(p["err"][int(np.argmax(p["learned"])), 0] <= 5 and p["err"][int(np.argmax(p["learned"])), 1] <= 5)
            for p in pairs]
    return float(np.mean(hits)) if hits else float("nan")


def ceiling(pairs: list[dict], docked_only: bool = False) -> float:
    return float(np.mean([np.any((p["err"][:n, 0] <= 5) & (p["err"][:n, 1] <= 5))
                          for p in pairs for n in [p["n_docked"] if docked_only else len(p["err"])]]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--collection", default="../shared/data/repair-dev")
    p.add_argument("--dpi", type=float, default=150.0)
    p.add_argument("--train", default="31-36", help="training wall seeds (the weight is chosen on these)")
    p.add_argument("--test", default="21-23", help="test wall seeds")
    p.add_argument("--weights", default="0,0.5,1,2,3,4,6,8")
    p.add_argument("--picture", default="", help="PNG of the collection's true pairs at the chosen poses")
    p.add_argument("--lines", action="store_true", help="merge the pose hypotheses from painted lines")
    p.add_argument("--line-weight", type=float, default=20.0,
                   help="mm of contact one continued line crossing is worth (with --lines; 20 chosen on walls 31-36)")
    args = p.parse_args(argv)
    from common.synth.wall import generate_wall

    weights = [float(w) for w in args.weights.split(",")]
    t0, c0 = time.time(), time.process_time()
    sets: dict[str, list] = {}
    costs = []
    for role, ss in (("train", seeds(args.train)), ("test", seeds(args.test))):
        for s in ss:
            wall = generate_wall(16, seed=s, dpi=40, preset="pompeii", colour_only=True)
            pairs, cd, cp, cl = wall_pairs(wall, lines=args.lines)
            sets[f"{role} {s}"] = pairs
            costs.append((f"synthetic {s}", len(pairs), cd, cp, cl))
    if args.collection and Path(args.collection).is_dir():
        from common.matching.collection import collection_wall

        pairs, cd, cp, cl = wall_pairs(collection_wall(args.collection, dpi=args.dpi), lines=args.lines)
        sets["collection"] = pairs
        costs.append((args.collection, len(pairs), cd, cp, cl))
    elif args.collection:
        print(f"{args.collection}: no such directory, skipped")

    names = list(sets)
    lw = args.line_weight if args.lines else 0.0
    print(f"\npose accuracy (5°, 5 mm) of the chosen candidate, {N_POSES} candidates ({PER_ANGLE} per rotation)"
          + (f" + up to {N_LINE_POSES} line hypotheses, + {lw:g} × line continuity" if args.lines else ""))
    print(f"{'weight':>7s} " + " ".join(f"{n:>11s}" for n in names) + f" {'train mean':>10s} {'test mean':>9s}")
    table = {}
    for w in weights:
        acc = {n: accuracy(sets[n], w, lw) for n in names}
        table[w] = acc
        tr = [acc[n] for n in names if n.startswith("train")]
        te = [acc[n] for n in names if n.startswith("test")]
        print(f"{w:7.2f} " + " ".join(f"{acc[n]:11.3f}" for n in names) +
              f" {np.mean(tr) if tr else float('nan'):10.3f} {np.mean(te) if te else float('nan'):9.3f}")
    if not args.lines:      # the learned chooser over the docking's candidates: the station's pose
        acc = {n: learned_accuracy(sets[n]) for n in names}
        tr = [acc[n] for n in names if n.startswith("train")]
        te = [acc[n] for n in names if n.startswith("test")]
        print(f"{'learned':>7s} " + " ".join(f"{acc[n]:11.3f}" for n in names) +
              f" {np.mean(tr) if tr else float('nan'):10.3f} {np.mean(te) if te else float('nan'):9.3f}"
              "   (the station's chooser: pose.learned_pose_scores)")
    print(f"{'ceiling':>7s} " + " ".join(f"{ceiling(sets[n]):11.3f}" for n in names))
    if args.lines:
        print(f"{'docked':>7s} " + " ".join(f"{ceiling(sets[n], docked_only=True):11.3f}" for n in names)
              + "   (ceiling of the docking's own candidates)")
    train = [n for n in names if n.startswith("train")]
    if train:
        best = max(weights, key=lambda w: (round(float(np.mean([table[w][n] for n in train])), 9), -w))
        print(f"\nweight chosen on the training walls: {best:g} (pose.POSE_PAINT_WEIGHT = {POSE_PAINT_WEIGHT:g})")
    docking = "docking + lines" if args.lines else "docking"
    print("\nCPU per pair: " + "; ".join(f"{n} ({k} pairs): {docking} {cd / max(k, 1) * 1e3:.0f} ms, "
                                         f"paint of the candidates {cp / max(k, 1) * 1e3:.0f} ms, "
                                         f"learned chooser {cl / max(k, 1) * 1e3:.0f} ms"
                                         for n, k, cd, cp, cl in costs))
    if args.picture and sets.get("collection"):
        picture(sets["collection"], args.picture)
    print(f"{time.time() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
