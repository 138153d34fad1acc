"""common/imports/sources.py: what was imported before, by the sha256 of its files, and what a new item may not be."""

from __future__ import annotations

import numpy as np

from common.imports.sources import ImportedSource, SourceIndex
from common.rgbn.image import RGBNImage, save_rgbn
from common.store import Store

SHA = "ab" * 32


def _index(**kw) -> SourceIndex:
    e = dict(sha256=SHA, fragment="Inv.-12", face="front", dpi=300.0, key="k1", artifact="fragments/Inv.-12/rgbn/front-k1.h5")
    e.update(kw)
    return SourceIndex([ImportedSource(**e)])


def test_a_file_may_become_one_fragment_face_at_one_dpi():
    index = _index()
    assert index.conflict([SHA], "Inv.-12", "front", 300, "k1") is None            # the same item (in the ledger)
    assert index.conflict(["cd" * 32], "F9", "front", 300, "k9") is None           # another file
    assert index.conflict([SHA], "Inv.-12", "front", 300.0, "k2") is None          # other metadata: replaces, as before
    other_id = index.conflict([SHA], "RPf_1", "front", 300, "k3")
    assert "already imported as fragment Inv.-12 (front, 300 dpi: fragments/Inv.-12/rgbn/front-k1.h5)" in other_id
    assert "not imported again as RPf_1 (front)" in other_id and "--allow-duplicates" in other_id
    assert "as fragment Inv.-12 (front" in index.conflict([SHA], "Inv.-12", "back", 300, "k4")   # its other face
    assert index.conflict([SHA], "RPf_1", "front", 300, "k3", allow_duplicates=True) is None
    rescaled = index.conflict(["00" * 32, SHA], "Inv.-12", "front", 150, "k5")
    assert "at 300 dpi; this import gives 150 dpi" in rescaled and "--replace" in rescaled
    assert index.conflict([SHA], "Inv.-12", "front", 150, "k5", replace=True) is None
    assert _index(dpi=None).conflict([SHA], "Inv.-12", "front", 150, "k5") is None   # no dpi known: nothing to compare


def test_the_index_is_read_from_the_ledger_and_from_the_artifacts_of_every_store(tmp_path):
    shared, spool = Store(tmp_path / "shared"), Store(tmp_path / "spool")
    img = RGBNImage(np.full((8, 8, 3), 0.5), np.ones((8, 8), bool), 200.0)
    save_rgbn(shared, "fragments/A/rgbn/front-aaaa.h5", img, provenance={"source_sha256": "11" * 32, "dpi": 200.0})
    save_rgbn(spool, "fragments/B/rgbn/back-bbbb.h5", img, provenance={"source_sha256": ["22" * 32, "33" * 32]})
    save_rgbn(shared, "fragments/C/rgbn/front-cccc.h5", img, provenance={"stage": "solver"})   # scanned: no files
    save_rgbn(shared, "fragments/D/rgbn/front-dddd.h5", img)
    ledger = [{"key": "dddd", "fragment": "D", "face": "front", "digests": ["44" * 32], "dpi": 600,
               "artifacts": ["fragments/D/rgbn/front-dddd.h5"]},
              {"key": "gone", "fragment": "E", "face": "front", "digests": ["55" * 32], "dpi": 600,
               "artifacts": ["fragments/E/rgbn/front-gone.h5"]},   # no longer on storage: not counted
              {"key": "old", "fragment": "F", "face": "front", "artifacts": ["fragments/F/rgbn/front-old.h5"]}]
    index = SourceIndex.load([shared, spool], ledger, tmp_path / "sources.jsonl")
    assert index.find("11" * 32) == [ImportedSource("11" * 32, "A", "front", 200.0, "aaaa", "fragments/A/rgbn/front-aaaa.h5")]
    assert [(e.fragment, e.face, e.dpi) for e in index.find("33" * 32)] == [("B", "back", 200.0)]   # dpi: the face's
    assert [(e.fragment, e.dpi) for e in index.find("44" * 32)] == [("D", 600.0)]
    assert index.find("55" * 32) == [] and len(index) == 4
    again = SourceIndex.load([shared, spool], ledger, tmp_path / "sources.jsonl")   # from the cache
    assert len(again) == 4 and len((tmp_path / "sources.jsonl").read_text().splitlines()) == 3


def test_shared_files_say_nothing_and_scan_sets_are_read_from_storage(tmp_path):
    """An item's shared files (an RTI rig's light file, the same for every capture) are no sign of a fragment:
    left out of the ledger's and the provenance's digests, and out of a ledger line written before ``shared``
    was (an ``rti`` item's non-image and mask files). Scan sets on storage are read as the front face of their
    fragment, at their first scan's dpi; several files name the one already imported."""
    import json

    import h5py

    shared, img = Store(tmp_path / "shared"), RGBNImage(np.full((8, 8, 3), 0.5), np.ones((8, 8), bool), 96.0)
    save_rgbn(shared, "fragments/A/rgbn/front-aaaa.h5", img,
              provenance={"source_sha256": ["11" * 32, "1f" * 32], "shared_sha256": ["1f" * 32], "dpi": 96.0})
    scans = shared.path("fragments/S/scans/scans-ssss.h5")
    scans.parent.mkdir(parents=True)
    with h5py.File(scans, "w") as f:   # as an import before scan sets' provenance had dpi
        f.attrs["provenance"] = json.dumps({"importer": "tessera import scans", "source_sha256": ["66" * 32]})
        f.create_group("front").create_dataset("scan_0", data=np.zeros((2, 2, 3), np.uint8)).attrs["dpi"] = 600.0
    ledger = [{"key": "dddd", "kind": "rti", "fragment": "D", "face": "front", "dpi": 96,
               "sources": ["c/img0.png", "c/capture.lp", "c/mask.png"], "digests": ["44" * 32, "4f" * 32, "4e" * 32],
               "artifacts": ["fragments/A/rgbn/front-aaaa.h5"]},          # written before "shared"
              {"key": "eeee", "kind": "rti", "fragment": "E", "face": "front", "dpi": 96, "shared": ["5f" * 32],
               "sources": ["e/img0.png", "e/dirs.txt"], "digests": ["55" * 32, "5f" * 32],
               "artifacts": ["fragments/A/rgbn/front-aaaa.h5"]}]
    index = SourceIndex.load([shared], ledger, tmp_path / "sources.jsonl")
    assert [e.fragment for e in index.find("44" * 32)] == ["D"] and [e.fragment for e in index.find("55" * 32)] == ["E"]
    for sha in ("1f", "4f", "4e", "5f"):
        assert index.find(sha * 32) == [], sha
    assert index.find("66" * 32) == [ImportedSource("66" * 32, "S", "front", 600.0, "ssss",
                                                    "fragments/S/scans/scans-ssss.h5")]
    reason = index.conflict(["77" * 32, "66" * 32], "T", "front", 600, "tttt", names=["scan_0.png", "scan_1.png"])
    assert reason.startswith("scan_1.png: the same file (sha256 666666666666…) is already imported as fragment S "
                             "(front, 600 dpi: fragments/S/scans/scans-ssss.h5)")
    assert "scan_0.png: the same file is already imported for fragment S (front) at 600 dpi" in index.conflict(
        ["66" * 32], "S", "front", 300, "tttt", names=["scan_0.png"])
