import json
import subprocess
import sys

import pytest

from common.render._heap import _glibc

PAGES = (64 << 20) // 4096   # a 64 MiB array: above glibc's largest mmap threshold (32 MiB)

# Measured in a fresh interpreter: a process that has rendered before keeps free chunks in its heap
# (freed arrays that were not at its top), so there a "fresh" array may come from the heap already
# faulted in, whatever this module does (seen in the full test suite: 0 faults for 64 MiB).
_MEASURE = """
import json, resource
import numpy as np
from numpy._core import multiarray
from common.render._heap import reuse_freed_memory

multiarray._set_madvise_hugepage(False)   # 4 KiB pages, so a page fault is countable

def faults_of_a_fresh_array():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(64 << 20, np.uint8)   # touches every page
    del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

outside = [faults_of_a_fresh_array() for _ in range(2)]
with reuse_freed_memory():
    with reuse_freed_memory():              # re-entrant (render -> render_tiled)
        faults_of_a_fresh_array()
    inside = [faults_of_a_fresh_array() for _ in range(3)]
after = [faults_of_a_fresh_array() for _ in range(2)]
print(json.dumps({"outside": outside, "inside": inside, "after": after}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or not _glibc(), reason="glibc's malloc only")
def test_freed_arrays_are_reused_inside_a_rendering_and_returned_after():
    out = subprocess.run([sys.executable, "-c", _MEASURE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    faults = json.loads(out.stdout.strip().splitlines()[-1])
    assert min(faults["outside"]) > 0.9 * PAGES   # mmap'd afresh: every page faulted, every time
    assert max(faults["inside"]) < 0.1 * PAGES    # the freed array's pages are reused
    assert min(faults["after"]) > 0.9 * PAGES     # defaults back: the memory went back to the kernel


def test_numpy_asks_for_no_huge_pages_during_a_rendering_and_as_before_after():
    # huge-page compaction at the fault was most of a rendering's erratic system time (_heap)
    from numpy._core import multiarray

    from common.render._heap import reuse_freed_memory

    was = multiarray._set_madvise_hugepage(True)
    try:
        with reuse_freed_memory():
            with reuse_freed_memory():
                assert multiarray._get_madvise_hugepage() is False
            assert multiarray._get_madvise_hugepage() is False
        assert multiarray._get_madvise_hugepage() is True
    finally:
        multiarray._set_madvise_hugepage(was)
