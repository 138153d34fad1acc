"""tessera scanner — capture fragments at the bench (simulated flatbed by default, or SANE)."""

from __future__ import annotations

from common.config import add_config_arguments, config_from_arguments


def add_parser(sub) -> None:
    p = sub.add_parser("scanner", help="capture fragments at the bench and emit fragment.ready")
    p.add_argument("--count", type=int, default=None, metavar="N", help="fragments to capture (default [scanner] fragments)")
    p.add_argument("--no-wait", action="store_true", help="exit after capturing even if the outbox is not empty yet "
                                                          "(it is delivered at the next start)")
    add_config_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from common.bus.security import check
    from services.scanner import main

    cfg = config_from_arguments(args)
    check(cfg, "client")   # a bad key file stops the bench now (one line, naming it), not at its first drain
    return main(cfg, count=args.count, wait_drained=not args.no_wait)
