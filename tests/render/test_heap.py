import resource
import sys

import numpy as np
import pytest

from common.render._heap import _glibc, reuse_freed_memory

PAGES = (64 << 20) // 4096   # a 64 MiB array: above glibc's largest mmap threshold (32 MiB)


def _faults_of_a_fresh_array() -> int:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(64 << 20, np.uint8)   # touches every page
    del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


@pytest.fixture
def small_pages():
    """numpy's transparent huge pages off for the test, so a page fault is 4 KiB (countable)."""
    from numpy._core import multiarray

    was = multiarray._get_madvise_hugepage()
    multiarray._set_madvise_hugepage(False)
    yield
    multiarray._set_madvise_hugepage(was)


@pytest.mark.skipif(not sys.platform.startswith("linux") or not _glibc(), reason="glibc's malloc only")
def test_freed_arrays_are_reused_inside_a_rendering_and_returned_after(small_pages):
    outside = [_faults_of_a_fresh_array() for _ in range(2)]
    assert min(outside) > 0.9 * PAGES          # mmap'd afresh: every page faulted, every time
    with reuse_freed_memory():
        with reuse_freed_memory():              # re-entrant (render -> render_tiled)
            _faults_of_a_fresh_array()
        inside = [_faults_of_a_fresh_array() for _ in range(3)]
    assert max(inside) < 0.1 * PAGES           # the freed array's pages are reused
    after = [_faults_of_a_fresh_array() for _ in range(2)]
    assert min(after) > 0.9 * PAGES            # defaults back: the memory went back to the kernel
