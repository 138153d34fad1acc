"""The bench never blocks: scanner with the broker or the storage down, real processes."""

from __future__ import annotations

import shutil
import time

import pytest

from common.bus.client import BrokerClient
from common.bus.outbox import Outbox
from common.messages import new_message
from common.store import Store

from .conftest import collect, free_port, wait_for

pytest.importorskip("common.synth")
pytest.importorskip("common.acquisition.capture")

FAST_CAPTURE = ["--set", "scanner.colour_only=true", "--set", "scanner.prescan_dpi=25", "--set", "scanner.dpi=100",
                "--set", "scanner.wall_dpi=100", "--set", "scanner.seed=1"]


def test_broker_down_while_scanner_captures_three_fragments(make_station):
    st = make_station(services={"noop": {}})
    scanner = st.spawn("scanner", "--count", "3", *FAST_CAPTURE)
    box = st.root / "bench" / "outbox.sqlite"
    wait_for(lambda: box.exists() and len(Outbox(st.root / "bench")) == 3, 120, "three fragments captured into the outbox")
    assert scanner.poll() is None, "the scanner waits for the lab, it does not fail"
    st.broker()
    st.worker()
    with st.subscriber(0) as sub:
        events = collect(sub, lambda ev: sum(e["type"] == "noop.done" for _, e in ev) == 3, 60, "3 fragments through")
    ready = [e for _, e in events if e["type"] == "fragment.ready"]
    assert len(ready) == 3 and len({e["fragment"] for e in ready}) == 3
    store = Store(st.root / "storage")
    for e in ready:
        with store.open(e["artifact"], schema="tessera.scans") as f:
            assert f.attrs["fragment"] == e["fragment"]
    assert scanner.wait(30) == 0, "the scanner exits once its outbox is delivered"
    assert len(Outbox(st.root / "bench")) == 0


def test_outbox_spools_when_storage_is_unreachable_and_drains_in_order(tmp_path):
    """Storage (an NFS mount) missing: artifacts go to the spool, events wait; both drain in order."""
    from tests.bus.conftest import Station
    st = Station(tmp_path)
    mount = tmp_path / "nfs"
    storage = Store(mount, create=False)
    assert not storage.available()
    box = Outbox(tmp_path / "bench")
    sent = []
    for i in range(3):
        ref = box.spool.write(f"fragments/F{i}/scans/scans-{i}.h5", "tessera.scans", 1,
                              lambda f, i=i: f.create_dataset("x", data=[i]))
        ev = new_message("fragment.ready", fragment=f"F{i}", artifact=ref)
        box.put(ev, spooled=ref.path, sha256=ref.sha256)
        sent.append(ev)
    client = BrokerClient.from_config(st.config, timeout_s=0.3, retries=1)
    assert box.drain(client, storage) == 0 and len(box) == 3, "nothing leaves while storage is away"
    mount.mkdir()  # the share comes back, the broker is still down
    assert box.drain(client, storage) == 0, "the broker is down: events wait"
    assert storage.exists("fragments/F0/scans/scans-0.h5"), "the first artifact was uploaded ahead of its event"
    st.broker()
    try:
        assert box.drain(client, storage) == 3 and len(box) == 0
        with st.subscriber(0) as sub:
            got = collect(sub, lambda ev: len([e for _, e in ev if e["type"] == "fragment.ready"]) == 3, 10, "events")
        assert [e["uid"] for _, e in got if e["type"] == "fragment.ready"] == [e["uid"] for e in sent]
        for e in sent:
            with storage.open(e["artifact"]) as f:  # digest checked against the spooled original
                assert f["x"][0] == int(e["fragment"][1:])
        assert not list((tmp_path / "bench" / "spool").rglob("*.h5")), "spool emptied after upload"
    finally:
        client.close()
        st.stop()


class _Refusing:
    """A stand-in broker client answering every submit with one refusal."""

    def __init__(self, exc):
        self.exc, self.calls = exc, 0

    def submit(self, event):
        self.calls += 1
        raise self.exc


def test_outbox_keeps_an_event_the_broker_cannot_journal_now(tmp_path):
    """Issue 19: the broker's journal failed; the outbox logged "refused ... dropped" and lost a
    fragment.ready. A refusal marked retry keeps the entry in place, in order."""
    from common.bus.client import BrokerRefused
    box = Outbox(tmp_path / "bench")
    events = [new_message("fragment.ready", fragment=f"F{i}", artifact={"path": f"f{i}.h5", "sha256": "0" * 64,
                                                                         "bytes": 1}) for i in range(2)]
    for e in events:
        box.put(e)
    storage = Store(tmp_path / "storage")
    client = _Refusing(BrokerRefused("broker journal cannot write", retry=True))
    assert box.drain(client, storage) == 0 and len(box) == 2 and client.calls == 1
    client = _Refusing(BrokerRefused("fragment.ready message: fragment 'x' is wrong"))
    assert box.drain(client, storage) == 2 and len(box) == 0
    kept = box.refused()
    assert [e["uid"] for _, e, _ in kept] == [e["uid"] for e in events], "refused for good: set aside, not dropped"
    assert "is wrong" in kept[0][2]
    box.close()


def test_scanner_spools_when_the_storage_refuses_the_write(tmp_path, monkeypatch):
    """A storage that is there but refuses writes (full or read-only) sends the scans to the spool."""
    import errno

    import common.acquisition.capture as capture
    from common.store import StorageFull
    from services.scanner import store_scans

    def write_scans(store, fragment_id, result):
        return store.write(f"fragments/{fragment_id}/scans/scans-k.h5", "tessera.scans", 1,
                           lambda f: f.create_dataset("x", data=[1]))

    class FullStore(Store):
        def write(self, *a, **kw):
            raise StorageFull(errno.ENOSPC, "storage full: test")

    class Result:
        fragment_id, device, colour_only = "F0001", "sim", True

    monkeypatch.setattr(capture, "write_scans", write_scans)
    box = Outbox(tmp_path / "bench")
    event, spooled = store_scans(Result(), FullStore(tmp_path / "storage"), box)
    assert spooled and box.spool.exists(event["artifact"]["path"])
    assert [e["uid"] for _, e, s in box.pending()] == [event["uid"]]
    box.close()
