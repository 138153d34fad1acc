"""Worker runtime: runs one stage module's ``handle(job, ctx)`` for the broker.

After the ZeroMQ Guide's ``mdwrkapi.py`` / ``ppworker.py``: a DEALER socket announces READY for
its service, heartbeats both ways (interval and liveness from ``[broker]``), reconnects with
exponential back-off when the broker goes quiet or says DISCONNECT, and holds one job at a time.
The job runs in a separate thread so heartbeats continue while a long stage computes. An exception
in a job, or a result over the message limits, is reported (FAIL; the broker counts attempts) and
the process stays up; a job whose input is bad (:class:`~common.messages.MessageError`,
:class:`~common.store.ArtifactError`) is reported as rejected, which the broker parks at once with
an ``input.rejected`` event. On SIGTERM the worker finishes its job within
``worker.shutdown_grace_s`` or hands it back, then says DISCONNECT. Nothing important lives only
in the worker's memory: kill -9 loses at most the job in flight, which the broker re-queues.

A stage module ``services/<name>.py`` exposes ``SERVICE``, ``VERSION`` and
``handle(job: dict, ctx: StageContext) -> list[dict]`` (the events to publish).
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import logging
import os
import queue
import signal
import socket as _socket
import sqlite3
import threading
import time
import traceback
import uuid
from dataclasses import dataclass, field
from typing import Callable, Mapping

import zmq

from common import messages
from common.bus import protocol as P
from common.bus.broker import MAX_FRAME_BYTES, MAX_RESULT_EVENTS
from common.bus.security import secure_client_socket
from common.config import broker_endpoint, service_config
from common.store import ArtifactError, ArtifactMissing, StorageError, StorageUnavailable, Store

log = logging.getLogger("tessera.worker")

# errors that mean "this input is bad": retrying will not help, so the broker parks at once
REJECTED_ERRORS: tuple[type[BaseException], ...] = (messages.MessageError, ArtifactError)
# errors that mean "the storage refuses writes right now" (full, read-only, unmounted): the job is
# retried in this worker with back-off (heartbeats go on) instead of burning the broker's attempts
STORAGE_ERRORS: tuple[type[BaseException], ...] = (StorageError, StorageUnavailable)
_STORAGE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS}
# SQLite's words for the same (a stage's database on the storage, e.g. the matcher's proposal store)
_SQLITE_STORAGE = ("disk is full", "readonly database", "read-only", "disk i/o error", "database is locked")


def storage_refused(exc: BaseException) -> bool:
    """True if ``exc`` means the storage refuses writes right now (full, read-only, unmounted, busy),
    whichever layer raised it: the store, the OS, or SQLite."""
    if isinstance(exc, STORAGE_ERRORS):
        return True
    if isinstance(exc, OSError) and exc.errno in _STORAGE_ERRNOS:
        return True
    if isinstance(exc, sqlite3.OperationalError):
        text = str(exc).lower()
        return any(w in text for w in _SQLITE_STORAGE)
    return False


@dataclass
class StageContext:
    """What a stage's ``handle(job, ctx)`` gets besides the job.

    Attributes
    ----------
    store : Store
        The artifact store (storage root from ``[storage]``).
    config : dict
        This service's ``[services.<name>]`` section (may be empty: use defaults).
    log : logging.Logger
        Logger named ``tessera.<service>``.
    progress : callable(fraction, text)
        Report progress in [0, 1]; shown by ``tessera status``. Cheap; call it as often as useful.
    service, job_id, attempt
        Which stage, which job, which attempt (1 = first).
    stopping : threading.Event
        Set when the worker was asked to stop; a long job may finish early by raising.
    """

    store: Store
    config: dict
    log: logging.Logger
    progress: Callable[[float, str], None]
    service: str = ""
    job_id: str = ""
    attempt: int = 1
    stopping: threading.Event = field(default_factory=threading.Event)


def _result_frame(events) -> bytes:
    """The RESULT frame of a stage's events, held to the limits the broker holds a result to.

    Each event is a valid message of at most :data:`~common.messages.MAX_MESSAGE_BYTES`, at most
    ``MAX_RESULT_EVENTS`` of them, and the frame within ``MAX_FRAME_BYTES`` (ZeroMQ drops a larger
    one: the job would hang in flight). Raises :class:`~common.messages.MessageError` naming the
    first limit broken.
    """
    events = list(events)
    if len(events) > MAX_RESULT_EVENTS:
        raise messages.MessageError(f"{len(events)} events in one result (at most {MAX_RESULT_EVENTS})")
    checked = []
    for ev in events:
        ev = messages.validate(ev)
        messages.check_packed_size(ev)
        checked.append(ev)
    frame = P.dumps(checked)
    if len(frame) > MAX_FRAME_BYTES:
        raise messages.MessageError(f"result of {len(frame)} bytes (at most {MAX_FRAME_BYTES} a frame)")
    return frame


def load_stage(name: str):
    """Import ``services.<name>`` and check it is a stage module (SERVICE, VERSION, handle)."""
    try:
        module = importlib.import_module(f"services.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"services.{name}":
            raise ValueError(f"service {name!r}: no module services/{name}.py in this build") from exc
        raise
    for attr in ("SERVICE", "VERSION", "handle"):
        if not hasattr(module, attr):
            raise ValueError(f"service {name!r}: services/{name}.py lacks {attr} (not a stage module)")
    return module


class _JobRunner(threading.Thread):
    """Runs jobs one at a time in its own thread; outcomes and progress go to :attr:`outcomes`."""

    def __init__(self, handle, make_context, *, retry=(1.0, 30.0, 600.0), stop: threading.Event | None = None):
        super().__init__(name="job-runner", daemon=True)
        self.handle, self.make_context = handle, make_context
        self.retry_min, self.retry_max, self.retry_budget = (float(x) for x in retry)
        self.stop = stop or threading.Event()
        self.jobs: queue.Queue = queue.Queue()
        self.outcomes: queue.Queue = queue.Queue()

    def run(self) -> None:
        while True:
            item = self.jobs.get()
            if item is None:
                break
            jid, attempt, event = item

            last = [0.0]

            def progress(fraction: float, text: str = "", _jid=jid, _last=last) -> None:
                now = time.monotonic()
                if now - _last[0] >= 0.2 or fraction >= 1.0:  # a stage may call this per row: send 5/s at most
                    _last[0] = now
                    self.outcomes.put(("progress", _jid, float(fraction), str(text)))

            try:
                stage_ctx = self.make_context(jid, attempt, progress)
                result = self._handle_retrying_storage(jid, event, stage_ctx, progress)
                try:
                    payload = _result_frame(result)
                except Exception as exc:  # the stage's fault, not its input's: an ordinary failure
                    raise RuntimeError(f"stage returned an invalid event: {exc}") from None
                self.outcomes.put(("result", jid, payload))
            except ArtifactMissing as exc:  # maybe not visible yet on a network share: an ordinary, retried failure
                log.warning("job %s: %s", jid, exc)
                self.outcomes.put(("fail", jid, P.FAIL_ERROR, f"{type(exc).__name__}: {exc}"))
            except REJECTED_ERRORS as exc:
                log.warning("job %s rejected: %s", jid, exc)
                self.outcomes.put(("fail", jid, P.FAIL_REJECTED, f"{type(exc).__name__}: {exc}"))
            except BaseException as exc:  # one bad job (even one calling sys.exit) must never take the worker down
                tb = traceback.extract_tb(exc.__traceback__)[-3:]
                where = "; ".join(f"{os.path.basename(f.filename)}:{f.lineno} in {f.name}" for f in tb)
                log.exception("job %s failed", jid)
                self.outcomes.put(("fail", jid, P.FAIL_ERROR, f"{type(exc).__name__}: {exc} (at {where})"))


    def _handle_retrying_storage(self, jid: str, event: dict, stage_ctx, progress) -> list:
        """Run the stage; while the storage refuses writes, wait (doubling) and run it again.

        Stage outputs are content-keyed, so re-running after a refused write redoes only what is
        missing. After ``retry_budget`` seconds (or when the worker stops) the storage error is
        raised: the broker counts one failed attempt.
        """
        wait, started = self.retry_min, time.monotonic()
        while True:
            try:
                return self.handle(event, stage_ctx) or []
            except Exception as exc:
                if not storage_refused(exc):
                    raise
                spent = time.monotonic() - started
                if spent + wait > self.retry_budget or self.stop.is_set():
                    raise
                log.warning("job %s: %s; retrying in %.1f s (%.0f of %.0f s spent)", jid, exc, wait, spent,
                            self.retry_budget)
                progress(0.0, f"storage refuses writes ({type(exc).__name__}); retrying in {wait:.0f} s")
                if self.stop.wait(wait):
                    raise
                wait = min(wait * 2, self.retry_max)


def run_worker(service_module_name: str, config: Mapping, *, stop: threading.Event | None = None,
               context: zmq.Context | None = None, install_signals: bool = True) -> int:
    """Serve one stage for the broker until stopped.

    Parameters
    ----------
    service_module_name : str
        Stage module under ``services/`` (``solver``, ``features``, ``noop``, ...).
    config : dict
        Loaded configuration (:func:`common.config.load_config`).
    stop : threading.Event, optional
        Set it to stop the worker (SIGTERM/SIGINT set it too when ``install_signals``).
    context : zmq.Context, optional
    install_signals : bool
        Install SIGTERM/SIGINT handlers (only possible in the main thread).

    Returns
    -------
    int
        Exit status: 0 after a clean stop.
    """
    module = load_stage(service_module_name)
    service = str(module.SERVICE)
    stop = stop or threading.Event()
    if install_signals and threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    b, w = config["broker"], config["worker"]
    interval, liveness_max = float(b["heartbeat_interval_s"]), int(b["heartbeat_liveness"])
    store = Store.from_config(config)
    stage_log = logging.getLogger(f"tessera.{service}")
    with contextlib.suppress(OSError):  # storage may be away at start; the jobs will say so
        for rel in store.sweep_temporary():
            stage_log.warning("removed %s: left by a writer that died mid-write", rel)
    settings = service_config(config, service_module_name)
    ctx = context or zmq.Context.instance()
    endpoint = broker_endpoint(config)
    info = {"host": _socket.gethostname(), "pid": os.getpid(), "version": str(module.VERSION)}

    def make_context(jid, attempt, progress):
        return StageContext(store=store, config=settings, log=stage_log, progress=progress,
                            service=service, job_id=jid, attempt=attempt, stopping=stop)

    runner = _JobRunner(module.handle, make_context, stop=stop,
                        retry=(w["storage_retry_min_s"], w["storage_retry_max_s"], w["storage_retry_budget_s"]))
    runner.start()

    sock = None
    current: str | None = None       # job in flight
    stop_seen_at: float | None = None
    backoff = float(w["reconnect_min_s"])

    def connect():
        nonlocal sock
        if sock is not None:
            sock.close(linger=0)
        sock = secure_client_socket(ctx.socket(zmq.DEALER), config)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.ROUTING_ID, f"{service}-{info['pid']}-{uuid.uuid4().hex[:8]}".encode())
        sock.connect(endpoint)
        ready = dict(info, job=current) if current else info
        sock.send_multipart([b"", P.WORKER, P.READY, service.encode(), P.dumps(ready)])
        log.info("worker %s connected to %s%s", service, endpoint, f" (still running {current})" if current else "")

    connect()
    last_heard = time.monotonic()
    next_heartbeat = time.monotonic() + interval

    def reconnect() -> None:
        """Connect again after the back-off, which doubles up to ``reconnect_max_s`` until the broker
        sends a job or a heartbeat: a broker that is away, or refuses this worker, is not hammered."""
        nonlocal backoff, last_heard
        if not stop.wait(backoff):
            backoff = min(backoff * 2, float(w["reconnect_max_s"]))
            connect()
        last_heard = time.monotonic()

    def from_broker(frames: list[bytes]) -> None:
        nonlocal current, last_heard, backoff
        last_heard = time.monotonic()
        if len(frames) >= 5 and frames[1:3] == [P.CLIENT, P.ERR]:   # the broker refused a frame of ours (docs/messages.md)
            try:
                why = P.loads(frames[4]).get("error")
            except Exception:   # an unreadable body: still a refusal, said as such
                why = None
            log.warning("broker refused %s's frame: %s", service, str(why)[:500] if why else "(no reason given)")
            return
        if len(frames) < 3 or frames[1] != P.WORKER:
            log.warning("malformed frame from broker ignored: %d parts", len(frames))
            return
        command = frames[2]
        if command in (P.JOB, P.HEARTBEAT):  # the broker took this worker: the next reconnection is quick
            backoff = float(w["reconnect_min_s"])
        if command == P.JOB:
            try:
                jid, attempt, body = frames[3].decode(), int(frames[4]), frames[5]
            except (IndexError, ValueError) as exc:  # a malformed frame must never end the worker
                log.warning("malformed JOB frame from broker ignored (%d parts): %s", len(frames), exc)
                return
            if current is not None:  # the broker thinks we are idle: tell it this job cannot run here
                sock.send_multipart([b"", P.WORKER, P.FAIL, jid.encode(), P.FAIL_ERROR,
                                     f"worker busy with {current}".encode()])
                return
            try:
                # a job is a journalled event: an old one may hold a verdict word the door no longer takes
                event = messages.unpack(body, legacy_verdicts=True)
            except messages.MessageError as exc:
                sock.send_multipart([b"", P.WORKER, P.FAIL, jid.encode(), P.FAIL_REJECTED,
                                     f"MessageError: {exc}".encode()])
                return
            current = jid
            runner.jobs.put((jid, attempt, event))
        elif command == P.DISCONNECT:
            log.info("broker asked %s to reconnect; reconnecting in %.2f s", service, backoff)
            reconnect()
        # HEARTBEAT: only a sign of life

    try:
        while True:
            if stop.is_set():
                if stop_seen_at is None:
                    stop_seen_at = time.monotonic()
                    log.info("worker %s stopping%s", service, f"; finishing {current}" if current else "")
                if current is None:
                    sock.send_multipart([b"", P.WORKER, P.DISCONNECT, b""])
                    break
                if time.monotonic() - stop_seen_at > float(w["shutdown_grace_s"]):
                    log.warning("worker %s: job %s not finished in time; handing it back", service, current)
                    sock.send_multipart([b"", P.WORKER, P.DISCONNECT, current.encode()])
                    break
            timeout = max(0.0, min(next_heartbeat - time.monotonic(), 0.2))
            if current is not None:
                # busy: wait for the job's outcome (a queue wake-up is immediate), then read the broker
                try:
                    item = runner.outcomes.get(timeout=timeout)
                except queue.Empty:
                    item = None
                while item is not None:
                    kind, jid = item[0], item[1]
                    if kind == "progress":
                        sock.send_multipart([b"", P.WORKER, P.PROGRESS, jid.encode(),
                                             P.dumps({"fraction": item[2], "text": item[3]})])
                    else:
                        if kind == "result":
                            sock.send_multipart([b"", P.WORKER, P.RESULT, jid.encode(), item[2]])
                        else:
                            sock.send_multipart([b"", P.WORKER, P.FAIL, jid.encode(), item[2], item[3].encode()])
                        if jid == current:
                            current = None
                    try:
                        item = runner.outcomes.get_nowait()
                    except queue.Empty:
                        item = None
                while sock.poll(0):
                    from_broker(sock.recv_multipart())
            elif sock.poll(timeout * 1000):
                while True:
                    from_broker(sock.recv_multipart())
                    if current is not None or not sock.poll(0):
                        break
            if time.monotonic() >= next_heartbeat:
                if time.monotonic() - last_heard > interval * liveness_max:
                    log.warning("broker silent for %.1f s; reconnecting in %.2f s", interval * liveness_max, backoff)
                    reconnect()
                else:
                    sock.send_multipart([b"", P.WORKER, P.HEARTBEAT])
                next_heartbeat = time.monotonic() + interval
    finally:
        runner.jobs.put(None)
        if sock is not None:
            sock.close(linger=200)
    log.info("worker %s stopped", service)
    return 0
