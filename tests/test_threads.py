"""c1mesh.core.threads: prefetching block generators, parallel ranges, the BLAS limit, and the
one thread-count knob every pool follows (bit-identical results for every count)."""
import json
import os
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from c1mesh.core import threads
from c1mesh.core.errors import InputError
from c1mesh.core.threads import blas_threads, ring, run_parallel

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"


@pytest.fixture
def two_workers():
    """prefetch_dealt runs one producer thread per worker when more than one is allowed."""
    with threads.limit(2):
        yield


def _dealt_reusing(count: int, buffers: int, size: int = 1000, made: dict | None = None):
    """make(w, producers) for prefetch_dealt: blocks w, w + producers, ... of `count`, each
    (like Refinement's) overwriting one of the producer's own `buffers` arrays in turn and
    holding its number; made[number] records the thread that made it."""
    def make(w: int, producers: int):
        pool = [np.empty(size) for _ in range(buffers)]
        for k, i in enumerate(range(w, count, producers)):
            block = pool[k % buffers]
            block[:] = i
            if made is not None:
                made[i] = threading.get_ident()
            yield block
    return make


@pytest.mark.parametrize("workers", [2, 3])
def test_dealt_blocks_come_in_order_from_every_producer_with_a_slow_consumer(workers):
    depth, made = 3, {}
    seen = []
    with threads.limit(workers):
        for block in threads.prefetch_dealt(_dealt_reusing(40, ring(depth), made=made), depth):
            time.sleep(0.001)                       # the producers run ahead meanwhile
            seen.append((block.min(), block.max()))  # a block overwritten early would show here
    assert seen == [(i, i) for i in range(40)]
    assert len(set(made.values())) == workers and threading.get_ident() not in made.values()
    assert all(made[i] == made[i % workers] for i in range(40))


def test_too_few_buffers_would_be_overwritten(two_workers):
    """The check above can fail: with fewer buffers than ring(depth) a held block changes."""
    depth = 3
    changed = False
    for i, block in enumerate(threads.prefetch_dealt(_dealt_reusing(40, depth), depth)):
        time.sleep(0.002)
        changed |= bool(block[0] != i)
    assert changed


def test_a_producers_error_is_raised_at_its_item(two_workers):
    def make(w, producers):
        for i in range(w, 10, producers):
            if i == 5:
                raise OSError("disk gone")
            yield i
    got = []
    with pytest.raises(OSError, match="disk gone"):
        for item in threads.prefetch_dealt(make, 2):
            got.append(item)
    assert got == [0, 1, 2, 3, 4]


def test_closing_early_stops_every_producer(two_workers):
    produced = []

    def make(w, producers):
        i = w
        while True:
            produced.append(i)
            yield i
            i += producers
    before = threading.active_count()
    stream = threads.prefetch_dealt(make, 2)
    assert [next(stream) for _ in range(5)] == list(range(5))
    stream.close()
    assert threading.active_count() == before
    count = len(produced)
    time.sleep(0.05)
    assert len(produced) == count and count <= 5 + 2 * (2 + 1)


def test_the_sequence_ends_with_its_last_block_whichever_producer_has_it(two_workers):
    for n in range(0, 7):
        assert list(threads.prefetch_dealt(lambda w, k: iter(range(w, n, k)), 2)) == list(range(n))


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


def test_map_in_threads_keeps_the_items_order_and_uses_the_threads():
    """Results come back in the items' order however the threads took them (a slow first
    item lets the other thread take the rest); at 1 thread all run in the caller's."""
    ran_in = {}

    def slow_square(i):
        if i == 0:
            time.sleep(0.2)
        ran_in[i] = threading.get_ident()
        return i * i
    assert threads.map_in_threads(slow_square, list(range(6)), threads=2) == [0, 1, 4, 9, 16, 25]
    assert len(set(ran_in.values())) == 2
    ran_in.clear()
    assert threads.map_in_threads(slow_square, list(range(6)), threads=1) == [0, 1, 4, 9, 16, 25]
    assert set(ran_in.values()) == {threading.get_ident()}
    with pytest.raises(ZeroDivisionError):
        threads.map_in_threads(lambda i: 1 // (i - 3), list(range(6)), threads=2)


def test_one_worker_prefetches_in_the_callers_thread():
    seen = []

    def make(w, producers):
        assert (w, producers) == (0, 1)
        for i in range(5):
            seen.append(threading.get_ident())
            yield i
    with threads.limit(1):
        assert list(threads.prefetch_dealt(make, 2)) == list(range(5))
    assert set(seen) == {threading.get_ident()}


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


def test_blas_threads_limits_a_blas_loaded_after_the_first_call():
    """The controller is kept between calls (core.threads._controller) but made again
    after an import: scipy.linalg brings scipy's own OpenBLAS, which a limit entered
    after it must reach as well as numpy's. In a child, so that scipy.linalg is not
    loaded yet."""
    import subprocess

    code = """if True:
        import numpy
        from threadpoolctl import threadpool_info
        from c1mesh.core.threads import blas_threads
        paths = lambda: {p["filepath"] for p in threadpool_info() if p["user_api"] == "blas"}
        before = paths()
        with blas_threads(1):
            pass
        import scipy.linalg
        assert paths() - before, "scipy.linalg should load a BLAS of its own"
        with blas_threads(1):
            print(sorted({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}))
    """
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[1]"


# --- the one knob ---------------------------------------------------------------------------


def _blas():
    from threadpoolctl import threadpool_info
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_the_default_is_the_cpus_this_process_may_use_and_limit_nests():
    assert threads.workers() == threads.available_cpus()
    with threads.limit(3) as inner:
        assert inner == threads.workers() == 3 and set(_blas()) == {3}
        with threads.limit(1):
            assert threads.workers() == 1 and set(_blas()) == {1}
        assert threads.workers() == 3 and threads.workers(5) == 5   # a per-call count wins
        with threads.limit(None):
            assert threads.workers() == 3
    assert threads.workers() == threads.available_cpus()


@pytest.mark.parametrize("bad", [0, -2, 1.5, "2", True])
def test_a_bad_thread_count_is_an_input_error(bad):
    with pytest.raises(InputError, match="threads"):
        with threads.limit(bad):
            pass


@pytest.mark.parametrize("total, processes, each", [(8, 2, 4), (8, 3, 2), (2, 4, 1), (1, 1, 1)])
def test_processes_share_the_threads_without_oversubscribing(total, processes, each):
    assert threads.per_process(total, processes) == each
    assert threads.per_process(None, 1) == threads.available_cpus()


class _ThreadCensus:
    """Records every Python thread started, every ThreadPoolExecutor's size and the size of
    every group of more than one thread that threads.run_parallel runs for
    threads.parallel_blocks (the coefficient, limiter and interpolator blocks)."""

    def __init__(self, monkeypatch):
        self.started, self.pools = 0, []
        start, init = threading.Thread.start, ThreadPoolExecutor.__init__
        run_parallel = threads.run_parallel

        def recording_run_parallel(work, ranges):
            if len(ranges) > 1:
                self.pools.append(len(ranges))
            return run_parallel(work, ranges)
        monkeypatch.setattr(threads, "run_parallel", recording_run_parallel)

        def counting_start(thread, *a, **k):
            self.started += 1
            return start(thread, *a, **k)

        def recording_init(pool, max_workers=None, *a, **k):
            self.pools.append(max_workers)
            return init(pool, max_workers, *a, **k)
        monkeypatch.setattr(threading.Thread, "start", counting_start)
        monkeypatch.setattr(ThreadPoolExecutor, "__init__", recording_init)


def _big_mesh_inputs(n=60_000, seed=0):
    """Enough points for several coefficient blocks."""
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2))
    return xy, np.sin(3 * xy[:, 0]) * xy[:, 1], np.column_stack([np.cos(xy[:, 1]), xy[:, 0]])


def test_one_worker_starts_no_thread_anywhere(monkeypatch, tmp_path):
    from c1mesh.engine.interpolator import RSDInterpolator
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.stages.trim import trim
    xy, z, g = _big_mesh_inputs()
    census = _ThreadCensus(monkeypatch)
    with threads.limit(1):
        tri, _ = trim(xy, delaunay(xy))
        RSDInterpolator(xy, z, g, triangles=tri).refine(2)
    fit(SAMPLES / "hill.ply", tmp_path / "o.ply", FitOptions(smooth="off", level=2, workers=1), keep_mesh=False)
    assert census.started == 0 and census.pools == []


def test_every_pool_stays_within_the_limit(monkeypatch, tmp_path):
    from c1mesh.engine import refine
    from c1mesh.engine.interpolator import RSDInterpolator
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.stages.trim import trim
    xy, z, g = _big_mesh_inputs()
    census = _ThreadCensus(monkeypatch)
    parallel = []
    real = refine.run_parallel
    monkeypatch.setattr(refine, "run_parallel", lambda work, ranges: (parallel.append(len(ranges)),
                                                                      real(work, ranges)))
    with threads.limit(3):
        tri, _ = trim(xy, delaunay(xy))
        RSDInterpolator(xy, z, g, triangles=tri).refine(2)
    assert census.pools and max(census.pools) == 3          # the tiles and the coefficients
    assert parallel == [3]
    before = len(census.pools)
    with threads.limit(2):
        interp = RSDInterpolator(xy, z, g, triangles=tri)
    interp.refine(2, workers=2)
    assert parallel[-1] == 2 and max(census.pools[before:]) == 2


def test_results_are_bit_identical_for_every_thread_count():
    from c1mesh.engine.interpolator import RSDInterpolator
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.stages.trim import trim
    xy, z, g = _big_mesh_inputs()
    results = []
    for count in (1, 2, 3):
        with threads.limit(count):
            tri, _ = trim(xy, delaunay(xy))
            interp = RSDInterpolator(xy, z, g, triangles=tri)
            mesh = interp.refine(3)
        results.append((tri, interp.coefficients, mesh.points, mesh.values, mesh.gradients,
                        mesh.triangles))
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert a.tobytes() == b.tobytes()


def test_the_fit_writes_the_same_bytes_with_one_thread_or_several(tmp_path):
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit
    written = []
    for count in (1, 2, 4):
        out = tmp_path / f"t{count}.ply"
        report = fit(SAMPLES / "hill.ply", out, FitOptions(smooth="off", level=3, workers=count), keep_mesh=False).report
        assert report["threads"] == count
        written.append(out.read_bytes())
    assert written[0] == written[1] == written[2]


def test_cli_threads_are_shared_by_the_jobs(tmp_path):
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    for name in (a, b):
        name.write_bytes((SAMPLES / "hill.ply").read_bytes())
    command = [sys.executable, "-m", "c1mesh.cli", "fit", str(a), str(b), "-O", str(tmp_path / "out"),
               "--level", "1", "--jobs", "2", "--threads", "4", "--report", str(tmp_path / "r.json")]
    proc = subprocess.run(command, capture_output=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    inputs = json.loads((tmp_path / "r.json").read_text())["inputs"]
    assert [entry["report"]["threads"] for entry in inputs] == [2, 2]
    single = subprocess.run(command[:5] + ["-o", str(tmp_path / "one.ply"), "--level", "1",
                                           "--threads", "1", "--report", str(tmp_path / "s.json")],
                            capture_output=True, timeout=300)
    assert single.returncode == 0, single.stderr
    assert json.loads((tmp_path / "s.json").read_text())["threads"] == 1


@pytest.mark.parametrize("args, each", [(["--threads", "1"], "1"),
                                        (["--threads", "4", "--jobs", "2"], "2")])
def test_cli_asks_openmp_for_the_same_share(tmp_path, monkeypatch, args, each):
    """Open3D's normal estimation (OpenMP) is outside threadpoolctl's reach: the CLI sets
    OMP_NUM_THREADS to each process's share before Open3D starts."""
    from click.testing import CliRunner

    from c1mesh.cli import main
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    inputs = []
    for name in ("a.ply", "b.ply"):
        inputs.append(tmp_path / name)
        inputs[-1].write_bytes((SAMPLES / "hill.ply").read_bytes())
    result = CliRunner().invoke(main, ["fit", "--smooth", "off", *map(str, inputs), "-O", str(tmp_path / "out"),
                                       "--level", "1", *args])
    assert result.exit_code == 0, result.output
    assert os.environ["OMP_NUM_THREADS"] == each


def test_limits_that_close_out_of_order_give_back_the_setting_before_them():
    """Tiles fitted in two threads each open a limit; the first opened may close first."""
    before, blas_before = threads.workers(), _blas()
    first, second = threads.limit(2), threads.limit(1)
    first.__enter__()
    second.__enter__()
    assert threads.workers() == 1 and set(_blas()) == {1}
    first.__exit__(None, None, None)
    assert threads.workers() == 1 and set(_blas()) == {1}      # the newest open block holds
    second.__exit__(None, None, None)
    assert threads.workers() == before and _blas() == blas_before


def test_parallel_blocks_start_no_block_after_an_error():
    """A failed block stops the other threads taking more (the tiled Delaunay relies on
    it to skip the rest of a failed tiling); the error reaches the caller."""
    started = []

    def work(block):
        started.append(block.start)
        if block.start == 0:
            raise ValueError("block 0 failed")
        time.sleep(0.01)
    with pytest.raises(ValueError, match="block 0 failed"):
        threads.parallel_blocks(work, 100, 1, threads=2)
    assert 0 in started and len(started) < 10


def _recording_blocks(taken: list):
    """work(block) that squares its slice of 0..count-1 into `out` and records who took it."""
    out = np.zeros(1000)

    def work(block):
        taken.append((block.start, threading.current_thread().name))
        out[block] = np.arange(block.start, block.stop, dtype=float) ** 2
        time.sleep(0.002)
    return work, out


def test_blocks_ahead_begin_in_the_background_and_the_caller_finishes_them(two_workers):
    """The blocks start while the caller's block runs, before finish(); finish() has the
    caller take the rest; every block is done once, the results those of a plain loop."""
    taken: list = []
    work, out = _recording_blocks(taken)
    with threads.blocks_ahead(work, 1000, 10) as finish:
        deadline = time.monotonic() + 5
        while len(taken) < 5 and time.monotonic() < deadline:
            time.sleep(0.001)                             # the caller's own step
        assert len(taken) >= 5                            # taken before finish()
        assert {name for _, name in taken} == {"c1mesh-ahead"}
        finish()
    np.testing.assert_array_equal(out, np.arange(1000.0) ** 2)
    assert sorted(start for start, _ in taken) == list(range(0, 1000, 10))
    assert threading.current_thread().name in {name for _, name in taken}    # the caller joined in


def test_blocks_ahead_raise_a_block_error_in_finish_and_stop_without_it(two_workers):
    def failing(block):
        time.sleep(0.001)
        if block.start == 30:
            raise ValueError("block 30 failed")
    with threads.blocks_ahead(failing, 1000, 10) as finish:
        with pytest.raises(ValueError, match="block 30 failed"):
            finish()
    taken: list = []
    work, _ = _recording_blocks(taken)
    with threads.blocks_ahead(work, 1000, 10):
        time.sleep(0.01)                                  # left without finish()
    done = len(taken)
    time.sleep(0.05)
    assert 0 < done < 100 and len(taken) == done          # no block after the block ended


def test_blocks_ahead_with_one_worker_start_nothing_early():
    taken: list = []
    work, out = _recording_blocks(taken)
    with threads.limit(1), threads.blocks_ahead(work, 1000, 10) as finish:
        time.sleep(0.02)
        assert taken == []
        finish()
    np.testing.assert_array_equal(out, np.arange(1000.0) ** 2)
    assert {name for _, name in taken} == {threading.current_thread().name}


@pytest.mark.parametrize("cliff", [False, True])
def test_the_guessed_triangulation_is_used_only_when_it_is_the_height_fields(monkeypatch, cliff):
    """With two threads the in-memory fit triangulates a guess of the height field's plane
    points beside the height normals (driver._guessed_triangles); its triangles serve only
    when the true xy equal the guess, bit for bit. Here a terrain with a duplicate point, and
    with a vertical cliff whose steep points the normals drop (the guess keeps them): the
    fit's triangles are those of one thread, which triangulates only the true xy, and the
    number of triangulations says whether the guess was taken."""
    from c1mesh.core.cloud import PointCloud
    from c1mesh.pipeline import driver
    from c1mesh.pipeline.driver import FitOptions, build_surface

    rng = np.random.default_rng(5)
    xy = rng.random((3000, 2)) * 10
    z = np.sin(xy[:, 0]) + 0.5 * xy[:, 1]
    points = np.column_stack([xy, z])
    points[7] = points[3]                                    # a duplicate: merged in either xy
    if cliff:                                                # a wall at x = 5: steep normals
        wall = np.column_stack([np.full(60, 5.0) + rng.random(60) * 1e-3, rng.random(60) * 10,
                                rng.random(60) * 20])
        points = np.vstack([points, wall])
    calls = []
    real = driver.delaunay
    monkeypatch.setattr(driver, "delaunay", lambda xy: calls.append(len(xy)) or real(xy))
    options = FitOptions(smooth="off", axis="z", normals="estimate", level=1)
    models = {}
    for count in (1, 2):
        calls.clear()
        with threads.limit(count):
            models[count] = build_surface(PointCloud(points.copy()), options)
        assert len(calls) == (2 if count == 2 and cliff else 1)
    one, two = models[1], models[2]
    assert (one.hf.dropped["too_steep"] > 0) == cliff
    assert one.hf.xy.tobytes() == two.hf.xy.tobytes()
    assert one.interp.triangles.tobytes() == two.interp.triangles.tobytes()
    assert one.interp.coefficients.tobytes() == two.interp.coefficients.tobytes()


@pytest.mark.parametrize("change", ["none", "duplicate", "steep normal"])
def test_given_normals_triangulate_the_projection_beside_the_height_field(monkeypatch, change):
    """With given normals and two threads the fit triangulates every point's projection
    (driver._projected_triangles) while it makes the height field; the triangles serve only
    when the height field keeps every point. A duplicate point (merged) or a normal steeper
    than max_slope (dropped) make the xy differ: the fit triangulates again, and its
    triangles and coefficients are those of one thread, which triangulates once."""
    from c1mesh.core.cloud import PointCloud
    from c1mesh.pipeline import driver
    from c1mesh.pipeline.driver import FitOptions, build_surface

    rng = np.random.default_rng(6)
    xy = rng.random((3000, 2)) * 10
    points = np.column_stack([xy, np.sin(xy[:, 0]) + 0.5 * xy[:, 1]])
    normals = np.column_stack([-np.cos(xy[:, 0]), np.full(3000, -0.5), np.ones(3000)])
    if change == "duplicate":
        points[7], normals[7] = points[3], normals[3]
    if change == "steep normal":
        normals[11] = [1.0, 0.0, 0.01]
    calls = []
    real = driver.delaunay
    monkeypatch.setattr(driver, "delaunay", lambda xy: calls.append(len(xy)) or real(xy))
    options = FitOptions(smooth="off", axis="z", level=1)
    models = {}
    for count in (1, 2):
        calls.clear()
        with threads.limit(count):
            models[count] = build_surface(PointCloud(points.copy(), normals.copy()), options)
        assert len(calls) == (2 if count == 2 and change != "none" else 1)
    one, two = models[1], models[2]
    assert len(one.hf.xy) == (3000 if change == "none" else 2999)
    assert one.hf.xy.tobytes() == two.hf.xy.tobytes()
    assert one.interp.triangles.tobytes() == two.interp.triangles.tobytes()
    assert one.interp.coefficients.tobytes() == two.interp.coefficients.tobytes()


def test_background_runs_beside_the_block_and_one_worker_runs_it_when_asked():
    """threads.background: with two workers the work runs in another thread while the block
    goes on (it waits for an event the block sets), its error is raised by result; with one
    worker it runs in the caller's thread, when its result is first asked for, once."""
    started = threading.Event()
    seen = []

    def work():
        seen.append(threading.get_ident())
        started.set()
        return 42
    with threads.limit(2):
        with threads.background(work) as result:
            assert started.wait(5)
            assert result() == 42 and seen[0] != threading.get_ident()
        with pytest.raises(ZeroDivisionError):
            with threads.background(lambda: 1 / 0) as result:
                result()
    seen.clear()
    with threads.limit(1):
        with threads.background(work) as result:
            assert seen == []
            assert result() == 42 and result() == 42
    assert seen == [threading.get_ident()]


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_compress_and_take_rows_are_numpys_at_any_thread_count(threads):
    """core.threads.compress_rows against np.compress on rows (n, 3) with blocks of 7: a
    mask keeping most rows, none, all, and fewer rows than a block; take_rows against
    fancy indexing of rows (n, 3) and of a column (n,), with repeats and no index."""
    from c1mesh.core.threads import compress_rows, limit, take_rows
    rng = np.random.default_rng(threads)
    rows = rng.integers(0, 1000, (100, 3))
    with limit(threads):
        for keep in (rng.random(100) > 0.2, np.zeros(100, bool), np.ones(100, bool)):
            assert np.array_equal(compress_rows(keep, rows, block=7), np.compress(keep, rows, axis=0))
        assert np.array_equal(compress_rows(keep[:5], rows[:5], block=7), rows[:5])
        index = rng.integers(0, 100, 60)
        for table in (rows, rows[:, 1].copy(), rows.astype(float)):
            assert np.array_equal(take_rows(table, index, block=7), table[index])
            assert take_rows(table, index[:0], block=7).shape == table[:0].shape
