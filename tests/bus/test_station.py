"""tessera station: the one-command station, in demo mode and until Ctrl-C."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import psutil
import pytest

from .conftest import REPO, collect, wait_for

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


def test_station_without_a_scanner_captures_nothing(make_station, stations):
    """A lab importing its own pictures runs the stages alone: with the simulated scanner, `tessera station`
    captured [scanner] fragments synthetic fragments into the lab's storage, beside the real ones."""
    st = make_station(routing={"fragment.ready": ["noop"]})
    p = _station(st, "--no-scanner", "--set", "scanner.fragments=1")
    stations.append(p)
    wait_for(lambda: _answers(st), 60, "the station's broker")
    children = [" ".join(c.cmdline()) for c in psutil.Process(p.pid).children(recursive=True)]
    assert children and not [c for c in children if " scanner " in f"{c} "], children   # broker and worker only
    p.send_signal(signal.SIGTERM)
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 130, out
    fragments = st.root / "storage" / "fragments"
    assert not fragments.exists() or not any(fragments.iterdir())


def test_station_delivers_what_waited_in_the_outbox(make_station, stations):
    """Pictures imported while the station was down leave their events in this machine's outbox; the
    station run for imported fragments (--no-scanner) has no scanner to send them, so it sends them itself."""
    from common.bus.outbox import Outbox
    from common.messages import new_message
    st = make_station(routing={"noop.job": ["noop"]})
    box = Outbox(st.root / "bench")                     # [scanner] spool_dir of this station
    for i in range(2):
        box.put(new_message("noop.job", n=i))
    box.close()
    p = _station(st, "--no-scanner")
    stations.append(p)
    wait_for(lambda: _answers(st), 60, "the station's broker")
    wait_for(lambda: len(Outbox(st.root / "bench")) == 0, 60, "the outbox to be delivered")
    with st.subscriber(since=0) as sub:
        got = collect(sub, lambda evs: sum(e["type"] == "noop.job" for _, e in evs) >= 2, 30, "both waiting events")
    assert sorted(e["n"] for _, e in got if e["type"] == "noop.job") == [0, 1]
    p.send_signal(signal.SIGTERM)
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 130, out
    assert "2 event(s) from imports or captures made while the station was down" in out


def _answers(st) -> bool:
    try:
        return any(w["service"] == "noop" for ws in st.status()["workers"].values() for w in ws)
    except Exception:
        return False


def test_station_restarts_a_killed_worker_and_keeps_running(make_station, stations):
    """Issue 19: one worker dying stopped the whole station."""
    import os
    import time
    st = make_station(routing={"fragment.ready": ["noop"]})
    p = _station(st, "--set", "scanner.fragments=1")
    stations.append(p)
    wait_for(lambda: _answers(st), 60, "the station's noop worker")
    first = [w["pid"] for ws in st.status()["workers"].values() for w in ws if w["service"] == "noop"][0]
    os.kill(first, signal.SIGKILL)
    t0 = time.monotonic()
    again = wait_for(lambda: [w["pid"] for ws in _status(st).get("workers", {}).values() for w in ws
                              if w["service"] == "noop" and w["pid"] != first], 60, "a new noop worker")
    assert again and p.poll() is None, "the station is still running"
    assert time.monotonic() - t0 >= 0.9, "restarted after the back-off, not at once"


def _status(st) -> dict:
    try:
        return st.status()
    except Exception:
        return {}


def test_a_crash_loop_is_reported_with_growing_back_off(tmp_path, monkeypatch):
    import io

    from services.cli import station
    kids = station.Children([], tmp_path)
    monkeypatch.setattr(kids, "command", lambda *a: [sys.executable, "-c", "import sys; sys.exit(3)"])
    out = io.StringIO()
    kids.start("solver", "worker", "solver")
    now, starts, waits = 0.0, 1, []
    while now < 200 and len(kids.crash_loops) == 0:
        kids.procs["solver"].wait(10)
        kids.supervise(now, out)
        waits.append(kids.restart_at["solver"] - now)
        now = kids.restart_at["solver"]
        kids.supervise(now, out)
        starts += 1
    kids.procs["solver"].wait(10)
    assert waits[:5] == [1.0, 2.0, 4.0, 8.0, 16.0], waits
    assert "solver" in kids.crash_loops and kids.restarts["solver"] == starts - 1
    text = out.getvalue()
    assert "solver exited with status 3; restarting it in 1 s" in text
    assert "CRASH LOOP: solver died 5 times" in text


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this platform")
def test_a_pinned_child_runs_on_its_core_and_keeps_it_across_a_restart(tmp_path, monkeypatch):
    # `tessera perf` pins one worker set per core through the station's own spawner
    import io

    from services.cli import station
    kids = station.Children([], tmp_path, env=dict(os.environ, TESSERA_PIN_TEST="1"))
    script = ("import os, sys; print(sorted(os.sched_getaffinity(0)), os.environ.get('TESSERA_PIN_TEST'), flush=True);"
              " sys.exit(3)")
    monkeypatch.setattr(kids, "command", lambda *a: [sys.executable, "-c", script])
    core = max(os.sched_getaffinity(0))
    kids.start("solver", "worker", "solver", cpu=core)
    kids.procs["solver"].wait(10)
    kids.supervise(0.0, io.StringIO())
    kids.supervise(kids.restart_at["solver"], io.StringIO())   # restarted with the same pinning
    kids.procs["solver"].wait(10)
    lines = (tmp_path / "solver.log").read_text().splitlines()
    assert lines == [f"[{core}] 1", f"[{core}] 1"]


def test_a_perf_station_starts_the_command_it_is_given_and_hands_back_the_process(tmp_path):
    # the soak kills and restarts the processes of `tessera perf`'s station: spawn must start
    # `tessera <args>` (not the role's name) and return the process (it once did neither)
    from services.cli.perf import _Station
    (tmp_path / "source").mkdir()
    st = _Station(tmp_path, tmp_path / "source", "st")
    p = st.spawn("probe", "keys", "--help")
    assert p.wait(60) == 0 and st.roles == {"probe-0": "probe"}
    assert "usage: tessera keys" in (st.dir / "probe-0.log").read_text()
