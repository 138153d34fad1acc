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
    p.add_argument("--cut-tiles", nargs="*", metavar="FRAGMENT",
                   help="cut the tile pyramids (albedo, normals, renders; the fragment page's relight tiles) of these "
                        "fragments, or of every fragment "
                        "on storage when none is named, and exit (pages otherwise cut them on first view)")
    p.add_argument("--rebuild-catalogue", action="store_true",
                   help="rebuild the catalogue's index from storage and the proposal store, and exit")
    add_config_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from common.bus.security import SecurityError, check as check_keys
    from services import web

    log = logging.getLogger("tessera.web")
    try:
        cfg = config_from_arguments(args)
        settings = web.web_settings(cfg)
        check_keys(cfg, "client")   # a bad key file stops the pages now, not at their first write to the broker
    except (ConfigError, web.WebConfigError, SecurityError) as exc:
        print(f"error: {exc}")
        return 2
    if args.print_token:
        token, path = web.station_token(cfg, settings)
        print(token)
        return 0
    if args.cut_tiles is not None:
        return cut_tiles(cfg, args.cut_tiles)
    if args.rebuild_catalogue:
        return rebuild_catalogue(cfg, settings)
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


def cut_tiles(cfg, fragments: list[str]) -> int:
    """Cut every pyramid of the named fragments (all on storage when none), with a progress bar."""
    from common.imports.export import fragment_ids
    from common.imports.progress import ProgressBar
    from common.store import Store
    from common.web.relight import cut_archive_tiles
    from common.web.tiles import face_sources

    store = Store(cfg["storage"]["root"], create=False)
    ids = fragments or fragment_ids(store)
    sources = [rel for fid in ids for src in face_sources(store, fid).values()
               for rel in [src["rgbn"], *src["renders"].values()]]
    missing = [fid for fid in fragments if not face_sources(store, fid)]
    if missing:
        print(f"error: no face on storage for {', '.join(missing)}")
        return 2
    bar, failed = ProgressBar(len(sources), "cut tiles"), 0
    for i, rel in enumerate(sources):
        try:
            bar.update(i + 1, f"{rel} ({cut_archive_tiles(store, rel)} tiles)")
        except Exception as exc:   # one bad artifact must not stop the others
            failed += 1
            bar.update(i + 1, f"{rel}: {exc}")
    bar.close()
    print(f"{len(sources) - failed} pyramids ready, {failed} failed")
    return 1 if failed else 0


def rebuild_catalogue(cfg, settings) -> int:
    from common.imports.progress import ProgressBar
    from common.store import Store
    from common.web.catalogue import Catalogue
    from common.web.review import ReviewData
    from services import web

    store = Store(cfg["storage"]["root"], create=False)
    path = web.catalogue_path(cfg, settings)
    cat = Catalogue(path, store, proposals=ReviewData.from_config(cfg).db_path)
    bar = ProgressBar(len(cat.fragment_ids()), "catalogue")
    n = cat.rebuild(progress=lambda done, total, fid: bar.update(done, fid))
    bar.close()
    print(f"{n} fragments in the catalogue ({path})")
    return 0
