"""tessera reconcile and tessera status, as a user runs them."""

from __future__ import annotations

import subprocess
import sys

from common.bus.reconcile import missing_stages
from common.store import Store

from .conftest import REPO, collect, free_port


def _h5(store: Store, rel: str):
    return store.write(rel, "tessera.test", 1, lambda f: f.create_dataset("x", data=[1]))


def _storage(store: Store) -> dict:
    return {
        "scans_only": _h5(store, "fragments/F1/scans/scans-aaa.h5"),
        "rgbn_front": _h5(store, "fragments/F2/rgbn/front-bbb.h5"),
        "f2_scans": _h5(store, "fragments/F2/scans/scans-ccc.h5"),
        "f3": [_h5(store, f"fragments/F3/{d}/front-ddd.h5") for d in ("rgbn", "features", "renders")]
              + [_h5(store, "fragments/F3/scans/scans-eee.h5")],
    }


def test_missing_stages_finds_inputs_whose_outputs_are_absent(tmp_path):
    store = Store(tmp_path)
    refs = _storage(store)
    store.path("fragments/F2/rgbn/.front-tmp.h5.x.tmp").write_bytes(b"partial")  # never counted
    events = missing_stages(store)
    got = sorted((e["type"], e["fragment"], e.get("face"), e["artifact"]["path"]) for e in events)
    assert got == [("fragment.ready", "F1", None, refs["scans_only"].path),
                   ("rgbn.ready", "F2", "front", refs["rgbn_front"].path)]
    assert all(e["artifact"]["sha256"] == store.ref(e["artifact"]["path"]).sha256 for e in events)


def _tessera(st, *args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())", *args,
                           "--config", str(st.config_path)], capture_output=True, text=True, timeout=60, cwd=REPO)


def test_reconcile_command_queues_missing_stages_and_status_shows_them(make_station):
    st = make_station(routing={"fragment.ready": ["solver"], "rgbn.ready": ["features", "renderer"]})
    _storage(Store(st.root / "storage"))
    st.broker()
    dry = _tessera(st, "reconcile", "--dry-run")
    assert dry.returncode == 0 and "2 event(s) would be queued" in dry.stdout
    with st.subscriber(0) as sub:
        assert sub.next(0.3) is None, "a dry run queues nothing"
        run = _tessera(st, "reconcile")
        assert run.returncode == 0, run.stdout + run.stderr
        events = collect(sub, lambda ev: len(ev) == 2, 10, "two reconciled events")
    assert {(e["type"], e["fragment"]) for _, e in events} == {("fragment.ready", "F1"), ("rgbn.ready", "F2")}
    status = _tessera(st, "status")
    assert status.returncode == 0
    assert "solver=1" in status.stdout and "features=1" in status.stdout and "renderer=1" in status.stdout
    down = _tessera(st, "status", "--set", f"broker.port={free_port()}", "--set", "client.timeout_s=0.2",
                    "--set", "client.retries=1")
    assert down.returncode == 1 and "did not answer" in down.stdout


def _scans(store: Store, fragment: str, faces: tuple[str, ...]):
    def fill(f):
        for face in ("front", "back"):
            g = f.create_group(face)
            if face in faces:
                g.create_dataset("scan_0", data=[1, 2, 3])
    return store.write(f"fragments/{fragment}/scans/scans-{fragment.lower()}.h5", "tessera.scans", 1, fill)


def _matcher_db(path, rows):
    import sqlite3
    path.parent.mkdir(parents=True, exist_ok=True)
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE fragments (fragment TEXT, face TEXT, artifact TEXT, sha256 TEXT, bytes INTEGER, added REAL)")
    con.executemany("INSERT INTO fragments VALUES (?, ?, ?, ?, ?, 0)", [(f, fa, r.path, r.sha256, r.bytes) for f, fa, r in rows])
    con.commit()
    con.close()


def test_reconcile_checks_each_face_and_each_stage_including_the_matcher(tmp_path):
    """Issue 19: a missing face was missed (only empty folders counted) and features -> matcher
    was not checked at all."""
    store = Store(tmp_path / "storage")
    a = _scans(store, "A", ("front", "back"))                  # both faces scanned, only the front solved
    for d in ("rgbn", "features", "renders"):
        _h5(store, f"fragments/A/{d}/front-1.h5")
    _scans(store, "B", ("front", "back"))                      # complete, but the back has no illustration
    for d in ("rgbn", "features", "renders"):
        _h5(store, f"fragments/B/{d}/front-2.h5")
    back = _h5(store, "fragments/B/rgbn/back-2.h5")
    _h5(store, "fragments/B/features/back-2.h5")
    _scans(store, "C", ("front",))                             # complete, but the matcher never saw it
    c_rgbn = _h5(store, "fragments/C/rgbn/front-3.h5")
    c_feat = _h5(store, "fragments/C/features/front-3.h5")
    _h5(store, "fragments/C/renders/front-3.h5")
    db = tmp_path / "proposals.sqlite"
    a_feat = store.ref("fragments/A/features/front-1.h5")
    b_feat = store.ref("fragments/B/features/front-2.h5")
    _matcher_db(db, [("A", "front", a_feat), ("B", "front", b_feat)])
    got = sorted((e["type"], e["fragment"], e.get("face"), e["artifact"]["path"], tuple(e["missing"]))
                 for e in missing_stages(store, matcher_db=db))
    assert got == [("features.ready", "C", "front", c_feat.path, ("matcher/front",)),
                   ("fragment.ready", "A", None, a.path, ("rgbn/back",)),
                   ("rgbn.ready", "B", "back", back.path, ("renders/back",))]
    assert c_rgbn.path not in {g[3] for g in got}
    # the same storage with jobs already waiting at the broker: nothing is queued twice
    pending = [("solver", "queued", "fragment.ready", "A", None),
               ("renderer", "inflight", "rgbn.ready", "B", "back"),
               ("solver", "queued", "fragment.ready", "C", None)]  # an earlier stage of C covers the matcher step
    assert missing_stages(store, pending=pending, matcher_db=db) == []
    assert [e["fragment"] for e in missing_stages(store, pending=pending[:1], matcher_db=db)] == ["B", "C"]


def test_status_into_a_closed_pipe_prints_no_traceback(make_station):
    """Issue 19: `tessera status | head` printed a BrokenPipe traceback."""
    st = make_station()
    st.broker()
    cmd = (f"{sys.executable} -c 'import sys; from services.cli import main; sys.exit(main())' status --json "
           f"--config {st.config_path} | true")
    for _ in range(3):
        r = subprocess.run(["bash", "-c", f"set -o pipefail; {cmd}"], capture_output=True, text=True, timeout=60, cwd=REPO)
        assert "Traceback" not in r.stderr and "BrokenPipe" not in r.stderr, r.stderr
        assert r.returncode == 0, r.stderr


def test_an_event_json_cannot_hold_is_printed_as_a_line_saying_so():
    """Issue 19: an event nested 1,000 deep crashed `tessera events` with RecursionError."""
    import json

    from services.cli.events import event_line
    deep = []
    for _ in range(100000):
        deep = [deep]
    line = json.loads(event_line(7, "s", {"type": "noop.job", "uid": "u", "x": deep}))
    assert line["seq"] == 7 and line["type"] == "noop.job" and "not representable" in line["error"]
    assert json.loads(event_line(8, "s", {"type": "noop.job", "x": [[1]]}))["x"] == [[1]]


def test_an_event_carrying_nan_is_printed_as_strict_json():
    # a docked proposal's alignment gap_mm is NaN ("not measured"); a bare NaN breaks `tessera events | jq`
    import json

    from services.cli.events import event_line

    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    line = json.loads(event_line(9, "s", {"type": "match.proposed", "alignment": {"gap_mm": float("nan"),
                                                                                  "contact_mm": 30.0}}),
                      parse_constant=refuse)
    assert line["alignment"] == {"gap_mm": None, "contact_mm": 30.0} and line["seq"] == 9


def test_a_face_solved_again_needs_outputs_of_its_newest_rgbn(tmp_path):
    """docs/storage.md: every RGBN face needs a feature table and an illustration. Any output of the face counted,
    so a face solved again (a new RGBN) whose stages never ran for it was never queued; an output counts when its
    provenance names the newest RGBN (or names no input at all, as artifacts without provenance did before)."""
    import os

    store = Store(tmp_path)
    old = _h5(store, "fragments/G/rgbn/front-old.h5")
    made = lambda d, src: store.write(f"fragments/G/{d}/front-{src.path[-6:-3]}.h5", "tessera.test", 1,  # noqa: E731
                                      lambda f: f.create_dataset("x", data=[1]), provenance={"inputs": [src.to_dict()]})
    made("features", old), made("renders", old)
    assert missing_stages(store) == []
    new = _h5(store, "fragments/G/rgbn/front-new.h5")
    os.utime(store.path(new.path), (os.path.getmtime(store.path(old.path)) + 10,) * 2)   # the newer capture
    (e,) = missing_stages(store)
    assert (e["type"], e["face"], e["artifact"]["path"], e["missing"]) == ("rgbn.ready", "front", new.path,
                                                                           ["features/front", "renders/front"])
    made("features", new)
    (e,) = missing_stages(store)
    assert e["missing"] == ["renders/front"]


def test_an_output_made_by_an_older_version_of_its_stage_is_made_again(tmp_path):
    """A fix of the renderer (render-2.1: an imported picture was drawn as a white silhouette) reached only faces
    drawn after it: reconcile counted any illustration of the face. Given the stages' current versions, an output
    whose provenance names another stage_version counts as missing; one that names none counts as made."""
    store = Store(tmp_path)
    rgbn = _h5(store, "fragments/H/rgbn/front-rrr.h5")

    def made(d, version, key):
        prov = {"inputs": [rgbn.to_dict()], **({"stage_version": version} if version else {})}
        return store.write(f"fragments/H/{d}/front-{key}.h5", "tessera.test", 1,
                           lambda f: f.create_dataset("x", data=[1]), provenance=prov)

    made("features", "features-9", "f1"), made("renders", "render-1", "r1")
    now = {"features": "features-9", "renders": "render-2"}
    assert missing_stages(store) == []                      # any version counts without versions
    (e,) = missing_stages(store, versions=now)
    assert (e["type"], e["face"], e["artifact"]["path"], e["missing"]) == ("rgbn.ready", "front", rgbn.path,
                                                                           ["renders/front"])
    made("renders", "render-2", "r2")
    assert missing_stages(store, versions=now) == []
    made("features", None, "f0")                            # an output recording no version still counts
    assert missing_stages(store, versions={**now, "features": "features-10"}) == []


def test_a_face_solved_by_an_older_solver_is_solved_again_from_its_scans(tmp_path):
    """A fix of the solver reached only fragments captured after it: reconcile counted any RGBN of the face.
    Given the solver's current version, a face whose newest RGBN an older solver made is solved again (its
    features and illustration then follow from the new RGBN, not from the old one); an imported RGBN, with no
    scans to solve, and one that records no version are left as they are."""
    store = Store(tmp_path)

    def rgbn(frag, face, key, **prov):
        return store.write(f"fragments/{frag}/rgbn/{face}-{key}.h5", "tessera.test", 1,
                           lambda f: f.create_dataset("x", data=[1]), provenance=prov)

    def later_stages(frag, face, ref):
        for d in ("features", "renders"):
            store.write(f"fragments/{frag}/{d}/{face}-{ref.sha256[:6]}.h5", "tessera.test", 1,
                        lambda f: f.create_dataset("x", data=[1]), provenance={"inputs": [ref.to_dict()]})

    scans = store.write("fragments/S/scans/scans-s1.h5", "tessera.test", 1,
                        lambda f: [f.create_group(face).create_dataset("scan0", data=[1]) for face in ("front", "back")])
    for face in ("front", "back"):
        later_stages("S", face, rgbn("S", face, "old", stage="solver", stage_version="flatbed-ps-1.0"))
    later_stages("I", "front", rgbn("I", "front", "imp", stage="import images", stage_version="images-3"))
    later_stages("N", "front", rgbn("N", "front", "nov", stage="solver"))
    store.write("fragments/N/scans/scans-n1.h5", "tessera.test", 1,
                lambda f: f.create_group("front").create_dataset("scan0", data=[1]))
    now = {"rgbn": "flatbed-ps-1.1", "features": None, "renders": None}
    assert missing_stages(store) == []                      # any version counts without versions
    (e,) = missing_stages(store, versions=now)
    assert (e["type"], e["fragment"], e["artifact"]["path"], e["missing"]) == (
        "fragment.ready", "S", scans.path, ["rgbn/back", "rgbn/front"])
    assert missing_stages(store, versions=now, pending=[("solver", "queued", "fragment.ready", "S", None)]) == []
    # once a face is solved again its newest RGBN is the current solver's, and its later stages are asked for
    # the new RGBN (not for the old one while the face waits to be solved)
    new = rgbn("S", "front", "new", stage="solver", stage_version="flatbed-ps-1.1")
    got = sorted((e["type"], e.get("face"), e["artifact"]["path"], e["missing"]) for e in missing_stages(store, versions=now))
    assert got == [("fragment.ready", None, scans.path, ["rgbn/back"]),
                   ("rgbn.ready", "front", new.path, ["features/front", "renders/front"])]
    later_stages("S", "front", new)
    later_stages("S", "back", rgbn("S", "back", "new", stage="solver", stage_version="flatbed-ps-1.1"))
    assert missing_stages(store, versions=now) == []
