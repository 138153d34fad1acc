"""The broker process: parse config -> CPU priority -> bind -> poll loop until SIGTERM/SIGINT."""

from __future__ import annotations

import logging
import os
import signal
import threading

from common.bus.broker import Broker

log = logging.getLogger("tessera.broker")


def set_priority(nice: int) -> int:
    """Run this process at ``nice`` (``[broker] nice``); returns the nice value it runs at.

    The broker is the station's latency-critical process (STATUS within 100 ms, heartbeats): on a
    loaded machine its poll loop waits for a CPU far longer than it works (docs/performance.md),
    so it asks for a higher priority than the compute workers. Set before any thread starts, so
    the journal writer and ZeroMQ's I/O thread inherit it (on Linux a nice value is per thread, so
    threads already running, e.g. a BLAS pool started at import, are set one by one).
    A value below the current one needs root, ``CAP_SYS_NICE`` or the unit's ``Nice=``/``LimitNICE=``;
    without it the broker runs as it is and says so.
    """
    current = os.getpriority(os.PRIO_PROCESS, 0)
    if nice != current:
        try:
            tids = [int(t) for t in os.listdir("/proc/self/task")]
        except OSError:  # not Linux: the process
            tids = [0]
        try:
            for tid in sorted(tids, key=lambda t: t != threading.get_native_id()):  # this thread first
                try:
                    os.setpriority(os.PRIO_PROCESS, tid, nice)
                except ProcessLookupError:  # a thread that ended meanwhile
                    pass
        except OSError as exc:
            log.warning("cannot run at nice %d (%s; needs root, CAP_SYS_NICE or Nice=/LimitNICE= in the unit): "
                        "running at %d, so STATUS may answer late on a loaded machine", nice, exc.strerror, current)
    return os.getpriority(os.PRIO_PROCESS, 0)


def main(config: dict) -> int:
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    nice = set_priority(int(config["broker"]["nice"]))
    broker = Broker(config)
    broker.bind()
    log.info("broker runs at nice %d", nice)
    broker.run(stop)
    return 0
