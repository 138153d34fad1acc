"""tessera station — the whole station on this machine: broker, scanner, one worker per stage.

Children are separate processes (as on a real station, where they may live on other hosts):
the broker, one worker for each stage listed in ``[station] stages`` whose module exists (a
missing one is skipped with a log line), and the scanner on the simulated flatbed. Logs go to
``<storage>/logs/``. ``--no-scanner`` leaves the scanner out (fragments then come by ``tessera import``, or
from ``tessera scanner`` at the bench); the pages are ``tessera web``. ``--demo N`` captures N synthetic fragments, waits until the station is
idle (every stage's output exists or the failure is parked), prints a per-fragment summary and
exits 0 if every fragment went through every stage, else 1. Without ``--demo`` it runs until
Ctrl-C and then stops every child cleanly (SIGTERM, then SIGKILL after a grace period).

A child that dies (a worker, or the broker) is started again after a back-off that doubles
with each death in the last ``CRASH_WINDOW_S`` (``RESTART_MIN_S`` up to ``RESTART_MAX_S``); the
station goes on meanwhile (the broker re-queues a dead worker's job; its journal makes a broker
restart lose nothing). ``CRASH_LOOP_DEATHS`` deaths within the window is a crash loop: reported
on the terminal and in the log at every restart, never hidden; the demo's summary lists it and
fails. The scanner is not restarted (it ends when its capture is done).
"""

from __future__ import annotations

import collections
import importlib.util
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from common.config import add_config_arguments, config_from_arguments

log = logging.getLogger("tessera.station")

# stage -> event type of its output (what the demo waits for per fragment)
OUTPUT_EVENT = {"solver": "rgbn.ready", "features": "features.ready", "renderer": "render.ready",
                "matcher": "match.proposed", "noop": "noop.done"}
_LAUNCH = "import sys; from services.cli import main; sys.exit(main())"

# supervision of the children (restart with back-off, crash-loop report)
RESTART_MIN_S = 1.0
RESTART_MAX_S = 60.0
CRASH_WINDOW_S = 300.0
CRASH_LOOP_DEATHS = 5


def add_parser(sub) -> None:
    p = sub.add_parser("station", help="run broker, scanner and one worker per stage on this machine",
                       description=__doc__.split("\n\n")[0] + " The pages are `tessera web`.")
    p.add_argument("--demo", type=int, metavar="N", default=None,
                   help="capture N synthetic fragments, wait for every stage, print a summary, exit 0/1")
    p.add_argument("--no-scanner", action="store_true",
                   help="broker and stage workers only: no capture (for fragments that come by `tessera import`, "
                        "or a scanner run at the bench with `tessera scanner`)")
    add_config_arguments(p)
    p.set_defaults(func=run)


class Children:
    """The station's child processes, started and stopped together."""

    def __init__(self, config_args: list[str], log_dir: Path, env: dict | None = None):
        self.config_args = config_args
        self.log_dir = log_dir
        self.env = env  # None: this process's environment
        self.procs: dict[str, subprocess.Popen] = {}
        self.args: dict[str, tuple] = {}
        self.deaths: dict[str, collections.deque] = collections.defaultdict(collections.deque)
        self.restart_at: dict[str, float] = {}
        self.crash_loops: set[str] = set()
        self.restarts: collections.Counter = collections.Counter()

    def command(self, *args: str) -> list[str]:
        """The command line of a child running ``tessera <args>`` with the station's config."""
        return [sys.executable, "-c", _LAUNCH, *args, *self.config_args]

    def start(self, name: str, *args: str, to_terminal: bool = False, cpu: int | None = None) -> subprocess.Popen:
        """Start ``tessera <args>`` as child ``name`` (log ``<log_dir>/<name>.log``); ``cpu``: pin it
        to that core (``tessera perf`` measures one worker set per core)."""
        out = None if to_terminal else open(self.log_dir / f"{name}.log", "ab")
        pin = None if cpu is None else (lambda: os.sched_setaffinity(0, {cpu}))
        p = subprocess.Popen(self.command(*args), stdout=out, stderr=subprocess.STDOUT if out else None,
                             start_new_session=True, env=self.env, preexec_fn=pin)
        if out is not None:
            out.close()  # the child holds its own descriptor
        self.procs[name] = p
        self.args[name] = (args, to_terminal, cpu)
        log.info("started %s (pid %d)%s", name, p.pid, "" if to_terminal else f", log {self.log_dir / (name + '.log')}")
        return p

    def supervise(self, now: float | None = None, out=None) -> None:
        """Restart dead children (not the scanner) with back-off; report crash loops. Call it often."""
        now = time.monotonic() if now is None else now
        out = out or sys.stdout
        for name, p in list(self.procs.items()):
            if name == "scanner" or p.poll() is None:
                continue
            if name not in self.restart_at:
                deaths = self.deaths[name]
                deaths.append(now)
                while deaths and deaths[0] < now - CRASH_WINDOW_S:
                    deaths.popleft()
                wait = min(RESTART_MAX_S, RESTART_MIN_S * 2 ** (len(deaths) - 1))
                self.restart_at[name] = now + wait
                msg = (f"{name} exited with status {p.returncode}; restarting it in {wait:.0f} s "
                       f"(log {self.log_dir / (name + '.log')})")
                if len(deaths) >= CRASH_LOOP_DEATHS:
                    self.crash_loops.add(name)
                    msg = (f"CRASH LOOP: {name} died {len(deaths)} times in the last {CRASH_WINDOW_S:.0f} s "
                           f"(status {p.returncode}); restarting it in {wait:.0f} s; see {self.log_dir / (name + '.log')}")
                log.error("%s", msg)
                print(f"station: {msg}", file=out, flush=True)
            elif now >= self.restart_at[name]:
                del self.restart_at[name]
                args, to_terminal, cpu = self.args[name]
                self.start(name, *args, to_terminal=to_terminal, cpu=cpu)
                self.restarts[name] += 1

    def stop(self, grace_s: float = 10.0) -> None:
        order = [n for n in self.procs if n not in ("broker",)] + [n for n in self.procs if n == "broker"]
        for group in (order[:-1], order[-1:]):  # workers and scanner first, the broker last
            for n in group:
                if self.procs[n].poll() is None:
                    self.procs[n].send_signal(signal.SIGTERM)
            deadline = time.monotonic() + grace_s
            for n in group:
                p = self.procs[n]
                try:
                    p.wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop in %.0f s: killing it", n, grace_s)
                    p.kill()
                    p.wait(5)


def _port_free(bind: str, port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("" if bind == "*" else bind, port))
            return True
        except OSError:
            return False


def _stage_present(name: str) -> bool:
    try:
        return importlib.util.find_spec(f"services.{name}") is not None
    except ImportError:
        return False


def _config_args(args) -> list[str]:
    out = ["--config", args.config] if args.config else []
    for item in args.set or []:
        out += ["--set", item]
    return out


def run(args) -> int:
    from common.bus.client import BrokerClient
    config = config_from_arguments(args)
    root = Path(config["storage"]["root"])
    log_dir = root / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    kids = Children(_config_args(args), log_dir)
    stages = []
    for name in config["station"]["stages"]:
        if _stage_present(name):
            stages.append(name)
        else:
            log.warning("stage %s skipped: services/%s.py is not part of this build", name, name)
    busy = [k for k in ("port", "feed_port") if not _port_free(config["broker"]["bind"], config["broker"][k])]
    if busy:
        print("error: " + ", ".join(f"broker.{k} {config['broker'][k]}" for k in busy) + " already in use on this "
              "machine (another station?). Stop it, or choose free ports, e.g. "
              "--set broker.port=5565 --set broker.feed_port=5566")
        return 1
    status = 0
    drainer = None

    def interrupt(*_):  # systemd and kill send SIGTERM: stop the children as for Ctrl-C
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, interrupt)
    try:
        broker = kids.start("broker", "broker")
        with BrokerClient.from_config(config, timeout_s=0.5, retries=1) as bus:
            deadline = time.monotonic() + 20
            while True:
                try:
                    if bus.status()["pid"] != broker.pid:  # somebody else's broker answers on our port
                        print(f"error: another broker answers on port {config['broker']['port']}; stopping")
                        return 1
                    break
                except (KeyError, TypeError, OSError, RuntimeError):
                    if broker.poll() is not None or time.monotonic() > deadline:
                        tail = (log_dir / "broker.log").read_text(errors="replace")[-1500:]
                        print(f"error: the broker did not start (is another station using port "
                              f"{config['broker']['port']}?)\n{tail}")
                        return 1
            for name in stages:
                kids.start(name, "worker", name)
            drainer = _drain_outbox(config)
            if args.no_scanner and args.demo is None:
                log.info("no scanner: fragments come by `tessera import` or `tessera scanner` at the bench")
            elif config["scanner"]["device"] != "simulated" and args.demo is None:
                log.info("scanner device is %s: run `tessera scanner` at the bench", config["scanner"]["device"])
            else:
                if args.demo is None:   # said before it happens: these fragments join whatever the storage holds
                    print(f"the simulated scanner captures {config['scanner']['fragments']} synthetic fragment(s) "
                          f"into {root.resolve()} ([scanner] fragments; --no-scanner for none)", flush=True)
                count = args.demo if args.demo is not None else config["scanner"]["fragments"]
                kids.start("scanner", "scanner", "--count", str(count), to_terminal=True)
            if args.demo is None:
                print(f"station running (storage {root.resolve()}); `tessera status` and `tessera events` "
                      f"show what it does; Ctrl-C stops it", flush=True)
                while True:
                    time.sleep(0.5)
                    kids.supervise()
            status = _demo(config, kids, stages, args.demo)
    except KeyboardInterrupt:
        print("stopping the station", flush=True)
        status = 130
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the orderly stop short
        if drainer is not None:
            drainer.stop.set()
            drainer.wake.set()
            drainer.join(5)
            drainer.outbox.close()
        kids.stop()
    return status


def _drain_outbox(config):
    """Deliver this machine's outbox while the station runs (a started ``services.scanner.Drainer``).

    ``tessera import`` and the scanner put their events there first; what could not go out then (the
    station was down) would otherwise wait for the next import or capture, and a station run with
    ``--no-scanner`` — the one for imported fragments — has no scanner to send it. The scanner child
    drains the same outbox; an event sent twice is dropped by the broker (de-duplicated by uid)."""
    from common.bus.outbox import Outbox
    from common.store import Store
    from services.scanner import Drainer
    outbox = Outbox(config["scanner"]["spool_dir"])
    if len(outbox):
        print(f"{len(outbox)} event(s) from imports or captures made while the station was down wait in "
              f"{outbox.dir}; delivering them", flush=True)
    drainer = Drainer(config, outbox, Store.from_config(config))
    drainer.start()
    return drainer


def _demo(config, kids: Children, stages: list[str], n: int) -> int:
    """Follow the feed until the station is idle; print the per-fragment summary; 0 if all went through."""
    from common.bus.client import BrokerClient
    from common.bus.feed import FeedSubscriber
    seen: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    failures: dict[str, list[str]] = collections.defaultdict(list)
    deadline = time.monotonic() + float(config["station"]["demo_timeout_s"])
    idle_since = None
    timed_out = False
    with FeedSubscriber.from_config(config, since=0) as feed, BrokerClient.from_config(config) as bus:
        while time.monotonic() < deadline:
            kids.supervise()
            item = feed.next(0.5)
            if item is not None:
                _, ev = item
                frag = ev.get("fragment")
                if frag is None:
                    continue
                seen[frag][ev["type"]] += 1
                if ev["type"] in ("stage.failed", "input.rejected"):
                    failures[frag].append(f"{ev.get('service', '?')}: {ev.get('error', '')}")
                idle_since = None
                continue
            scanner = kids.procs.get("scanner")
            if scanner is not None and scanner.poll() is None:
                continue
            s = bus.status()
            busy = s["in_flight"] or any(s["queues"].get(x, 0) for x in stages)
            if busy:
                idle_since = None
            elif idle_since is None:
                idle_since = time.monotonic()
            elif time.monotonic() - idle_since > 2 * float(config["broker"]["heartbeat_interval_s"]):
                break
        else:
            print("demo timed out before the station became idle")
            timed_out = True
        parked = {p["fragment"]: p for p in bus.status()["parked"]}
    scanner = kids.procs.get("scanner")
    if scanner is not None and scanner.returncode:
        print(f"the scanner exited with status {scanner.returncode} (its output is above)")
    frags = sorted(f for f in seen if seen[f]["fragment.ready"])
    cols = [("scans", "fragment.ready")] + [(s, OUTPUT_EVENT.get(s, f"{s}.ready")) for s in stages]
    print()
    print(f"{'fragment':<20}" + "".join(f"{c:>10}" for c, _ in cols) + "  failures")
    ok = len(frags) == n
    for f in frags:
        row = [seen[f][etype] for _, etype in cols]
        required = [c for c, _ in cols if c != "matcher"]  # no proposal is a valid outcome for one fragment
        complete = all(seen[f][etype] for c, etype in cols if c in required)
        ok &= complete and not failures[f]
        note = "; ".join(failures[f]) or (parked[f]["error"] if f in parked else "")
        print(f"{f:<20}" + "".join(f"{v:>10}" for v in row) + f"  {note}")
    print("(events per stage: one per face from solver, features and renderer; from the matcher one per join "
          "proposal, and again once docked where the docking changed it)")
    for name in sorted(kids.restarts):
        print(f"{name} was restarted {kids.restarts[name]} time(s)"
              f"{' (CRASH LOOP)' if name in kids.crash_loops else ''}; see its log in {Path(config['storage']['root']) / 'logs'}")
    ok &= not kids.crash_loops
    print(f"\n{len(frags)} of {n} fragments captured; "
          f"{'every stage done' if ok else 'some stages missing or failed'}; storage {Path(config['storage']['root']).resolve()}")
    return 0 if ok and not timed_out else 1
