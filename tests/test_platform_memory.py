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


@pytest.mark.parametrize("user, expected", [(None, "False"), ("1", "True")])
def test_the_command_turns_numpys_huge_pages_off_unless_the_user_chose(user, expected):
    """prefer_small_pages, called before numpy's import (as cli.run does), leaves numpy
    allocating without MADV_HUGEPAGE; a user's own NUMPY_MADVISE_HUGEPAGE wins. Read back
    through numpy's setter, which returns the setting it replaces."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if user is not None:
        env["NUMPY_MADVISE_HUGEPAGE"] = user
    code = ("from c1mesh.core.platform_memory import prefer_small_pages; prefer_small_pages(); "
            "import numpy; from numpy._core.multiarray import _set_madvise_hugepage; "
            "print(_set_madvise_hugepage(False))")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == expected
