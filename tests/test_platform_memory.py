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


def test_a_held_heap_keeps_a_freed_array_until_released():
    """hold_freed_heap (the command's): a freed 16 MB array stays resident for the next
    ones (glibc's default maps it alone and unmaps it on free), release_free_heap gives it
    back; the settings reach the processes it starts (GLIBC_TUNABLES), which then keep
    their tasks' heap (release_task_heap does nothing). Resident pages from
    /proc/self/statm, in a child so this process's allocator is left as it was."""
    import subprocess

    code = """if True:
        import os
        from c1mesh.core.platform_memory import (HELD_HEAP, heap_held, hold_freed_heap, release_free_heap,
                                                 release_task_heap)
        def resident():
            with open("/proc/self/statm") as file:
                return int(file.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        def freed_block_kept():
            block = bytearray(16 << 20)          # zero-filled: every page resident
            before = resident()
            del block
            return resident() > before - 8e6
        assert not heap_held() and not freed_block_kept()
        assert release_task_heap()
        hold_freed_heap()
        assert heap_held() and os.environ["GLIBC_TUNABLES"] == HELD_HEAP
        assert freed_block_kept()
        assert not release_task_heap()
        held = resident()
        assert release_free_heap() and resident() < held - 8e6
        print("ok")
    """
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr



def test_a_held_heap_serves_one_threads_frees_to_another():
    """With the held heap the threads share one arena: 16 MB a background thread allocated
    and freed are what the main thread's next 16 MB reuse. With the same thresholds but an
    arena per thread (glibc's default), the freed block stays in the thread's arena and the
    main thread's is new: 16 MB more resident. In children, so this process's allocator is
    left as it was."""
    import subprocess

    code = """if True:
        import os, sys, threading
        from c1mesh.core import platform_memory as memory
        def resident():
            with open("/proc/self/statm") as file:
                return int(file.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        if sys.argv[1] == "held":
            memory.hold_freed_heap()
        else:
            memory._mallopt(memory._M_MMAP_THRESHOLD, memory.HELD_MMAP_THRESHOLD)
            memory._mallopt(memory._M_TRIM_THRESHOLD, memory.HELD_TRIM_THRESHOLD)
        def background():
            block = bytearray(16 << 20)          # zero-filled: every page resident
            del block
        thread = threading.Thread(target=background)
        thread.start()
        thread.join()
        before = resident()
        again = bytearray(16 << 20)
        print(resident() - before > 8e6)
    """
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "MALLOC_ARENA_MAX")}
    grew = {}
    for mode in ("held", "arena per thread"):
        done = subprocess.run([sys.executable, "-c", code, mode], env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        grew[mode] = done.stdout.strip()
    assert grew == {"held": "False", "arena per thread": "True"}


def test_a_held_heap_serves_a_large_array_from_what_an_earlier_one_freed():
    """Above glibc's largest mmap threshold (32 MiB) an array is mapped on its own; freed,
    it is unmapped, and the next one faults every page in again (16k faults for 64 MB).
    The command's held heap maps none (HELD_MMAPS): the second 64 MB come from the freed
    first and fault in almost nothing. In children, so this process's allocator is left
    as it was."""
    import subprocess

    code = """if True:
        import resource, sys
        from c1mesh.core import platform_memory as memory
        if sys.argv[1] == "held":
            memory.hold_freed_heap()
        else:
            memory._mallopt(memory._M_MMAP_THRESHOLD, memory.HELD_MMAP_THRESHOLD)
            memory._mallopt(memory._M_TRIM_THRESHOLD, memory.HELD_TRIM_THRESHOLD)
        first = bytearray(64 << 20)              # zero-filled: every page touched
        del first
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        again = bytearray(64 << 20)
        print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "MALLOC_ARENA_MAX")}
    faults = {}
    for mode in ("held", "mapped"):
        done = subprocess.run([sys.executable, "-c", code, mode], env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        faults[mode] = int(done.stdout)
    pages = (64 << 20) // 4096
    assert faults["mapped"] > pages // 2 and faults["held"] < pages // 20, faults


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="a BLAS worker thread needs a second core")
def test_idle_blas_threads_sleep_instead_of_spinning():
    """After a product in two BLAS threads, OpenBLAS's worker spins (about 0.1 s by default)
    before it sleeps: CPU time runs on while the caller sleeps. With sleep_idle_blas,
    called before numpy's import as the command does, it sleeps at once. In children, so
    that this process's OpenBLAS keeps its setting."""
    import subprocess

    code = """if True:
        import sys, time
        from c1mesh.core.platform_memory import sleep_idle_blas
        if sys.argv[1] == "sleep":
            sleep_idle_blas()
        import numpy as np
        from threadpoolctl import threadpool_limits
        a = np.random.default_rng(0).random((800, 800))
        with threadpool_limits(2, user_api="blas"):
            spent = []
            for _ in range(3):
                a @ a
                start = time.process_time()
                time.sleep(0.3)
                spent.append(time.process_time() - start)
        print(min(spent))
    """
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_THREAD_TIMEOUT"}
    spent = {}
    for mode in ("sleep", "default"):
        done = subprocess.run([sys.executable, "-c", code, mode], env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        spent[mode] = float(done.stdout)
    assert spent["default"] > 0.02 and spent["sleep"] < 0.01, spent
