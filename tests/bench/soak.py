"""Soak with faults (on demand): many synthetic fragments through every stage while things break.

    python tests/bench/soak.py                      # 300 fragments at 100 dpi (capture ~13 min, then ~4 min of station on 2 busy cores)
    python tests/bench/soak.py --fragments 20       # a short run
    python tests/bench/soak.py --captured /tmp/tessera-soak-123/source   # reuse an earlier capture

Two workers per stage (solver, features, renderer, matcher) and a broker, real processes over
loopback. Fragments are submitted in bench-like batches while a chaos thread

* kills a random worker with SIGKILL every ``--kill-every`` seconds (and starts a replacement),
* kills the broker once (SIGKILL, at 40 % of the submissions) and restarts it on the same journal,
* cuts one "worker host" off for ``--cut-s`` seconds (the four workers of one set are frozen with
  SIGSTOP, so the broker sees them go silent as across a broken link, then SIGCONT: they come back
  with results for jobs the broker has meanwhile given to others),

and, unless ``--no-attacks`` (issue 19; the storage faults need root: the storage root is then a
tmpfs mount of its own),

* fills the storage for ``--full-s`` seconds (a ballast file takes every free byte, at 20 %),
* remounts the storage read-only for ``--ro-s`` seconds (at 30 %),
* sends a forged ``RESULT`` for a queued solver job from a peer that never registered (at 50 %),
* floods the broker with ``--garbage`` malformed frames from four sockets (at 70 %),
* probes STATUS every 0.5 s throughout from a process of its own (a new connection each time, as
  ``tessera status``) and times each answer, keeping the broker's own account of its poll loop
  (STATUS ``loop``: CPU, waiting for a CPU, GC) and the prober's wait for a CPU, so a late answer
  is put down to the broker or to the machine.

At the end (jobs parked after repeated kills are re-run once, as an operator would; after the
workers stop, the temporary-file sweep of ``tessera reconcile`` runs and its removals are printed)
it checks and prints: every fragment has exactly one RGBN, feature and rendering artifact per face on storage
and the events announce no other; no temporary files are left; the proposal store holds every
front face; a job still parked is re-run once in-process without faults (a fragment whose input a
stage refuses again the same way, e.g. scans that cannot be registered, is listed as refused:
its error event is the right outcome and its missing outputs are not losses; any other parked job
or missing output fails the soak); the resident memory of the long-running processes did not keep growing
(median of the last fifth of the samples at most 1.25 x + 30 MB that of the second fifth, after
start-up; the matcher's index grows by design and is only reported); with the attacks: no forged event
was published, the catch-up history starts at 1 and has no gap, and every STATUS probe outside the
broker's restart was answered within 100 ms. Exit status 0 if all hold.
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import shutil
import signal
import statistics
import subprocess
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


_PROBER = r"""
import json, os, sys, time
from common.bus.client import BrokerClient
from common.config import load_config

def waited_ms():  # run-queue wait of every thread of this process so far (ZeroMQ's I/O thread too)
    total = 0
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/schedstat") as fh:
                total += int(fh.read().split()[1])
        except (OSError, ValueError, IndexError):
            pass
    return total / 1e6

config, out = load_config(sys.argv[1]), open(sys.argv[2], "a", buffering=1)
while True:
    time.sleep(0.5)
    q0, t0, t = waited_ms(), time.time(), time.monotonic()
    try:
        with BrokerClient.from_config(config, timeout_s=2.0, retries=1) as c:  # a new connection, as `tessera status`
            loop = c.status().get("loop")
        ms = (time.monotonic() - t) * 1000
    except Exception:  # no answer within 2 s
        loop, ms = None, None
    out.write(json.dumps([t0, ms, loop, waited_ms() - q0]) + "\n")
"""


def _start_prober(config_path: Path, out: Path) -> subprocess.Popen:
    """STATUS asked every 0.5 s from a process of its own (in a thread of the soak it would wait for
    this process's GIL); each line: time, answer ms (None: none within 2 s), the broker's STATUS
    ``loop`` account, and the prober's own wait for a CPU during the ask (ms)."""
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    return subprocess.Popen([sys.executable, "-c", _PROBER, str(config_path), str(out)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _read_probes(path: Path, t0: float, restarts: list[tuple[float, float]]) -> list[tuple]:
    """(station time, ms, broker restarting, loop, prober run-queue ms) of every probe."""
    import json
    probes = []
    for line in path.read_text().splitlines() if path.exists() else []:
        t, ms, loop, waited = json.loads(line)
        # a probe sent up to its 2-s timeout before the broker was killed cannot be answered either
        probes.append((t - t0, ms, any(a - 2.5 <= t <= b for a, b in restarts), loop, waited))
    return probes


def _storage_on_tmpfs(storage: Path, headroom_mb: int) -> bool:
    """Move ``storage`` onto a tmpfs mount of its own (its size + headroom); False if not possible."""
    if os.geteuid() != 0:
        return False
    staged = storage.with_name(storage.name + ".staged")
    storage.rename(staged)
    storage.mkdir()
    used_mb = sum(f.stat().st_size for f in staged.rglob("*") if f.is_file()) // 2**20
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={used_mb + headroom_mb}m", "tmpfs", str(storage)],
                       capture_output=True, text=True)
    if r.returncode:
        storage.rmdir()
        staged.rename(storage)
        print(f"  (no tmpfs for the storage: {r.stderr.strip()}; disk-full and read-only faults skipped)", flush=True)
        return False
    shutil.copytree(staged, storage, dirs_exist_ok=True)
    shutil.rmtree(staged)
    return True


def _fill_disk(path: Path) -> int:
    """Write zeros into ``path`` until the file system is full; returns the bytes written."""
    n = 0
    with open(path, "wb") as fh:
        try:
            while True:
                fh.write(b"\0" * (1 << 20))
                fh.flush()
                n += 1 << 20
        except OSError:
            pass
    return n


def _garbage_frames(rng: random.Random):
    from common.bus import protocol as P
    kinds = [
        lambda: [b"garbage"],
        lambda: [b"", b"XX9", b"HELLO"],
        lambda: [b"", P.CLIENT, P.SUBMIT, b"t", b"\xc1" + os.urandom(rng.randint(0, 40))],
        lambda: [b"", P.CLIENT, P.SUBMIT, b"t", P.dumps({"v": 1, "type": "noop.job", "uid": 2 ** 64 - 1, "time": 1.0})],
        lambda: [b"", P.WORKER, P.RESULT, b"0123456789ab-solver", P.dumps([])],
        lambda: [os.urandom(rng.randint(0, 30)) for _ in range(rng.randint(1, 5))],
    ]
    while True:
        yield rng.choice(kinds)()


def _flood(endpoint: str, n: int, seconds: float, seed: int) -> float:
    """Send ``n`` malformed frames to the broker over ``seconds``; returns the seconds it took."""
    import zmq
    ctx = zmq.Context()
    socks = []
    for _ in range(4):
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.SNDHWM, 0)
        sock.connect(endpoint)
        socks.append(sock)
    rng = random.Random(seed)
    frames = _garbage_frames(rng)
    t0 = time.monotonic()
    try:
        for i in range(n):
            socks[i % 4].send_multipart(next(frames))
            if i % 1000 == 999:
                for sock in socks:  # drop the ERR replies
                    while sock.poll(0):
                        sock.recv_multipart()
                behind = t0 + seconds * (i + 1) / n - time.monotonic()
                if behind > 0:
                    time.sleep(behind)
    finally:
        ctx.destroy(linger=0)
    return time.monotonic() - t0


def _forge_result(endpoint: str, client) -> str | None:
    """Send RESULT for the newest solver job from a peer that never said READY; returns the job id."""
    import zmq

    from common.bus import protocol as P
    from common.messages import new_message
    last = client.status()["last_seq"]
    r = client.since(max(0, last - 500), 1000, types=["fragment.ready"])
    if not r["events"]:
        return None
    ev = unpack(r["events"][-1][1])
    jid = f"{ev['uid'][:12]}-solver"
    forged = new_message("rgbn.ready", fragment=ev["fragment"], face="front", forged=True,
                         artifact={"path": f"fragments/{ev['fragment']}/rgbn/front-forged.h5", "sha256": "0" * 64,
                                   "bytes": 1})
    ctx = zmq.Context()
    try:
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 500)
        sock.connect(endpoint)
        sock.send_multipart([b"", P.WORKER, P.RESULT, jid.encode(), P.dumps([forged])])
        sock.poll(2000)
    finally:
        ctx.destroy(linger=500)
    return jid


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
    ap.add_argument("--no-attacks", action="store_true", help="only the process faults (no disk, forged or garbage faults)")
    ap.add_argument("--full-s", type=float, default=30.0, help="seconds the storage stays full")
    ap.add_argument("--ro-s", type=float, default=20.0, help="seconds the storage stays read-only")
    ap.add_argument("--garbage", type=int, default=100000, help="malformed frames in the flood")
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
    storage = Path(st.config["storage"]["root"])
    mounted = not args.no_attacks and _storage_on_tmpfs(storage, headroom_mb=2048)
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    attacks = {"forged": None, "flood_s": None}
    # broker start and restart windows (wall clock): start-up (imports, journal replay) is not "serving"
    restarts: list[list[float]] = []
    t0 = time.time()  # the station's clock: capture (serial, simulated) is not station time
    restarts.append([t0, float("inf")])
    broker = st.spawn("broker", "broker")
    with BrokerClient.from_config(st.config, timeout_s=2.0, retries=1000) as c0:
        c0.status()
    restarts[-1][1] = time.time()
    prober = _start_prober(st.config_path, base / "probes.jsonl")
    workers: dict[tuple[int, str], object] = {}
    for s in (0, 1):
        for stage in STAGES:
            workers[(s, stage)] = st.spawn(stage, "worker", stage)
    rss = collections.defaultdict(list)
    faults = collections.Counter()
    stop = threading.Event()
    lock = threading.Lock()

    def attack(progress: float, done: set) -> None:
        """The issue-19 faults, each once, in the chaos thread."""
        def note(text):
            print(f"  [{time.time() - t0:6.0f} s] {text}", flush=True)
        if mounted and "full" not in done and progress >= 0.2:
            done.add("full")
            ballast = storage / ".soak-ballast"
            n = _fill_disk(ballast)
            note(f"storage full ({n / 2**20:.0f} MB of ballast) for {args.full_s:g} s")
            time.sleep(args.full_s)
            ballast.unlink()
            faults["disk full"] += 1
        elif mounted and "ro" not in done and progress >= 0.3:
            done.add("ro")
            # a read-only bind mount over the storage (a plain remount is refused while the matcher
            # holds its SQLite file open): every new open or create sees EROFS, as on a share gone ro
            subprocess.run(["mount", "--bind", str(storage), str(storage)], check=True)
            try:
                subprocess.run(["mount", "-o", "remount,bind,ro", str(storage)], check=True)
                note(f"storage read-only for {args.ro_s:g} s")
                time.sleep(args.ro_s)
            finally:
                # the read-only bind goes, rw again (lazily: a file opened during the window keeps it busy)
                subprocess.run(["umount", "-l", str(storage)], check=True)
            faults["read-only remount"] += 1
        elif "forged" not in done and progress >= 0.5:
            done.add("forged")
            try:
                with BrokerClient.from_config(st.config, timeout_s=2.0, retries=3) as fc:
                    attacks["forged"] = _forge_result(endpoint, fc)
                note(f"forged RESULT sent for job {attacks['forged']}")
                faults["forged results"] += 1
            except Exception as exc:  # noqa: BLE001
                note(f"forged RESULT not sent: {exc}")
        elif "flood" not in done and progress >= 0.7 and args.garbage:
            done.add("flood")
            note(f"flooding the broker with {args.garbage} malformed frames")
            # from a process of its own, as an attacker would (in a thread here it would hold this
            # process's GIL and slow the STATUS prober, not the broker)
            t = time.monotonic()
            subprocess.run([sys.executable, "-c", "import sys; from tests.bench.soak import _flood; "
                            f"_flood({endpoint!r}, {args.garbage}, {max(10.0, args.garbage / 5000)}, {args.seed})"],
                           cwd=str(Path(__file__).resolve().parents[2]), check=True)
            attacks["flood_s"] = time.monotonic() - t
            note(f"flood done in {attacks['flood_s']:.0f} s")
            faults["garbage frames"] += args.garbage

    def chaos():
        nonlocal broker
        next_kill = time.monotonic() + args.kill_every
        broker_done = cut_done = False
        attacked: set = set()
        while not stop.wait(1.0):
            if not args.no_attacks:
                try:
                    attack(sent[0] / len(events), attacked)
                except Exception as exc:  # noqa: BLE001 - a fault that cannot be staged must not stop the others
                    print(f"  attack failed to run: {type(exc).__name__}: {exc}", flush=True)
                    faults["attacks that could not run"] += 1
            with lock:
                # sample memory of the long-running processes (the broker and the current workers)
                rss["broker"].append(_rss_mb(broker.pid))
                for (s, stage), p in workers.items():
                    rss[f"{stage}"].append(_rss_mb(p.pid))
                progress = sent[0] / len(events)
                if not broker_done and progress >= 0.4:
                    restarts.append([time.time(), float("inf")])
                    broker.send_signal(signal.SIGKILL)
                    broker.wait()
                    time.sleep(1.0)
                    broker = st.spawn("broker", "broker")
                    broker_done = True
                    restarts[-1][1] = time.time() + 10.0  # start-up (journal replay) is not "serving"
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
                    workers[key] = st.spawn(key[1], "worker", key[1])
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
            evs, after, seqs = [], 0, []
            first_seq = c.since(0, 1)["first_seq"]
            while (r := c.since(after, 5000))["events"]:
                evs += [unpack(b) for _, b in r["events"]]
                seqs += [q for q, _ in r["events"]]
                after = r["events"][-1][0]
            end_status = c.status()
            parked_end = end_status["parked"]
    finally:
        stop.set()
        chaos_thread.join(120)
        prober.terminate()
        prober.wait(10)
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
    if not args.no_attacks:
        probes = _read_probes(base / "probes.jsonl", t0, [(a, b) for a, b in restarts])
        ok &= _check_attacks(evs, seqs, first_seq, end_status, probes, attacks)
    if mounted:
        subprocess.run(["umount", "-l", str(storage)], check=False)
    print("soak (with the attacks): PASS" if ok else "soak (with the attacks): FAIL")
    return 0 if ok else 1


def _check_attacks(evs, seqs, first_seq, status, probes, attacks) -> bool:
    """The issue-19 end checks: nothing forged got in, history intact, STATUS answered in time."""
    forged = [e for e in evs if e.get("forged")]
    gaps = [b for a, b in zip(seqs, seqs[1:]) if b != a + 1]
    serving = [p[1] for p in probes if not p[2]]
    answered = sorted(ms for ms in serving if ms is not None)
    silent = sum(ms is None for ms in serving)
    slow = [ms for ms in answered if ms > 100.0]
    q = (lambda f: answered[min(len(answered) - 1, int(f * len(answered)))]) if answered else (lambda f: float("nan"))
    summaries = [e for e in evs if e["type"] == "input.rejected" and e.get("refused")]
    print(f"  attacks: forged RESULT for {attacks['forged']}: {len(forged)} forged event(s) published; refused frames "
          f"{status.get('refused')}; {len(summaries)} refusal summary event(s); duplicates dropped "
          f"{status.get('duplicates_dropped')}")
    print(f"  catch-up history: first_seq {first_seq}, {len(seqs)} events, {len(gaps)} gap(s)")
    print(f"  STATUS probes (every 0.5 s, outside the broker restart): {len(serving)}; median {q(0.5):.1f} ms, "
          f"p99 {q(0.99):.1f} ms, max {answered[-1] if answered else float('nan'):.1f} ms; over 100 ms: {len(slow)}; "
          f"unanswered within 2 s: {silent}")
    late = [(round(p[0]), None if p[1] is None else round(p[1])) for p in probes if not p[2] and (p[1] is None or p[1] > 100)]
    if late:
        print(f"  late STATUS answers (station time s, ms; None = none within 2 s): {late[:40]}"
              f"{' ...' if len(late) > 40 else ''}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for line in _explain_late(probes)[:40]:
        print(line)
    late_p = [p for p in probes if not p[2] and p[1] is not None and p[1] > 100]
    broker_slow = sum(1 for p in late_p if p[3] and (p[3].get("worst_ms") or {}).get("stall", 0) > 100)
    broker_cpu = sum(1 for p in late_p if p[3] and (p[3].get("worst_ms") or {}).get("cpu", 0) > 50)
    prober = sum(1 for p in late_p if p[1] - p[4] <= 100)
    if late_p:
        print(f"  of the {len(late_p)} late answers: the broker's worst poll-loop iteration of the last 10 s was over "
              f"100 ms for {broker_slow} (over 50 ms of its own CPU: {broker_cpu}); the prober's own wait for a CPU "
              f"covers the excess over 100 ms for {prober}")
    loop = status.get("loop") or {}
    if loop:
        print(f"  broker poll loop since its restart (nice {status.get('nice')}): {loop['iterations']} iterations, "
              f"CPU {loop['cpu_s']:.1f} s, waiting for a CPU {loop['runqueue_s']:.1f} s, GC {loop['gc_s']:.2f} s")
    return not forged and first_seq == 1 and not gaps and not slow and not silent


def _explain_late(probes, limit_ms: float = 100.0) -> list[str]:
    """Why each late STATUS answer was late, from the broker's own account (STATUS ``loop``): its
    poll loop's CPU and run-queue wait since the previous probe, its worst iteration of the last
    seconds (CPU, waiting for a CPU, GC, other), and the prober's own wait for a CPU."""
    lines, prev = [], None
    for t, ms, restarting, loop, probe_rq in probes:
        if loop is not None and prev is not None and loop["iterations"] < prev["iterations"]:
            prev = None  # the broker restarted: its counters start again
        if not restarting and (ms is None or ms > limit_ms):
            if loop is None:
                lines.append(f"    [{t:5.0f} s] no answer within 2 s; the prober waited {probe_rq:.0f} ms for a CPU")
            else:
                w = loop.get("worst_ms") or {}
                d = (lambda k: (loop[k] - prev[k]) * 1e3) if prev else (lambda k: float("nan"))
                lines.append(f"    [{t:5.0f} s] {ms:.0f} ms: broker loop since the previous probe: CPU {d('cpu_s'):.0f} ms, "
                             f"waiting for a CPU {d('runqueue_s'):.0f} ms; worst iteration {w.get('stall', 0):.0f} ms "
                             f"(CPU {w.get('cpu', 0):.0f}, waiting for a CPU {w.get('runqueue', 0):.0f}, GC "
                             f"{w.get('gc', 0):.0f}, other {w.get('other', 0):.0f}); the prober waited {probe_rq:.0f} ms "
                             f"for a CPU")
        prev = loop or prev
    return lines


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
