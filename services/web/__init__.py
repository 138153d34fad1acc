"""The station's web pages: operator bench, match review, station status, the archive.

``tessera web`` serves the pages to the people at the station, from the station itself, with
every asset local (no CDN: the lab has no internet). The app is Flask's large-application
pattern: :func:`create_app` is the factory, each page or API area is a blueprint in its own
module of this package, and :data:`BLUEPRINTS` registers them all:

* :mod:`.auth`    — ``/login``, ``/logout`` and the access decorator :func:`.auth.writes`;
* :mod:`.bench`   — ``/bench``: the operator's front end to the scanner (this process owns it);
* :mod:`.review`  — ``/review``: ranked join proposals, verdicts as ``match.verified`` events;
* :mod:`.status`  — ``/status``: the broker's services, workers, queues, parked failures;
* :mod:`.catalogue` — ``/fragments``: the archive's catalogue, metadata edits as ``fragment.annotated``;
* :mod:`.tiles`, :mod:`.iiif`, :mod:`.downloads` — tile pyramids and Deep Zoom, IIIF Image and
  Presentation, ``tessera export``'s files;
* :mod:`.fragment`, :mod:`.reconstruction` — the archive's fragment page and reconstruction.

What a blueprint reads (store root, settings, bench, broker link, proposal store, tiles, catalogue,
event feed) is the app's
:class:`.station.Station` (``station()`` inside a request); templates are in ``templates/``,
scripts and styles in ``static/``.

Access: it listens on 127.0.0.1 unless ``[services.web] host`` opens it to the lab network.
Reading is open; everything that writes (scan, verdict, re-run) needs the station's access token
(``[services.web] token``, or generated at first start into ``token_file``; see
:mod:`common.web.auth`). Browsers log in once with the token and then carry a session cookie
(HttpOnly, SameSite=Strict) plus a CSRF value in a header; scripts send ``Authorization: Bearer``.
"""

from __future__ import annotations

import hashlib
import ipaddress
import logging
import os
import re
import threading
from pathlib import Path
from typing import Any, Callable, Mapping

from flask import Flask, abort, jsonify, redirect, request, session, url_for
from flask.json.provider import DefaultJSONProvider

from common.web.auth import MIN_TOKEN_CHARS, load_or_create_token, save_token, session_secret

from common.messages import finite
from common.store import Store
from common.web.bench import BenchSession
from common.web.tiles import TileCache

from . import auth as auth_pages
from . import bench as bench_pages
from . import catalogue as catalogue_pages
from . import downloads as downloads_api
from . import fragment as fragment_page
from . import iiif as iiif_api
from . import reconstruction as reconstruction_page
from . import review as review_pages
from . import status as status_pages

#: CSP hash of the stylesheet OpenSeadragon 6 injects (static/vendor/openseadragon: its
#: ``data-openseadragon-mobile-css`` rule), recomputed when the vendored version changes
OPENSEADRAGON_STYLE_HASH = "sha256-9xTiqzfwFaL2SGb1rmr8gysEwVVjIvqWAgmZgqFqpEE="
from . import tiles as tiles_api
from .station import EXTENSION, FeedFollower, Station, StationLink, build_bench

__all__ = ["DEFAULTS", "BLUEPRINTS", "WebConfigError", "web_settings", "station_token", "local_state_dir", "create_app", "serve",
           "StationLink", "build_bench", "ReviewViews"]

SERVICE = "web"
VERSION = "1"

log = logging.getLogger("tessera.web")

HERE = Path(__file__).resolve().parent

#: settings of ``[services.web]`` and their defaults
DEFAULTS: dict[str, Any] = {
    "host": "127.0.0.1",        # "0.0.0.0" (or the lab interface's address) opens it to the lab network
    "port": 8080,
    "token": "",                # access token; empty: generated at first start into token_file
    "token_file": "",           # default <local state dir>/web_token (local_state_dir(); never the shared storage)
    "operator": "",             # name recorded with verdicts when the browser sends none
    "long_poll_s": 3.0,         # how long a page's live request waits for a change
    "picture_px": 640,          # longest side of the review pictures
    "catalogue_db": "",         # the catalogue's index; default <storage root>/web/catalogue.sqlite (rebuildable)
    "feed_interval_s": 1.0,     # how often the catalogue asks the broker for new events
    "public_origin": "",        # the pages' address behind a TLS reverse proxy, e.g. "https://tessera.lab.example"
    "allowed_hosts": [],        # further names the pages answer under, e.g. ["tessera-lab"]; set, the Host check
                                # applies on the lab network too (empty: only on loopback)
}


#: addresses a browser on this machine reaches pages listening on loopback under (any port: an SSH tunnel's may differ)
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "[::1]"})


#: an ``allowed_hosts`` entry: a host name or IPv4 address, or an IPv6 address in brackets; no scheme, port or path
_ALLOWED_HOST = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9.])?|\[[0-9A-Fa-f:.]+\]")


def _allowed_host_error(entry: Any) -> str | None:
    """Why ``entry`` is not a valid ``allowed_hosts`` entry, or None if it is."""
    if not isinstance(entry, str) or not _ALLOWED_HOST.fullmatch(entry):
        return "not a host name"
    if entry.startswith("["):
        try:
            ipaddress.IPv6Address(entry[1:-1])
        except ValueError:
            return "not an IPv6 address"
    return None


def _allowed_name(entry: str) -> str:
    """An ``allowed_hosts`` entry as :func:`_host_name` gives a Host header's: lower case, no final dot, an IPv6
    address in a browser's (compressed) form."""
    if entry.startswith("["):
        return f"[{ipaddress.IPv6Address(entry[1:-1]).compressed}]"
    return entry.lower().rstrip(".")


def _host_name(host: str) -> str:
    """The name in a ``Host`` header, lower case, without the port or a final dot (``[::1]:8080`` -> ``[::1]``)."""
    name = host.split("]", 1)[0] + "]" if host.startswith("[") else host.rsplit(":", 1)[0]
    return name.lower().rstrip(".")


class StrictJSONProvider(DefaultJSONProvider):
    """Flask's JSON writer, but NaN and ±inf are written as ``null``: a browser's ``JSON.parse``
    refuses a bare ``NaN`` (a docked proposal's ``alignment.gap_mm`` is NaN), and the review page
    then showed an empty queue."""

    def dumps(self, obj, **kwargs):
        kwargs.setdefault("allow_nan", False)
        return super().dumps(finite(obj), **kwargs)


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
    if out["token"] and len(out["token"]) < MIN_TOKEN_CHARS:
        raise WebConfigError(f"services.web.token: must be at least {MIN_TOKEN_CHARS} characters")
    if out["long_poll_s"] <= 0 or out["picture_px"] < 64:
        raise WebConfigError("services.web.long_poll_s must be positive and services.web.picture_px >= 64")
    if out["feed_interval_s"] <= 0:
        raise WebConfigError("services.web.feed_interval_s must be positive")
    origin = out["public_origin"]
    if origin and not re.fullmatch(r"https?://[A-Za-z0-9.-]+(:[0-9]{1,5})?", origin):
        raise WebConfigError(f"services.web.public_origin: expected scheme://host[:port] without a path, e.g. "
                             f"'https://tessera.lab.example', got {origin!r}")
    for entry in out["allowed_hosts"]:
        why = _allowed_host_error(entry)
        if why:
            raise WebConfigError(f"services.web.allowed_hosts: entry {entry!r} is {why}: give each name or IP address "
                                 f"alone, without scheme, port, path or spaces (an IPv6 address in brackets), e.g. "
                                 f"[\"tessera-lab\", \"tessera-lab.example.org\", \"[fe80::7]\"]")
    out["allowed_hosts"] = list(out["allowed_hosts"])
    return out


def local_state_dir() -> Path:
    """This host's directory for Tessera's local state (the web token), never the shared storage.

    ``$STATE_DIRECTORY`` when systemd gives one (``StateDirectory=tessera``), else
    ``/var/lib/tessera`` for root, else ``$XDG_STATE_HOME/tessera`` (default
    ``~/.local/state/tessera``), per the XDG base-directory specification.
    """
    if os.environ.get("STATE_DIRECTORY"):
        return Path(os.environ["STATE_DIRECTORY"].split(":")[0])
    if os.geteuid() == 0:
        return Path("/var/lib/tessera")
    return Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state") / "tessera"


def station_token(cfg: Mapping, settings: Mapping) -> tuple[str, Path | None]:
    """The access token and the file it was read from / generated into (None if from config).

    The default file is ``<local_state_dir()>/web_token`` (mode 0600). A token kept by an older
    version at ``<storage root>/web/web_token`` (readable on the shared storage) is read once
    when the local file is absent, written to the local file, and the log says so.
    """
    if settings["token"]:
        return settings["token"], None
    if settings["token_file"]:
        path = Path(settings["token_file"])
        return load_or_create_token(path), path
    path = local_state_dir() / "web_token"
    old = Path(cfg["storage"]["root"]) / "web" / "web_token"
    if not path.exists() and old.is_file():
        token = load_or_create_token(old)  # refuses a truncated file, as for the new one
        save_token(path, token)
        log.warning("web token moved from the storage root (%s) to local disk (%s); delete the old copy: "
                    "anyone who can read the storage can read it", old, path)
    return load_or_create_token(path), path



# --------------------------------------------------------------------------------------------
# the application
# --------------------------------------------------------------------------------------------
#: every page/API area of the app, registered in this order by :func:`create_app`
BLUEPRINTS = (auth_pages.bp, bench_pages.bp, review_pages.bp, status_pages.bp, catalogue_pages.bp, tiles_api.bp,
              iiif_api.bp, downloads_api.bp, fragment_page.bp, reconstruction_page.bp)

#: picture views of a proposal offered by the review page
ReviewViews = review_pages.VIEWS


def static_version(path: Path) -> str:
    """The version a static file's URLs carry (``?v=``): the first 12 hex digits of its sha256, kept
    per modification time. A page's scripts, styles and the vendored viewer are then cached by the
    browser for good (``immutable``) and fetched again only when they change."""
    stat = path.stat()
    key = (str(path), stat.st_mtime_ns, stat.st_size)
    if key not in _STATIC_VERSIONS:
        _STATIC_VERSIONS[key] = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
    return _STATIC_VERSIONS[key]


_STATIC_VERSIONS: dict[tuple, str] = {}


def create_app(*, token: str, settings: Mapping | None = None, store_root: str | os.PathLike,
               bench: BenchSession | None = None, link: StationLink | None = None, review=None, catalogue=None,
               feed: FeedFollower | None = None) -> Flask:
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
    catalogue : common.web.catalogue.Catalogue, optional
        The archive's index (``/fragments``); without it the catalogue answers 503.
    feed : FeedFollower, optional
        The event feed the catalogue follows (polled at once after an edit).
    """
    if not token or len(token) < MIN_TOKEN_CHARS:
        raise ValueError(f"token must be at least {MIN_TOKEN_CHARS} characters")
    settings = dict(DEFAULTS, **(settings or {}))
    app = Flask("tessera.web", static_folder=str(HERE / "static"), template_folder=str(HERE / "templates"),
                static_url_path="/static")
    app.json = StrictJSONProvider(app)
    app.secret_key = session_secret(token)
    app.config.update(SESSION_COOKIE_HTTPONLY=True, SESSION_COOKIE_SAMESITE="Strict",
                      SESSION_COOKIE_NAME="tessera_session", MAX_CONTENT_LENGTH=64 * 1024,
                      PERMANENT_SESSION_LIFETIME=12 * 3600)
    app.extensions[EXTENSION] = Station(token=token, settings=settings, store_root=Path(store_root), bench=bench,
                                        link=link, review=review, catalogue=catalogue, feed=feed,
                                        tiles=TileCache(Store(store_root, create=False)))
    for bp in BLUEPRINTS:
        app.register_blueprint(bp)

    # Pages listening on loopback answer only under a loopback name, the name public_origin publishes them under or
    # one of allowed_hosts: another Host is a site whose name was pointed at 127.0.0.1 (DNS rebinding) to read the
    # open pages. On the lab network the names the lab uses for this host are known only if allowed_hosts lists
    # them: then the same check applies there; with it empty there is none
    on_loopback = settings["host"] in ("127.0.0.1", "localhost", "::1")
    public = settings["public_origin"]
    allowed = {_allowed_name(name) for name in settings["allowed_hosts"]}
    known_hosts = LOOPBACK_NAMES | ({_host_name(public.split("://", 1)[1])} if public else set()) | allowed
    check_host = on_loopback or bool(allowed)

    @app.before_request
    def known_host():
        if check_host and _host_name(request.host) not in known_hosts:
            return (f"421 Misdirected Request: these pages listen on {settings['host']} and answer only under "
                    f"localhost, 127.0.0.1 or [::1] (or [services.web] public_origin or a name in [services.web] "
                    f"allowed_hosts), not {request.host[:100]!r}\n",
                    421, {"Content-Type": "text/plain; charset=utf-8"})

    @app.before_request
    def bounded_body():
        # the size limit before any view runs, so a request is refused for its size whatever the view would
        # have answered first; a chunked body has no length to check, and Werkzeug cuts one silently at the
        # limit instead of refusing it, so it is refused as such (the pages and scripts send a length)
        if "chunked" in request.headers.get("Transfer-Encoding", "").lower():
            message = "send the request body with a Content-Length (chunked bodies are not accepted)"
            if request.path.startswith("/api/"):
                return jsonify(error=message), 411
            return f"411 Length Required: {message}\n", 411, {"Content-Type": "text/plain; charset=utf-8"}
        if (request.content_length or 0) > app.config["MAX_CONTENT_LENGTH"]:
            abort(413)

    @app.url_defaults
    def versioned_static(endpoint, values):
        # every url_for('static', ...) carries the file's version: cached for good, new when it changes
        if endpoint == "static" and "v" not in values:
            path = HERE / "static" / values.get("filename", "")
            if path.is_file():
                values["v"] = static_version(path)

    @app.get("/")
    def index():
        return redirect(url_for("bench.page") if bench is not None else url_for("review.page"))

    @app.context_processor
    def page_context():
        logged_in = auth_pages.logged_in()
        return {"logged_in": logged_in, "csrf": session.get("csrf", "") if logged_in else "",
                "has_scanner": bench is not None, "station_host": request.host}

    @app.after_request
    def headers(resp):
        # pages are local-only: no framing by other sites, no third-party anything
        resp.headers.setdefault("X-Frame-Options", "DENY")
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        resp.headers.setdefault("Referrer-Policy", "same-origin")  # no-referrer would make Origin "null"
        # the one inline style OpenSeadragon adds (no focus outline on touch screens) is allowed by
        # its hash, nothing else inline (tests/web/test_fragment_page.py checks the console)
        resp.headers.setdefault("Content-Security-Policy",
                                "default-src 'self'; img-src 'self' data:; "
                                f"style-src 'self' '{OPENSEADRAGON_STYLE_HASH}'; script-src 'self'; "
                                "frame-ancestors 'none'; form-action 'self'")
        if request.path.startswith("/api/"):
            resp.headers.setdefault("Cache-Control", "no-store")
        elif (request.path.startswith("/static/") and resp.status_code == 200
              and request.args.get("v") == static_version(HERE / "static" / request.path[len("/static/"):])):
            # a versioned URL names one content: no revalidation on the next page
            resp.headers["Cache-Control"] = "public, max-age=31536000, immutable"
        return resp

    @app.errorhandler(400)
    def bad_request(exc):
        return jsonify(error=getattr(exc, "description", "bad request")), 400

    @app.errorhandler(413)
    def too_large(exc):
        # the JSON API answers in JSON, as its other errors; a page's form keeps Flask's page
        if not request.path.startswith("/api/"):
            return exc
        limit = app.config["MAX_CONTENT_LENGTH"]
        return jsonify(error=f"the request body is larger than {limit // 1024} KiB, the most the pages accept"), 413

    return app

# --------------------------------------------------------------------------------------------
# running it
# --------------------------------------------------------------------------------------------
def catalogue_path(cfg: Mapping, settings: Mapping) -> Path:
    """Where the catalogue's index is kept (``[services.web] catalogue_db``)."""
    return Path(settings["catalogue_db"] or Path(cfg["storage"]["root"]) / "web" / "catalogue.sqlite")


def open_catalogue(cfg: Mapping, settings: Mapping, link: StationLink, review=None):
    """The catalogue and the feed follower that keeps it current (:func:`start_following` starts it).

    On the first round, and whenever the feed cannot be followed without a hole, the catalogue
    is rebuilt from storage.
    """
    from common.web.catalogue import FRAGMENT_EVENTS, JOIN_EVENTS, Catalogue

    from .bench import failures_by_fragment

    catalogue = Catalogue(catalogue_path(cfg, settings), link.storage,
                          proposals=getattr(review, "db_path", None))

    def rebuild(stream: str, last: int) -> int:
        n = catalogue.rebuild(failed=failures_by_fragment(link))
        log.info("catalogue: %d fragments indexed from storage (feed %s:%d)", n, stream, last)
        return last

    feed = FeedFollower(link, start=catalogue.position(), interval_s=float(settings["feed_interval_s"]),
                        on_gap=rebuild)
    feed.subscribe(FRAGMENT_EVENTS + JOIN_EVENTS,
                   lambda event, seq: catalogue.apply(event, seq, failed=failures_by_fragment(link)),
                   position=lambda stream, seq: (catalogue.flush(), catalogue.set_position(stream, seq)))

    return catalogue, feed


def start_following(catalogue, feed: FeedFollower) -> None:
    """Start the feed follower in the background (after the app is built, so every blueprint has
    subscribed); if the broker cannot be reached and the index is empty, index storage meanwhile."""
    def first_round():
        try:
            feed.poll()
        except Exception as exc:
            log.warning("catalogue: the broker cannot be reached (%s); indexing storage meanwhile", exc)
            if catalogue.counts()["total"] == 0:
                n = catalogue.rebuild()
                log.info("catalogue: %d fragments indexed from storage", n)
        feed.start()

    threading.Thread(target=first_round, name="catalogue-start", daemon=True).start()


def serve(cfg: Mapping, *, host: str | None = None, port: int | None = None, with_scanner: bool = True,
          ready: Callable[[str], None] | None = None, stop: threading.Event | None = None) -> int:
    """Run the web server until ``stop`` is set (or SIGINT/SIGTERM); returns an exit status."""
    from werkzeug.serving import make_server

    from common.web.review import ReviewData

    settings = web_settings(cfg)
    host = settings["host"] = host or settings["host"]   # the address bound (--host): the Host check follows it
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
    # verdicts and metadata edits go through the outbox too: one kept while the broker was away is sent when it is
    # back, with or without a scanner (the review host runs --no-scanner)
    link.start_drain()
    catalogue, feed = open_catalogue(cfg, settings, link, review)
    app = create_app(token=token, settings=settings, store_root=cfg["storage"]["root"], bench=bench, link=link,
                     review=review, catalogue=catalogue, feed=feed)
    start_following(catalogue, feed)
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
        feed.close()
        link.close()
        if bench is not None:
            bench.cancel()
    return 0


