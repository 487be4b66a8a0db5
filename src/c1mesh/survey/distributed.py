"""Running tile tasks in this process, on a local pool, or on Dask (TaskRunner, the one
executor choice): the seamless fit's (c1mesh.survey.tiles.TileTask, run_tiles) and the
memory-bounded fit's passes (c1mesh.pipeline.bounded_fit).

Each tile is one task; its result depends only on the task, never on where or in which
order it ran, so the written bytes do not depend on the scheduler or the worker count.
A seamless tile's result comes back to the caller, which writes it (tiles.write_tiles), so
its workers need no shared file system; a memory-bounded fit's tasks read and write spill
files, so its workers must see the folder they are in.
"""
from __future__ import annotations

import multiprocessing
import os
import tempfile
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Callable, Iterator, Sequence

from c1mesh.core.errors import InputError
from c1mesh.core.platform_memory import release_task_heap
from c1mesh.survey.tiles import TileResult, TileTask, run_tile, temp_path, tile_failure

CONNECT_SECONDS = 30
"""How long to try reaching a --scheduler before giving up."""


def run_tiles(tasks: Sequence[TileTask], scheduler: str | None = None,
              jobs: int = 1) -> Iterator[TileResult]:
    """Yield the TileResult of every task, in completion order.

    tasks: a sequence (tiles.TilePlan builds each task when indexed); at most _IN_FLIGHT
    tasks per worker are built and pending at a time, so memory holds those, not all.
    scheduler: address of a running dask.distributed scheduler ("tcp://host:port") to
    send the tasks to; else jobs > 1 runs them on `jobs` local processes (TaskRunner);
    else the tasks run here, one after the other.
    A task that fails raises tiles.TileError naming its tile (the rest are cancelled).
    """
    if scheduler is None and jobs <= 1:
        for task in tasks:
            yield _run_here(task)
        return
    with TaskRunner(scheduler, jobs, start_method=None, scatter=True) as runner:
        for _, result in runner.map(run_tile, len(tasks), lambda i: (tasks[i],), lambda i: tasks[i].name):
            yield result


def _run_here(task: TileTask) -> TileResult:
    """Run a task in this process, streaming its mesh to its temporary file."""
    try:
        return run_tile(task, target=temp_path(task.output))
    except Exception as exc:  # noqa: BLE001 — any failure of a tile is named by its tile
        raise tile_failure(task.name, exc) from exc


_IN_FLIGHT = 2
"""Tasks built and submitted per worker ahead of their results."""


def _windowed(count: int, window: int, pending: dict, submit, wait_some) -> Iterator[tuple[object, int]]:
    """Submit tasks 0..count-1 keeping at most `window` pending; yield (future, index) as they finish.

    pending: the caller's dict future -> task index (so it can cancel what is left);
    submit(i) returns a future; wait_some() returns finished futures among the pending.
    """
    next_index = 0
    while next_index < count or pending:
        while next_index < count and len(pending) < window:
            pending[submit(next_index)] = next_index
            next_index += 1
        for future in list(wait_some()):
            yield future, pending.pop(future)


SOCKET_PATH_LIMIT = 104
"""Bytes of a Unix socket's path, less its terminating zero, that every platform takes
(sun_path: 108 on Linux, 104 on macOS)."""
FORKSERVER_SOCKET_EXTRA = 40
"""What multiprocessing's forkserver adds to the temporary folder for its socket:
/pymp-XXXXXXXX/listener-XXXXXXXX and a margin."""


def pool_start_method(asked: str | None) -> str | None:
    """The start method a local pool uses: the one asked for, except "forkserver" under a
    temporary folder (tempfile.gettempdir(), $TMPDIR) too deep for the forkserver's Unix
    socket, which would fail with "AF_UNIX path too long" (a long $TMPDIR: a CI job's or a
    batch system's scratch folder); "spawn" then, which needs no socket and also starts
    each worker without a copy of this process's pages."""
    if asked != "forkserver":
        return asked
    folder = os.fsencode(tempfile.gettempdir())
    return asked if len(folder) + FORKSERVER_SOCKET_EXTRA < SOCKET_PATH_LIMIT else "spawn"


class TaskRunner:
    """Where tile tasks run: in this process (jobs 1), on a local pool of `jobs`
    processes (a ProcessPoolExecutor), or on the Dask cluster at `scheduler`. Use as a
    context manager; the pool or client is started once and serves every `map` (a
    memory-bounded fit, c1mesh.pipeline.bounded_fit, maps each of its passes over the tiles).

    Why a pool and not a Dask LocalCluster locally: measured on 9 tiles of a 200k-point
    survey at level 4 (2 cores, heavily shared), time of the tile stage: in the process
    8.7 s, a pool of 2 processes 14.4 s, a LocalCluster of 2 workers 31.2 s (about 10 s
    of it starting the cluster): the pool starts in well under a second and needs no
    scheduler round trips; a cluster is worth its start-up only across machines
    (--scheduler).

    start_method: how the pool starts its processes (multiprocessing; None: the
    platform's default). The memory-bounded fit uses "forkserver", so a worker holds only
    what its tasks read, not a copy of this process's pages. scatter: send each task's
    arguments to Dask as data (large arrays), not inside the task graph.
    """

    def __init__(self, scheduler: str | None = None, jobs: int = 1, start_method: str | None = "forkserver",
                 scatter: bool = False):
        self.scheduler, self.jobs = scheduler, max(1, int(jobs))
        self.start_method, self.scatter = start_method, scatter
        self.pool = self.client = None

    @property
    def kind(self) -> str:
        """How the tasks run, for the report."""
        if self.scheduler is not None:
            return self.scheduler
        if self.jobs == 1:
            return "in process"
        return f"{self.jobs} local processes"

    @property
    def workers(self) -> int:
        """Tasks that run at once."""
        if self.client is not None:
            return max(1, sum(self.client.nthreads().values()))
        return self.jobs

    def __enter__(self) -> "TaskRunner":
        if self.scheduler is not None:
            from distributed import Client

            try:
                self.client = Client(self.scheduler, timeout=CONNECT_SECONDS)
            except (OSError, TimeoutError, ValueError) as exc:
                raise InputError(f"cannot reach the Dask scheduler {self.scheduler}: {exc}") from exc
        elif self.jobs > 1:
            method = pool_start_method(self.start_method)
            self.pool = ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context(method))
        return self

    def __exit__(self, *exc) -> None:
        if self.client is not None:
            self.client.close()
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
        self.pool = self.client = None

    def map(self, function: Callable, count: int, arguments: Callable[[int], tuple],
            name: Callable[[int], str]) -> Iterator[tuple[int, object]]:
        """Yield (i, function(*arguments(i))) for i in range(count), in completion order.
        A task that raises stops the run: tiles.TileError "tile NAME: ..." (name(i)), the
        tasks not yet finished are cancelled."""
        if self.pool is None and self.client is None:
            for i in range(count):
                try:
                    result = function(*arguments(i))
                except Exception as exc:  # noqa: BLE001 — any failure of a tile is named by its tile
                    raise tile_failure(name(i), exc) from exc
                release_task_heap()
                yield i, result
            return
        pending: dict = {}
        if self.pool is not None:
            submit = lambda i: self.pool.submit(_then_release, function, *arguments(i))  # noqa: E731
            wait_some = lambda: wait(pending, return_when=FIRST_COMPLETED).done  # noqa: E731
            failed = lambda future: future.exception()                          # noqa: E731
        else:
            from distributed import as_completed

            completed = as_completed()

            def submit(i):
                data = arguments(i)
                if self.scatter:                 # the arrays travel as data, not in the graph
                    data = [self.client.scatter(a, hash=False) for a in data]
                future = self.client.submit(function, *data, pure=False, key=f"c1mesh-tile-{i}-{id(pending):x}")
                completed.add(future)
                return future
            wait_some = lambda: [next(completed)]                                # noqa: E731
            failed = lambda future: future.exception() if future.status == "error" else None  # noqa: E731
        try:
            for future, i in _windowed(count, _IN_FLIGHT * self.workers, pending, submit, wait_some):
                exc = failed(future)
                if exc is not None:
                    raise tile_failure(name(i), exc)
                result = future.result()
                if self.client is not None:
                    future.release()
                yield i, result
        finally:
            if self.client is not None:
                self.client.cancel(list(pending))
            else:
                for future in pending:
                    future.cancel()


def _then_release(function: Callable, *arguments):
    """function(*arguments) in a pool worker, then the heap it freed given back
    (platform_memory.release_task_heap; the command holds it for the next task instead):
    tasks of one size then peak at one size, however many a worker has run; the same is
    done after each task run in this process."""
    try:
        return function(*arguments)
    finally:
        release_task_heap()
