"""The station's web pages: operator bench, match review, station status.

``tessera web`` serves three pages to the people at the station, from the station itself, with
every asset local (no CDN: the lab has no internet):

* **Bench** (``/bench``) — the operator's front end to the scanner. This process owns the scanner:
  it runs the capture workflow in a background thread (:class:`common.web.bench.BenchSession`)
  and delivers the scans through the same spool and outbox as ``services/scanner.py``, so
  captures are kept when the lab is unreachable. Today's fragments and their pipeline state
  update live (long-poll).
* **Review** (``/review``) — ranked join proposals from the matcher's proposal store, both
  fragments side by side and joined at the proposed pose, in colour and in relief; verdicts are
  submitted to the broker as ``match.verified`` events (the matcher records them).
* **Status** (``/status``) — the broker's status: services and workers per host, queues, jobs in
  flight, parked failures with a re-run button, throughput.

Access: it listens on 127.0.0.1 unless ``[services.web] host`` opens it to the lab network.
Reading is open; everything that writes (scan, verdict, re-run) needs the station's access token
(``[services.web] token``, or generated at first start into ``token_file``; see
:mod:`common.web.auth`). Browsers log in once with the token and then carry a session cookie
(HttpOnly, SameSite=Strict) plus a CSRF value in a header; scripts send ``Authorization: Bearer``.
"""

from __future__ import annotations

import collections
import functools
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable, Mapping

from flask import Flask, abort, jsonify, redirect, render_template, request, session, url_for

from common.messages import new_message
from common.web import auth
from common.web.bench import BenchBusy, BenchSession, check_fragment_id
from common.web.pipeline import fragment_state, fragments_since, start_of_today

SERVICE = "web"
VERSION = "1"

log = logging.getLogger("tessera.web")

HERE = Path(__file__).resolve().parent

#: settings of ``[services.web]`` and their defaults
DEFAULTS: dict[str, Any] = {
    "host": "127.0.0.1",        # "0.0.0.0" (or the lab interface's address) opens it to the lab network
    "port": 8080,
    "token": "",                # access token; empty: generated at first start into token_file
    "token_file": "",           # default <storage root>/web/web_token  (keep it on local disk)
    "operator": "",             # name recorded with verdicts when the browser sends none
    "long_poll_s": 3.0,         # how long a page's live request waits for a change
    "picture_px": 640,          # longest side of the review pictures
}


class WebConfigError(ValueError):
    """A ``[services.web]`` setting is invalid; the message names it."""


def web_settings(cfg: Mapping) -> dict:
    """``[services.web]`` of the station config over :data:`DEFAULTS`, checked."""
    given = dict(cfg.get("services", {}).get(SERVICE, {}))
    out = dict(DEFAULTS)
    for key, value in given.items():
        if key not in DEFAULTS:
            raise WebConfigError(f"services.web.{key}: unknown setting (known: {', '.join(sorted(DEFAULTS))})")
        want = type(DEFAULTS[key])
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, want) or isinstance(value, bool) != (want is bool):
            raise WebConfigError(f"services.web.{key}: expected {want.__name__}, got {value!r}")
        out[key] = value
    if not 1 <= out["port"] <= 65535:
        raise WebConfigError(f"services.web.port: expected a TCP port 1-65535, got {out['port']}")
    if out["token"] and len(out["token"]) < auth.MIN_TOKEN_CHARS:
        raise WebConfigError(f"services.web.token: must be at least {auth.MIN_TOKEN_CHARS} characters")
    if out["long_poll_s"] <= 0 or out["picture_px"] < 64:
        raise WebConfigError("services.web.long_poll_s must be positive and services.web.picture_px >= 64")
    return out


def station_token(cfg: Mapping, settings: Mapping) -> tuple[str, Path | None]:
    """The access token and the file it was read from / generated into (None if from config)."""
    if settings["token"]:
        return settings["token"], None
    path = Path(settings["token_file"] or Path(cfg["storage"]["root"]) / "web" / "web_token")
    return auth.load_or_create_token(path), path


# --------------------------------------------------------------------------------------------
# the application
# --------------------------------------------------------------------------------------------
def create_app(*, token: str, settings: Mapping | None = None, store_root: str | os.PathLike,
               bench: BenchSession | None = None, link=None, review=None) -> Flask:
    """The Flask application.

    Parameters
    ----------
    token : str
        Station access token (required for every write).
    settings : mapping, optional
        ``[services.web]`` settings (:func:`web_settings`).
    store_root : path
        Storage root (pipeline state is read from its tree).
    bench : BenchSession, optional
        The scanner's capture session; without it the bench page says there is no scanner here.
    link : StationLink, optional
        The broker (status, re-run, submitting verdicts) and the bench's outbox.
    review : common.web.review.ReviewData, optional
        Proposals, verdict history and pictures.
    """
    if not token or len(token) < auth.MIN_TOKEN_CHARS:
        raise ValueError(f"token must be at least {auth.MIN_TOKEN_CHARS} characters")
    settings = dict(DEFAULTS, **(settings or {}))
    app = Flask("tessera.web", static_folder=str(HERE / "web_static"), template_folder=str(HERE / "web_templates"),
                static_url_path="/static")
    app.secret_key = auth.session_secret(token)
    app.config.update(SESSION_COOKIE_HTTPONLY=True, SESSION_COOKIE_SAMESITE="Strict",
                      SESSION_COOKIE_NAME="tessera_session", MAX_CONTENT_LENGTH=64 * 1024,
                      PERMANENT_SESSION_LIFETIME=12 * 3600)
    store_root = Path(store_root)
    sent_verdicts: collections.deque = collections.deque(maxlen=200)   # shown until the matcher records them

    # -- access ----------------------------------------------------------------------------
    def logged_in() -> bool:
        return bool(session.get("auth"))  # the cookie is signed with a key derived from the token

    def authorised() -> bool:
        """A write is allowed with the bearer token, or a logged-in session echoing its CSRF value."""
        bearer = auth.bearer_token(request.headers.get("Authorization"))
        if bearer is not None:
            return auth.check_token_slowly(bearer, token)  # a wrong Bearer token is slowed like /login
        if not logged_in():
            return False
        return auth.token_matches(request.headers.get("X-CSRF-Token"), session.get("csrf", ""))

    def same_origin() -> bool:
        origin = request.headers.get("Origin")
        return origin is None or origin == request.host_url.rstrip("/")

    def writes(view: Callable) -> Callable:
        @functools.wraps(view)
        def guarded(*args, **kwargs):
            if not same_origin():
                return jsonify(error="cross-site request refused"), 403
            if not authorised():
                return jsonify(error="log in with the station's access token to do this"), 401
            if not request.is_json:
                return jsonify(error="send the request body as application/json"), 415
            return view(*args, **kwargs)
        return guarded

    def body() -> dict:
        data = request.get_json(silent=True)
        if not isinstance(data, dict):
            abort(400, "request body must be a JSON object")
        return data

    @app.context_processor
    def page_context():
        return {"logged_in": logged_in(), "csrf": session.get("csrf", "") if logged_in() else "",
                "has_scanner": bench is not None, "station_host": request.host}

    @app.after_request
    def headers(resp):
        # pages are local-only: no framing by other sites, no third-party anything
        resp.headers.setdefault("X-Frame-Options", "DENY")
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        resp.headers.setdefault("Referrer-Policy", "same-origin")  # no-referrer would make Origin "null"
        resp.headers.setdefault("Content-Security-Policy",
                                "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
                                "frame-ancestors 'none'; form-action 'self'")
        if request.path.startswith("/api/"):
            resp.headers.setdefault("Cache-Control", "no-store")
        return resp

    @app.errorhandler(400)
    def bad_request(exc):
        return jsonify(error=getattr(exc, "description", "bad request")), 400

    # -- pages -----------------------------------------------------------------------------
    @app.get("/")
    def index():
        return redirect(url_for("bench_page") if bench is not None else url_for("review_page"))

    @app.get("/bench")
    def bench_page():
        return render_template("bench.html", page="bench")

    @app.get("/review")
    def review_page():
        return render_template("review.html", page="review", fragment=request.args.get("fragment", ""))

    @app.get("/status")
    def status_page():
        return render_template("status.html", page="status")

    @app.get("/login")
    def login_form():
        return render_template("login.html", page="login", error="", next=_safe_next(request.args.get("next")))

    @app.post("/login")
    def login():
        nxt = _safe_next(request.form.get("next"))
        if not same_origin():
            abort(403)
        if not auth.token_matches(request.form.get("token", "").strip(), token):
            time.sleep(0.5)  # slows guessing; the token's 256 bits do the real work
            return render_template("login.html", page="login", error="That is not this station's access token.",
                                   next=nxt), 401
        session.clear()
        session.permanent = True
        session.update(auth=True, csrf=auth.new_csrf_value(),
                       who=request.form.get("who", "").strip()[:64])
        return redirect(nxt)

    @app.post("/logout")
    def logout():
        if same_origin():
            session.clear()
        return redirect(url_for("index"))

    # -- bench -----------------------------------------------------------------------------
    def today_fragments() -> list[dict]:
        matched = review.matched_fragments() if review is not None else set()
        failed = _failures_by_fragment(link)
        rows = []
        for fid, t in fragments_since(store_root, start_of_today()):
            st = fragment_state(store_root, fid, matched=matched, failed=failed.get(fid))
            st["scanned_at"] = t
            rows.append(st)
        if bench is not None:   # captures kept locally (lab unreachable) are not on storage yet
            listed = {r["fragment"] for r in rows}
            for rec in bench.state()["history"]:
                if rec["outcome"] == "kept" and rec["fragment"] not in listed:
                    rows.insert(0, {"fragment": rec["fragment"], "stages": {"scanned": "kept"}, "errors": {},
                                    "updated": rec["finished"], "scanned_at": rec["started"]})
                    listed.add(rec["fragment"])
        return rows

    @app.get("/api/bench")
    def bench_state():
        after = request.args.get("after", type=int)
        if bench is None:
            st = {"phase": "none", "message": "No scanner is attached to this station.", "seq": 0, "history": []}
        elif after is not None:
            st = bench.wait_for_change(after, float(settings["long_poll_s"]))
        else:
            st = bench.state()
        return jsonify(bench=st, fragments=today_fragments(), time=time.time())

    @app.get("/api/bench/prescan.png")
    def bench_prescan_png():
        png = bench.prescan_png() if bench is not None else None
        if not png:
            abort(404)
        return png, 200, {"Content-Type": "image/png"}

    def bench_action(fn: Callable[[dict], dict]):
        if bench is None:
            return jsonify(error="No scanner is attached to this station."), 409
        try:
            return jsonify(bench=fn(body()))
        except BenchBusy as exc:
            return jsonify(error=str(exc)), 409
        except ValueError as exc:
            return jsonify(error=str(exc)), 400

    @app.post("/api/bench/prescan")
    @writes
    def bench_prescan():
        return bench_action(lambda b: bench.prescan(b.get("fragment", "")))

    @app.post("/api/bench/empty-glass")
    @writes
    def bench_empty_glass():
        return bench_action(lambda b: bench.scan_empty_glass())

    @app.post("/api/bench/scan")
    @writes
    def bench_scan():
        return bench_action(lambda b: bench.start(b.get("fragment", "")))

    @app.post("/api/bench/proceed")
    @writes
    def bench_proceed():
        return bench_action(lambda b: bench.proceed(int(b.get("step", -1))))

    @app.post("/api/bench/cancel")
    @writes
    def bench_cancel():
        return bench_action(lambda b: bench.cancel())

    # -- review ----------------------------------------------------------------------------
    def need_review():
        if review is None:
            abort(503, "the proposal store is not available on this station")

    @app.get("/api/review/queue")
    def review_queue():
        need_review()
        limit = min(max(request.args.get("limit", 50, type=int), 1), 500)
        return jsonify(proposals=review.pending(limit), counts=review.counts())

    @app.get("/api/review/fragment/<fid>")
    def review_fragment(fid):
        need_review()
        try:
            fid = check_fragment_id(fid)
        except ValueError as exc:
            abort(400, str(exc))
        return jsonify(fragment=fid, proposals=review.ranked(fid))

    @app.get("/api/review/history")
    def review_history():
        need_review()
        recorded = review.history(limit=100)
        keys = {(v["fragment_a"], v["fragment_b"], v["verdict"]) for v in recorded}
        waiting = [v for v in sent_verdicts if (v["fragment_a"], v["fragment_b"], v["verdict"]) not in keys
                   or v["time"] > max((r["time"] for r in recorded), default=0)]
        return jsonify(history=recorded, sent=list(waiting))

    @app.get("/api/review/picture/<int:pid>/<view>.png")
    def review_picture(pid, view):
        need_review()
        if view not in ReviewViews or not 0 <= pid < 2 ** 63:  # no proposal id beyond SQLite's integers
            abort(404)
        try:
            png = review.picture(pid, view, max_side_px=int(settings["picture_px"]))
        except LookupError as exc:
            return jsonify(error=str(exc)), 404
        return png, 200, {"Content-Type": "image/png", "Cache-Control": "private, max-age=60"}

    @app.post("/api/review/verdict")
    @writes
    def review_verdict():
        need_review()
        b = body()
        verdict = b.get("verdict")
        if verdict not in ("confirmed", "rejected"):
            return jsonify(error="verdict must be 'confirmed' or 'rejected' (skip sends nothing)"), 400
        prop = review.proposal(b.get("proposal"))
        if prop is None:
            return jsonify(error=f"no proposal {b.get('proposal')!r}"), 404
        who = (session.get("who") or settings["operator"] or "web")[:64]
        msg = new_message("match.verified", fragment=prop["fragment_a"], other=prop["fragment_b"], verdict=verdict,
                          proposal=prop["id"], probability=prop["probability"], by=who,
                          model_version=prop.get("model_version"))
        if link is None:
            return jsonify(error="the broker is not configured on this station; the verdict was not sent"), 503
        try:
            delivered = link.submit(msg)
        except Exception as exc:  # the page must say the verdict did not go through
            log.warning("verdict %s not sent: %s", msg["uid"], exc)
            return jsonify(error=f"the verdict could not be sent to the broker: {exc}"), 503
        entry = {"fragment_a": prop["fragment_a"], "fragment_b": prop["fragment_b"], "verdict": verdict, "by": who,
                 "time": msg["time"], "uid": msg["uid"], "proposal": prop["id"], "delivered": delivered}
        sent_verdicts.appendleft(entry)
        return jsonify(sent=entry)

    # -- status ----------------------------------------------------------------------------
    @app.get("/api/status")
    def station_status():
        if link is None:
            return jsonify(error="the broker is not configured on this station"), 503
        try:
            st = link.status()
        except Exception as exc:
            return jsonify(error=f"the broker cannot be reached: {exc}", reachable=False), 503
        st["reachable"] = True
        st["outbox"] = link.outbox_depth()
        return jsonify(st)

    @app.post("/api/status/rerun")
    @writes
    def station_rerun():
        if link is None:
            return jsonify(error="the broker is not configured on this station"), 503
        job = str(body().get("job", "")).strip()
        if not job:
            return jsonify(error="name the parked job to re-run (or 'all')"), 400
        try:
            return jsonify(link.rerun(job))
        except Exception as exc:
            return jsonify(error=f"the broker cannot be reached: {exc}"), 503

    return app


#: picture views of a proposal offered by the review page
ReviewViews = ("pair-colour", "pair-relief", "joined-colour", "joined-relief")


def _safe_next(target: str | None) -> str:
    """Only local paths are followed after login (no open redirect)."""
    if target and target.startswith("/") and not target.startswith("//") and "\\" not in target:
        return target
    return "/"


def _failures_by_fragment(link) -> dict[str, dict[str, str]]:
    if link is None:
        return {}
    try:
        parked = link.status(cached_s=5.0).get("parked", [])
    except Exception:
        return {}
    out: dict[str, dict[str, str]] = collections.defaultdict(dict)
    for job in parked:
        if job.get("fragment"):
            out[str(job["fragment"])][str(job.get("service"))] = str(job.get("error", ""))
    return out


# --------------------------------------------------------------------------------------------
# running it
# --------------------------------------------------------------------------------------------
def serve(cfg: Mapping, *, host: str | None = None, port: int | None = None, with_scanner: bool = True,
          ready: Callable[[str], None] | None = None, stop: threading.Event | None = None) -> int:
    """Run the web server until ``stop`` is set (or SIGINT/SIGTERM); returns an exit status."""
    from werkzeug.serving import make_server

    from common.web.review import ReviewData

    settings = web_settings(cfg)
    host = host or settings["host"]
    port = int(port if port is not None else settings["port"])
    token, token_path = station_token(cfg, settings)
    link = StationLink(cfg)
    review = ReviewData.from_config(cfg)
    bench = None
    if with_scanner:
        try:
            bench = build_bench(cfg, link=link)
        except Exception as exc:  # the review and status pages are still worth serving
            log.error("no scanner for the bench page (%s: %s); serving review and status only",
                      type(exc).__name__, exc)
    if bench is not None:
        link.start_drain()
    app = create_app(token=token, settings=settings, store_root=cfg["storage"]["root"], bench=bench, link=link,
                     review=review)
    if not log.isEnabledFor(logging.DEBUG):   # one line per poll of every open page is noise
        logging.getLogger("werkzeug").setLevel(logging.WARNING)
    server = make_server(host, port, app, threaded=True)
    url = f"http://{host if host not in ('0.0.0.0', '::') else '127.0.0.1'}:{server.server_port}"
    where = "this machine only" if host in ("127.0.0.1", "localhost", "::1") else "the lab network"
    log.info("web pages at %s (listening on %s:%d, reachable from %s)", url, host, server.server_port, where)
    if token_path is not None:
        log.info("access token for scan/verdict/re-run is in %s", token_path)
    if ready is not None:
        ready(url)
    stop = stop or threading.Event()
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.5}, daemon=True)
    thread.start()
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
        link.close()
        if bench is not None:
            bench.cancel()
    return 0


# --------------------------------------------------------------------------------------------
# the station behind the pages: broker, outbox, scanner
# --------------------------------------------------------------------------------------------
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
