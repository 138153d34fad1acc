"""Stress tests reuse the bus tests' throw-away station (real processes on loopback)."""

from tests.bus.conftest import make_station  # noqa: F401  (fixture re-exported for this folder)
