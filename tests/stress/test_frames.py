"""Random and malformed frames on every socket of the bus: nobody crashes, each case is reported.

Every socket a peer can reach is hit: the broker's ROUTER (as a client, as a worker, as
nothing at all), its PUB feed (subscriptions and raw bytes), raw non-ZMTP bytes on both TCP
ports, and a worker's DEALER (from a fake broker it connects to). Counts and durations are
bounded; only loopback addresses are used. Afterwards the broker and workers are alive, the
feed is gap-free and good jobs submitted around the garbage are done exactly once.
"""

from __future__ import annotations

import os
import random
import socket
import subprocess
import sys
import time

import msgpack
import pytest
import zmq

from common import messages
from common.bus import protocol as P
from common.messages import VERSION, new_message
from tests.bus.conftest import REPO, collect, free_port, wait_for

pytestmark = pytest.mark.timeout(120)

COMMANDS = [P.READY, P.HEARTBEAT, P.PROGRESS, P.RESULT, P.FAIL, P.DISCONNECT, P.JOB,
            P.SUBMIT, P.STATUS, P.RERUN, P.SINCE, b"", b"\x00", b"BOGUS"]
HEADERS = [P.WORKER, P.CLIENT, b"", b"TW2", b"\xff" * 3]


def _dealer(ctx, endpoint: str, identity: bytes | None = None):
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 500)
    s.setsockopt(zmq.SNDHWM, 100000)
    if identity:
        s.setsockopt(zmq.ROUTING_ID, identity)
    s.connect(endpoint)
    return s


def _odd_msgpack(rng: random.Random) -> bytes:
    """msgpack of a value of the wrong shape: scalars, lists, maps with odd keys and values."""
    choices = [0, -1, 2**63, 1.5, float("nan"), "", "x" * rng.randint(0, 300), b"\x00\xff", None, True,
               [], [1, "a"], {}, {"job": 3}, {"fraction": "x", "text": []}, {1: 2}, {"after": "x"},
               {"after": -5, "limit": 10**12}, {"job": ["all"]}, {"host": None, "pid": "pid"}]
    return msgpack.packb(rng.choice(choices), use_bin_type=True)


def _bad_event(rng: random.Random) -> bytes:
    """A message that looks almost right: valid msgpack, one field of a wrong type or value."""
    base = {"v": VERSION, "type": "noop.job", "uid": os.urandom(16).hex(), "time": time.time()}
    key, value = rng.choice([("time", "yesterday"), ("time", [1]), ("time", None), ("uid", [1, 2]),
                             ("uid", {"a": 1}), ("v", "1"), ("type", 7), ("artifact", "here"),
                             ("artifact", {"path": 1}), ("type", "fragment.ready")])
    base[key] = value
    return msgpack.packb(base, use_bin_type=True)


def _random_frames(rng: random.Random) -> list[bytes]:
    kind = rng.random()
    if kind < 0.25:  # pure noise, any shape
        return [os.urandom(rng.randint(0, 64)) for _ in range(rng.randint(1, 7))]
    header = rng.choice(HEADERS)
    command = rng.choice(COMMANDS)
    n = rng.randint(0, 4)
    rest = [rng.choice([os.urandom(rng.randint(0, 40)), _odd_msgpack(rng), _bad_event(rng), b"", b"1-noop"])
            for _ in range(n)]
    lead = [b""] if rng.random() < 0.9 else [os.urandom(3)]
    return [*lead, header, command, *rest]


def _events(st, since=0):
    with st.client() as c:
        out, after = [], since
        while True:
            r = c.since(after, 5000)
            if not r["events"]:
                return out
            for seq, body in r["events"]:
                out.append((seq, messages.unpack(body)))
                after = seq


def _rejections(events) -> list[str]:
    return [e["error"] for _, e in events if e["type"] == "input.rejected"]


def _err_reply(sock, timeout_s: float = 5.0):
    """The next ERR reply on ``sock`` (skipping heartbeats), or None."""
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        if not sock.poll(left * 1000):
            return None
        frames = sock.recv_multipart()
        if len(frames) >= 5 and frames[1] == P.CLIENT and frames[2] == P.ERR:
            return msgpack.unpackb(frames[4])
    return None


def test_malformed_frames_of_every_kind_each_get_an_err_reply_and_are_counted(make_station):
    st = make_station()
    broker = st.broker()
    worker = st.worker()
    st.workers_ready(1)
    ctx = zmq.Context()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    fake = _dealer(ctx, endpoint, b"fuzz-worker")
    # a registered worker of a service nothing routes to (it never gets jobs) sends bad bodies
    fake.send_multipart([b"", P.WORKER, P.READY, b"fuzz", P.dumps({"host": "fuzz", "pid": 1})])
    cases = {
        "no delimiter": [b"garbage"],
        "unknown header": [b"", b"XX9", b"HELLO"],
        "ready info not a map": [b"", P.WORKER, P.READY, b"fuzz2", P.dumps([1, 2])],
        "ready pid not a number": [b"", P.WORKER, P.READY, b"fuzz3", P.dumps({"pid": "one"})],
        "ready service not a name": [b"", P.WORKER, P.READY, b"../x", P.dumps({"pid": 1})],
        "fail without parts": [b"", P.WORKER, P.FAIL],
        "unknown worker command": [b"", P.WORKER, b"EXPLODE"],
        "since body not a map": [b"", P.CLIENT, P.SINCE, b"t1", P.dumps([0])],
        "since after not a number": [b"", P.CLIENT, P.SINCE, b"t2", P.dumps({"after": "x"})],
        "rerun body not a map": [b"", P.CLIENT, P.RERUN, b"t3", P.dumps("all")],
        "rerun without job": [b"", P.CLIENT, P.RERUN, b"t3b", P.dumps({})],
        "unknown client command": [b"", P.CLIENT, b"BOGUS", b"t3c", b""],
        "submit time not a number": [b"", P.CLIENT, P.SUBMIT, b"t4", msgpack.packb(
            {"v": VERSION, "type": "noop.job", "uid": "a" * 32, "time": "yesterday"})],
        "submit uid not hashable": [b"", P.CLIENT, P.SUBMIT, b"t5", msgpack.packb(
            {"v": VERSION, "type": "noop.job", "uid": [1], "time": 1.0})],
        "submit uid 2**64-1": [b"", P.CLIENT, P.SUBMIT, b"t6", msgpack.packb(
            {"v": VERSION, "type": "noop.job", "uid": 2**64 - 1, "time": 1.0})],
        "submit fragment a path": [b"", P.CLIENT, P.SUBMIT, b"t7", msgpack.packb(
            {"v": VERSION, "type": "noop.job", "uid": "b" * 32, "time": 1.0, "fragment": "a/b/c"})],
        "submit nested 1000 deep": [b"", P.CLIENT, P.SUBMIT, b"t8", msgpack.packb(
            {"v": VERSION, "type": "noop.job", "uid": "c" * 32, "time": 1.0, "x": _nested(1000)})],
        "submit too large": [b"", P.CLIENT, P.SUBMIT, b"t9", msgpack.packb(
            {"v": VERSION, "type": "noop.job", "uid": "d" * 32, "time": 1.0, "x": ["y" * 1000] * 1000})],
    }
    good = [new_message("noop.job", n=i) for i in range(2)]
    answers = {}
    try:
        with st.client() as c:
            c.submit(good[0])
            time.sleep(0.3)  # the fake worker's READY is in before its bad bodies
            for name, frames in cases.items():
                sock = fake if frames[1:2] == [P.WORKER] and frames[2] not in (P.READY,) else _dealer(ctx, endpoint)
                sock.send_multipart(frames)
                answers[name] = _err_reply(sock)
            c.submit(good[1])
            want = {g["uid"] for g in good}  # done, and their events journaled and on the feed
            wait_for(lambda: {e["job"] for _, e in _events(st) if e["type"] == "noop.done"} >= want, 20,
                     "the good jobs to be done")
            refused = c.status()["refused"]
            events = _events(st)
    finally:
        ctx.destroy(linger=0)
    assert broker.poll() is None and worker.poll() is None, st.logs()
    silent = [n for n, a in answers.items() if not (isinstance(a, dict) and a.get("error"))]
    assert not silent, f"no ERR reply for {silent}"
    assert "64-bit" in answers["submit uid 2**64-1"]["error"] and "fragment" in answers["submit fragment a path"]["error"]
    assert "deeper" in answers["submit nested 1000 deep"]["error"]
    assert "bytes refused" in answers["submit too large"]["error"]
    assert sum(refused.values()) >= len(cases), refused
    seqs = [s for s, _ in events]
    assert seqs == list(range(1, len(seqs) + 1)), "the feed has no gaps after bad submissions"
    assert len(_rejections(events)) == 1, "one summary event for the lot, not one per frame"
    done = {e["job"] for _, e in events if e["type"] == "noop.done"}
    assert done == {g["uid"] for g in good}, "the good jobs are done, once each"


def _nested(depth: int):
    obj = []
    for _ in range(depth - 1):
        obj = [obj]
    return obj


def test_random_frames_on_the_router_crash_nothing_and_lose_nothing(make_station):
    rng = random.Random(20261122)
    st = make_station()
    broker = st.broker()
    worker = st.worker()
    st.workers_ready(1)
    ctx = zmq.Context()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    good = [new_message("noop.job", n=i) for i in range(20)]
    sent = 0
    deadline = time.monotonic() + 8.0
    socks = [_dealer(ctx, endpoint, f"fuzz-{i}".encode()) for i in range(4)]
    try:
        with st.client() as c:
            for g in good:
                c.submit(g)
                for _ in range(100):
                    rng.choice(socks).send_multipart(_random_frames(rng))
                    sent += 1
                if time.monotonic() > deadline:
                    break
            submitted = {g["uid"] for g in good[: good.index(g) + 1]}
            wait_for(lambda: c.status()["completed"] >= len(submitted), 30, "the good jobs")
            # "completed" counts a result when it arrives; its event is published once journaled
            wait_for(lambda: {e["job"] for _, e in _events(st) if e["type"] == "noop.done"} >= submitted, 10,
                     "the good jobs' events on the feed")
            events = _events(st)
    finally:
        ctx.destroy(linger=0)
    assert broker.poll() is None, f"broker crashed after {sent} random messages:\n{st.logs()}"
    assert worker.poll() is None, st.logs()
    seqs = [s for s, _ in events]
    assert seqs == list(range(1, len(seqs) + 1)), "feed without gaps"
    done = [e["job"] for _, e in events if e["type"] == "noop.done"]
    assert sorted(done) == sorted(submitted), "every good job done exactly once"
    with st.client() as c:
        refused = sum(c.status()["refused"].values())
    assert refused > sent // 4, f"random frames are counted as refused ({refused} of {sent})"
    assert len(_rejections(events)) <= 2, "refused frames are summarised, not journaled one by one"


def test_raw_bytes_and_odd_subscriptions_on_both_ports_leave_the_broker_serving(make_station):
    rng = random.Random(7)
    st = make_station()
    broker = st.broker()
    st.worker()
    st.workers_ready(1)
    ports = (st.config["broker"]["port"], st.config["broker"]["feed_port"])
    for port in ports:
        for i in range(30):  # not ZeroMQ at all, a truncated greeting, a greeting then noise
            payload = [os.urandom(rng.randint(1, 2000)), b"\xff" + b"\x00" * 8 + b"\x7f",
                       b"\xff" + b"\x00" * 8 + b"\x7f\x03\x00NULL" + os.urandom(300)][i % 3]
            with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
                try:
                    s.sendall(payload)
                except OSError:
                    pass  # the peer may hang up first: that is the point
    ctx = zmq.Context()
    try:
        xsub = ctx.socket(zmq.XSUB)
        xsub.connect(f"tcp://127.0.0.1:{ports[1]}")
        for _ in range(200):
            xsub.send(rng.choice([b"\x01" + os.urandom(rng.randint(0, 50)), b"\x00", os.urandom(10), b""]))
        time.sleep(0.5)
    finally:
        ctx.destroy(linger=0)
    job = new_message("noop.job")
    with st.client() as c:
        c.submit(job)
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: any(e["type"] == "noop.done" for _, e in ev), 20, "the job done")
    assert broker.poll() is None, st.logs()
    assert [e["job"] for _, e in events if e["type"] == "noop.done"] == [job["uid"]]


def _fake_broker_config(tmp_path, port):
    cfg = tmp_path / "worker.toml"
    cfg.write_text("\n".join([
        "[storage]", f'root = "{tmp_path / "storage"}"',
        "[broker]", 'host = "127.0.0.1"', f"port = {port}", "heartbeat_interval_s = 0.2", "heartbeat_liveness = 50",
        "[worker]", "reconnect_min_s = 0.1", "reconnect_max_s = 0.5", "shutdown_grace_s = 2.0"]) + "\n")
    return cfg


def test_a_worker_survives_malformed_frames_from_its_broker(tmp_path):
    rng = random.Random(11)
    port = free_port()
    ctx = zmq.Context()
    router = ctx.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    router.bind(f"tcp://127.0.0.1:{port}")
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    log = open(tmp_path / "worker.log", "wb")
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())",
                             "worker", "noop", "--config", str(_fake_broker_config(tmp_path, port))],
                            stdout=log, stderr=subprocess.STDOUT, env=env)

    def replies(want: bytes, timeout: float):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if router.poll(100):
                frames = router.recv_multipart()
                if frames[3:4] == [want]:
                    return frames
        return None

    try:
        ready = replies(P.READY, 20)
        assert ready is not None, (tmp_path / "worker.log").read_text()
        ident = ready[0]
        bad = [[b"", P.WORKER, P.JOB], [b"", P.WORKER, P.JOB, b"1-noop"],
               [b"", P.WORKER, P.JOB, b"1-noop", b"first", b"\x80"], [b"", P.WORKER, P.JOB, b"\xff\xfe", b"1", b"x"],
               [b"", P.WORKER], [b"", b"TW9", P.JOB], [], [b"\x00" * 5], [b"", P.WORKER, b"REBOOT", b"now"]]
        bad += [[os.urandom(rng.randint(0, 9)) for _ in range(rng.randint(0, 6))] for _ in range(200)]
        for frames in bad:
            router.send_multipart([ident, *frames])
        time.sleep(0.5)
        assert proc.poll() is None, "worker crashed on a malformed frame:\n" + (tmp_path / "worker.log").read_text()
        # it still does real work: a good job after the garbage gets its RESULT
        ident = (replies(P.READY, 0.2) or [ident])[0]  # it may have re-announced itself
        job = new_message("noop.job")
        router.send_multipart([ident, b"", P.WORKER, P.JOB, b"7-noop", b"1", messages.pack(job)])
        result = replies(P.RESULT, 20)
        assert result is not None and result[4] == b"7-noop", (tmp_path / "worker.log").read_text()
        assert P.loads(result[5])[0]["job"] == job["uid"]
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
        ctx.destroy(linger=0)
