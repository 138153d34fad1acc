"""What each cue and stage of the station's matcher adds: every stage left out in turn, the rest as the station ranks.

Each variant ranks placed collections exactly as ``tessera evaluate --collection`` does
(:func:`common.matching.report.evaluate_collection`, the station's default bootstrap model, nothing fitted on the
collections), with one part of the matcher switched off:

- ``station``: nothing left out;
- ``no-hubness``: stage 2's patch logit not corrected for the two fragments' hubness (``MatchIndex(use_hubness=False)``);
- ``no-ribbon``: no stage 2½ (the colour ribbon); stage 3 docks stage 2's best;
- ``no-rarity``: the ribbon without its rarity weighting (every colour match counts alike);
- ``no-fresco``: no same-fresco ratio (``fresco.FRESCO_WEIGHT`` 0);
- ``no-docking``: no stage 3 (the poses are the 2-D ribbon matcher's check of the best 3);
- ``no-dock-hubness``: the docking contact not corrected for the two fragments' docking hubness;
- ``no-earlier``: stage 3 ranks by the docking (and paint) alone, without the earlier stages' evidence;
- ``no-paint``: the paint continuity not added to a docked pair's evidence (it still helps choose the pose);
- mutual proximity is the station's order of every variant; each run's order before it (a query's own order, a
  pair's larger probability) is printed beside (``by query``).

Collections: ``--collection DIR`` (repeatable; RePAIR-layout folders, e.g. ../shared/data/repair-dev) and
``--factory P`` (repeatable): a RePAIR-like factory collection of six pompeii walls of 8 pieces sharing palette P,
written once under ``--work`` as ``c{P}`` by ``tessera synth --preset pompeii --fragments 8 --seed 10P+k --dpi 150
--colour-only --palette-seed P --collection DIR`` (k = 1…6), as in docs/matching.md. Each collection's fragments are
imported and their features extracted once (cached under ``--work``), then every variant ranks them in its own
process (``--jobs`` at once). Printed per variant: within-object @1 / @3 hits, pooled top-5 links, pair AP, pose
accuracy and CPU seconds, for each collection and summed over the factory ones; ``--json`` keeps every figure and
``--picture`` draws them.

Run::

    python tests/bench/bench_ablation.py --collection ../shared/data/repair-dev \\
        --factory 10 --factory 11 --factory 12 --factory 13 --factory 18 --factory 19 --factory 20 --factory 21 \\
        --work DIR [--variants station no-paint ...] [--jobs 2] [--json FILE] [--picture FILE]

About 1–1.5 min CPU per collection and variant (a factory collection takes 2–3 min CPU to write, once).
Measured (session 21): docs/matching.md, "What each cue and stage adds, as the station ranks".
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import json
import multiprocessing as mp
import pickle
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

#: issue 15's targets for within-object @1, @3 and pooled top-5 (the dashed lines of the picture)
TARGETS = (0.6, 0.9, 0.8)
VARIANTS = ("station", "no-hubness", "no-ribbon", "no-rarity", "no-fresco", "no-docking", "no-dock-hubness",
            "no-earlier", "no-paint")


@contextlib.contextmanager
def left_out(variant: str):
    """The station's matcher with one part switched off (module state patched for the block)."""
    from common.matching import fresco, index, paint, report

    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; one of {', '.join(VARIANTS)}")
    saved = []

    def patch(obj, name, value):
        saved.append((obj, name, getattr(obj, name)))
        setattr(obj, name, value)

    if variant == "no-hubness":   # the evaluation's index (report._index_of) built without it
        patch(report, "MatchIndex", functools.partial(index.MatchIndex, use_hubness=False))
    elif variant == "no-ribbon":
        patch(index.MatchIndex, "uses_ribbon", lambda self, fragment, model: False)
    elif variant == "no-rarity":
        patch(index, "sample_rarity", lambda *a, **k: None)
    elif variant == "no-fresco":
        patch(fresco, "FRESCO_WEIGHT", 0.0)
    elif variant == "no-docking":
        patch(index.MatchIndex, "uses_docking", lambda self, fragment, model: False)
    elif variant == "no-dock-hubness":
        patch(index, "hub_corrected", lambda contact, *a, **k: np.asarray(contact, float))
    elif variant == "no-earlier":
        patch(index, "DOCK_KEEPS_EARLIER_EVIDENCE", False)
    elif variant == "no-paint":
        with_paint = paint.with_paint
        patch(paint, "with_paint", lambda p, m, slope, weight=None: with_paint(p, m, slope, 0.0))
    try:
        yield
    finally:
        for obj, name, value in reversed(saved):
            setattr(obj, name, value)


def factory_collection(work: Path, palette: int) -> Path:
    """Six pompeii walls of 8 pieces sharing palette ``palette``, written once under ``work``."""
    out = work / f"c{palette}"
    if out.is_dir() and any(out.iterdir()):
        return out
    for k in range(1, 7):
        subprocess.run([sys.executable, "-c", "import sys, services.cli; sys.exit(services.cli.main())", "synth", "--preset", "pompeii", "--fragments", "8",
                        "--seed", str(10 * palette + k), "--dpi", "150", "--colour-only", "--palette-seed",
                        str(palette), "--collection", str(out)], check=True, stdout=subprocess.DEVNULL,
                       cwd=Path(__file__).resolve().parents[2])
    return out


def _cache_path(work: Path, collection: Path) -> Path:
    # named by a digest of the path (Python's str hash changes from run to run: the cache would never be found)
    return work / "cache" / f"{collection.name}-{hashlib.sha1(str(collection.resolve()).encode()).hexdigest()[:8]}.pkl"


def prepare(args) -> str:
    """Import a collection's fragments and extract their features once (the same for every variant)."""
    collection, work, dpi = args
    path = _cache_path(work, collection)
    if path.is_file():
        return f"{collection.name}: cached"
    from common.matching.collection import collection_wall
    from common.matching.online import wall_cues

    t0 = time.process_time()
    wall = collection_wall(collection, dpi=dpi)
    tables, cues, poses = wall_cues(wall)
    wall = replace(wall, fragments=[replace(f, rgbn=None) for f in wall.fragments])   # the images are not needed
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as fh:
        pickle.dump((wall, tables, cues, poses), fh)
    tmp.replace(path)
    return f"{collection.name}: features of {len(tables)} fragments in {time.process_time() - t0:.0f} s CPU"


def _run(args) -> dict:
    """One variant on one collection, in a process of its own (the patches never leak)."""
    variant, collection, work, dpi, model_path = args
    from common.matching import collection as coll, report
    from common.matching.models import MatchModel  # noqa: F401  (the pickle's class)

    with open(_cache_path(work, collection), "rb") as fh:
        wall, tables, cues, poses = pickle.load(fh)
    with open(model_path, "rb") as fh:
        model = pickle.load(fh)
    coll.collection_wall = lambda *a, **k: wall
    report.wall_cues = lambda *a, **k: (tables, cues, poses)
    with left_out(variant):
        index_of, made = report._index_of, []
        report._index_of = lambda *a, **k: made.append(index_of(*a, **k)) or made[-1]   # to count the pairs it docked
        r = report.evaluate_collection(collection, dpi=dpi, model=model)
    n = r["within_object_fragments"]
    return {"variant": variant, "collection": collection.name, "n_queries": n,
            "within_1": round(r["within_object_recall"][1] * n), "within_3": round(r["within_object_recall"][3] * n),
            "within_1_by_query": round(r["within_object_recall_by_query"][1] * n),
            "links": 2 * r["n_true_pairs"],
            "pooled_5": round(r["pooled_topk"][5] * 2 * r["n_true_pairs"]),
            "pooled_5_by_probability": round(r["pooled_topk_by_probability"][5] * 2 * r["n_true_pairs"]),
            "pair_ap": r["pair_ap"], "pose_right": round(r["pose_accuracy"] * r["n_true_pairs"]),
            "pose_offered": round(r["pose_offered"] * r["n_true_pairs"]), "n_pairs": r["n_true_pairs"],
            "cpu_seconds": r["cpu_seconds"], "docked_pairs": len(made[0]._dockings) if made else 0}


def _row(label, rows) -> str:
    q, l, p = (sum(r[k] for r in rows) for k in ("n_queries", "links", "n_pairs"))
    w1, w3, w1q, t5, t5p, pr = (sum(r[k] for r in rows) for k in ("within_1", "within_3", "within_1_by_query",
                                                                  "pooled_5", "pooled_5_by_probability", "pose_right"))
    ap = np.mean([r["pair_ap"] for r in rows])
    cpu = sum(r["cpu_seconds"] for r in rows)
    docked = sum(r.get("docked_pairs", 0) for r in rows)
    return (f"{label:34s} within @1 {w1:3d} ({w1 / q:.3f}) @3 {w3:3d} ({w3 / q:.3f}) of {q:3d} | "
            f"pooled top-5 {t5:4d} ({t5 / l:.3f}) of {l:4d} | AP {ap:.3f} | pose {pr:3d} ({pr / p:.3f}) of {p:3d} | "
            f"by query @1 {w1q / q:.3f}, top-5 {t5p / l:.3f} | {cpu:6.0f} s CPU, {docked} pairs docked")


def draw(results: list[dict], groups: dict, path: Path) -> None:
    """Bars: within-object @1 / @3 and pooled top-5 per variant, for each group of collections."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = [v for v in VARIANTS if any(r["variant"] == v for r in results)]
    figures = (("within_1", "n_queries", "within-object @1"), ("within_3", "n_queries", "within-object @3"),
               ("pooled_5", "links", "pooled top-5"))
    fig, axes = plt.subplots(1, len(groups), figsize=(5.5 * len(groups), 4.2), dpi=90, squeeze=False)
    for ax, (name, members) in zip(axes[0], groups.items()):
        x = np.arange(len(variants))
        for j, (key, total, label) in enumerate(figures):
            vals = []
            for v in variants:
                rows = [r for r in results if r["variant"] == v and r["collection"] in members]
                vals.append(sum(r[key] for r in rows) / max(1, sum(r[total] for r in rows)))
            ax.bar(x + (j - 1) * 0.27, vals, 0.27, label=label)
        for (key, _, _), target, colour in zip(figures, TARGETS, ("C0", "C1", "C2")):
            ax.axhline(target, color=colour, lw=0.8, ls="--")
        ax.set_xticks(x, variants, rotation=40, ha="right", fontsize=8)
        ax.set_ylim(0, 1.05)
        ax.set_title(name, fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle("Each part of the matcher left out in turn, as the station ranks (bootstrap model; dashed: the "
                 "issue's targets)", fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--collection", action="append", default=[], type=Path, help="a placed collection (repeatable)")
    p.add_argument("--factory", action="append", default=[], type=int, help="a factory collection's palette seed")
    p.add_argument("--work", type=Path, help="where factory collections and feature caches are kept (required to run)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--dpi", type=float, default=150.0)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--json", type=Path)
    p.add_argument("--picture", type=Path)
    p.add_argument("--redraw", type=Path, metavar="JSON", help="only draw --picture from an earlier run's --json")
    a = p.parse_args(argv)
    if a.redraw:
        if not a.picture:
            p.error("--redraw needs --picture")
        done = json.loads(a.redraw.read_text())
        draw(done["results"], done["groups"], a.picture)
        return 0
    if a.work is None:
        p.error("--work is required (factory collections and feature caches are kept there)")
    a.work.mkdir(parents=True, exist_ok=True)
    factory = [factory_collection(a.work, pal) for pal in a.factory]
    collections = [c.resolve() for c in a.collection] + factory
    if not collections:
        p.error("give at least one --collection or --factory")
    ctx = mp.get_context("fork")
    with ctx.Pool(a.jobs) as pool:
        for line in pool.imap_unordered(prepare, [(c, a.work, a.dpi) for c in collections]):
            print(line, flush=True)
    from common.matching.online import bootstrap_model

    t0 = time.process_time()
    model_path = a.work / "bootstrap_model.pkl"
    with open(model_path, "wb") as fh:
        pickle.dump(bootstrap_model(), fh)
    print(f"bootstrap model trained in {time.process_time() - t0:.0f} s CPU", flush=True)
    tasks = [(v, c, a.work, a.dpi, model_path) for v in a.variants for c in collections]
    results, t_wall = [], time.time()
    with ctx.Pool(a.jobs, maxtasksperchild=1) as pool:
        for i, r in enumerate(pool.imap_unordered(_run, tasks)):
            results.append(r)
            print(f"[{i + 1}/{len(tasks)}, {time.time() - t_wall:.0f} s] {r['variant']} on {r['collection']}: "
                  f"@1 {r['within_1']}/{r['n_queries']}, top-5 {r['pooled_5']}/{r['links']}, "
                  f"pose {r['pose_right']}/{r['n_pairs']}, {r['cpu_seconds']:.0f} s CPU", flush=True)
    groups = {c.name: [c.name] for c in a.collection}
    if factory:
        groups[f"factory ({len(factory)} collections)"] = [c.name for c in factory]
    for name, members in groups.items():
        print(f"\n{name}")
        for v in a.variants:
            print(_row(v, [r for r in results if r["variant"] == v and r["collection"] in members]))
    if a.json:
        a.json.write_text(json.dumps({"results": results, "groups": groups}, indent=1))
    if a.picture:
        draw(results, groups, a.picture)
    return 0


if __name__ == "__main__":
    sys.exit(main())
