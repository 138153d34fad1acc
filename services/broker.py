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
    _group_priority(nice)
    return os.getpriority(os.PRIO_PROCESS, 0)


def _group_priority(nice: int) -> None:
    """With Linux autogroups (``kernel.sched_autogroup_enabled``) CPU time is shared between
    sessions first, and a thread's nice value counts only inside its session's group.
    ``tessera station`` starts the broker and every worker in a session of its own, so there the
    broker's group is the broker alone: give the group ``nice`` too. In a shared session (a
    terminal, a test) the group is left as it is."""
    if os.getsid(0) != os.getpid():
        return
    try:
        with open("/proc/self/autogroup", "w") as fh:
            fh.write(str(nice))
    except FileNotFoundError:  # no autogroups (or not Linux): nothing to do
        pass
    except OSError as exc:
        log.warning("cannot give the broker's session group nice %d (%s)", nice, exc.strerror)


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
