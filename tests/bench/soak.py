"""Soak with faults (on demand): many synthetic fragments through every stage while things break.

    python tests/bench/soak.py                      # 300 fragments at 100 dpi (capture ~13 min, then ~4 min of station on 2 busy cores)
    python tests/bench/soak.py --fragments 20       # a short run
    python tests/bench/soak.py --captured /tmp/tessera-soak-123/source   # reuse an earlier capture

Two workers per stage (solver, features, renderer, matcher) and a broker, real processes over
loopback. Fragments are submitted in bench-like batches while a chaos thread

* kills a random worker with SIGKILL every ``--kill-every`` seconds (and starts a replacement),
* kills the broker once (SIGKILL, at 40 % of the submissions) and restarts it on the same journal,
* cuts one "worker host" off for ``--cut-s`` seconds (both workers of one set are frozen with
  SIGSTOP, so the broker sees them go silent as across a broken link, then SIGCONT: they come back
  with results for jobs the broker has meanwhile given to others).

At the end (jobs parked after repeated kills are re-run once, as an operator would; after the
workers stop, the temporary-file sweep of ``tessera reconcile`` runs and its removals are printed)
it checks and prints: every fragment has exactly one RGBN, feature and rendering artifact per face on storage
and the events announce no other; no temporary files are left; the proposal store holds every
front face; a job still parked is re-run once in-process without faults (a fragment whose input a
stage refuses again the same way, e.g. scans that cannot be registered, is listed as refused:
its error event is the right outcome and its missing outputs are not losses; any other parked job
or missing output fails the soak); the resident memory of the long-running processes did not keep growing
(median of the last quarter of samples vs the first quarter). Exit status 0 if all hold.
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import shutil
import signal
import statistics
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.bus.client import BrokerClient  # noqa: E402
from common.config import load_config  # noqa: E402
from common.messages import unpack  # noqa: E402
from common.store import Store  # noqa: E402
from services.cli.perf import _capture, _rss_mb, _Station  # noqa: E402

STAGES = ("solver", "features", "renderer", "matcher")
OUTPUT_DIRS = {"rgbn": "rgbn.ready", "features": "features.ready", "renders": "render.ready"}


def _captured(source: Path, root: Path, n: int) -> list[dict]:
    """fragment.ready events (new uids) for the first n fragments captured into ``source`` earlier."""
    from common.messages import new_message
    if root.resolve() != source.resolve():
        shutil.rmtree(root, ignore_errors=True)
        shutil.copytree(source, root, ignore=shutil.ignore_patterns("rgbn", "features", "renders", "matches"))
    store = Store(root)
    scans = sorted((root / "fragments").glob("*/scans/*.h5"))[:n]
    if len(scans) < n:
        raise RuntimeError(f"only {len(scans)} captured fragments in {source}")
    return [new_message("fragment.ready", fragment=p.parts[-3], artifact=store.ref(str(p.relative_to(root))), device="sim")
            for p in scans]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fragments", type=int, default=300)
    ap.add_argument("--dpi", type=int, default=100, help="scan resolution (100: fast; the station default is 300)")
    ap.add_argument("--batch", type=int, default=10, help="fragments per submission batch")
    ap.add_argument("--batch-every", type=float, default=5.0, help="seconds between batches")
    ap.add_argument("--kill-every", type=float, default=20.0)
    ap.add_argument("--cut-s", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--dir", default=None, help="work directory (default: a new one under /tmp)")
    ap.add_argument("--captured", default=None, help="reuse the scans captured by an earlier soak (its <dir>/source)")
    args = ap.parse_args(argv)
    rng = random.Random(args.seed)
    base = Path(args.dir or f"/tmp/tessera-soak-{os.getpid()}")
    base.mkdir(parents=True, exist_ok=True)
    config = load_config(None, {"scanner.dpi": args.dpi, "scanner.wall_dpi": args.dpi, "scanner.prescan_dpi": 25})
    print(f"capturing {args.fragments} fragments at {args.dpi:g} dpi into {base} ...", flush=True)
    if args.captured:
        events = _captured(Path(args.captured), base / "source", args.fragments)
        print(f"  reused {len(events)} captured fragments from {args.captured}", flush=True)
    else:
        events, cap = _capture(config, base / "source", args.fragments)
        print(f"  {cap:.2f} s per fragment", flush=True)
    st = _Station(base, base / "source", "station")
    t0 = time.time()  # the station's clock: capture (serial, simulated) is not station time
    broker = st.spawn("broker")
    workers: dict[tuple[int, str], object] = {}
    for s in (0, 1):
        for stage in STAGES:
            workers[(s, stage)] = st.spawn("worker", stage)
    rss = collections.defaultdict(list)
    faults = collections.Counter()
    stop = threading.Event()
    lock = threading.Lock()

    def chaos():
        nonlocal broker
        next_kill = time.monotonic() + args.kill_every
        broker_done = cut_done = False
        while not stop.wait(1.0):
            with lock:
                # sample memory of the long-running processes (the broker and the current workers)
                rss["broker"].append(_rss_mb(broker.pid))
                for (s, stage), p in workers.items():
                    rss[f"{stage}"].append(_rss_mb(p.pid))
                progress = sent[0] / len(events)
                if not broker_done and progress >= 0.4:
                    broker.send_signal(signal.SIGKILL)
                    broker.wait()
                    time.sleep(1.0)
                    broker = st.spawn("broker")
                    broker_done = True
                    faults["broker restarts"] += 1
                    print(f"  [{time.time() - t0:6.0f} s] broker killed and restarted", flush=True)
                elif not cut_done and progress >= 0.6:
                    frozen = [p for (s, _), p in workers.items() if s == 1]
                    for p in frozen:
                        p.send_signal(signal.SIGSTOP)
                    print(f"  [{time.time() - t0:6.0f} s] worker host 1 cut off for {args.cut_s:g} s", flush=True)
                    time.sleep(args.cut_s)
                    for p in frozen:
                        p.send_signal(signal.SIGCONT)
                    cut_done = True
                    faults["host cut-offs"] += 1
                elif time.monotonic() >= next_kill:
                    key = rng.choice(sorted(workers))
                    workers[key].send_signal(signal.SIGKILL)
                    workers[key].wait()
                    workers[key] = st.spawn("worker", key[1])
                    faults["workers killed"] += 1
                    next_kill = time.monotonic() + args.kill_every

    sent = [0]
    chaos_thread = threading.Thread(target=chaos, daemon=True)
    chaos_thread.start()
    ok = True
    try:
        with BrokerClient.from_config(st.config, timeout_s=5.0, retries=20) as c:
            for i in range(0, len(events), args.batch):
                batch = events[i:i + args.batch]
                while True:
                    try:
                        c.submit_many(batch)
                        break
                    except Exception as exc:  # the broker may be down right now: the bench retries
                        print(f"  submit retry: {exc}", flush=True)
                        time.sleep(1.0)
                sent[0] = i + len(batch)
                time.sleep(args.batch_every)
            reran = False
            while True:
                try:
                    s = c.status()
                except Exception:
                    time.sleep(1.0)
                    continue
                idle = not s["in_flight"] and not any(s["queues"].values())
                if idle and s["parked"] and not reran:
                    print(f"  re-running {len(s['parked'])} parked job(s): "
                          f"{collections.Counter(p['service'] for p in s['parked'])}", flush=True)
                    faults["parked then re-run"] += len(c.rerun("all"))
                    reran = True
                    continue
                # every batch is in and nothing is queued or running: jobs live only in the broker's
                # journal, so idle means done (its "completed" counter restarts with the broker)
                if idle:
                    time.sleep(3.0)
                    s2 = c.status()
                    if not s2["in_flight"] and not any(s2["queues"].values()):
                        break
                time.sleep(2.0)
            evs, after = [], 0
            while (r := c.since(after, 5000))["events"]:
                evs += [unpack(b) for _, b in r["events"]]
                after = r["events"][-1][0]
            parked_end = c.status()["parked"]
    finally:
        stop.set()
        chaos_thread.join(60)
        for p in workers.values():
            try:
                p.send_signal(signal.SIGCONT)
            except ProcessLookupError:
                pass
        st.stop()
    wall_s = time.time() - t0  # station start until every job is done or parked
    # what an operator runs after a crash (`tessera reconcile` sweeps first): temporary files of
    # writers killed mid-write on this host go at once; whatever is left after it counts as a leak
    swept = Store(st.config["storage"]["root"]).sweep_temporary()
    print(f"\nsweep after the workers stopped (as tessera reconcile does): {len(swept)} temporary file(s) "
          f"of writers killed mid-write removed{': ' + ', '.join(swept[:5]) if swept else ''}", flush=True)
    ok &= _check(st, events, evs, parked_end, rss, faults, wall_s)
    return 0 if ok else 1


def control_rerun(root: Path, scratch: Path, config, parked: list[dict], inputs: list[dict]) -> dict[str, str]:
    """Re-run each parked job once, in this process, without faults, on a scratch copy of its input.

    A job the faults made fail completes here; a job a stage refuses because of its input (scans
    that cannot be registered, say) fails again the same way. Returns ``{job id: outcome}``, the
    outcome starting with ``"reproduced: "`` (the same exception type) or ``"completed"``.
    """
    import importlib
    import logging
    from common.bus.worker import StageContext
    from common.store import ArtifactRef
    routing = config.get("routing", {})
    outcome = {}
    for p in parked:
        job = next((e for e in inputs if p["service"] in routing.get(e["type"], ()) and e.get("fragment") == p["fragment"]
                    and (p.get("face") is None or e.get("face") == p.get("face"))), None)
        if job is None:
            outcome[p["job"]] = "input event not found"
            continue
        work = scratch / p["job"]
        shutil.rmtree(work, ignore_errors=True)
        rel = ArtifactRef.from_dict(job["artifact"]).path
        (work / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(root / rel, work / rel)
        if (root / "calibration").is_dir():  # the solver takes the device's newest calibration
            shutil.copytree(root / "calibration", work / "calibration")
        module = importlib.import_module(f"services.{p['service']}")
        ctx = StageContext(store=Store(work), config=dict(config.get("services", {}).get(p["service"], {})),
                           log=logging.getLogger(f"soak.control.{p['service']}"), progress=lambda f, t="": None,
                           service=p["service"], job_id=p["job"])
        try:
            module.handle(job, ctx)
            outcome[p["job"]] = "completed"
        except Exception as exc:  # noqa: BLE001  (the outcome is the point)
            same = p["error"].startswith(type(exc).__name__)
            outcome[p["job"]] = f"{'reproduced' if same else 'failed differently'}: {type(exc).__name__}: {exc}"
        shutil.rmtree(work, ignore_errors=True)
    return outcome


def _check(st, events, evs, parked_end, rss, faults, wall_s) -> bool:
    root = Path(st.config["storage"]["root"])
    frags = [e["fragment"] for e in events]
    ok = True
    files = collections.Counter()
    for sub in OUTPUT_DIRS:
        for f in frags:
            for p in (root / "fragments" / f / sub).glob("*.h5"):
                files[(f, sub, p.name.split("-")[0])] += 1
    announced = collections.defaultdict(set)
    for e in evs:
        if e["type"] in OUTPUT_DIRS.values():
            announced[(e["fragment"], e["type"], e.get("face"))].add(e["artifact"]["path"])
    missing = [(f, sub, face) for f in frags for sub in OUTPUT_DIRS for face in ("front", "back")
               if files[(f, sub, face)] != 1]
    multi = {k: v for k, v in announced.items() if len(v) != 1}
    temps = [p for p in root.rglob("*") if p.is_file() and p.name.startswith(".") and p.name.endswith(".tmp")]
    from common.matching.proposals import ProposalStore
    db = root / "matches" / "proposals.sqlite"
    fronts = set()
    if db.exists():
        with ProposalStore(db) as ps:
            fronts = {r["fragment"] for r in ps.fragments("front")}
            n_prop = ps.count()
    else:
        n_prop = 0
    missing_fronts = sorted(set(frags) - fronts)
    # a parked job that fails again the same way without any fault is the stage refusing its input
    # (with a clear error event: nothing was lost); the fragments downstream of it are explained
    control = control_rerun(root, root.parent / "control", st.config, parked_end, list(events) + list(evs))
    refused = {p["fragment"] for p in parked_end if control.get(p["job"], "").startswith("reproduced")}
    fault_parked = [p for p in parked_end if p["fragment"] not in refused]
    print(f"soak: {len(frags)} fragments through the station in {wall_s / 60:.1f} min, from its start to the "
          f"last job ({3600 * len(frags) / wall_s:.0f} fragments/hour with the faults); faults: {dict(faults)}")
    print(f"  outputs: {sum(files.values())} artifacts, {len(missing)} (fragment, stage, face) not exactly once"
          f"{': ' + str(missing[:5]) if missing else ''}")
    print(f"  events announcing more than one artifact for one output: {len(multi)}")
    print(f"  temporary files left: {len(temps)}{': ' + str(temps[:3]) if temps else ''}")
    print(f"  proposal store: {len(fronts)} front faces, {n_prop} proposals; missing fronts: {missing_fronts[:5]}")
    print(f"  parked at the end: {len(parked_end)}; each re-run once in-process without faults:")
    for p in parked_end:
        print(f"    {p['service']} {p['fragment']} {p.get('face') or ''}: {control.get(p['job'])[:200]}")
    unexplained = [m for m in missing if m[0] not in refused]
    unexplained_fronts = [f for f in missing_fronts if f not in refused]
    print(f"  fragments a stage refused on their own input (reproduced without faults): {len(refused)} "
          f"{sorted(refused)[:5]}; outputs missing for other reasons: {len(unexplained)}, fronts: "
          f"{len(unexplained_fronts)}, parked for other reasons: {len(fault_parked)}")
    ok &= not unexplained and not multi and not temps and not unexplained_fronts and not fault_parked
    print("  resident memory (MB), median of the 2nd fifth of the samples (after start-up) -> last fifth:")
    for name, vals in sorted(rss.items()):
        vals = [v for v in vals if v == v]
        if len(vals) < 10:
            continue
        q = len(vals) // 5
        a, b = statistics.median(vals[q:2 * q]), statistics.median(vals[-q:])
        if name == "matcher":  # its index holds every fragment by design: report the growth per fragment
            print(f"    {name:9s} {a:7.0f} -> {b:7.0f}  peak {max(vals):7.0f}  "
                  f"({(b - a) / max(1, len(frags)) * 1000:.0f} kB per fragment: the index of all fragments)")
            continue
        bounded = b <= 1.25 * a + 30
        ok &= bounded
        print(f"    {name:9s} {a:7.0f} -> {b:7.0f}  peak {max(vals):7.0f}  {'ok' if bounded else 'GROWING'}")
    if ok and refused:
        print(f"soak: PASS (nothing lost to the faults; {len(refused)} of {len(frags)} fragments refused by a stage "
              "on their own input, each with its error event, listed above)")
    else:
        print("soak: PASS" if ok else "soak: FAIL")
    return ok


if __name__ == "__main__":
    sys.exit(main())
