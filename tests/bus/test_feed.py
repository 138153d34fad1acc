"""The event feed: a subscriber that disconnects and reconnects misses nothing, in order."""

from __future__ import annotations

import json
import signal
import time

from common.messages import new_message

from .conftest import collect, wait_for


def test_subscriber_reconnecting_with_since_gets_every_missed_event_in_order(make_station):
    st = make_station(routing={"fragment.ready": ["noop"]})  # noop.job goes nowhere: pure feed traffic
    st.broker()
    sub = st.spawn("events", "--since", "0")  # `tessera events` prints JSON lines to its log
    out1 = sub.log_path
    batch1 = [new_message("noop.job", n=i) for i in range(10)]
    with st.client() as c:
        c.submit_many(batch1)
        wait_for(lambda: len(_lines_from_log(out1)) >= 10, 20, "first subscriber to print 10 events")
        sub.send_signal(signal.SIGKILL)
        sub.wait(5)
        seen = _lines_from_log(out1)
        last = seen[-1]["seq"]
        batch2 = [new_message("noop.job", n=10 + i) for i in range(15)]
        c.submit_many(batch2[:8])
        c.submit(batch2[8])
        c.submit_many(batch2[9:])
    again = st.spawn("events", "--since", str(last), "--idle-exit", "2")
    assert again.wait(30) == 0
    resumed = _lines_from_log(again.log_path)
    allseen = seen + resumed
    assert [e["seq"] for e in allseen] == list(range(1, 26)), "contiguous sequence numbers, no gap, no repeat"
    assert [e["uid"] for e in allseen] == [e["uid"] for e in batch1 + batch2], "every event, in submission order"
    assert len({e["stream"] for e in allseen}) == 1


def _lines_from_log(path):
    out = []
    with open(path) as fh:
        for line in fh:
            if line.startswith("{"):
                out.append(json.loads(line))
    return out


def test_subscriber_fills_gaps_across_a_broker_restart_and_filters_types(make_station):
    st = make_station(routing={"fragment.ready": ["noop"]})
    broker = st.broker()
    with st.client() as c:
        c.submit(new_message("noop.job", n=0))
    with st.subscriber(0) as sub:
        got = collect(sub, lambda ev: len(ev) == 1, 10, "first event")
        broker.send_signal(signal.SIGKILL)
        broker.wait(5)
        st.broker()
        with st.client() as c:
            c.submit_many([new_message("noop.job", n=i) for i in range(1, 30)])
        got += collect(sub, lambda ev: len(ev) == 29, 20, "events after the restart")
    assert [s for s, _ in got] == list(range(1, 31))
    assert [e["n"] for _, e in got] == list(range(30))
    with st.client() as c:
        c.submit(new_message("match.verified", fragment="A", other="B", verdict=True))
    with st.subscriber(0, types=["match.verified"]) as only:
        got = collect(only, lambda ev: len(ev) == 1, 10, "the filtered event")
        assert got[0][1]["type"] == "match.verified" and got[0][0] == 31
        assert only.next(0.5) is None


def test_live_subscriber_without_since_sees_only_new_events(make_station):
    st = make_station(routing={"fragment.ready": ["noop"]})
    st.broker()
    with st.client() as c:
        c.submit_many([new_message("noop.job", n=i) for i in range(5)])
        with st.subscriber(None) as sub:
            assert sub.next(0.5) is None
            c.submit(new_message("noop.job", n=99))
            seq, ev = collect(sub, lambda ev: len(ev) == 1, 10, "the new event")[0]
    assert (seq, ev["n"]) == (6, 99)


def test_since_filters_types_and_heartbeats_flow_while_other_events_do(make_station):
    """Issue 19: SINCE had no type filter, and feed heartbeats stopped while other types flowed
    (a SUB socket subscribed to a few topics heard nothing)."""
    import zmq

    from common.bus import protocol as P
    st = make_station(routing={})
    st.broker()
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, P.FEED_HEARTBEAT)  # heartbeats only
    sub.connect(f"tcp://127.0.0.1:{st.config['broker']['feed_port']}")
    beats = []
    try:
        with st.client() as c:
            start = time.monotonic()
            t_end, sent = start + 2.0, 0
            # a steady flow of other events, faster than the heartbeat, for 2 s and at least 25 events (a
            # loaded machine answers a submit in up to a few hundred ms; 10 s at most)
            while time.monotonic() < t_end or (sent < 25 and time.monotonic() < start + 10.0):
                c.submit(new_message("noop.job"))
                sent += 1
                while sub.poll(0):
                    beats.append(sub.recv_multipart())
                time.sleep(0.02)
            elapsed = time.monotonic() - start
            c.submit(new_message("match.verified", fragment="A", other="B", verdict="confirmed"))
            r = c.since(0, 1000, types=["match.verified"])
            assert [P.loads(b)["type"] for _, b in r["events"]] == ["match.verified"]
            # the filter scanned the whole log: every noop job and the verdict
            assert r["scanned_to"] == r["last_seq"] and r["last_seq"] >= sent + 1 > 20
            few = c.since(0, 5, types=["noop.job"])
            assert len(few["events"]) == 5 and few["scanned_to"] == few["events"][-1][0]
    finally:
        ctx.destroy(linger=0)
    # half of the 10 an exact clock would give (the subscription joins late, a busy loop beats late);
    # before the fix none came at all while other types flowed
    assert len(beats) >= 0.5 * elapsed / 0.2, f"{len(beats)} heartbeats in {elapsed:.1f} s of traffic (interval 0.2 s)"
