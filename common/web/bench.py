"""The operator's capture session at the bench, between the web page and the capture workflow.

One process owns the scanner. The bench page asks this session to pre-scan or to capture a
fragment; the capture workflow (:func:`common.acquisition.capture.capture_fragment`) runs in a
background thread and calls the operator back before every scan with a ``CaptureStep``
(“Turn the fragment 90° clockwise”). The session publishes that instruction as its state and
waits until the operator presses *Done* on the page (:meth:`BenchSession.proceed`), so the page
only ever polls :meth:`BenchSession.state` and sends the operator's clicks. Errors become the
plain-language text of ``CaptureError.operator_message``.

The session is plumbing without sockets: the capture, delivery (store + outbox) and pre-scan
functions are passed in, so it is tested with any callables.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from common.messages import FRAGMENT_PATTERN


#: phases of a session, in the order a capture goes through them
PHASES = ("idle", "prescanning", "waiting", "scanning", "saving", "done", "error", "cancelled")

# scanner status names (SANE and the simulated flatbed) -> what the operator reads
_SCANNER_STATUS_TEXT = {
    "SANE_STATUS_DEVICE_BUSY": "The scanner is busy. Wait a moment, then press Scan again.",
    "SANE_STATUS_JAMMED": "The scanner reports a jam. Open the lid, check nothing blocks the glass, then press Scan again.",
    "SANE_STATUS_COVER_OPEN": "The scanner lid is open. Close it, then press Scan again.",
    "SANE_STATUS_IO_ERROR": "The scanner stopped answering. Check its cable and power, then press Scan again.",
    "SANE_STATUS_NO_DOCS": "The scanner sees nothing to scan. Place the fragment on the glass.",
}


class BenchBusy(RuntimeError):
    """The scanner is already in use by a pre-scan or a capture."""


def check_fragment_id(fragment_id: str) -> str:
    """Return ``fragment_id`` stripped, or raise ValueError if it cannot name a fragment.

    IDs become directory names on storage, so only letters, digits, ``.``, ``_`` and ``-`` (1–64
    characters, not starting with punctuation) are accepted.
    """
    fid = str(fragment_id or "").strip()
    if not FRAGMENT_PATTERN.match(fid):
        raise ValueError(f"fragment_id {fragment_id!r} is not valid: use 1-64 letters, digits, '.', '_' or '-', "
                         "starting with a letter or digit")
    return fid


def describe_error(exc: BaseException) -> dict:
    """What the bench page shows for an exception: ``{kind, message, detail}``.

    ``kind`` is ``no_fragment``, ``multiple_fragments``, ``scanner`` or ``internal``; ``message``
    is plain language for the operator (the error's ``operator_message`` where it has one);
    ``detail`` is the technical text for whoever fixes it.
    """
    names = [c.__name__ for c in type(exc).__mro__]
    operator_message = getattr(exc, "operator_message", None)
    if "NoFragmentError" in names:
        kind = "no_fragment"
    elif "MultipleFragmentsError" in names:
        kind = "multiple_fragments"
    elif "ScannerError" in names:
        kind = "scanner"
        status = getattr(exc, "status", "unknown")
        if not operator_message or operator_message == str(exc):  # only the technical text was given
            operator_message = _SCANNER_STATUS_TEXT.get(status, operator_message)
    elif "CaptureError" in names:
        kind = "capture"
    else:
        kind = "internal"
        operator_message = ("Something went wrong that the operator cannot fix. The scans taken so far are "
                            "kept. Tell the station's technician; the details are below.")
    return {"kind": kind, "message": operator_message or str(exc), "detail": f"{type(exc).__name__}: {exc}"}


@dataclass
class _Record:
    fragment: str
    started: float
    finished: float | None = None
    outcome: str = "capturing"      # capturing, sent, kept (lab unreachable), failed, cancelled
    note: str = ""


@dataclass
class _State:
    phase: str = "idle"
    fragment: str | None = None
    step: dict | None = None
    scans_done: int = 0
    scans_total: int = 0
    message: str = ""
    error: dict | None = None
    delivery: dict | None = None
    seq: int = 0
    history: list = field(default_factory=list)


class BenchSession:
    """Run pre-scans and captures for the bench page, one at a time.

    Parameters
    ----------
    capture : callable(fragment_id, operator) -> result
        Runs the whole capture, calling ``operator(step)`` before each scan (the contract of
        ``capture_fragment``); raises ``CaptureError`` subclasses on failure.
    deliver : callable(fragment_id, result) -> dict
        Writes the scans and sends ``fragment.ready``; returns at least ``{"sent": bool}``
        (False: the lab is unreachable, the scans are spooled and sent later) and may add
        ``"artifact"`` and ``"message"``.
    prescan : callable(fragment_id) -> dict, optional
        Low-dpi scan of the glass with the detected fragment outlined: ``{"png": bytes,
        "message": str}``; raises ``CaptureError`` when there is no (or more than one) fragment.
    act : callable(step), optional
        Performs a step physically — the simulated operator of the simulated flatbed. Called
        after the operator presses *Done* and before the scan.
    empty_glass : callable() -> str, optional
        Scans the empty glass as the background that pre-scans are compared with (§3.3.4: an
        empty-bed pre-scan finds fragments larger than the estimated background's window);
        returns a message for the operator.
    log : logging.Logger, optional
    """

    def __init__(self, *, capture: Callable, deliver: Callable, prescan: Callable | None = None,
                 act: Callable | None = None, empty_glass: Callable | None = None,
                 log: logging.Logger | None = None):
        self._capture, self._deliver, self._prescan, self._act = capture, deliver, prescan, act
        self._empty_glass = empty_glass
        self.log = log or logging.getLogger("tessera.web.bench")
        self._scanner = threading.Lock()      # held for the whole of a pre-scan or a capture
        self._cond = threading.Condition()   # guards _state and the operator hand-shake
        self._state = _State()
        # names this session in every state: ``seq`` starts again when the station restarts, so the page
        # orders the answers it gets by (session, seq) and draws none older than the one it shows
        self._session = secrets.token_hex(8)
        self._released: int | None = None    # step index the operator has confirmed
        self._cancel = False
        self._thread: threading.Thread | None = None
        self._prescan_png: bytes | None = None

    # -- what the page reads ----------------------------------------------------------------
    def state(self) -> dict:
        """A JSON-able snapshot: phase, fragment, current step, counts, message, error, history, and
        ``session`` and ``seq``, which order the snapshots (``seq`` grows with every change in a session)."""
        with self._cond:
            s = self._state
            return {"phase": s.phase, "fragment": s.fragment, "step": dict(s.step) if s.step else None,
                    "scans_done": s.scans_done, "scans_total": s.scans_total, "message": s.message,
                    "error": dict(s.error) if s.error else None,
                    "delivery": dict(s.delivery) if s.delivery else None, "seq": s.seq, "session": self._session,
                    "busy": self._scanner.locked(),
                    "history": [vars(r).copy() for r in s.history]}

    def prescan_png(self) -> bytes | None:
        """PNG of the last pre-scan with the detected fragment outlined (None before one)."""
        with self._cond:
            return self._prescan_png

    def wait_for_change(self, seq: int, timeout_s: float) -> dict:
        """Block until the state's ``seq`` differs from ``seq`` (or ``timeout_s``); return the state."""
        with self._cond:
            self._cond.wait_for(lambda: self._state.seq != seq, timeout=timeout_s)
        return self.state()

    def _update(self, **changes: Any) -> None:
        with self._cond:
            for k, v in changes.items():
                setattr(self._state, k, v)
            self._state.seq += 1
            self._cond.notify_all()

    # -- what the page asks -----------------------------------------------------------------
    def prescan(self, fragment_id: str) -> dict:
        """Pre-scan now (in the caller's thread: it takes a second or two); return the state."""
        fid = check_fragment_id(fragment_id)
        if self._prescan is None:
            raise BenchBusy("this station's scanner offers no pre-scan")
        if not self._scanner.acquire(blocking=False):
            raise BenchBusy("the scanner is busy with another scan; wait until it finishes")
        try:
            self._update(phase="prescanning", fragment=fid, error=None, message="Pre-scanning the glass…",
                         step=None, delivery=None)
            try:
                out = self._prescan(fid)
            except Exception as exc:  # every failure is shown to the operator, never lost
                self.log.warning("pre-scan of %s failed: %s", fid, exc)
                with self._cond:
                    self._prescan_png = getattr(exc, "png", None)
                self._update(phase="error", error=describe_error(exc), message="")
                return self.state()
            with self._cond:
                self._prescan_png = out.get("png")
            self._update(phase="idle", message=out.get("message", "Fragment found. Press Scan to capture it."))
            return self.state()
        finally:
            self._scanner.release()

    def scan_empty_glass(self) -> dict:
        """Scan the empty glass as the background for finding fragments; return the state."""
        if self._empty_glass is None:
            raise BenchBusy("this station's scanner takes no background scan")
        if not self._scanner.acquire(blocking=False):
            raise BenchBusy("the scanner is busy with another scan; wait until it finishes")
        try:
            self._update(phase="prescanning", error=None, step=None, delivery=None,
                         message="Scanning the empty glass…")
            try:
                text = self._empty_glass()
            except Exception as exc:
                self.log.warning("empty-glass scan failed: %s", exc)
                self._update(phase="error", error=describe_error(exc), message="")
                return self.state()
            self._update(phase="idle", message=text or "Empty glass scanned.")
            return self.state()
        finally:
            self._scanner.release()

    def start(self, fragment_id: str) -> dict:
        """Start capturing ``fragment_id`` in the background; raise :class:`BenchBusy` if scanning."""
        fid = check_fragment_id(fragment_id)
        if not self._scanner.acquire(blocking=False):
            raise BenchBusy("a scan is already running; finish or cancel it first")
        record = _Record(fid, time.time())
        with self._cond:
            self._released = None
            self._cancel = False
            self._state.history.insert(0, record)
        self._update(phase="scanning", fragment=fid, step=None, scans_done=0, scans_total=0, error=None,
                     delivery=None, message="Starting the capture…")
        self._thread = threading.Thread(target=self._run, args=(fid, record), name=f"capture-{fid}", daemon=True)
        self._thread.start()
        return self.state()

    def proceed(self, step_index: int) -> dict:
        """The operator has done step ``step_index``; the scan it announced may start.

        A repeated click for the same step (or a stale page) does nothing.
        """
        with self._cond:
            s = self._state
            if s.phase == "waiting" and s.step and s.step["index"] == int(step_index):
                self._released = int(step_index)
                self._cond.notify_all()
        return self.state()

    def cancel(self) -> dict:
        """Stop the capture before its next scan (scans taken so far are discarded)."""
        with self._cond:
            self._cancel = True
            self._cond.notify_all()
        return self.state()

    def join(self, timeout_s: float | None = None) -> None:
        """Wait for the background capture to end (tests and shutdown)."""
        if self._thread is not None:
            self._thread.join(timeout_s)

    # -- the capture thread -----------------------------------------------------------------
    def _operator(self, step) -> None:
        info = {"index": int(step.index), "total": int(step.total), "face": str(step.face),
                "rotation": float(step.rotation), "instruction": str(step.instruction)}
        self._update(phase="waiting", step=info, scans_done=int(step.index), scans_total=int(step.total),
                     message=step.instruction)
        with self._cond:
            self._cond.wait_for(lambda: self._cancel or self._released == info["index"])
            if self._cancel:
                raise _Cancelled()
        if self._act is not None:
            self._act(step)
        self._update(phase="scanning", message=f"Scanning the {info['face']} face, "
                                                f"scan {info['index'] + 1} of {info['total']}…")

    def _run(self, fid: str, record: _Record) -> None:
        try:
            try:
                result = self._capture(fid, self._operator)
                self._update(phase="saving", step=None, message="Saving the scans…",
                             scans_done=self._state.scans_total)
                delivery = dict(self._deliver(fid, result) or {})
            except _Cancelled:
                record.outcome, record.finished = "cancelled", time.time()
                self._update(phase="cancelled", step=None, message="Capture cancelled; nothing was saved.")
                return
            except Exception as exc:
                self.log.warning("capture of %s failed: %s", fid, exc, exc_info=True)
                err = describe_error(exc)
                record.outcome, record.finished, record.note = "failed", time.time(), err["message"]
                self._update(phase="error", step=None, error=err, message="")
                return
            sent = bool(delivery.get("sent"))
            record.outcome = "sent" if sent else "kept"
            record.finished = time.time()
            if sent:
                msg = delivery.get("message") or f"Fragment {fid} is captured and sent to the lab."
            else:
                msg = delivery.get("message") or (f"Fragment {fid} is captured. The lab cannot be reached: the scans "
                                                  "are kept on this machine and will be sent automatically.")
            record.note = msg
            self._update(phase="done", step=None, delivery=delivery, message=msg)
        finally:
            self._scanner.release()


class _Cancelled(Exception):
    """Raised inside the capture thread to stop at the next operator step."""
