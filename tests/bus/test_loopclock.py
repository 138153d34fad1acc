"""LoopClock: the broker's account of where its poll loop's time goes (CPU, run queue, GC, other)."""

from __future__ import annotations

import gc
import time

from common.bus.broker import LoopClock


def _iteration(clock: LoopClock, work) -> None:
    before = clock.mark()
    woke = clock.woke()
    work()
    clock.done(before, woke)


def _burn_cpu(seconds: float) -> None:
    t = time.thread_time()
    while time.thread_time() - t < seconds:
        pass


def test_cpu_work_is_counted_as_cpu_and_a_blocking_call_as_other():
    clock = LoopClock(window_s=60)
    try:
        _iteration(clock, lambda: _burn_cpu(0.03))
        w = clock.summary()["worst_ms"]
        assert w["cpu"] >= 30 and w["stall"] >= w["cpu"]
        assert w["other"] < w["cpu"]
        _iteration(clock, lambda: time.sleep(0.2))  # off CPU and not runnable: neither CPU nor run queue
        w = clock.summary()["worst_ms"]
        assert w["stall"] >= 200 and w["other"] >= 150 and w["cpu"] < 50
        s = clock.summary()
        assert s["iterations"] == 2 and s["cpu_s"] >= 0.03
    finally:
        clock.close()


def test_garbage_collection_inside_an_iteration_is_counted():
    clock = LoopClock(window_s=60)
    try:
        junk = [[i] for i in range(200000)]
        _iteration(clock, lambda: gc.collect())
        del junk
        assert clock.summary()["worst_ms"]["gc"] > 0
        assert clock.summary()["gc_s"] > 0
    finally:
        clock.close()


def test_the_worst_iteration_is_forgotten_after_the_window():
    clock = LoopClock(window_s=0.3)
    try:
        _iteration(clock, lambda: time.sleep(0.15))
        assert clock.summary()["worst_ms"]["stall"] >= 150
        time.sleep(0.35)
        _iteration(clock, lambda: None)
        assert clock.summary()["worst_ms"]["stall"] < 150
        time.sleep(0.35)
        assert clock.summary()["worst_ms"] is None
    finally:
        clock.close()
