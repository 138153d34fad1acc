"""The pose's margin as join evidence: does a pair whose best pose stands out join more often? (issue 15, session 14)

    python tests/bench/bench_pose_margin.py [--train 31-40] [--test 21-23] [--collection ../shared/data/repair-dev]
                                            [--cache DIR]

Every pair of fragments within a synthetic wall (``generate_wall(16, seed, dpi=40, preset="pompeii",
colour_only=True)``: 120 pairs a wall) and within an object of a placed collection (RePAIR at 150 dpi) is
docked as the station's stage 3 docks it (``dock_outlines(n_poses=30, per_angle=3)``, the paint continuity
at each candidate, ``pose.learned_pose_scores`` of ``pose.pose_features``). Per pair it keeps the docking's
contact, the best paint, and the **pose margin**: the learned chooser's score of the chosen pose less the
median of its 30 candidates' (how far the best pose stands out). Then each query fragment's partners are
ranked (within its wall or object; @1 / @3 of its true neighbours, as ``within_object_recall``) by the
contact, by contact + 6 × paint, by the margin alone, and by logistic regressions fitted on the training
walls ONLY (class-balanced, standardised, C 0.1) over (contact, paint) and (contact, paint, margin); the
training walls' own figures are left-one-wall-out. This is the docking's evidence alone: the station's
ranking adds stages 2 and 2½ and the hubness corrections, and there the margin was measured separately
(docs/matching.md, "The pose's margin as join evidence").
"""

from __future__ import annotations

import argparse
import itertools
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.docking import dock_outlines, docking_contact_mm  # noqa: E402
from common.matching.paint import paint_continuity, paint_field_from_profile  # noqa: E402
from common.matching.pose import learned_pose_scores, pose_features  # noqa: E402
from tests.bench.bench_pose import seeds  # noqa: E402


def group_pairs(wall, group_of) -> list[dict]:
    """Every pair of fragments of one group (``group_of(id)``, None: left out) with its docking evidence."""
    from common.matching.online import wall_cues

    tables, _, _ = wall_cues(wall)
    ids = sorted(k for k, t in tables.items() if len(t.contour_mm) > 3 and group_of(k) is not None)
    true = {frozenset((a, b)) for a, b, *_ in wall.adjacency}
    fields = {k: paint_field_from_profile(tables[k].contour_mm, tables[k].boundary_profile) for k in ids}
    out = []
    for a, b in itertools.combinations(ids, 2):
        if group_of(a) != group_of(b):
            continue
        ca, cb = tables[a].contour_mm, tables[b].contour_mm
        docks = dock_outlines(ca, cb, n_poses=30, per_angle=3)
        paint = paint_continuity(fields[a], fields[b], np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks]))
        s = learned_pose_scores(pose_features(docks, paint, ca, cb))
        out.append(dict(a=a, b=b, true=frozenset((a, b)) in true, contact=docking_contact_mm(docks[0]),
                        paint=float(np.max(paint)), margin=float(s.max() - np.median(s))))
    return out


def hits(pairs: list[dict], scores) -> tuple[float, float, int]:
    """@1 and @3 of the queries that have a true neighbour (:func:`~common.matching.collection.within_object_recall`
    of each fragment's partners in its wall or object, best score first), and their number."""
    from common.matching.collection import within_object_recall

    scored: dict = {}
    neighbours: dict = {}
    for p, s in zip(pairs, scores):
        for q, o in (("a", "b"), ("b", "a")):
            me, other = (p["src"], p[q]), (p["src"], p[o])
            scored.setdefault(me, []).append((-float(s), len(scored.get(me, ())), other))
            if p["true"]:
                neighbours.setdefault(me, set()).add(other)
    rankings = {f: [o for *_, o in sorted(v)] for f, v in scored.items()}
    r = within_object_recall(rankings, neighbours, ks=(1, 3))
    return r["recall"][1], r["recall"][3], r["n"]


def columns(pairs, names) -> np.ndarray:
    return np.array([[p[n] for n in names] for p in pairs], float)


def fitted(train, names):
    from sklearn.linear_model import LogisticRegression
    from sklearn.preprocessing import StandardScaler

    x = columns(train, names)
    scaler = StandardScaler().fit(x)
    model = LogisticRegression(C=0.1, class_weight="balanced", max_iter=5000).fit(
        scaler.transform(x), [p["true"] for p in train])
    return lambda rows: model.decision_function(scaler.transform(columns(rows, names)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--train", default="31-40")
    ap.add_argument("--test", default="21-23")
    ap.add_argument("--collection", default="../shared/data/repair-dev")
    ap.add_argument("--dpi", type=float, default=150.0)
    ap.add_argument("--cache", default="", help="keep each wall's pairs here (pickles) and reuse them")
    args = ap.parse_args(argv)
    from common.synth.wall import generate_wall

    def load(name, make):
        path = Path(args.cache) / f"{name}.pkl" if args.cache else None
        if path is not None and path.exists():
            return pickle.load(open(path, "rb"))
        rows = [dict(p, src=name) for p in make()]
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            pickle.dump(rows, open(path, "wb"))
        print(f"{name}: {len(rows)} pairs, {sum(p['true'] for p in rows)} true", flush=True)
        return rows

    def wall(s):
        return load(f"wall{s}", lambda: group_pairs(generate_wall(16, seed=s, dpi=40, preset="pompeii",
                                                                  colour_only=True), lambda k: 0))

    if len(seeds(args.train)) < 2:
        ap.error("--train needs at least two walls (the fitted rows are left-one-wall-out)")
    train = {s: wall(s) for s in seeds(args.train)}
    sets = {"test walls": [p for s in seeds(args.test) for p in wall(s)]}
    if args.collection and Path(args.collection).is_dir():
        from common.matching.collection import collection_wall

        def repair():
            w = collection_wall(args.collection, dpi=args.dpi)
            obj = {f.id: (None if f.pose is None else f.notes.get("object")) for f in w.fragments}
            return group_pairs(w, obj.get)
        sets["collection"] = load("collection", repair)
    all_train = [p for rows in train.values() for p in rows]
    rules = {"contact": lambda r: columns(r, ["contact"])[:, 0],
             "contact + 6 × paint": lambda r: columns(r, ["contact"])[:, 0] + 6 * columns(r, ["paint"])[:, 0],
             "margin alone": lambda r: columns(r, ["margin"])[:, 0]}
    print(f"\n{'@1 / @3 (queries)':28s} {'training walls':>22s} " + " ".join(f"{n:>22s}" for n in sets))
    for label, score in rules.items():
        print(f"{label:28s} {'%.3f / %.3f (%d)' % hits(all_train, score(all_train)):>22s} "
              + " ".join(f"{'%.3f / %.3f (%d)' % hits(rows, score(rows)):>22s}" for rows in sets.values()))
    for label, names in (("fitted: contact, paint", ["contact", "paint"]),
                         ("fitted: + margin", ["contact", "paint", "margin"])):
        held = [hits(train[s], fitted([p for t, rows in train.items() if t != s for p in rows], names)(train[s]))
                for s in train]                # left-one-wall-out on the training walls
        n = sum(h[2] for h in held)
        cv = (sum(h[0] * h[2] for h in held) / n, sum(h[1] * h[2] for h in held) / n, n)
        score = fitted(all_train, names)
        print(f"{label:28s} {'%.3f / %.3f (%d)' % cv:>22s} "
              + " ".join(f"{'%.3f / %.3f (%d)' % hits(rows, score(rows)):>22s}" for rows in sets.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
