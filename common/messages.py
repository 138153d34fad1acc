"""Message (event) documents: the one place every message type is declared.

Every message is a msgpack map with at least ``v`` (schema version), ``type``, ``uid`` (unique
per message) and ``time`` (UNIX seconds, float). Fragment events also carry ``fragment`` and
``face``; results carry an ``artifact`` pointer ``{path, sha256, bytes}`` (see
:class:`common.store.ArtifactRef`). Unknown fields are ignored by readers; a breaking change
bumps ``v``. ``docs/messages.md`` documents each type with an example and is checked against
:data:`EVENT_TYPES` by the tests.
"""

from __future__ import annotations

import json
import math
import re
import sys
import time as _time
import uuid
from typing import Any, Mapping

import msgpack

VERSION = 1

#: limits every message must respect (checked by :func:`validate` and :func:`unpack`)
MAX_MESSAGE_BYTES = 256 * 1024    # packed size of one message
MAX_DEPTH = 16                    # nesting of maps and lists (the message itself is depth 1)
MAX_STRING_CHARS = 16384          # any one string (an error text is cut to this by its sender)
MAX_ITEMS = 10000                 # entries of any one map or list
MAX_PATH_CHARS = 1024             # an artifact pointer's path
MAX_KEY_CHARS = 256               # any map key
INT_RANGE = (-(2 ** 63), 2 ** 63 - 1)  # integers a journal, SQLite or a JSON reader can hold
#: The patterns end in ``\Z``, not ``$``: ``$`` also matches before a final newline, so ``"F1\n"`` would pass
#: as a fragment id (and name a folder with a newline on storage).
#: ``uid``: 32 lower-case hex digits (a UUID4 ``hex``)
UID_PATTERN = re.compile(r"^[0-9a-f]{32}\Z")
#: ``fragment`` and ``other``: 1-64 letters, digits, '.', '_' or '-', starting with a letter or digit
FRAGMENT_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}\Z")
#: ``face``: 1-32 lower-case letters, digits, '_' or '-' (``front``, ``back``)
FACE_PATTERN = re.compile(r"^[a-z][a-z0-9_-]{0,31}\Z")
#: ``match.refitted`` and ``match.reranked`` ``model_version``: 1-64 letters, digits, '.', '_' or '-', starting
#: with a letter or digit (``"0003-1a2b3c4d"``)
MODEL_VERSION_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}\Z")
#: ``match.reranked`` ``redock``: at most this many fragments (the matcher sends a few per job)
MAX_REDOCK_FRAGMENTS = 64
_SHA256 = re.compile(r"^[0-9a-f]{64}\Z")
#: ``match.verified`` ``verdict``: what producers send
VERDICTS = ("confirmed", "rejected")
#: what readers of a journal also read as a verdict (the door, :func:`validate`, takes only VERDICTS and booleans)
_VERDICT_WORDS = {"confirmed": "confirmed", "confirm": "confirmed", "accept": "confirmed", "accepted": "confirmed",
                  "yes": "confirmed", "rejected": "rejected", "reject": "rejected", "no": "rejected"}
#: ``fragment.annotated`` ``changes``: the catalogue fields a person may edit, and their length
ANNOTATION_FIELDS = ("inventory", "find_spot", "context", "date", "notes")
MAX_ANNOTATION_CHARS = 2000
MAX_BY_CHARS = 64


class MessageError(ValueError):
    """A message that cannot be accepted: malformed, unknown type, wrong version, missing field."""


# type -> (one-line description, required fields beyond v/type/uid/time)
EVENT_TYPES: dict[str, tuple[str, tuple[str, ...]]] = {
    "fragment.ready": ("Raw scans of one fragment face (or both) are on storage.", ("fragment", "artifact")),
    "rgbn.ready": ("An RGBN image (albedo, normals, mask, confidence) of one face is on storage.",
                   ("fragment", "face", "artifact")),
    "features.ready": ("The feature table of one face is on storage.", ("fragment", "face", "artifact")),
    "render.ready": ("An illustration of one face is on storage.", ("fragment", "face", "artifact")),
    "match.proposed": ("A ranked join proposal between two fragments, with probability and pose.",
                       ("fragment", "other", "probability")),
    "match.ranked": ("A fragment's joins were proposed from the fast stages (1-2½); the matcher docks its best "
                     "candidates next and proposes again with poses.", ("fragment", "face", "artifact")),
    "match.verified": ("A person confirmed or rejected a proposal.", ("fragment", "other", "verdict")),
    "match.refitted": ("The matcher re-fitted its model from the verdicts; it ranks every fragment again under the "
                       "new model next.", ("model_version",)),
    "match.reranked": ("Every fragment was ranked again under a new model; the matcher docks the listed fragments' "
                       "pairs that were never docked and proposes them again.", ("model_version", "redock")),
    "fragment.annotated": ("A person edited a fragment's catalogue metadata (find-spot, context, date, notes, "
                           "inventory); carries the changed fields and who.", ("fragment", "changes", "by")),
    "stage.failed": ("A job failed its last attempt and is parked; carries the error.", ("service", "error")),
    "input.rejected": ("A message, frame or artifact was refused as malformed; carries the reason.", ("error",)),
    "noop.job": ("A job for the no-op stage: plumbing tests and the broker benchmark.", ()),
    "noop.done": ("The no-op stage finished a job; names the job and when the worker received it.", ("job",)),
}


def verdict_of(value: Any) -> str:
    """The verdict (``"confirmed"`` or ``"rejected"``) a ``match.verified`` ``verdict`` field means.

    Producers send one of :data:`VERDICTS`; ``True``/``False`` (sent by older tools) are read as well, and
    so are a few words (``confirm``, ``accept``, ``reject``, ``yes``, ``no``) that journals written before
    :func:`validate` refused them at the door may hold. Anything else raises :class:`MessageError`.
    """
    if value is True or value is False:
        return "confirmed" if value else "rejected"
    if isinstance(value, str) and value in _VERDICT_WORDS:
        return _VERDICT_WORDS[value]
    raise MessageError(f"match.verified verdict must be 'confirmed' or 'rejected', got {_short(value)}")


#: a relative pose's fields: B in A's frame, ``p_a = R(angle_deg) p_b + (tx_mm, ty_mm)``
POSE_FIELDS = ("angle_deg", "tx_mm", "ty_mm")
#: the largest translation a pose may state, mm (a join across a 10 m wall)
MAX_POSE_MM = 10_000.0


#: most candidate poses a ``match.proposed`` alignment may offer beside its own (``alternatives``)
MAX_ALTERNATIVE_POSES = 32


def pose_of(value: Any, what: str = "pose") -> dict:
    """A pose map (:data:`POSE_FIELDS`, finite numbers, the angle within ±360°, the translation within
    ±:data:`MAX_POSE_MM`) as plain floats; anything else raises :class:`MessageError` naming ``what``."""
    if not (isinstance(value, Mapping) and set(value) == set(POSE_FIELDS)):
        raise MessageError(f"{what} must be a map of exactly {', '.join(POSE_FIELDS)}, got {_short(value)}")
    out = {}
    for k in POSE_FIELDS:
        v = value[k]
        limit = 360.0 if k == "angle_deg" else MAX_POSE_MM
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not -limit <= v <= limit:   # also refuses nan
            raise MessageError(f"{what} {k} {_short(v)} is not a number within ±{limit:g}")
        out[k] = float(v)
    return out


def new_message(type: str, **fields: Any) -> dict:
    """A new message document of ``type`` with fresh ``uid`` and ``time``.

    Artifact pointers may be given as :class:`~common.store.ArtifactRef`; they are stored as dicts.
    """
    if type not in EVENT_TYPES:
        raise MessageError(f"unknown message type {type!r}; known: {sorted(EVENT_TYPES)}")
    msg = {"v": VERSION, "type": type, "uid": uuid.uuid4().hex, "time": _time.time()}
    for k, v in fields.items():
        msg[k] = v.to_dict() if hasattr(v, "to_dict") else v
    validate(msg)
    return msg


def _check_shape(msg: Mapping) -> None:
    """Depth, sizes, key types and integer ranges of a whole document, without recursion."""
    stack = [(msg, 1)]
    while stack:
        obj, depth = stack.pop()
        if isinstance(obj, (Mapping, list, tuple)):
            if depth > MAX_DEPTH:
                raise MessageError(f"message nested deeper than {MAX_DEPTH} levels")
            if len(obj) > MAX_ITEMS:
                raise MessageError(f"message holds a map or list of {len(obj)} entries (at most {MAX_ITEMS})")
            if isinstance(obj, Mapping):
                for k in obj:
                    if not isinstance(k, str):
                        raise MessageError(f"message has a non-text key {str(k)[:40]!r}")
                    if len(k) > MAX_KEY_CHARS:
                        raise MessageError(f"message has a key longer than {MAX_KEY_CHARS} characters")
                stack.extend((v, depth + 1) for v in obj.values())
            else:
                stack.extend((v, depth + 1) for v in obj)
        elif isinstance(obj, bool) or obj is None:
            continue
        elif isinstance(obj, int):
            if not INT_RANGE[0] <= obj <= INT_RANGE[1]:
                raise MessageError("message holds an integer outside the signed 64-bit range")
        elif isinstance(obj, float):
            continue  # nan is a legitimate "not measured" (e.g. an alignment residual)
        elif isinstance(obj, (str, bytes)):
            if len(obj) > MAX_STRING_CHARS:
                raise MessageError(f"message holds a string of {len(obj)} characters (at most {MAX_STRING_CHARS})")
        else:
            raise MessageError(f"message holds a value of type {type(obj).__name__}")


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _check_name(msg: Mapping, key: str, pattern: re.Pattern, what: str) -> None:
    if key in msg and not (isinstance(msg[key], str) and pattern.match(msg[key])):
        raise MessageError(f"{msg['type']} message: {key} {str(msg[key])[:80]!r} is not {what}")


def validate(msg: Any, *, legacy_verdicts: bool = False) -> dict:
    """Check a decoded message against its declared type; return it or raise :class:`MessageError`.

    Besides the required fields of its type: ``uid`` is 32 hex digits (:data:`UID_PATTERN`),
    ``time`` a finite number of seconds, ``fragment``/``other`` match :data:`FRAGMENT_PATTERN`,
    ``face`` :data:`FACE_PATTERN`, an ``artifact`` pointer has a relative ``path``, a 64-hex
    ``sha256`` and a non-negative ``bytes``, ``probability`` and ``mutual`` are in [0, 1], a ``match.proposed``
    or ``match.verified`` names two different fragments, a ``match.verified`` verdict is one of
    :data:`VERDICTS` or a boolean (with ``legacy_verdicts``, any value :func:`verdict_of` reads: a reader of
    a journal, whose older events may hold words the door no longer takes) and its optional ``pose`` one
    :func:`pose_of` reads, a
    ``match.proposed`` alignment's ``alternatives`` are at most :data:`MAX_ALTERNATIVE_POSES` poses
    :func:`pose_of` reads, a ``match.refitted`` or ``match.reranked`` ``model_version`` matches
    :data:`MODEL_VERSION_PATTERN`, a ``match.reranked`` ``redock`` is a list of 1 to
    :data:`MAX_REDOCK_FRAGMENTS` fragment ids, a ``fragment.annotated`` edit changes only
    :data:`ANNOTATION_FIELDS` (text of at most :data:`MAX_ANNOTATION_CHARS`); the whole document is
    at most :data:`MAX_DEPTH` deep, with strings, maps and lists within :data:`MAX_STRING_CHARS`
    and :data:`MAX_ITEMS` and integers within 64 bits.
    """
    if not isinstance(msg, Mapping):
        raise MessageError(f"message must be a map, got {type(msg).__name__}")
    for key in ("v", "type", "uid", "time"):
        if key not in msg:
            raise MessageError(f"message lacks required field {key!r}")
    if type(msg["v"]) is not int:  # not True, not 1.0: docs/messages.md says an integer
        raise MessageError(f"message schema version {_short(msg['v'])} is not an integer")
    if msg["v"] != VERSION:
        raise MessageError(f"message schema version {_short(msg['v'])} not supported (this reader speaks v{VERSION})")
    kind = msg["type"]
    if not isinstance(kind, str) or kind not in EVENT_TYPES:
        raise MessageError(f"unknown message type {str(kind)[:64]!r}")
    missing = [f for f in EVENT_TYPES[kind][1] if f not in msg]
    if missing:
        raise MessageError(f"{kind} message lacks {', '.join(missing)}")
    _check_shape(msg)
    _check_name(msg, "fragment", FRAGMENT_PATTERN, "a fragment id (1-64 letters, digits, '.', '_', '-')")
    _check_name(msg, "other", FRAGMENT_PATTERN, "a fragment id (1-64 letters, digits, '.', '_', '-')")
    _check_name(msg, "face", FACE_PATTERN, "a face name (lower-case letters, digits, '_', '-')")
    art = msg.get("artifact")
    if art is not None:
        if not (isinstance(art, Mapping) and {"path", "sha256", "bytes"} <= set(art)):
            raise MessageError(f"{kind} message has a malformed artifact pointer {str(art)[:120]!r}")
        path, sha, size = art["path"], art["sha256"], art["bytes"]
        if not isinstance(path, str) or not path or path.startswith("/") or ".." in path.split("/"):
            raise MessageError(f"{kind} message: artifact path {str(path)[:120]!r} must be relative to the storage root")
        if len(path) > MAX_PATH_CHARS:
            raise MessageError(f"{kind} message: artifact path of {len(path)} characters (at most {MAX_PATH_CHARS})")
        if not (isinstance(sha, str) and _SHA256.match(sha)):
            raise MessageError(f"{kind} message: artifact sha256 {str(sha)[:80]!r} is not 64 hex digits")
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            raise MessageError(f"{kind} message: artifact bytes {str(size)[:40]!r} is not a size")
    if kind == "fragment.annotated":
        ch, by = msg["changes"], msg["by"]
        if not (isinstance(ch, Mapping) and ch and all(isinstance(k, str) and isinstance(v, str) for k, v in ch.items())):
            raise MessageError(f"{kind} message: changes {str(ch)[:80]!r} is not a non-empty map of field to text")
        for k, v in ch.items():
            if k not in ANNOTATION_FIELDS:
                raise MessageError(f"{kind} message: changes field {k[:40]!r} is not one of {', '.join(ANNOTATION_FIELDS)}")
            if len(v) > MAX_ANNOTATION_CHARS:
                raise MessageError(f"{kind} message: changes field {k} is {len(v)} characters "
                                   f"(at most {MAX_ANNOTATION_CHARS})")
        if not isinstance(by, str) or len(by) > MAX_BY_CHARS:
            raise MessageError(f"{kind} message: by {str(by)[:80]!r} is not a name of at most {MAX_BY_CHARS} characters")
    if kind == "match.proposed" and isinstance(msg.get("alignment"), Mapping) and "alternatives" in msg["alignment"]:
        alts = msg["alignment"]["alternatives"]
        if not isinstance(alts, (list, tuple)) or len(alts) > MAX_ALTERNATIVE_POSES:
            raise MessageError(f"{kind} message: alignment alternatives must be a list of at most "
                               f"{MAX_ALTERNATIVE_POSES} poses, got {_short(alts)}")
        for i, alt in enumerate(alts):
            pose_of(alt, f"{kind} message: alignment alternative {i}")
    if kind in ("match.refitted", "match.reranked"):
        _check_name(msg, "model_version", MODEL_VERSION_PATTERN, "a model version (1-64 letters, digits, '.', '_', '-')")
    if kind == "match.reranked":
        redock = msg["redock"]
        if not (isinstance(redock, (list, tuple)) and 1 <= len(redock) <= MAX_REDOCK_FRAGMENTS
                and all(isinstance(f, str) and FRAGMENT_PATTERN.match(f) for f in redock)):
            raise MessageError(f"{kind} message: redock must be a list of 1 to {MAX_REDOCK_FRAGMENTS} fragment ids, "
                               f"got {_short(redock)}")
    if kind in ("match.proposed", "match.verified") and msg["fragment"] == msg["other"]:
        raise MessageError(f"{kind} message: fragment and other are both {msg['fragment']!r} (a join needs two)")
    if kind == "match.verified":
        v = msg["verdict"]
        if legacy_verdicts:   # a reader of a journal: the words older journals may hold are read
            verdict_of(v)
        elif not (v is True or v is False or (isinstance(v, str) and v in VERDICTS)):
            # the door: the words older journals may hold are read (verdict_of), never taken in anew
            raise MessageError(f"match.verified verdict must be 'confirmed' or 'rejected', got {_short(v)}")
        if msg.get("pose") is not None:
            pose_of(msg["pose"], f"{kind} message: pose")
    for name in ("probability", "mutual"):
        if name in msg:
            p = msg[name]
            if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 <= p <= 1.0:  # also refuses nan
                raise MessageError(f"{kind} message: {name} {str(p)[:40]!r} is not in [0, 1]")
    if not (isinstance(msg["uid"], str) and UID_PATTERN.match(msg["uid"])):
        raise MessageError(f"{kind} message: uid {str(msg['uid'])[:80]!r} is not 32 lower-case hex digits")
    t = msg["time"]
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 <= t < 1e11:
        raise MessageError(f"{kind} message: time {str(t)[:40]!r} is not UNIX seconds")
    return dict(msg)


def pack(msg: Mapping) -> bytes:
    """msgpack bytes of a message."""
    return msgpack.packb(dict(msg), use_bin_type=True)


def check_packed_size(msg: Mapping) -> int:
    """The packed size of a message (bytes); :class:`MessageError` when it is over :data:`MAX_MESSAGE_BYTES`, the
    limit of every message, which :func:`unpack` applies to what arrives and producers to what they send."""
    size = len(pack(msg))
    if size > MAX_MESSAGE_BYTES:
        raise MessageError(f"{msg.get('type', 'message')} of {size} bytes refused (at most {MAX_MESSAGE_BYTES})")
    return size


def finite(value: Any) -> Any:
    """``value`` with every float that is not finite (NaN, ±inf) replaced by None, recursively through maps,
    lists and tuples. A message may carry NaN ("not measured", e.g. a docked proposal's ``gap_mm``).

    Numpy scalars (float16/32/64, ints, bools) and 0-d arrays become their Python values, numpy arrays
    lists of them, under the same rule: JSON holds none of them but float64 (a float), and a float32
    NaN went to ``to_json``'s ``default`` (``str``: the text ``"nan"``, a bool ``"True"``).

    Examples
    --------
    >>> import numpy as np
    >>> finite({"a": np.float32("nan"), "b": np.array([1.5, np.inf]), "c": np.int64(3), "d": np.bool_(True)})
    {'a': None, 'b': [1.5, None], 'c': 3, 'd': True}
    """
    # a numpy value exists only when numpy is loaded: not imported here, for the broker and CLI without it
    np = sys.modules.get("numpy")
    if np is not None and isinstance(value, (np.generic, np.ndarray)):
        value = value.tolist()   # Python scalars (of a 0-d array too), nested lists of them for an array
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    return value


def to_json(value: Any, *, default: Any = str, **kwargs: Any) -> str:
    """Strict JSON text of a message or any document: NaN and ±inf written as ``null``.

    Python's ``json.dumps`` writes them as bare ``NaN`` / ``Infinity``, which no JSON reader but
    Python's accepts (``jq``, a browser's ``JSON.parse``). Numpy scalars and arrays are written as their
    Python values and lists (:func:`finite`). ``default`` turns what JSON cannot hold else into something it
    can (``str`` unless given); what it returns is made finite too. Other keyword arguments go to
    ``json.dumps`` (``indent``, ``sort_keys``).
    """
    return json.dumps(finite(value), default=lambda obj: finite(default(obj)), allow_nan=False, **kwargs)


def unpack(data: bytes, *, legacy_verdicts: bool = False) -> dict:
    """Decode and validate msgpack bytes; any defect raises :class:`MessageError`.

    More than :data:`MAX_MESSAGE_BYTES` is refused before decoding. ``legacy_verdicts`` is
    :func:`validate`'s: readers of journalled events (a worker's jobs, the web app's feed) pass True,
    the broker's door (``SUBMIT``) does not.
    """
    if len(data) > MAX_MESSAGE_BYTES:
        raise MessageError(f"message of {len(data)} bytes refused (at most {MAX_MESSAGE_BYTES})")
    try:
        msg = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise MessageError(f"undecodable message ({type(exc).__name__}: {exc})") from exc
    return validate(msg, legacy_verdicts=legacy_verdicts)
