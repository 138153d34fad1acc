"""Broker benchmark: jobs/s with 1, 2, 4 no-op workers (journal on), dispatch latency at 100 jobs/s.

Run: ``python tests/bench/bench_broker.py [--jobs 20000] [--seconds 10]``

Real processes on loopback, as in production: one broker (journal fsynced per batch), k worker
processes running ``services/noop.py``, one client submitting pipelined. Throughput = jobs
completed / time from the first submission to the last completion. Dispatch latency = time the
worker received the job − time the event was created just before submission (so it includes
the journal's fsync before the job may be dispatched, and the network hops).
Targets (issue 2): >= 2,000 jobs/s on a 2-core machine; p99 dispatch latency < 10 ms at 100 jobs/s.
Garbage flood (issue 19, ``--flood N``): N malformed frames from four sockets as fast as they go
while STATUS is asked every 0.1 s and good jobs flow: refusals/s, STATUS answer times (target:
every one within 100 ms), the journal's event count before and after (refusals are summarised,
not journaled), and the good jobs done.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.bus.client import BrokerClient  # noqa: E402
from common.messages import new_message  # noqa: E402
from tests.bus.conftest import Station, wait_for  # noqa: E402


def throughput(workers: int, jobs: int) -> tuple[float, float]:
    with tempfile.TemporaryDirectory() as d:
        st = Station(Path(d), services={"noop": {"emit": False}})
        try:
            st.broker()
            for _ in range(workers):
                st.worker()
            st.workers_ready(workers)
            events = [new_message("noop.job", n=i) for i in range(jobs)]
            with BrokerClient.from_config(st.config, timeout_s=10.0) as c:  # a loaded machine stalls for seconds
                t0 = time.perf_counter()
                c.submit_many(events, window=1000)
                t_sub = time.perf_counter() - t0
                wait_for(lambda: c.status()["completed"] >= jobs, 600, f"{jobs} jobs", interval=0.1)
                elapsed = time.perf_counter() - t0
        finally:
            st.stop()
    return jobs / elapsed, jobs / t_sub


_PEER = """
import sys, zmq
d = zmq.Context().socket(zmq.DEALER); d.connect(sys.argv[1]); d.send_multipart([b"", b"TW1", b"READY"])
while True:
    f = d.recv_multipart()
    if f[-1] == b"stop": break
    d.send_multipart([b"", b"TW1", b"RESULT", f[4], b"\\x90"])
"""


def pingpong(n: int = 5000) -> float:
    """Reference: bare pyzmq ROUTER<->DEALER round trips/s between two processes right now (the
    ceiling of any Python broker with one job in flight per worker on this machine and load)."""
    import subprocess
    import zmq
    r = zmq.Context.instance().socket(zmq.ROUTER)
    port = r.bind_to_random_port("tcp://127.0.0.1")
    p = subprocess.Popen([sys.executable, "-c", _PEER, f"tcp://127.0.0.1:{port}"])
    ident = r.recv_multipart()[0]
    t0 = time.perf_counter()
    for _ in range(n):
        r.send_multipart([ident, b"", b"TW1", b"JOB", b"id", b"1", b"body"])
        r.recv_multipart()
    rate = n / (time.perf_counter() - t0)
    r.send_multipart([ident, b"stop"])
    p.wait(10)
    r.close(0)
    return rate


def latency(rate: float, seconds: float) -> np.ndarray:
    with tempfile.TemporaryDirectory() as d:
        st = Station(Path(d), services={"noop": {}})
        try:
            st.broker()
            st.worker()
            st.workers_ready(1)
            n = int(rate * seconds)
            sent = {}
            with st.client() as c, st.subscriber(None) as sub:
                t_next = time.perf_counter()
                for i in range(n):
                    while (dt := t_next - time.perf_counter()) > 0:
                        time.sleep(min(dt, 0.002))
                    ev = new_message("noop.job", n=i)
                    sent[ev["uid"]] = ev["time"]
                    c.submit(ev)
                    t_next += 1.0 / rate
                got = {}
                deadline = time.monotonic() + 30
                while len(got) < n and time.monotonic() < deadline:
                    item = sub.next(0.5)
                    if item and item[1]["type"] == "noop.done":
                        got[item[1]["job"]] = item[1]["received"]
        finally:
            st.stop()
    return np.array([got[u] - sent[u] for u in got if u in sent]) * 1e3


def _schedstat_ms() -> tuple[float, float]:
    """This thread's CPU and run-queue wait so far (ms), from /proc (zeros elsewhere)."""
    try:
        with open("/proc/thread-self/schedstat") as fh:
            run, wait = fh.read().split()[:2]
        return int(run) / 1e6, int(wait) / 1e6
    except (OSError, ValueError):
        return 0.0, 0.0


def flood(n: int, seconds: float = 0.0, nice: int | None = None) -> dict:
    """Malformed frames from another process against a broker serving a worker; STATUS timed meanwhile.

    The flood runs in its own process (in a thread here it would hold this process's GIL and slow
    the STATUS probe, not the broker). Each probe keeps the broker's own account of its poll loop
    (STATUS ``loop``) and this thread's run-queue wait during the probe, so a late answer can be
    put down to the broker (CPU inside its loop) or to the machine (waiting for a CPU).
    ``nice``: the broker's ``[broker] nice`` (default: the config's).
    """
    import subprocess
    import threading
    with tempfile.TemporaryDirectory() as d:
        st = Station(Path(d), services={"noop": {}})
        try:
            if nice is None:
                st.broker()
            else:
                st.spawn("broker", "--set", f"broker.nice={nice}")
                wait_for(lambda: _answers(st), 30, "the broker to answer")
            st.worker()
            st.workers_ready(1)
            endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
            probes, done = [], threading.Event()

            def probe():
                with BrokerClient.from_config(st.config, timeout_s=2.0, retries=1) as c:
                    prev = None
                    while not done.wait(0.1):
                        t = time.perf_counter()
                        _, q0 = _schedstat_ms()
                        try:
                            loop = c.status()["loop"]
                            ms = (time.perf_counter() - t) * 1e3
                        except Exception:  # noqa: BLE001
                            loop, ms = None, float("inf")
                        _, q1 = _schedstat_ms()
                        probes.append({"ms": ms, "probe_rq_ms": q1 - q0, "loop": loop, "prev": prev})
                        prev = loop or prev
            with BrokerClient.from_config(st.config, timeout_s=10.0) as c:
                before = c.status()["last_seq"]
                good = [new_message("noop.job", n=i) for i in range(200)]
                th = threading.Thread(target=probe, daemon=True)
                th.start()
                cpu0 = time.process_time()
                t0 = time.perf_counter()
                sender = subprocess.Popen([sys.executable, "-c", "import sys; from tests.bench.soak import _flood; "
                                           f"_flood({endpoint!r}, {n}, {seconds}, 1)"],
                                          cwd=str(Path(__file__).resolve().parents[2]))
                for i in range(0, len(good), 20):   # good work keeps flowing during the flood
                    c.submit_many(good[i:i + 20])
                    time.sleep(0.05)
                sender.wait()
                wait_for(lambda: sum(c.status()["refused"].values()) >= n * 0.95, 120, "the flood to be refused",
                         interval=0.2)
                wall = time.perf_counter() - t0
                wait_for(lambda: c.status()["completed"] >= len(good), 60, "the good jobs", interval=0.2)
                done.set()
                th.join(5)
                s = c.status()
        finally:
            st.stop()
    return {"refused": sum(s["refused"].values()), "wall_s": wall, "cpu_s_client": time.process_time() - cpu0,
            "status_ms": np.array([p["ms"] for p in probes]), "probes": probes, "loop": s["loop"],
            "journaled": s["last_seq"] - before, "good_done": s["completed"]}


def _answers(st) -> bool:
    try:
        st.status()
        return True
    except Exception:  # noqa: BLE001
        return False


def explain_late(probes: list[dict], limit_ms: float = 100.0) -> list[str]:
    """One line per late STATUS answer: the broker's worst loop iteration of the last seconds
    (its CPU, run-queue wait, GC, other) and the broker's and the prober's run-queue waits meanwhile."""
    lines = []
    for p in probes:
        if p["ms"] <= limit_ms:
            continue
        loop, prev = p["loop"], p["prev"]
        if loop is None:
            lines.append(f"    {p['ms']:.0f} ms: no answer")
            continue
        w = loop["worst_ms"] or {}
        rq = (loop["runqueue_s"] - prev["runqueue_s"]) * 1e3 if prev else float("nan")
        cpu = (loop["cpu_s"] - prev["cpu_s"]) * 1e3 if prev else float("nan")
        lines.append(f"    {p['ms']:.0f} ms: broker loop since the previous probe: CPU {cpu:.0f} ms, waiting for a CPU "
                     f"{rq:.0f} ms; worst iteration {w.get('stall', 0):.0f} ms (CPU {w.get('cpu', 0):.0f}, run queue "
                     f"{w.get('runqueue', 0):.0f}, GC {w.get('gc', 0):.0f}, other {w.get('other', 0):.0f}); "
                     f"the prober waited {p['probe_rq_ms']:.0f} ms for a CPU")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=20000)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2, 4], help="worker counts for the throughput runs")
    ap.add_argument("--flood", type=int, default=100000, help="malformed frames in the flood run (0: skip)")
    ap.add_argument("--flood-seconds", type=float, default=0.0,
                    help="spread the flood over this many seconds (0: as fast as it goes)")
    ap.add_argument("--flood-only", action="store_true", help="only the flood run")
    ap.add_argument("--broker-nice", type=int, nargs="*", default=None,
                    help="flood runs with the broker at these nice values, alternately (default: once, as configured)")
    ap.add_argument("--repeat", type=int, default=1, help="rounds of the --broker-nice flood runs")
    args = ap.parse_args()
    cpu0, wall0 = time.process_time(), time.perf_counter()
    print(f"broker benchmark: {args.jobs} no-op jobs per run, journal on (fsync per batch); "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if not args.flood_only:
        print(f"  reference: bare pyzmq round trips between two processes: {pingpong():.0f}/s")
        for k in args.workers:
            rate, accept = throughput(k, args.jobs)
            print(f"  {k} worker(s): {rate:8.0f} jobs/s completed   (submissions acknowledged at {accept:.0f}/s)")
        lat = latency(100.0, args.seconds)
        print(f"dispatch latency at 100 jobs/s, 1 worker, {len(lat)} jobs: "
              f"p50 {np.percentile(lat, 50):.2f} ms  p99 {np.percentile(lat, 99):.2f} ms  max {lat.max():.2f} ms")
    if args.flood and args.broker_nice:
        print("garbage flood, the broker at each nice value in turn (broker's own account of its poll loop):")
        for r in range(args.repeat):
            for nice in args.broker_nice:
                f = flood(args.flood, args.flood_seconds, nice)
                ms, loop = f["status_ms"], f["loop"]
                w = loop["worst_ms"] or {}
                print(f"  nice {nice:3d} (load {os.getloadavg()[0]:4.1f}): {f['refused']} refused in {f['wall_s']:.1f} s; "
                      f"STATUS p50 {np.percentile(ms, 50):.1f} ms, p99 {np.percentile(ms, 99):.1f} ms, max {ms.max():.1f} ms, "
                      f"{int((ms > 100).sum())}/{len(ms)} over 100 ms; loop CPU {loop['cpu_s']:.2f} s, waiting for a CPU "
                      f"{loop['runqueue_s']:.2f} s; worst iteration of the last 10 s {w.get('stall', 0):.0f} ms "
                      f"(CPU {w.get('cpu', 0):.0f}, waiting {w.get('runqueue', 0):.0f})")
    elif args.flood:
        f = flood(args.flood, args.flood_seconds)
        ms = f["status_ms"]
        loop = f["loop"]
        print(f"garbage flood: {f['refused']} frames refused in {f['wall_s']:.1f} s ({f['refused'] / f['wall_s']:.0f}/s); "
              f"events journaled meanwhile {f['journaled']} (200 good jobs and their results, plus refusal summaries); "
              f"good jobs done {f['good_done']}/200")
        print(f"  STATUS during the flood ({len(ms)} asks, every 0.1 s): p50 {np.percentile(ms, 50):.1f} ms  "
              f"p99 {np.percentile(ms, 99):.1f} ms  max {ms.max():.1f} ms; over 100 ms: {int((ms > 100).sum())}")
        print(f"  broker poll loop over the whole run: {loop['iterations']} iterations, CPU {loop['cpu_s']:.1f} s, "
              f"waiting for a CPU {loop['runqueue_s']:.1f} s, GC {loop['gc_s']:.2f} s")
        for line in explain_late(f["probes"]):
            print(line)
    print(f"bench: CPU {time.process_time() - cpu0:.1f} s (this process), wall {time.perf_counter() - wall0:.1f} s; "
          f"load average at the end {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
