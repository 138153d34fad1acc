"""The broker process: parse config -> bind -> poll loop until SIGTERM/SIGINT."""

from __future__ import annotations

import signal
import threading

from common.bus.broker import Broker


def main(config: dict) -> int:
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    broker = Broker(config)
    broker.bind()
    broker.run(stop)
    return 0
