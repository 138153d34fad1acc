"""Bad artifacts through the real stages: truncated and corrupted HDF5, wrong schema, images of
nothing, absurd sizes and dpi. Each bad input ends in exactly one clear error event per job
(``input.rejected`` at once, or ``stage.failed`` after the retries), no worker dies, and a good
fragment submitted among them comes through every stage."""

from __future__ import annotations

import collections

import h5py
import numpy as np
import pytest

from common import messages
from common.acquisition.capture import CaptureResult, Scan, write_scans
from common.messages import new_message
from common.rgbn.image import RGBNImage, save_rgbn
from common.store import Store
from tests.bus.conftest import wait_for

pytestmark = pytest.mark.timeout(150)

ERROR_TYPES = ("input.rejected", "stage.failed")


def _disc(n: int = 64, dpi: float = 100.0) -> RGBNImage:
    """A small domed disc: a plausible fragment face."""
    yy, xx = np.mgrid[:n, :n]
    c = (n - 1) / 2
    r = np.hypot(yy - c, xx - c) / (0.4 * n)
    nrm = np.dstack([0.3 * (xx - c) / (0.4 * n), -0.3 * (yy - c) / (0.4 * n), np.ones((n, n))])
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    alb = np.dstack([np.full((n, n), 0.6), 0.4 + 0.1 * np.sin(xx / 5.0), np.full((n, n), 0.3)])
    return RGBNImage(albedo=alb.astype(np.float32), mask=r < 1, dpi=dpi, normals=nrm.astype(np.float32))


def _patch_attr(store: Store, rel: str, name: str, value):
    with h5py.File(store.path(rel), "r+") as f:
        f.attrs[name] = value
    return store.ref(rel)  # a pointer with the digest of the altered file: only reading can tell


def _corrupt_middle(store: Store, rel: str):
    path = store.path(rel)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 4096] = bytes(len(data[mid:mid + 4096]))  # a zeroed block inside the compressed chunks
    path.write_bytes(bytes(data))
    return store.ref(rel)


def _truncate(store: Store, rel: str):
    path = store.path(rel)
    with open(path, "r+b") as fh:
        fh.truncate(path.stat().st_size // 2)
    return store.ref(rel)


def _blank_scans(dpi=100.0, h=64, w=64):
    return [Scan(np.full((h, w, 3), 50000, np.uint16), dpi, rot, (0.0, 0.0, w * 25.4 / 100, h * 25.4 / 100), 16)
            for rot in (0, 90, 180, 270)]


def _huge_rgbn(store: Store, rel: str, side: int = 200_000):
    """An RGBN artifact declaring a side × side face (chunked, never written: the file stays tiny)."""
    def fill(f):
        f.attrs["dpi"] = 100.0
        f.create_dataset("albedo", shape=(side, side, 3), dtype=np.float32, chunks=(64, 64, 3), compression="gzip")
        f.create_dataset("mask", shape=(side, side), dtype=bool, chunks=(64, 64), compression="gzip")
    return store.write(rel, "tessera.rgbn", 1, fill)


def _huge_scans(store: Store, fid: str, side: int = 200_000):
    """A scans artifact declaring four side × side scans of the front face (never written)."""
    def fill(f):
        f.attrs.update(fragment=fid, device="sim-stress", calibration="", colour_only=False)
        g = f.create_group("front")
        f.create_group("back")
        for k, rot in enumerate((0, 90, 180, 270)):
            d = g.create_dataset(f"scan_{k}", shape=(side, side, 3), dtype=np.uint16, chunks=(64, 64, 3),
                                 compression="gzip")
            d.attrs.update(dpi=100.0, rotation_deg=rot, area_mm=np.array([0.0, 0.0, 50.0, 50.0]), depth=16)
    return store.write(f"fragments/{fid}/scans/scans-huge.h5", "tessera.scans", 1, fill)


def _bad_rgbn(store: Store) -> dict[str, object]:
    """fragment id -> pointer of a bad RGBN face."""
    out = {}
    out["BAD-truncated"] = _truncate(store, save_rgbn(store, "fragments/BAD-truncated/rgbn/front-1.h5", _disc()).path)
    out["BAD-corrupt"] = _corrupt_middle(store, save_rgbn(store, "fragments/BAD-corrupt/rgbn/front-1.h5", _disc()).path)
    out["BAD-digest"] = dict(save_rgbn(store, "fragments/BAD-digest/rgbn/front-1.h5", _disc()).to_dict(), sha256="0" * 64)
    out["BAD-schema"] = store.write("fragments/BAD-schema/rgbn/front-1.h5", "tessera.noop", 1,
                                    lambda f: f.create_dataset("x", data=np.zeros(3)))
    out["BAD-lacks-albedo"] = store.write("fragments/BAD-lacks-albedo/rgbn/front-1.h5", "tessera.rgbn", 1,
                                          lambda f: f.attrs.__setitem__("dpi", 100.0))
    out["BAD-dpi-zero"] = _patch_attr(store, save_rgbn(store, "fragments/BAD-dpi-zero/rgbn/front-1.h5", _disc()).path,
                                      "dpi", 0.0)
    out["BAD-dpi-nan"] = _patch_attr(store, save_rgbn(store, "fragments/BAD-dpi-nan/rgbn/front-1.h5", _disc()).path,
                                     "dpi", float("nan"))
    # 1e9 dpi: a 64-px face 1.6 µm wide; resampled to the feature grid it would need TiB
    out["BAD-dpi-1e9"] = save_rgbn(store, "fragments/BAD-dpi-1e9/rgbn/front-1.h5", _disc(dpi=1e9))
    out["BAD-dpi-0.001"] = save_rgbn(store, "fragments/BAD-dpi-0.001/rgbn/front-1.h5", _disc(dpi=0.001))
    out["BAD-size-200000"] = _huge_rgbn(store, "fragments/BAD-size-200000/rgbn/front-1.h5")
    empty = _disc()
    empty.mask[:] = False
    out["BAD-nothing"] = save_rgbn(store, "fragments/BAD-nothing/rgbn/front-1.h5", empty)
    return out


def _bad_scans(store: Store) -> dict[str, object]:
    """fragment id -> pointer of a bad scans artifact."""
    out = {}
    for fid, scans in (("SCN-empty-glass", _blank_scans()), ("SCN-dpi-zero", _blank_scans(dpi=0.0)),
                       ("SCN-dpi-0.001", _blank_scans(dpi=0.001)), ("SCN-dpi-1e9", _blank_scans(dpi=1e9))):
        out[fid] = write_scans(store, fid, CaptureResult(fid, "sim-stress", {"front": scans, "back": []}))
    out["SCN-size-200000"] = _huge_scans(store, "SCN-size-200000")
    ref = write_scans(store, "SCN-truncated", CaptureResult("SCN-truncated", "sim-stress",
                                                            {"front": _blank_scans(), "back": []}))
    out["SCN-truncated"] = _truncate(store, ref.path)
    return out


def test_bad_artifacts_each_end_in_one_error_event_and_a_good_face_still_goes_through(make_station):
    st = make_station(routing={"rgbn.ready": ["features", "renderer"], "fragment.ready": ["solver"]})
    store = Store(st.root / "storage")
    bad_rgbn, bad_scans = _bad_rgbn(store), _bad_scans(store)
    good = save_rgbn(store, "fragments/GOOD/rgbn/front-1.h5", _disc())
    st.broker()
    workers = [st.worker("features"), st.worker("renderer"), st.worker("solver")]
    for service in ("features", "renderer", "solver"):
        st.workers_ready(1, service, timeout=60)
    submitted = [new_message("rgbn.ready", fragment=fid, face="front", artifact=ref) for fid, ref in bad_rgbn.items()]
    submitted += [new_message("fragment.ready", fragment=fid, artifact=ref) for fid, ref in bad_scans.items()]
    submitted.insert(len(submitted) // 2, new_message("rgbn.ready", fragment="GOOD", face="front", artifact=good))
    n_jobs = 2 * (len(bad_rgbn) + 1) + len(bad_scans)
    with st.client() as c:
        c.submit_many(submitted)

        def settled():
            s = c.status()
            return not s["in_flight"] and not any(s["queues"].values()) and s["completed"] + len(s["parked"]) >= n_jobs
        wait_for(settled, 120, "every job done or parked", interval=0.5)
        events, after = [], 0
        while (r := c.since(after, 5000))["events"]:
            events += [messages.unpack(b) for _, b in r["events"]]
            after = r["events"][-1][0]
    assert all(w.poll() is None for w in workers) and st.procs[0].poll() is None, "no process died\n" + st.logs()
    errors = collections.defaultdict(list)
    ready = collections.defaultdict(list)
    for e in events:
        if e["type"] in ERROR_TYPES:
            errors[e.get("fragment")].append((e["service"], e["type"], e["error"]))
        elif e["type"].endswith(".ready") and e["uid"] not in {s["uid"] for s in submitted}:
            ready[e["fragment"]].append(e["type"])
    assert sorted(ready["GOOD"]) == ["features.ready", "render.ready"], "the good face went through both stages"
    assert "GOOD" not in errors
    unreadable = ("BAD-truncated", "BAD-corrupt", "BAD-digest", "BAD-schema", "BAD-lacks-albedo",
                  "BAD-dpi-zero", "BAD-dpi-nan")
    for fid in unreadable:  # both stages refuse it, once each, saying why
        services = sorted(s for s, _, _ in errors[fid])
        assert services == ["features", "renderer"], f"{fid}: {errors[fid]}"
        assert not ready[fid], f"{fid} must not produce outputs: {ready[fid]}"
    for fid, words in (("BAD-truncated", "HDF5"), ("BAD-digest", "sha256"), ("BAD-schema", "schema"),
                       ("BAD-lacks-albedo", "albedo"), ("BAD-dpi-zero", "dpi"), ("BAD-dpi-nan", "dpi")):
        assert all(words in err for _, _, err in errors[fid]), f"{fid}: error does not say {words!r}: {errors[fid]}"
    # absurd dpi and sizes: both stages reject them at once (input.rejected), naming the value
    for fid, words in (("BAD-dpi-1e9", "dpi 1e+09"), ("BAD-dpi-0.001", "dpi 0.001"),
                       ("BAD-size-200000", "200000×200000")):
        assert sorted((s, t) for s, t, _ in errors[fid]) == [("features", "input.rejected"),
                                                             ("renderer", "input.rejected")], f"{fid}: {errors[fid]}"
        assert all(words in err for _, _, err in errors[fid]), f"{fid}: error does not say {words!r}: {errors[fid]}"
        assert not ready[fid]
    for fid, words in (("SCN-dpi-1e9", "dpi 1e+09"), ("SCN-dpi-0.001", "dpi 0.001"),
                       ("SCN-size-200000", "200000×200000")):
        assert [(s, t) for s, t, _ in errors[fid]] == [("solver", "input.rejected")], f"{fid}: {errors[fid]}"
        assert words in errors[fid][0][2], f"{fid}: error does not say {words!r}: {errors[fid]}"
    # images of nothing: at least the feature stage says so (a blank drawing is harmless)
    for fid, words in (("BAD-nothing", "empty"),):
        feats = [err for s, _, err in errors[fid] if s == "features"]
        assert len(feats) == 1 and words in feats[0], f"{fid}: {errors[fid]}"
    for fid in bad_scans:
        assert [s for s, _, _ in errors[fid]] == ["solver"], f"{fid}: {errors[fid]}"
        assert not ready[fid]
    # the door check of common/acquisition/capture.py refuses an empty glass as a blank scan
    assert any(w in errors["SCN-empty-glass"][0][2] for w in ("fragment visible", "blank"))
    assert "dpi" in errors["SCN-dpi-zero"][0][2]
    with st.client() as c:
        parked = c.status()["parked"]
    assert len(parked) == sum(len(v) for v in errors.values()), "each error event is one parked job"
