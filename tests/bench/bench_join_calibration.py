"""Stage 3's join probability recalibrated: fit ``index.JOIN_CALIBRATION`` and check it (issue 15, session 17).

    python tests/bench/bench_join_calibration.py [--train 10-13] [--test 18-21]
                                                 [--collection ../shared/data/repair-dev] [--work DIR] [--first]

Stage 3 adds its evidence as independent log odds, so its probability saturates: almost every proposal of a real
import read 99–100 %. This bench writes factory collections in RePAIR's layout (``tessera synth --preset pompeii
--fragments 8 --colour-only --palette-seed P --seed 10P+k --collection``, six walls per palette; the same as the
session-15 collections), ranks every fragment against its collection as the matcher proposes (stage 1's 100
candidates, stages 2–3, the docked best 12) with the recalibration switched off, fits Platt's scaling of the logit on
the training palettes' docked candidates (true join or not) and prints the constants and the reliability — predicted
against observed share of joins, log-loss, Brier score — before and after, on the test palettes and on a real
collection (never fitted on). About 90 s CPU per collection. ``--first`` does the same for the matcher's first answer
(every fragment's top 10 from stages 1–2½, before its docking job): ``index.FIRST_CALIBRATION``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import common.matching.index as index_module  # noqa: E402
from tests.bench.bench_pose import seeds  # noqa: E402


def collection(palette: int, work: Path) -> Path:
    """The six-wall collection of one palette, written once under ``work``."""
    from services.cli import main

    out = work / f"c{palette}"
    if not out.is_dir():
        for k in range(1, 7):
            main(["synth", "--preset", "pompeii", "--fragments", "8", "--seed", str(10 * palette + k), "--dpi", "150",
                  "--colour-only", "--palette-seed", str(palette), "--collection", str(out)])
    return out


def docked_candidates(path: Path, *, first: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(raw probability, true join) of every fragment's docked best, as the matcher proposes them; ``first``: of
    every fragment's top 10 as the matcher's first answer gives them (stages 1–2½, before the docking job)."""
    from common.matching.collection import collection_wall
    from common.matching.online import bootstrap_model, wall_cues
    from common.matching.report import _index_of

    wall = collection_wall(path, dpi=150)
    model = bootstrap_model()
    tables, cues, _ = wall_cues(wall)
    index = _index_of(tables, cues)
    ids = list(index._order)
    index.refresh_hubness(ids, model, n_candidates=100)
    truth: dict = {}
    for a, b, *_ in wall.adjacency:
        truth.setdefault(a, set()).add(b)
        truth.setdefault(b, set()).add(a)
    p, y = [], []
    for f in ids:
        if first:
            found = index.rank(index.cues[f], index.candidates(index.cues[f], model, 100), model, dock_candidates=0)
            kept = [c for c in found[:10] if np.isfinite(c.probability)]
        else:
            kept = [c for c in index.rank(index.cues[f], index.candidates(index.cues[f], model, 100), model)
                    if c.docking is not None]
        for c in kept:
            p.append(c.probability)
            y.append(c.other in truth.get(f, ()))
    return np.array(p), np.array(y, int)


def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-15, 1 - 1e-15)
    return np.log(p) - np.log1p(-p)


def reliability(name: str, p: np.ndarray, y: np.ndarray, slope: float, intercept: float) -> None:
    q = 1 / (1 + np.exp(-(slope * logit(p) + intercept)))

    def loss(v):
        v = np.clip(v, 1e-12, 1 - 1e-12)
        return float(-np.mean(y * np.log(v) + (1 - y) * np.log(1 - v)))

    print(f"{name}: {len(y)} candidates, {y.sum()} true joins ({y.mean():.3f}); mean probability "
          f"{p.mean():.3f} -> {q.mean():.3f}; log-loss {loss(p):.3f} -> {loss(q):.3f}; "
          f"Brier {np.mean((p - y) ** 2):.3f} -> {np.mean((q - y) ** 2):.3f}")
    for lo, hi in ((0, 0.9), (0.9, 0.99), (0.99, 0.999), (0.999, 1.01)):
        m = (p >= lo) & (p < hi)
        if m.any():
            print(f"   before [{lo:g}, {hi:g}): {m.sum():4d}, joins {y[m].mean():.3f}")
    for lo, hi in ((0, 0.05), (0.05, 0.1), (0.1, 0.2), (0.2, 0.4), (0.4, 0.7), (0.7, 1.01)):
        m = (q >= lo) & (q < hi)
        if m.any():
            print(f"   after  [{lo:g}, {hi:g}): {m.sum():4d}, predicted {q[m].mean():.3f}, joins {y[m].mean():.3f}")


def main(argv=None) -> int:
    from sklearn.linear_model import LogisticRegression

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--train", default="10-13", help="palettes fitted on (default 10-13)")
    ap.add_argument("--test", default="18-21", help="palettes checked on (default 18-21)")
    ap.add_argument("--collection", default="../shared/data/repair-dev", help="a real collection, checked on")
    ap.add_argument("--work", default="", help="folder for the collections (default: a temporary one)")
    ap.add_argument("--first", action="store_true",
                    help="fit FIRST_CALIBRATION: the first answer's top 10 (stages 1-2.5), not the docked best")
    args = ap.parse_args(argv)
    index_module.JOIN_CALIBRATION = {"slope": 1.0, "intercept": 0.0}   # the raw probability
    with tempfile.TemporaryDirectory(prefix="tessera-calibration-") as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        sets = {}
        for name, spec in (("train", args.train), ("test", args.test)):
            got = [docked_candidates(collection(pal, work), first=args.first) for pal in seeds(spec)]
            sets[name] = (np.concatenate([g[0] for g in got]), np.concatenate([g[1] for g in got]))
        if args.collection and Path(args.collection).is_dir():
            sets[args.collection] = docked_candidates(Path(args.collection), first=args.first)
    p, y = sets["train"]
    fit = LogisticRegression(C=1e6).fit(logit(p)[:, None], y)
    slope, intercept = float(fit.coef_[0, 0]), float(fit.intercept_[0])
    print(f'{"FIRST" if args.first else "JOIN"}_CALIBRATION = {{"slope": {slope:.4f}, "intercept": {intercept:.4f}}}   '
          f"(palettes {args.train}: {len(y)} candidates, {y.sum()} joins)")
    for name, (p, y) in sets.items():
        reliability(name, p, y, slope, intercept)
    return 0


if __name__ == "__main__":
    sys.exit(main())
