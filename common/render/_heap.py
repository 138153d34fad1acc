"""Freed image arrays reused during a rendering instead of being handed back to the kernel.

A rendering allocates and frees arrays of 50-200 MB dozens of times (a smoothed normal map at
12 Mpx is 144 MB). glibc serves every block above its mmap threshold (at most 32 MB) with a
fresh ``mmap`` and returns it with ``munmap`` when freed, so each new array page-faults all its
pages again, and the kernel zeroes them. On the shared station machine this was measured at a
quarter of a rendering's CPU time: the segments recipe at 12 Mpx, 245,000-252,000 minor page
faults and 4.9-6.2 s of system time beside 11.9-12.0 s of user time; with mmap off, 39,000
faults, 1.6-2.1 s system, 11.4 s user (``tests/bench/bench_render.py --child recipe-segments --size
3464``, ``GLIBC_TUNABLES=glibc.malloc.mmap_max=0``, load 15-18; ``--no-heap-reuse`` measures this
module's effect the same way).

:func:`reuse_freed_memory` turns glibc's mmap off for the duration of a rendering, so large
arrays come from the heap and a freed one is reused by the next, and afterwards restores the
default and trims the heap (``malloc_trim``), so the process gives the memory back. It changes
no result, only where the memory comes from. Elsewhere than glibc it does nothing.

It also stops numpy from asking for transparent huge pages (``madvise(MADV_HUGEPAGE)`` on arrays of
4 MB and more) while it is open. Where the kernel compacts memory to find a huge page at the fault
(``/sys/kernel/mm/transparent_hugepage/defrag`` = ``madvise``, Debian's default), that compaction
is system time that varies from run to run: on this machine, quiet, at 12 Mpx the segments recipe took
3.0-3.6 s of system time with huge pages and 0.95-1.2 s without (user time the same, 8.8-9.2 s), the
specular style 1.9-2.0 s and 0.64-0.69 s (``NUMPY_MADVISE_HUGEPAGE=1|0``, two runs each).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import threading

#: glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
#: glibc's defaults, restored afterwards: 65536 mmapped blocks, a 128 KiB trim threshold.
_DEFAULT_MMAP_MAX, _DEFAULT_TRIM_THRESHOLD = 65536, 128 * 1024
#: Free memory kept at the heap's top during a rendering (not trimmed between arrays), bytes: all of
#: it (glibc's largest threshold). Keeping free heap never raises the peak — what is kept was mapped
#: at the peak already — and a freed array is then always there for the next one: trimmed to 256 MiB,
#: a 12-Mpx colour_relief drawing page-faulted 248,000 times instead of 195,000, and a 51-Mpx gooch
#: drawing in tiles (each tile's arrays the next one's) 1.14 million times instead of 251,000 for a
#: heap of 0.8 GB.
_KEEP_BYTES = 2 ** 31 - 1

_lock = threading.Lock()
_depth = 0
_libc = None
_hugepage_before = None


def _glibc():
    global _libc
    if _libc is None:
        try:
            lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            lib.mallopt.argtypes, lib.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
            lib.malloc_trim.argtypes, lib.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
            _libc = lib
        except (OSError, AttributeError):   # not glibc (musl, macOS): nothing to tune
            _libc = False
    return _libc


@contextlib.contextmanager
def reuse_freed_memory():
    """Context manager: large allocations come from the heap (glibc ``M_MMAP_MAX = 0``, its free
    memory kept, :data:`_KEEP_BYTES`) and numpy asks for no huge pages while it is open; on leaving
    the outermost one the defaults are restored and the free heap is returned to the kernel.
    Re-entrant; the heap part is a no-op without glibc."""
    global _depth, _hugepage_before
    lib = _glibc()
    with _lock:
        _depth += 1
        if _depth == 1:
            _hugepage_before = _set_hugepage(False)
            if lib:
                lib.mallopt(_M_MMAP_MAX, 0)
                lib.mallopt(_M_TRIM_THRESHOLD, _KEEP_BYTES)
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _set_hugepage(_hugepage_before)
                if lib:
                    lib.mallopt(_M_MMAP_MAX, _DEFAULT_MMAP_MAX)
                    lib.mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM_THRESHOLD)
                    lib.malloc_trim(0)


def _set_hugepage(enabled):
    """numpy's huge-page advice on (True) or off (False); the previous setting (None: numpy has no
    such switch, and ``enabled`` None leaves it alone)."""
    try:
        from numpy._core import multiarray
    except ImportError:   # numpy 1.x
        from numpy.core import multiarray
    if enabled is None or not hasattr(multiarray, "_set_madvise_hugepage"):
        return None
    return bool(multiarray._set_madvise_hugepage(bool(enabled)))
