"""Tests of the catalogue: common/web/catalogue.py and the /fragments API (services/web/catalogue.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from common.matching.proposals import Proposal, ProposalStore
from common.rgbn.image import RGBNImage, save_rgbn
from common.rgbn.io import srgb_to_linear
from common.store import Store
from common.web import catalogue as cat
from common.web.catalogue import Catalogue

from .conftest import TOKEN

BEARER = {"Authorization": f"Bearer {TOKEN}"}


def _rgba(rgb, n=4):
    px = np.zeros((n, n, 4), np.uint8)
    px[..., :3] = rgb
    px[..., 3] = 255
    return px


@pytest.mark.parametrize("rgb, family", [
    ((250, 250, 245), "white"), ((128, 128, 130), "grey"), ((20, 15, 10), "black"), ((200, 30, 30), "red"),
    ((190, 110, 40), "orange"), ((220, 200, 40), "yellow"), ((40, 160, 60), "green"), ((40, 70, 200), "blue"),
    ((140, 50, 170), "purple")])
def test_colour_family_of_plain_colours(rgb, family):
    assert cat.colour_family(_rgba(rgb)) == family


def test_colour_family_is_the_most_frequent_and_ignores_pixels_off_the_fragment():
    px = _rgba((40, 70, 200), 10)
    px[:4, :, :3] = (200, 30, 30)          # 40 red, 60 blue
    px[5:, :, 3] = 0                        # ... but the lower half is off the fragment: 40 red, 10 blue
    assert cat.colour_family(px) == "red"
    px[..., 3] = 0
    assert cat.colour_family(px) == ""
    with pytest.raises(ValueError, match="rgba must be"):
        cat.colour_family(np.zeros((4, 4, 3), np.uint8))


def test_pipeline_state_is_the_last_stage_reached_without_a_gap():
    assert cat.pipeline_state({"scanned": "done", "normals": "done", "features": "waiting"}) == "normals"
    assert cat.pipeline_state({"scanned": "waiting", "normals": "done", "features": "done"}) == "features"  # imported
    assert cat.pipeline_state({"imported": "done", "normals": "done", "features": "waiting"}) == "normals"
    assert cat.pipeline_state({"scanned": "done", "normals": "failed"}) == "failed"
    assert cat.pipeline_state({"scanned": "waiting"}) == "waiting"


def test_changes_are_checked():
    assert cat.check_changes({"notes": "  x "}) == {"notes": "x"}
    for bad, phrase in (({}, "non-empty"), ({"colour": "red"}, "unknown field 'colour'"),
                        ({"notes": 3}, "must be text"), ({"notes": "x" * 2001}, "at most 2000")):
        with pytest.raises(ValueError, match=phrase):
            cat.check_changes(bad)


def _fragment(store, fid, rgb, metadata=None, size=(40, 50), face="front"):
    lin = srgb_to_linear(np.array(rgb, np.float32) / 255.0)
    albedo = np.broadcast_to(lin, size + (3,)).copy()
    attrs = {"metadata": json.dumps(metadata)} if metadata else {}
    rel = f"fragments/{fid}/rgbn/{face}-{abs(hash((fid, face))) % 10 ** 16:016d}.h5"
    save_rgbn(store, rel, RGBNImage(albedo, np.ones(size, bool), 100.0, normals=None, attrs=attrs))
    return rel


@pytest.fixture
def collection(tmp_path):
    store = Store(tmp_path / "storage")
    _fragment(store, "F001", (200, 30, 30), {"inventory": "INV-1", "find_spot": "Room 3", "context": "US 12",
                                             "date": "1st c. AD", "notes": "red band", "source_file": "a.png"})
    _fragment(store, "F002", (40, 70, 200), {"inventory": "INV-2", "find_spot": "Room 4"})
    _fragment(store, "F003", (40, 70, 200))
    (store.root / "fragments/F004/scans").mkdir(parents=True)   # scanned, not solved yet
    (store.root / "fragments/F004/scans/scans-1.h5").write_bytes(b"x")
    db = tmp_path / "proposals.sqlite"
    with ProposalStore(db) as ps:
        ps.upsert([Proposal("F001", "F002", 0.9, "m"), Proposal("F002", "F003", 0.4, "m")])
        ps.record_verdict("F001", "F002", "confirmed", by="test")
    c = Catalogue(tmp_path / "catalogue.sqlite", store, proposals=db)
    assert c.rebuild() == 4
    return store, c, db


def test_the_catalogue_is_built_from_storage_and_the_proposal_store(collection):
    store, c, db = collection
    rows = {r["id"]: r for r in c.query()["fragments"]}
    assert list(rows) == ["F001", "F002", "F003", "F004"]
    assert rows["F001"]["inventory"] == "INV-1" and rows["F001"]["date"] == "1st c. AD"
    assert rows["F001"]["extra"] == {"source_file": "a.png"}
    assert rows["F001"]["colour"] == "red" and rows["F002"]["colour"] == "blue"
    assert rows["F001"]["state"] == "normals" and rows["F004"]["state"] == "scanned"
    assert rows["F004"]["faces"] == {} and not rows["F004"]["has_thumb"]
    assert (rows["F001"]["confirmed"], rows["F001"]["pending"]) == (1, 0)
    assert (rows["F002"]["confirmed"], rows["F002"]["pending"]) == (1, 1) and rows["F003"]["pending"] == 1
    assert rows["F001"]["faces"]["front"]["width"] == 50
    thumb = c.thumbnail("F001")
    assert thumb.startswith(b"\x89PNG")


def test_search_filters_and_paging(collection):
    store, c, db = collection
    ids = lambda **kw: [r["id"] for r in c.query(**kw)["fragments"]]  # noqa: E731
    assert ids(text="room") == ["F001", "F002"] and ids(text="US 12") == ["F001"]
    assert ids(text="f00") == ["F001", "F002", "F003", "F004"] and ids(text="100%") == []
    assert ids(colour="blue") == ["F002", "F003"]
    assert ids(state="scanned") == ["F004"]
    assert ids(joins="none") == ["F004"] and ids(joins="pending", colour="blue") == ["F002", "F003"]
    assert ids(joins="confirmed") == ["F001", "F002"]
    page = c.query(page=2, per_page=3)
    assert page["total"] == 4 and [r["id"] for r in page["fragments"]] == ["F004"]
    # a page past the last is empty, however far (SQLite's OFFSET overflowed into a 500 at 2**63)
    for far in (3, 2 ** 63 - 1, 10 ** 20):
        page = c.query(page=far, per_page=3)
        assert page["total"] == 4 and page["fragments"] == [] and page["page"] == far
    for kw, phrase in (({"state": "done"}, "state must be"), ({"colour": "teal"}, "colour must be"),
                       ({"joins": "some"}, "joins must be"), ({"per_page": 0}, "per_page")):
        with pytest.raises(ValueError, match=phrase):
            c.query(**kw)


def test_annotations_apply_in_order_are_kept_on_storage_and_survive_a_rebuild(collection, tmp_path):
    from common.messages import new_message

    store, c, db = collection
    first = new_message("fragment.annotated", fragment="F002", changes={"find_spot": "Room 5", "notes": "n1"},
                        by="ann", previous={"find_spot": "Room 4"})
    second = new_message("fragment.annotated", fragment="F002", changes={"notes": "n2"}, by="bob")
    assert c.apply(first, 7) == "annotated" and c.apply(second, 8) == "annotated"
    assert c.apply(second, 8) == "annotated"                                  # replayed: no second entry
    row = c.get("F002")
    assert (row["find_spot"], row["notes"], row["inventory"]) == ("Room 5", "n2", "INV-2")
    assert [h["by"] for h in row["history"]] == ["bob", "ann"]              # newest first
    assert len(list((store.root / "fragments/F002/annotations").glob("*.json"))) == 2
    assert c.apply(new_message("fragment.annotated", fragment="NOPE", changes={"notes": "x"}, by="a")) == "ignored"
    # the index is a cache: a new one built from storage alone has the same values and history
    fresh = Catalogue(tmp_path / "other.sqlite", store, proposals=db)
    fresh.rebuild()
    again = fresh.get("F002")
    assert (again["find_spot"], again["notes"]) == ("Room 5", "n2")
    assert [h["uid"] for h in again["history"]] == [h["uid"] for h in row["history"]]
    assert c.query(text="room 5")["total"] == 1



def test_match_events_recount_the_joins_once_per_batch(collection):
    from common.messages import new_message

    store, c, db = collection
    with ProposalStore(db) as ps:
        ps.upsert([Proposal("F003", "F004", 0.7, "m")])
    event = new_message("match.proposed", fragment="F003", other="F004", probability=0.7)
    assert c.apply(event, 9) == "joins" and c.get("F004")["pending"] == 0   # not counted yet
    c.flush()
    assert c.get("F004")["pending"] == 1 and c.get("F003")["pending"] == 2


# -- the web API ---------------------------------------------------------------------------------

def test_catalogue_api_lists_filters_and_serves_thumbnails(collection):
    from services import web

    store, c, db = collection
    client = web.create_app(token=TOKEN, store_root=store.root, catalogue=c).test_client()
    assert client.get("/fragments").status_code == 200
    d = client.get("/api/catalogue?colour=blue&per_page=1").json
    assert d["total"] == 2 and [f["id"] for f in d["fragments"]] == ["F002"] and d["counts"]["total"] == 4
    assert client.get("/api/catalogue?state=nonsense").status_code == 400
    assert client.get("/api/catalogue/F001").json["inventory"] == "INV-1"
    assert client.get("/api/catalogue/F009").status_code == 404
    r = client.get("/api/catalogue/F001/thumb.png")
    assert r.status_code == 200 and r.headers["Content-Type"] == "image/png"
    assert client.get("/api/catalogue/F004/thumb.png").status_code == 404
    # writes need the token; without a broker the edit says it was not sent
    assert client.post("/api/catalogue/F001/metadata", json={"changes": {"notes": "x"}}).status_code == 401
    r = client.post("/api/catalogue/F001/metadata", json={"changes": {"notes": "x"}}, headers=BEARER)
    assert r.status_code == 503 and "not sent" in r.json["error"]
    r = client.post("/api/catalogue/F001/metadata", json={"changes": {"colour": "x"}}, headers=BEARER)
    assert r.status_code == 400 and "unknown field" in r.json["error"]
    assert web.create_app(token=TOKEN, store_root=store.root).test_client().get("/api/catalogue").status_code == 503


def test_an_imported_fragment_says_imported_with_when_and_from_what_not_scanned_waiting(tmp_path):
    """The RePAIR trial: fragments brought in by ``tessera import images`` were listed ``scanned: waiting`` (never
    scanned: imported). Their first stage is ``imported`` and the row says when, by what and from which file;
    a scanned fragment is as before."""
    import datetime as dt

    from services import web
    from services.cli import main
    from tests.imports.test_import_images import _picture

    _picture(tmp_path / "RPf_00123.png", 3, alpha=True)
    store = Store(tmp_path / "storage")
    assert main(["import", "images", str(tmp_path / "RPf_00123.png"), "--dpi", "187.2", "--store", str(store.root)]) == 0
    (store.root / "fragments/S1/scans").mkdir(parents=True)   # scanned here, not solved yet
    (store.root / "fragments/S1/scans/scans-1.h5").write_bytes(b"x")
    c = Catalogue(tmp_path / "catalogue.sqlite", store)
    assert c.rebuild() == 2
    row = c.get("RPf_00123")
    assert "scanned" not in row["stages"] and list(row["stages"])[:2] == ["imported", "normals"]
    assert row["stages"]["imported"] == "done" and row["state"] == "normals"
    assert {k: row["imported"][k] for k in ("face", "by", "file")} == {
        "face": "front", "by": "tessera import images", "file": "RPf_00123.png"}
    assert abs(dt.datetime.fromisoformat(row["imported"]["time"]).timestamp() - dt.datetime.now().timestamp()) < 600
    scanned = c.get("S1")
    assert scanned["stages"]["scanned"] == "done" and "imported" not in scanned["stages"] and scanned["imported"] is None
    assert [r["id"] for r in c.query(state="normals")["fragments"]] == ["RPf_00123"]
    got = web.create_app(token=TOKEN, store_root=store.root, catalogue=c).test_client().get("/api/catalogue/RPf_00123")
    assert got.json["imported"]["by"] == "tessera import images" and "scanned" not in got.json["stages"]


def test_a_colour_only_fragment_says_normals_not_applicable_not_done(tmp_path):
    """An imported picture (or a ``--colour-only`` scan) has no normals, yet its ``normals`` stage said ``done``:
    it says ``n/a``, in the index and the API; a fragment with normals on a face says ``done`` as before. The
    state still counts the stage passed (``normals`` until features come), and a failed solve stays failed."""
    from services import web

    store = Store(tmp_path / "storage")
    _fragment(store, "C1", (200, 30, 30))                                  # colour-only
    n = np.zeros((40, 50, 3), np.float32)
    n[..., 2] = 1.0
    save_rgbn(store, "fragments/N1/rgbn/front-0000000000000001.h5",
              RGBNImage(np.full((40, 50, 3), 0.5, np.float32), np.ones((40, 50), bool), 100.0, normals=n))
    _fragment(store, "M1", (40, 70, 200), face="back")                   # colour-only back, normals on the front
    save_rgbn(store, "fragments/M1/rgbn/front-0000000000000002.h5",
              RGBNImage(np.full((40, 50, 3), 0.5, np.float32), np.ones((40, 50), bool), 100.0, normals=n))
    _fragment(store, "C2", (40, 70, 200))                                  # colour-only, features computed
    (store.root / "fragments/C2/features").mkdir(parents=True)
    (store.root / "fragments/C2/features/front-1.h5").write_bytes(b"x")
    c = Catalogue(tmp_path / "catalogue.sqlite", store)
    assert c.rebuild() == 4
    rows = {r["id"]: r for r in c.query()["fragments"]}
    assert rows["C1"]["stages"] == {"imported": "done", "normals": "n/a", "features": "waiting",
                                    "matched": "waiting", "rendered": "waiting"}
    assert rows["C1"]["state"] == "normals" and rows["C2"]["state"] == "features"
    assert rows["C2"]["stages"]["normals"] == cat.NOT_APPLICABLE
    assert rows["N1"]["stages"]["normals"] == "done" and rows["M1"]["stages"]["normals"] == "done"
    got = web.create_app(token=TOKEN, store_root=store.root, catalogue=c).test_client().get("/api/catalogue/C1")
    assert got.json["stages"]["normals"] == "n/a"
    # a parked failure of the solver is not hidden behind n/a
    c.index_fragment("C1", failed={"solver": "boom"})
    assert c.get("C1")["stages"]["normals"] == "failed" and c.get("C1")["state"] == "failed"
    assert cat.pipeline_state({"imported": "done", "normals": "n/a", "features": "done"}) == "features"


def test_an_index_made_by_another_version_is_rebuilt_at_the_next_start(collection, tmp_path):
    """Rows indexed before imported fragments said so would keep ``scanned: waiting``: an index whose rows
    another version made forgets its feed position, so the first round of the feed rebuilds it."""
    store, c, db = collection
    c.set_position("stream-1", 42)
    assert Catalogue(c.path, store).position() == ("stream-1", 42)   # same version: followed on
    with c._db() as con:
        con.execute("UPDATE meta SET value = '1' WHERE key = 'rows'")
    assert Catalogue(c.path, store).position() == ("", 0)


def test_an_edit_goes_through_the_bus_and_comes_back_from_the_feed(station_config, broker, tmp_path):
    from common.bus.client import BrokerClient
    from common.messages import unpack
    from services import web
    from services.web.station import FeedFollower

    store = Store(station_config["storage"]["root"])
    _fragment(store, "F010", (220, 200, 40), {"inventory": "INV-10", "notes": "old"})
    link = web.StationLink(station_config)
    c = Catalogue(tmp_path / "cat.sqlite", store)
    rebuilt = []
    feed = FeedFollower(link, start=c.position(), on_gap=lambda s, last: rebuilt.append(c.rebuild()) or last)
    feed.subscribe(cat.FRAGMENT_EVENTS + cat.JOIN_EVENTS, c.apply,
                   position=lambda stream, seq: (c.flush(), c.set_position(stream, seq)))
    feed.poll()                                   # first round: no position yet, so built from storage
    assert rebuilt == [1] and c.get("F010")["notes"] == "old"
    app = web.create_app(token=TOKEN, store_root=store.root, link=link, catalogue=c, feed=feed)
    client = app.test_client()
    r = client.post("/api/catalogue/F010/metadata", json={"changes": {"notes": "new", "inventory": "INV-10"}},
                    headers=BEARER)
    assert r.status_code == 200 and r.json["sent"]["delivered"] is True
    assert r.json["sent"]["changes"] == {"notes": "new"}          # unchanged fields are not sent
    with BrokerClient.from_config(station_config) as bus:
        events = [unpack(bytes(b)) for _, b in bus.since(0)["events"]]
    ann = [e for e in events if e["type"] == "fragment.annotated"]
    assert len(ann) == 1 and ann[0]["by"] == "web" and ann[0]["previous"] == {"notes": "old"}
    row = client.get("/api/catalogue/F010").json                  # the edit polled the feed: applied
    assert row["notes"] == "new" and row["history"][0]["uid"] == ann[0]["uid"] and row["sent"] == []
    assert c.position()[1] >= 1
    assert client.post("/api/catalogue/F010/metadata", json={"changes": {"notes": "new"}},
                       headers=BEARER).json["error"] == "nothing changed"
    link.close()


class _FakeFeed:
    """A broker's SINCE answers from a list of events (for the follower's bookkeeping)."""

    def __init__(self, events, stream="s1", first=1):
        self.events, self.stream, self.first = events, stream, first

    def client(self):
        feed = self

        class C:
            def __enter__(self):
                return self

            def __exit__(self, *a):
                return False

            def since(self, after, limit=1000, types=None):
                from common.messages import pack
                ev = [(s, pack(e)) for s, e in feed.events if s > after and (types is None or e["type"] in types)]
                last = feed.events[-1][0] if feed.events else 0
                return {"stream": feed.stream, "first_seq": feed.first, "last_seq": last,
                        "scanned_to": max(last, after), "events": ev[:limit]}
        return C()


def test_the_feed_follower_dispatches_in_order_and_catches_up_after_a_hole():
    from common.messages import new_message
    from services.web.station import FeedFollower

    ev = [(i, new_message("match.verified", fragment="A", other="B", verdict="confirmed")) for i in (1, 2, 3)]
    ev.append((4, new_message("noop.job")))
    link = _FakeFeed(ev)
    gaps, seen, positions = [], [], []
    f = FeedFollower(link, start=("s1", 1), on_gap=lambda s, last: gaps.append((s, last)) or last)
    f.subscribe(["match.verified"], lambda e, seq: seen.append(seq), position=lambda s, q: positions.append(q))
    assert f.poll() == 2 and seen == [2, 3] and positions == [4] and gaps == []   # noop.job filtered out
    link.stream = "s2"                                    # a new broker journal: caught up from storage
    assert f.poll() == 0 and gaps == [("s2", 4)] and f.seq == 4
    link.stream, link.first = "s2", 9                     # the broker forgot events 5..8: a hole
    link.events.append((10, new_message("match.verified", fragment="A", other="C", verdict="rejected")))
    assert f.poll() == 0 and gaps[-1] == ("s2", 10) and seen == [2, 3]
    f._lock.acquire()
    try:
        assert f.poll(blocking=False) == -1               # a page never waits for a running round
    finally:
        f._lock.release()


def test_the_feed_follower_reads_a_journalled_verdict_in_an_older_word(caplog):
    """docs/messages.md: a journal written before the broker refused them may hold the verdict words
    confirm/accept/yes/reject/no, "which its readers still read"; the web app's feed dropped such an
    event as "not understood" (the reconstruction page reads it with verdict_of). A verdict no word
    means is still not understood."""
    from common.messages import new_message, verdict_of
    from services.web.station import FeedFollower

    ev = [(i, dict(new_message("match.verified", fragment="A", other="B", verdict="confirmed"), verdict=w))
          for i, w in ((1, "accept"), (2, "no"), (3, "maybe"))]
    seen = []
    f = FeedFollower(_FakeFeed(ev), start=("s1", 0), on_gap=lambda s, last: last)
    f.subscribe(["match.verified"], lambda e, seq: seen.append((seq, verdict_of(e["verdict"]))))
    f.poll()
    assert seen == [(1, "confirmed"), (2, "rejected")] and f.seq == 3
    assert "event 3 not understood" in caplog.text and "event 1 " not in caplog.text



def test_a_damaged_face_is_listed_without_a_thumbnail_and_stops_nothing(tmp_path):
    store = Store(tmp_path / "storage")
    _fragment(store, "G1", (200, 30, 30))
    bad = store.root / "fragments/G2/rgbn/front-0000000000000bad.h5"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not an HDF5 file")
    c = Catalogue(tmp_path / "c.sqlite", store)
    assert c.rebuild() == 2
    rows = {r["id"]: r for r in c.query()["fragments"]}
    assert rows["G1"]["has_thumb"] and not rows["G2"]["has_thumb"] and rows["G2"]["colour"] == ""


def test_a_rejected_input_marks_its_fragment_failed_like_a_failed_stage(collection):
    """docs/messages.md: input.rejected parks the job at once, as stage.failed does after the last
    attempt; the catalogue re-indexed a fragment on stage.failed only, so a fragment whose scans
    were refused (truncated, wrong digest, newer schema) kept its old state until a rebuild."""
    from common.messages import new_message

    store, c, db = collection
    assert c.get("F004")["state"] != "failed"
    failed = {"F004": {"solver": "ArtifactError: artifact … has schema version 2; this reader understands up to 1"}}
    event = new_message("input.rejected", service="solver", error=failed["F004"]["solver"], fragment="F004",
                        job="0123456789ab-solver", attempts=1)
    assert c.apply(event, 10, failed=failed) == "reindexed"
    assert c.get("F004")["state"] == "failed"
    summary = new_message("input.rejected", error="3 frame(s) refused", source="broker", refused=3)
    assert c.apply(summary, 11) == "ignored", "the broker's refusal summary names no fragment"


def _newer_rgbn(store, rel, **attrs):
    """An RGBN face written by a newer Tessera (schema version one above this reader's), with a mask and dpi."""
    from common.rgbn.image import SCHEMA, SCHEMA_VERSION

    def fill(f):
        f.create_dataset("mask", data=np.ones((30, 40), bool))
        f.create_dataset("normals", data=np.zeros((30, 40, 3), np.float32))
        f.attrs.update(dpi=300.0, metadata=json.dumps({"inventory": "INV-9"}), **attrs)

    return store.write(rel, SCHEMA, SCHEMA_VERSION + 1, fill, provenance={"importer": "tessera import images"})


def test_a_face_of_a_newer_schema_version_is_not_read_by_the_catalogue(tmp_path, caplog):
    """docs/storage.md: every reader opens a file with its schema and the highest version it understands
    and refuses a newer one. The catalogue read a face's mask, dpi and metadata with a plain h5py.File,
    so a face written by a newer Tessera was listed with its size and dpi as if understood."""
    from common.rgbn.image import SCHEMA_VERSION

    store = Store(tmp_path / "storage")
    rel = "fragments/N1/rgbn/front-00000000000000aa.h5"
    _newer_rgbn(store, rel)
    info = cat._face_info(store, rel)
    assert info["rgbn"] == rel and info["metadata"] == {}
    assert not {"dpi", "width", "height", "has_normals", "imported"} & set(info), info
    assert f"schema version {SCHEMA_VERSION + 1}" in caplog.text and rel in caplog.text
    c = Catalogue(tmp_path / "c.sqlite", store)                  # listed, without those details, never dropped
    assert c.rebuild() == 1
    row = c.query()["fragments"][0]
    assert row["id"] == "N1" and row["inventory"] == "" and not row["has_thumb"]
