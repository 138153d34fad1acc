"""tessera perf — measure the station on this machine and write docs/performance.md.

What it measures (real processes, the real stages, synthetic fragments from the simulated flatbed):

1. **per-stage latency** with one fragment alone in the station (no queueing: service time plus
   bus overhead) — solver, features, renderer, matcher;
2. **throughput**: ``--fragments N`` submitted at once to a station with one worker per stage, all
   pinned to core 0 (``os.sched_setaffinity`` in the child), then with two workers per stage,
   one set per core; fragments per hour end to end, per-fragment end-to-end time, per-stage
   latency under load;
3. **matching cost vs number of fragments**: the matcher stage's ``handle`` timed in-process as
   the k-th fragment's features arrive (k = 1..``--match-fragments``).

Scans are captured once (simulated flatbed, ``[scanner]`` dpi) and copied into a fresh storage root
for every run, so no run finds another's content-keyed outputs.
"""

from __future__ import annotations

import collections
import os
import platform
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

from common.config import add_config_arguments, config_from_arguments
from common.messages import to_json

REPO = Path(__file__).resolve().parents[2]
#: heading of the soak's section of docs/performance.md, kept when the report is rewritten
SOAK_SECTION = "## Soak with faults"


def add_parser(sub) -> None:
    p = sub.add_parser("perf", help="measure throughput, latency, scaling and matching cost; write docs/performance.md")
    p.add_argument("--fragments", type=int, default=24, help="fragments per throughput run (default 24)")
    p.add_argument("--match-fragments", type=int, default=40, help="fragments for the matching-cost curve (default 40)")
    p.add_argument("--output", default=str(REPO / "docs" / "performance.md"), help="report path")
    p.add_argument("--keep", action="store_true", help="keep the temporary station directories")
    add_config_arguments(p)
    p.set_defaults(func=run)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _capture(config, root: Path, n: int) -> tuple[list[dict], float]:
    """Capture n synthetic fragments into ``root`` (plus a calibration); fragment.ready events, s/fragment.

    As a bench operator would, pieces the capture refuses (larger than the bed; a pre-scan that
    shows no or several objects, e.g. a sliver lying beside its fragment) are put aside and
    counted, not scanned.
    """
    from common.acquisition.calibration import calibrate_scanner, save_calibration, simulated_target_operator
    from common.acquisition.capture import capture_fragment, simulated_operator, write_scans
    from common.acquisition.errors import CaptureError
    from common.acquisition.flatbed_sim import SimulatedFlatbed
    from common.messages import new_message
    from common.store import Store
    from services.scanner import fragments
    sc = config["scanner"]
    store = Store(root)
    sim = SimulatedFlatbed("sim", seed=int(sc["seed"]))
    save_calibration(store, calibrate_scanner(sim, simulated_target_operator(sim), area_mm=(50, 50, 70, 70)))
    events, t0 = [], time.perf_counter()
    refused = collections.Counter()
    for fid, surface in fragments(config, 2 * n):
        if len(events) == n:
            break
        try:
            sim.place(surface)
            res = capture_fragment(sim, fid, operator=simulated_operator(sim), dpi=sc["dpi"],
                                   prescan_dpi=sc["prescan_dpi"], depth=sc["depth"], margin_mm=sc["margin_mm"])
        except (ValueError, CaptureError) as exc:
            refused[type(exc).__name__] += 1
            print(f"  {fid} put aside: {exc}", flush=True)
            continue
        ref = write_scans(store, fid, res)
        events.append(new_message("fragment.ready", fragment=fid, artifact=ref, device=res.device))
    if len(events) < n:
        raise RuntimeError(f"only {len(events)} of {n} synthetic fragments could be captured ({dict(refused)})")
    if refused:
        print(f"  {sum(refused.values())} piece(s) put aside: {dict(refused)}", flush=True)
    return events, (time.perf_counter() - t0) / max(1, n)


class _Station:
    """Broker + workers over loopback, storage in its own directory; the processes are
    :class:`services.cli.station.Children` (the station's own spawner), pinned per core."""

    def __init__(self, base: Path, source: Path, name: str):
        from services.cli.station import Children
        self.dir = base / name
        shutil.copytree(source, self.dir / "storage")
        port, feed = _free_port(), _free_port()
        self.config_path = self.dir / "station.toml"
        self.config_path.write_text("\n".join([
            "[storage]", f'root = "{self.dir / "storage"}"',
            "[broker]", 'host = "127.0.0.1"', 'bind = "127.0.0.1"', f"port = {port}", f"feed_port = {feed}",
            f'journal_dir = "{self.dir / "journal"}"', "heartbeat_interval_s = 0.5", "heartbeat_liveness = 10",
            "[client]", "timeout_s = 5.0", "retries = 3"]) + "\n")
        from common.config import load_config
        self.config = load_config(self.config_path)
        self.children = Children(["--config", str(self.config_path)], self.dir,
                                 env=dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1"))
        #: child name -> what its peak memory is reported under (the stage, or "broker")
        self.roles: dict[str, str] = {}

    def spawn(self, role: str, *args: str, cpu: int | None = None) -> subprocess.Popen:
        """Start ``tessera <args>``, its memory reported under ``role``; returns the process."""
        name = f"{role}-{len(self.roles)}"
        self.roles[name] = role
        return self.children.start(name, *args, cpu=cpu)

    def stop(self) -> None:
        self.children.stop(grace_s=20.0)


def _rss_mb(pid: int) -> float:
    """Resident memory of a process in MiB (NaN once it has gone)."""
    try:
        return psutil.Process(pid).memory_info().rss / 2**20
    except psutil.Error:
        return float("nan")


def _pipeline_run(base: Path, source: Path, name: str, events: list[dict], sets: list[int | None],
                  warmup: dict | None = None, timeout_s: float = 1800) -> dict:
    """Run the station with one worker per stage per entry of ``sets`` (the CPU it is pinned to).

    ``warmup`` (a fragment.ready) goes through first and is waited for, so start-up costs (imports,
    the matcher's bootstrap model) are not counted in the timed run.
    """
    from common.bus.client import BrokerClient
    from common.messages import unpack
    st = _Station(base, source, name)
    try:
        st.spawn("broker", "broker", cpu=sets[0])
        stages = ("solver", "features", "renderer", "matcher")
        for cpu in sets:
            for stage in stages:
                st.spawn(stage, "worker", stage, cpu=cpu)
        with BrokerClient.from_config(st.config) as c:
            deadline = time.monotonic() + 60
            while True:
                try:
                    s = c.status()
                    if sum(len(v) for v in s["workers"].values()) >= len(sets) * len(stages):
                        break
                except Exception:
                    pass
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{name}: workers did not come up; logs in {st.dir}")
                time.sleep(0.3)
            def idle(need):
                s = c.status()
                return s["completed"] + len(s["parked"]) >= need and not s["in_flight"] and not any(s["queues"].values())
            per_fragment = 1 + 2 * 3  # solver, then per face features + renderer + matcher
            done_before = 0
            if warmup is not None:
                c.submit(warmup)
                while not idle(per_fragment):
                    if time.monotonic() > deadline + timeout_s:
                        raise RuntimeError(f"{name}: warm-up fragment not done; logs in {st.dir}")
                    time.sleep(0.3)
                done_before = per_fragment
            need = done_before + len(events) * per_fragment
            t_submit = time.time()
            c.submit_many(events)
            peak_rss = collections.defaultdict(float)
            while True:
                s = c.status()
                if s["completed"] + len(s["parked"]) >= need and not s["in_flight"] and not any(s["queues"].values()):
                    break
                for child, p in st.children.procs.items():
                    role = st.roles[child]
                    peak_rss[role] = max(peak_rss[role], _rss_mb(p.pid))
                if time.time() - t_submit > timeout_s:
                    raise RuntimeError(f"{name}: not done after {timeout_s} s; logs in {st.dir}")
                time.sleep(0.5)
            t_done = time.time()
            parked = s["parked"]
            evs, after = [], 0
            while (r := c.since(after, 5000))["events"]:
                evs += [unpack(b) for _, b in r["events"]]
                after = r["events"][-1][0]
    finally:
        st.stop()
    timed = {e["fragment"] for e in events}
    return _analyse([e for e in evs if e.get("fragment") in timed], t_submit, t_done, parked, dict(peak_rss))


def _analyse(evs: list[dict], t_submit: float, t_done: float, parked: list, peak_rss: dict) -> dict:
    # a fragment.ready was made at capture, before the run: its job starts at submission
    ready = {e["fragment"]: max(e["time"], t_submit) for e in evs if e["type"] == "fragment.ready"}
    rgbn = {(e["fragment"], e["face"]): e["time"] for e in evs if e["type"] == "rgbn.ready"}
    lat = collections.defaultdict(list)
    last = collections.defaultdict(float)
    for e in evs:
        f = e.get("fragment")
        if f not in ready:
            continue
        last[f] = max(last[f], e["time"])
        if e["type"] == "rgbn.ready":
            lat["solver"].append(e["time"] - ready[f])
        elif e["type"] in ("features.ready", "render.ready") and (f, e.get("face")) in rgbn:
            lat["features" if e["type"] == "features.ready" else "renderer"].append(e["time"] - rgbn[(f, e["face"])])
    e2e = [last[f] - ready[f] for f in ready]
    n = len(ready)
    makespan = t_done - t_submit
    return {"fragments": n, "makespan_s": makespan, "per_hour": 3600 * n / makespan if makespan > 0 else float("nan"),
            "e2e": e2e, "latency": {k: v for k, v in lat.items()}, "parked": len(parked), "peak_rss_mb": peak_rss,
            "stage_counts": collections.Counter(e["type"] for e in evs)}


def _matching_curve(config, base: Path, n: int) -> list[tuple[int, float, int]]:
    """Time the matcher stage's handle as the k-th front face arrives (k = 1..n)."""
    import logging
    from common.bus.worker import StageContext
    from common.features import extract_features, save_features
    from common.messages import new_message
    from common.store import Store
    from common.synth import generate_wall
    import services.matcher as matcher
    store = Store(base / "matching")
    wall = generate_wall(n, int(config["scanner"]["seed"]) + 101, dpi=float(config["scanner"]["wall_dpi"]))
    refs = []
    for frag in wall.fragments[:n]:
        table = extract_features(frag.rgbn, face="front")
        refs.append((frag.id, save_features(store, f"fragments/{frag.id}/features/front-perf.h5", table)))
    ctx = StageContext(store=store, config={}, log=logging.getLogger("tessera.matcher"), progress=lambda f, t: None)
    out = []
    for k, (fid, ref) in enumerate(refs, 1):
        job = new_message("features.ready", fragment=fid, face="front", artifact=ref)
        t0 = time.perf_counter()
        proposed = matcher.handle(job, ctx)
        out.append((k, time.perf_counter() - t0, len(proposed)))
    return out


def _fmt_lat(values: list[float]) -> str:
    if not values:
        return "–"
    return f"{statistics.median(values):.1f} s (max {max(values):.1f} s, n={len(values)})"


def _report(args, config, capture_s, single, one, two, curve, started: float) -> str:
    cpu = "unknown CPU"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    load = os.getloadavg()
    lines = [
        "# Performance on this machine",
        "",
        f"Written by `tessera perf --fragments {args.fragments} --match-fragments {args.match_fragments}` on "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime(started))} — {os.cpu_count()} cores ({cpu}), "
        f"Python {platform.python_version()}; load average at the end {load[0]:.1f}/{load[1]:.1f}/{load[2]:.1f} "
        "(other work was running on the machine: treat the figures as lower bounds).",
        f"Synthetic fresco fragments from the simulated flatbed at {config['scanner']['dpi']} dpi, both faces, "
        "4 rotation scans each; every stage (solver, features, renderer, matcher) in its own process over the bus. "
        "Each station is timed after one warm-up fragment (imports, the matcher's bootstrap model); all fragments "
        "of a run are submitted at once.",
        "",
        "## End to end",
        "",
        "| station | workers | fragments | makespan | fragments per hour | end-to-end per fragment (median, max) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for label, r, w in (("1 worker per stage, all on core 0", one, "4"), ("2 workers per stage, one set per core", two, "8")):
        if r is None:
            continue
        lines.append(f"| {label} | {w} | {r['fragments']} | {r['makespan_s']:.0f} s | **{r['per_hour']:.0f}** | "
                     f"{statistics.median(r['e2e']):.0f} s, {max(r['e2e']):.0f} s |")
    if one and two:
        lines += ["", f"Scaling 1 → 2 workers per stage (one per core): throughput × {two['per_hour'] / one['per_hour']:.2f}. "
                  "With 2 cores the second set can at best double it; when other processes use the cores (load "
                  "average above) the gain shrinks, so read this as a lower bound."]
    lines += ["", f"The simulated bench captured a fragment (8 scans) in {capture_s:.1f} s here; a real bench "
              "scans about 20 fragments an hour, so one station of this size keeps up with "
              f"{(two or one)['per_hour'] / 20:.1f} benches.",
              "", "## Per stage", "",
              "Latency = output event time − input event time (queueing included). *Alone*: one fragment in an idle "
              "station (≈ service time). *Under load*: the throughput runs above.", "",
              "| stage | alone | under load, 1 worker per stage | under load, 2 per stage | throughput alone (jobs/h) |",
              "| --- | --- | --- | --- | --- |"]
    for stage in ("solver", "features", "renderer"):
        alone = single["latency"].get(stage, []) if single else []
        thr = f"{3600 / statistics.median(alone):.0f}" if alone else "–"
        lines.append(f"| {stage} | {_fmt_lat(alone)} | {_fmt_lat(one['latency'].get(stage, []) if one else [])} | "
                     f"{_fmt_lat(two['latency'].get(stage, []) if two else [])} | {thr} |")
    lines += ["", "The matcher is not in this table: it answers a front face only with proposals (none is a valid "
              "answer), so the feed cannot time every job; its cost is the curve below, and it is inside the "
              "end-to-end figures (including its first job in each fresh station, which fits the bootstrap model).", ""]
    if one or two:
        rss = (two or one)["peak_rss_mb"]
        lines += ["Peak resident memory during the throughput run (MB): " +
                  ", ".join(f"{k} {v:.0f}" for k, v in sorted(rss.items())) + ".", ""]
    lines += ["## Matching cost vs number of fragments", "",
              "The matcher stage (`services/matcher.py` `handle`, in-process) timed as the k-th fragment's front-face "
              "features arrive: it indexes the new fragment and proposes its joins against the k − 1 already there.", "",
              "| fragments in the index (k) | time for the k-th fragment | proposals it returned |", "| --- | --- | --- |"]
    picks = sorted({k for k in (1, 2, 5, 10, 20, 30, 40, 60, 80, 100) if k <= len(curve)} | {len(curve)})
    for k in picks:
        lines.append(f"| {k} | {curve[k - 1][1]:.3f} s | {curve[k - 1][2]} |")
    if len(curve) >= 10:
        import numpy as np
        ks = np.array([c[0] for c in curve[1:]], float)
        ts = np.array([c[1] for c in curve[1:]], float)
        slope, icpt = np.polyfit(ks, ts, 1)
        lines += ["", f"Least-squares line over k = 2..{len(curve)}: {icpt:.3f} s + {1000 * slope:.2f} ms × k; "
                  f"total for all {len(curve)}: {sum(c[1] for c in curve):.1f} s (the first call also fits the "
                  "bootstrap model)."]
    lines += ["", "Regenerate: `tessera perf` (about 5–10 minutes; it starts its own stations on free loopback ports).", ""]
    return "\n".join(lines)


def run(args) -> int:
    config = config_from_arguments(args)
    if args.fragments < 1 or args.match_fragments < 2:
        print("error: --fragments must be >= 1 and --match-fragments >= 2", file=sys.stderr)
        return 2
    started = time.time()
    base = Path(tempfile.mkdtemp(prefix="tessera-perf-"))
    try:
        print(f"capturing {args.fragments} synthetic fragments ...", flush=True)
        events, capture_s = _capture(config, base / "source", args.fragments + 1)
        warm, events = events[:1], events[1:]  # a warm-up fragment goes first through every station
        cpus = sorted(os.sched_getaffinity(0))
        c0, c1 = cpus[0], cpus[1 % len(cpus)]
        print("one fragment alone ...", flush=True)
        single = _pipeline_run(base, base / "source", "single", events[:1], [c0], warmup=warm[0])
        print(f"{args.fragments} fragments, 1 worker per stage on core {c0} ...", flush=True)
        one = _pipeline_run(base, base / "source", "one", events, [c0], warmup=warm[0])
        print(f"{args.fragments} fragments, 2 workers per stage on cores {c0} and {c1} ...", flush=True)
        two = _pipeline_run(base, base / "source", "two", events, [c0, c1], warmup=warm[0])
        print(f"matching cost for 1..{args.match_fragments} fragments ...", flush=True)
        curve = _matching_curve(config, base, args.match_fragments)
        text = _report(args, config, capture_s, single, one, two, curve, started)
        out = Path(args.output)
        out.parent.mkdir(parents=True, exist_ok=True)
        if out.exists() and SOAK_SECTION in out.read_text():
            # the soak (tests/bench/soak.py) writes its own section: keep it
            old = out.read_text()
            text = text.rstrip("\n") + "\n\n" + old[old.index(SOAK_SECTION):]
        out.write_text(text)
        print(text)
        print(to_json({"per_hour_1": one["per_hour"], "per_hour_2": two["per_hour"],
                          "parked": [single["parked"], one["parked"], two["parked"]]}), flush=True)
        return 0
    finally:
        if not args.keep:
            shutil.rmtree(base, ignore_errors=True)
