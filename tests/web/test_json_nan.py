"""The pages' JSON is valid JSON for a browser: no bare ``NaN`` / ``Infinity``.

A docked proposal's alignment carries ``gap_mm = NaN`` (common/matching/index.py: the docking
measures no RMS gap). Flask's default JSON writer emits it as a bare ``NaN``, which the browser's
``JSON.parse`` (``fetch().json()``) refuses; ``Tessera.api`` then reads ``{}`` and the review page
said "Nothing to review" while the queue held every proposal of a real import (RePAIR, 16 fragments).
"""

from __future__ import annotations

import json
import math

from common.matching.proposals import Proposal, ProposalStore
from common.store import Store
from common.web.review import ReviewData
from services import web

from .conftest import TOKEN


def _strict(text: str):
    """Parse as a browser does: bare NaN / Infinity are errors."""
    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=refuse)


def test_review_queue_of_docked_proposals_is_strict_json(tmp_path):
    store = Store(tmp_path / "storage")
    db_path = tmp_path / "storage" / "matches" / "proposals.sqlite"
    alignment = {"angle_deg": 90.0, "tx_mm": 1.0, "ty_mm": 2.0, "gap_mm": float("nan"), "contact_mm": 30.0,
                 "overlap_mm2": 0.0, "score": float("inf")}
    with ProposalStore(db_path) as db:
        db.upsert([Proposal("A", "B", 0.9, "m1", angle_deg=90.0, tx_mm=1.0, ty_mm=2.0, alignment=alignment)])
    c = web.create_app(token=TOKEN, store_root=store.root, review=ReviewData(db_path, store)).test_client()
    for url in ("/api/review/queue", "/api/review/fragment/A"):
        resp = c.get(url)
        assert resp.status_code == 200
        data = _strict(resp.get_data(as_text=True))   # raised before the fix: bare NaN
        (p,) = data["proposals"]
        assert p["alignment"]["gap_mm"] is None and p["alignment"]["score"] is None   # not finite: null
        assert p["alignment"]["contact_mm"] == 30.0 and p["probability"] == 0.9


def test_finite_values_and_nesting_are_kept(tmp_path):
    app = web.create_app(token=TOKEN, store_root=tmp_path)
    text = app.json.dumps({"a": [1.5, float("-inf"), {"b": float("nan"), "c": (2, 3)}], "d": "NaN", "e": True})
    assert _strict(text) == {"a": [1.5, None, {"b": None, "c": [2, 3]}], "d": "NaN", "e": True}
    assert not math.isnan(app.json.loads("1.0"))
