"""Tests of common/web/pipeline.py: fragment pipeline state from the storage tree."""

import os
import time

import numpy as np

from common.store import Store
from common.web.pipeline import fragment_state, fragments_since, start_of_today


def _write(store, rel):
    return store.write(rel, "tessera.test", 1, lambda f: f.create_dataset("x", data=np.zeros(2)))


def test_stages_follow_the_artifacts_on_storage(tmp_path):
    store = Store(tmp_path)
    st = fragment_state(tmp_path, "F1")
    assert set(st["stages"].values()) == {"waiting"} and st["updated"] is None
    _write(store, "fragments/F1/scans/scans-abc.h5")
    _write(store, "fragments/F1/rgbn/front-abc.h5")
    st = fragment_state(tmp_path, "F1")
    assert st["stages"] == {"scanned": "done", "normals": "done", "features": "waiting", "matched": "waiting",
                            "rendered": "waiting"}
    _write(store, "fragments/F1/features/front-abc.h5")
    _write(store, "fragments/F1/renders/front-abc.h5")
    st = fragment_state(tmp_path, "F1", matched={"F1"})
    assert set(st["stages"].values()) == {"done"}


def test_a_partial_temporary_file_does_not_count(tmp_path):
    (tmp_path / "fragments/F2/rgbn").mkdir(parents=True)
    (tmp_path / "fragments/F2/rgbn/.front-abc.h5.123.tmp").write_bytes(b"partial")
    (tmp_path / "fragments/F2/rgbn/.hidden.h5").write_bytes(b"partial")
    assert fragment_state(tmp_path, "F2")["stages"]["normals"] == "waiting"


def test_parked_failure_marks_the_blocked_stage(tmp_path):
    _write(Store(tmp_path), "fragments/F3/scans/s.h5")
    st = fragment_state(tmp_path, "F3", failed={"solver": "RegistrationError: scan 2"})
    assert st["stages"]["normals"] == "failed"
    assert st["errors"]["normals"].startswith("RegistrationError")
    assert st["stages"]["scanned"] == "done"
    _write(Store(tmp_path), "fragments/F3/rgbn/front-abc.h5")   # front solved, back parked
    assert fragment_state(tmp_path, "F3", failed={"solver": "x"})["stages"]["normals"] == "failed"


def test_fragments_since_lists_recent_scans_newest_first(tmp_path):
    store = Store(tmp_path)
    _write(store, "fragments/OLD/scans/s.h5")
    old = time.time() - 3 * 86400
    os.utime(tmp_path / "fragments/OLD/scans/s.h5", (old, old))
    _write(store, "fragments/A/scans/s.h5")
    time.sleep(0.02)
    _write(store, "fragments/B/scans/s.h5")
    (tmp_path / "fragments/NOSCANS").mkdir()
    got = [f for f, _ in fragments_since(tmp_path, start_of_today())]
    assert got == ["B", "A"]
    assert fragments_since(tmp_path / "absent", 0) == []


def test_start_of_today_is_local_midnight():
    t = start_of_today()
    lt = time.localtime(t)
    assert (lt.tm_hour, lt.tm_min, lt.tm_sec) == (0, 0, 0)
    assert 0 <= time.time() - t < 86400 + 3600
