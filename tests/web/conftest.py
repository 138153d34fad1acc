"""Fixtures of the web tests: a station configuration on free loopback ports, a broker in a thread."""

from __future__ import annotations

import threading

import pytest

from tests.conftest import free_port, wait_for  # noqa: F401  (re-exported to the tests here)

from common.config import load_config

TOKEN = "test-token-" + "0123456789abcdef"


def station_overrides(root, **extra) -> dict:
    """Config overrides for a throw-away station under ``root`` (loopback, free ports, quick timeouts)."""
    out = {
        "storage.root": str(root / "storage"),
        "broker.host": "127.0.0.1", "broker.bind": "127.0.0.1",
        "broker.port": free_port(), "broker.feed_port": free_port(),
        "broker.journal_dir": str(root / "journal"), "broker.heartbeat_interval_s": 0.2,
        "broker.max_attempts": 2,
        "client.timeout_s": 0.5, "client.retries": 1,
        "scanner.spool_dir": str(root / "bench"), "scanner.drain_interval_s": 0.3,
    }
    out.update(extra)
    return out


@pytest.fixture
def station_config(tmp_path):
    cfg = load_config(None, station_overrides(tmp_path))
    cfg["routing"]["noop.job"] = ["noop"]   # dotted event types cannot be given as --set keys
    return cfg


@pytest.fixture
def broker(station_config):
    """A real broker on loopback, in a thread, for the duration of one test."""
    from common.bus.broker import Broker

    stop = threading.Event()
    b = Broker(station_config)
    b.bind()
    t = threading.Thread(target=b.run, args=(stop,), daemon=True)
    t.start()
    yield b
    stop.set()
    t.join(10)


@pytest.fixture
def noop_worker(station_config, broker):
    """A worker of the no-op stage (``noop.job`` with ``fail = true`` fails, to park a job)."""
    from common.bus.worker import run_worker

    stop = threading.Event()
    t = threading.Thread(target=run_worker, args=("noop", station_config),
                         kwargs={"stop": stop, "install_signals": False}, daemon=True)
    t.start()
    yield
    stop.set()
    t.join(10)
