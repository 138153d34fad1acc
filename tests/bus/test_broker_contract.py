"""docs/messages.md's promises about what the broker publishes, against a real broker process."""

from __future__ import annotations

import time

import pytest

from common.bus import protocol as P
from common.messages import new_message

from .conftest import collect, wait_for
from .test_broker import _FakeWorker

pytestmark = pytest.mark.timeout(120)


def test_a_result_with_invalid_events_gives_one_input_rejected_per_job(make_station):
    """input.rejected: "one event per job". A result holding many invalid events (a worker that
    does not validate what it returns, up to 1,000 a result) published one input.rejected each."""
    st = make_station()
    st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    job = new_message("noop.job", fragment="F7", face="front")
    jid = f"{job['uid'][:12]}-noop"
    w = _FakeWorker(endpoint, 333)
    try:
        with st.client() as c:
            c.submit(job)
            wait_for(lambda: w.pump(0.1) or w.jobs, 10, "the fake worker to get the job")
            good = new_message("noop.done", job=job["uid"], received=time.time(), attempt=1)
            bad = [{"type": "noop.done"}, {"v": 1, "type": "nope", "uid": "0" * 32, "time": 1.0},
                   dict(good, uid="1" * 32, probability=2.0)]
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
    assert "3 invalid event(s)" in r["error"] and r["job"] == jid and r["service"] == "noop"
    assert (r["input"], r["fragment"], r["face"]) == (job["uid"], "F7", "front")
    assert [e["uid"] for _, e in events if e["type"] == "noop.done"] == [good["uid"]], "the valid event is published"
