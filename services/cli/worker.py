"""tessera worker <service> — run one stage worker (solver, features, matcher, renderer, noop)."""

from __future__ import annotations

import logging

from common.config import add_config_arguments, config_from_arguments


def add_parser(sub) -> None:
    p = sub.add_parser("worker", help="run one stage worker for the broker")
    p.add_argument("service", help="stage module under services/: solver, features, matcher, renderer, noop")
    add_config_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from common.bus.worker import run_worker
    config = config_from_arguments(args)
    try:
        return run_worker(args.service, config)
    except ValueError as exc:
        logging.getLogger("tessera.worker").error("%s", exc)
        return 2
