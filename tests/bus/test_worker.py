"""Worker runtime: a job that meets full or read-only storage is retried in the worker with
back-off (heartbeats go on), not failed three times in milliseconds (issue 19)."""

from __future__ import annotations

import errno
import threading
import time

import pytest

from common.bus import protocol as P
from common.bus.worker import _JobRunner
from common.store import StorageFull, StorageReadOnly


def _run(handle, retry, stop=None):
    runner = _JobRunner(handle, lambda jid, attempt, progress: None, retry=retry, stop=stop)
    runner.start()
    runner.jobs.put(("j1", 1, {"type": "noop.job"}))
    outcomes = []
    while True:
        item = runner.outcomes.get(timeout=30)
        outcomes.append(item)
        if item[0] != "progress":
            break
    runner.jobs.put(None)
    return outcomes


def test_storage_errors_are_retried_with_growing_waits_then_the_job_succeeds():
    calls = []

    def handle(job, ctx):
        calls.append(time.monotonic())
        if len(calls) == 1:
            raise StorageFull(errno.ENOSPC, "storage full: test")
        if len(calls) == 2:
            raise StorageReadOnly(errno.EROFS, "storage read-only: test")
        return []

    outcomes = _run(handle, retry=(0.2, 1.0, 10.0))
    assert outcomes[-1][0] == "result" and outcomes[-1][2] == P.dumps([])
    assert len(calls) == 3
    gaps = [b - a for a, b in zip(calls, calls[1:])]
    assert 0.2 <= gaps[0] < 0.4 and 0.4 <= gaps[1] < 0.7, f"back-off doubles: {gaps}"
    assert any(o[0] == "progress" and "retrying" in o[3] for o in outcomes), "the wait is shown as progress"


def test_storage_errors_fail_the_attempt_only_after_the_budget():
    calls = []

    def handle(job, ctx):
        calls.append(time.monotonic())
        raise StorageFull(errno.ENOSPC, "storage full: test")

    t0 = time.monotonic()
    outcomes = _run(handle, retry=(0.1, 0.2, 1.0))
    assert outcomes[-1][0] == "fail" and outcomes[-1][2] == P.FAIL_ERROR and "StorageFull" in outcomes[-1][3]
    assert 0.6 <= time.monotonic() - t0 < 3.0 and 4 <= len(calls) <= 8


def test_other_errors_are_not_retried_in_the_worker():
    calls = []

    def handle(job, ctx):
        calls.append(1)
        raise RuntimeError("a bug")

    outcomes = _run(handle, retry=(0.1, 0.2, 5.0))
    assert outcomes[-1][0] == "fail" and len(calls) == 1


def test_a_stopping_worker_stops_retrying():
    stop = threading.Event()

    def handle(job, ctx):
        stop.set()
        raise StorageFull(errno.ENOSPC, "storage full: test")

    t0 = time.monotonic()
    outcomes = _run(handle, retry=(5.0, 5.0, 60.0), stop=stop)
    assert outcomes[-1][0] == "fail" and time.monotonic() - t0 < 2.0


def _done_event(**extra) -> dict:
    from common.messages import new_message
    return new_message("noop.done", job="0" * 32, received=1.0, attempt=1, **extra)


@pytest.mark.parametrize("events, reason", [
    # valid, but over the 256 KiB every message is held to (20 strings of 16,000 characters)
    (lambda: [_done_event(padding=["x" * 16000] * 20)], "bytes refused (at most 262144)"),
    # more than broker.MAX_RESULT_EVENTS (1,000)
    (lambda: [_done_event() for _ in range(1001)], "1001 events in one result (at most 1000)"),
    # each event within its limit, the RESULT frame over the broker's 1 MiB (ZeroMQ would drop it)
    (lambda: [_done_event(padding=["x" * 16000] * 15) for _ in range(5)], "(at most 1048576 a frame)"),
], ids=["oversized-event", "too-many-events", "result-over-the-frame-cap"])
def test_a_result_over_the_message_limits_is_an_ordinary_failure(events, reason):
    """docs/messages.md (input.rejected): Tessera's worker checks a stage's events first and counts an
    invalid one as an ordinary failure (retried, finally stage.failed), the limits included: an event
    over 256 KiB, more than 1,000 events, a result the broker's frame cap would drop (the job hung)."""
    result = events()
    outcome = _run(lambda job, ctx: result, retry=(0.1, 0.2, 5.0))[-1]
    assert outcome[:3] == ("fail", "j1", P.FAIL_ERROR), f"sent to the broker as a {outcome[0]}"
    error = outcome[3]
    assert error.startswith("RuntimeError: stage returned an invalid event:") and reason in error, error


# -- end to end, on a real read-only and a real full file system (root: a tmpfs mount) --------------

import os  # noqa: E402
import subprocess  # noqa: E402

from common.messages import new_message  # noqa: E402

from .conftest import collect, wait_for  # noqa: E402


def _mount_tmpfs(path, size="2m"):
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True, text=True)
    if r.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")


def fill_disk(directory):
    """Fill the file system of ``directory`` with a ``ballast`` file until it refuses; the file's path."""
    ballast = directory / "ballast"
    with open(ballast, "wb") as fh:
        try:
            while True:
                fh.write(b"\0" * 65536)
                fh.flush()
        except OSError:
            pass
    return ballast


@pytest.fixture
def mounts():
    made = []
    yield made
    for m in made:
        subprocess.run(["umount", "-l", str(m)], check=False)


def _fast_retry(st):
    text = st.config_path.read_text().replace(
        "shutdown_grace_s = 5.0", "shutdown_grace_s = 5.0\nstorage_retry_min_s = 0.2\nstorage_retry_max_s = 0.5\n"
                                  "storage_retry_budget_s = 60.0")
    st.config_path.write_text(text)


def test_a_job_on_read_only_storage_waits_and_finishes_on_its_first_attempt(make_station, mounts):
    """Issue 19: a job failing on EROFS burned its 3 attempts within milliseconds and was parked."""
    st = make_station(services={"noop": {"write_output": True}})
    storage = st.root / "storage"
    _mount_tmpfs(storage)
    mounts.append(storage)
    _fast_retry(st)
    subprocess.run(["mount", "-o", "remount,ro", str(storage)], check=True)
    st.broker()
    worker = st.worker()
    st.workers_ready(1)
    job = new_message("noop.job", fragment="F0001", face="front")
    with st.client() as c:
        c.submit(job)
        inflight = wait_for(lambda: c.status()["in_flight"], 10, "the job in flight")
        time.sleep(2.0)  # several refused writes
        s = c.status()
        assert s["parked"] == [] and s["in_flight"][0]["attempt"] == 1, s
        assert "retrying" in (s["in_flight"][0]["progress"] or ["", ""])[1]
    subprocess.run(["mount", "-o", "remount,rw", str(storage)], check=True)
    with st.subscriber(0) as sub:
        events = collect(sub, lambda ev: any(e["type"] == "noop.done" for _, e in ev), 20, "noop.done")
    done = [e for _, e in events if e["type"] == "noop.done"]
    assert len(done) == 1 and done[0]["attempt"] == 1 and not any(e["type"] == "stage.failed" for _, e in events)
    assert worker.poll() is None and inflight


def test_broker_journal_on_a_full_disk_refuses_with_retry_and_recovers(make_station, mounts):
    """The broker's journal disk fills: submissions get ERR (retry), STATUS says so, nothing is
    lost, and it accepts again once space is freed."""
    from common.bus.client import BrokerRefused
    st = make_station()
    journal = st.root / "journal"
    _mount_tmpfs(journal, size="4m")
    mounts.append(journal)
    st.broker()
    st.worker()
    st.workers_ready(1)
    ok = new_message("noop.job", n=0)
    with st.client() as c:
        c.submit(ok)
        ballast = fill_disk(journal)
        refused, accepted = None, []
        for i in range(200):  # the WAL has some room left: keep submitting until the journal fails
            try:
                e = new_message("noop.job", n=i + 1, pad="x" * 8000)
                c.submit(e)
                accepted.append(e["uid"])
            except BrokerRefused as exc:
                refused, refused_event = exc, e
                break
        assert refused is not None and refused.retry and "journal" in str(refused)
        assert c.status()["journal_ok"] is False
        ballast.unlink()
        later = new_message("noop.job", n=999)
        wait_for(lambda: _submits(c, later), 30, "the broker to accept again")
        assert c.status()["journal_ok"] is True
        c.submit(refused_event)  # what the outbox does with a refusal marked retry: harmless if it got in
    with st.subscriber(0) as sub:
        want = {ok["uid"], later["uid"], refused_event["uid"], *accepted}
        events = collect(sub, lambda ev: {e["job"] for _, e in ev if e["type"] == "noop.done"} >= want, 60,
                         "every accepted job done")
    assert len([e for _, e in events if e["type"] == "noop.done"]) == len(want), "each once"


def _submits(c, event) -> bool:
    from common.bus.client import BrokerRefused
    try:
        c.submit(event)
        return True
    except BrokerRefused:
        return False


def test_sqlite_and_os_words_for_a_refusing_disk_are_storage_errors_too():
    """The matcher's proposal store is SQLite on the storage: "database or disk is full" burned its
    attempts in the soak. It is retried with back-off like StorageFull."""
    import sqlite3

    from common.bus.worker import storage_refused
    assert storage_refused(sqlite3.OperationalError("database or disk is full"))
    assert storage_refused(sqlite3.OperationalError("attempt to write a readonly database"))
    assert storage_refused(sqlite3.OperationalError("database is locked"))
    assert storage_refused(OSError(errno.EROFS, "Read-only file system"))
    assert storage_refused(StorageFull(errno.ENOSPC, "x"))
    assert not storage_refused(sqlite3.OperationalError("no such table: fragments"))
    assert not storage_refused(OSError(errno.ENOENT, "missing"))
    assert not storage_refused(RuntimeError("database or disk is full"))
    calls = []

    def handle(job, ctx):
        calls.append(1)
        if len(calls) < 3:
            raise sqlite3.OperationalError("database or disk is full")
        return []

    outcomes = _run(handle, retry=(0.05, 0.1, 5.0))
    assert outcomes[-1][0] == "result" and len(calls) == 3


# -- reconnecting: told DISCONNECT (a refused registration, a restarted broker), with back-off --------

import zmq  # noqa: E402

from common.bus.worker import run_worker  # noqa: E402


def _serve(router, seconds: float, answer) -> list:
    """Serve as a fake broker for ``seconds``, answering each worker frame with ``answer(identity,
    command)``; return the times READY came."""
    readies, end = [], time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        if router.poll(left * 1000):
            frames = router.recv_multipart()
            if frames[3] == P.READY:
                readies.append(time.monotonic())
            answer(frames[0], frames[3])
    return readies


def _noop_worker_beside_a_fake_broker(config):
    """A real noop worker (a thread) connected to a bare ROUTER bound where its broker would be: the test plays
    the broker. Returns (context, router, stop event, worker thread)."""
    ctx = zmq.Context()
    router = ctx.socket(zmq.ROUTER)
    router.bind(f"tcp://127.0.0.1:{config['broker']['port']}")
    stop = threading.Event()
    worker = threading.Thread(target=run_worker, args=("noop", config),
                              kwargs={"stop": stop, "context": ctx, "install_signals": False}, daemon=True)
    worker.start()
    return ctx, router, stop, worker


def test_a_worker_told_to_disconnect_reconnects_with_back_off(make_station, caplog):
    """docs/messages.md: the worker reconnects with exponential back-off ([worker] reconnect_min_s,
    doubling to reconnect_max_s; reset once the broker exchanges heartbeats with it); docs/security.md:
    a refused registration gets ERR and DISCONNECT. Told DISCONNECT, the worker reconnected at once,
    so a key whose role is refused looped READY/ERR/DISCONNECT as fast as it could; and it logged the
    ERR as a "malformed frame", not the reason the broker gave."""
    st = make_station()  # its configuration only (reconnect 0.1 s doubling to 0.5 s): the broker is a fake
    ctx, router, stop, worker = _noop_worker_beside_a_fake_broker(st.config)

    def send(identity, header, command, *parts):
        router.send_multipart([identity, b"", header, command, *parts])

    def refuse(identity, command):  # as the broker refuses a key of the wrong role
        if command == P.READY:
            send(identity, P.CLIENT, P.ERR, b"", P.dumps({"error": "a key of role 'web' may not serve 'noop'"}))
            send(identity, P.WORKER, P.DISCONNECT)

    registered = []

    def register(identity, command):  # READY taken, heartbeats answered
        registered.append(identity)
        send(identity, P.WORKER, P.HEARTBEAT)

    try:
        refused = _serve(router, 2.0, refuse)
        gaps = [b - a for a, b in zip(refused, refused[1:])]
        assert 4 <= len(refused) <= 8, f"{len(refused)} READYs in 2 s: {gaps[:10]}"
        assert all(g >= 0.9 * min(0.1 * 2 ** i, 0.5) for i, g in enumerate(gaps)), f"back-off doubles: {gaps}"
        assert "broker refused noop's frame: a key of role 'web' may not serve 'noop'" in caplog.text
        assert "malformed frame" not in caplog.text

        # registered at last: the heartbeat exchange resets the back-off, so told DISCONNECT it is back in 0.1 s
        assert _serve(router, 1.2, register), "the worker came back"
        told = time.monotonic()
        send(registered[-1], P.WORKER, P.DISCONNECT)
        again = _serve(router, 1.0, lambda identity, command: None)
        assert again and 0.09 <= again[0] - told < 0.3, f"READY {again[0] - told if again else None} s after DISCONNECT"
    finally:
        stop.set()
        worker.join(5)
        ctx.destroy(linger=0)
    assert not worker.is_alive()


# -- a job from an older journal: a match.verified in a verdict word the door no longer takes -------------

def test_a_re_queued_verdict_in_an_older_word_is_handled_not_parked(make_station):
    """docs/messages.md: a journal written before the broker refused them may hold the verdict words
    confirm/accept/accepted/yes/reject/no, "which its readers still read". The worker decoded every job
    strictly, so such a re-queued match.verified came back FAIL rejected (parked as bad input) and the
    matcher's verdict_of never saw it. A verdict no word means is still refused."""
    st = make_station()  # its configuration only: the broker is a fake
    ctx, router, stop, worker = _noop_worker_beside_a_fake_broker(st.config)

    def job_body(verdict):
        msg = new_message("match.verified", fragment="A", other="B", verdict="confirmed")
        return P.dumps(dict(msg, verdict=verdict)), msg["uid"]

    def answer_to(jid: bytes, identity, body, seconds=10.0):
        router.send_multipart([identity, b"", P.WORKER, P.JOB, jid, b"1", body])
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            if router.poll(left * 1000):
                frames = router.recv_multipart()
                if frames[3] in (P.RESULT, P.FAIL) and frames[4] == jid:
                    return frames[3:]
        raise AssertionError(f"no answer to job {jid!r}")

    try:
        assert router.poll(10_000), "the worker registers"
        identity = router.recv_multipart()[0]
        router.send_multipart([identity, b"", P.WORKER, P.HEARTBEAT])
        body, uid = job_body("confirm")
        answer = answer_to(b"j1", identity, body)
        assert answer[0] == P.RESULT, f"old-word verdict parked: {answer[2:]}"
        assert [e["type"] for e in P.loads(answer[2])] == ["noop.done"]
        assert P.loads(answer[2])[0]["job"] == uid
        body, _ = job_body("maybe")
        answer = answer_to(b"j2", identity, body)
        assert answer[:3] == [P.FAIL, b"j2", P.FAIL_REJECTED] and b"verdict" in answer[3]
    finally:
        stop.set()
        worker.join(5)
        ctx.destroy(linger=0)
    assert not worker.is_alive()
