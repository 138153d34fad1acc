"""The broker with real processes: redelivery, restart, parking, bad input, journal compaction."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import zmq

from common.bus import protocol as P
from common.bus.client import BrokerRefused
from common.messages import VERSION, new_message
from common.store import Store

from .conftest import collect, wait_for


def _done(events, uids=None):
    return {e["job"] for _, e in events if e["type"] == "noop.done" and (uids is None or e["job"] in uids)}


def test_worker_killed_mid_job_is_redelivered(make_station):
    st = make_station(services={"noop": {"sleep_s": 1.5, "write_output": True}})
    st.broker()
    st.worker()
    st.worker()
    st.workers_ready(2)
    job = new_message("noop.job", fragment="F0001", face="front")
    with st.client() as c:
        c.submit(job)
    inflight = wait_for(lambda: st.status()["in_flight"], 10, "the job to be in flight")
    pid = int(inflight[0]["worker"].rsplit(":", 1)[1])
    os.kill(pid, signal.SIGKILL)
    with st.subscriber(0) as sub:
        events = collect(sub, lambda ev: _done(ev), 20, "noop.done")
    done = [e for _, e in events if e["type"] == "noop.done"]
    assert len(done) == 1 and done[0]["job"] == job["uid"]
    assert done[0]["attempt"] == 2, "the second delivery (after the kill) completed it"
    outputs = [p for p in (st.root / "storage" / "fragments" / "F0001" / "noop").iterdir() if not p.name.startswith(".")]
    assert len(outputs) == 1, f"exactly one result artifact, got {outputs}"
    assert not any(e["type"] == "stage.failed" for _, e in events)
    alive = [p for p in st.procs[1:] if p.poll() is None]
    assert len(alive) == 1 and alive[0].pid != pid


def test_broker_restart_with_queued_and_inflight_jobs_loses_none(make_station):
    st = make_station(services={"noop": {"sleep_s": 0.4}})
    broker = st.broker()
    st.worker()
    st.workers_ready(1)
    jobs = [new_message("noop.job", n=i) for i in range(8)]
    with st.client() as c:
        c.submit_many(jobs)
    wait_for(lambda: st.status()["in_flight"], 10, "a job in flight")
    s = st.status()
    assert s["queues"]["noop"] >= 4, "jobs are still queued when the broker dies"
    broker.send_signal(signal.SIGKILL)
    broker.wait(5)
    time.sleep(0.5)
    st.broker()
    uids = {j["uid"] for j in jobs}
    with st.subscriber(0) as sub:
        events = collect(sub, lambda ev: _done(ev, uids) == uids, 40, "all eight jobs done")
    seqs = [s for s, _ in events]
    assert seqs == list(range(1, len(seqs) + 1)), "the feed after restart is complete and in order"
    submitted = [e["uid"] for _, e in events if e["type"] == "noop.job"]
    assert submitted == [j["uid"] for j in jobs], "every accepted event survived, in order, once"


def test_failing_job_is_parked_with_stage_failed_and_can_be_rerun(make_station):
    st = make_station()
    st.broker()
    st.worker()
    st.workers_ready(1)
    bad = new_message("noop.job", fail=True)
    good = new_message("noop.job")
    with st.client() as c:
        c.submit(bad)
        c.submit(good)
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: any(e["type"] == "stage.failed" for _, e in ev) and _done(ev), 20,
                             "stage.failed and the good job")
            failed = [e for _, e in events if e["type"] == "stage.failed"][0]
            assert failed["service"] == "noop" and failed["attempts"] == 3 and "asked to fail" in failed["error"]
            parked = c.status()["parked"]
            assert [p["job"] for p in parked] == [failed["job"]] and parked[0]["attempts"] == 3
            assert c.rerun("all") == [failed["job"]]
            again = collect(sub, lambda ev: any(e["type"] == "stage.failed" for _, e in ev), 20, "second stage.failed")
            assert [e for _, e in again if e["type"] == "stage.failed"][0]["job"] == failed["job"]
    assert _done(events) == {good["uid"]}


def _raw_send(endpoint: str, *frames: bytes) -> None:
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 500)
    s.connect(endpoint)
    s.send_multipart(list(frames))
    s.close()


def test_bad_inputs_are_refused_or_reported_and_nothing_else_is_lost(make_station):
    st = make_station(services={"noop": {"schema": "tessera.scans", "schema_version": 1}})
    st.broker()
    worker = st.worker()
    st.workers_ready(1)
    store = Store(st.root / "storage")
    fill = lambda f: f.create_dataset("x", data=np.arange(1000.0))  # noqa: E731
    ok_ref = store.write("fragments/F0002/scans/scans-a.h5", "tessera.scans", 1, fill)
    trunc_ref = store.write("fragments/F0003/scans/scans-b.h5", "tessera.scans", 1, fill)
    with open(store.path(trunc_ref.path), "r+b") as fh:
        fh.truncate(trunc_ref.bytes // 2)
    trunc_ref = store.ref(trunc_ref.path)  # digest of the truncated file: only HDF5 can tell
    bad_digest = dict(ok_ref.to_dict(), sha256="0" * 64)
    future = store.write("fragments/F0004/scans/scans-c.h5", "tessera.scans", 7, fill)   # newer schema version
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    good = [new_message("noop.job", n=i) for i in range(3)]
    with st.client() as c:
        c.submit(good[0])
        _raw_send(endpoint, b"garbage")                                        # malformed frames
        _raw_send(endpoint, b"", b"XX9", b"HELLO")                             # unknown protocol
        _raw_send(endpoint, b"", P.WORKER, P.RESULT, b"no-such-job", b"\xc1\xc1")  # worker frame from nowhere
        for doc in ({"v": VERSION, "type": "no.such.type", "uid": "u1", "time": 0.0},   # unknown type
                    {"v": 99, "type": "noop.job", "uid": "u2", "time": 0.0}):          # wrong version
            with pytest.raises(BrokerRefused):
                c.request(P.SUBMIT, P.dumps(doc))
        with pytest.raises(BrokerRefused):
            c.request(P.SUBMIT, b"\xc1not msgpack")
        c.submit(good[1])
        trunc = new_message("fragment.ready", fragment="F0003", artifact=trunc_ref)
        wrong = new_message("fragment.ready", fragment="F0002", artifact=bad_digest)
        fine = new_message("fragment.ready", fragment="F0002", artifact=ok_ref)
        newer = new_message("fragment.ready", fragment="F0004", artifact=future)
        c.submit_many([trunc, wrong, newer, fine, good[2]])
        want = {g["uid"] for g in good} | {fine["uid"]}
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: _done(ev) >= want and
                             sum(e["type"] == "input.rejected" for _, e in ev) >= 4, 20, "good jobs and rejections")
        rejected = [e for _, e in events if e["type"] == "input.rejected"]
        errors = " | ".join(e["error"] for e in rejected)
        # bad artifacts: one input.rejected per job, with the reason
        for phrase in ("not a readable HDF5", "sha256", "schema version 7; this reader understands up to 1"):
            assert phrase in errors, f"no input.rejected saying {phrase!r}: {errors}"
        # refused frames: ERR to the sender (BrokerRefused above), counted, one summary event per interval
        summaries = [e for e in rejected if e.get("refused")]
        assert len(summaries) == 1 and "frame(s) refused" in summaries[0]["error"], errors
        refused = c.status()["refused"]
        assert sum(refused.values()) >= 6 and refused.get("invalid", 0) >= 3 and refused.get("malformed", 0) >= 2, refused
        parked = {p["fragment"] for p in c.status()["parked"]}
        assert parked == {"F0002", "F0003", "F0004"}, "bad artifacts are parked at once, not retried"
    assert _done(events) == want
    assert all(p.poll() is None for p in st.procs), "broker and worker stay up"
    assert worker.poll() is None


def test_journal_is_compacted_and_keeps_pending_jobs(make_station):
    st = make_station(extra="")
    cfg = st.config_path.read_text().replace("max_attempts = 3", "max_attempts = 3\nfeed_history = 50")
    st.config_path.write_text(cfg)
    st.broker()
    st.worker()
    st.workers_ready(1)
    with st.client() as c:
        c.submit_many([new_message("noop.job", n=i) for i in range(400)])
        wait_for(lambda: c.status()["completed"] >= 400, 30, "400 jobs done")
        time.sleep(1.5)  # two compaction periods
        first = c.since(0, 10)["first_seq"]
    assert first > 800 - 50 - 5, f"old events dropped from the journal (first retained {first})"
    db = st.root / "journal" / "journal.sqlite"
    import sqlite3
    with sqlite3.connect(db) as con:
        n_events = con.execute("SELECT COUNT(*) FROM events").fetchone()[0]
        n_jobs = con.execute("SELECT COUNT(*) FROM jobs").fetchone()[0]
    assert n_events <= 50 + 5 and n_jobs == 0


def test_worker_finishes_its_job_on_sigterm(make_station):
    st = make_station(services={"noop": {"sleep_s": 1.0}})
    st.broker()
    w = st.worker()
    st.workers_ready(1)
    job = new_message("noop.job")
    with st.client() as c:
        c.submit(job)
        wait_for(lambda: c.status()["in_flight"], 10, "job in flight")
        w.send_signal(signal.SIGTERM)
        assert w.wait(10) == 0
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: _done(ev), 5, "the job finished before exit")
    assert _done(events) == {job["uid"]}
    assert [e["attempt"] for _, e in events if e["type"] == "noop.done"] == [1]


def test_worker_hands_back_a_long_job_on_sigterm_and_another_worker_runs_it(make_station):
    st = make_station(services={"noop": {"sleep_s": 3.0}})
    st.broker()
    slow = st.spawn("worker", "noop", "--set", "worker.shutdown_grace_s=0.3")
    st.workers_ready(1)
    job = new_message("noop.job")
    with st.client() as c:
        c.submit(job)
        inflight = wait_for(lambda: c.status()["in_flight"], 10, "job in flight")
        assert inflight[0]["worker"].endswith(f":{slow.pid}")
        wait_for(lambda: (c.status()["in_flight"] or [{}])[0].get("progress"), 5, "progress reported")
        slow.send_signal(signal.SIGTERM)
        assert slow.wait(10) == 0
        st.worker()
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: _done(ev), 20, "the handed-back job done elsewhere")
        assert [e["attempt"] for _, e in events if e["type"] == "noop.done"] == [1], "a hand-back is not a failure"
        assert c.status()["parked"] == []


def test_stage_calling_exit_or_returning_bad_events_is_parked_and_worker_survives(make_station):
    st = make_station()
    st.broker()
    worker = st.worker()
    st.workers_ready(1)
    bad = [new_message("noop.job", fail="exit"), new_message("noop.job", fail="bad-event")]
    good = new_message("noop.job")
    with st.client() as c:
        c.submit_many(bad + [good])
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: sum(e["type"] == "stage.failed" for _, e in ev) == 2 and _done(ev),
                             30, "two stage.failed and the good job")
    failed = {e["input"]: e["error"] for _, e in events if e["type"] == "stage.failed"}
    assert "SystemExit" in failed[bad[0]["uid"]]
    assert "invalid event" in failed[bad[1]["uid"]]
    assert _done(events) == {good["uid"]} and worker.poll() is None


class _FakeWorker:
    """A raw DEALER speaking the worker protocol (common/bus/protocol.py), heartbeating by hand."""

    def __init__(self, endpoint: str, pid: int, service: bytes = b"noop", security: dict | None = None,
                 claim: str | None = None):
        """``claim``: the job id its READY names (a worker reconnecting mid-job)."""
        from common.bus.security import secure_client_socket

        self.sock = secure_client_socket(zmq.Context.instance().socket(zmq.DEALER), security or {})
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.pid = pid
        self.jobs: list[str] = []
        self.told: list[bytes] = []   # every command the broker sent it (JOB, HEARTBEAT, ERR, DISCONNECT, ...)
        info = {"host": "fake", "pid": pid}
        if claim is not None:
            info["job"] = claim
        self.send(P.READY, service, P.dumps(info))

    def send(self, command: bytes, *parts: bytes) -> None:
        self.sock.send_multipart([b"", P.WORKER, command, *parts])

    def pump(self, seconds: float) -> None:
        """Heartbeat and collect JOB frames (and every command, ``told``) for ``seconds``."""
        end = time.monotonic() + seconds
        while True:
            self.send(P.HEARTBEAT)
            while self.sock.poll(20):
                frames = self.sock.recv_multipart()
                if frames[2] == P.JOB:
                    self.jobs.append(frames[3].decode())
                self.told.append(frames[2])
            if time.monotonic() >= end:
                return

    def close(self) -> None:
        self.send(P.DISCONNECT)
        self.sock.close()


def _pump(seconds: float, *workers: _FakeWorker) -> None:
    end = time.monotonic() + seconds
    while True:
        for w in workers:
            w.pump(0.0)
        if time.monotonic() >= end:
            return


def test_worker_messages_for_a_job_it_does_not_hold_are_ignored(make_station):
    st = make_station()
    st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    j1, j2, j3 = (new_message("noop.job", n=i) for i in range(3))
    jid = {j["uid"]: f"{j['uid'][:12]}-noop" for j in (j1, j2, j3)}
    a = _FakeWorker(endpoint, 111)
    b = None
    try:
        with st.client() as c:
            c.submit(j1)
            wait_for(lambda: a.pump(0.1) or a.jobs, 10, "worker A to get j1")
            b = _FakeWorker(endpoint, 222)
            c.submit(j2)
            wait_for(lambda: _pump(0.1, a, b) or b.jobs, 10, "worker B to get j2")
            c.submit(j3)  # no idle worker: stays queued
            assert (a.jobs, b.jobs) == ([jid[j1["uid"]]], [jid[j2["uid"]]])
            # A meddles with B's job and with the queued one
            forged = P.dumps([new_message("noop.done", job=j2["uid"], received=0.0, attempt=1)])
            a.send(P.PROGRESS, jid[j2["uid"]].encode(), P.dumps({"fraction": 0.9, "text": "hijacked"}))
            a.send(P.FAIL, jid[j2["uid"]].encode(), P.FAIL_ERROR, b"forged failure")
            a.send(P.FAIL, jid[j3["uid"]].encode(), P.FAIL_REJECTED, b"forged rejection")
            a.send(P.RESULT, jid[j2["uid"]].encode(), forged)
            a.send(P.RESULT, b"no-such-job", P.dumps([]))
            _pump(1.0, a, b)
            s = c.status()
            inflight = {f["job"]: f for f in s["in_flight"]}
            assert set(inflight) == {jid[j1["uid"]], jid[j2["uid"]]}, "both jobs still in flight with their workers"
            assert inflight[jid[j1["uid"]]]["worker"] == "fake:111" and inflight[jid[j2["uid"]]]["worker"] == "fake:222"
            assert inflight[jid[j2["uid"]]]["progress"] is None, "another worker's progress is not shown"
            assert s["queues"]["noop"] == 1 and s["parked"] == [] and s["completed"] == 0
            assert a.jobs == [jid[j1["uid"]]], "A was not put on the idle list: it got no second job"
            # the honest path still works: B finishes j2 and then gets j3; A finishes j1
            b.send(P.PROGRESS, jid[j2["uid"]].encode(), P.dumps({"fraction": 0.5, "text": "half"}))
            _pump(0.3, a, b)
            assert {f["job"]: f["progress"] for f in c.status()["in_flight"]}[jid[j2["uid"]]] == [0.5, "half"]
            b.send(P.RESULT, jid[j2["uid"]].encode(), forged)
            wait_for(lambda: _pump(0.1, a, b) or len(b.jobs) == 2, 10, "worker B to get j3")
            assert b.jobs[1] == jid[j3["uid"]]
            a.send(P.RESULT, jid[j1["uid"]].encode(), P.dumps([]))
            b.send(P.RESULT, jid[j3["uid"]].encode(), P.dumps([]))
            wait_for(lambda: _pump(0.1, a, b) or c.status()["completed"] == 3, 10, "three jobs completed")
            events = c.since(0, 100)["events"]
        docs = [P.loads(e) for _, e in events]
        types = [d["type"] for d in docs]
        assert "stage.failed" not in types
        assert all(d.get("refused") for d in docs if d["type"] == "input.rejected"), "only the refusal summary"
        assert types.count("noop.done") == 1, "the forged result did not complete j2; B's did, once"
    finally:
        a.close()
        if b is not None:
            b.close()


def test_result_from_a_peer_that_never_registered_cannot_complete_a_job(make_station):
    """Issue 19, job hijack: job ids are derivable from the public feed; a RESULT for one from a
    peer that never said READY must neither complete the job nor route its forged events."""
    st = make_station()
    st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    job = new_message("noop.job", n=1)
    jid = f"{job['uid'][:12]}-noop".encode()
    ctx = zmq.Context()
    rogue = ctx.socket(zmq.DEALER)
    rogue.setsockopt(zmq.LINGER, 0)
    rogue.connect(endpoint)
    try:
        with st.client() as c:
            c.submit(job)  # no worker yet: the job is queued
            forged = new_message("noop.done", job=job["uid"], received=0.0, attempt=1, forged=True)
            rogue.send_multipart([b"", P.WORKER, P.RESULT, jid, P.dumps([forged])])
            rogue.send_multipart([b"", P.WORKER, P.FAIL, jid, P.FAIL_REJECTED, b"forged"])
            assert rogue.poll(3000), "the rogue is answered (told to DISCONNECT)"
            assert rogue.recv_multipart()[2] == P.DISCONNECT
            time.sleep(0.3)
            s = c.status()
            assert s["queues"]["noop"] == 1 and s["completed"] == 0 and s["parked"] == []
            assert s["refused"].get("not-worker", 0) == 2
            st.worker()  # the real worker runs the job
            with st.subscriber(0) as sub:
                events = collect(sub, lambda ev: _done(ev), 20, "the real noop.done")
        done = [e for _, e in events if e["type"] == "noop.done"]
        assert len(done) == 1 and not done[0].get("forged") and done[0]["uid"] != forged["uid"]
    finally:
        ctx.destroy(linger=0)


def test_ready_claiming_another_services_job_does_not_take_it(make_station):
    st = make_station()
    st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    job = new_message("noop.job", n=2)
    jid = f"{job['uid'][:12]}-noop"
    ctx = zmq.Context()
    rogue = ctx.socket(zmq.DEALER)
    rogue.setsockopt(zmq.LINGER, 0)
    rogue.connect(endpoint)
    try:
        with st.client() as c:
            c.submit(job)
            rogue.send_multipart([b"", P.WORKER, P.READY, b"other", P.dumps({"host": "rogue", "pid": 9, "job": jid})])
            time.sleep(0.3)
            rogue.send_multipart([b"", P.WORKER, P.RESULT, jid.encode(), P.dumps([])])
            time.sleep(0.3)
            s = c.status()
            assert s["queues"]["noop"] == 1 and s["completed"] == 0 and s["in_flight"] == []
    finally:
        ctx.destroy(linger=0)


def test_a_worker_that_lost_its_connection_mid_job_reclaims_it_with_security_off(make_station):
    """docs/messages.md: a worker reconnecting mid-job names its job in READY and gets it back, so its result is
    not lost. With CURVE off there is no key to check the claim against: any worker of the service may make it
    (docs/security.md); with CURVE on only the key the job was last given to (test_security.py)."""
    st = make_station()
    st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    job = new_message("noop.job", n=7)
    w = _FakeWorker(endpoint, 701)
    again = None
    try:
        with st.client() as c:
            c.submit(job)
            wait_for(lambda: w.pump(0.1) or w.jobs, 10, "the worker to get the job")
            jid = w.jobs[0]
            w.sock.close()   # the connection is lost, silently: the broker declares it dead and re-queues the job
            wait_for(lambda: not c.status()["in_flight"], 10, "the job to be re-queued")
            again = _FakeWorker(endpoint, 701, claim=jid)   # a new connection, the same job
            again.pump(0.3)
            s = c.status()
            assert [(j["job"], j["worker"]) for j in s["in_flight"]] == [(jid, "fake:701")], s["in_flight"]
            assert again.jobs == [] and s["refused"].get("not-holder", 0) == 0
            again.send(P.RESULT, jid.encode(), P.dumps([new_message("noop.done", job=job["uid"], received=0.0,
                                                                    attempt=1)]))
            wait_for(lambda: again.pump(0.1) or c.status()["completed"] == 1, 10, "the reclaimed job to complete")
    finally:
        if again is not None:
            again.close()


def test_rerun_without_a_job_is_refused_not_a_rerun_of_everything(make_station):
    st = make_station()
    st.broker()
    with st.client() as c:
        c.submit(new_message("noop.job", fail=True))
        st.worker()
        wait_for(lambda: c.status()["parked"], 30, "the failing job to be parked")
        for body in (b"", P.dumps({}), P.dumps({"job": 3}), P.dumps("all")):
            with pytest.raises(BrokerRefused):
                c.request(P.RERUN, body)
        assert len(c.status()["parked"]) == 1, "nothing was re-run"
        assert len(c.rerun("all")) == 1


def test_the_same_output_is_announced_once_even_for_a_resubmitted_input(make_station):
    """Issue 19: a re-submitted fragment.ready (fresh uid) re-announced every downstream event.
    A worker returning the same output again (same fields but uid and time) is not announced again,
    not even after a broker restart."""
    st = make_station()
    broker = st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    art = {"path": "fragments/F1/noop/front-k.h5", "sha256": "ab" * 32, "bytes": 10}

    def run_once(worker):
        job = new_message("noop.job", fragment="F1", face="front")
        with st.client() as c:
            c.submit(job)
        wait_for(lambda: worker.pump(0.1) or len(worker.jobs) > run_once.n, 10, "the job")
        out = new_message("noop.done", job="same", received=0.0, attempt=1, fragment="F1", face="front", artifact=art)
        worker.send(P.RESULT, worker.jobs[-1].encode(), P.dumps([out]))
        run_once.n += 1
        wait_for(lambda: worker.pump(0.05) or st.status()["queues"]["noop"] == 0 and not st.status()["in_flight"],
                 10, "the result")
    run_once.n = 0
    w = _FakeWorker(endpoint, 1)
    try:
        run_once(w)
        run_once(w)
    finally:
        w.close()
    broker.send_signal(signal.SIGTERM)
    broker.wait(10)
    st.broker()
    w = _FakeWorker(endpoint, 2)
    try:
        run_once.n = 0
        run_once(w)
        s = st.status()
    finally:
        w.close()
    with st.client() as c:
        types = [P.loads(b)["type"] for _, b in c.since(0, 100)["events"]]
    assert types.count("noop.job") == 3 and types.count("noop.done") == 1, types
    assert s["duplicates_dropped"] == 1, "the third one, after the restart, was recognised from the journal"


def test_broker_and_all_its_threads_run_at_the_configured_priority(make_station):
    # the broker is the latency-critical process: its poll loop, journal writer and ZeroMQ I/O
    # thread all take [broker] nice (a positive value needs no privilege, so this runs anywhere)
    st = make_station()
    p = st.spawn("broker", "--set", "broker.nice=7")
    with st.client() as c:
        wait_for(lambda: _status_or_none(c) is not None, 20, "the broker to answer")
        s = c.status()
    assert s["nice"] == 7
    tids = [int(t) for t in os.listdir(f"/proc/{p.pid}/task")]
    assert len(tids) >= 3  # poll loop, journal writer, ZeroMQ I/O thread
    assert {os.getpriority(os.PRIO_PROCESS, t) for t in tids} == {7}


def test_status_accounts_the_poll_loop_time(make_station):
    st = make_station()
    st.broker()
    with st.client() as c:
        first = c.status()["loop"]
        time.sleep(0.6)  # a few idle poll timeouts
        second = c.status()["loop"]
    assert second["iterations"] > first["iterations"] >= 1
    assert second["cpu_s"] > first["cpu_s"] >= 0 and second["cpu_s"] > 0
    assert second["runqueue_s"] >= first["runqueue_s"] >= 0
    worst = second["worst_ms"]
    assert set(worst) == {"stall", "cpu", "runqueue", "gc", "other"}
    assert worst["stall"] >= worst["cpu"] >= 0


def _status_or_none(c):
    try:
        return c.status()
    except Exception:  # noqa: BLE001
        return None


def test_status_reply_has_exactly_the_fields_docs_messages_lists(make_station):
    import re
    doc = (Path(__file__).resolve().parents[2] / "docs" / "messages.md").read_text()
    row = re.search(r"^\| `STATUS` \| empty \| `\{([^}]*)\}`", doc, re.M)
    assert row, "docs/messages.md has no STATUS row"
    documented = {k.strip() for k in row.group(1).split(",")}
    st = make_station()
    st.broker()
    assert set(st.status()) == documented


def test_a_worker_claiming_a_job_another_holds_gets_no_job_until_it_reports(make_station):
    """Soak, 300 fragments: a worker declared dead while descheduled reconnects claiming its job,
    which another worker holds by then. It was treated as idle: every job dispatched to it came
    back "busy" at once and burnt an attempt (two jobs were parked). Now it gets nothing until it
    reports, and its report on the other worker's job is ignored."""
    st = make_station()
    st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    ctx = zmq.Context()
    socks = []

    def worker(claim=None):
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(endpoint)
        info = {"host": "t", "pid": 1 + len(socks)}
        if claim:
            info["job"] = claim
        sock.send_multipart([b"", P.WORKER, P.READY, b"noop", P.dumps(info)])
        socks.append(sock)
        return sock

    def next_job(sock, within_s):
        """The next JOB frame within the time (heartbeats answered meanwhile), else None."""
        deadline = time.monotonic() + within_s
        while time.monotonic() < deadline:
            for s in socks:
                s.send_multipart([b"", P.WORKER, P.HEARTBEAT])
            if sock.poll(50):
                f = sock.recv_multipart()
                if f[2] == P.JOB:
                    return f[3].decode()
        return None

    try:
        with st.client() as c:
            holder = worker()
            time.sleep(0.2)
            first = new_message("noop.job", n=1)
            c.submit(first)
            jid = next_job(holder, 5)
            assert jid == f"{first['uid'][:12]}-noop"
            claimant = worker(claim=jid)  # busy with the job the holder runs
            time.sleep(0.3)
            second = new_message("noop.job", n=2)
            c.submit(second)
            assert next_job(claimant, 1.5) is None, "a busy claimant must not be given a job"
            forged = new_message("noop.done", job=first["uid"], received=0.0, attempt=1, forged=True)
            claimant.send_multipart([b"", P.WORKER, P.RESULT, jid.encode(), P.dumps([forged])])
            assert next_job(claimant, 5) == f"{second['uid'][:12]}-noop", "idle once it reported"
            s = c.status()
            assert s["completed"] == 0 and s["parked"] == []
            assert [j["job"] for j in s["in_flight"] if j["job"] == jid], "the holder still holds its job"
            assert all(j["attempt"] == 1 for j in s["in_flight"])
    finally:
        ctx.destroy(linger=0)


@pytest.mark.skipif(not os.path.exists("/proc/self/autogroup"), reason="no Linux autogroups here")
def test_a_broker_in_a_session_of_its_own_gives_its_session_group_the_priority(make_station, tmp_path):
    # as `tessera station` starts it (start_new_session): with autogroups a thread's nice counts
    # only inside its session's group, so the broker's group takes [broker] nice too
    import subprocess
    import sys
    st = make_station()
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    p = subprocess.Popen([sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())",
                          "broker", "--set", "broker.nice=6", "--config", str(st.config_path)],
                         env=env, cwd=tmp_path, start_new_session=True, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
    st.procs.append(p)
    with st.client() as c:
        wait_for(lambda: _status_or_none(c) is not None, 20, "the broker to answer")
    # the file is empty for a process the kernel schedules by cgroup instead (containers, CI runners)
    with open(f"/proc/{p.pid}/autogroup") as fh:
        broker_group = fh.read().split()
    if not broker_group:
        pytest.skip("the broker is scheduled by cgroup, not by autogroup, here")
    assert broker_group[-1] == "6"
    with open("/proc/self/autogroup") as fh:   # this test's own session group is untouched
        own = fh.read().split()
    assert not own or own[-1] == "0"
