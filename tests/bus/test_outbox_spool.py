"""A spooled artifact that can never be uploaded is set aside, not retried forever
(docs/storage.md, "Spool and outbox at the bench"): the entries behind it — verdicts, catalogue
edits — go on. Storage that cannot take the upload just now still only pauses the drain."""

from __future__ import annotations

import errno

import pytest

from common.bus.outbox import Outbox
from common.messages import new_message
from common.store import Store, StorageFull, StorageUnavailable

from .test_outbox_versions import _Accepting


def _bench(tmp_path):
    """An outbox whose head entry is a spooled scan, followed by a verdict and a catalogue edit."""
    box = Outbox(tmp_path / "bench")
    ref = box.spool.write("fragments/F0/scans/scans-0.h5", "tessera.scans", 1, lambda f: f.create_dataset("x", data=[0]))
    box.put(new_message("fragment.ready", fragment="F0", artifact=ref), spooled=ref.path, sha256=ref.sha256)
    behind = [new_message("match.verified", fragment="A", other="B", verdict="confirmed"),
              new_message("fragment.annotated", fragment="A", by="x", changes={"notes": "n"})]
    for e in behind:
        box.put(e)
    return box, ref, [e["uid"] for e in behind]


@pytest.mark.parametrize("bad", ["corrupt", "missing", "other-on-storage"])
def test_an_upload_that_can_never_succeed_is_set_aside_and_the_rest_goes_out(tmp_path, bad):
    box, ref, behind = _bench(tmp_path)
    storage = Store(tmp_path / "storage")
    spooled = box.spool.path(ref.path)
    if bad == "corrupt":
        spooled.write_bytes(spooled.read_bytes()[:-1] + b"!")
    elif bad == "missing":
        spooled.unlink()
    else:  # storage holds other bytes under that name: never replaced, never announced as ours
        storage.write(ref.path, "tessera.scans", 1, lambda f: f.create_dataset("y", data=[1]))
    client = _Accepting()
    assert box.drain(client, storage) == 3 and len(box) == 0
    assert client.sent == behind, "the entries behind the bad one are delivered, in order"
    (_, kept, reason), = box.refused()
    assert kept["fragment"] == "F0" and ref.path in reason
    if bad != "missing":
        assert spooled.is_file(), "the spool copy stays for a person to look at"
    box.close()


@pytest.mark.parametrize("exc", [StorageFull(errno.ENOSPC, "storage full: test"),
                                 StorageUnavailable("storage root gone: test")], ids=["full", "unreachable"])
def test_storage_that_cannot_take_the_upload_now_only_pauses_the_drain(tmp_path, exc):
    class Refusing(Store):
        def import_file(self, *a, **kw):
            raise exc
    box, ref, behind = _bench(tmp_path)
    client = _Accepting()
    assert box.drain(client, Refusing(tmp_path / "storage")) == 0 and len(box) == 3
    assert client.sent == [] and box.refused() == []
    assert box.drain(client, Store(tmp_path / "storage")) == 3 and box.refused() == []
    box.close()


def test_a_spooled_artifact_without_its_digest_is_refused_when_queued(tmp_path):
    """drain checks the upload against the entry's sha256; an entry with one and not the other failed there with a
    TypeError, long after the scan; now put names it at once."""
    box = Outbox(tmp_path / "bench")
    ev = new_message("match.verified", fragment="A", other="B", verdict="confirmed")
    with pytest.raises(ValueError, match="needs its sha256"):
        box.put(ev, spooled="fragments/F0/scans/scans-0.h5")
    with pytest.raises(ValueError, match="needs its sha256"):
        box.put(ev, sha256="0" * 64)
    assert len(box) == 0
