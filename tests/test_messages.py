"""Message documents: validation, packing, and docs/messages.md covering every type."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from common.messages import (EVENT_TYPES, MAX_DEPTH, MAX_MESSAGE_BYTES, VERSION, MessageError, new_message, pack,
                             unpack, validate)
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


# -- field validation by type and range (issue 19) -----------------------------------------------

def _doc(**over):
    d = {"v": VERSION, "type": "noop.job", "uid": "0123456789abcdef" * 2, "time": 1.7e9}
    d.update(over)
    return d


@pytest.mark.parametrize("over, phrase", [
    ({"uid": 2 ** 64 - 1}, "64-bit"),
    ({"uid": 12345}, "32 lower-case hex"),
    ({"uid": "x" * 32}, "32 lower-case hex"),
    ({"uid": "ABCDEF0123456789" * 2}, "32 lower-case hex"),
    ({"time": "yesterday"}, "UNIX seconds"),
    ({"time": float("nan")}, "UNIX seconds"),
    ({"probability": float("nan")}, r"\[0, 1\]"),
    ({"time": True}, "UNIX seconds"),
    ({"fragment": "a/b/c"}, "fragment id"),
    ({"fragment": "<script>"}, "fragment id"),
    ({"fragment": ".."}, "fragment id"),
    ({"fragment": "F" * 65}, "fragment id"),
    ({"other": 7}, "fragment id"),
    ({"face": "Front/../x"}, "face name"),
    ({"artifact": {"path": "/etc/passwd", "sha256": "0" * 64, "bytes": 1}}, "relative"),
    ({"artifact": {"path": "a/../../b", "sha256": "0" * 64, "bytes": 1}}, "relative"),
    ({"artifact": {"path": "a.h5", "sha256": "xyz", "bytes": 1}}, "64 hex"),
    ({"artifact": {"path": "a.h5", "sha256": "0" * 64, "bytes": -1}}, "not a size"),
    ({"probability": 1.5}, r"\[0, 1\]"),
    ({"x": "y" * 20000}, "string of 20000"),
    ({"x": list(range(20000))}, "20000 entries"),
    ({"x": {1: 2}}, "non-text key"),
])
def test_fields_are_validated_by_type_and_range(over, phrase):
    with pytest.raises(MessageError, match=phrase):
        validate(_doc(**over))


def test_nesting_is_capped_without_recursion():
    deep = []
    for _ in range(100000):  # deeper than Python's recursion limit: the check must not recurse
        deep = [deep]
    with pytest.raises(MessageError, match="deeper than"):
        validate(_doc(x=deep))
    ok = []
    for _ in range(MAX_DEPTH - 2):
        ok = [ok]
    assert validate(_doc(x=ok))["x"] == ok


def test_oversized_message_is_refused_before_decoding():
    body = pack(_doc(x=["y" * 1000] * 300))
    assert len(body) > MAX_MESSAGE_BYTES
    with pytest.raises(MessageError, match=f"at most {MAX_MESSAGE_BYTES}"):
        unpack(body)


def test_fragment_ids_the_station_makes_are_valid():
    for fid in ("F0001", "wall-3-0042", "DAFNE_adam-12", "a.b_c-d"):
        assert validate(_doc(fragment=fid, face="front"))["fragment"] == fid


def test_nan_in_other_fields_is_allowed():
    """A stage may report a quantity it could not measure as nan (the matcher's alignment does)."""
    m = new_message("match.proposed", fragment="A", other="B", probability=0.5,
                    alignment={"residual_mm": float("nan")})
    assert unpack(pack(m))["alignment"]["residual_mm"] != unpack(pack(m))["alignment"]["residual_mm"]
