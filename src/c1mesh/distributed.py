"""Running tile tasks (c1mesh.tiles.TileTask) in this process or on Dask.

Each tile is one task; its result depends only on the task, never on where or in which
order it ran, so the written bytes do not depend on the scheduler or the worker count.
Results are handed back to the caller as they complete; it writes them (tiles.write_tiles),
so workers need no shared file system.
"""
from __future__ import annotations

from typing import Iterator, Sequence

from c1mesh.tiles import TileResult, TileTask, run_tile, tile_failure


def run_tiles(tasks: Sequence[TileTask], scheduler: str | None = None,
              jobs: int = 1) -> Iterator[TileResult]:
    """Yield the TileResult of every task, in completion order.

    scheduler: address of a running dask.distributed scheduler ("tcp://host:port") to
    send the tasks to; else jobs > 1 starts a local Dask cluster of `jobs` single-thread
    worker processes for this run; else the tasks run here, one after the other.
    A task that fails raises tiles.TileError naming its tile (the rest are cancelled).
    """
    if scheduler is None and jobs <= 1:
        for task in tasks:
            yield _run_here(task)
        return
    from distributed import Client, LocalCluster

    if scheduler is not None:
        with Client(scheduler) as client:
            yield from _run_on(client, tasks)
        return
    with LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        yield from _run_on(client, tasks)


def _run_here(task: TileTask) -> TileResult:
    try:
        return run_tile(task)
    except Exception as exc:  # noqa: BLE001 — any failure of a tile is named by its tile
        raise tile_failure(task, exc) from exc


def _run_on(client, tasks: Sequence[TileTask]) -> Iterator[TileResult]:
    """Submit every task to client, yield results as they complete."""
    from distributed import as_completed

    futures = {}
    for task in tasks:
        future = client.submit(run_tile, task, key=f"c1mesh-tile-{task.index}-{id(task):x}", pure=False)
        futures[future.key] = (future, task)
    try:
        for future in as_completed([f for f, _ in futures.values()]):
            task = futures[future.key][1]
            if future.status == "error":
                raise tile_failure(task, future.exception())
            yield future.result()
            future.release()
    finally:
        client.cancel([f for f, _ in futures.values()])
