"""tessera broker — run the broker (queues, journal, event feed) in the foreground."""

from __future__ import annotations

from common.config import add_config_arguments, config_from_arguments


def add_parser(sub) -> None:
    p = sub.add_parser("broker", help="run the broker: job queues, journal, event feed")
    add_config_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from services.broker import main
    return main(config_from_arguments(args))
