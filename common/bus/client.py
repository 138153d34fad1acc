"""Bus client: submit events to the broker, query its status, re-run parked jobs.

Used by the scanner's outbox, ``tessera ps``/``status``/``reconcile``, the web pages (a
conservator's verdict is a ``match.verified`` event) and any script::

    from common.bus.client import BrokerClient
    from common.messages import new_message
    with BrokerClient.from_config(cfg) as bus:
        seq = bus.submit(new_message("match.verified", fragment="F0001", other="F0002", verdict="confirmed"))
        print(bus.status()["queues"])

Every call has a timeout (``[client] timeout_s``) and retries (``retries``, Lazy Pirate
pattern: a silent broker's socket is closed and reopened) and then raises
:class:`BrokerUnavailable` — it never blocks forever. A submitted event is acknowledged only
once the broker has journaled it; re-submitting the same event (same ``uid``) after a lost
acknowledgement is harmless (the broker de-duplicates by ``uid``).
"""

from __future__ import annotations

import itertools
import time
import uuid
from typing import Iterable, Mapping

import zmq

from common import messages
from common.bus import protocol as P
from common.bus.security import secure_client_socket
from common.config import broker_endpoint


class BrokerUnavailable(ConnectionError):
    """The broker did not answer within the timeout and retries."""


class BrokerRefused(RuntimeError):
    """The broker answered with an error (e.g. a malformed event); the message says why.

    ``retry`` is True when the refusal is the broker's own, passing state (its journal cannot
    write): the same request will be accepted later, so a sender keeps it.
    """

    def __init__(self, message: str, *, retry: bool = False):
        super().__init__(message)
        self.retry = bool(retry)


def _refused(reply) -> BrokerRefused:
    if isinstance(reply, dict):
        return BrokerRefused(str(reply.get("error", "refused")), retry=bool(reply.get("retry", False)))
    return BrokerRefused(str(reply))


class BrokerClient:
    """Request/reply client of the broker (DEALER socket; thread-confined: one per thread).

    Parameters
    ----------
    endpoint : str
        Broker ROUTER endpoint, e.g. ``tcp://127.0.0.1:5555``.
    timeout_s : float
        Seconds to wait for each reply.
    retries : int
        Attempts before :class:`BrokerUnavailable`.
    """

    def __init__(self, endpoint: str, *, timeout_s: float = 2.5, retries: int = 3, context: zmq.Context | None = None,
                 security: Mapping | None = None):
        self.endpoint = endpoint
        self.security = security or {}  # a config with [security]: CURVE keys when curve is on
        self.timeout_s = float(timeout_s)
        self.retries = max(1, int(retries))
        self.ctx = context or zmq.Context.instance()
        self._sock = None
        self._tags = itertools.count(1)
        self._prefix = uuid.uuid4().hex[:8]

    @classmethod
    def from_config(cls, config: Mapping, **kw) -> "BrokerClient":
        """Client for the broker named by a loaded configuration."""
        c = config["client"]
        return cls(broker_endpoint(config), timeout_s=kw.pop("timeout_s", c["timeout_s"]),
                   retries=kw.pop("retries", c["retries"]), security=kw.pop("security", config), **kw)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close(linger=0)
            self._sock = None

    def _socket(self):
        if self._sock is None:
            self._sock = secure_client_socket(self.ctx.socket(zmq.DEALER), self.security)
            self._sock.setsockopt(zmq.LINGER, 0)
            self._sock.connect(self.endpoint)
        return self._sock

    def _tag(self) -> bytes:
        return f"{self._prefix}-{next(self._tags)}".encode()

    def request(self, command: bytes, body: bytes = b"") -> object:
        """Send one request and return the decoded reply body (retrying, then raising)."""
        for _attempt in range(self.retries):
            sock = self._socket()
            tag = self._tag()
            sock.send_multipart([b"", P.CLIENT, command, tag, body])
            deadline = time.monotonic() + self.timeout_s
            while (left := deadline - time.monotonic()) > 0:
                if not sock.poll(left * 1000):
                    break
                frames = sock.recv_multipart()
                if len(frames) < 5 or frames[3] != tag:
                    continue  # a late reply to an earlier, timed-out request
                reply = P.loads(frames[4])
                if frames[2] != P.OK:
                    raise _refused(reply)
                return reply
            self.close()  # Lazy Pirate: a fresh socket for the retry
        raise BrokerUnavailable(f"broker at {self.endpoint} did not answer {command.decode()} "
                                f"within {self.timeout_s:g} s x {self.retries}")

    def submit(self, event: Mapping) -> int:
        """Submit one event; returns its feed sequence number once the broker journaled it."""
        return int(self.request(P.SUBMIT, messages.pack(messages.validate(event)))["seq"])

    def submit_many(self, events: Iterable[Mapping], *, window: int = 500) -> list[int]:
        """Submit events pipelined (up to ``window`` unacknowledged); returns their sequence numbers.

        Much faster than :meth:`submit` in a loop: the broker journals a whole window with one
        fsync. Raises :class:`BrokerUnavailable` if acknowledgements stop for ``timeout_s``
        (events already acknowledged stay accepted; re-submitting all is harmless).
        """
        bodies = [messages.pack(messages.validate(e)) for e in events]
        seqs: list[int | None] = [None] * len(bodies)
        sock = self._socket()
        pending: dict[bytes, int] = {}
        nxt = 0
        deadline = time.monotonic() + self.timeout_s
        while nxt < len(bodies) or pending:
            while nxt < len(bodies) and len(pending) < window:
                tag = self._tag()
                pending[tag] = nxt
                sock.send_multipart([b"", P.CLIENT, P.SUBMIT, tag, bodies[nxt]])
                nxt += 1
            left = deadline - time.monotonic()
            if left <= 0 or not sock.poll(left * 1000):
                self.close()
                raise BrokerUnavailable(f"broker at {self.endpoint} stopped acknowledging "
                                        f"({len(pending)} events unacknowledged)")
            while True:
                try:
                    frames = sock.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                i = pending.pop(frames[3], None) if len(frames) >= 5 else None
                if i is None:
                    continue
                reply = P.loads(frames[4])
                if frames[2] != P.OK:
                    raise _refused(reply)
                seqs[i] = int(reply["seq"])
                deadline = time.monotonic() + self.timeout_s
        return [int(s) for s in seqs]

    def status(self) -> dict:
        """Broker status: ``queues`` (service -> queued jobs), ``workers`` (host -> list of
        {service, pid, job, up_s}), ``in_flight``, ``parked`` (job, service, fragment, attempts,
        error), ``completed``, ``jobs_per_s`` (last minute), ``last_seq``, ``stream``, ``routing``."""
        return self.request(P.STATUS)

    def rerun(self, job: str = "all") -> list[str]:
        """Re-queue a parked job (``"all"``: every parked job); returns the job ids re-queued."""
        return list(self.request(P.RERUN, P.dumps({"job": job}))["rerun"])

    def since(self, after: int, limit: int = 1000, types: Iterable[str] | None = None) -> dict:
        """Retained events with sequence number > ``after``: ``{stream, last_seq, first_seq,
        scanned_to, events: [[seq, msgpack bytes], ...]}`` (oldest first, at most ``limit``; of
        ``types`` only if given, and then ``scanned_to`` is how far the broker looked)."""
        req = {"after": int(after), "limit": int(limit)}
        if types:
            req["types"] = sorted(types)
        return self.request(P.SINCE, P.dumps(req))

    def pending(self) -> list[tuple]:
        """Queued and in-flight jobs: ``(service, state, event type, fragment, face)`` each."""
        return [tuple(x) for x in self.request(P.PENDING)["pending"]]


def submit(event: Mapping, config: Mapping) -> int:
    """Submit one event to the broker of ``config``; returns its sequence number."""
    with BrokerClient.from_config(config) as bus:
        return bus.submit(event)


def status(config: Mapping) -> dict:
    """Status of the broker of ``config`` (see :meth:`BrokerClient.status`)."""
    with BrokerClient.from_config(config) as bus:
        return bus.status()


def rerun(job: str, config: Mapping) -> list[str]:
    """Re-run a parked job (or ``"all"``) on the broker of ``config``."""
    with BrokerClient.from_config(config) as bus:
        return bus.rerun(job)
