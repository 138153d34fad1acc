"""Real processes on loopback with free ports: a broker, workers, a scanner, as the station runs them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import free_port, wait_for  # noqa: F401  (re-exported to the tests here)

from common.bus.client import BrokerClient
from common.bus.feed import FeedSubscriber
from common.config import load_config

REPO = Path(__file__).resolve().parents[2]
HEARTBEAT_S = 0.2


class Station:
    """A throw-away station: config file, storage, journal, and its child processes."""

    def __init__(self, root: Path, *, services: dict | None = None, routing: dict | None = None, extra: str = ""):
        self.root = root
        port, feed = free_port(), free_port()
        routing = routing or {"noop.job": ["noop"], "fragment.ready": ["noop"]}
        lines = [
            "[storage]", f'root = "{root / "storage"}"',
            "[broker]", 'host = "127.0.0.1"', 'bind = "127.0.0.1"', f"port = {port}", f"feed_port = {feed}",
            f'journal_dir = "{root / "journal"}"', f"heartbeat_interval_s = {HEARTBEAT_S}", "heartbeat_liveness = 3",
            "max_attempts = 3", "compact_interval_s = 0.5",
            "[worker]", "reconnect_min_s = 0.1", "reconnect_max_s = 0.5", "shutdown_grace_s = 5.0",
            "[client]", "timeout_s = 1.0", "retries = 2",
            "[routing]", *[f'"{k}" = {list(v)!r}'.replace("'", '"') for k, v in routing.items()],
            "[scanner]", f'spool_dir = "{root / "bench"}"', "drain_interval_s = 0.3",
        ]
        for name, settings in (services or {}).items():
            lines.append(f"[services.{name}]")
            lines += [f"{k} = {str(v).lower() if isinstance(v, bool) else v!r}" for k, v in settings.items()]
        self.config_path = root / "station.toml"
        self.config_path.write_text("\n".join(lines) + "\n" + extra)
        self.config = load_config(self.config_path)
        self.procs: list[subprocess.Popen] = []
        self._n = 0

    def spawn(self, *args: str) -> subprocess.Popen:
        self._n += 1
        log = open(self.root / f"proc{self._n}-{args[0]}.log", "wb")
        env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
        p = subprocess.Popen([sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())",
                              *args, "--config", str(self.config_path)], stdout=log, stderr=subprocess.STDOUT,
                             cwd=self.root, env=env)
        p.log_path = log.name
        self.procs.append(p)
        return p

    def broker(self) -> subprocess.Popen:
        p = self.spawn("broker")
        with self.client() as c:  # ready when it answers
            wait_for(lambda: _answers(c), 20, "the broker to answer")
        return p

    def worker(self, service: str = "noop") -> subprocess.Popen:
        return self.spawn("worker", service)

    def client(self) -> BrokerClient:
        return BrokerClient.from_config(self.config)

    def subscriber(self, since=0, **kw) -> FeedSubscriber:
        return FeedSubscriber.from_config(self.config, since=since, **kw)

    def status(self) -> dict:
        with self.client() as c:
            return c.status()

    def workers_ready(self, n: int, service: str = "noop", timeout: float = 20):
        def count():
            try:
                s = self.status()
            except Exception:
                return False
            return sum(w["service"] == service for ws in s["workers"].values() for w in ws) >= n
        wait_for(count, timeout, f"{n} {service} worker(s)")

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)

    def logs(self) -> str:
        return "\n".join(f"--- {p.args[3:5]} ---\n" + Path(p.log_path).read_text(errors="replace")[-3000:]
                         for p in self.procs)


def _answers(c: BrokerClient) -> bool:
    try:
        c.status()
        return True
    except Exception:
        return False


@pytest.fixture
def make_station(tmp_path):
    """Factory of stations; every process started is stopped at the end of the test."""
    made = []

    def make(**kw) -> Station:
        st = Station(_mk(tmp_path / f"s{len(made)}"), **kw)
        made.append(st)
        return st

    yield make
    for st in made:
        st.stop()


def _mk(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


def collect(sub: FeedSubscriber, predicate, timeout: float, what: str) -> list:
    """Read events from ``sub`` until ``predicate(events)`` holds; fail after ``timeout``."""
    events = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        item = sub.next(0.2)
        if item is not None:
            events.append(item)
        if predicate(events):
            return events
    raise AssertionError(f"timed out after {timeout} s waiting for {what}; got {[(s, e['type']) for s, e in events]}")
