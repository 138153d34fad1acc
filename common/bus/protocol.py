"""Wire protocol of the Tessera bus (documented for other implementers in ``docs/messages.md``).

Majordomo-style (ZeroMQ Guide, ch. 4, MDP/0.2): one ROUTER socket at the broker serves workers
and clients; each multipart message after the ROUTER identity starts with an empty delimiter
frame and a protocol header naming the peer kind.

Worker <-> broker (header ``TW1``)::

    worker -> broker   READY      service  info(msgpack {host, pid})
    worker -> broker   HEARTBEAT
    worker -> broker   PROGRESS   job_id   msgpack {fraction, text}
    worker -> broker   RESULT     job_id   msgpack [event, ...]
    worker -> broker   FAIL       job_id   kind(b"error" | b"rejected")  error text (utf-8)
    worker -> broker   DISCONNECT [job_id handed back]
    broker -> worker   JOB        job_id   attempt(ascii)  event(msgpack)
    broker -> worker   HEARTBEAT
    broker -> worker   DISCONNECT

Client <-> broker (header ``TC1``): request ``[b"", TC1, command, tag, body]``, reply
``[b"", TC1, b"OK" | b"ERR", tag, body]`` where ``tag`` is the caller's correlation id, so a
DEALER client may pipeline requests. Commands: ``SUBMIT`` (body: one msgpack event; reply
``{seq}``), ``STATUS`` (reply: status map), ``RERUN`` (body ``{job}``; ``"all"`` for every parked
job; a body without ``job`` is refused), ``SINCE`` (body ``{after, limit, types?}``; reply ``{stream,
last_seq, first_seq, scanned_to, events: [[seq, event], ...]}``), ``PENDING`` (reply ``{pending:
[[service, state, type, fragment, face], ...]}``: queued and in-flight jobs). Every refused request
gets ``ERR`` with ``{error}``; so does any other frame the broker refuses, where it can answer.

Event feed (PUB): ``[topic, stream, seq(ascii), event(msgpack)]`` with ``topic`` the event type;
a heartbeat every interval ``[b"HEARTBEAT", stream, last_seq(ascii), b""]``.
"""

from __future__ import annotations

import msgpack

WORKER = b"TW1"
CLIENT = b"TC1"

READY = b"READY"
HEARTBEAT = b"HEARTBEAT"
PROGRESS = b"PROGRESS"
RESULT = b"RESULT"
FAIL = b"FAIL"
DISCONNECT = b"DISCONNECT"
JOB = b"JOB"

SUBMIT = b"SUBMIT"
STATUS = b"STATUS"
RERUN = b"RERUN"
SINCE = b"SINCE"
PENDING = b"PENDING"
OK = b"OK"
ERR = b"ERR"

FAIL_ERROR = b"error"
FAIL_REJECTED = b"rejected"

FEED_HEARTBEAT = b"HEARTBEAT"


def dumps(obj) -> bytes:
    """msgpack encoding used on every frame that carries a structure."""
    return msgpack.packb(obj, use_bin_type=True)


def loads(data: bytes):
    """Inverse of :func:`dumps` (raises msgpack's errors on garbage; callers turn them into rejections)."""
    return msgpack.unpackb(data, raw=False, strict_map_key=False)
