"""tessera web — the operator bench, match review and station status pages."""

from __future__ import annotations

import logging
import signal
import threading

from common.config import ConfigError, add_config_arguments, config_from_arguments


def add_parser(sub) -> None:
    p = sub.add_parser("web", help="serve the bench, review and status pages (http://127.0.0.1:8080)",
                       description="Serve the station's web pages. Listens on 127.0.0.1 unless "
                                   "[services.web] host (or --host) opens it to the lab network. "
                                   "Scanning, verdicts and re-runs need the access token it prints the place of.")
    p.add_argument("--host", help="interface to listen on (default [services.web] host, 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (default [services.web] port, 8080)")
    p.add_argument("--no-scanner", action="store_true",
                   help="review and status only: this machine does not drive the scanner")
    p.add_argument("--print-token", action="store_true", help="print the access token and exit")
    add_config_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from services import web

    log = logging.getLogger("tessera.web")
    try:
        cfg = config_from_arguments(args)
        settings = web.web_settings(cfg)
    except (ConfigError, web.WebConfigError) as exc:
        print(f"error: {exc}")
        return 2
    if args.print_token:
        token, path = web.station_token(cfg, settings)
        print(token)
        return 0
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        return web.serve(cfg, host=args.host, port=args.port, with_scanner=not args.no_scanner,
                         ready=lambda url: print(f"Tessera pages at {url}/", flush=True), stop=stop)
    except OSError as exc:
        log.error("cannot serve the pages: %s", exc)
        print(f"error: cannot listen ({exc.strerror or exc}); is another `tessera web` running on that port?")
        return 1
