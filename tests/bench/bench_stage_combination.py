"""Stage 3's combination of the stage scores, re-ranked offline on traced candidates (issue 15).

Reads what ``bench_stage_recall.py --cache DIR --traces DIR --sets synthetic-train,synthetic,dafne,repair``
kept (the prepared sets' models and every query's traced candidates with their stage scores), fits
the learned combination on the synthetic *training* wall's docked candidates (as
:func:`common.matching.online.stage_combination` does, one row per docked candidate, four terms from
:meth:`~common.matching.models.MatchModel.stage_terms`), re-scores the docked 12 of every test query
with it (the rest stay below them, as in ``_rank_by_docking``) and prints pooled top-1 / 5 / 10 for
subsets of the terms, beside the fixed rules' figures of the traces themselves:

    python tests/bench/bench_stage_combination.py --cache DIR --traces DIR
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.evaluation import top_k_recall  # noqa: E402

TERMS = ("patch", "ribbon", "docking", "paint")


def terms(model, ev):
    return model.stage_terms([ev["patch_logit"]], [ev["ribbon"]], [ev["contact_mm"]], [ev["paint_mm"]])[0]


def fit(traces, adjacency, model_of, cols, head=12):
    """Logistic regression on the docked candidates' terms ``cols`` (others weighted 0), as stage_combination."""
    from sklearn.linear_model import LogisticRegression

    truth: dict = {}
    for a, b, *_ in adjacency:
        truth.setdefault(a, set()).add(b)
        truth.setdefault(b, set()).add(a)
    x, y = [], []
    for i, t in enumerate(traces):
        for o in t.order["ribbon"][:head]:
            x.append(terms(model_of(i), t.evidence[o]))
            y.append(o in truth.get(t.fragment, ()))
    x = np.array(x)
    fill = np.nanmean(np.where(np.isfinite(x), x, np.nan), axis=0)
    fill = np.where(np.isfinite(fill), fill, 0.0)
    lr = LogisticRegression(max_iter=1000).fit(np.where(np.isfinite(x), x, fill)[:, list(cols)], np.array(y))
    w = np.zeros(len(TERMS))
    w[list(cols)] = lr.coef_[0]
    return w, float(lr.intercept_[0]), fill


def pooled(traces, model_of, combo=None, head=12):
    """Pooled scores (larger side) with the docked ``head`` re-scored by ``combo``; None: the traced ones."""
    out: dict = {}
    for i, t in enumerate(traces):
        probs = dict(t.probability)
        if combo is not None:
            w, b, fill = combo
            m = model_of(i)
            probs = {}
            for o in t.order["ribbon"][:head]:
                x = terms(m, t.evidence[o])
                probs[o] = float(1 / (1 + np.exp(-(np.where(np.isfinite(x), x, fill) @ w + b))))
            floor = min(probs.values()) if probs else 1.0
            rs, rb = m.ribbon
            for o in t.order["ribbon"][head:]:
                r = t.evidence[o]["ribbon"]
                p = 1 / (1 + np.exp(-(rs * r + rb))) if np.isfinite(r) else t.probability.get(o, 0.0)
                probs[o] = min(float(p), floor)
        for o, p in probs.items():
            key = tuple(sorted((t.fragment, o)))
            out[key] = max(out.get(key, 0.0), p)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", required=True, help="bench_stage_recall.py's --cache directory")
    ap.add_argument("--traces", required=True, help="bench_stage_recall.py's --traces directory")
    args = ap.parse_args(argv)
    t0, c0 = time.time(), time.process_time()

    def load(path):
        with open(path, "rb") as fh:
            return pickle.load(fh)

    synth = load(Path(args.cache) / "synthetic.pkl")
    train, adj_train = load(Path(args.traces) / "synthetic-train.traces.pkl")
    sets = {"synthetic": (*load(Path(args.traces) / "synthetic.traces.pkl"), lambda i: synth["model"])}
    if (Path(args.traces) / "dafne.traces.pkl").exists():
        d = load(Path(args.cache) / "dafne.pkl")
        n0 = len(d["halves"][1] | d["spurious"])   # the first half's run ranks halves[1] and the spurious ones
        sets["DAFNE"] = (*load(Path(args.traces) / "dafne.traces.pkl"),
                         lambda i: d["models"][0] if i < n0 else d["models"][1])
    if (Path(args.traces) / "repair.traces.pkl").exists():
        r = load(Path(args.cache) / "repair.pkl")
        sets["RePAIR"] = (*load(Path(args.traces) / "repair.traces.pkl"), lambda i: r["model"])
    print("| stage 3 of the docked 12 | " + " | ".join(sets) + " |")
    print("|---|" + "---|" * len(sets))

    def row(label, combo):
        cells = []
        for traces, adj, model_of in sets.values():
            rec = top_k_recall(pooled(traces, model_of, combo), adj, (1, 5, 10))
            cells.append(f"{rec[1]:.3f} / **{rec[5]:.3f}** / {rec[10]:.3f}")
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)

    row("fixed rules (the traces' own)", None)
    for cols in ((0, 1, 2, 3), (1, 2, 3), (0, 1, 2), (0, 1), (1, 3), (1,)):
        combo = fit(train, adj_train, lambda i: synth["model"], cols)
        row("learned: " + " + ".join(TERMS[c] for c in cols) + " (w " + ", ".join(f"{v:.2f}" for v in combo[0]) + ")",
            combo)
    print(f"{time.time() - t0:.0f} s wall / {time.process_time() - c0:.0f} s CPU; "
          f"load {open('/proc/loadavg').read().split()[:3]}")


if __name__ == "__main__":
    main()
