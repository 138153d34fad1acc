"""The ``tessera`` command.

Each sub-command lives in its own module of this package and exposes
``add_parser(subparsers)``, which adds its parser and sets ``func`` (called with the parsed
arguments; returns the exit status). Adding a command = adding a module and its name below.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

# module names in services/cli/, in the order shown by --help
COMMANDS = [
    "station", "broker", "worker", "scanner", "events", "status", "reconcile",
    "calibrate", "ps", "imports", "export", "synth", "features", "evaluate", "render", "web", "keys", "perf",
    "reconstruct",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tessera", description="Fragment-scanning station for archaeology.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"services.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"services.cli.{name}":
                continue  # command not part of this build
            raise
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from common.bus.security import SecurityError
    from common.config import ConfigError
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ConfigError, SecurityError) as exc:
        # a bad setting or key file: one line naming it (DESIGN: "a bad config fails at start with
        # a clear message"; docs/security.md), not a traceback
        print(f"tessera {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
