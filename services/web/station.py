"""What every page reads: the station behind the pages (store, proposal store, broker, scanner).

:func:`station` gives a blueprint the running app's :class:`Station` (the token, the settings, the
storage root, the bench session, the broker link, the review data); :func:`requires` turns a
missing part into a clear 503. :class:`StationLink` is the broker as the pages need it plus the
bench's durable outbox; :func:`build_bench` wires the capture workflow to the configured scanner.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import threading
import time
from pathlib import Path
from typing import Any, Callable, Mapping

from flask import abort, current_app, jsonify, make_response

from common.web.bench import BenchSession

log = logging.getLogger("tessera.web")

#: key of :class:`Station` in ``app.extensions``
EXTENSION = "tessera"


@dataclasses.dataclass
class Station:
    """The parts of the station one app serves; any of the optional ones may be absent."""

    token: str
    settings: dict
    store_root: Path
    bench: BenchSession | None = None
    link: "StationLink | None" = None
    review: Any = None                      # common.web.review.ReviewData
    #: tile pyramids of the faces (common.web.tiles.TileCache over the storage root)
    tiles: Any = None
    #: the archive's catalogue index (common.web.catalogue.Catalogue) or None
    catalogue: Any = None
    #: the broker's event feed, followed in the background (:class:`FeedFollower`) or None
    feed: "FeedFollower | None" = None
    #: metadata edits sent from this app, shown until the feed brings them back
    sent_edits: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=200))
    #: verdicts sent from this app, shown until the matcher records them
    sent_verdicts: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=200))


def station() -> Station:
    """The :class:`Station` of the app handling the current request."""
    return current_app.extensions[EXTENSION]


def requires(part: str, message: str) -> Callable:
    """Decorator of a JSON route: answer 503 with ``{"error": message}`` when the station has no ``part``
    (e.g. ``"review"``), so the page can say why (an HTML error page would leave it a generic message)."""
    def wrap(view: Callable) -> Callable:
        @functools.wraps(view)
        def checked(*args, **kwargs):
            if getattr(station(), part) is None:
                abort(make_response(jsonify(error=message), 503))
            return view(*args, **kwargs)
        return checked
    return wrap


def submit_or_503(msg: dict, what: str) -> bool:
    """Send a write (a verdict, a metadata edit) through the station's bus link; return whether
    the broker took it now (False: kept in the durable outbox for later).

    Answers 503 with ``{"error": ...}`` naming ``what`` when the station has no broker configured
    or the outbox refuses it: the page must say the write did not go through."""
    st = station()
    if st.link is None:
        abort(make_response(jsonify(error=f"the broker is not configured on this station; the {what} was not sent"), 503))
    try:
        return st.link.submit(msg)
    except Exception as exc:
        log.warning("%s %s not sent: %s", what, msg["uid"], exc)
        abort(make_response(jsonify(error=f"the {what} could not be sent to the broker: {exc}"), 503))

def answers_in_json(bp):
    """Make a blueprint of JSON routes answer its 404s, unreadable artifacts and refused writes as JSON.

    ``{"error": ...}`` with 404, 500 for a face on storage that cannot be read (truncated, replaced, not
    HDF5), or 507 when the storage refuses what a read must write (an export, tiles: full or read-only):
    the error is said and the rest of the archive is served. Returns ``bp``.
    """
    from common.store import ArtifactError, StorageError

    @bp.errorhandler(404)
    def not_found(exc):
        return jsonify(error=getattr(exc, "description", "not found")), 404

    @bp.errorhandler(ArtifactError)
    def unreadable(exc):
        return jsonify(error=f"the face cannot be read: {exc}"), 500

    @bp.errorhandler(StorageError)
    def refused(exc):
        return jsonify(error=f"the storage refuses the files this needs: {exc}"), 507

    return bp


# --------------------------------------------------------------------------------------------
# the station behind the pages: broker, outbox, event feed, scanner
# --------------------------------------------------------------------------------------------
class FeedFollower:
    """Follows the broker's event feed (``SINCE`` requests) and hands every event to subscribers.

    One per app. :meth:`poll` asks for the events after the last one seen (at most ``batch``),
    decodes them and calls each subscriber whose types match with ``(event, seq)``, in feed order.
    A subscriber must be idempotent: after a restart the feed is replayed from ``start``.
    ``on_gap(stream, last_seq)`` is called when the feed cannot be followed without a hole — at the
    first round without a position, when the broker's journal is new (another stream id) or no
    longer holds the events after the position — and returns the sequence number to continue
    after (the catalogue rebuilds from storage there); without ``on_gap`` the follower starts at
    the broker's last event.
    :meth:`start` runs :meth:`poll` every ``interval_s`` in a daemon thread; the broker being away
    only delays it.
    """

    def __init__(self, link: "StationLink", *, start: tuple[str, int] = ("", 0), interval_s: float = 1.0,
                 batch: int = 1000, on_gap: Callable[[str, int], int] | None = None):
        self.link = link
        self.stream, self.seq = start
        self.interval_s = float(interval_s)
        self.batch = int(batch)
        self.on_gap = on_gap
        self._subs: list[tuple[frozenset[str] | None, Callable[[dict, int], None], Callable | None]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.error = ""

    def subscribe(self, types, callback: Callable[[dict, int], None], *,
                  position: Callable[[str, int], None] | None = None) -> None:
        """Call ``callback(event, seq)`` for events of ``types`` (None: every event); ``position(stream,
        seq)`` after each batch (to persist where the subscriber got to)."""
        self._subs.append((frozenset(types) if types is not None else None, callback, position))

    def poll(self, *, blocking: bool = True) -> int:
        """One round: fetch and dispatch the next events; return how many were dispatched.

        With ``blocking=False`` it returns -1 at once if another round is under way (a page must not
        wait for a catch-up from storage)."""
        if not self._lock.acquire(blocking=blocking):
            return -1
        try:
            return self._poll()
        finally:
            self._lock.release()

    def _poll(self) -> int:
        from common.messages import MessageError, unpack

        kinds = [t for t, _, _ in self._subs]
        types = None if not kinds or None in kinds else sorted(frozenset().union(*kinds))
        with self.link.client() as c:
            answer = c.since(self.seq, limit=self.batch, types=types)
        stream, first = str(answer.get("stream", "")), int(answer.get("first_seq") or 0)
        last = int(answer.get("last_seq") or 0)
        if stream != self.stream or (self.seq and first > self.seq + 1):
            if self.stream or self.on_gap is not None:
                log.info("event feed: starting after %s:%d, broker stream %s holds %d..%d; catching up from "
                         "storage", self.stream or "-", self.seq, stream, first, last)
            self.seq = self.on_gap(stream, last) if self.on_gap is not None else last
            self.stream = stream
            self._positions()
            return 0
        n = 0
        for seq, data in answer.get("events", []):
            try:
                event = unpack(bytes(data), legacy_verdicts=True)   # the journal's: older verdict words too
            except MessageError as exc:   # the broker validated it; a newer schema, perhaps
                log.warning("event feed: event %d not understood: %s", seq, exc)
                event = None
            if event is not None:
                for kinds_, callback, _ in self._subs:
                    if kinds_ is None or event["type"] in kinds_:
                        try:
                            callback(event, int(seq))
                        except Exception:   # one bad event must not stop the feed
                            log.exception("event feed: %s %s (seq %d) failed", event["type"], event["uid"], seq)
            n += 1
            self.seq = int(seq)
        self.seq = max(self.seq, int(answer.get("scanned_to") or 0))
        self._positions()
        return n

    def _positions(self) -> None:
        for _, _, position in self._subs:
            if position is not None:
                position(self.stream, self.seq)

    def start(self) -> None:
        def loop():
            while not self._stop.is_set():
                try:
                    more = self.poll() >= self.batch
                    self.error = ""
                except Exception as exc:   # the broker is away: try again later
                    self.error = str(exc)
                    more = False
                if not more:
                    self._stop.wait(self.interval_s)

        self._thread = threading.Thread(target=loop, name="event-feed", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)


class StationLink:
    """The broker as the pages need it, plus the bench's durable outbox.

    A short-lived :class:`~common.bus.client.BrokerClient` per call (clients are thread-confined); the
    status is cached for ``cached_s`` so that many open pages do not hammer the broker. Verdicts go
    through the outbox too, so a verdict given while the broker is down is sent when it is back.
    """

    def __init__(self, cfg: Mapping):
        from common.bus.outbox import Outbox
        from common.store import Store

        self.cfg = cfg
        self._status: tuple[float, dict] | None = None
        self._lock = threading.Lock()
        self._drain_lock = threading.Lock()
        self.outbox = Outbox(cfg["scanner"]["spool_dir"])
        st = cfg["storage"]
        self.storage = Store(st["root"], file_locking=st["file_locking"], create=st.get("create_root", True))
        self._stop = threading.Event()
        self._drain_thread: threading.Thread | None = None

    def client(self):
        """A fresh client (clients are thread-confined and requests run on many threads).

        One short attempt: a page must not hang while the broker is down; the outbox retries.
        """
        from common.bus.client import BrokerClient

        return BrokerClient.from_config(self.cfg, timeout_s=min(1.0, float(self.cfg["client"]["timeout_s"])),
                                        retries=1)

    def status(self, cached_s: float = 0.0) -> dict:
        """The broker's status; with ``cached_s``, an answer (or failure) that recent is reused,
        so the bench's live poll never waits for a broker that is down."""
        with self._lock:
            if cached_s and self._status and time.monotonic() - self._status[0] < cached_s:
                if isinstance(self._status[1], Exception):
                    raise self._status[1]
                return dict(self._status[1])
        try:
            with self.client() as c:
                st = c.status()
        except Exception as exc:
            with self._lock:
                self._status = (time.monotonic(), exc)
            raise
        with self._lock:
            self._status = (time.monotonic(), st)
        return dict(st)

    def rerun(self, job: str) -> dict:
        with self.client() as c:
            return {"rerun": c.rerun(job)}

    def outbox_depth(self) -> int:
        return len(self.outbox)

    def submit(self, event: Mapping) -> bool:
        """Queue an event durably and try to send it now; True if the broker has it already."""
        self.outbox.put(event)
        return self.drain()

    def drain(self) -> bool:
        """Send what the outbox holds; True when it is empty afterwards."""
        with self._drain_lock, self.client() as c:   # one drain at a time keeps the outbox's order
            try:
                self.outbox.drain(c, self.storage)
            except Exception as exc:  # never let a drain error reach the operator's request
                log.warning("outbox drain failed: %s", exc)
        return len(self.outbox) == 0

    def start_drain(self) -> None:
        """Retry the outbox every ``[scanner] drain_interval_s`` in the background."""
        interval = float(self.cfg["scanner"]["drain_interval_s"])

        def loop():
            while not self._stop.wait(interval):
                if len(self.outbox):
                    self.drain()

        self._drain_thread = threading.Thread(target=loop, name="outbox-drain", daemon=True)
        self._drain_thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._drain_thread is not None:
            self._drain_thread.join(5)
        self.outbox.close()


def _simulated_bench(cfg: Mapping):
    """A simulated flatbed and the fragments it can be given, by id (the synthetic fresco).

    The fresco is generated at the first request for a fragment, not at start, so the pages come
    up at once. A known fresco id gets its fragment; any other id the next fragment nobody asked
    for by name (the operator's labels are free text).
    """
    from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface

    sc = cfg["scanner"]
    sim = SimulatedFlatbed("sim", seed=int(sc["seed"]))
    surfaces: dict[str, Any] = {}
    order: list[str] = []
    lock = threading.Lock()
    made = []

    def surface_for(fid: str):
        with lock:
            if not made:
                made.append(True)
                try:
                    from common.synth import generate_wall

                    wall = generate_wall(int(sc["fragments"]), int(sc["seed"]), dpi=float(sc["wall_dpi"]))
                    surfaces.update({f.id: f.surface for f in wall.fragments})
                    order.extend(surfaces)
                except ImportError:  # any fragment-like surface will do
                    log.info("common.synth.generate_wall not available; the simulated glass gets demo fragments")
            if fid not in surfaces:
                if order:
                    surfaces[fid] = surfaces[order.pop(0)]
                else:
                    seed = int.from_bytes(fid.encode()[:4].ljust(4, b"\0"), "little")
                    surfaces[fid] = demo_surface(40.0, float(sc["wall_dpi"]), seed=seed)
            elif fid in order:
                order.remove(fid)
            return surfaces[fid]

    return sim, surface_for


def build_bench(cfg: Mapping, *, link: StationLink, scanner=None, surface_for=None) -> BenchSession:
    """The bench's capture session on the configured scanner, delivering through ``link``'s outbox.

    With ``[scanner] device = "simulated"`` the glass is a :class:`SimulatedFlatbed`: pressing
    *Done* on the page performs the step (place, turn, flip) on it.
    """
    import numpy as np

    from common.acquisition import capture as cap
    from common.acquisition.locate import fragment_mask, locate_fragment, locate_fragments, to_float
    from common.web.compose import COLOUR_B, encode_png, outline_detected

    sc = cfg["scanner"]
    act = None
    if scanner is None:
        if sc["device"] == "simulated":
            scanner, surface_for = _simulated_bench(cfg)
        else:
            from common.acquisition.scanners import SaneScanner

            scanner = SaneScanner(sc["sane_device"])
    sim_act = cap.simulated_operator(scanner) if surface_for is not None else None
    current = {"fragment": None}
    glass = {"background": None}   # empty-bed pre-scan: finds fragments of any size (§3.3.4)

    def empty_glass():
        if surface_for is not None:
            scanner.clear()   # simulated: the operator takes everything off the glass
        pre = scanner.scan(None, float(sc["prescan_dpi"]), int(sc["depth"]))
        # only something fragment-sized counts: the estimated background lets noise through as specks
        blobs = [b for b in locate_fragments(pre, float(sc["prescan_dpi"])) if b.area_mm2 >= 100.0]
        if blobs:
            raise cap.CaptureError(f"empty-glass scan shows {len(blobs)} object(s)",
                                   "Something is still on the glass. Take everything off, close the lid and "
                                   "press 'Scan empty glass' again.")
        glass["background"] = pre
        return "Empty glass scanned: fragments will be found against it. Place a fragment and press Pre-scan."

    if surface_for is not None:
        def act(step):
            if step.action == "place":
                scanner.place(surface_for(current["fragment"]))
            else:
                sim_act(step)

    def capture(fid, operator):
        current["fragment"] = fid
        return cap.capture_fragment(scanner, fid, operator=operator, dpi=float(sc["dpi"]),
                                    prescan_dpi=float(sc["prescan_dpi"]), depth=int(sc["depth"]),
                                    colour_only=bool(sc["colour_only"]), margin_mm=float(sc["margin_mm"]),
                                    background=glass["background"])

    def deliver(fid, result):
        # exactly the scanner service's path: storage, else the local spool; fragment.ready via the outbox
        from services.scanner import store_scans

        event, spooled = store_scans(result, link.storage, link.outbox)
        sent = link.drain()
        out = {"sent": sent, "artifact": event["artifact"]["path"], "spooled": spooled}
        if not sent and not spooled:  # the scans are on the lab's storage; only the broker is away
            out["message"] = (f"Fragment {fid} is captured and its scans are on the lab's storage. The broker cannot "
                              "be reached: the announcement waits on this machine and is sent automatically.")
        return out

    def prescan(fid):
        if surface_for is not None:
            scanner.place(surface_for(fid))   # simulated: the operator puts the fragment down
        dpi = float(sc["prescan_dpi"])
        pre = scanner.scan(None, dpi, int(sc["depth"]))
        shown = to_float(pre)
        pixel = 25.4 / dpi
        try:
            left, top, right, bottom = locate_fragment(pre, dpi, margin_mm=float(sc["margin_mm"]),
                                                       bed_mm=tuple(scanner.bed_mm), background=glass["background"])
        except cap.CaptureError as exc:
            boxes = [tuple(int(round(v / pixel)) for v in (b.bbox_mm[1], b.bbox_mm[0], b.bbox_mm[3], b.bbox_mm[2]))
                     for b in locate_fragments(pre, dpi, background=glass["background"])]
            img = shown
            for box in boxes:
                img = outline_detected(img, bbox=box, colour=COLOUR_B, thickness_px=2)
            exc.png = encode_png(outline_detected(img) if not boxes else img)
            raise
        r0, c0 = int(top / pixel), int(left / pixel)
        r1, c1 = int(np.ceil(bottom / pixel)), int(np.ceil(right / pixel))
        mask = np.zeros(shown.shape[:2], bool)
        mask[r0:r1, c0:c1] = fragment_mask(pre[r0:r1, c0:c1], dpi)
        png = encode_png(outline_detected(shown, mask, bbox=(r0, c0, r1, c1)))
        w, h = right - left, bottom - top
        return {"png": png, "message": f"Fragment found ({w:.0f} × {h:.0f} mm with margin). Press Scan to capture it."}

    session = BenchSession(capture=capture, deliver=deliver, prescan=prescan, act=act, empty_glass=empty_glass, log=log)
    if surface_for is not None:
        session.scan_empty_glass()   # simulated: the glass starts empty, take its background now
    return session
