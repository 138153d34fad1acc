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
    m = new_message("match.verified", fragment="A", other="B", verdict="confirmed", note="new field")
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
    ({"x": {"k" * 257: 1}}, "key longer than 256"),
    ({"artifact": {"path": "a/" * 512 + "b.h5", "sha256": "0" * 64, "bytes": 1}}, "at most 1024"),
    ({"artifact": {"path": "a.h5", "sha256": "A" * 64, "bytes": 1}}, "64 hex"),
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


# -- the contract of docs/messages.md against the code (audit of docs vs code) -------------------

_ROOT = Path(__file__).resolve().parents[1]


def _section(kind: str) -> str:
    """The text of ``### `kind` `` in docs/messages.md, up to the next heading."""
    m = re.search(rf"^### `{re.escape(kind)}`\n(.*?)(?=^##)", DOC.read_text(), re.S | re.M)
    assert m, f"docs/messages.md has no section for {kind}"
    return m.group(1)


def test_the_docs_list_exactly_the_required_fields_the_schema_checks():
    """Each section's "Required: ..." names the fields EVENT_TYPES requires, no more, no fewer."""
    for kind, (_, required) in EVENT_TYPES.items():
        text = _section(kind)
        if "Required:" not in text:
            assert not required, f"docs/messages.md: {kind} has no 'Required:' list"
            continue
        rest = text.split("Required:", 1)[1]
        while re.search(r"\([^()]*\)", rest):   # explanations in parentheses, innermost first
            rest = re.sub(r"\([^()]*\)", "", rest)
        listed = re.findall(r"`([a-z_]+)`", re.split(r";|\.\s", rest, maxsplit=1)[0])
        assert sorted(listed) == sorted(required), f"{kind}: docs require {listed}, EVENT_TYPES {list(required)}"


def _builders():
    """(file, line, type, field names) of every ``new_message("<type>", field=...)`` and importer
    ``Output("<type>", ref, {field: ...})`` in the product's code."""
    import ast
    for path in sorted([*(_ROOT / "common").rglob("*.py"), *(_ROOT / "services").rglob("*.py")]):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call):
                continue
            name = getattr(node.func, "attr", getattr(node.func, "id", None))
            if not node.args or name not in ("new_message", "Output"):
                continue
            kind = node.args[0].value if isinstance(node.args[0], ast.Constant) else None  # None: computed
            if name == "new_message":
                fields = [kw.arg for kw in node.keywords if kw.arg]
            elif name == "Output" and len(node.args) >= 3 and isinstance(node.args[2], ast.Dict):
                fields = [k.value for k in node.args[2].keys if isinstance(k, ast.Constant)]
            else:
                continue
            yield path.relative_to(_ROOT).as_posix(), node.lineno, kind, fields


def test_every_message_the_code_builds_is_a_documented_type_with_documented_fields():
    """A field a producer sets that docs/messages.md does not name in the type's section (or in
    the common fields) is drift: another lab's subscriber cannot know what it means."""
    common = re.search(r"## Common fields\n(.*?)## Message types", DOC.read_text(), re.S).group(1)
    # builders whose type is computed: the types they may build
    computed = {"common/bus/broker.py": ("stage.failed", "input.rejected"),   # _job_failed: parked or rejected
                "common/imports/driver.py": ()}                               # Output(...)'s, checked below
    seen, undocumented = set(), []
    for where, line, kind, fields in _builders():
        if kind is None:
            assert where in computed, f"{where}:{line} builds a message of a computed type: list which in this test"
            kinds = computed[where]
        else:
            assert kind in EVENT_TYPES, f"{where}:{line} builds an undeclared message type {kind!r}"
            kinds = (kind,)
        for k in kinds:
            seen.add(k)
            text = _section(k)
            undocumented += [f"{where}:{line} {k}.{f}" for f in fields if f"`{f}`" not in text + common]
    assert not undocumented, "fields set by the code but not in docs/messages.md:\n" + "\n".join(undocumented)
    # noop.job is submitted by tests and the broker benchmark with any fields
    assert seen >= set(EVENT_TYPES) - {"noop.job"}, f"no builder found for {set(EVENT_TYPES) - seen}"


def test_match_proposed_fields_are_documented():
    from common.matching.proposals import Proposal
    p = Proposal("A", "B", 0.5, "m1", patch_a=1, patch_b=None, angle_deg=10.0, tx_mm=1.0, ty_mm=2.0,
                 alignment={"angle_deg": 10.0, "tx_mm": 1.0, "ty_mm": 2.0, "gap_mm": float("nan"),
                            "contact_mm": 12.0, "overlap_mm2": 0.0, "score": 11.0}, id=3)
    m = new_message("match.proposed", stage="docked", **p.to_event_fields())
    text = _section("match.proposed")
    for key in set(m) - {"v", "type", "uid", "time"}:
        assert f"`{key}`" in text, f"match.proposed.{key} is not documented"
    for key in m["alignment"]:
        assert f"`{key}`" in text, f"match.proposed.alignment.{key} is not documented"


def test_the_routing_the_docs_state_is_the_default_config():
    from common.config import DEFAULTS
    text = DOC.read_text()
    m = re.search(r"config's `\[routing\]` table\s*\(default: (.*?)\)\.", text, re.S)
    assert m, "docs/messages.md does not state the default routing"
    documented: dict = {}
    for kind, services in re.findall(r"`([a-z.]+) → ([a-z, ]+)`", m.group(1)):
        documented[kind] = [s.strip() for s in services.split(",")]
    assert documented == DEFAULTS["routing"]


@pytest.mark.parametrize("v", [1.0, True, "1"])
def test_the_schema_version_must_be_the_integer_1(v):
    with pytest.raises(MessageError, match="schema version"):
        validate(_doc(v=v))


@pytest.mark.parametrize("value, meaning", [("confirmed", "confirmed"), ("rejected", "rejected"),
                                            (True, "confirmed"), (False, "rejected")])
def test_verdicts_are_read_as_documented(value, meaning):
    from common.messages import verdict_of
    assert verdict_of(validate(_doc(type="match.verified", fragment="A", other="B", verdict=value))["verdict"]) == meaning


@pytest.mark.parametrize("value", ["maybe", 1, None, "", ["confirmed"], "yes", "accept", "no"])
def test_a_verdict_that_is_neither_confirmed_nor_rejected_is_refused_at_the_door(value):
    """docs/messages.md: verdict is confirmed or rejected. It was journaled, published and routed
    to the matcher, which then parked the job; the review pages showed the raw value."""
    with pytest.raises(MessageError, match="verdict"):
        validate(_doc(type="match.verified", fragment="A", other="B", verdict=value))


def test_a_verdict_may_carry_the_pose_the_person_set():
    pose = {"angle_deg": -30.0, "tx_mm": 12.0, "ty_mm": 4}
    msg = validate(_doc(type="match.verified", fragment="A", other="B", verdict="confirmed", pose=pose))
    assert msg["pose"] == pose


@pytest.mark.parametrize("pose, phrase", [
    ({"angle_deg": 1.0, "tx_mm": 2.0}, "exactly"),
    ({"angle_deg": 1.0, "tx_mm": 2.0, "ty_mm": 3.0, "z": 0.0}, "exactly"),
    ({"angle_deg": float("nan"), "tx_mm": 2.0, "ty_mm": 3.0}, "angle_deg"),
    ({"angle_deg": 1.0, "tx_mm": 2e7, "ty_mm": 3.0}, "tx_mm"),
    ({"angle_deg": 1.0, "tx_mm": "2", "ty_mm": 3.0}, "tx_mm"),
    ([1.0, 2.0, 3.0], "map"),
])
def test_a_verdicts_pose_that_is_not_a_pose_is_refused(pose, phrase):
    with pytest.raises(MessageError, match=phrase):
        validate(_doc(type="match.verified", fragment="A", other="B", verdict="confirmed", pose=pose))


@pytest.mark.parametrize("over, phrase", [
    ({"type": "match.reranked", "model_version": "0004-3c5d7e9f", "redock": []}, "redock"),
    ({"type": "match.reranked", "model_version": "0004-3c5d7e9f", "redock": ["F1"] * 65}, "redock"),
    ({"type": "match.reranked", "model_version": "0004-3c5d7e9f", "redock": ["../F1"]}, "redock"),
    ({"type": "match.reranked", "model_version": "0004-3c5d7e9f", "redock": "F1"}, "redock"),
    ({"type": "match.reranked", "model_version": "no spaces", "redock": ["F1"]}, "model version"),
    ({"type": "match.refitted", "model_version": ""}, "model version"),
    ({"type": "match.refitted", "model_version": 4}, "model version"),
])
def test_a_re_rank_message_without_a_model_version_or_with_a_malformed_fragment_list_is_refused(over, phrase):
    """docs/messages.md: match.refitted and match.reranked name the model (1-64 letters, digits, '.', '_',
    '-'); match.reranked lists 1-64 fragment ids."""
    with pytest.raises(MessageError, match=phrase):
        validate(_doc(**over))
    ok = dict(over, model_version="0004-3c5d7e9f", redock=["F1", "F2"]) if over["type"] == "match.reranked" \
        else dict(over, model_version="0004-3c5d7e9f")
    assert validate(_doc(**ok))["type"] == over["type"]


@pytest.mark.parametrize("changes, phrase", [
    ({"colour": "red"}, "not one of"),
    ({"notes": "x" * 2001}, "at most 2000"),
    ({"notes": 3}, "map of field to text"),
    ({}, "non-empty"),
])
def test_an_annotation_outside_the_documented_fields_is_refused_at_the_door(changes, phrase):
    """docs/messages.md: fields inventory, find_spot, context, date, notes; at most 2,000 characters
    each. An edit submitted with other fields was journaled and published, then refused by every
    catalogue that applied it."""
    with pytest.raises(MessageError, match=phrase):
        validate(_doc(type="fragment.annotated", fragment="F1", by="M. Rossi", changes=changes))
    ok = {"inventory": "I-1", "find_spot": "Room 3", "context": "", "date": "1990", "notes": "x" * 2000}
    assert validate(_doc(type="fragment.annotated", fragment="F1", by="M. Rossi", changes=ok))["changes"] == ok


def test_the_catalogue_edits_the_fields_the_schema_declares():
    from common.messages import ANNOTATION_FIELDS, MAX_ANNOTATION_CHARS
    from common.web.catalogue import FIELDS, MAX_FIELD_CHARS
    assert (tuple(FIELDS), MAX_FIELD_CHARS) == (ANNOTATION_FIELDS, MAX_ANNOTATION_CHARS)
    assert all(f"`{f}`" in _section("fragment.annotated") for f in ANNOTATION_FIELDS)


def test_the_limits_the_docs_state_are_the_codes():
    from common import messages
    from common.bus import broker
    text = " ".join(DOC.read_text().split())
    num = lambda s: int(s.replace(",", ""))  # noqa: E731
    m = re.search(r"at most \*\*(\d+) KiB\*\* packed, nested at most \*\*(\d+)\*\* levels", text)
    assert m and num(m.group(1)) * 1024 == messages.MAX_MESSAGE_BYTES and num(m.group(2)) == messages.MAX_DEPTH
    m = re.search(r"any string at most ([\d,]+) characters, any map or list at most ([\d,]+) entries, map keys are "
                  r"strings of at most (\d+) characters", text)
    assert m and (num(m.group(1)), num(m.group(2)), num(m.group(3))) == (messages.MAX_STRING_CHARS, messages.MAX_ITEMS,
                                                                        messages.MAX_KEY_CHARS)
    assert re.search(r"Frames larger than 1 MiB are dropped", text) and broker.MAX_FRAME_BYTES == 1 << 20
    assert f"at most {messages.MAX_PATH_CHARS:,} characters" in text


def test_the_bus_commands_the_docs_list_are_the_protocols():
    from common.bus import broker, protocol as P
    text = DOC.read_text()
    client = re.search(r"\| command \| body \| reply body \(msgpack\) \|\n\|[-| ]+\|\n((?:\|.*\n)+)", text).group(1)
    documented = {re.match(r"\| `([A-Z]+)`", row).group(1) for row in client.splitlines()}
    src = Path(broker.__file__).read_text()
    handled = set(re.findall(r"command == P\.([A-Z]+):", src[src.index("def _client_message"):src.index("def status")]))
    assert documented == handled == {"SUBMIT", "STATUS", "RERUN", "SINCE", "PENDING"}
    assert all(getattr(P, c) == c.encode() for c in documented)
    workers = re.search(r"### Workers \(header `TW1`\)\n(.*?)\n\n", text, re.S).group(1)
    rows = re.findall(r"\| (worker → broker|broker → worker) \| `([A-Z]+)", workers)
    assert {c for d, c in rows if d.startswith("worker")} == {"READY", "HEARTBEAT", "PROGRESS", "RESULT", "FAIL",
                                                               "DISCONNECT"}
    to_worker = set()
    for row in re.findall(r"^\| broker → worker \| (.*)$", workers, re.M):
        to_worker |= set(re.findall(r"`([A-Z]+)", row))
    assert to_worker == {"JOB", "HEARTBEAT", "DISCONNECT"}
    assert all(getattr(P, c) == c.encode() for c in to_worker | {c for _, c in rows})
    assert (P.WORKER, P.CLIENT, P.FAIL_ERROR, P.FAIL_REJECTED) == (b"TW1", b"TC1", b"error", b"rejected")
    assert '"error"|"rejected"' in workers.replace("\\|", "|")


@pytest.mark.parametrize("bad", [1.5, -0.1, float("nan"), "0.9", True])
def test_a_proposal_with_a_mutual_proximity_out_of_range_is_refused(bad):
    with pytest.raises(MessageError, match="mutual"):
        new_message("match.proposed", fragment="F-1", other="F-2", probability=0.5, mutual=bad)
    msg = new_message("match.proposed", fragment="F-1", other="F-2", probability=0.5, mutual=0.5)
    msg["mutual"] = bad   # as a peer might send it
    with pytest.raises(MessageError, match="mutual"):
        validate(msg)


def test_a_proposals_alternative_poses_are_checked():
    """``match.proposed``'s ``alignment.alternatives`` (docs/messages.md) are poses: a bad one is named,
    too many are refused."""
    from common.messages import MAX_ALTERNATIVE_POSES

    ok = {"angle_deg": 10.0, "tx_mm": 1.0, "ty_mm": -2.0}
    msg = new_message("match.proposed", fragment="A-1", other="B-2", probability=0.5,
                      alignment={"angle_deg": 0.0, "tx_mm": 0.0, "ty_mm": 0.0, "alternatives": [ok, ok]})
    assert len(validate(msg)["alignment"]["alternatives"]) == 2
    with pytest.raises(MessageError, match="alternative 1 tx_mm"):
        validate(dict(msg, alignment={"alternatives": [ok, dict(ok, tx_mm=float("nan"))]}))
    with pytest.raises(MessageError, match="alternative 0 must be a map"):
        validate(dict(msg, alignment={"alternatives": [[1, 2, 3]]}))
    with pytest.raises(MessageError, match="at most"):
        validate(dict(msg, alignment={"alternatives": [ok] * (MAX_ALTERNATIVE_POSES + 1)}))


@pytest.mark.parametrize("word, meaning", [("yes", "confirmed"), ("accept", "confirmed"), ("reject", "rejected")])
def test_the_words_an_older_journal_may_hold_are_still_read_as_verdicts(word, meaning):
    """The door takes only confirmed / rejected (and booleans); a journal written before it refused the
    other words is still read by the review and reconstruction pages."""
    from common.messages import verdict_of
    assert verdict_of(word) == meaning


@pytest.mark.parametrize("kind, extra", [("match.verified", {"verdict": "confirmed"}), ("match.proposed", {"probability": 0.5})])
def test_a_join_of_a_fragment_with_itself_is_refused_at_the_door(kind, extra):
    """It was journaled and routed to the matcher, which failed on it until the job was parked."""
    with pytest.raises(MessageError, match="fragment and other are both"):
        validate(_doc(type=kind, fragment="A", other="A", **extra))


@pytest.mark.parametrize("field, value", [("fragment", "F1\n"), ("face", "front\n"), ("uid", "0" * 32 + "\n"),
                                          ("other", "F2\n")])
def test_an_id_with_a_trailing_newline_is_refused(field, value):
    """``$`` matches before a final newline: ``"F1\\n"`` passed as a fragment id (a folder with a newline on
    storage) and a uid with one escaped the duplicate check. docs/security.md: ids are checked against their
    patterns, whole."""
    kind = "match.proposed" if field == "other" else "features.ready"
    extra = {"fragment": "F1", "other": "F2", "probability": 0.5} if kind == "match.proposed" else \
        {"fragment": "F1", "face": "front", "artifact": {"path": "a/b.h5", "sha256": "0" * 64, "bytes": 1}}
    with pytest.raises(MessageError, match=field):
        validate(_doc(type=kind, **{**extra, field: value}))


def test_an_artifact_digest_with_a_trailing_newline_is_refused():
    art = {"path": "a/b.h5", "sha256": "0" * 64 + "\n", "bytes": 1}
    with pytest.raises(MessageError, match="sha256"):
        validate(_doc(type="features.ready", fragment="F1", face="front", artifact=art))


def test_to_json_writes_nan_and_infinity_as_null_at_any_depth():
    import json

    import numpy as np

    from common.messages import to_json

    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    doc = {"a": [1.5, float("-inf"), {"b": float("nan"), "c": (2, 3)}], "d": "NaN", "e": True,
           "f": np.float32("nan"), "g": np.float64("inf"), "h": b"\x01"}
    # what ``default`` returns is made finite too; numpy values do not need it (to_json writes them)
    got = json.loads(to_json(doc, default=lambda o: float(o) if isinstance(o, np.floating) else o.hex()),
                     parse_constant=refuse)
    assert got == {"a": [1.5, None, {"b": None, "c": [2, 3]}], "d": "NaN", "e": True, "f": None, "g": None,
                   "h": "01"}


@pytest.mark.parametrize("dtype", ["float16", "float32", "float64"])
def test_numpy_floats_are_numbers_their_nan_and_infinities_null(dtype):
    """A numpy float32 (or float16) is not a Python float: to_json passed it to ``default`` (str), so a NaN
    came out as the text "nan" and a number as a string; numpy scalars, 0-d arrays and arrays are written as
    their Python values and lists, non-finite floats as null at any depth."""
    import json

    import numpy as np

    from common.messages import finite, to_json

    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    t = np.dtype(dtype).type
    doc = {"nan": t("nan"), "inf": t("inf"), "-inf": t("-inf"), "half": t(0.5), "zero-d": np.array(t("nan")),
           "array": np.array([[0.25, np.nan], [np.inf, -2.0]], dtype=dtype), "nested": ({"x": t("nan")}, [t(1.5)])}
    want = {"nan": None, "inf": None, "-inf": None, "half": 0.5, "zero-d": None, "array": [[0.25, None], [None, -2.0]],
            "nested": [{"x": None}, [1.5]]}
    assert json.loads(to_json(doc), parse_constant=refuse) == want
    got = finite(doc)
    assert got == want and type(got["half"]) is float and type(got["array"][0][0]) is float


def test_numpy_ints_and_bools_are_json_numbers_and_booleans():
    import json

    import numpy as np

    from common.messages import finite, to_json

    ints = [np.dtype(d).type(7) for d in ("int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64")]
    doc = {"ints": ints, "big": np.uint64(2 ** 64 - 1), "yes": np.bool_(True), "no": np.False_,
           "mask": np.array([True, False]), "counts": np.arange(3, dtype=np.int64), "zero-d": np.array(5)}
    text = to_json(doc)
    assert json.loads(text) == {"ints": [7] * 8, "big": 2 ** 64 - 1, "yes": True, "no": False, "mask": [True, False],
                                "counts": [0, 1, 2], "zero-d": 5}
    assert '"yes": true' in text and '"7"' not in text              # not their text ("True", "7")
    got = finite(doc)
    assert type(got["yes"]) is bool and all(type(v) is int for v in got["ints"]) and type(got["zero-d"]) is int


@pytest.mark.parametrize("word", ["confirm", "accept", "accepted", "yes", "reject", "no"])
def test_a_journalled_verdict_in_an_older_word_is_read_by_readers_but_refused_at_the_door(word):
    """docs/messages.md: a journal written before the broker refused them may hold these words, "which
    its readers still read". The worker decodes every job with unpack, so a re-queued match.verified in
    one of them was parked as bad input before the matcher's verdict_of could read it."""
    from common.messages import verdict_of
    doc = _doc(type="match.verified", fragment="A", other="B", verdict=word)
    with pytest.raises(MessageError, match="verdict"):
        unpack(pack(doc))                                 # the door (SUBMIT) stays strict
    with pytest.raises(MessageError, match="verdict"):
        validate(doc)
    back = unpack(pack(doc), legacy_verdicts=True)        # a reader of the journal
    assert back["verdict"] == word and verdict_of(back["verdict"]) in ("confirmed", "rejected")
    assert validate(doc, legacy_verdicts=True) == doc


@pytest.mark.parametrize("value", ["maybe", 1, None, "", ["confirmed"], "Confirmed"])
def test_a_reader_of_the_journal_still_refuses_a_verdict_no_word_means(value):
    with pytest.raises(MessageError, match="verdict"):
        validate(_doc(type="match.verified", fragment="A", other="B", verdict=value), legacy_verdicts=True)
