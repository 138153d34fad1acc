"""A fragment the matcher takes in after its last artifact event still reaches ``matched`` / ``rendered``.

Seen on a real import (16 RePAIR fragments through the station): the matcher trained its bootstrap
model for half a minute, so the first fragments' ``render.ready`` came before the matcher recorded
them; the only events after that were ``match.proposed``, which recounted the joins but left the
pipeline state at ``features`` ("0 confirmed · 13 pending", state *features*) until a rebuild.
"""

from __future__ import annotations

import json

import numpy as np

from common.matching.proposals import Proposal, ProposalStore
from common.messages import new_message
from common.rgbn.image import RGBNImage, save_rgbn
from common.store import Store
from common.web.catalogue import Catalogue


def _face(store, fid):
    save_rgbn(store, f"fragments/{fid}/rgbn/front-0000000000000001.h5",
              RGBNImage(np.full((30, 40, 3), 0.5, np.float32), np.ones((30, 40), bool), 100.0, normals=None))
    for stage in ("features", "renders"):   # features and the renderer's output are on storage
        (store.root / f"fragments/{fid}/{stage}").mkdir(parents=True, exist_ok=True)
        (store.root / f"fragments/{fid}/{stage}/front-1.h5").write_bytes(b"x")


def test_a_match_event_brings_the_matched_stage_of_a_fragment_indexed_before_the_matcher_took_it(tmp_path):
    store = Store(tmp_path / "storage")
    for fid in ("A", "B"):
        _face(store, fid)
    db = tmp_path / "proposals.sqlite"
    with ProposalStore(db):   # the matcher has not recorded them yet (still training)
        pass
    c = Catalogue(tmp_path / "catalogue.sqlite", store, proposals=db)
    c.rebuild()
    assert c.get("A")["state"] == "features" and c.get("A")["stages"]["matched"] == "waiting"
    with ProposalStore(db) as ps:   # now it does, and proposes A-B
        for fid in ("A", "B"):
            ps.add_fragment(fid, "front", {"path": f"fragments/{fid}/features/front-1.h5", "sha256": fid, "bytes": 1})
        ps.upsert([Proposal("A", "B", 0.9, "m")])
    assert c.apply(new_message("match.proposed", fragment="A", other="B", probability=0.9), 5) == "joins"
    c.flush()
    for fid in ("A", "B"):
        row = c.get(fid)
        assert row["pending"] == 1
        assert row["stages"]["matched"] == "done" and row["state"] == "rendered", (fid, row["state"])
    assert c.query(state="rendered")["total"] == 2 and c.query(state="features")["total"] == 0
    assert json.loads(json.dumps(c.counts())) == {"total": 2, "states": {"rendered": 2}, "colours": c.counts()["colours"]}
