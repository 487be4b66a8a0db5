"""Seamless surveys (c1mesh.survey.tiles): union of the per-input outputs equals the whole fit.

Ground truth is the fit of the concatenated cloud (one file), computed independently of
the tile code; the per-input outputs are read back from disk and merged by exactly equal
vertex coordinates, as a user would merge them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from scipy.spatial import cKDTree

from c1mesh.cli import main
from c1mesh.core.cloud import PointCloud
from c1mesh.testing.samples import sample_surface, write_points_ply


def _load(path):
    mesh = trimesh.load(path, process=False, force="mesh")
    return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)


def _merge_exact(meshes):
    """Concatenate meshes and merge vertices with bit-identical coordinates."""
    vertices = np.concatenate([v for v, _ in meshes])
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes])[:-1]
    faces = np.concatenate([f + o for (_, f), o in zip(meshes, offsets)])
    unique, inverse = np.unique(vertices, axis=0, return_inverse=True)
    return unique, inverse.ravel()[faces]


def _boundary_edges(faces):
    """Undirected edges used by exactly one face, as sorted (a, b) rows."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]


def _face_set(faces):
    return {tuple(sorted(f)) for f in faces.tolist()}


def _grid_cells(points, nx=2, ny=2):
    """Cell (0..nx·ny−1) of each point in an nx × ny grid over the points' xy bounds."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    ij = np.minimum(((points[:, :2] - lo) / (hi - lo) * [nx, ny]).astype(int), [nx - 1, ny - 1])
    return ij[:, 0] + nx * ij[:, 1]


def _assert_union_is_whole(whole_path, tile_paths):
    """The exact-vertex merge of the tiles is the whole mesh: the same vertices to the bit
    (matched one to one), same faces, the same boundary; and every vertex the tiles share
    is bit-identical (else the merge would keep two copies and have more vertices)."""
    wv, wf = _load(whole_path)
    tiles = [_load(p) for p in tile_paths]
    mv, mf = _merge_exact(tiles)
    assert mv.shape == wv.shape
    assert {row.tobytes() for row in mv} == {row.tobytes() for row in wv}
    distance, match = cKDTree(wv).query(mv)
    assert distance.max() == 0
    assert np.unique(match).size == match.size                     # one to one
    assert _face_set(match[mf]) == _face_set(wf)
    assert _face_set(match[_boundary_edges(mf)]) == _face_set(_boundary_edges(wf))
    for v, f in tiles:                       # each tile's faces are a sub-mesh: none twice
        assert len(_face_set(f)) == len(f)
    assert sum(len(f) for _, f in tiles) == len(wf)               # every triangle exactly once


@pytest.fixture(scope="module")
def hill_tiles(tmp_path_factory):
    """A hill with exact normals cut into a 2×2 grid of PLY files, and their concatenation."""
    folder = tmp_path_factory.mktemp("hill_tiles")
    cloud = sample_surface("hill", n=3000, seed=5)
    cells = _grid_cells(cloud.points)
    paths, parts = [], []
    for i in range(4):
        part = cloud.subset(cells == i)
        paths.append(folder / f"tile{i}.ply")
        write_points_ply(part, paths[-1])
        parts.append(part)
    whole = folder / "whole.ply"
    write_points_ply(PointCloud(np.concatenate([p.points for p in parts]),
                                np.concatenate([p.normals for p in parts])), whole)
    return folder, [str(p) for p in paths], str(whole)


def test_seamless_single_output_is_the_concatenated_fit(hill_tiles):
    folder, paths, whole = hill_tiles
    runner = CliRunner()
    result = runner.invoke(main, ["fit", *paths, "--seamless", "-o", str(folder / "seam.ply"), "--level", "3"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(main, ["fit", whole, "-o", str(folder / "whole_fit.ply"), "--level", "3"])
    assert result.exit_code == 0, result.output
    assert (folder / "seam.ply").read_bytes() == (folder / "whole_fit.ply").read_bytes()


def test_seamless_tiles_merge_into_the_whole_fit(hill_tiles, tmp_path):
    folder, paths, whole = hill_tiles
    runner = CliRunner()
    assert runner.invoke(main, ["fit", whole, "-o", str(tmp_path / "whole.ply"), "--level", "3"]).exit_code == 0
    result = runner.invoke(main, ["fit", *paths, "--seamless", "-O", str(tmp_path / "out"), "--level", "3",
                                  "--report", str(tmp_path / "report.json")])
    assert result.exit_code == 0, result.output
    outputs = [tmp_path / "out" / (Path(p).stem + ".c1.ply") for p in paths]
    _assert_union_is_whole(tmp_path / "whole.ply", outputs)
    # no boundary edge of any tile output lies inside the survey: the tiles' boundary
    # edges that are not the whole mesh's boundary all pair up with a neighbour's edge
    wv, wf = _load(tmp_path / "whole.ply")
    whole_boundary = {tuple(sorted(map(tuple, wv[e]))) for e in _boundary_edges(wf)}
    inner = []
    for path in outputs:
        v, f = _load(path)
        inner += [tuple(sorted(map(tuple, v[e]))) for e in _boundary_edges(f)]
    inner = [e for e in inner if e not in whole_boundary]
    assert inner, "the tiles share no border: the test would prove nothing"
    _, counts = np.unique(np.asarray(inner).reshape(len(inner), -1), axis=0, return_counts=True)
    assert (counts == 2).all()


def test_real_lidar_ground_cut_into_four_las_files(tmp_path, crop_ground):
    cells = _grid_cells(crop_ground.xyz)
    paths = [crop_ground.write(tmp_path / f"ground{i}.las", cells == i) for i in range(4)]
    crop_ground.write(tmp_path / "ground.las", np.argsort(cells, kind="stable"))
    runner = CliRunner()
    args = ["--level", "2", "--normals", "estimate"]
    assert runner.invoke(main, ["fit", str(tmp_path / "ground.las"), "-o", str(tmp_path / "whole.ply"),
                                *args]).exit_code == 0
    result = runner.invoke(main, ["fit", *paths, "--seamless", "-O", str(tmp_path / "out"), *args])
    assert result.exit_code == 0, result.output
    _assert_union_is_whole(tmp_path / "whole.ply",
                           [tmp_path / "out" / f"ground{i}.c1.ply" for i in range(4)])
    # The survey's CRS (EPSG:2903, from the LAS header) travels to every tile as to the
    # whole fit: the same PLY header comment and the same .prj sidecar.
    whole_crs = _crs_comment(tmp_path / "whole.ply")
    assert whole_crs == "comment crs EPSG:2903"
    whole_prj = (tmp_path / "whole.prj").read_text()
    for i in range(4):
        assert _crs_comment(tmp_path / "out" / f"ground{i}.c1.ply") == whole_crs
        assert (tmp_path / "out" / f"ground{i}.c1.prj").read_text() == whole_prj
    assert sorted(p.name for p in (tmp_path / "out").iterdir() if p.name.startswith(".")) == []


def _crs_comment(path):
    """The `comment crs ...` line of a PLY header, or None."""
    header = Path(path).read_bytes().split(b"end_header", 1)[0].decode("ascii")
    return next((line for line in header.splitlines() if line.startswith("comment crs")), None)


def test_tiles_in_different_crs_are_refused_before_any_output(tmp_path, crop_ground):
    """c1mesh does not reproject: two tiles declaring different CRSs stop the run with one
    line naming both files, and nothing is written."""
    pytest.importorskip("pyproj")
    x = crop_ground.xyz[:, 0]
    half = x < np.median(x)
    paths = [crop_ground.write(tmp_path / f"part{i}.las", rows, epsg=epsg)
             for i, (rows, epsg) in enumerate(((half, 2903), (~half, 32613)))]
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["fit", *paths, "--seamless", "-O", str(out), "--level", "1"])
    assert result.exit_code == 1
    assert result.output.count("\n") == 1
    assert paths[0] in result.output and paths[1] in result.output and "reproject" in result.output
    assert list(out.iterdir()) == []


def test_failed_tile_is_named_and_leaves_no_output(hill_tiles, tmp_path, monkeypatch):
    import c1mesh.survey.distributed as distributed

    folder, paths, _ = hill_tiles
    real = distributed.run_tile

    def failing(task, target=None):
        if task.index == 2:
            raise MemoryError("simulated")
        return real(task, target)
    monkeypatch.setattr(distributed, "run_tile", failing)
    result = CliRunner().invoke(main, ["fit", *paths, "--seamless", "-O", str(tmp_path / "out"), "--level", "2"])
    assert result.exit_code == 1
    assert "tile " + paths[2] in result.output and result.output.count("\n") == 1
    assert list((tmp_path / "out").iterdir()) == []          # tiles 0 and 1 were written, then removed


def test_dask_local_cluster_writes_the_same_bytes(hill_tiles, tmp_path):
    """Tiles sent to a dask.distributed LocalCluster of two workers (threads, to start fast)."""
    distributed = pytest.importorskip("distributed")
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline.run import fit

    folder, paths, _ = hill_tiles
    options = FitOptions(level=2)
    outputs = {name: [str(tmp_path / name / (Path(p).stem + ".ply")) for p in paths] for name in ("here", "dask")}
    for dst in outputs.values():
        Path(dst[0]).parent.mkdir()
    here = fit(paths, None, options, outputs=outputs["here"]).report
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        report = fit(paths, None, options, outputs=outputs["dask"], tiles=TiledRun(scheduler=cluster.scheduler_address)).report
        workers = set(cluster.scheduler.workers)
    for a, b in zip(outputs["here"], outputs["dask"]):
        assert Path(a).read_bytes() == Path(b).read_bytes()
    rows = report["tiles"]
    assert [r["tile"] for r in rows] == paths
    assert {r["worker"] for r in rows} <= workers and len(workers) == 2
    assert all(r["worker"] not in workers for r in here["tiles"])
    assert [r["triangles"] for r in rows] == [4 * r["base_triangles"] for r in rows]
    assert [r["triangles"] for r in rows] == [r["triangles"] for r in here["tiles"]]


def test_jobs_run_tiles_in_other_processes(hill_tiles, tmp_path):
    import json
    import os
    import socket

    folder, paths, _ = hill_tiles
    runner = CliRunner()
    for name, jobs in (("here", "1"), ("dask", "2")):
        result = runner.invoke(main, ["fit", *paths, "--seamless", "-O", str(tmp_path / name), "--level", "2",
                                      "-j", jobs, "--report", str(tmp_path / f"{name}.json")])
        assert result.exit_code == 0, result.output
    for path in paths:
        out = Path(path).stem + ".c1.ply"
        assert (tmp_path / "here" / out).read_bytes() == (tmp_path / "dask" / out).read_bytes()
    rows = json.loads((tmp_path / "dask.json").read_text())["tiles"]
    assert [r["tile"] for r in rows] == paths
    assert all(r["worker"] != f"{socket.gethostname()}:{os.getpid()}" for r in rows)


def _free_port():
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_real_dask_scheduler_and_two_workers(hill_tiles, tmp_path, dask_processes):
    """`dask scheduler` + two `dask worker` processes on 127.0.0.1, then --scheduler."""
    import json

    folder, paths, _ = hill_tiles
    runner = CliRunner()
    result = runner.invoke(main, ["fit", *paths, "--seamless", "-O", str(tmp_path / "here"), "--level", "2"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(main, ["fit", *paths, "--seamless", "-O", str(tmp_path / "cluster"), "--level", "2",
                                  "--scheduler", dask_processes, "--report", str(tmp_path / "report.json")])
    assert result.exit_code == 0, result.output
    for path in paths:
        out = Path(path).stem + ".c1.ply"
        assert (tmp_path / "here" / out).read_bytes() == (tmp_path / "cluster" / out).read_bytes()
    workers = {row["worker"] for row in json.loads((tmp_path / "report.json").read_text())["tiles"]}
    assert len(workers) == 2


def test_unreachable_scheduler_is_one_line_and_no_output(hill_tiles, tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    import c1mesh.survey.distributed as distributed

    monkeypatch.setattr(distributed, "CONNECT_SECONDS", 1)
    folder, paths, _ = hill_tiles
    address = f"tcp://127.0.0.1:{_free_port()}"                 # nothing listens there
    result = CliRunner().invoke(main, ["fit", *paths, "--seamless", "-O", str(tmp_path / "out"),
                                       "--scheduler", address])
    assert result.exit_code == 1
    assert result.output.startswith(f"c1mesh: error: cannot reach the Dask scheduler {address}")
    assert result.output.count("\n") == 1
    assert not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("signum_name", ["SIGINT", "SIGTERM"])
def test_an_interrupted_seamless_run_leaves_no_tile_files(hill_tiles, tmp_path, signum_name):
    """Interrupt `--seamless -O` once the first tile's hidden file is complete (renamed from
    its .tmp into .NAME.tile-PID.ply) and later tiles are still running: nothing is left."""
    import os
    import signal
    import subprocess
    import sys
    import time

    signum = getattr(signal, signum_name)
    folder, paths, _ = hill_tiles
    out = tmp_path / "out"
    out.mkdir()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-m", "c1mesh.cli", "fit", *paths, "--seamless", "-O", str(out),
                             "--level", "24"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    deadline = time.monotonic() + 240
    while not any(".tile-" in p.name and not p.name.endswith(".tmp") for p in out.iterdir()):
        assert proc.poll() is None, f"c1mesh ended before a tile was written: {proc.stderr.read().decode()}"
        assert time.monotonic() < deadline, "no tile file appeared"
        time.sleep(0.01)
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, stderr
    assert stderr.decode().splitlines() == [f"c1mesh: error: interrupted ({signum_name})"]
    assert list(out.iterdir()) == []


def test_seamless_survey_dem_and_hillshade_equal_the_concatenated_fit(tmp_path, crop_ground):
    """`--seamless -o dem.tif` with rasters: the survey's GeoTIFFs hold the same cells as
    those of the fit of the concatenated file (and its CRS); -O refuses raster options."""
    rasterio = pytest.importorskip("rasterio")
    x = crop_ground.xyz[:, 0]
    west = x < np.median(x)
    paths = [crop_ground.write(tmp_path / name, rows)
             for name, rows in (("west.las", west), ("east.las", ~west),
                                ("whole.las", np.argsort(~west, kind="stable")))]
    runner = CliRunner()
    raster_args = ["--resolution", "4", "--slope", str(tmp_path / "{}slope.tif")]
    survey = runner.invoke(main, ["fit", *paths[:2], "--seamless", "-o", str(tmp_path / "dem.tif"),
                                  *[a.format("s") for a in raster_args]])
    assert survey.exit_code == 0, survey.output
    whole = runner.invoke(main, ["fit", paths[2], "-o", str(tmp_path / "whole.tif"),
                                 *[a.format("w") for a in raster_args]])
    assert whole.exit_code == 0, whole.output
    for ours, theirs in (("dem.tif", "whole.tif"), ("sslope.tif", "wslope.tif")):
        with rasterio.open(tmp_path / ours) as a, rasterio.open(tmp_path / theirs) as b:
            assert a.crs.to_epsg() == 2903 and a.transform == b.transform
            cells = a.read(1)
            assert np.isfinite(cells).mean() > 0.5
            np.testing.assert_array_equal(cells, b.read(1))
    refused = runner.invoke(main, ["fit", *paths[:2], "--seamless", "-O", str(tmp_path / "out"),
                                   "--hillshade", str(tmp_path / "h.tif")])
    assert refused.exit_code == 2 and "--seamless -o" in refused.output


def _assert_tiles_share_border_bits(whole_path, tile_paths):
    """The -O outputs join exactly (docs/tiles.md): a vertex held by several tiles has the
    same bits in each, so merging exactly equal vertices gives the whole fit's vertex
    count, and the merged vertices are the whole fit's, bit for bit.

    Which tiles hold a vertex is decided without its bits: every tile vertex is matched to
    the nearest vertex of the whole fit (the ground truth, fitted from one file)."""
    wv, _ = _load(whole_path)
    tiles = [_load(p) for p in tile_paths]
    tree = cKDTree(wv)
    holders = {}                                        # whole-fit vertex -> its copies in the tiles
    for v, _ in tiles:
        distance, match = tree.query(v)
        assert distance.max() <= 1e-9 * np.abs(wv).max()
        for index, row in zip(match.tolist(), v):
            holders.setdefault(index, []).append(row.tobytes())
    shared = {i: copies for i, copies in holders.items() if len(copies) > 1}
    assert len(shared) > 100, "the tiles share few border vertices: the test would prove little"
    differing = [i for i, copies in shared.items() if len(set(copies)) > 1]
    assert differing == [], f"{len(differing)} of {len(shared)} border vertices differ between tiles"
    merged, _ = _merge_exact(tiles)
    assert len(merged) == len(wv)
    assert {row.tobytes() for row in merged} == {row.tobytes() for row in wv}


@pytest.fixture(scope="module")
def large_hill_survey(tmp_path_factory):
    """A 2×2 survey large enough that each tile refines full blocks and a short last one
    (50k points with exact normals, level 2: about 25k base triangles per tile against
    21,845 per block), and the whole fit of its concatenation."""
    folder = tmp_path_factory.mktemp("large_hill")
    cloud = sample_surface("hill", n=50_000, seed=5)
    cells = _grid_cells(cloud.points)
    paths, parts = [], []
    for i in range(4):
        parts.append(cloud.subset(cells == i))
        paths.append(str(folder / f"tile{i}.ply"))
        write_points_ply(parts[-1], paths[-1])
    whole = folder / "whole.ply"
    write_points_ply(PointCloud(np.concatenate([p.points for p in parts]),
                                np.concatenate([p.normals for p in parts])), whole)
    result = CliRunner().invoke(main, ["fit", str(whole), "-o", str(folder / "whole.c1.ply"), "--level", "2"])
    assert result.exit_code == 0, result.output
    return paths, folder / "whole.c1.ply"


@pytest.mark.slow
@pytest.mark.parametrize("jobs", ["1", "2"])
def test_tiles_share_every_border_vertex_to_the_bit(large_hill_survey, tmp_path, jobs):
    """Issue 21: the four -O outputs merged into 23 more vertices than the whole fit,
    border vertices written with different bits by the two tiles holding them."""
    paths, whole = large_hill_survey
    result = CliRunner().invoke(main, ["fit", *paths, "--seamless", "-O", str(tmp_path), "--level", "2",
                                       "-j", jobs])
    assert result.exit_code == 0, result.output
    _assert_tiles_share_border_bits(whole, [tmp_path / (Path(p).stem + ".c1.ply") for p in paths])


@pytest.mark.slow
def test_tiles_on_a_dask_cluster_share_every_border_vertex_to_the_bit(large_hill_survey, tmp_path):
    distributed = pytest.importorskip("distributed")
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline.run import fit

    paths, whole = large_hill_survey
    outputs = [str(tmp_path / (Path(p).stem + ".ply")) for p in paths]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        fit(paths, None, FitOptions(level=2), outputs=outputs, tiles=TiledRun(scheduler=cluster.scheduler_address))
    _assert_tiles_share_border_bits(whole, outputs)


@pytest.mark.parametrize("columns", [2, 3])
def test_bounds_are_the_columns_least_and_largest(columns):
    """core.tile.bounds against numpy's reduction over the rows, on points with negative
    and repeated values, a NaN in one column (it propagates into that column only) and
    integer points (their dtype kept)."""
    from c1mesh.core.tile import bounds

    rng = np.random.default_rng(5)
    points = np.round(rng.normal(0.0, 1e3, (10_001, columns)), 1)
    lower, upper = bounds(points)
    np.testing.assert_array_equal(lower, points.min(axis=0))
    np.testing.assert_array_equal(upper, points.max(axis=0))
    points[17, 1] = np.nan
    lower, upper = bounds(points)
    assert np.isnan(lower[1]) and np.isnan(upper[1]) and lower[0] == points[:, 0].min()
    whole = rng.integers(-50, 50, (999, columns))
    lower, upper = bounds(whole)
    assert lower.dtype == whole.dtype and list(lower) == list(whole.min(axis=0)) and list(upper) == list(whole.max(axis=0))


@pytest.mark.parametrize("columns", [1, 3])
def test_row_min_and_row_any_are_the_reductions_over_each_row(columns):
    """core.tile.row_min and row_any against numpy's min(axis=1) and any(axis=1): integer
    triangle lists (their dtype kept, the input untouched), a non-contiguous view, and
    flags with none, one or every value set in a row."""
    from c1mesh.core.tile import row_any, row_min

    rng = np.random.default_rng(9)
    triangles = rng.integers(-5, 1_000_000, (20_001, columns))
    before = triangles.copy()
    least = row_min(triangles)
    assert least.dtype == triangles.dtype and np.array_equal(least, triangles.min(axis=1))
    assert np.array_equal(triangles, before)
    view = triangles[::3, ::-1]
    assert np.array_equal(row_min(view), view.min(axis=1))
    flags = rng.random((20_001, columns)) < 0.2
    flags[0], flags[1] = False, True
    assert np.array_equal(row_any(flags), flags.any(axis=1)) and not row_any(flags)[0] and row_any(flags)[1]


def test_finite_rows_are_the_rows_without_nan_or_inf():
    """core.tile.finite_rows against np.isfinite(...).all(axis=1): NaN, +inf and -inf in
    each column, a row with two of them, one-column points."""
    from c1mesh.core.tile import finite_rows

    points = np.random.default_rng(6).normal(size=(1000, 3))
    points[[3, 10, 500], [0, 1, 2]] = [np.nan, np.inf, -np.inf]
    points[700, :2] = np.nan
    np.testing.assert_array_equal(finite_rows(points), np.isfinite(points).all(axis=1))
    assert finite_rows(points).sum() == 996
    np.testing.assert_array_equal(finite_rows(points[:, 2:]), np.isfinite(points[:, 2]))
