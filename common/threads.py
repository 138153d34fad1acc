"""One BLAS thread for the many small matrix products of the solver and the matcher.

OpenBLAS's threads only contend on products this size (tall-and-skinny or a few thousand
elements): measured 5 ms vs 0.8 ms CPU per solver product on a shared 2-core machine, and a
matcher proposal 2× slower. The threadpool controller is made once: finding the BLAS libraries
costs ~0.3 ms per call (more under load), which a per-call ``threadpool_limits`` would pay.
"""

from __future__ import annotations

import contextlib

_CONTROLLER = None


def one_blas_thread():
    """Context manager limiting BLAS to one thread (a no-op without threadpoolctl)."""
    global _CONTROLLER
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - scikit-learn brings it
        return contextlib.nullcontext()
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")
