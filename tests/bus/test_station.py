"""tessera station: the one-command station, in demo mode and until Ctrl-C."""

from __future__ import annotations

import signal
import subprocess
import sys

import psutil
import pytest

from .conftest import REPO, wait_for

pytest.importorskip("common.synth")
pytest.importorskip("common.acquisition.capture")

FAST = ["--set", "scanner.colour_only=true", "--set", "scanner.prescan_dpi=25", "--set", "scanner.dpi=100",
        "--set", "scanner.wall_dpi=100", "--set", "scanner.seed=1", "--set", 'station.stages=["noop", "nosuchstage"]']


@pytest.fixture
def stations():
    """Station processes started by a test; interrupted (then killed) at its end, children included."""
    started = []
    yield started
    for p in started:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                for c in psutil.Process(p.pid).children(recursive=True):
                    c.kill()
                p.kill()


def _station(st, *args, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())",
                             "station", *args, "--config", str(st.config_path), *FAST],
                            cwd=st.root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


def test_station_demo_runs_every_stage_and_prints_a_summary(make_station, stations):
    st = make_station(routing={"fragment.ready": ["noop"]})
    p = _station(st, "--demo", "2")
    stations.append(p)
    out, _ = p.communicate(timeout=240)
    assert p.returncode == 0, out
    assert "stage nosuchstage skipped" in out
    lines = [line.split() for line in out.splitlines() if line.startswith("s1n8-")]
    assert len(lines) == 2 and all(cols[1:3] == ["1", "1"] for cols in lines), out  # scans, noop done
    assert "2 of 2 fragments captured; every stage done" in out


def test_station_runs_until_interrupted_and_stops_its_children(make_station, stations):
    st = make_station(routing={"fragment.ready": ["noop"]})
    p = _station(st, "--set", "scanner.fragments=1")
    stations.append(p)
    wait_for(lambda: _answers(st), 60, "the station's broker")
    children = psutil.Process(p.pid).children(recursive=True)
    assert len(children) >= 3  # broker, noop worker, scanner
    p.send_signal(signal.SIGTERM)  # as systemd stops it; Ctrl-C (SIGINT) takes the same path
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 130, out
    assert not [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]


def _answers(st) -> bool:
    try:
        return any(w["service"] == "noop" for ws in st.status()["workers"].values() for w in ws)
    except Exception:
        return False
