"""The few places c1mesh uses more than one core, in one module, and the one knob for them.

* `workers()`: how many threads c1mesh may use at once. Every pool in the package
  (spline coefficients, tiled triangulation, trimming, refinement, prefetching, the
  background writer) asks it, and so does BLAS inside `limit`. Default: the CPUs this
  process may use (`available_cpus`); `limit(n)` changes it for a block
  (FitOptions.workers, the CLI's --threads). With 1 worker nothing
  runs in a second thread. Results do not depend on the count: every pool splits work
  into the same blocks and collects them in the same order.
* `run_parallel`: contiguous ranges of independent work in threads (Refinement.mesh
  evaluates ranges of triangle blocks into disjoint slices of its outputs);
  `parallel_blocks`: the same over fixed-size blocks of a range (element-wise passes of
  the limiter and the interpolator, each block's temporaries small enough for the cache).
* `overlap` and `background`: one piece of work in a second thread beside the caller's
  (the in-memory fit triangulates a guess of its plane points beside the height normals
  and the height field);
* `prefetch_dealt`: a sequence of blocks dealt round-robin to one producer thread per
  worker, each a few blocks ahead of the consumer, handed over in the sequence's order (a
  streamed fit: spline evaluation in the producers, packing rows for the file format in
  the consumer, the file write in one more thread).
* `blas_threads`: the BLAS thread pool limited while our own threads run, since a
  multi-threaded BLAS called from several threads oversubscribes the cores.

numpy releases the GIL inside its kernels (matrix products, gathers, ufuncs), which is
what makes plain threads pay off here.

Blocks handed over by a producer of `prefetch_dealt` must not be overwritten while the
consumer still holds them: a producer that reuses buffers has to rotate through at least
`depth + 2` of them (one being filled, `depth` queued, one held by the consumer), which is
what `ring(depth)` says.
"""
from __future__ import annotations

import contextlib
import itertools
import os
import queue
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterator, TypeVar

import numpy as np
from threadpoolctl import ThreadpoolController

from c1mesh.core.errors import InputError

Item = TypeVar("Item")

_DONE = object()


_OPEN_LIMITS: list[tuple[object, int]] = []
"""(token, count) of every `limit` block open now, oldest first: the newest one is in force.
A list, not a saved previous value, because blocks opened in two threads (tiles fitted in
a thread pool) may close in any order."""

_LIMITS_LOCK = threading.Lock()
_BLAS_BEFORE_LIMITS = None
"""threadpoolctl's limiter made when the first open block began; it restores BLAS's own
setting when the last one ends."""


def workers(requested: int | None = None) -> int:
    """Threads a c1mesh stage may use: `requested` when given (a per-call `workers=`
    argument), else the newest open `limit` block's, else the CPUs this process may use."""
    if requested is not None:
        return _checked(requested)
    if _OPEN_LIMITS:
        return _OPEN_LIMITS[-1][1]
    return available_cpus()


def _checked(count) -> int:
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise InputError(f"the number of threads must be a whole number >= 1, got {count!r}")
    return int(count)


@contextlib.contextmanager
def limit(count: int | None) -> Iterator[int]:
    """Within the block every c1mesh pool, and BLAS, use at most `count` threads
    (None: leave the current setting); yields the count in force. The setting is
    process-wide while the block runs (not per thread), like threadpoolctl's; the newest
    open block is in force, and blocks may close in any order."""
    if count is None:
        yield workers()
        return
    token = object()
    with _LIMITS_LOCK:
        _OPEN_LIMITS.append((token, _checked(count)))
        _follow_open_limits()
    try:
        yield count
    finally:
        with _LIMITS_LOCK:
            _OPEN_LIMITS[:] = [entry for entry in _OPEN_LIMITS if entry[0] is not token]
            _follow_open_limits()


def _follow_open_limits() -> None:
    """BLAS follows the newest open `limit` block; with none open, BLAS gets back the
    setting it had before the first (called with _LIMITS_LOCK held)."""
    global _BLAS_BEFORE_LIMITS
    if _OPEN_LIMITS:
        limiter = _controller().limit(limits=_OPEN_LIMITS[-1][1], user_api="blas")
        if _BLAS_BEFORE_LIMITS is None:
            _BLAS_BEFORE_LIMITS = limiter
    elif _BLAS_BEFORE_LIMITS is not None:
        _BLAS_BEFORE_LIMITS.restore_original_limits()
        _BLAS_BEFORE_LIMITS = None


def per_process(total: int | None, processes: int) -> int:
    """Threads for each of `processes` processes sharing `total` threads (None: the CPUs
    this process may use), at least 1, so N processes do not oversubscribe the cores."""
    return max(1, workers(total) // max(1, int(processes)))


def openmp_at_start(count: int) -> None:
    """Ask OpenMP runtimes that have not started yet for `count` threads.

    Open3D's normal estimation runs OpenMP threads that threadpoolctl cannot see (its
    runtime is linked in); OpenMP reads OMP_NUM_THREADS when it starts, so the CLI calls
    this before anything imports Open3D. It holds for the rest of the process, and for
    processes started from it (the --jobs workers)."""
    os.environ["OMP_NUM_THREADS"] = str(_checked(count))


def ring(depth: int) -> int:
    """Buffers a generator must rotate through to be prefetched `depth` blocks ahead."""
    return depth + 2


def prefetch_dealt(make: Callable[[int, int], Iterator[Item]], depth: int = 2) -> Iterator[Item]:
    """Yield the items of a sequence computed by `workers()` producer threads, in the
    sequence's order. make(w, count) yields the items w, w + count, w + 2·count, ... of the
    sequence (the blocks dealt round-robin to `count` producers), each producer up to
    `depth` items ahead of the consumer; item i is taken from producer i mod count. The
    first producer that runs out ends the sequence (the ones after it have nothing left).

    Why: one producer thread left the evaluation of a streamed surface on one core while
    the consumer waited for it (at 2 threads, a 1M-point PLY to level 4: the writer waited
    0.7-1.1 s for blocks). Dealt blocks are computed by the same code on
    buffers of the same shapes whichever thread takes them, so the items, and the bytes a
    writer makes of them, do not depend on the count. An error raised by a producer is
    re-raised at its item; closing the stream early stops every producer at its next
    item and waits for it. With one worker, make(0, 1) runs in the caller's thread."""
    count = workers()
    if count == 1:
        yield from make(0, 1)
        return
    producers = [make(w, count) for w in range(count)]
    handovers = [queue.Queue(maxsize=depth) for _ in range(count)]
    stop = threading.Event()

    def put(handover: queue.Queue, item) -> bool:
        while not stop.is_set():
            try:
                handover.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce(w: int) -> None:
        try:
            for item in producers[w]:
                if not put(handovers[w], (item, None)):
                    return
        except BaseException as error:            # handed to the consumer, raised there
            put(handovers[w], (_DONE, error))
            return
        put(handovers[w], (_DONE, None))

    threads = [threading.Thread(target=produce, args=(w,), name="c1mesh-prefetch", daemon=True)
               for w in range(count)]
    for thread in threads:
        thread.start()
    try:
        for w in itertools.cycle(range(count)):
            item, error = handovers[w].get()
            if error is not None:
                raise error
            if item is _DONE:
                return
            yield item
    finally:
        stop.set()
        for thread in threads:
            thread.join()
        for producer in producers:
            close = getattr(producer, "close", None)
            if close is not None:
                close()


def blas_threads(limit: int | None) -> contextlib.AbstractContextManager:
    """A context limiting the BLAS thread pools to `limit` threads (None: no change).

    Two of our threads each calling a multi-threaded BLAS oversubscribe the cores and
    serialise on its pool (measured at 1M points, level 4: Refinement.mesh with two
    workers took 0.95 s with BLAS's two threads each, 0.58 s with one; a single worker
    0.85 s); an idle BLAS pool also spins on the core a writer thread needs. The limit
    is process-wide while the context is open (threadpoolctl does it for OpenBLAS, MKL
    and BLIS alike).
    """
    if limit is None:
        return contextlib.nullcontext()
    return _controller().limit(limits=limit, user_api="blas")


_CONTROLLER: tuple[int, ThreadpoolController] | None = None
"""(len(sys.modules) when it was made, threadpoolctl's controller): `_controller`'s cache."""


def _controller() -> ThreadpoolController:
    """threadpoolctl's controller of the BLAS libraries loaded now. Making one reads the
    process's library map (~1.5 ms: the DTM job's strength search made 110, 0.16 s with
    the GIL held), so it is made again only when a module was imported since the last:
    a library loaded after the first call (scipy's own OpenBLAS, CHOLMOD's) comes with an
    import, and is then limited too."""
    global _CONTROLLER
    modules = len(sys.modules)
    cached = _CONTROLLER
    if cached is None or cached[0] != modules:
        cached = _CONTROLLER = (modules, ThreadpoolController())
    return cached[1]


def available_cpus() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                                  # not Linux
        return os.cpu_count() or 1


def overlap(second: Callable[[], Item], foreground: Callable[[], object]) -> tuple:
    """(second(), foreground()): the first run in a second thread while the second runs
    in this one (numpy releases the GIL in both), or one after the other when only one
    worker is allowed (`background`). An error in either is raised here."""
    with background(second) as result:
        here = foreground()
        return result(), here


@contextlib.contextmanager
def background(work: Callable[[], Item]) -> Iterator[Callable[[], Item]]:
    """Run work() in a second thread while the block runs; yields `result`, which waits for
    it and returns its value (an error in it is raised there). Leaving the block waits for
    the thread, so none outlives it. With one worker (`workers`) nothing runs in a thread:
    work() runs in the caller when result is first called (not at all if never). Unlike
    `overlap`, the caller's side may be several steps, the result asked for between them."""
    if workers() == 1:
        done: list = []

        def result_here() -> Item:
            if not done:
                done.append(work())
            return done[0]
        yield result_here
        return
    with ThreadPoolExecutor(1, thread_name_prefix="c1mesh-background") as pool:
        pending = pool.submit(work)
        yield pending.result


@contextlib.contextmanager
def blocks_ahead(work: Callable[[slice], None], count: int, block: int,
                 prepare: Callable[[], None] | None = None) -> Iterator[Callable[[], None]]:
    """work(slice) for the consecutive blocks of `block` items of range(count), begun at
    once by one background thread while the caller's block runs, after prepare() (None:
    nothing to prepare; what work reads, made there too); yields finish(), which has the
    caller's threads (`workers`) take the blocks still untaken and returns once every
    block is done (the first error raised by prepare or any block is raised there).

    Why: work that does not need the caller's next step (the smoothing's data term, which
    needs no strength) fills the core that step leaves idle (the strength search's direct
    factorisations hold one core and the GIL), and the caller's threads still finish it
    if the step ends first. The blocks are the same whoever takes them, so element-wise
    work writing disjoint slices has the same bits as parallel_blocks'. Each block must
    be long (a kernel without the GIL): a block's return waits for the GIL, which a
    caller in a long C call holds. With one worker nothing starts early: finish() runs
    prepare and every block. Leaving the block without finish() lets the background take
    no more blocks and waits for its current one."""
    stopped, prepared = threading.Event(), threading.Event()
    take = _block_taker(work, count, block, stopped)
    errors: list = []

    def ahead() -> None:
        try:
            if prepare is not None:
                prepare()
            prepared.set()
            take()
        except BaseException as error:     # re-raised by finish()
            errors.append(error)
            stopped.set()
            prepared.set()
    thread = None
    if workers() > 1:
        thread = threading.Thread(target=ahead, name="c1mesh-ahead", daemon=True)
        thread.start()

    def finish() -> None:
        if thread is None:
            if prepare is not None:
                prepare()
        else:
            prepared.wait()
        if not errors:
            run_parallel(take, [()] * max(1, workers() - (thread is not None)))
        if thread is not None:
            thread.join()
        if errors:
            raise errors[0]
    try:
        yield finish
    finally:
        stopped.set()
        if thread is not None:
            thread.join()


def run_parallel(work: Callable[..., None], ranges: list[tuple]) -> None:
    """work(*r) for every r in ranges: the first in this thread, the rest in threads;
    the first error raised by any of them is re-raised here."""
    errors = []

    def guarded(*r):
        try:
            work(*r)
        except BaseException as error:                     # re-raised in the caller
            errors.append(error)
    threads = [threading.Thread(target=guarded, args=r, name="c1mesh-worker", daemon=True) for r in ranges[1:]]
    for thread in threads:
        thread.start()
    guarded(*ranges[0])
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]


def parallel_blocks(work: Callable[[slice], None], count: int, block: int = 1 << 16,
                    threads: int | None = None) -> None:
    """work(slice) for the consecutive blocks of `block` items of range(count), in
    `workers(threads)` threads (run_parallel), each taking the next block not yet taken
    (so a core busy with other work does not hold up the rest). The blocks are the same
    for every thread count, so element-wise work writing disjoint slices gives the same
    bits with any count; the first error raised is re-raised here, and once one is
    raised no thread takes another block."""
    blocks = -(-count // block)
    if blocks == 0:
        return
    run_parallel(_block_taker(work, count, block, threading.Event()), [()] * max(1, min(workers(threads), blocks)))


def _block_taker(work: Callable[[slice], None], count: int, block: int,
                 stopped: threading.Event) -> Callable[[], None]:
    """The loop each thread of parallel_blocks and blocks_ahead runs: take the next block of
    `block` items of range(count) not yet taken (a shared counter, atomic under the GIL) and
    run work(slice) on it, until none is left or `stopped` is set; a block's error sets
    `stopped`, so that no thread takes another, and is raised."""
    blocks = -(-count // block)
    taken = itertools.count()

    def take() -> None:
        for b in iter(taken.__next__, None):
            if b >= blocks or stopped.is_set():
                return
            try:
                work(slice(b * block, min(count, (b + 1) * block)))
            except BaseException:
                stopped.set()
                raise
    return take


def take_rows(rows: np.ndarray, index: np.ndarray, block: int = 1 << 16) -> np.ndarray:
    """rows[index] (m, ...) for index (m,) into rows (n, ...), the blocks of index gathered
    by parallel_blocks in the thread knob's threads (numpy's take releases the GIL), so
    the new array's pages fault in on every core. The same array at any thread count."""
    out = np.empty((index.shape[0],) + rows.shape[1:], dtype=rows.dtype)
    parallel_blocks(lambda part: np.take(rows, index[part], axis=0, out=out[part]), index.shape[0], block)
    return out


def compress_rows(keep: np.ndarray, rows: np.ndarray, block: int = 1 << 16) -> np.ndarray:
    """np.compress(keep, rows, axis=0): the rows (n, ...) where keep (n,) bool is set, in
    their order, each block's rows copied by parallel_blocks in the thread knob's threads
    into its place (the kept rows before it counted first), so the new array's pages
    fault in on every core. The same array at any thread count."""
    count = keep.shape[0]
    starts = np.zeros(-(-count // block) + 1, dtype=np.int64)
    starts[1:] = np.cumsum([np.count_nonzero(keep[b:b + block]) for b in range(0, count, block)])
    out = np.empty((int(starts[-1]),) + rows.shape[1:], dtype=rows.dtype)

    def copy(part: slice) -> None:
        b = part.start // block
        np.compress(keep[part], rows[part], axis=0, out=out[starts[b]:starts[b + 1]])
    parallel_blocks(copy, count, block)
    return out


def map_in_threads(function: Callable[[Item], object], items: list, threads: int | None = None) -> list:
    """[function(item) for item in items], the items shared among `workers(threads)`
    threads (parallel_blocks, one item a block) and the results in the items' order, so
    the result is the same for every thread count; the first error raised is re-raised,
    and no item is started after it."""
    results: list = [None] * len(items)

    def run(block: slice) -> None:
        results[block.start] = function(items[block.start])
    parallel_blocks(run, len(items), 1, threads)
    return results
