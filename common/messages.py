"""Message (event) documents: the one place every message type is declared.

Every message is a msgpack map with at least ``v`` (schema version), ``type``, ``uid`` (unique
per message) and ``time`` (UNIX seconds, float). Fragment events also carry ``fragment`` and
``face``; results carry an ``artifact`` pointer ``{path, sha256, bytes}`` (see
:class:`common.store.ArtifactRef`). Unknown fields are ignored by readers; a breaking change
bumps ``v``. ``docs/messages.md`` documents each type with an example and is checked against
:data:`EVENT_TYPES` by the tests.
"""

from __future__ import annotations

import time as _time
import uuid
from typing import Any, Mapping

import msgpack

VERSION = 1


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
    "match.verified": ("A person confirmed or rejected a proposal.", ("fragment", "other", "verdict")),
    "stage.failed": ("A job failed its last attempt and is parked; carries the error.", ("service", "error")),
    "input.rejected": ("A message, frame or artifact was refused as malformed; carries the reason.", ("error",)),
    "noop.job": ("A job for the no-op stage: plumbing tests and the broker benchmark.", ()),
    "noop.done": ("The no-op stage finished a job; names the job and when the worker received it.", ("job",)),
}


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


def validate(msg: Any) -> dict:
    """Check a decoded message against its declared type; return it or raise :class:`MessageError`."""
    if not isinstance(msg, Mapping):
        raise MessageError(f"message must be a map, got {type(msg).__name__}")
    for key in ("v", "type", "uid", "time"):
        if key not in msg:
            raise MessageError(f"message lacks required field {key!r}")
    if msg["v"] != VERSION:
        raise MessageError(f"message schema version {msg['v']!r} not supported (this reader speaks v{VERSION})")
    kind = msg["type"]
    if kind not in EVENT_TYPES:
        raise MessageError(f"unknown message type {kind!r}")
    missing = [f for f in EVENT_TYPES[kind][1] if f not in msg]
    if missing:
        raise MessageError(f"{kind} message lacks {', '.join(missing)}")
    art = msg.get("artifact")
    if art is not None and not (isinstance(art, Mapping) and {"path", "sha256", "bytes"} <= set(art)):
        raise MessageError(f"{kind} message has a malformed artifact pointer {art!r}")
    return dict(msg)


def pack(msg: Mapping) -> bytes:
    """msgpack bytes of a message."""
    return msgpack.packb(dict(msg), use_bin_type=True)


def unpack(data: bytes) -> dict:
    """Decode and validate msgpack bytes; any defect raises :class:`MessageError`."""
    try:
        msg = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise MessageError(f"undecodable message ({type(exc).__name__}: {exc})") from exc
    return validate(msg)
