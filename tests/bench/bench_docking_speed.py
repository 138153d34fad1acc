"""CPU per docked pair at real fragment sizes: stage 3 as before (two searches per pair) against one
search whose frames are kept (issue 15 item 5).

    python tests/bench/bench_docking_speed.py [--collection ../shared/data/repair-dev] [--dpi 150]
                                              [--queries 4] [--partners 12]

A proposal docks one new fragment against its best 12 candidates (``index.DOCK_CANDIDATES``). For
``--queries`` fragments of the collection, each against ``--partners`` others (drawn at random, seed
0), it times with ``time.process_time`` (CPU of this process):

* **two searches** — what stage 3 did until 2026-11-25: the pose (``dock_outlines(n_poses=1)``, coarse
  to fine) and, for the paint continuity, a second full search of 30 candidate poses
  (``dock_outlines(n_poses=30, per_angle=3)`` inside ``paint.paint_pair_mm``); every map and spectrum
  recomputed per pair;
* **one search, frames kept** — what stage 3 does now (``MatchIndex._dock_pair``): one
  ``dock_frames(n_poses=30, per_angle=3)`` per pair gives the pose (its best) and the paint's
  candidates, the query's :class:`~common.matching.docking.DockingFrame` (its maps and spectra at the
  90 rotations) serving all its partners, docked in order of FFT size as the index does; the query is
  turned (B) against every partner, as in the station where the new fragment has the newest id;
* **one search, no frames kept** — the same search with fresh frames per pair (the worst case of the
  cache: a partner the query is held against);
* the paint scoring of the 30 poses (``paint_continuity``), the same in all three;

and it prints the frames' memory (bytes the query's frame holds while it serves its partners) and
whether the one search gives the same pose and paint evidence as the two (it must: the same search).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching.collection import collection_wall  # noqa: E402
from common.matching.docking import DockingFrame, dock_frames, dock_outlines  # noqa: E402
from common.matching.online import wall_cues  # noqa: E402
from common.matching.paint import paint_field_from_profile, paint_pair_mm  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--collection", default=str(Path(__file__).resolve().parents[3] / "shared/data/repair-dev"))
    ap.add_argument("--dpi", type=float, default=150.0)
    ap.add_argument("--queries", type=int, default=4)
    ap.add_argument("--partners", type=int, default=12)
    args = ap.parse_args()

    wall = collection_wall(args.collection, dpi=args.dpi)
    tables, _, _ = wall_cues(wall)
    ids = sorted(f for f in tables if tables[f].boundary_profile is not None)
    contour = {f: tables[f].contour_mm for f in ids}
    field = {f: paint_field_from_profile(tables[f].contour_mm, tables[f].boundary_profile) for f in ids}
    rng = np.random.default_rng(0)
    queries = [ids[i] for i in rng.choice(len(ids), size=min(args.queries, len(ids)), replace=False)]
    work = [(q, [ids[i] for i in rng.choice(len(ids), size=min(args.partners, len(ids) - 1) + 1, replace=False)
                 if ids[i] != q][:args.partners]) for q in queries]
    n_pairs = sum(len(p) for _, p in work)
    print(f"{args.collection}: {len(ids)} fragments, {len(queries)} queries x {args.partners} partners "
          f"= {n_pairs} pairs")

    cpu: dict[str, float] = {}

    def timed(key, fn):
        t = time.process_time()
        out = fn()
        cpu[key] = cpu.get(key, 0.0) + time.process_time() - t
        return out

    before = {}
    for q, partners in work:
        for o in partners:
            pose = timed("two searches: the pose (coarse to fine)", lambda: dock_outlines(contour[o], contour[q])[0])
            docks = timed("two searches: 30 paint poses", lambda: dock_outlines(contour[o], contour[q], n_poses=30,
                                                                                per_angle=3))
            mm = timed("paint scoring of 30 poses", lambda: paint_pair_mm(field[o], field[q], contour[o], contour[q],
                                                                          docks=docks)[0])
            timed("one search, no frames kept", lambda: dock_frames(DockingFrame(contour[o]), DockingFrame(contour[q]),
                                                                    n_poses=30, per_angle=3))
            before[q, o] = pose, docks, mm
    same_docks = same_paint = same_pose = 0
    frame_bytes = []
    for q, partners in work:
        frame_q = DockingFrame(contour[q])
        frames = {o: DockingFrame(contour[o]) for o in partners}
        # in order of FFT size, as the index docks them (MatchIndex._dock_pairs): one size's spectra at a time
        for o in sorted(partners, key=lambda o: frames[o].fft_size(frame_q)):
            docks = timed("one search, frames kept", lambda: dock_frames(frames[o], frame_q, n_poses=30, per_angle=3))
            pose, docks_before, mm = before[q, o]
            same_docks += docks == docks_before
            same_paint += paint_pair_mm(field[o], field[q], contour[o], contour[q], docks=docks)[0] == mm
            same_pose += abs(docks[0].score - pose.score) < 1e-3
            frame_bytes.append(frame_q.nbytes)
    for k, v in cpu.items():
        print(f"{k:42s} {1e3 * v / n_pairs:7.1f} ms CPU per pair")
    two = cpu["two searches: the pose (coarse to fine)"] + cpu["two searches: 30 paint poses"]
    one = cpu["one search, frames kept"]
    print(f"{'stage 3 docking per pair: before / now':42s} {1e3 * two / n_pairs:7.1f} / "
          f"{1e3 * one / n_pairs:.1f} ms CPU "
          f"({two / one:.1f}x)")
    print(f"a query's frame while it serves its partners (one FFT size's turned spectra kept): "
          f"{np.median(frame_bytes) / 2 ** 20:.0f} MB median, {np.max(frame_bytes) / 2 ** 20:.0f} MB max")
    print(f"one search with kept frames = the 30-pose search without: {same_docks}/{n_pairs} pairs (same poses and "
          f"scores), same paint evidence {same_paint}/{n_pairs}; its best pose scores as the coarse-to-fine pose for "
          f"{same_pose}/{n_pairs} (the rest: the full search finds a better one)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
