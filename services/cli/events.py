"""tessera events — print the event feed as JSON lines (the reference subscriber).

Each line is one event document plus ``seq`` and ``stream``. With ``--since N`` every retained
event after sequence N is printed first; the subscriber fills any gap from the broker, so a
client that remembers the last ``seq`` it saw and restarts with ``--since`` misses nothing.
"""

from __future__ import annotations

import json
import sys

from common.config import add_config_arguments, config_from_arguments
from common.messages import to_json


def add_parser(sub) -> None:
    p = sub.add_parser("events", help="print the event feed as JSON lines")
    p.add_argument("--since", type=int, default=None, metavar="N", help="first print every event after sequence N")
    p.add_argument("--type", action="append", default=None, metavar="T", help="only events of this type (repeatable)")
    p.add_argument("--idle-exit", type=float, default=None, metavar="S", help="exit after S seconds without events")
    p.add_argument("--count", type=int, default=None, metavar="K", help="exit after K events")
    add_config_arguments(p)
    p.set_defaults(func=run)


def _plain(obj):
    if isinstance(obj, bytes):
        return obj.hex()
    return str(obj)


def event_line(seq: int, stream: str | None, event: dict) -> str:
    """One JSON line for an event; an event JSON cannot hold (e.g. nested deeper than the encoder
    goes, from a journal older than the broker's depth check) gives a line saying so, never a crash."""
    try:
        return to_json({"seq": seq, "stream": stream, **event}, default=_plain)   # a NaN ("not measured") as null
    except (RecursionError, ValueError, TypeError) as exc:
        return json.dumps({"seq": seq, "stream": stream, "type": str(event.get("type", "?"))[:64],
                           "uid": str(event.get("uid", ""))[:64], "error": f"event not representable as JSON: "
                                                                           f"{type(exc).__name__}"})


def run(args) -> int:
    from common.bus.feed import FeedSubscriber
    config = config_from_arguments(args)
    n = 0
    with FeedSubscriber.from_config(config, since=args.since, types=args.type) as sub:
        try:
            for seq, event in sub.events(timeout_s=args.idle_exit):
                sys.stdout.write(event_line(seq, sub.stream, event) + "\n")
                sys.stdout.flush()
                n += 1
                if args.count is not None and n >= args.count:
                    break
        except BrokenPipeError:  # `tessera events | head`: the reader left
            import os
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no complaint at exit
            return 0
    return 0
