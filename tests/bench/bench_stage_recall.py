"""Where the true partners are lost: a stage-by-stage recall table of the staged matcher (issue 15).

For every query fragment of a test set, the rank of each of its true neighbours after stage 1 (the
KD-tree's 100 candidates), stage 2 (patch classifier with hubness), stage 2½ (colour ribbon on the best
50), stage 3 (docking + paint of the best 12) and in the final pooled ranking (the larger of the two
sides' probabilities, as ``tessera evaluate`` counts top-k), and the share of true links still in reach
(in the stage's list) and in its top 1 / 5 / 10 / 12 / 50:

    python tests/bench/bench_stage_recall.py [--sets synthetic,dafne,repair] [--cache DIR] [--json FILE]
                                             [--png FILE] [--traces DIR]

Sets: ``synthetic`` — ``tessera evaluate``'s walls (150 fragments, 100 dpi, train seed 11, test seed 12;
model and its ribbon/docking calibrations fitted on the training wall); ``dafne`` — the DAFNE halves
(train one half, rank the other with the spurious fragments, both ways); ``repair`` —
../shared/data/repair-dev at 150 dpi, pooled, with the station's bootstrap model (nothing fitted on it).
``--cache DIR`` keeps the feature tables and models between runs (pickles; the first run builds them);
``--traces DIR`` keeps each set's traces (to re-rank them offline, e.g. by another stage-3 combination);
the set ``synthetic-train`` traces the training wall with its own model (what stage 3's learned
combination is fitted on; never a test figure). Figures and timings: docs/matching.md, "Where the true
partners are lost".
"""

from __future__ import annotations

import argparse
import json
import pickle
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"
KS = (1, 5, 10, 12, 50)
STAGES = (("prune", "stage 1: KD-tree, 100 candidates"), ("patch", "stage 2: patch classifier + hubness"),
          ("ribbon", "stage 2½: ribbon on the best 50"), ("dock", "stage 3: docking + paint of the best 12"),
          ("final", "final: pooled (max of both sides)"))


def _cached(cache, name, build):
    path = Path(cache) / f"{name}.pkl" if cache else None
    if path is not None and path.exists():
        with open(path, "rb") as fh:
            return pickle.load(fh)
    data = build()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            pickle.dump(data, fh)
    return data


def build_synthetic():
    from common.matching.online import ribbon_calibration, train_model, wall_cues
    from common.matching.pairs import training_set
    from common.matching.report import _docking_of
    from common.synth.wall import generate_wall

    wall = generate_wall(150, seed=11, dpi=100.0)
    tables, cues, poses = wall_cues(wall)
    ts = training_set(cues, poses, wall.adjacency, negatives_per_positive=10.0, seed=11)
    wall2 = generate_wall(150, seed=12, dpi=100.0)
    tables2, cues2, poses2 = wall_cues(wall2)
    model, _ = train_model(ts, info={"trained_on": wall.id}, ribbon=ribbon_calibration(tables, wall.adjacency),
                           docking=_docking_of(wall, tables, 11))
    for w in (wall, wall2):
        for f in w.fragments:
            f.rgbn = None
    return dict(train=(wall, tables, cues, poses), test=(wall2, tables2, cues2, poses2), model=model)


def build_dafne():
    from common.matching.online import ribbon_calibration, train_model, wall_cues
    from common.matching.pairs import training_set
    from common.matching.report import _docking_of
    from common.synth.dafne import import_dafne
    from common.synth.wall import Wall

    wall = import_dafne(str(DATA / "dafne-adam"))
    tables, cues, poses = wall_cues(wall)
    placed = {f.id: f.pose for f in wall.fragments if f.pose is not None}
    xs = {fid: p[1] for fid, p in placed.items()}
    cut = float(np.median(list(xs.values())))
    halves = [{f for f in xs if xs[f] < cut}, {f for f in xs if xs[f] >= cut}]
    spurious = {f.id for f in wall.fragments if f.pose is None}
    models = []
    for h in range(2):
        train_ids = halves[h]
        adj_tr = [p for p in wall.adjacency if p[0] in train_ids and p[1] in train_ids]
        ts_h = training_set({f: cues[f] for f in train_ids}, placed, adj_tr, negatives_per_positive=10.0, seed=h)
        half = Wall(f"{wall.id}-half{h}", [f for f in wall.fragments if f.id in train_ids], adj_tr, {}, 0.0, 0.0,
                    wall.dpi)
        model, _ = train_model(ts_h, ribbon=ribbon_calibration({f: tables[f] for f in train_ids}, adj_tr),
                               docking=_docking_of(half, {f: tables[f] for f in train_ids}, h))
        models.append(model)
    for f in wall.fragments:
        f.rgbn = None
    return dict(wall=wall, tables=tables, cues=cues, poses=poses, halves=halves, spurious=spurious, models=models)


def build_repair():
    from common.matching.collection import collection_wall
    from common.matching.online import bootstrap_model, wall_cues

    wall = collection_wall(str(DATA / "repair-dev"), dpi=150, near_px=48.0, min_run_px=100.0)
    model = bootstrap_model()
    tables, cues, poses = wall_cues(wall)
    for f in wall.fragments:
        f.rgbn = None
    return dict(wall=wall, tables=tables, cues=cues, poses=poses, model=model)


def traces_of(tables, cues, ids, model, progress=None):
    """Every fragment of ``ids`` traced through the stages, as ``rank_all_pairs`` ranks them."""
    from common.matching.evaluation import trace_stages
    from common.matching.index import MatchIndex

    idx = MatchIndex()
    for f in sorted(ids, key=str):
        idx.add(cues[f], tables[f].contour_mm, tables[f].boundary_profile)
    order = list(idx._order)
    idx.refresh_hubness(order, model, n_candidates=100)
    out = []
    for i, f in enumerate(order):
        out.append(trace_stages(idx, model, f, order))
        if progress and (i % 25 == 0 or i == len(order) - 1):
            progress(f"  traced {i + 1}/{len(order)}")
    return out


def set_traces(name, data):
    """(traces, true neighbour pairs) of one test set."""
    say = lambda s: print(s, flush=True)   # noqa: E731
    if name == "synthetic":
        wall2, tables2, cues2, _ = data["test"]
        return traces_of(tables2, cues2, list(cues2), data["model"], say), wall2.adjacency
    if name == "dafne":
        wall, halves, spurious = data["wall"], data["halves"], data["spurious"]
        traces = []
        for h in range(2):
            traces += traces_of(data["tables"], data["cues"], halves[1 - h] | spurious, data["models"][h], say)
        return traces, [p for p in wall.adjacency if (p[0] in halves[0]) == (p[1] in halves[0])]
    if name == "synthetic-train":   # the training wall with its own model (to fit on; never a test figure)
        wall, tables, cues, _ = data["train"]
        return traces_of(tables, cues, list(cues), data["model"], say), wall.adjacency
    if name == "repair":
        return traces_of(data["tables"], data["cues"], list(data["cues"]), data["model"], say), data["wall"].adjacency
    raise SystemExit(f"unknown set {name!r}: synthetic, dafne, repair")


def print_table(name, rec, n_links):
    print(f"\n{name}: {n_links} true links (each pair from both sides)")
    print("| stage | in reach | top-1 | top-5 | top-10 | top-12 | top-50 | median rank of the kept |")
    print("|---|---|---|---|---|---|---|---|")
    for stage, label in STAGES:
        r = rec[stage]
        kept = [x for x in rec["ranks"][stage] if x is not None]
        med = f"{np.median(kept) + 1:.0f}" if kept else "—"
        print(f"| {label} | {r['kept']:.3f} | " + " | ".join(f"{r[k]:.3f}" for k in KS) + f" | {med} |")


def plot_stage_recall(result: dict, path) -> None:
    """The tables as a picture: per set, the share of true links in reach and in the top 5 / 12 after each stage."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(result), figsize=(4.2 * len(result), 3.6), dpi=90, squeeze=False)
    short = ["1 prune", "2 patch", "2½ ribbon", "3 dock+paint", "final pooled"]
    for ax, (name, rec) in zip(axes[0], result.items()):
        for key, label, style in (("kept", "in reach", "k-"), ("12", "top 12", "C0o-"), ("5", "top 5", "C3o-"),
                                  ("1", "top 1", "C2o:")):
            # keys are ints in a fresh result and strings once read back from --json
            ys = [rec["table"][s][key] if key in rec["table"][s] else rec["table"][s][int(key)] for s, _ in STAGES]
            ax.plot(range(len(STAGES)), ys, style, label=label)
        ax.axhline(0.8, color="0.6", lw=0.8, ls="--")
        ax.set_xticks(range(len(STAGES)))
        ax.set_xticklabels(short, rotation=30, fontsize=7)
        ax.set_ylim(0, 1.02)
        ax.set_title(f"{name} ({len(rec['links'])} links)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("share of true neighbour links")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Where the true partners are lost (dashed: the 0.8 target)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None):
    from common.matching.evaluation import stage_recall

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="synthetic,dafne,repair")
    ap.add_argument("--cache", help="directory for the prepared sets (pickles)")
    ap.add_argument("--json", help="write the tables and the per-link ranks as JSON")
    ap.add_argument("--png", help="draw the tables (share in reach and in the top 1/5/12 per stage) into this file")
    ap.add_argument("--traces", help="directory: pickle each set's traces and true pairs (<set>.traces.pkl)")
    args = ap.parse_args(argv)
    builders = {"synthetic": build_synthetic, "synthetic-train": build_synthetic, "dafne": build_dafne,
                "repair": build_repair}
    result = {}
    for name in [s.strip() for s in args.sets.split(",") if s.strip()]:
        if name not in builders:
            raise SystemExit(f"unknown set {name!r}: {', '.join(builders)}")
        t0, c0 = time.time(), time.process_time()
        data = _cached(args.cache, name.split("-")[0], builders[name])
        t1, c1 = time.time(), time.process_time()
        traces, adjacency = set_traces(name, data)
        if args.traces:
            Path(args.traces).mkdir(parents=True, exist_ok=True)
            with open(Path(args.traces) / f"{name}.traces.pkl", "wb") as fh:
                pickle.dump((traces, adjacency), fh)
        rec = stage_recall(traces, adjacency, ks=KS)
        print_table(name, rec, len(rec["links"]))
        print(f"{name}: prepare {t1 - t0:.0f} s wall / {c1 - c0:.0f} s CPU, trace {time.time() - t1:.0f} s wall / "
              f"{time.process_time() - c1:.0f} s CPU; load {open('/proc/loadavg').read().split()[:3]}; "
              f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB", flush=True)
        result[name] = {"table": {s: rec[s] for s, _ in STAGES}, "links": rec["links"], "ranks": rec["ranks"]}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=str))
    if args.png and result:
        plot_stage_recall(result, args.png)


if __name__ == "__main__":
    main()
