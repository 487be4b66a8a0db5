"""c1mesh.core.platform_memory: the one module that asks the C library and the OS about memory.

Ground truth: the kernel's count of this process's resident pages (/proc/self/statm)."""
from __future__ import annotations

import os
import sys

import pytest

from c1mesh.core.platform_memory import madvise, peak_rss_mb, release_free_heap

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc and /proc are Linux's")


def _resident_bytes() -> int:
    with open("/proc/self/statm") as file:
        return int(file.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def test_release_free_heap_returns_the_pages_that_freed_chunks_below_the_top_hold():
    blocks = [bytearray(4000) for _ in range(25_000)]       # 100 MB of heap chunks
    pin = bytearray(4000)                                    # the heap's top stays in use
    held = _resident_bytes()
    del blocks
    assert release_free_heap()
    assert _resident_bytes() < held - 60e6
    assert len(pin) == 4000


def test_peak_rss_is_at_least_what_is_resident_now():
    assert peak_rss_mb() * 1024 * 1024 >= 0.99 * _resident_bytes()


def test_madvise_is_callable_here():
    assert madvise is not None
