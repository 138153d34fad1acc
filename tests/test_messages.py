"""Message documents: validation, packing, and docs/messages.md covering every type."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from common.messages import EVENT_TYPES, VERSION, MessageError, new_message, pack, unpack, validate
from common.store import ArtifactRef

DOC = Path(__file__).resolve().parents[1] / "docs" / "messages.md"


def test_round_trip_keeps_fields_and_turns_refs_into_dicts():
    ref = ArtifactRef("fragments/F1/scans/scans-1.h5", "a" * 64, 123)
    m = new_message("fragment.ready", fragment="F1", artifact=ref, extra=[1, 2])
    back = unpack(pack(m))
    assert back == m and back["artifact"] == {"path": ref.path, "sha256": ref.sha256, "bytes": 123}
    assert back["v"] == VERSION and len(back["uid"]) == 32


@pytest.mark.parametrize("doc, phrase", [
    ([1, 2], "must be a map"),
    ({"v": 1, "type": "rgbn.ready", "time": 0.0}, "uid"),
    ({"v": 2, "type": "rgbn.ready", "uid": "x", "time": 0.0}, "schema version 2"),
    ({"v": 1, "type": "nope", "uid": "x", "time": 0.0}, "unknown message type"),
    ({"v": 1, "type": "rgbn.ready", "uid": "x", "time": 0.0, "fragment": "F", "face": "front"}, "lacks artifact"),
    ({"v": 1, "type": "rgbn.ready", "uid": "x", "time": 0.0, "fragment": "F", "face": "front", "artifact": {"path": "p"}},
     "malformed artifact"),
])
def test_invalid_documents_are_refused_with_a_reason(doc, phrase):
    with pytest.raises(MessageError, match=phrase):
        validate(doc)


def test_garbage_bytes_are_a_message_error():
    with pytest.raises(MessageError, match="undecodable"):
        unpack(b"\xc1\xc1\xc1")


def test_unknown_fields_are_kept_for_readers_to_ignore():
    m = new_message("match.verified", fragment="A", other="B", verdict=True, note="new field")
    assert unpack(pack(m))["note"] == "new field"


def test_docs_describe_every_message_type_with_a_valid_example():
    text = DOC.read_text()
    for kind, (_, required) in EVENT_TYPES.items():
        m = re.search(rf"^### `{re.escape(kind)}`\n(.*?)```json\n(.*?)```", text, re.S | re.M)
        assert m, f"docs/messages.md lacks a section with a JSON example for {kind}"
        example = json.loads(m.group(2))
        assert validate(example)["type"] == kind
        for field in required:
            assert field in example
