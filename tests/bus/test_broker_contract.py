"""docs/messages.md's promises about what the broker publishes, against a real broker process."""

from __future__ import annotations

import time

import pytest

from common.bus import protocol as P
from common.messages import new_message

from .conftest import collect, wait_for
from .test_broker import _FakeWorker

pytestmark = pytest.mark.timeout(120)


def _noop_job_held_by_a_fake_worker(st, fragment: str, pid: int):
    """A noop job submitted to the station's broker and held by a fake worker: (job, job id, worker)."""
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    job = new_message("noop.job", fragment=fragment, face="front")
    w = _FakeWorker(endpoint, pid)
    with st.client() as c:
        c.submit(job)
    wait_for(lambda: w.pump(0.1) or w.jobs, 10, "the fake worker to get the job")
    return job, f"{job['uid'][:12]}-noop", w


def test_a_result_with_invalid_events_gives_one_input_rejected_per_job(make_station):
    """input.rejected: "one event per job". A result holding many invalid events (a worker that
    does not validate what it returns, up to 1,000 a result) published one input.rejected each. An event
    over the 256 KiB limit of every message is one of them: it is never journaled."""
    st = make_station()
    st.broker()
    job, jid, w = _noop_job_held_by_a_fake_worker(st, "F7", 333)
    try:
        good = new_message("noop.done", job=job["uid"], received=time.time(), attempt=1)
        # the last: valid but over the 256 KiB every message is held to (20 strings of 16,000 characters)
        bad = [{"type": "noop.done"}, {"v": 1, "type": "nope", "uid": "0" * 32, "time": 1.0},
               dict(good, uid="1" * 32, probability=2.0), dict(good, uid="2" * 32, padding=["x" * 16000] * 20)]
        w.send(P.RESULT, jid.encode(), P.dumps([*bad, good]))
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: any(e["type"] == "noop.done" for _, e in ev)
                             and any(e["type"] == "input.rejected" for _, e in ev), 20, "the result")
            end = time.monotonic() + 1.5          # and whatever follows
            while time.monotonic() < end:
                item = sub.next(0.2)
                if item is not None:
                    events.append(item)
    finally:
        w.close()
    rejected = [e for _, e in events if e["type"] == "input.rejected"]
    assert len(rejected) == 1, rejected
    r = rejected[0]
    assert "4 invalid event(s)" in r["error"] and r["job"] == jid and r["service"] == "noop"
    assert (r["input"], r["fragment"], r["face"]) == (job["uid"], "F7", "front")
    assert [e["uid"] for _, e in events if e["type"] == "noop.done"] == [good["uid"]], "the valid event is published"


def test_a_result_announcing_more_events_than_the_broker_takes_has_the_rest_refused_not_dropped(make_station):
    """A result may announce at most 1,000 events (``broker.MAX_RESULT_EVENTS``): the first 1,000 are published
    and the rest are counted in the job's one input.rejected, not silently cut."""
    from common.bus.broker import MAX_RESULT_EVENTS

    st = make_station()
    st.broker()
    job, jid, w = _noop_job_held_by_a_fake_worker(st, "F8", 334)
    try:
        done = [new_message("noop.done", job=job["uid"], received=time.time(), attempt=1)
                for _ in range(MAX_RESULT_EVENTS + 2)]
        w.send(P.RESULT, jid.encode(), P.dumps(done))
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: any(e["type"] == "input.rejected" for _, e in ev)
                             and sum(e["type"] == "noop.done" for _, e in ev) >= MAX_RESULT_EVENTS, 60,
                             "the result")
    finally:
        w.close()
    rejected = [e for _, e in events if e["type"] == "input.rejected"]
    assert len(rejected) == 1 and "2 invalid event(s)" in rejected[0]["error"]
    assert f"{MAX_RESULT_EVENTS + 2} events in one result" in rejected[0]["error"]
    assert [e["uid"] for _, e in events if e["type"] == "noop.done"] == [d["uid"] for d in done[:MAX_RESULT_EVENTS]]
