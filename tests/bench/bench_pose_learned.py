"""A learned pose chooser: the docking's 30 candidate poses ranked by a model of cheap cues (issue 15, session 13).

    python tests/bench/bench_pose_learned.py cache --cache DIR [--train 31-80] [--test 21-23]
                                                   [--collection ../shared/data/repair-dev] [--dpi 150]
    python tests/bench/bench_pose_learned.py fit --cache DIR [--train 31-80] [--test 21-23] [--no-lines]
                                                 [--drop GROUPS] [--trees] [--ablation] [--emit | --check]
    python tests/bench/bench_pose_learned.py cache --cache DIR2 --more 70 --no-lines --no-probes [...]
    python tests/bench/bench_pose_learned.py offer --cache DIR2 [--sizes 30,45,60,100]
    python tests/bench/bench_pose_learned.py cache --cache DIR3 --more 70 --no-lines --no-probes --scale 1.248 \
        --collection ""                      # the synthetic walls as a station told 150 dpi for 187.2 sees them

The station's model (``pose.POSE_MODEL_RAW`` / ``POSE_MODEL_Z``) is ``cache --cache DIR --train 31-80`` then
``fit --cache DIR --train 31-80 --no-lines --drop paint_peak,band,overlap,rank,support --emit`` (``--check``:
exit 1 unless the weights it fits are the station's).

``cache``: for every true neighbour pair of the realistic synthetic walls (``generate_wall(16, seed,
dpi=40, preset="pompeii", colour_only=True)``, as ``bench_pose.py``) and of the placed collection
(RePAIR), the pair is docked as the station's stage 3 docks it (``dock_outlines(n_poses=30,
per_angle=3)``), and for each candidate pose the cues the library already has are stored: the
docking's score, band contact and overlap, the paint continuity (``paint_continuity`` of the
profile fields, as the station) at the candidate and at the candidate moved ±3 mm along / ±1.5 mm
across its facing stretch and turned ±2° about it, the painted-line continuity
(``lines.line_continuity`` of ``line_ends`` from the images: not available to the station's
stage 3, which keeps no images), and the pose error against the truth. One pickle per wall.

``fit``: per candidate a feature vector (:func:`candidate_features`: the cues above plus the facing
geometry of the two outlines at the pose, :func:`common.matching.facing.facing_geometry` — facing
length, longest facing run, gap quantiles along it, the gap's roughness, length pushed inside the
other piece, whether the two outlines' curvature profiles agree along the facing run, how far apart
the facing runs end — and the candidate's rank and support among the pair's candidates), each as its
raw value and its z-score within the pair (:func:`common.matching.pose.pose_design`); label:
within 5° and 5 mm of the truth. Rankers (balanced logistic regression pointwise, a pairwise logistic
ranker on within-pair differences, gradient-boosted trees) are fitted on the training walls ONLY,
hyper-parameters chosen by cross-validation grouped by wall (best mean top-1 pose accuracy over the
held-out walls); the chosen model, refitted on all training walls, is measured on the test walls and
the collection, beside the hand-weighted rule ``contact + 6 × paint`` (``pose.pose_scores``, the
station's chooser before session 13). ``--ablation``
drops one feature group at a time (refit, same hyper-parameters; cross-validated held-out accuracy,
then the test walls and the collection).
Figures in docs/matching.md ("A learned pose chooser").

``offer`` (session 14): from a cache whose pairs hold the station's 30 candidates and 70 more
(``cache --more 70``: ``dock_outlines(..., more_poses=70)``, up to 10 maxima per rotation), how often a right
pose is among what the station offers a person — the pose chosen among the first 30 and the next 9 or 19 of
the first M candidates (``pose.offered_poses``) — and how the pose would fare chosen among all 100. Figures
in docs/matching.md ("More candidate poses to offer").

``cache --scale S`` (session 16): every length of the synthetic walls S times longer (:func:`wall_seen_at`), as RePAIR's
187.2-dpi files evaluated at a nominal 150 dpi are; docs/matching.md, "A collection seen at the wrong scale".
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.collection import relative_pose_error  # noqa: E402
from common.matching.docking import dock_outlines  # noqa: E402
from common.matching.facing import FACING_COLUMNS, facing_geometry, probe_poses  # noqa: E402
from common.matching.lines import line_continuity, line_ends  # noqa: E402
from common.matching.paint import paint_continuity, paint_field_from_profile  # noqa: E402
from common.matching.pose import (POSE_FEATURES, POSE_PAINT_WEIGHT, fit_pose_ranker, learned_pose_scores,  # noqa: E402
                                  pose_design)
from tests.bench.bench_pose import seeds, true_pairs  # noqa: E402

N_POSES, PER_ANGLE = 30, 3
RIGHT_DEG, RIGHT_MM = 5.0, 5.0


# ----------------------------------------------------------------------------------------------------------------
# cache

def wall_cache(wall, with_lines: bool = True, n_poses: int = N_POSES, per_angle: int = PER_ANGLE,
               with_probes: bool = True, more_poses: int = 0) -> tuple[list[dict], dict]:
    """Every true pair's candidates (``dock_outlines(n_poses=, per_angle=, more_poses=)``) and raw cues; (pairs,
    CPU seconds by stage). Without ``with_probes`` the paint probes are zeros (the station's model does not use
    them)."""
    tables, images, poses, pairs = true_pairs(wall)
    ends, fields, out = {}, {}, []
    cpu = dict(dock=0.0, paint=0.0, lines=0.0, geometry=0.0, probes=0.0)
    for a, b in pairs:
        ca, cb = tables[a].contour_mm, tables[b].contour_mm
        c0 = time.process_time()
        docks = dock_outlines(ca, cb, n_poses=n_poses, per_angle=per_angle, more_poses=more_poses)
        c1 = time.process_time()
        for f in (a, b):
            if f not in fields:
                fields[f] = paint_field_from_profile(tables[f].contour_mm, tables[f].boundary_profile)
        pose_arr = np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks], float)
        paint = paint_continuity(fields[a], fields[b], pose_arr)
        c2 = time.process_time()
        cont = np.zeros(len(docks))
        if with_lines:
            for f in (a, b):
                if f not in ends:
                    ends[f] = line_ends(images[f].albedo, images[f].mask, 25.4 / images[f].dpi)
            cont = line_continuity(ends[a], ends[b], pose_arr)
        c3 = time.process_time()
        rows, directions, centres = facing_geometry(ca, cb, pose_arr)
        c4 = time.process_time()
        if with_probes:
            probes = probe_poses(pose_arr, directions, centres).reshape(-1, 3)
            probe_paint = paint_continuity(fields[a], fields[b], probes).reshape(len(docks), -1)
        else:
            probe_paint = np.zeros((len(docks), 6))
        c5 = time.process_time()
        for k, v in zip(cpu, (c1 - c0, c2 - c1, c3 - c2, c4 - c3, c5 - c4)):
            cpu[k] += v
        err = np.array([relative_pose_error(poses[a], poses[b], pz, cb.mean(axis=0)) for pz in pose_arr])
        out.append({"names": (a, b), "contours": (ca, cb),
                    "docks": np.array([(d.angle_deg, d.tx_mm, d.ty_mm, d.score, d.contact_mm, d.overlap_mm2)
                                       for d in docks], float),
                    "paint": np.asarray(paint, float), "probe_paint": probe_paint, "continuity": cont,
                    "geometry": rows, "err": err})
    return out, cpu


def wall_seen_at(wall, scale: float):
    """The wall as a station told a dpi ``scale`` times too low sees it: every length ``scale`` times longer
    (the images' dpi divided by it, poses and crack lengths multiplied). RePAIR's files are sampled at
    187 dpi and evaluated at a nominal 150 (docs/matching.md, "A collection seen at the wrong scale")."""
    from dataclasses import replace

    frags = [replace(f, rgbn=replace(f.rgbn, dpi=f.rgbn.dpi / scale),
                     pose=None if f.pose is None else (f.pose[0], f.pose[1] * scale, f.pose[2] * scale),
                     contour_mm=None if f.contour_mm is None else f.contour_mm * scale,
                     area_mm2=f.area_mm2 * scale * scale) for f in wall.fragments]
    return replace(wall, fragments=frags, adjacency=[(a, b, length * scale) for a, b, length in wall.adjacency],
                   correspondences={k: (u * scale, v * scale) for k, (u, v) in wall.correspondences.items()},
                   width_mm=wall.width_mm * scale, height_mm=wall.height_mm * scale, dpi=wall.dpi / scale)


def cmd_cache(args) -> int:
    from common.synth.wall import generate_wall

    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    jobs = [(f"wall{s}", s) for s in seeds(args.train) + seeds(args.test)]
    if args.collection:
        jobs.append(("collection", None))
    for name, s in jobs:
        path = cache / f"{name}.pkl"
        if path.exists() and not args.force:
            continue
        c0 = time.process_time()
        if s is None:
            from common.matching.collection import collection_wall

            if not Path(args.collection).is_dir():
                print(f"{args.collection}: no such directory, skipped")
                continue
            wall = collection_wall(args.collection, dpi=args.dpi)
        else:
            wall = generate_wall(16, seed=s, dpi=40, preset="pompeii", colour_only=True)
            if args.scale != 1.0:
                wall = wall_seen_at(wall, args.scale)
        c1 = time.process_time()
        pairs, cpu = wall_cache(wall, with_lines=not args.no_lines, n_poses=args.poses, per_angle=args.per_angle,
                               with_probes=not args.no_probes, more_poses=args.more)
        with open(path, "wb") as fh:
            pickle.dump({"pairs": pairs, "cpu": cpu, "cpu_wall": c1 - c0}, fh)
        n = max(len(pairs), 1)
        print(f"{name}: {len(pairs)} pairs; CPU per pair: " + ", ".join(f"{k} {v / n * 1e3:.0f} ms"
                                                                      for k, v in cpu.items())
              + f"; generation / features {c1 - c0:.0f} s", flush=True)
    return 0


# ----------------------------------------------------------------------------------------------------------------
# features

#: feature groups (the ablation drops one group at a time)
GROUPS = {
    "contact": ("contact_mm",),
    "band": ("band_mm",),
    "overlap": ("overlap_mm2",),
    "paint": ("paint_mm",),
    "paint_peak": ("paint_peak_along", "paint_peak_across", "paint_peak_turn"),
    "lines": ("continuity",),
    "facing": ("face_mm", "run_mm", "tight_mm"),
    "gap": ("gap_q10_mm", "gap_median_mm", "gap_q90_mm", "gap_rough_mm"),
    "inside": ("inside_mm", "depth_mm"),
    "curvature": ("curvature_mismatch", "curvature_correlation"),
    "ends": ("end_mismatch_mm",),
    "rank": ("dock_rank",),
    "support": ("support",),
}


def candidate_features(pair: dict) -> tuple[np.ndarray, list[str]]:
    """Raw per-candidate features of one pair: (N, F) and the names."""
    d = pair["docks"]
    contact = d[:, 3] * 1.5 / 2.0                           # docking_contact_mm (1.5 mm cells)
    paint = np.nan_to_num(pair["paint"])
    pp = np.nan_to_num(pair["probe_paint"])
    cols = {"contact_mm": contact, "band_mm": d[:, 4], "overlap_mm2": d[:, 5], "paint_mm": paint,
            "paint_peak_along": paint - pp[:, 0:2].max(1), "paint_peak_across": paint - pp[:, 2:4].max(1),
            "paint_peak_turn": paint - pp[:, 4:6].max(1), "continuity": pair["continuity"]}
    for i, name in enumerate(FACING_COLUMNS):
        cols[name] = pair["geometry"][:, i]
    order = np.argsort(-pose_scores_raw(d), kind="stable")
    rank = np.empty(len(d))
    rank[order] = np.arange(len(d))
    cols["dock_rank"] = rank
    # support: other candidates within 6° and 8 mm (B's outline centre) of this one
    cb = pair["contours"][1].mean(0)
    r = np.radians(d[:, 0])
    centres = np.stack([np.cos(r) * cb[0] - np.sin(r) * cb[1], np.sin(r) * cb[0] + np.cos(r) * cb[1]], 1) + d[:, 1:3]
    dang = np.abs((d[:, None, 0] - d[None, :, 0] + 180) % 360 - 180)
    dpos = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    cols["support"] = ((dang <= 6) & (dpos <= 8)).sum(1) - 1.0
    names = [n for g in GROUPS.values() for n in g]
    return np.stack([cols[n] for n in names], 1), names


def pose_scores_raw(d: np.ndarray) -> np.ndarray:
    return d[:, 3]


def load(cache: Path, names: list[str]) -> dict[str, list[dict]]:
    out = {}
    for n in names:
        p = cache / f"{n}.pkl"
        if not p.exists():
            print(f"{p}: missing (run `cache` first)")
            continue
        with open(p, "rb") as fh:
            out[n] = pickle.load(fh)
    return out


def right(err: np.ndarray) -> np.ndarray:
    return (err[:, 0] <= RIGHT_DEG) & (err[:, 1] <= RIGHT_MM)


# ----------------------------------------------------------------------------------------------------------------
# rankers

class Ranker:
    """A scorer of candidate poses fitted on pairs, over the raw feature columns ``columns`` (default all):
    ``kind`` "pairwise" or "pointwise" (:func:`common.matching.pose.fit_pose_ranker`: a logistic regression on
    within-pair differences right − wrong, or on the candidates, class-balanced; both over each feature's raw
    value and within-pair z-score, :func:`~common.matching.pose.pose_design`) or "trees" (gradient-boosted
    trees on the same design, pointwise)."""

    def __init__(self, kind: str, C: float = 1.0, columns=None, depth: int = 3, lr: float = 0.05, iters: int = 200):
        self.kind, self.C, self.columns = kind, C, columns
        self.depth, self.lr, self.iters = depth, lr, iters

    def _x(self, X):
        return X if self.columns is None else X[:, self.columns]

    def fit(self, pairs_X: list[np.ndarray], pairs_y: list[np.ndarray], seed: int = 0) -> "Ranker":
        Xs = [self._x(X) for X in pairs_X]
        if self.kind == "trees":
            from sklearn.ensemble import HistGradientBoostingClassifier

            X, y = np.vstack([pose_design(x) for x in Xs]), np.concatenate(pairs_y)
            self.model = HistGradientBoostingClassifier(max_depth=self.depth, learning_rate=self.lr,
                                                        max_iter=self.iters, class_weight="balanced",
                                                        l2_regularization=1.0 / self.C, random_state=seed)
            self.model.fit(X, y)
            return self
        self.weights = fit_pose_ranker(Xs, pairs_y, C=self.C, kind=self.kind, seed=seed)
        return self

    def score(self, X: np.ndarray) -> np.ndarray:
        if self.kind == "trees":
            return self.model.predict_proba(pose_design(self._x(X)))[:, 1]
        return learned_pose_scores(self._x(X), self.weights)


def top1(pairs_X, pairs_y, scorer) -> float:
    return float(np.mean([y[int(np.argmax(scorer(X)))] for X, y in zip(pairs_X, pairs_y)])) if pairs_X else np.nan


def rule(X: np.ndarray, names: list[str]) -> np.ndarray:
    """The hand-weighted rule, contact + POSE_PAINT_WEIGHT × paint (the station's chooser before session 13)."""
    return X[:, names.index("contact_mm")] + POSE_PAINT_WEIGHT * X[:, names.index("paint_mm")]


def cmd_fit(args) -> int:
    cache = Path(args.cache)
    train_names = [f"wall{s}" for s in seeds(args.train)]
    test_names = [f"wall{s}" for s in seeds(args.test)]
    data = load(cache, train_names + test_names + ["collection"])
    feats = {}
    names = None
    for w, blob in data.items():
        Xs, ys = [], []
        for p in blob["pairs"]:
            X, names = candidate_features(p)
            Xs.append(X)
            ys.append(right(p["err"]))
        feats[w] = (Xs, ys)
    train_names = [w for w in train_names if w in feats]
    test_names = [w for w in test_names if w in feats]
    print(f"{len(names)} features: {', '.join(names)}")

    def st(X):
        return rule(X, names)

    def block(ws):
        return [x for w in ws for x in feats[w][0]], [y for w in ws for y in feats[w][1]]

    n_raw = len(names)
    dropped = {m for g in (args.drop.split(",") if args.drop else []) for m in GROUPS[g]}
    if args.no_lines:
        dropped |= set(GROUPS["lines"])
    base_cols = [i for i in range(n_raw) if names[i] not in dropped]
    print("features used: " + ", ".join(n for n in names if n not in dropped))
    # hyper-parameter grid
    grid = []
    for C in (0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0):
        grid.append(("pointwise", dict(C=C)))
        grid.append(("pairwise", dict(C=C)))
    if args.trees:
        for depth in (2, 3):
            for iters in (100, 300):
                for C in (0.1, 1.0):
                    grid.append(("trees", dict(depth=depth, iters=iters, C=C)))
    folds = np.array_split(np.array(train_names), min(args.folds, len(train_names)))
    c0 = time.process_time()
    cv = []
    for kind, kw in grid:
        accs = []
        for k, held in enumerate(folds):
            fit_w = [w for w in train_names if w not in held]
            Xf, yf = block(fit_w)
            r = Ranker(kind, columns=base_cols, **kw).fit(Xf, yf)
            for w in held:
                accs.append(top1(*feats[w], r.score))
        cv.append((float(np.mean(accs)), kind, kw))
        print(f"  cv {kind:9s} {kw}: {np.mean(accs):.3f}", flush=True)
    print(f"cross-validation: {time.process_time() - c0:.0f} s CPU")
    best_acc, kind, kw = max(cv, key=lambda t: t[0])
    cv_station = float(np.mean([top1(*feats[w], st) for w in train_names]))
    print(f"\nchosen by cross-validation grouped by wall ({len(folds)} folds over {len(train_names)} walls): "
          f"{kind} {kw}, held-out mean {best_acc:.3f} (rule contact + 6 × paint {cv_station:.3f})")
    for k2 in ("pointwise", "pairwise", "trees"):
        sub = [t for t in cv if t[1] == k2]
        if sub:
            b = max(sub, key=lambda t: t[0])
            print(f"  best {k2}: {b[2]} {b[0]:.3f}")
    Xtr, ytr = block(train_names)
    model = Ranker(kind, columns=base_cols, **kw).fit(Xtr, ytr)
    c1 = time.process_time()
    for X in Xtr[:50]:
        model.score(X)
    score_ms = (time.process_time() - c1) / 50 * 1e3

    def report(label, scorer):
        tr = [top1(*feats[w], scorer) for w in train_names]
        te = [top1(*feats[w], scorer) for w in test_names]
        col = top1(*feats["collection"], scorer) if "collection" in feats else np.nan
        print(f"{label:34s} {np.mean(tr):10.3f} " + " ".join(f"{v:7.3f}" for v in te)
              + f" {np.mean(te):9.3f} {col:8.3f}")
        return np.mean(te), col

    print(f"\n{'pose accuracy (5°, 5 mm)':34s} {'train mean':>10s} " + " ".join(f"{w:>7s}" for w in test_names)
          + f" {'test mean':>9s} {'RePAIR':>8s}")
    report("rule: contact + 6 × paint", st)
    report("docking alone (contact)", lambda X: X[:, names.index("contact_mm")])
    report(f"learned ({kind})", model.score)
    for k2 in ("pointwise", "pairwise", "trees"):
        sub = [t for t in cv if t[1] == k2]
        if sub and k2 != kind:
            b = max(sub, key=lambda t: t[0])
            report(f"learned ({k2}, best of its cv)", Ranker(k2, columns=base_cols, **b[2]).fit(Xtr, ytr).score)
    if not args.no_lines:     # without the line continuity (the station's stage 3 keeps no images)
        no_lines = [i for i in range(n_raw) if names[i] != "continuity"]
        report(f"learned ({kind}), no line cue", Ranker(kind, columns=no_lines, **kw).fit(Xtr, ytr).score)
    ceil = {w: float(np.mean([y.any() for y in feats[w][1]])) for w in feats}
    print(f"{'ceiling (a candidate right)':34s} {np.mean([ceil[w] for w in train_names]):10.3f} "
          + " ".join(f"{ceil[w]:7.3f}" for w in test_names)
          + f" {np.mean([ceil[w] for w in test_names]):9.3f} {ceil.get('collection', np.nan):8.3f}")
    print(f"\nCPU per pair (cache stage, process_time): " + "; ".join(
        f"{w}: " + ", ".join(f"{k} {v / max(len(data[w]['pairs']), 1) * 1e3:.0f} ms" for k, v in data[w]["cpu"].items())
        for w in test_names + ["collection"] if w in data) + f"; the model's scoring {score_ms:.2f} ms")
    if args.ablation:
        print(f"\nablation ({kind} {kw}; refit on the training walls without one group)")
        print(f"{'dropped':14s} {'cv held-out':>11s} {'train mean':>10s} {'test mean':>9s} {'RePAIR':>8s}")
        for g, members in [("(none)", ())] + list(GROUPS.items()):
            cols = [i for i in base_cols if names[i] not in members]
            if len(cols) == len(base_cols) and g != "(none)":
                continue                       # not among the features used
            held_out = []
            for held in folds:
                fit_w = [w for w in train_names if w not in held]
                r = Ranker(kind, columns=cols, **kw).fit(*block(fit_w))
                held_out += [top1(*feats[w], r.score) for w in held]
            r = Ranker(kind, columns=cols, **kw).fit(Xtr, ytr)
            tr = np.mean([top1(*feats[w], r.score) for w in train_names])
            te = np.mean([top1(*feats[w], r.score) for w in test_names])
            col = top1(*feats["collection"], r.score) if "collection" in feats else np.nan
            print(f"{g:14s} {np.mean(held_out):11.3f} {tr:10.3f} {te:9.3f} {col:8.3f}", flush=True)
    used = [names[i] for i in base_cols]
    if (args.emit or args.check) and kind != "trees":
        raw, z = model.weights
        print(f"\nweights ({kind} {kw}) over {', '.join(used)}:")
        print("POSE_MODEL_RAW = (" + ", ".join(f"{v:.6g}" for v in raw) + ")")
        print("POSE_MODEL_Z = (" + ", ".join(f"{v:.6g}" for v in z) + ")")
    if args.check:
        from common.matching import pose

        same = (tuple(used) == POSE_FEATURES and kind != "trees"
                and np.allclose(model.weights[0], pose.POSE_MODEL_RAW, rtol=1e-4, atol=1e-9)
                and np.allclose(model.weights[1], pose.POSE_MODEL_Z, rtol=1e-4, atol=1e-9))
        print("the station's weights (pose.POSE_MODEL_RAW / _Z) " + ("are reproduced" if same else "DIFFER"))
        if not same:
            return 1
    if args.save:
        with open(args.save, "wb") as fh:
            pickle.dump({"model": model, "kind": kind, "kw": kw, "names": names}, fh)
    return 0


def cmd_offer(args) -> int:
    """What the station offers a person (the proposed pose and its alternatives) from the candidates of a cache
    made with ``--more``: the pose chosen among the first 30 (:func:`common.matching.pose.offered_poses`), the
    alternatives from the first M candidates, and the pose chosen among all of them instead."""
    from common.matching.docking import Docking
    from common.matching.pose import offered_poses

    cache = Path(args.cache)
    groups = {"training walls": [f"wall{s}" for s in seeds(args.train)],
              "test walls": [f"wall{s}" for s in seeds(args.test)], "collection": ["collection"]}
    sizes = sorted({int(m) for m in args.sizes.split(",")})
    for label, names in groups.items():
        pairs = [p for blob in load(cache, names).values() for p in blob["pairs"]]
        if not pairs:
            continue
        if min(len(p["docks"]) for p in pairs) < max(sizes):
            print(f"{label}: fewer than {max(sizes)} candidates for some pairs (make the cache with --more)")
        offered = {(m, k): [] for m in sizes for k in (9, 19)}
        chosen, among_all, ceiling = [], [], []
        for p in pairs:
            X, names_ = candidate_features(p)
            F = X[:, [names_.index(f) for f in POSE_FEATURES]]
            docks = [Docking(*map(float, r)) for r in p["docks"]]
            ok = right(p["err"])
            for m in sizes:
                o = offered_poses(docks[:m], None, F[:m], choose_among=N_POSES)
                for k in (9, 19):
                    offered[(m, k)].append(any(ok[docks.index(d)] for d in o[:1 + k]))
            chosen.append(ok[int(np.argmax(learned_pose_scores(F[:N_POSES])))])
            among_all.append(ok[int(np.argmax(learned_pose_scores(F)))])
            ceiling.append(ok.any())
        chosen, among_all = np.array(chosen), np.array(among_all)
        print(f"{label} ({len(pairs)} true pairs): pose chosen among the first {N_POSES} {chosen.mean():.3f}; among all "
              f"{among_all.mean():.3f} (right where it was wrong {int((among_all & ~chosen).sum())}, wrong where it "
              f"was right {int((chosen & ~among_all).sum())}); a right candidate among all {np.mean(ceiling):.3f}")
        for m in sizes:
            print(f"  offered from the first {m:3d}: with 9 alternatives {np.mean(offered[(m, 9)]):.3f}, "
                  f"with 19 {np.mean(offered[(m, 19)]):.3f}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cache", help="dock every true pair and store the cues of its candidates")
    c.add_argument("--cache", required=True)
    c.add_argument("--train", default="31-50")
    c.add_argument("--test", default="21-23")
    c.add_argument("--collection", default="../shared/data/repair-dev")
    c.add_argument("--dpi", type=float, default=150.0)
    c.add_argument("--no-lines", action="store_true")
    c.add_argument("--no-probes", action="store_true", help="skip the paint probes (not in the station's model)")
    c.add_argument("--poses", type=int, default=N_POSES, help="candidates per pair (the station: 30)")
    c.add_argument("--per-angle", type=int, default=PER_ANGLE, help="local maxima per rotation (the station: 3)")
    c.add_argument("--more", type=int, default=0,
                   help="further candidates after those (dock_outlines' more_poses, 10 per rotation; the station: 70)")
    c.add_argument("--scale", type=float, default=1.0,
                   help="see the synthetic walls at a dpi this many times too low (RePAIR at 150 dpi: 187.2 / 150)")
    c.add_argument("--force", action="store_true")
    f = sub.add_parser("fit", help="fit rankers on the training walls, measure on the test walls and the collection")
    f.add_argument("--cache", required=True)
    f.add_argument("--train", default="31-50")
    f.add_argument("--test", default="21-23")
    f.add_argument("--folds", type=int, default=5)
    f.add_argument("--trees", action="store_true", help="also gradient-boosted trees (slow; not better in session 13)")
    f.add_argument("--no-lines", action="store_true",
                   help="without the painted-line continuity (the station's stage 3 keeps no images to find lines)")
    f.add_argument("--ablation", action="store_true")
    f.add_argument("--drop", default="", help="feature groups left out, comma-separated (" + ", ".join(GROUPS) + ")")
    f.add_argument("--save", default="")
    f.add_argument("--emit", action="store_true", help="print the chosen linear model's weights as code")
    f.add_argument("--check", action="store_true",
                   help="exit 1 unless the chosen model's weights equal pose.POSE_MODEL_RAW / POSE_MODEL_Z")
    o = sub.add_parser("offer", help="the proposed pose and the alternatives offered, from a cache made with --more")
    o.add_argument("--cache", required=True)
    o.add_argument("--train", default="31-80")
    o.add_argument("--test", default="21-23")
    o.add_argument("--sizes", default="30,45,60,100", help="offer from the first M candidates, comma-separated")
    args = p.parse_args(argv)
    return {"cache": cmd_cache, "fit": cmd_fit, "offer": cmd_offer}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
