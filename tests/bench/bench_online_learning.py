"""Does the station get better as the conservator gives verdicts? A whole review session, simulated.

The matcher re-fits its patch classifier on every verdict (docs/matching.md, "Models and online learning": the
bootstrap rows plus each verdicted pair's evidence rows at ``verdict_weight``) and ranks every fragment again. This
bench measures what that buys on a placed collection, against the same session with the model left as it was:

- the collection is imported and ranked as ``tessera evaluate --collection`` does (pooled: every fragment against
  every other, the station's default model);
- a simulated conservator works through the review queue in the station's order (docs/web.md: the pending proposals
  — every fragment's best ``--top`` — by mutual proximity, then probability), ``--batch`` proposals at a time, and
  answers truly (confirmed when the two are true neighbours, else rejected);
- after each batch the *learning* session re-fits the model on all verdicts so far
  (:func:`common.matching.online.refit_with_verdicts`, as the matcher) and every fragment is ranked again; the
  *fixed* session keeps the bootstrap model (it only drops the verdicted pairs from the queue).

Printed per batch, for both sessions: verdicts given, true joins confirmed so far (of all true pairs), and the
ranking of what is left — for every fragment with a true neighbour not yet verdicted, whether one is its first /
among its first 5 unverdicted candidates (hit rates). A picture of the confirmed joins against verdicts is written
with ``--picture``.

Run::

    python tests/bench/bench_online_learning.py [--collection ../shared/data/repair-dev] [--dpi 150]
        [--batch 10] [--verdicts 150] [--top 10] [--picture docs/matching/online_learning.png]
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.collection import collection_wall  # noqa: E402
from common.matching.mutual import mutual_pair_scores  # noqa: E402
from common.matching.online import (VERDICT_WEIGHT, bootstrap_model, evidence_dict, refit_with_verdicts,  # noqa: E402
                                    verdict_rows, wall_cues)
from common.matching.report import _index_of  # noqa: E402


def rank_everything(index, ids, model):
    """Every fragment ranked pooled under ``model``: lists of Candidates, best first by the station's order."""
    index.refresh_hubness(ids, model, n_candidates=100)
    ranked = {f: index.rank(index.cues[f], [o for o in ids if o != f], model) for f in ids}
    mutual = mutual_pair_scores({f: [c.other for c in cs] for f, cs in ranked.items()})
    return ranked, mutual


def key(a, b):
    return (a, b) if a < b else (b, a)


def stage3_terms(model, c):
    """A docked candidate's stage terms (patch, ribbon, docking, paint logits) and its same-fresco ratio."""
    t = model.stage_terms([c.patch_logit], [c.ribbon_score], [c.docking_contact_mm], [c.paint_mm])[0]
    return np.append(t, c.fresco_llr)


def fit_adjustment(x, y, offset, *, l2):
    """Logistic regression with an offset: ``σ(offset + x·w + b)``, L2 penalty ``l2`` on w and b (Newton steps).
    The offset is the station's own logit, so no verdicts leave it as it is and few move it little."""
    fill = np.nanmean(np.where(np.isfinite(x), x, np.nan), axis=0)
    fill = np.where(np.isfinite(fill), fill, 0.0)
    x = np.where(np.isfinite(x), x, fill)
    mu, sd = x.mean(axis=0), x.std(axis=0) + 1e-9
    z = np.column_stack([(x - mu) / sd, np.ones(len(x))])
    beta = np.zeros(z.shape[1])
    for _ in range(50):
        p = 1 / (1 + np.exp(-np.clip(offset + z @ beta, -30, 30)))
        g = z.T @ (p - y) + l2 * beta
        h = (z * (p * (1 - p))[:, None]).T @ z + l2 * np.eye(len(beta))
        step = np.linalg.solve(h, g)
        beta -= step
        if np.abs(step).max() < 1e-8:
            break
    return fill, mu, sd, beta


def adjusted(ranked, model, adj):
    """Each fragment's docked head re-ordered by the adjusted logit; the rest after it, as stage 3 orders."""
    fill, mu, sd, beta = adj
    out = {}
    for f, cs in ranked.items():
        head = [c for c in cs if np.isfinite(c.docking_contact_mm)]
        tail = [c for c in cs if not np.isfinite(c.docking_contact_mm)]
        if head:
            x = np.array([stage3_terms(model, c) for c in head])
            x = (np.where(np.isfinite(x), x, fill) - mu) / sd
            p = np.clip([c.probability for c in head], 1e-12, 1 - 1e-12)
            z = np.log(p) - np.log1p(-p) + x @ beta[:-1] + beta[-1]
            head = [c for _, c in sorted(zip(-z, head), key=lambda t: t[0])]
        out[f] = head + tail
    return out


def session(index, ids, truth, model0, *, learn, batch, n_verdicts, top, say, adapt_l2=None):
    """One simulated review session; returns rows (verdicts, confirmed, hit@1, hit@5, n queries).
    ``learn``: re-fit the patch classifier on the verdicts, as the matcher does. ``adapt_l2``: also adjust stage 3's
    order by a logistic fit on the verdicted docked pairs' stage terms, offset by the station's logit."""
    model, verdicts, rows = model0, {}, []
    seen = {}   # verdicted pair -> (stage-3 terms, logit at the verdict, label), docked ones only
    adj = None
    base_x, base_y = model0.training[0], model0.training[1]
    confirmed = 0
    while True:
        t0 = time.process_time()
        ranked, mutual = rank_everything(index, ids, model)
        if adj is not None:
            ranked = adjusted(ranked, model, adj)
            mutual = mutual_pair_scores({f: [c.other for c in cs] for f, cs in ranked.items()})
        # what is left: each fragment's unverdicted candidates in its order by mutual proximity
        hits1 = hits5 = n = 0
        for f, cs in ranked.items():
            left_true = {o for o in truth.get(f, ()) if key(f, o) not in verdicts}
            if not left_true:
                continue
            order = sorted((c for c in cs if key(f, c.other) not in verdicts),
                           key=lambda c: (-mutual.get(key(f, c.other), 0.0), -c.probability))
            firsts = [c.other for c in order[:5]]
            n += 1
            hits1 += bool(firsts[:1] and firsts[0] in left_true)
            hits5 += bool(left_true & set(firsts))
        rows.append((len(verdicts), confirmed, hits1, hits5, n))
        name = "adapting" if adapt_l2 is not None else "learning" if learn else "fixed"
        say(f"{name:8s} verdicts {len(verdicts):4d}  joins confirmed {confirmed:3d}  "
            f"left: @1 {hits1}/{n}  @5 {hits5}/{n}  ({time.process_time() - t0:.1f} s CPU, model {model.version})")
        if len(verdicts) >= n_verdicts:
            return rows
        # the review queue: every fragment's best `top`, pending, by mutual proximity then probability
        queue = {}
        for f, cs in ranked.items():
            for c in cs[:top]:
                k = key(f, c.other)
                if k not in verdicts and (k not in queue or c.probability > queue[k].probability):
                    queue[k] = c
        if not queue:
            return rows
        todo = sorted(queue, key=lambda k: (-mutual.get(k, 0.0), -queue[k].probability))[:batch]
        for k in todo:
            verdict = "confirmed" if k[1] in truth.get(k[0], ()) else "rejected"
            confirmed += verdict == "confirmed"
            verdicts[k] = verdict_rows(evidence_dict(queue[k], model.columns), verdict, model.columns)
            c = queue[k]
            if np.isfinite(c.docking_contact_mm):
                pr = min(max(c.probability, 1e-12), 1 - 1e-12)
                seen[k] = (stage3_terms(model, c), float(np.log(pr / (1 - pr))), verdict == "confirmed")
        if learn:
            model = refit_with_verdicts(base_x, base_y, list(verdicts.values()), previous=model,
                                        verdict_weight=VERDICT_WEIGHT)
        if adapt_l2 is not None and seen:
            x = np.array([v[0] for v in seen.values()])
            y = np.array([v[2] for v in seen.values()], float)
            off = np.array([v[1] for v in seen.values()])
            adj = fit_adjustment(x, y, off, l2=adapt_l2)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--collection", default=str(Path(__file__).resolve().parents[3] / "shared/data/repair-dev"))
    p.add_argument("--dpi", type=float, default=150.0)
    p.add_argument("--batch", type=int, default=10)
    p.add_argument("--verdicts", type=int, default=150)
    p.add_argument("--top", type=int, default=10)
    p.add_argument("--picture", metavar="PNG")
    p.add_argument("--adapt", type=float, nargs="*", default=[], metavar="L2",
                   help="also run sessions that adjust stage 3 from the verdicts, at these L2 penalties")
    args = p.parse_args(argv)

    def say(text):
        print(text, flush=True)

    t0, c0 = time.time(), time.process_time()
    wall = collection_wall(args.collection, dpi=args.dpi)
    model0 = bootstrap_model()
    tables, cues, _ = wall_cues(wall)
    index = _index_of(tables, cues)
    ids = list(index._order)
    truth: dict = {}
    for a, b, *_ in wall.adjacency:
        truth.setdefault(a, set()).add(b)
        truth.setdefault(b, set()).add(a)
    say(f"{args.collection}: {len(ids)} fragments, {len(wall.adjacency)} true pairs, model {model0.version}")
    rank_everything(index, ids, model0)   # the dockings made once; each session starts from this index's copy
    results = {learn: session(copy.deepcopy(index), ids, truth, model0, learn=learn, batch=args.batch,
                              n_verdicts=args.verdicts, top=args.top, say=say)
               for learn in (False, True)}
    for l2 in args.adapt:
        results[f"adapt {l2:g}"] = session(copy.deepcopy(index), ids, truth, model0, learn=True, batch=args.batch,
                                           n_verdicts=args.verdicts, top=args.top, say=say, adapt_l2=l2)
    for name, rows in results.items():
        if isinstance(name, str):
            say(f"{name}: joins confirmed " + " ".join(f"{r[1]}@{r[0]}" for r in rows))
    say(f"\n| verdicts | joins confirmed, fixed / learning | left @1, fixed / learning | left @5, fixed / learning |")
    say("|---|---|---|---|")
    for (v, cf, h1f, h5f, nf), (_, cl, h1l, h5l, nl) in zip(results[False], results[True]):
        say(f"| {v} | {cf} / {cl} of {len(wall.adjacency)} | {h1f}/{nf} / {h1l}/{nl} | {h5f}/{nf} / {h5l}/{nl} |")
    say(f"{time.time() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU")
    if args.picture:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.5, 3.8), dpi=120)
        labels = {False: "bootstrap model kept", True: "patch classifier re-fitted on verdicts (the station)"}
        for name, rows in results.items():
            r = np.array(rows, float)
            ax.plot(r[:, 0], r[:, 1], "--" if name is False else "-", marker="o", ms=3,
                    label=labels[name] if isinstance(name, bool) else f"and stage 3 adjusted ({name.replace('adapt', 'L2')})")
        ax.set_xlabel("verdicts given (review queue order)")
        ax.set_ylabel(f"true joins confirmed (of {len(wall.adjacency)})")
        ax.set_title(Path(args.collection).name, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(args.picture)
        say(f"picture: {args.picture}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
