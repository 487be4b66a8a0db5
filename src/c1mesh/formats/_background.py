"""Write to a file from a second thread, so computing the next block overlaps the write.

A streamed mesh is computed block by block; writing a block (copying it into the page
cache) releases the GIL, so handing the bytes to a writer thread lets the two cores work
at once. The queue is bounded, so memory stays a few blocks. An error in the writer
thread (disk full) is raised in the caller at its next write or at the end.
"""
from __future__ import annotations

import contextlib
import queue
import threading
from typing import IO, Callable, Iterator

from c1mesh.core.threads import workers

_DEPTH = 4   # blocks in flight


@contextlib.contextmanager
def background_writes(f: IO[bytes]) -> Iterator[Callable[[object], None]]:
    """Yield write(buffer): queue `buffer` (bytes-like, not modified afterwards) for `f`.

    With one worker allowed (c1mesh.core.threads.workers()) buffers are written at once, in
    the caller's thread."""
    if workers() == 1:
        yield f.write
        return
    pending: queue.Queue = queue.Queue(maxsize=_DEPTH)
    failure: list[BaseException] = []

    def drain() -> None:
        while True:
            item = pending.get()
            if item is None:
                return
            if not failure:
                try:
                    f.write(item)
                except BaseException as exc:   # re-raised in the caller's thread
                    failure.append(exc)

    worker = threading.Thread(target=drain, name="c1mesh-writer", daemon=True)
    worker.start()

    def write(buffer) -> None:
        if failure:
            raise failure[0]
        pending.put(buffer)

    try:
        yield write
    finally:
        pending.put(None)
        worker.join()
    if failure:
        raise failure[0]
