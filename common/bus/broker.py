"""The broker: Majordomo-style job queues, a durable journal and the event feed.

After the ZeroMQ Guide's ``mdbroker.py`` (ch. 4, Majordomo Protocol): one ROUTER socket; workers
announce READY for a service, heartbeat both ways, hold one job at a time; a queue per service.
Tessera adds what a station needs on top:

* **routing** — every accepted event becomes one job per service listed for its type in the
  config's ``[routing]`` table; a job's result is a list of new events, routed in turn;
* **at-least-once** — every accepted event and its jobs are in the journal (SQLite, local disk,
  group commit: one fsync per poll-loop batch) before the submitter gets its acknowledgement and
  before the event is published; a dead worker's job is re-queued; a broker restart replays the
  journal (queued and in-flight jobs are queued again); stage outputs are content-keyed, so a
  repeated job is harmless;
* **failure parking** — after ``max_attempts`` failures (exceptions or dead workers) a job is
  parked and a ``stage.failed`` event carries the error; a rejected input (malformed message,
  digest mismatch, truncated HDF5) is parked at once with an ``input.rejected`` event; parked jobs
  are listed by STATUS and re-run by RERUN;
* **event feed** — every event is published on a PUB socket with a per-stream sequence number and
  a heartbeat every interval; SINCE requests return retained events after a sequence number (the
  Guide's Clone pattern), so a subscriber that reconnects misses nothing;
* **defence** — every frame is checked before anything is journaled: message fields by type and
  range (:func:`common.messages.validate`), sizes and nesting capped; every refusal that can be
  answered gets an ``ERR`` reply; refused frames are counted (STATUS ``refused``) and summarised in
  at most one ``input.rejected`` event per ``refusal_event_interval_s``, so garbage never pushes
  the catch-up history out; a result is accepted only from the worker holding the job; with CURVE
  on, a key's role (``tessera keys add --role``) decides what it may register as and submit;
* **idempotent announcements** — an output event a worker returns is announced once: the same
  output (same fields apart from ``uid`` and ``time``) returned again, e.g. after a re-submitted
  ``fragment.ready``, is dropped, so no stage downstream runs twice for it.

The wire protocol is in :mod:`common.bus.protocol` and ``docs/messages.md``.
"""

from __future__ import annotations

import collections
import gc
import hashlib
import logging
import os
import re
import socket as _socket
import threading
import time
from dataclasses import dataclass, field
from typing import Mapping

import zmq

from common import messages
from common.bus import protocol as P
from common.bus import security
from common.bus.journal import Journal

log = logging.getLogger("tessera.broker")

# timing defaults (overridden by [broker] in the config)
HEARTBEAT_INTERVAL_S = 1.0
HEARTBEAT_LIVENESS = 3
DONE_DELAY_S = 0.05      # completions alone are journaled at most this late (group commit)
REFUSAL_LOG_INTERVAL_S = 5.0   # refused frames: one log line per this, with the count
MAX_FRAME_BYTES = 4 * messages.MAX_MESSAGE_BYTES  # a peer sending a larger frame is disconnected by ZeroMQ
MAX_ERROR_CHARS = 2000   # a worker's error text is cut to this before it goes into an event
MAX_RESULT_EVENTS = 1000  # events one job's result may announce; more are refused (input.rejected)
SERVICE_NAME = re.compile(r"^[a-z][a-z0-9_-]{0,31}\Z")

# what a CURVE key of each role may do (docs/security.md); "admin" is the lab's own tools
# (reconcile, imports, re-runs); any role may ask STATUS, SINCE and PENDING
ROLE_SUBMITS: dict[str, frozenset] = {
    "scanner": frozenset({"fragment.ready", "rgbn.ready"}),
    "web": frozenset({"match.verified", "fragment.annotated"}),
    "admin": frozenset(messages.EVENT_TYPES),
}
# a bench PC runs `tessera web` with its scanner under one host key: its captures and its verdicts
ROLE_SUBMITS["bench"] = ROLE_SUBMITS["scanner"] | ROLE_SUBMITS["web"]
ROLE_SERVES: dict[str, frozenset] = {r: frozenset({r}) for r in ("solver", "features", "matcher", "renderer")}
ROLE_SERVES["admin"] = frozenset({"*"})
ROLE_RERUNS = frozenset({"web", "bench", "admin"})
#: what a stage key's worker may announce in its results (a renderer's key cannot slip in a verdict); admin any,
#: every other role (and a key without one: revoked, or made before roles) nothing
ROLE_ANNOUNCES: dict[str, frozenset] = {
    "solver": frozenset({"rgbn.ready"}),
    "features": frozenset({"features.ready"}),
    "matcher": frozenset({"match.proposed", "match.ranked", "match.refitted", "match.reranked"}),
    "renderer": frozenset({"render.ready"}),
}


def output_key(event: Mapping) -> str:
    """Identity of an output event: digest of its fields other than ``uid`` and ``time``."""
    core = {k: v for k, v in event.items() if k not in ("uid", "time")}
    return hashlib.sha256(P.dumps(_canonical(core))).hexdigest()[:32]


def _canonical(obj):
    if isinstance(obj, Mapping):
        return [[k, _canonical(obj[k])] for k in sorted(obj)]
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    return obj


@dataclass
class Job:
    id: str
    seq: int
    service: str
    body: bytes                 # the event, msgpack, exactly as journaled
    failures: int = 0
    state: str = "queued"       # queued | inflight | parked
    error: str = ""
    worker: bytes | None = None
    # the CURVE key (z85) of the worker it was last given to: a READY may reclaim the job only under that key.
    # None: security off, or not given since the broker started (a job re-queued from the journal)
    key: bytes | None = None
    started: float = 0.0
    progress: tuple | None = None
    _event: dict | None = None

    @property
    def event(self) -> dict:
        if self._event is None:
            try:
                self._event = P.loads(self.body)
            except Exception:
                self._event = {}
        return self._event


@dataclass
class Worker:
    identity: bytes
    service: str
    host: str = "?"
    pid: int = 0
    expiry: float = 0.0
    job: str | None = None
    since: float = field(default_factory=time.time)
    key: bytes | None = None    # its CURVE public key (None: security off): its role is looked up again before each job


class LoopClock:
    """Where the poll loop's time goes: its own CPU, waiting for a CPU, garbage collection.

    A STATUS answer is late either because the loop was busy (CPU inside the loop: the broker's
    fault) or because the loop was runnable and the machine did not run it (the run-queue wait
    of the loop's thread, read from ``/proc/thread-self/schedstat``: the machine's fault). Each
    iteration is timed from the moment ``poll`` could have returned to the end of its work:
    ``stall`` = run-queue wait while polling + the work's wall time, which is the most a message
    that arrived during the poll waited for its answer inside the broker process.

    ``summary()`` gives cumulative CPU, run-queue and GC seconds of the loop's thread and the worst
    iteration of the last ``window_s`` seconds with its parts (``cpu_ms``, ``runqueue_ms``,
    ``gc_ms``, and ``other_ms``: waiting for the GIL held by the journal writer, or a blocking call).
    Without ``/proc`` (not Linux) the run-queue figures are 0.
    """

    def __init__(self, window_s: float = 10.0):
        self.window_s = float(window_s)
        try:
            self._fd = os.open("/proc/thread-self/schedstat", os.O_RDONLY)  # the calling (poll-loop) thread
        except OSError:
            self._fd = None
        self.iterations = 0
        self.cpu_s = self.runqueue_s = 0.0
        self.gc_s = 0.0
        self._gc_started = 0.0
        self._gc_in_iteration = 0.0
        self._worst: collections.deque = collections.deque()   # (monotonic, stall_ms, cpu, rq, gc, other)
        gc.callbacks.append(self._on_gc)

    def close(self) -> None:
        try:
            gc.callbacks.remove(self._on_gc)
        except ValueError:
            pass
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._gc_started = time.perf_counter()
        elif self._gc_started:
            dt = time.perf_counter() - self._gc_started
            self.gc_s += dt
            self._gc_in_iteration += dt
            self._gc_started = 0.0

    def runqueue_ns(self) -> int:
        """Nanoseconds the loop's thread has spent runnable but not running (0 without /proc)."""
        if self._fd is None:
            return 0
        try:
            return int(os.pread(self._fd, 128, 0).split()[1])
        except (OSError, IndexError, ValueError):
            return 0

    def mark(self) -> tuple:
        """Before ``poll``: the clocks."""
        self._gc_in_iteration = 0.0
        return self.runqueue_ns(), time.thread_time()

    def woke(self) -> tuple:
        """After ``poll`` returned: the clocks at the start of the work."""
        return time.perf_counter(), self.runqueue_ns(), time.thread_time()

    def done(self, before: tuple, woke: tuple) -> None:
        """After the iteration's work: account it."""
        q0, c0 = before
        t1, q1, c1 = woke
        # read in the reverse order of woke(): the CPU interval then lies inside the wall interval,
        # so an iteration's CPU never exceeds its stall by the time the clocks themselves take
        c2 = time.thread_time()
        q2 = self.runqueue_ns()
        t2 = time.perf_counter()
        self.iterations += 1
        self.cpu_s += c2 - c0
        self.runqueue_s += (q2 - q0) / 1e9
        wake_rq = (q1 - q0) / 1e6
        work = (t2 - t1) * 1e3
        cpu, rq, gcm = (c2 - c1) * 1e3, (q2 - q1) / 1e6, self._gc_in_iteration * 1e3
        stall = wake_rq + work
        now = time.monotonic()
        w = self._worst
        while w and (w[0][0] < now - self.window_s or w[-1][1] <= stall):
            if w[0][0] < now - self.window_s:
                w.popleft()
            else:
                w.pop()
        w.append((now, stall, cpu, wake_rq + rq, gcm, max(0.0, work - cpu - rq)))

    def summary(self) -> dict:
        """Cumulative seconds and the worst iteration of the last ``window_s`` (ms)."""
        now = time.monotonic()
        worst = next(((s, c, q, g, o) for t, s, c, q, g, o in self._worst if t >= now - self.window_s), None)
        # microseconds: an idle loop's first second costs well under a millisecond of CPU
        out = {"iterations": self.iterations, "cpu_s": round(self.cpu_s, 6), "runqueue_s": round(self.runqueue_s, 6),
               "gc_s": round(self.gc_s, 6), "window_s": self.window_s, "worst_ms": None}
        if worst is not None:
            out["worst_ms"] = {k: round(v, 2) for k, v in zip(("stall", "cpu", "runqueue", "gc", "other"), worst)}
        return out


class Broker:
    """The station's broker.

    Parameters
    ----------
    config : dict
        Loaded configuration (:func:`common.config.load_config`); uses ``[broker]`` and ``[routing]``.
    context : zmq.Context, optional
        Shared context (a new one by default).

    Examples
    --------
    A service process runs it until SIGTERM::

        broker = Broker(load_config())
        broker.run(stop_event)
    """

    def __init__(self, config: Mapping, context: zmq.Context | None = None):
        b = config["broker"]
        self.config = config
        self.routing: dict[str, list[str]] = {k: list(v) for k, v in config["routing"].items()}
        self.interval = float(b.get("heartbeat_interval_s", HEARTBEAT_INTERVAL_S))
        self.liveness = int(b.get("heartbeat_liveness", HEARTBEAT_LIVENESS))
        self.max_attempts = int(b["max_attempts"])
        self.batch_max = int(b["batch_max"])
        self.history = int(b["feed_history"])
        self.ctx = context or zmq.Context.instance()
        self.journal = Journal(b["journal_dir"], history=self.history, compact_interval_s=b["compact_interval_s"])
        state = self.journal.load()
        self.stream = state.stream.encode()
        self.last_seq = state.last_seq          # highest sequence number assigned
        self.published_seq = state.last_seq     # highest sequence number durable and published
        self.jobs: dict[str, Job] = {}
        self.queues: dict[str, collections.deque] = collections.defaultdict(collections.deque)
        self.waiting: dict[str, collections.deque] = collections.defaultdict(collections.deque)
        self.workers: dict[bytes, Worker] = {}
        self._uids: dict[str, int] = {}
        self._uid_order: collections.deque = collections.deque()
        for uid, seq in state.uids:
            self._remember(uid, seq)
        self._outputs: set[str] = set(state.outputs)
        self.duplicates_dropped = 0
        self.refused: collections.Counter = collections.Counter()   # reason kind -> count
        self._refused_window = 0          # refusals since the last summary event
        self._refused_last = ""
        self._refusal_logged = 0.0
        self._refusal_evented = 0.0
        self.refusal_interval = float(b.get("refusal_event_interval_s", 60.0))
        for jid, seq, service, st, failures, error, body in state.jobs:
            job = Job(jid, seq, service, bytes(body), failures=failures, error=error,
                      state="parked" if st == "parked" else "queued")
            self.jobs[jid] = job
            if job.state == "queued":
                self.queues[service].append(jid)
        self._ops: list = []
        self._after: list = []
        self._waiting_batches: collections.OrderedDict = collections.OrderedDict()
        self._batch_id = 0
        self._dirty: set[str] = set(self.queues)
        self._completed = 0
        self._rate: collections.deque = collections.deque()   # (second, completions)
        self._started = time.time()
        self._last_feed = 0.0
        self._last_flush = 0.0
        self._journal_ok = True
        self.router = self.feed = self._signal = None
        self._auth = None
        self.clock: LoopClock | None = None
        if state.jobs:
            log.info("journal replayed: %d queued, %d parked jobs; stream %s at seq %d",
                     sum(j.state == "queued" for j in self.jobs.values()),
                     sum(j.state == "parked" for j in self.jobs.values()), state.stream, self.last_seq)

    # -- sockets ---------------------------------------------------------------------------
    def bind(self) -> None:
        """Bind the ROUTER and PUB sockets and start the journal writer."""
        b = self.config["broker"]
        self._auth = security.start_authenticator(self.ctx, self.config)  # None unless [security] curve
        self.router = security.secure_server_socket(self.ctx.socket(zmq.ROUTER), self.config)
        self.router.setsockopt(zmq.LINGER, 0)
        self.router.setsockopt(zmq.ROUTER_HANDOVER, 1)
        self.router.setsockopt(zmq.SNDHWM, 100000)
        self.router.setsockopt(zmq.RCVHWM, 100000)
        self.router.setsockopt(zmq.MAXMSGSIZE, MAX_FRAME_BYTES)
        self.router.bind(f"tcp://{b['bind']}:{b['port']}")
        self.feed = security.secure_server_socket(self.ctx.socket(zmq.PUB), self.config)
        self.feed.setsockopt(zmq.LINGER, 0)
        self.feed.setsockopt(zmq.SNDHWM, 100000)
        self.feed.bind(f"tcp://{b['bind']}:{b['feed_port']}")
        endpoint = f"inproc://journal-{id(self)}"
        self._signal = self.ctx.socket(zmq.PAIR)
        self._signal.bind(endpoint)
        self.journal.start(self.ctx, endpoint)
        log.info("broker on port %d, feed on port %d, journal %s, stream %s at seq %d",
                 b["port"], b["feed_port"], self.journal.path, self.stream.decode(), self.last_seq)

    def close(self) -> None:
        """Flush the journal and close the sockets."""
        self._flush(force=True)
        deadline = time.monotonic() + 10
        while self._waiting_batches and time.monotonic() < deadline:
            if self._signal.poll(100):
                self._on_durable(self._signal.recv())
        self.journal.stop()
        for s in (self.router, self.feed, self._signal):
            if s is not None:
                s.close(linger=0)
        if self._auth is not None:
            self._auth.stop()

    def run(self, stop: threading.Event | None = None) -> None:
        """The poll loop: until ``stop`` is set (or forever)."""
        if self.router is None:
            self.bind()
        stop = stop or threading.Event()
        poller = zmq.Poller()
        poller.register(self.router, zmq.POLLIN)
        poller.register(self._signal, zmq.POLLIN)
        next_heartbeat = time.monotonic() + self.interval
        self.clock = clock = LoopClock()
        try:
            while not stop.is_set():
                timeout = max(0.0, min(next_heartbeat - time.monotonic(), DONE_DELAY_S if self._ops else 0.25))
                before = clock.mark()
                ready = dict(poller.poll(timeout * 1000))
                woke = clock.woke()
                if self.router in ready:
                    for _ in range(self.batch_max):
                        try:
                            frames = self.router.recv_multipart(zmq.NOBLOCK, copy=self._auth is None)
                        except zmq.Again:
                            break
                        role = key = None
                        if self._auth is not None:  # CURVE: the ZAP handler's User-Id is the peer's public key
                            key = self._key_of(frames[0])
                            role = self._role_for(key)
                            frames = [f.bytes for f in frames]
                        self._handle(frames, role, key)
                    self._dispatch_dirty()
                    self._flush()
                if self._signal in ready:
                    while True:
                        try:
                            self._on_durable(self._signal.recv(zmq.NOBLOCK))
                        except zmq.Again:
                            break
                    self._dispatch_dirty()
                if self._ops and not ready:
                    self._flush()
                if time.monotonic() >= next_heartbeat:
                    self._heartbeat()
                    self._dispatch_dirty()
                    self._flush()
                    next_heartbeat = time.monotonic() + self.interval
                clock.done(before, woke)
        finally:
            clock.close()
            self.close()

    # -- batches and durability ------------------------------------------------------------
    def _flush(self, force: bool = False) -> None:
        """Hand this batch's journal operations to the writer; defer its side effects until durable.

        A batch of nothing but completions waits up to ``DONE_DELAY_S`` to join the next one: no
        reply depends on it, and losing it in a crash only repeats (idempotent) jobs.
        """
        if self._ops and not self._after and not force and self._only_done() and \
                time.monotonic() - self._last_flush < DONE_DELAY_S:
            return
        self._last_flush = time.monotonic()
        if self._ops:
            self._batch_id += 1
            self.journal.append(self._batch_id, self._ops)
            self._waiting_batches[self._batch_id] = self._after
            self._ops, self._after = [], []
        elif self._after:
            if self._waiting_batches:  # keep order behind a batch still being written
                next(reversed(self._waiting_batches.values())).extend(self._after)
            else:
                self._run_actions(self._after)
            self._after = []

    def _only_done(self) -> bool:
        return all(op[0] == "done" for op in self._ops)

    def _on_durable(self, frame: bytes) -> None:
        if frame == b"FAILED":
            self._journal_ok = False
            log.error("journal cannot write: submissions are refused until it can")
            return
        if not self._journal_ok:
            log.warning("journal writable again: submissions accepted")
        self._journal_ok = True
        upto = int(frame)
        while self._waiting_batches:
            bid = next(iter(self._waiting_batches))
            if bid > upto:
                break
            self._run_actions(self._waiting_batches.pop(bid))

    def _run_actions(self, actions: list) -> None:
        for act in actions:
            kind = act[0]
            if kind == "reply":
                self.router.send_multipart([act[1], b"", P.CLIENT, act[2], act[3], act[4]])
            elif kind == "publish":
                _, etype, seq, body = act
                self.feed.send_multipart([etype.encode(), self.stream, str(seq).encode(), body])
                self.published_seq = seq
                self._last_feed = time.monotonic()

    # -- events ----------------------------------------------------------------------------
    def _remember(self, uid: str, seq: int) -> None:
        self._uids[uid] = seq
        self._uid_order.append(uid)
        while len(self._uid_order) > self.history:
            self._uids.pop(self._uid_order.popleft(), None)

    def accept_event(self, event: dict, body: bytes | None = None) -> int:
        """Journal an event and the jobs its type routes to; publish and queue them once durable."""
        when = float(event["time"])  # before a sequence number is taken: a bad field must not leave a gap
        seq = self.last_seq + 1
        self.last_seq = seq
        body = body if body is not None else P.dumps(event)
        etype = event["type"]
        self._ops.append(("event", seq, event["uid"], etype, when, body))
        self._remember(event["uid"], seq)
        for service in self.routing.get(etype, ()):
            # Dispatched at once, before the journal write completes (only the acknowledgement and
            # the publication wait for it): if the broker dies first, the submitter never got its
            # ack and re-submits the same uid, which makes the same job id, so a late result from
            # this early run completes the right job; stage outputs are content-keyed anyway.
            jid = f"{event['uid'][:12]}-{service}"
            self.jobs[jid] = Job(jid, seq, service, body, _event=event)
            self._ops.append(("job", jid, seq, service))
            self.queues[service].append(jid)
            self._dirty.add(service)
        self._after.append(("publish", etype, seq, body))
        return seq

    def _reject(self, error: str, **fields) -> None:
        """Publish an ``input.rejected`` about a job's input or output (bounded by the jobs there are)."""
        log.warning("rejected: %s", error)
        self.accept_event(messages.new_message("input.rejected", error=error[:MAX_ERROR_CHARS],
                                               broker=_socket.gethostname(), **fields))

    def _refuse(self, identity: bytes | None, kind: str, error: str, tag: bytes = b"", *, retry: bool = False) -> None:
        """Refuse one frame: ERR reply when it can be answered, counted, logged and summarised at a
        bounded rate (never one journaled event per frame: a flood must not push history out)."""
        error = error[:MAX_ERROR_CHARS]
        if identity is not None:
            body = {"error": error, "retry": True} if retry else {"error": error}
            self.router.send_multipart([identity, b"", P.CLIENT, P.ERR, tag[:256], P.dumps(body)])
        self.refused[kind] += 1
        self._refused_window += 1
        self._refused_last = error
        now = time.monotonic()
        if now - self._refusal_logged >= REFUSAL_LOG_INTERVAL_S:
            log.warning("refused %s: %s (%d refusal(s) since the last line)", kind, error, self._refused_window)
            self._refusal_logged = now
        self._refusal_summary(now)

    def _refusal_summary(self, now: float) -> None:
        if self._refused_window and now - self._refusal_evented >= self.refusal_interval:
            n, self._refused_window = self._refused_window, 0
            self._refusal_evented = now
            self.accept_event(messages.new_message(
                "input.rejected", error=f"{n} frame(s) refused; last: {self._refused_last}"[:MAX_ERROR_CHARS],
                source="broker", refused=n, broker=_socket.gethostname()))

    def _key_of(self, frame) -> bytes:
        """The CURVE public key (z85) that sent ``frame`` (b"" when unknown)."""
        try:
            key = frame.get("User-Id")
        except (zmq.ZMQError, AttributeError, ValueError):
            return b""
        return key.encode() if isinstance(key, str) else (key or b"")

    def _role_for(self, key: bytes) -> str:
        """Role of a CURVE key now ("" when unknown: allowed nothing but reading)."""
        provider = self._auth.credentials_providers.get("*") if self._auth is not None else None
        role_of = getattr(provider, "role_of", None)
        return (role_of(key) if role_of and key else "") or ""

    def _may_still_serve(self, worker: Worker) -> bool:
        """Whether a registered worker's key may still serve its service (a key revoked or re-roled since READY
        may return the job it holds, no other)."""
        if worker.key is None:
            return True
        return bool({worker.service, "*"} & ROLE_SERVES.get(self._role_for(worker.key), frozenset()))

    # -- frames ----------------------------------------------------------------------------
    def _handle(self, frames: list[bytes], role: str | None = None, key: bytes | None = None) -> None:
        """One message from the ROUTER; ``role`` is the CURVE key's role, ``key`` the key (None: security off)."""
        if len(frames) < 4 or frames[1] != b"":
            self._refuse(frames[0] if frames else None, "malformed",
                         f"malformed frame: {len(frames)} parts, expected identity, empty, header, command")
            return
        identity, header, command, rest = frames[0], frames[2], frames[3], frames[4:]
        try:
            if header == P.WORKER:
                self._worker_message(identity, command, rest, role, key)
            elif header == P.CLIENT:
                self._client_message(identity, command, rest, role)
            else:
                self._refuse(identity, "malformed", f"unknown protocol header {header[:16]!r}")
        except Exception as exc:  # any defect of one message (wrong shapes too) refuses it, never the broker
            tag = rest[0] if header == P.CLIENT and rest else b""
            self._refuse(identity, "malformed", f"malformed {header[:8]!r} {command[:16]!r} message: "
                                                f"{type(exc).__name__}: {str(exc)[:300]}", tag)

    def _send_worker(self, identity: bytes, command: bytes, *parts: bytes) -> None:
        self.router.send_multipart([identity, b"", P.WORKER, command, *parts])

    def _worker_message(self, identity: bytes, command: bytes, rest: list[bytes], role: str | None = None,
                        key: bytes | None = None) -> None:
        now = time.monotonic()
        worker = self.workers.get(identity)
        if command == P.READY:
            service = rest[0].decode(errors="replace") if rest else ""
            if not SERVICE_NAME.match(service):
                self._refuse(identity, "malformed", f"READY for {service[:40]!r}: not a service name")
                return
            if role is not None and not ({service, "*"} & ROLE_SERVES.get(role, frozenset())):
                self._refuse(identity, "role", f"a key of role {role or 'none'!r} may not serve {service!r}")
                self._send_worker(identity, P.DISCONNECT)
                return
            info = P.loads(rest[1]) if len(rest) > 1 else {}
            if not isinstance(info, dict):
                raise ValueError(f"READY info must be a map, got {type(info).__name__}")
            pid = info.get("pid", 0)
            if isinstance(pid, bool) or not isinstance(pid, int) or not 0 <= pid < 2 ** 31:
                raise ValueError(f"READY pid {str(pid)[:20]!r} is not a process id")
            busy = info.get("job")
            if busy is not None and not isinstance(busy, str):
                raise ValueError("READY job must be a job id")
            if worker is not None:  # a second READY is a protocol error (MDP): start afresh
                self._drop_worker(worker, "announced READY twice", count_failure=False)
            worker = Worker(identity, service, host=str(info.get("host", "?"))[:64], pid=pid,
                            expiry=now + self.interval * self.liveness, key=key)
            self.workers[identity] = worker
            job = self.jobs.get(busy) if busy else None
            if job is not None and (job.service != service or (job.state == "inflight" and job.worker in self.workers
                                                               and job.worker != identity)):
                # a claim on another service's job, or on a job a live worker holds: not this worker's.
                # It is still busy running it (e.g. declared dead while descheduled, the job given to
                # another since): no job is dispatched to it until it reports, and that report is
                # ignored (each job sent meanwhile would come back "busy" and burn an attempt)
                log.warning("worker %s:%d (%s) claimed job %s it cannot hold: its result will be ignored",
                            worker.host, worker.pid, service, busy[:64])
                job = None
            elif job is not None and job.key != key:
                # CURVE on: the job was last given to another key (or to none since the broker started),
                # so this is not the worker reconnecting mid-job it claims to be — a stage's key naming
                # another host's job (ids are derivable from the feed) must not complete it. Refused and
                # counted; the job keeps its state. The worker is still treated as busy with the job it
                # named (as above: a real worker that lost its job to another key, or that outlived a broker
                # restart, is still running it), and its result for it is ignored (not-holder). The ERR
                # tells the worker why (it logs it).
                # CURVE off: both keys are None, nothing to check the claim against (any worker of the
                # service may make it, as before).
                self._refuse(identity, "not-holder", f"worker {worker.host}:{worker.pid} ({service}) claimed job "
                                                 f"{busy[:64]!r} in READY, which was not last given to its key: "
                                                 "refused; its result will be ignored")
                job = None
            if busy:
                # a worker that reconnected mid-job is busy with it: its RESULT/FAIL for that job is
                # expected (even if the job was parked or completed meanwhile), nothing is dispatched
                worker.job = str(busy)
            if job is not None and job.state != "parked":  # ... and keeps a job still to be done
                job.state, job.worker, job.key = "inflight", identity, key
            elif not busy:
                self.waiting[worker.service].append(worker)
                self._dirty.add(worker.service)
            log.info("worker %s:%d ready for %s", worker.host, worker.pid, worker.service)
            return
        if worker is None:
            # not a registered worker: nothing it says touches a job (a peer that never said READY
            # cannot complete a job, issue 19). A real worker after a broker restart is told to
            # reconnect; its job was re-queued from the journal and runs again (outputs are
            # content-keyed, announcements de-duplicated).
            if command in (P.RESULT, P.FAIL, P.PROGRESS):
                self._refuse(None, "not-worker", f"{command.decode(errors='replace')} from a peer that is not a "
                                                 "registered worker: ignored")
            if command != P.DISCONNECT:
                self._send_worker(identity, P.DISCONNECT)
            return
        worker.expiry = now + self.interval * self.liveness
        if command == P.HEARTBEAT:
            return
        if command in (P.PROGRESS, P.RESULT, P.FAIL):
            jid = rest[0].decode(errors="replace")
            if jid != worker.job:
                # not the job this worker holds (a confused or hostile peer, or a duplicate): it must
                # neither touch that job nor make the worker look idle (it would get two jobs)
                self._refuse(None, "not-holder", f"worker {worker.host}:{worker.pid} ({worker.service}) sent "
                                                 f"{command.decode(errors='replace')} for job {jid[:64]!r} but holds "
                                                 f"{worker.job!r}: ignored")
                return
        if command == P.PROGRESS:
            job = self.jobs.get(jid)
            if job is not None and job.state == "inflight" and job.worker == identity:
                p = P.loads(rest[1])
                job.progress = (float(p.get("fraction", 0.0)), str(p.get("text", "")))
            return
        if command == P.RESULT:
            job = self.jobs.get(jid)
            if job is None or job.worker == identity or (job.state == "parked" and job.service == worker.service
                                                         and job.key == worker.key):
                self._complete(jid, rest[1], role=role)
            else:  # a job this worker claimed at READY but another worker (or key) holds, or another service's
                self._refuse(None, "not-holder", f"result of job {jid[:64]!r} from worker {worker.host}:{worker.pid} "
                                                 f"({worker.service}) which does not hold it: ignored")
            self._worker_idle(worker)
        elif command == P.FAIL:
            kind, error = rest[1], rest[2][:MAX_ERROR_CHARS].decode(errors="replace")
            job = self.jobs.get(jid)
            if job is not None and job.state == "inflight" and job.worker == identity:
                self._job_failed(job, error, rejected=(kind == P.FAIL_REJECTED), host=f"{worker.host}:{worker.pid}")
            elif job is not None and not (job.state == "parked" and job.service == worker.service
                                          and job.key == worker.key):
                # as for a result: a report on a job another worker (or key) holds changes nothing, and is counted
                self._refuse(None, "not-holder", f"failure of job {jid[:64]!r} from worker {worker.host}:{worker.pid} "
                                                 f"({worker.service}) which does not hold it: ignored")
            self._worker_idle(worker)
        elif command == P.DISCONNECT:
            handed_back = rest[0].decode() if rest and rest[0] else None
            self._drop_worker(worker, "disconnected", count_failure=False)
            if handed_back:
                log.info("worker %s:%d handed back job %s", worker.host, worker.pid, handed_back)
        else:
            self._refuse(identity, "malformed", f"unknown worker command {command[:16]!r}")

    def _worker_idle(self, worker: Worker) -> None:
        worker.job = None
        self.waiting[worker.service].append(worker)
        self._dirty.add(worker.service)

    def _dismiss(self, worker: Worker) -> None:
        """Tell an idle worker whose key may no longer serve its service to go (it reconnects and is refused)."""
        self._send_worker(worker.identity, P.DISCONNECT)
        self._drop_worker(worker, "dismissed: its key's role no longer allows this service", count_failure=False)

    def _drop_worker(self, worker: Worker, reason: str, *, count_failure: bool) -> None:
        self.workers.pop(worker.identity, None)
        try:
            self.waiting[worker.service].remove(worker)
        except ValueError:
            pass
        job = self.jobs.get(worker.job) if worker.job else None
        if job is not None and job.state == "inflight" and job.worker == worker.identity:
            if count_failure:
                self._job_failed(job, f"worker {worker.host}:{worker.pid} {reason}", host=f"{worker.host}:{worker.pid}")
            else:
                job.state, job.worker = "queued", None
                self.queues[job.service].appendleft(job.id)
                self._dirty.add(job.service)
        log.info("worker %s:%d (%s) %s", worker.host, worker.pid, worker.service, reason)

    def _complete(self, jid: str, payload: bytes, role: str | None = None) -> None:
        job = self.jobs.pop(jid, None)
        if job is None:
            log.debug("duplicate or unknown result for %s ignored", jid)
            return
        self._ops.append(("done", jid))
        self._completed += 1
        sec = int(time.time())
        if self._rate and self._rate[-1][0] == sec:
            self._rate[-1][1] += 1
        else:
            self._rate.append([sec, 1])
            while self._rate and self._rate[0][0] < sec - 60:
                self._rate.popleft()
        try:
            events = P.loads(payload)
            if not isinstance(events, list):
                raise messages.MessageError(f"result must be a list of events, got {type(events).__name__}")
        except Exception as exc:
            self._reject(f"undecodable result of job {jid}: {exc}", job=jid, service=job.service)
            return
        invalid, first_error = 0, ""
        if len(events) > MAX_RESULT_EVENTS:   # counted as refused, not silently cut
            invalid = len(events) - MAX_RESULT_EVENTS
            first_error = f"{len(events)} events in one result (at most {MAX_RESULT_EVENTS}); the rest refused"
        # None (anything): CURVE off, or an admin key. Any other role announces only its stage's events: none for a
        # role without a stage, or a key revoked or re-roled while its worker held the job (role "" or another)
        announces = None if role is None or role == "admin" else ROLE_ANNOUNCES.get(role, frozenset())
        for ev in events[:MAX_RESULT_EVENTS]:
            try:
                ev = messages.validate(ev)
                messages.check_packed_size(ev)   # the limit of every message, as for a SUBMIT (messages.unpack)
                if announces is not None and ev["type"] not in announces:
                    raise messages.MessageError(f"a key of role {role!r} may not announce {ev['type']}")
            except messages.MessageError as exc:
                invalid += 1
                first_error = first_error or str(exc)
                continue
            if ev["uid"] in self._uids:
                continue
            key = output_key(ev)
            if key in self._outputs:  # the same output announced before (a re-run of the same inputs)
                self.duplicates_dropped += 1
                log.info("job %s: %s for %s already announced; not again", jid, ev["type"], ev.get("fragment", "-"))
                continue
            seq = self.accept_event(ev)
            self._outputs.add(key)
            self._ops.append(("output", key, seq))
        if invalid:  # one input.rejected per job (docs/messages.md), however many events were invalid
            ctx = {k: job.event[k] for k in ("fragment", "face") if k in job.event}
            self._reject(f"job {jid} returned {invalid} invalid event(s); the first: {first_error}", job=jid,
                         service=job.service, input=job.event.get("uid"), **ctx)

    def _job_failed(self, job: Job, error: str, *, rejected: bool = False, host: str = "") -> None:
        job.failures += 1
        job.error = error
        job.worker = None
        ev = job.event
        ctx = {k: ev[k] for k in ("fragment", "face") if k in ev}
        if rejected or job.failures >= self.max_attempts:
            job.state = "parked"
            self._ops.append(("park", job.id, job.failures, error))
            kind = "input.rejected" if rejected else "stage.failed"
            log.warning("job %s parked after %d attempt(s): %s", job.id, job.failures, error)
            self.accept_event(messages.new_message(kind, service=job.service, error=error, job=job.id,
                                                   attempts=job.failures, input=ev.get("uid"), worker=host, **ctx))
        else:
            job.state = "queued"
            self._ops.append(("fail", job.id, job.failures, error))
            self.queues[job.service].append(job.id)
            self._dirty.add(job.service)
            log.info("job %s failed attempt %d, re-queued: %s", job.id, job.failures, error)

    def _dispatch_dirty(self) -> None:
        for service in self._dirty:
            queue, idle = self.queues.get(service), self.waiting.get(service)
            while queue and idle:
                job = self.jobs.get(queue.popleft())
                if job is None or job.state != "queued":
                    continue
                worker = idle.popleft()
                if not self._may_still_serve(worker):   # revoked or re-roled since READY: no further job
                    queue.appendleft(job.id)
                    self._dismiss(worker)
                    continue
                job.state, job.worker, job.started, job.progress = "inflight", worker.identity, time.time(), None
                job.key = worker.key   # who may reclaim it in READY (a worker of this key reconnecting mid-job)
                worker.job = job.id
                self._send_worker(worker.identity, P.JOB, job.id.encode(), str(job.failures + 1).encode(), job.body)
        self._dirty.clear()

    def _heartbeat(self) -> None:
        now = time.monotonic()
        for worker in list(self.workers.values()):
            if worker.expiry < now:
                self._drop_worker(worker, "stopped responding (heartbeat lost)", count_failure=True)
            elif worker.job is None and not self._may_still_serve(worker):   # idle, its key revoked or re-roled
                self._dismiss(worker)
            else:
                self._send_worker(worker.identity, P.HEARTBEAT)
        # every interval, whatever else flows: a subscriber of some types only still hears the position
        self.feed.send_multipart([P.FEED_HEARTBEAT, self.stream, str(self.published_seq).encode(), b""])
        self._last_feed = now
        self._refusal_summary(now)

    # -- clients ---------------------------------------------------------------------------
    def _client_message(self, identity: bytes, command: bytes, rest: list[bytes], role: str | None = None) -> None:
        tag, body = (rest + [b"", b""])[:2]

        def reply(status: bytes, obj) -> tuple:
            return ("reply", identity, status, tag, P.dumps(obj))

        def request_map() -> dict:
            req = P.loads(body) if body else {}
            if not isinstance(req, dict):
                raise ValueError(f"{command.decode(errors='replace')} body must be a map, got {type(req).__name__}")
            return req

        def number(req: dict, key: str, default: int) -> int:
            value = req.get(key, default)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2 ** 63:
                raise ValueError(f"{command.decode(errors='replace')} {key} must be a non-negative integer")
            return value

        if command == P.SUBMIT:
            if not self._journal_ok:
                self._refuse(identity, "journal", "broker journal cannot write (disk full?); see the broker log; "
                                                  "submissions resume when it can", tag, retry=True)
                return
            try:
                event = messages.unpack(body)
            except messages.MessageError as exc:
                self._refuse(identity, "invalid", f"submitted message refused: {exc}", tag)
                return
            if role is not None and event["type"] not in ROLE_SUBMITS.get(role, frozenset()):
                self._refuse(identity, "role", f"a key of role {role or 'none'!r} may not submit {event['type']}", tag)
                return
            seq = self._uids.get(event["uid"])
            if seq is None:
                seq = self.accept_event(event, body)
            self._after.append(reply(P.OK, {"seq": seq}))
        elif command == P.STATUS:
            self._run_actions([reply(P.OK, self.status())])
        elif command == P.SINCE:
            req = request_map()
            after = number(req, "after", 0)
            limit = max(1, min(number(req, "limit", 1000), 10000))
            types = req.get("types")
            if types is not None and not (isinstance(types, list) and len(types) <= 64
                                          and all(isinstance(t, str) and len(t) <= 64 for t in types)):
                raise ValueError("SINCE types must be a list of event type names")
            upto = self.published_seq
            events = self.journal.events_since(after, limit, upto, types or None)
            # with a type filter the reply says how far it looked, so the caller moves past the rest
            scanned = events[-1][0] if len(events) >= limit else max(upto, after)
            first = self.journal.first_seq()
            self._run_actions([reply(P.OK, {"stream": self.stream.decode(), "last_seq": upto, "scanned_to": scanned,
                                             "first_seq": first, "events": [[s, b] for s, b in events]})])
        elif command == P.PENDING:
            pending = [[j.service, j.state, j.event.get("type"), j.event.get("fragment"), j.event.get("face")]
                       for j in self.jobs.values() if j.state in ("queued", "inflight")]
            self._run_actions([reply(P.OK, {"pending": pending})])
        elif command == P.RERUN:
            if role is not None and role not in ROLE_RERUNS:
                self._refuse(identity, "role", f"a key of role {role or 'none'!r} may not re-run jobs", tag)
                return
            req = request_map()
            which = req.get("job")
            if not isinstance(which, str) or not which:
                self._refuse(identity, "invalid", "RERUN needs {job: <job id> | \"all\"}", tag)
                return
            rerun = []
            for job in self.jobs.values():
                if job.state == "parked" and (which == "all" or job.id == which):
                    job.state, job.failures, job.error = "queued", 0, ""
                    self._ops.append(("requeue", job.id))
                    self.queues[job.service].append(job.id)
                    self._dirty.add(job.service)
                    rerun.append(job.id)
            self._after.append(reply(P.OK, {"rerun": rerun}))
        else:
            self._refuse(identity, "malformed", f"unknown client command {command[:16]!r}", tag)

    def status(self) -> dict:
        """Queues, workers per host, jobs in flight, parked failures, throughput."""
        now = time.time()
        services = sorted(set(self.queues) | {w.service for w in self.workers.values()} |
                          {s for v in self.routing.values() for s in v})
        queued: collections.Counter = collections.Counter()
        inflight, parked = [], []
        for j in self.jobs.values():  # one pass: status is polled while thousands of jobs wait
            if j.state == "queued":
                queued[j.service] += 1
            elif j.state == "inflight":
                w = self.workers.get(j.worker)
                inflight.append({"job": j.id, "service": j.service, "fragment": j.event.get("fragment"),
                                 "worker": f"{w.host}:{w.pid}" if w else "?", "running_s": round(now - j.started, 2),
                                 "attempt": j.failures + 1, "progress": j.progress})
            else:
                parked.append({"job": j.id, "service": j.service, "fragment": j.event.get("fragment"),
                               "face": j.event.get("face"), "attempts": j.failures, "error": j.error})
        hosts: dict = collections.defaultdict(list)
        for w in self.workers.values():
            hosts[w.host].append({"service": w.service, "pid": w.pid, "job": w.job,
                                  "up_s": round(now - w.since, 1)})
        sec = int(now)
        recent = sum(c for s, c in self._rate if sec - 60 <= s < sec)
        span = min(60.0, max(1.0, now - self._started))
        return {
            "stream": self.stream.decode(), "last_seq": self.published_seq, "uptime_s": round(now - self._started, 1),
            "pid": os.getpid(), "host": _socket.gethostname(),
            "queues": {s: queued.get(s, 0) for s in services},
            "workers": {h: v for h, v in sorted(hosts.items())},
            "in_flight": inflight, "parked": parked,
            "completed": self._completed, "jobs_per_s": round(recent / span, 2),
            "journal_bytes": self.journal.size_bytes(), "routing": self.routing,
            "journal_ok": self._journal_ok, "refused": dict(self.refused),
            "duplicates_dropped": self.duplicates_dropped,
            "loop": self.clock.summary() if self.clock is not None else None,
            "nice": os.getpriority(os.PRIO_PROCESS, 0),
        }
