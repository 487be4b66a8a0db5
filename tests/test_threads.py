"""c1mesh.threads: prefetching block generators, parallel ranges, the BLAS limit."""
import threading
import time

import numpy as np
import pytest

from c1mesh.threads import blas_threads, prefetch, ring, run_parallel


def _reusing_blocks(count: int, buffers: int, size: int = 1000):
    """Blocks that, like Refinement's, overwrite one of `buffers` arrays in turn."""
    pool = [np.empty(size) for _ in range(buffers)]
    for i in range(count):
        block = pool[i % buffers]
        block[:] = i
        yield block


def test_prefetch_yields_every_block_in_order_with_a_slow_consumer():
    depth = 3
    seen = []
    for block in prefetch(_reusing_blocks(40, ring(depth)), depth):
        time.sleep(0.001)                       # the producer runs ahead meanwhile
        seen.append((block.min(), block.max()))  # a block overwritten early would show here
    assert seen == [(i, i) for i in range(40)]


def test_too_few_buffers_would_be_overwritten():
    """The check above can fail: with fewer buffers than ring(depth) a held block changes."""
    depth = 3
    changed = False
    for i, block in enumerate(prefetch(_reusing_blocks(40, depth), depth)):
        time.sleep(0.002)
        changed |= bool(block[0] != i)
    assert changed


def test_prefetch_reraises_the_producers_error():
    def failing():
        yield 1
        yield 2
        raise OSError("disk gone")
    got = []
    with pytest.raises(OSError, match="disk gone"):
        for item in prefetch(failing(), 2):
            got.append(item)
    assert got == [1, 2]


def test_closing_early_stops_the_producer():
    produced = []

    def endless():
        i = 0
        while True:
            produced.append(i)
            yield i
            i += 1
    before = threading.active_count()
    stream = prefetch(endless(), 2)
    assert [next(stream) for _ in range(5)] == list(range(5))
    stream.close()
    assert threading.active_count() == before
    count = len(produced)
    time.sleep(0.05)
    assert len(produced) == count and count <= 5 + 2 + 1


def test_run_parallel_covers_every_range_in_threads():
    seen = {}
    together = threading.Barrier(3, timeout=5)      # all alive at once: idents are distinct

    def work(first, last):
        seen[(first, last)] = threading.get_ident()
        together.wait()
    run_parallel(work, [(0, 3), (3, 5), (5, 9)])
    assert sorted(seen) == [(0, 3), (3, 5), (5, 9)]
    assert seen[(0, 3)] == threading.get_ident()
    assert len(set(seen.values())) == 3


def test_blas_threads_limits_inside_and_restores_after():
    from threadpoolctl import threadpool_info
    blas = lambda: [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]  # noqa: E731
    before = blas()
    assert before, "numpy's BLAS should be visible to threadpoolctl"
    with blas_threads(1):
        assert set(blas()) == {1}
    assert blas() == before
    with blas_threads(None):
        assert blas() == before
