"""CURVE between hosts: only clients with an admitted key can submit jobs, publish verdicts, serve
as workers or read the feed; what travels on the wire is encrypted (common/bus/security.py)."""

from __future__ import annotations

import os
import socket
import stat
import threading
import time

import pytest
import zmq

from common.bus.client import BrokerClient, BrokerRefused, BrokerUnavailable
from common.bus.security import (AuthorizedKeys, SecurityError, authorize, check, generate_keypair,
                                  secure_client_socket)
from common.messages import new_message
from services.cli import main as tessera

from .conftest import collect, free_port, wait_for

pytestmark = pytest.mark.timeout(120)


def _security_section(keys, host="lab"):
    return "\n".join(["[security]", "curve = true",
                      f'broker_secret_key = "{keys / "broker.key_secret"}"', f'authorized_keys = "{keys / "authorized"}"',
                      f'broker_public_key = "{keys / "broker.key"}"',
                      f'secret_key = "{keys / "hosts" / (host + ".key_secret")}"']) + "\n"


@pytest.fixture
def keys(tmp_path):
    d = tmp_path / "keys"
    assert tessera(["keys", "init", str(d)]) == 0
    assert tessera(["keys", "add", "lab", "--role", "admin", "--dir", str(d)]) == 0
    return d


def test_tessera_keys_makes_private_pairs_and_admits_only_added_hosts(keys, capsys):
    assert stat.S_IMODE(os.stat(keys / "broker.key_secret").st_mode) == 0o600
    assert stat.S_IMODE(os.stat(keys / "hosts" / "lab.key_secret").st_mode) == 0o600
    assert sorted(p.name for p in (keys / "authorized").iterdir()) == ["lab.key"]
    assert "secret-key" not in (keys / "authorized" / "lab.key").read_text()
    assert tessera(["keys", "add", "lab", "--role", "admin", "--dir", str(keys)]) == 2, "an existing pair is never overwritten"
    assert tessera(["keys", "add", "../evil", "--role", "web", "--dir", str(keys)]) == 2
    assert tessera(["keys", "revoke", "lab", "--dir", str(keys)]) == 0
    capsys.readouterr()
    assert tessera(["keys", "list", "--dir", str(keys)]) == 0
    assert capsys.readouterr().out.strip() == ""


def test_missing_or_wrong_key_files_are_named(keys, tmp_path):
    cfg = {"security": {"curve": True, "broker_public_key": str(keys / "broker.key"),
                        "secret_key": str(keys / "hosts" / "nobody.key_secret")}}
    with pytest.raises(SecurityError, match="nobody.key_secret"):
        check(cfg, "client")
    cfg["security"]["secret_key"] = str(keys / "broker.key")  # public half only
    with pytest.raises(SecurityError, match="only a public key"):
        check(cfg, "client")
    with pytest.raises(SecurityError, match="authorized_keys"):
        check({"security": {"curve": True, "broker_secret_key": str(keys / "broker.key_secret")}}, "broker")


@pytest.mark.parametrize("command", [["web", "--no-scanner"], ["scanner", "--count", "1"]])
def test_the_pages_and_the_bench_stop_at_start_on_a_missing_key_file(keys, tmp_path, command, capsys):
    """docs/security.md: a missing key file stops a client at start with one line naming the setting and the
    file. ``tessera web`` and ``tessera scanner`` connect to the broker only when they first send, so they
    started and logged a SecurityError at every drain or request instead."""
    cfg = tmp_path / "station.toml"
    cfg.write_text(_security_section(keys, host="nobody") + f'[storage]\nroot = "{tmp_path / "root"}"\n')
    code = tessera([*command, "--config", str(cfg)])
    out = capsys.readouterr()
    assert code == 2 and "nobody.key_secret" in out.out + out.err


class _Tap(threading.Thread):
    """A TCP relay that records every byte between a client and the broker."""

    def __init__(self, target_port: int):
        super().__init__(daemon=True)
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.target = target_port
        self.seen = bytearray()

    def run(self):
        conn, _ = self.server.accept()
        up = socket.create_connection(("127.0.0.1", self.target))

        def pump(a, b):
            try:
                while data := a.recv(65536):
                    self.seen += data
                    b.sendall(data)
            except OSError:
                pass
        threading.Thread(target=pump, args=(up, conn), daemon=True).start()
        pump(conn, up)


def test_only_admitted_keys_can_submit_serve_or_listen_and_the_wire_is_encrypted(make_station, keys, tmp_path):
    st = make_station(extra=_security_section(keys))
    st.broker()
    st.worker()
    st.workers_ready(1)
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    intruder = tmp_path / "intruder"
    generate_keypair(intruder, "mallory")  # a valid key pair the broker was never told about
    bad_cfg = {"security": dict(st.config["security"], secret_key=str(intruder / "mallory.key_secret"))}

    ctx = zmq.Context()
    spy = secure_client_socket(ctx.socket(zmq.SUB), bad_cfg)  # an unknown key reading the feed
    spy.setsockopt(zmq.SUBSCRIBE, b"")
    spy.connect(f"tcp://127.0.0.1:{st.config['broker']['feed_port']}")
    try:
        job = new_message("noop.job", n=1)
        verdict = new_message("match.verified", fragment="A", other="B", verdict="confirmed", by="mallory")
        for label, sec in (("unknown key", bad_cfg), ("no CURVE at all", {})):
            with BrokerClient(endpoint, timeout_s=0.7, retries=2, security=sec) as c:
                for ev in (new_message("noop.job", n=2), verdict):
                    with pytest.raises(BrokerUnavailable):
                        c.submit(ev)
        intruder_worker = st.spawn("worker", "noop", "--set", f'security.secret_key="{intruder / "mallory.key_secret"}"')
        tap = _Tap(st.config["broker"]["port"])
        tap.start()
        with BrokerClient(f"tcp://127.0.0.1:{tap.port}", timeout_s=2, retries=2, security=st.config) as c:
            c.submit(job)  # the admitted key, through the tap
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: any(e["type"] == "noop.done" for _, e in ev), 20, "the admitted job")
        time.sleep(1.0)
        status = st.status()
        assert spy.poll(200) == 0, "an unknown key receives nothing from the feed"
    finally:
        ctx.destroy(linger=0)
    types = [e["type"] for _, e in events]
    assert "match.verified" not in types and types.count("noop.job") == 1, f"only the admitted job got in: {types}"
    assert [e["job"] for _, e in events if e["type"] == "noop.done"] == [job["uid"]]
    workers = [w for ws in status["workers"].values() for w in ws]
    assert len(workers) == 1 and workers[0]["pid"] != intruder_worker.pid, "the unknown worker was not admitted"
    assert intruder_worker.poll() is None, "it keeps knocking, harmlessly"
    assert len(tap.seen) > 200 and job["uid"].encode() not in tap.seen and b"noop.job" not in tap.seen, \
        "the event crossed the wire encrypted"


def test_revoked_key_is_refused_on_its_next_connection_without_broker_restart(make_station, keys):
    assert tessera(["keys", "add", "desk", "--role", "admin", "--dir", str(keys)]) == 0
    st = make_station(extra=_security_section(keys))
    broker = st.broker()
    st.worker()
    st.workers_ready(1)
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    desk = {"security": dict(st.config["security"], secret_key=str(keys / "hosts" / "desk.key_secret"))}
    with BrokerClient(endpoint, timeout_s=2, retries=2, security=desk) as c:
        c.submit(new_message("noop.job", n=1))  # admitted
    assert tessera(["keys", "revoke", "desk", "--dir", str(keys)]) == 0
    with BrokerClient(endpoint, timeout_s=0.7, retries=2, security=desk) as c:
        with pytest.raises(BrokerUnavailable):
            c.submit(new_message("noop.job", n=2))  # the same client, a new connection: refused
    with BrokerClient(endpoint, timeout_s=2, retries=2, security=st.config) as c:
        c.submit(new_message("noop.job", n=3))  # other hosts' keys are unaffected
    authorize(keys / "hosts" / "desk.key", keys / "authorized")  # re-admitted: accepted again
    with BrokerClient(endpoint, timeout_s=2, retries=2, security=desk) as c:
        c.submit(new_message("noop.job", n=4))
    with st.subscriber(0) as sub:
        events = collect(sub, lambda ev: sum(e["type"] == "noop.done" for _, e in ev) >= 3, 20, "three jobs done")
    assert sorted(e["n"] for _, e in events if e["type"] == "noop.job") == [1, 3, 4]
    assert broker.poll() is None and st.procs[0] is broker, "the same broker process throughout"


def test_authorized_keys_follow_the_directory_and_fail_closed(keys, tmp_path):
    import zmq.auth
    d = keys / "authorized"
    provider = AuthorizedKeys(d)
    lab, _ = zmq.auth.load_certificate(str(keys / "hosts" / "lab.key"))
    assert provider.callback("*", lab)
    generate_keypair(keys / "hosts", "desk", authorize_in=d)
    desk, _ = zmq.auth.load_certificate(str(keys / "hosts" / "desk.key"))
    assert provider.callback("*", desk), "a key copied in is admitted at its first handshake"
    (d / "junk.key").write_text("not a key file\n")
    assert provider.callback("*", lab) and provider.callback("*", desk), "a malformed file spoils nothing else"
    (d / "lab.key").unlink()
    assert not provider.callback("*", lab), "a removed key is refused at once"
    assert provider.callback("*", desk)
    d.rename(tmp_path / "moved")
    assert not provider.callback("*", desk), "no directory: nobody is admitted"


def test_a_key_may_only_serve_and_submit_as_its_role(make_station, keys, tmp_path):
    """Issue 19: with CURVE on, the web host's key registered as a solver. Now a key's role decides."""
    for name, role in (("web1", "web"), ("solver1", "solver"), ("bench1", "scanner"), ("reader", "subscriber"),
                       ("benchpc", "bench")):
        assert tessera(["keys", "add", name, "--role", role, "--dir", str(keys)]) == 0
    st = make_station(extra=_security_section(keys), routing={"noop.job": ["noop"], "fragment.ready": ["solver"],
                                                                "match.verified": ["noop"]})
    st.broker()
    as_key = lambda name: ["--set", f'security.secret_key="{keys / "hosts" / (name + ".key_secret")}"']  # noqa: E731
    web_worker = st.spawn("worker", "noop", *as_key("web1"))        # the web host's key as a worker
    st.worker()                                                     # the admin key serves noop
    st.workers_ready(1)
    time.sleep(1.5)
    workers = [w for ws in st.status()["workers"].values() for w in ws]
    assert [w["service"] for w in workers] == ["noop"] and workers[0]["pid"] != web_worker.pid
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"

    def client(name):
        return BrokerClient(endpoint, timeout_s=2, retries=1,
                            security={"security": dict(st.config["security"],
                                                       secret_key=str(keys / "hosts" / f"{name}.key_secret"))})
    verdict = new_message("match.verified", fragment="A", other="B", verdict="confirmed")
    with client("web1") as c:
        with pytest.raises(BrokerRefused, match="role 'web' may not submit noop.job"):
            c.submit(new_message("noop.job"))
        c.submit(verdict)
        assert c.status()["workers"], "any role may read the status"
    with client("reader") as c:
        with pytest.raises(BrokerRefused, match="may not submit"):
            c.submit(new_message("match.verified", fragment="A", other="C", verdict="rejected"))
        with pytest.raises(BrokerRefused, match="may not re-run"):
            c.rerun("all")
        assert c.since(0)["events"], "a subscriber reads the history"
    with client("bench1") as c:
        with pytest.raises(BrokerRefused, match="may not submit match.verified"):
            c.submit(new_message("match.verified", fragment="A", other="D", verdict="rejected"))
    # a bench PC's `tessera web` scans and reviews under its one key (with "scanner" its verdicts were refused,
    # with "web" its captures); it may not serve a stage or submit what neither page makes
    art = {"path": "fragments/F9/scans/scans-9.h5", "sha256": "9" * 64, "bytes": 10}
    with client("benchpc") as c:
        c.submit(new_message("fragment.ready", fragment="F9", artifact=art))
        c.submit(new_message("match.verified", fragment="A", other="E", verdict="confirmed"))
        with pytest.raises(BrokerRefused, match="role 'bench' may not submit noop.job"):
            c.submit(new_message("noop.job"))
    s = st.status()
    assert s["refused"].get("role", 0) >= 5, s["refused"]
    assert web_worker.poll() is None, "the refused worker keeps knocking, harmlessly"


def _renderer_holding_a_job(make_station, keys, pid):
    """A CURVE station, a renderer-role key ``render1`` and a fake renderer worker under it that holds one
    rgbn.ready job: (station, worker, the job's artifact). The caller closes the worker."""
    from .test_broker import _FakeWorker

    assert tessera(["keys", "add", "render1", "--role", "renderer", "--dir", str(keys)]) == 0
    st = make_station(extra=_security_section(keys), routing={"rgbn.ready": ["renderer"]})
    st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    as_renderer = {"security": dict(st.config["security"], secret_key=str(keys / "hosts" / "render1.key_secret"))}
    art = {"path": "fragments/F1/rgbn/front-1.h5", "sha256": "1" * 64, "bytes": 10}
    w = _FakeWorker(endpoint, pid, service=b"renderer", security=as_renderer)
    try:
        with BrokerClient(endpoint, timeout_s=5, retries=2, security=st.config) as c:
            c.submit(new_message("rgbn.ready", fragment="F1", face="front", artifact=art))
        wait_for(lambda: w.pump(0.1) or w.jobs, 15, "the renderer's fake worker to get the job")
    except BaseException:
        w.close()
        raise
    return st, w, art


def test_a_stage_key_may_announce_only_its_stages_events(make_station, keys):
    """docs/security.md: a stage's key may submit nothing. Its worker's results were journaled and routed whatever
    their type, so a renderer's key could announce a verdict; now what a stage role announces is its stage's own
    events (``broker.ROLE_ANNOUNCES``), the rest refused in the job's one input.rejected."""
    from common.bus import protocol as P

    st, w, art = _renderer_holding_a_job(make_station, keys, 335)
    try:
        done = new_message("render.ready", fragment="F1", face="front", artifact=dict(art, path="fragments/F1/render/x.h5"))
        forged = new_message("match.verified", fragment="F1", other="F2", verdict="confirmed")
        w.send(P.RESULT, w.jobs[0].encode(), P.dumps([forged, done]))
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: any(e["type"] == "input.rejected" for _, e in ev)
                             and any(e["type"] == "render.ready" for _, e in ev), 20, "the result")
    finally:
        w.close()
    kinds = [e["type"] for _, e in events]
    assert "match.verified" not in kinds and kinds.count("render.ready") == 1
    (rejected,) = [e for _, e in events if e["type"] == "input.rejected"]
    assert "a key of role 'renderer' may not announce match.verified" in rejected["error"]


@pytest.mark.parametrize("change", [["revoke", "render1"], ["role", "render1", "web"]], ids=["revoked", "re-roled"])
def test_a_key_revoked_or_re_roled_while_its_worker_holds_a_job_announces_nothing_of_another_role(
        make_station, keys, change):
    """docs/security.md: a registered worker may still return the result of the job it holds, but what a key
    announces is its role's. A key whose role has no stage (re-roled to web, or revoked: no role) was let
    announce anything, a forged verdict included; now only an admin key (or CURVE off) announces any type."""
    from common.bus import protocol as P

    st, w, art = _renderer_holding_a_job(make_station, keys, 336)
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    try:
        assert tessera(["keys", *change, "--dir", str(keys)]) == 0
        with BrokerClient(endpoint, timeout_s=5, retries=2, security=st.config) as c:
            c.status()   # a handshake: the broker reads the key directory again
        w.pump(0.2)
        done = new_message("render.ready", fragment="F1", face="front", artifact=dict(art, path="fragments/F1/render/x.h5"))
        forged = new_message("match.verified", fragment="F1", other="F2", verdict="confirmed")
        w.send(P.RESULT, w.jobs[0].encode(), P.dumps([forged, done]))
        with st.subscriber(0) as sub:
            events = collect(sub, lambda ev: any(e["type"] == "input.rejected" for _, e in ev), 20, "the result")
    finally:
        w.close()
    kinds = [e["type"] for _, e in events]
    assert "match.verified" not in kinds and "render.ready" not in kinds, kinds
    (rejected,) = [e for _, e in events if e["type"] == "input.rejected"]
    assert "returned 2 invalid event(s)" in rejected["error"] and "may not announce match.verified" in rejected["error"]


@pytest.mark.parametrize("left", ["queued", "parked"])
def test_a_ready_reclaims_only_a_job_last_given_to_its_own_key(make_station, keys, left):
    """docs/security.md: a READY naming a job (a worker reconnecting mid-job) was taken for any queued or parked
    job of the service, so a host with a stage key could name another host's job (ids are derivable from the
    feed) and complete it with a forged result. Now the claim holds only for the key the job was last given to:
    another key's claim is refused (counted ``not-holder``), its result ignored; the job's own worker, back
    under its key, gets it back and its result completes it."""
    from common.bus import protocol as P

    from .test_broker import _FakeWorker

    for name in ("render1", "render2"):
        assert tessera(["keys", "add", name, "--role", "renderer", "--dir", str(keys)]) == 0
    st = make_station(extra=_security_section(keys), routing={"rgbn.ready": ["renderer"]})
    st.broker()
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"

    def as_key(name):
        return {"security": dict(st.config["security"], secret_key=str(keys / "hosts" / f"{name}.key_secret"))}
    art = {"path": "fragments/F1/rgbn/front-1.h5", "sha256": "1" * 64, "bytes": 10}
    job = new_message("rgbn.ready", fragment="F1", face="front", artifact=art)

    def render(by):
        return P.dumps([new_message("render.ready", fragment="F1", face="front", by=by,
                                    artifact=dict(art, path=f"fragments/F1/render/{by}.h5"))])
    workers = []

    def worker(pid, key, claim=None):
        workers.append(_FakeWorker(endpoint, pid, service=b"renderer", security=as_key(key), claim=claim))
        return workers[-1]
    try:
        with st.client() as c:
            w1 = worker(501, "render1")
            c.submit(job)
            wait_for(lambda: w1.pump(0.1) or w1.jobs, 10, "render1's worker to get the job")
            jid = w1.jobs[0]
            if left == "queued":   # its connection is lost mid-job: declared dead, the job re-queued
                w1.sock.close()
                wait_for(lambda: not c.status()["in_flight"], 10, "the job to be re-queued")
            else:                  # parked meanwhile (its connection lost after that)
                w1.send(P.FAIL, jid.encode(), P.FAIL_REJECTED, b"unreadable")
                wait_for(lambda: c.status()["parked"], 10, "the job to be parked")
                w1.sock.close()
            w2 = worker(502, "render2", claim=jid)   # another host of the same role names that job
            w2.pump(0.4)
            s = c.status()
            assert w2.jobs == [] and s["in_flight"] == [], "render2 was not given the job"
            assert s["refused"].get("not-holder", 0) == 1, s["refused"]
            assert (s["queues"].get("renderer", 0), len(s["parked"])) == ((1, 0) if left == "queued" else (0, 1))
            back = worker(501, "render1", claim=jid)  # the job's own worker, reconnected under its key
            back.pump(0.3)
            if left == "queued":
                assert [(j["job"], j["worker"]) for j in c.status()["in_flight"]] == [(jid, "fake:501")]
            w2.send(P.RESULT, jid.encode(), render("render2"))   # a forged result: ignored
            _pump_all = lambda: [w.pump(0.05) for w in (w2, back)]  # noqa: E731
            _pump_all()
            _pump_all()
            s = c.status()
            assert s["completed"] == 0, "render2's result completed nothing"
            assert s["refused"].get("not-holder", 0) == 2, ("the claim and the result", s["refused"])
            w2.send(P.FAIL, jid.encode(), P.FAIL_REJECTED, b"forged")   # a forged failure: ignored, counted too
            _pump_all()
            _pump_all()
            s = c.status()
            assert s["refused"].get("not-holder", 0) == 3, ("the claim, the result and the failure", s["refused"])
            assert (len(s["parked"]), s["completed"]) == ((0 if left == "queued" else 1), 0), "the failure changed nothing"
            back.send(P.RESULT, jid.encode(), render("render1"))
            wait_for(lambda: _pump_all() and c.status()["completed"] == 1, 10, "render1's result to complete it")
            s = c.status()
            assert s["in_flight"] == [] and s["parked"] == [] and s["queues"].get("renderer", 0) == 0
            events = c.since(0, 100)["events"]
        renders = [d["by"] for d in (P.loads(e) for _, e in events) if d["type"] == "render.ready"]
        assert renders == ["render1"], renders
    finally:
        for w in workers[1:]:
            w.close()


def test_keys_list_shows_roles_and_role_changes_them(keys, capsys):
    assert tessera(["keys", "add", "w", "--role", "web", "--dir", str(keys)]) == 0
    assert tessera(["keys", "role", "w", "subscriber", "--dir", str(keys)]) == 0
    capsys.readouterr()
    assert tessera(["keys", "list", "--dir", str(keys)]) == 0
    listing = capsys.readouterr().out
    assert "w " in listing and "subscriber" in listing and "admin" in listing
    provider = AuthorizedKeys(keys / "authorized")
    from common.bus.security import read_role
    assert read_role(keys / "authorized" / "w.key") == "subscriber"
    assert sorted(provider._roles.values()) == ["admin", "subscriber"]


def test_a_malformed_key_file_is_skipped_and_a_faulty_check_refuses_one_handshake(keys, caplog):
    """docs/security.md: a malformed file in the key directory is skipped with a warning. A ``public-key`` line
    without ``=`` made zmq raise IndexError, which was not caught: the ZAP thread died and every host was
    locked out until a restart (at start-up the broker stopped with a traceback)."""
    import zmq.auth
    d = keys / "authorized"
    lab, _ = zmq.auth.load_certificate(str(keys / "hosts" / "lab.key"))
    (d / "typo.key").write_text("metadata\ncurve\n    public-key\n")   # hand-edited, '= "…"' missing
    provider = AuthorizedKeys(d)   # at start-up
    assert provider.callback("*", lab), "the other keys stay valid"
    assert any(r.levelname == "WARNING" and "typo.key" in r.getMessage() for r in caplog.records)
    (d / "typo2.key").write_text("metadata\ncurve\n    public-key\n")  # while running
    assert provider.callback("*", lab)

    def broken():
        raise RuntimeError("unexpected")
    provider.refresh = broken
    assert provider.callback("*", lab) is False, "a check that fails refuses that handshake, it does not raise"


def test_a_dangling_key_entry_spoils_no_other_key(keys, caplog):
    """A dangling ``*.key`` symlink (or a file deleted by ``keys revoke`` between listing and stat) made the whole
    directory count as unreadable: nobody was admitted. Now only that entry is skipped, with a warning."""
    import zmq.auth
    d = keys / "authorized"
    lab, _ = zmq.auth.load_certificate(str(keys / "hosts" / "lab.key"))
    (d / "old-host.key").symlink_to(keys / "no-such-file.key")
    provider = AuthorizedKeys(d)
    assert provider.callback("*", lab)
    assert any(r.levelname == "WARNING" and "old-host.key" in r.getMessage() for r in caplog.records)


def test_an_unreadable_key_directory_admits_nobody_and_says_so_as_an_error(keys, monkeypatch, caplog):
    """docs/security.md: an unreadable directory admits nobody, logged as an error. Path.glob hides a
    PermissionError as an empty listing, so only a warning about removed keys was logged. (Tests run as root,
    which reads a mode 000 directory: the refusal is simulated.)"""
    import zmq.auth
    d = keys / "authorized"
    lab, _ = zmq.auth.load_certificate(str(keys / "hosts" / "lab.key"))
    provider = AuthorizedKeys(d)
    assert provider.callback("*", lab)

    def refused(path="."):
        raise PermissionError(13, "Permission denied", str(path))
    monkeypatch.setattr(os, "scandir", refused)
    assert not provider.callback("*", lab)
    assert any(r.levelname == "ERROR" and str(d) in r.getMessage() for r in caplog.records), caplog.text


def test_a_worker_whose_key_is_revoked_returns_its_job_and_gets_no_other(make_station, keys):
    """docs/security.md: a registered worker whose key is revoked may return the job it holds, and no more.
    The broker never looked at the role again once a worker was registered, so it kept giving it jobs."""
    from common.bus import protocol as P

    st, w, art = _renderer_holding_a_job(make_station, keys, 338)
    endpoint = f"tcp://127.0.0.1:{st.config['broker']['port']}"
    try:
        assert tessera(["keys", "revoke", "render1", "--dir", str(keys)]) == 0
        with BrokerClient(endpoint, timeout_s=5, retries=2, security=st.config) as c:
            c.status()   # a handshake: the broker reads the key directory again
            c.submit(new_message("rgbn.ready", fragment="F2", face="front",
                                 artifact=dict(art, path="fragments/F2/rgbn/front-1.h5")))
        w.pump(0.3)
        done = new_message("render.ready", fragment="F1", face="front", artifact=dict(art, path="fragments/F1/render/x.h5"))
        w.send(P.RESULT, w.jobs[0].encode(), P.dumps([done]))
        wait_for(lambda: w.pump(0.1) or P.DISCONNECT in w.told, 10, "the broker to tell the revoked worker to go")
        w.pump(0.5)
        status = st.status()
    finally:
        w.close()
    assert len(w.jobs) == 1, f"the revoked worker got another job: {w.jobs}"
    assert status["queues"]["renderer"] == 1 and status["completed"] == 1, status
    assert not status["workers"], status["workers"]


@pytest.mark.parametrize("verb", [["revoke", "../broker"], ["role", "../broker", "web"], ["revoke", "a/b"]])
def test_keys_revoke_and_role_refuse_names_that_are_paths(keys, verb, capsys):
    """``tessera keys revoke ../broker`` deleted the broker's public key: revoke and role now take only the names
    ``keys add`` makes."""
    before = sorted(p.name for p in keys.rglob("*"))
    broker_key = (keys / "broker.key").read_text()
    assert tessera(["keys", *verb, "--dir", str(keys)]) == 2
    assert "name" in capsys.readouterr().err
    assert sorted(p.name for p in keys.rglob("*")) == before and (keys / "broker.key").read_text() == broker_key
