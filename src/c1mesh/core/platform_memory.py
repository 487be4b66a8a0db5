"""What this process asks the operating system and the C library about its memory: the
one module that calls them (ctypes, resource), so the rest of c1mesh stays portable
and every such call has one place to fail soft.

- `madvise`: the C library's madvise, or None where it cannot be called (not Linux, no
  symbol); c1mesh.engine.refine pre-faults fresh arrays with it.
- `release_free_heap`: glibc keeps the heap that large frees leave (measured, the tiled
  fit of a 4M-point LAZ at --memory 300M: 80 MB of free heap held between stages), and a
  later tile's allocations do not always fit in it, so the peak climbs with the number
  of tiles run; malloc_trim(0) hands it back. Nothing happens without glibc.
- `hold_freed_heap`, `release_task_heap`: the command has glibc keep the heap a task
  frees for the next task's arrays (no array mapped on its own in the command's process,
  a 32 MiB mmap threshold in the processes it starts, no automatic trim), so
  a tiled fit's tasks stop faulting their pages in again after every task's
  malloc_trim; release_free_heap still runs at every stage's end.
- `peak_rss_mb`: the process's peak resident set so far.
- `prefer_small_pages`: numpy asks the kernel for transparent huge pages on every array
  of 4 MiB or more; on machines where a huge-page fault is slow (this project's VMs:
  up to ~100 µs each, zeroing 2 MiB) the fit's fresh arrays cost more in faults than in
  arithmetic. The `c1mesh` command turns that off for itself and the processes it starts.
- `sleep_idle_blas`: OpenBLAS's idle threads spin before they sleep; the command has them
  sleep at once, so that they leave the cores to c1mesh's own threads.
"""
from __future__ import annotations

import ctypes
import os
import resource
import sys


def _libc():
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


def _libc_function(name: str, argtypes: list, restype):
    """The C library's function `name` with its signature set, or None (not Linux, no
    such symbol)."""
    libc = _libc() if sys.platform.startswith("linux") else None
    function = getattr(libc, name, None)
    if function is None:
        return None
    function.argtypes, function.restype = argtypes, restype
    return function


madvise = _libc_function("madvise", [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int], ctypes.c_int)
_malloc_trim = _libc_function("malloc_trim", [ctypes.c_size_t], ctypes.c_int)
_mallopt = _libc_function("mallopt", [ctypes.c_int, ctypes.c_int], ctypes.c_int)

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -3, -4, -8
"""glibc's mallopt parameters (malloc.h)."""
HELD_MMAP_THRESHOLD = 32 << 20
"""Arrays from this size up are mapped on their own and unmapped when freed, as glibc does
by default above its (adaptive) threshold; 32 MiB is the largest glibc allows."""
HELD_MMAPS = 0
"""Arrays the command's own process maps on their own (glibc's M_MMAP_MAX): none, so that
its arrays of HELD_MMAP_THRESHOLD and more also come from the heap and reuse what earlier
ones freed, instead of being unmapped when freed and faulted in afresh when the next is
made (hold_freed_heap says what that saved). Set in this process only: the processes it
starts keep glibc's own maps above the threshold (HELD_HEAP), because a tiled fit's workers
were not faster without them."""
HELD_TRIM_THRESHOLD = (1 << 31) - 1
"""Free heap glibc keeps at its top before trimming by itself: never, in practice."""
HELD_ARENAS = 1
"""Heaps (glibc arenas) the threads share: one, so that what one thread frees serves the next
allocation of any other."""
HELD_HEAP = (f"glibc.malloc.mmap_threshold={HELD_MMAP_THRESHOLD}:"
             f"glibc.malloc.trim_threshold={HELD_TRIM_THRESHOLD}:glibc.malloc.arena_max={HELD_ARENAS}")
"""The same settings as glibc tunables, for the processes the command starts."""


def release_free_heap() -> bool:
    """Give the C heap's free pages back to the system (glibc malloc_trim(0)); False
    where there is no such call. Changes no live memory, only what RSS counts."""
    if _malloc_trim is None:
        return False
    _malloc_trim(0)
    return True


def hold_freed_heap() -> None:
    """Have glibc keep the heap this process frees, and the processes it starts (the
    tiled fit's local workers, through GLIBC_TUNABLES, unless the user set their own),
    for their later allocations: arrays below HELD_MMAP_THRESHOLD come from the heap,
    and freed heap stays until release_free_heap, which the tiled fit runs at every
    stage's end. release_task_heap then keeps a task's freed heap for the next task.

    Why: glibc's default hands freed memory back as it goes (an adaptive threshold), and
    the tiled fit trimmed after every task; every task then faulted its arrays' pages in
    afresh, at about 2 µs a page on this project's VMs. Measured, the 4M-point LAZ at
    --memory 400M, one process (TiledRun(jobs=1)): 6.1M page faults and 16.9 s of system
    time -> 0.18M and 5.7 s, user time alike, peak RSS 270 -> 269 MB. The threads share
    one arena (HELD_ARENAS): glibc gives each thread that allocates while another holds the
    heap an arena of its own, whose freed heap no other thread reuses, so a background
    thread's arrays (the smoothing's data term, core.threads.blocks_ahead) stayed resident
    beside the main thread's: the lattice DTM job's peak RSS 1.459 -> 1.419-1.431 GB, the 1M
    LAZ fit's 1.605 -> 1.585-1.588 GB, wall times alike (alternating runs, 2 threads). This
    process also maps no array on its own (HELD_MMAPS): glibc's largest threshold (32 MiB)
    left a 1M-point fit's big arrays (the stencil, the spline's coefficients, the refined
    mesh's blocks) mapped and unmapped one by one. Alternating runs, 2 threads: the DTM job
    (lattice, --smooth auto) 550k -> 350k page faults, 1.6-1.8 -> 1.2-1.3 s of system time;
    the 1M LAZ fit 5.00-5.17 -> 4.61-4.95 s and 1.55 -> 1.46-1.51 GB; 1M points with normals
    at level 4 5.95-6.34 -> 5.70-6.00 s and 1.47-1.51 -> 1.46 GB; the 4M tiled fit at
    --memory 2G alike (25.7-27.1 s, the parent 268-291 MB). Like prefer_small_pages, only
    the command calls it: a library does not change its host program's allocator."""
    os.environ.setdefault("GLIBC_TUNABLES", HELD_HEAP)
    if _mallopt is not None:
        _mallopt(_M_MMAP_THRESHOLD, HELD_MMAP_THRESHOLD)
        _mallopt(_M_TRIM_THRESHOLD, HELD_TRIM_THRESHOLD)
        _mallopt(_M_ARENA_MAX, HELD_ARENAS)
        _mallopt(_M_MMAP_MAX, HELD_MMAPS)


def heap_held() -> bool:
    """Whether this process runs with hold_freed_heap's settings: it called it, or was
    started with its GLIBC_TUNABLES by a process that did."""
    return os.environ.get("GLIBC_TUNABLES") == HELD_HEAP


def release_task_heap() -> bool:
    """After a task (c1mesh.survey.distributed): release_free_heap, unless the heap is held
    (heap_held), when the next task reuses it instead; True when released."""
    return not heap_held() and release_free_heap()


def peak_rss_mb() -> float:
    """The process's peak resident set size so far, in MB (Linux reports KiB)."""
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def prefer_small_pages() -> None:
    """Have numpy, imported after this in this process and in the processes it starts (the
    tiled fit's local workers inherit the environment), allocate without asking for
    transparent huge pages, unless the user set NUMPY_MADVISE_HUGEPAGE themselves.

    Measured, the 1M-point LAZ fit (`c1mesh fit terrain.laz --classes 2 --level 1`,
    benchmarks.stages), alternating runs on 2 threads: 10.5-11.7 s with huge pages,
    8.1-8.8 s without (the interpolate stage 3.5 -> 1.8-2.2 s), the same bytes. A
    library does not change this for its host program: only the command calls it."""
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


BLAS_THREAD_TIMEOUT = "4"
"""OPENBLAS_THREAD_TIMEOUT for the command: log2 of the CPU cycles an idle OpenBLAS thread
spins before it sleeps, at OpenBLAS's least (16 cycles; its default 28 is about 0.1 s)."""


def sleep_idle_blas() -> None:
    """Have OpenBLAS's idle threads (numpy's and scipy's libraries, CHOLMOD's), in this
    process and the processes it starts, sleep as soon as a call ends instead of spinning
    for the next one (BLAS_THREAD_TIMEOUT), unless the user set OPENBLAS_THREAD_TIMEOUT.
    OpenBLAS reads it when it is loaded: call this before numpy is imported.

    Why: c1mesh parallelises with its own threads, and the few BLAS calls it makes with
    the thread knob's threads (the frame's SVD, the DEM sampler's small products, the
    strength search's dot products) each left a BLAS worker spinning on the other core
    for 0.1-0.35 s while c1mesh's threads needed it: `perf record` of the DTM job (1M
    points, --smooth auto --spacing 1) found OpenBLAS's blas_thread_server in 7 % of its
    samples, about 1 s of a core in five bursts. Alternating runs, 2 threads, the same
    bytes: the DTM job's user time 13.4 -> 12.0-12.2 s, its wall 9.37-9.39 -> 9.02-9.22
    s; 1M points with normals at level 4, user time 6.5-8.2 -> 5.8-6.3 s. A library does
    not change this for its host program: only the command calls it."""
    os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", BLAS_THREAD_TIMEOUT)
