"""Scale benchmark of the staged matcher (thesis §5.2.1).

    python tests/bench/bench_matching.py [--sizes 250,500,1000,2000] [--repeats 20]
    python tests/bench/bench_matching.py --pool ../shared/data/repair-dev --sizes 2000 --repeats 5 [--hubness pool]

A model is trained on a small synthetic wall (60 fragments); the index is then filled with n
synthetic feature tables (allowed for the scale test): each is a real fragment's cues from a pool
of synthetic walls with its values jittered, so patch counts, value ranges and contours are
realistic. For each n it prints

* the time to propose joins for one new fragment (stage 1 prune + stage 2 rank + stage 2½ colour
  ribbon on the best 50, the ``features.ready`` path without the alignment check), and separately
  the alignment check of its best 3;
* the full re-rank after a model update: every fragment's ranking recomputed under a new model
  (:meth:`~common.matching.index.MatchIndex.rank_all`) and the re-scoring of the stored proposals (10 per
  fragment);
* peak resident memory of the process;

targets: ≤ 100 ms per new fragment, ≤ 10 min full re-rank, ≤ 4 GB at n = 2000.

``--pool DIR`` fills the index from a real placed collection instead (RePAIR's fragments: 75–115
patches each, outlines 10–20 cm) and gives the model the docking calibration of the bootstrap
model, so the proposal time includes stage 3 (docking the best ``--dock-candidates``, default
:data:`~common.matching.index.DOCK_CANDIDATES`, with their paint continuity) at real sizes. It prints
the docking cost per pair (one search of 30 candidate poses, the query's frame kept, as stage 3 does),
and beside each proposal's CPU the CPU of the matcher's first answer (stages 1–2½,
``propose(..., dock=False)``: what ``features.ready`` returns before its ``match.ranked`` job docks),
so stage 3's share is the difference; with ``--full-rerank-max`` every fragment is first proposed and
docked once (the arrivals), then re-ranked under a new model (the dockings cached); the alignment check is not
run (stage 3's docked pose is the alignment). The queries' ids sort after the index's, so each query
is the turned fragment of its dockings (its frame serves all its partners), as a new fragment is at
the station. The re-rank is the station's (:meth:`~common.matching.index.MatchIndex.rank_all`: every
fragment ranked with the dockings made before), and the pairs that entered a best ``--dock-candidates``
without a docking are docked after it, as their own jobs (each such fragment proposed again), timed
apart. At sizes where that would take hours, ``--rerank-sample K`` estimates both instead: every
fragment's hubness under the new model (measured whole) plus n × the mean of K sampled fragments, each
proposed and docked under the old model first, then ranked again under the new one (the re-rank), then
proposed under it (the follow-up where it has new pairs; the earlier estimate, printed beside it, took
this proposal as each fragment's whole re-rank). The "re-score s" column (a verdict's re-score of the
pending proposals, ``online.rerank``) is then every fragment's hubness under the model (measured whole)
plus the sample's stored pairs re-scored, times n / K.

    python tests/bench/bench_matching.py --pool ../shared/data/repair-dev --sizes 2000 --repeats 10 \
        --full-rerank-max 0 --rerank-sample 40 --hubness pool

``--kept-dockings K`` (with ``--pool``): K sampled fragments are proposed by an index that keeps its dockings in a
proposal store (a temporary SQLite file, as the matcher service does), then the best pairs they docked are
asked of a fresh index over that store (a restarted worker: read, not docked) and of a fresh index without it
(docked again, stage 3's way: each fragment's partners in one batch, its frame kept); it prints the CPU per
pair of each, and the store's bytes per docked pair (its file, and the rows' own payload).

    python tests/bench/bench_matching.py --pool ../shared/data/repair-dev --sizes 250 --repeats 3 \
        --full-rerank-max 0 --hubness pool --kept-dockings 20
"""

from __future__ import annotations

import argparse
import copy
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.index import DOCK_CANDIDATES, MatchIndex  # noqa: E402
from common.matching.online import ribbon_calibration, rerank, train_model, wall_cues  # noqa: E402
from common.matching.pairs import FragmentCues, training_set  # noqa: E402
from common.synth.wall import generate_wall  # noqa: E402


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def jittered(c: FragmentCues, fid: str, rng) -> FragmentCues:
    """A new fragment's cues: a real fragment's, with every value moved by 10 % of its size."""
    v = c.values * (1 + 0.1 * rng.standard_normal(c.values.shape))
    p = c.patches * (1 + 0.1 * rng.standard_normal(c.patches.shape))
    return FragmentCues(fid, v, p, c.arc_mm.copy(), c.points_mm.copy(), c.normals.copy(),
                        [s + 0.1 * rng.standard_normal(s.shape) for s in c.strips], c.patch_index)


def measure_kept_dockings(index: MatchIndex, model, k: int, docked: int, rng) -> None:
    """``--kept-dockings``: reading a pair's kept docking against docking it, and the store's size per pair."""
    import os
    import sqlite3
    import tempfile

    from common.matching.index import _pair
    from common.matching.proposals import ProposalStore

    def fresh(dockings):
        other = MatchIndex(dockings=dockings)
        for f in index._order:
            other.add(index.cues[f], index.contours.get(f), index._raw_profiles.get(f))
        return other

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "proposals.sqlite"
        empty = ProposalStore(path)
        base = os.path.getsize(path)
        writer = fresh(empty)
        sample = [str(f) for f in rng.choice(writer._order, k, replace=False)]
        t, tc = time.perf_counter(), time.process_time()
        for f in sample:   # the arrivals' docked answers, writing each pair's docking to the store
            writer.propose(writer.cues[f], model, n_candidates=100, top=10, check=0, dock_candidates=docked)
        print(f"kept dockings: {len(sample)} fragments proposed with their dockings written to the store: "
              f"{time.perf_counter() - t:.1f} s wall, {time.process_time() - tc:.1f} s CPU; "
              f"{empty.count_dockings()} pairs kept")
        # the same fragments' docked pairs, asked of a restarted worker (read) and of one without the store (docked)
        partners = {f: [o for o in writer.rankings[f][:docked] if _pair(f, o) in writer._dockings] for f in sample}
        n_pairs = len({_pair(f, o) for f, os_ in partners.items() for o in os_})
        timings = {}
        for name, other in (("read", fresh(ProposalStore(path))), ("docked", fresh(None))):
            t, tc = time.perf_counter(), time.process_time()
            for f, os_ in partners.items():
                other._dock_pairs(f, os_)
            timings[name] = (time.perf_counter() - t, time.process_time() - tc, len(other._dockings))
            for f, os_ in partners.items():   # the same numbers either way
                assert all(other.pose(f, o) == writer.pose(f, o) for o in os_)
        for name, (wall_s, cpu_s, n) in timings.items():
            print(f"kept dockings: {n_pairs} pairs {name} by a fresh index: {1e3 * wall_s / n_pairs:.2f} ms wall, "
                  f"{1e3 * cpu_s / n_pairs:.2f} ms CPU per pair")
        # writing: each pair's row stored again (one transaction each, as _dock_pair does; synchronous=FULL)
        from common.matching.index import docking_version

        kept = [empty.docking(*key, writer._inputs[key[0]], writer._inputs[key[1]], docking_version())
                for key in writer._dockings]
        t, tc = time.perf_counter(), time.process_time()
        for rec in kept:
            empty.put_docking(rec)
        print(f"kept dockings: {len(kept)} pairs written: {1e3 * (time.perf_counter() - t) / len(kept):.2f} ms wall, "
              f"{1e3 * (time.process_time() - tc) / len(kept):.2f} ms CPU per pair (storage: {path.parent})")
        empty._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        rows = empty.count_dockings()
        db = sqlite3.connect(path)
        payload = db.execute("SELECT SUM(length(fragment_a) + length(fragment_b) + length(inputs_a) + length(inputs_b)"
                             " + length(docking_version) + 8 * 9 + 1 + length(pose) + length(alternatives))"
                             " FROM dockings").fetchone()[0]
        db.close()
        print(f"kept dockings: store {os.path.getsize(path) - base} bytes for {rows} pairs = "
              f"{(os.path.getsize(path) - base) / rows:.0f} bytes per pair in the file "
              f"({payload / rows:.0f} bytes of row payload: names, digests, version, numbers, JSON poses)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="250,500,1000,2000")
    ap.add_argument("--repeats", type=int, default=20, help="new fragments timed per size")
    ap.add_argument("--full-rerank-max", type=int, default=2000, help="largest n where the full re-rank is run")
    ap.add_argument("--pool", help="a placed collection (repair-dev layout) whose real fragments fill the index; "
                                   "proposals then include the docking (stage 3)")
    ap.add_argument("--dpi", type=float, default=150.0, help="nominal dpi of --pool's images (default 150)")
    ap.add_argument("--hubness", choices=("all", "pool"), default="all",
                    help="the steady state's hubness: every indexed fragment's own (all: one stage-2 pass each, "
                         "~0.1-0.3 s CPU at real sizes) or, with --pool, each copied from its pool fragment's first "
                         "copy (pool: one pass per pool fragment; for large n on a busy machine)")
    ap.add_argument("--dock-candidates", type=int, default=DOCK_CANDIDATES,
                    help=f"with --pool: candidates docked per proposal (default {DOCK_CANDIDATES})")
    ap.add_argument("--kept-dockings", type=int, default=0,
                    help="with --pool: fragments proposed with their dockings kept in a proposal store, then read "
                         "by a fresh index against docked by one without the store (module docstring)")
    ap.add_argument("--rerank-sample", type=int, default=0,
                    help="with --pool, at sizes above --full-rerank-max: estimate the full re-rank from this many "
                         "fragments (each proposed and docked on arrival, then re-ranked under the new model) plus "
                         "every fragment's hubness under the new model")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    docked = args.dock_candidates
    rng = np.random.default_rng(0)

    t = time.perf_counter()
    wall = generate_wall(60, seed=0, dpi=100)
    tables, cues, poses = wall_cues(wall)
    model, _ = train_model(training_set(cues, poses, wall.adjacency), ribbon=ribbon_calibration(tables, wall.adjacency))
    model2 = copy.deepcopy(model)
    model2.coef = model.coef * (1 + 0.05 * rng.standard_normal(model.coef.shape))
    model2.version = "0002-bench"
    pool = [(cues[f], tables[f].contour_mm, tables[f].boundary_profile) for f in cues if len(cues[f]) >= 3]
    if args.pool:
        from common.matching.collection import collection_wall
        from common.matching.docking import DockingFrame, dock_frames
        from common.matching.index import DOCK_MORE_POSES, DOCK_PAINT_PER_ANGLE, DOCK_PAINT_POSES
        from common.matching.online import docking_calibration

        real = generate_wall(16, seed=1, dpi=40.0, preset="pompeii", colour_only=True)
        model.docking = model2.docking = docking_calibration(real, negatives_per_positive=2.0)
        rw = collection_wall(args.pool, dpi=args.dpi)
        rtables, rcues, _ = wall_cues(rw)
        pool = [(rcues[f], rtables[f].contour_mm, rtables[f].boundary_profile) for f in rcues if len(rcues[f]) >= 3]
        query = DockingFrame(pool[0][1])
        pairs = [pool[i][1] for i in rng.integers(len(pool), size=12)]
        tc = time.process_time()
        for a in pairs:
            dock_frames(DockingFrame(a), query, n_poses=DOCK_PAINT_POSES, per_angle=DOCK_PAINT_PER_ANGLE,
                        more_poses=DOCK_MORE_POSES)
        print(f"docking one pair of real fragments ({DOCK_PAINT_POSES} + {DOCK_MORE_POSES} poses, as stage 3; "
              f"the query's frame kept): "
              f"{1e3 * (time.process_time() - tc) / len(pairs):.0f} ms CPU; {args.dock_candidates} docked per proposal")
    print(f"model trained on {wall.id} in {time.perf_counter() - t:.1f} s; pool of {len(pool)} fragments; "
          f"median {int(np.median([len(p[0]) for p in pool]))} patches, "
          f"{int(np.median([len(p[2]) for p in pool]))} boundary samples per fragment")
    print("wall-clock times on a shared machine; 'cpu' columns are this process's CPU time")
    print(f"{'n':>6s} {'build s':>8s} {'propose ms med/p90':>21s} {'cpu ms':>8s} {'align3 ms':>10s} "
          f"{'full re-rank s/cpu s':>19s} {'re-score s':>10s} {'peak RSS MB':>12s}"
          + (f" {'first answer cpu ms':>19s} {'frames MB':>9s}" if args.pool else ""))
    index = MatchIndex()
    n_done = 0
    source = {}   # indexed fragment -> its pool fragment
    for n in sizes:
        t = time.perf_counter()
        while n_done < n:
            i = int(rng.integers(len(pool)))
            c, contour, profile = pool[i]
            index.add(jittered(c, f"F{n_done:05d}", rng), contour, profile + 0.02 * rng.standard_normal(profile.shape))
            source[f"F{n_done:05d}"] = i
            n_done += 1
        index._ensure()
        build = time.perf_counter() - t
        # steady state of the service: every indexed fragment was proposed on arrival, so it has
        # its hubness (index.py); a fresh worker gets it lazily, once per fragment and model
        t = time.perf_counter()
        if args.hubness == "pool":
            # each pool fragment's first copy gets its own; the other copies (jittered by 10 %) take it
            first = {}
            for f, i in source.items():
                first.setdefault(i, f)
            index.refresh_hubness(list(first.values()), model)
            for f, i in source.items():
                index.hubness.setdefault(f, index.hubness[first[i]])
        else:
            index.refresh_hubness(index._order, model)
        hub_s = time.perf_counter() - t
        # one new fragment at a time: add, propose (stage 1 + 2), then remove it again
        times, cpu, align_times, cpu_plain, cpu_mutual = [], [], [], [], []
        for r in range(args.repeats):
            c, contour, profile = pool[rng.integers(len(pool))]
            q = jittered(c, f"Q{n}-{r}", rng)
            t, tc = time.perf_counter(), time.process_time()
            index.add(q, contour, profile + 0.02 * rng.standard_normal(profile.shape))
            found = index.propose(q, model, n_candidates=100, top=10, check=0, dock_candidates=docked)
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - tc)
            # the matcher's docked answer then ranks the best partners again for mutual proximity
            # (services/matcher.py, _rank_partners_again: those whose ranking predates the new fragment)
            tc = time.process_time()
            index.rank_again([c.other for c in found], model, knowing=q.fragment)
            cpu_mutual.append(time.process_time() - tc)
            if args.pool:
                # the matcher's first answer (services/matcher.py): stages 1–2½, docking left to its own job
                tc = time.process_time()
                index.propose(q, model, n_candidates=100, top=10, check=0, dock=False)
                cpu_plain.append(time.process_time() - tc)
                align_times.append(np.nan)
            else:
                t = time.perf_counter()
                index.propose(q, model, n_candidates=100, top=10, check=3)
                align_times.append(time.perf_counter() - t - times[-1])
            index.remove(q.fragment)
        # full re-rank after a model update: re-propose for every fragment under model2
        full = full_cpu = np.nan
        stored_pairs, rescore_scale = [], 1.0
        if n <= args.full_rerank_max:
            if args.pool:
                # steady state: every fragment was proposed (and its best candidates docked) on arrival;
                # dockings do not depend on the model, so the re-rank docks only pairs new to a best 12
                t, tc = time.perf_counter(), time.process_time()
                for f in list(index._order):
                    index.propose(index.cues[f], model, n_candidates=100, top=10, check=0, dock_candidates=docked)
                print(f"every fragment proposed and docked once (arrivals): {time.perf_counter() - t:.0f} s wall, "
                      f"{time.process_time() - tc:.0f} s CPU")
            # the station's full re-rank (MatchIndex.rank_all): every hubness under the new model, every
            # fragment ranked with the dockings made before; the pairs new to a best 12 follow as their own
            # jobs (each such fragment proposed again, which docks them), timed apart
            t, tc = time.perf_counter(), time.process_time()
            undocked = index.rank_all(model2, n_candidates=100, dock_candidates=docked)
            full, full_cpu = time.perf_counter() - t, time.process_time() - tc
            stored_pairs = [(f, o) for f in index._order for o in index.rankings.get(f, [])[:10]]
            t, tc = time.perf_counter(), time.process_time()
            for f in undocked:
                index.propose(index.cues[f], model2, n_candidates=100, top=10, check=0, dock_candidates=docked)
            if undocked:
                print(f"follow-up dockings at n = {n}: {len(undocked)} fragments with "
                      f"{len({tuple(sorted((f, o))) for f, new in undocked.items() for o in new})} pairs new to a best "
                      f"{docked}, proposed again: {time.perf_counter() - t:.0f} s wall, {time.process_time() - tc:.0f} s CPU")
        elif args.pool and args.rerank_sample:
            # the re-rank is one pass per fragment: its hubness under the new model (once each), then its
            # ranking with the dockings made before (MatchIndex.rank_all); the pairs new to its best 12
            # follow as their own jobs. Every fragment's hubness is measured whole; the rest on a sample,
            # as its mean times n
            sample = [str(f) for f in rng.choice(index._order, args.rerank_sample, replace=False)]
            # every fragment's own hubness under the old model too (not its pool fragment's copy), so the
            # two models' best 12 differ only by the model change, as at a station
            index.hubness.clear()
            index.refresh_hubness(index._order, model)
            for f in sample:   # arrivals: proposed and docked under the old model
                index.propose(index.cues[f], model, n_candidates=100, top=10, check=0, dock_candidates=docked)
            tc = time.process_time()
            index.refresh_hubness(index._order, model2)
            hub2 = time.process_time() - tc
            ranked, proposed, new_pairs, follow = [], [], [], []
            for f in sample:
                # the re-rank proper (MatchIndex.rank_all's pass for one fragment): no new docking
                undocked = {}
                tc = time.process_time()
                index.rank_again([f], model2, n_candidates=100, dock_candidates=docked, undocked=undocked)
                ranked.append(time.process_time() - tc)
                new_pairs.append(len(undocked.get(f, [])))
                # then the fragment proposed under the new model, which docks those pairs: the earlier
                # estimate's whole re-rank of one fragment, and the follow-up job of a fragment with new pairs
                tc = time.process_time()
                index.propose(index.cues[f], model2, n_candidates=100, top=10, check=0, dock_candidates=docked)
                proposed.append(time.process_time() - tc)
                follow.append(proposed[-1] if f in undocked else 0.0)
            old_cpu = hub2 + n * float(np.mean(proposed))
            print(f"full re-rank at n = {n}, earlier estimate (every fragment re-proposed, docking pairs new to its "
                  f"best {docked}): hubness of all {n} under the new model {hub2:.0f} s CPU + {n} × "
                  f"{1e3 * np.mean(proposed):.0f} ms CPU per proposal (mean of {len(proposed)}; median "
                  f"{1e3 * np.median(proposed):.0f}, max {1e3 * np.max(proposed):.0f}) = {old_cpu:.0f} s CPU "
                  f"({old_cpu / 60:.1f} min)")
            full_cpu = hub2 + n * float(np.mean(ranked))
            print(f"full re-rank at n = {n}, estimated (MatchIndex.rank_all: the dockings made before, no new "
                  f"docking): {hub2:.0f} s CPU + {n} × {1e3 * np.mean(ranked):.0f} ms CPU per fragment (median "
                  f"{1e3 * np.median(ranked):.0f}, max {1e3 * np.max(ranked):.0f}) = {full_cpu:.0f} s CPU "
                  f"({full_cpu / 60:.1f} min)")
            # a verdict's re-score of the pending proposals, on the sample's stored pairs, times n / sample
            stored_pairs = [(f, o) for f in sample for o in index.rankings.get(f, [])[:10]]
            rescore_scale = n / len(sample)
            with_new = int(np.count_nonzero(new_pairs))
            print(f"follow-up dockings, estimated: {with_new} of {len(sample)} sampled fragments had pairs new to "
                  f"their best {docked} ({sum(new_pairs)} pairs, at most {max(new_pairs)} each), i.e. ≈ "
                  f"{n * with_new / len(sample):.0f} follow-up jobs docking ≈ {n * np.mean(new_pairs):.0f} pairs "
                  f"(a pair new to both fragments' best counted twice, docked once) at n = {n}; each job "
                  f"{1e3 * np.mean([x for x in follow if x]) if with_new else 0:.0f} ms CPU (mean), "
                  f"{n * np.mean(follow):.0f} s CPU in all ({n * np.mean(follow) / 60:.1f} min)")
        if args.pool and args.kept_dockings:
            measure_kept_dockings(index, model, args.kept_dockings, docked, rng)
        hub_wall = hub_cpu = 0.0
        if rescore_scale != 1:
            # a verdict's model: every fragment's hubness under it (measured whole, as each pending
            # proposal's partners are most of the fragments), then the sample's pairs ranked, times n / K
            index.hubness.clear()
            t, tc = time.perf_counter(), time.process_time()
            index.refresh_hubness(index._order, model)
            hub_wall, hub_cpu = time.perf_counter() - t, time.process_time() - tc
        t, tc = time.perf_counter(), time.process_time()
        rerank(index, model, stored_pairs)
        rescore = hub_wall + (time.perf_counter() - t) * rescore_scale
        rescore_cpu = hub_cpu + (time.process_time() - tc) * rescore_scale
        print(f"a verdict's re-score of the pending proposals at n = {n}: {rescore:.1f} s wall, {rescore_cpu:.1f} s CPU"
              + (f" (every hubness {hub_cpu:.0f} s CPU + the {len(stored_pairs)} stored pairs of the sampled fragments"
                 f" re-scored, times {rescore_scale:.0f})" if rescore_scale != 1 else ""))
        print(f"hubness of {n} fragments: {hub_s:.1f} s")
        print(f"partners ranked again after the docked answer (mutual proximity): median "
              f"{1e3 * np.median(cpu_mutual):.0f} ms CPU, max {1e3 * np.max(cpu_mutual):.0f} ms")
        print(f"{n:6d} {build:8.2f} {1e3 * np.median(times):10.1f} / {1e3 * np.percentile(times, 90):7.1f} "
              f"{1e3 * np.median(cpu):8.1f} {1e3 * np.median(align_times):10.1f} {full:9.1f} / {full_cpu:7.1f} "
              f"{rescore:10.1f} {peak_rss_mb():12.0f}"
              + (f" {1e3 * np.median(cpu_plain):19.1f} {sum(f.nbytes for f in index._frames.values()) / 2 ** 20:9.0f}"
                 if args.pool else ""))
        sys.stdout.flush()
        assert found and np.isfinite(found[0].ribbon_score)  # the last query got ribbon-ranked proposals
        assert not args.pool or found[0].docking is not None   # ... and docked ones with --pool
    return 0


if __name__ == "__main__":
    sys.exit(main())
