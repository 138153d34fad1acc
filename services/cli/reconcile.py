"""tessera reconcile — queue what is missing on storage, per stage and face (common/bus/reconcile.py), or made by
an older version of its stage (features, renderer), skipping fragments with a job already queued or in flight."""

from __future__ import annotations

from common.config import add_config_arguments, config_from_arguments


def add_parser(sub) -> None:
    p = sub.add_parser("reconcile", help="find fragments whose later stages are missing on storage (or made by an older version of "
                                           "the stage) and queue them")
    p.add_argument("--dry-run", action="store_true", help="only list what would be queued")
    add_config_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from common.bus.client import BrokerClient, BrokerUnavailable
    from common.bus.reconcile import missing_stages
    from common.store import Store
    config = config_from_arguments(args)
    st = config["storage"]
    store = Store(st["root"], file_locking=st["file_locking"], create=False)
    if not store.available():
        print(f"error: storage root {store.root} is not reachable")
        return 1
    if not args.dry_run:
        for rel in store.sweep_temporary():
            print(f"removed {rel}: left by a writer that died mid-write")
    try:
        with BrokerClient.from_config(config) as bus:
            pending = bus.pending()
    except BrokerUnavailable as exc:
        if not args.dry_run:
            print(f"error: {exc}")
            return 1
        print(f"warning: {exc}; jobs already queued or in flight are not known, so they are listed too")
        pending = []
    from common.matching.proposals import proposals_path
    db = proposals_path(store.root, (config.get("services", {}).get("matcher", {}) or {}).get("db"))
    from services.features import VERSION as FEATURES_VERSION
    from services.renderer import VERSION as RENDERER_VERSION
    from services.solver import VERSION as SOLVER_VERSION
    # made by an older stage counts as missing: a face drawn before a fix of the renderer is drawn again, a
    # face solved before a fix of the solver is solved again from its scans
    events = missing_stages(store, pending=pending, matcher_db=db,
                            versions={"rgbn": SOLVER_VERSION, "features": FEATURES_VERSION,
                                      "renders": RENDERER_VERSION})
    for e in events:
        print(f"{e['fragment']:<12} {e['type']:<15} {e.get('face', ''):<6} {e['artifact']['path']}  "
              f"(missing {', '.join(e['missing'])})")
    if args.dry_run or not events:
        print(f"{len(events)} event(s) {'would be ' if args.dry_run else ''}queued")
        return 0
    try:
        with BrokerClient.from_config(config) as bus:
            bus.submit_many(events)
    except BrokerUnavailable as exc:
        print(f"error: {exc}")
        return 1
    print(f"{len(events)} event(s) queued")
    return 0
