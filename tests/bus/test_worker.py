"""Worker runtime: a job that meets full or read-only storage is retried in the worker with
back-off (heartbeats go on), not failed three times in milliseconds (issue 19)."""

from __future__ import annotations

import errno
import threading
import time

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
