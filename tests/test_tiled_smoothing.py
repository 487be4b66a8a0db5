"""The smoothing fit in tiles (c1mesh.survey.smoothing_runs) against the whole fit.

Ground truth: the in-memory smoothing fit of the same points (`c1mesh fit --smooth S`,
pipeline.driver.build_surface → stages.smoothing.smooth_fit on the whole mesh), which
never cuts the survey. Both measure the spacing h on the same sample of positions (every
one below 40,000), so both use the same λ and the tiled fit may differ only through its
halos' cut. Planes are reproduced by every tile's solve whatever its halo (the energy of a
plane is zero).
"""
from __future__ import annotations

import io
import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from scipy.spatial import cKDTree

laspy = pytest.importorskip("laspy")

from c1mesh.cli import main
from c1mesh.pipeline.driver import FitOptions
from c1mesh.stages import smoothing
from c1mesh.stages.smoothing import HEIGHT_GRADIENTS_WEIGHT
from c1mesh.core.plan import TiledRun
from c1mesh.pipeline.run import fit
from test_smoothing import interior_or_at_limit


def _terrain_las(path, n, seed=0, noise=0.02, plane=False, plane_noise=0.0):
    """n points over a square of side sqrt(n / 4) (mean spacing 0.5): a smooth terrain with
    Gaussian noise, or with plane=True the plane z = 100 + 0.3 x − 0.2 y without noise (on
    the file's grid: x, y in mm, z in 0.1 mm, so the plane's heights are stored exactly)
    or with Gaussian noise of σ plane_noise."""
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001, 0.001, 0.0001], [500000, 4000000, 0]
    rng = np.random.default_rng(seed)
    side = np.sqrt(n / 4.0)
    x, y = np.round(rng.uniform(0, side, n), 3), np.round(rng.uniform(0, side, n), 3)   # the LAS's grid
    if plane:
        z = 100 + 0.3 * x - 0.2 * y + (rng.normal(0, plane_noise, n) if plane_noise else 0.0)
    else:
        z = 100 + 3 * np.sin(x / 17) * np.cos(y / 23) + rng.normal(0, noise, n)
    record = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    record.x, record.y, record.z = x + 500000, y + 4000000, z
    record.classification = np.full(n, 2, np.uint8)
    with laspy.open(str(path), mode="w", header=header) as writer:
        writer.write_points(record)


def _heights_at(reference: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """The heights of reference's vertices at vertices' (x, y), which must be among them."""
    distance, nearest = cKDTree(reference[:, :2]).query(vertices[:, :2])
    assert distance.max() < 1e-9
    return reference[nearest, 2]


def _in_memory(tmp_path, source, strength, *more: str) -> tuple[np.ndarray, dict]:
    out, report = tmp_path / "whole.ply", tmp_path / "whole.json"
    result = CliRunner().invoke(main, ["fit", str(source), "--classes", "2", "--level", "1", "--smooth",
                                       str(strength), *more, "-o", str(out), "--report", str(report)])
    assert result.exit_code == 0, result.output
    return trimesh.load(out, process=False).vertices, json.loads(report.read_text())


@pytest.mark.parametrize("strength", [3.0, 100.0])
def test_tiled_smoothing_matches_the_whole_fit(tmp_path, strength):
    source = tmp_path / "terrain.las"
    _terrain_las(source, 12000, seed=2)
    whole, whole_report = _in_memory(tmp_path, source, strength)
    report = fit(source, tmp_path / "tiled.ply", replace(FitOptions(classes=[2], level=1, smooth=strength), memory=10**9), tiles=TiledRun(per_tile=1500)).report
    assert report["tiles"] == 9
    fitted = report["smoothing"]
    # one h: the stacking test's, measured alike in tiles and in memory (the frames' local
    # coordinates may differ in a last bit: this survey sits 4,000 km from its origin)
    assert fitted["spacing"] == report["points"]["spacing"]
    assert fitted["spacing"] == pytest.approx(whole_report["points"]["spacing"], rel=1e-12)
    assert fitted["lam"] == pytest.approx(whole_report["smoothing"]["lam"], rel=1e-12)
    # both paths fit the heights' own gradients as data, with the same weight
    assert whole_report["smoothing"]["gradient_weight"] == fitted["gradient_weight"] == HEIGHT_GRADIENTS_WEIGHT > 0
    vertices = trimesh.load(tmp_path / "tiled.ply", process=False).vertices
    assert len(vertices) == len(whole)
    difference = np.abs(vertices[:, 2] - _heights_at(whole, vertices))
    rms = whole_report["smoothing"]["residual_rms"]
    assert 0.015 < rms < 0.025                                 # the 2 cm noise, mostly removed from the fit
    assert difference.max() < 0.01 * rms
    assert fitted["residual_rms"] == pytest.approx(rms, rel=0.01)


def test_tiles_fit_the_plans_scheme(tmp_path):
    """--scheme enters the tiled solve as it enters the in-memory fit (the tiles once fitted
    the sextic's energy whatever the scheme, and refined with the scheme asked for: 0.1 m
    off here). In one tile the two fits are the same solve. (In 9 tiles the quintic's
    heights differed from the whole fit's by up to 0.05 m, the sextic's by under 2e-4 m:
    probably because the quintic does not reproduce planes, so the plane each tile's fit
    subtracts, smoothing.weighted_plane, changes its result.)"""
    source = tmp_path / "terrain.las"
    _terrain_las(source, 4000, seed=3)
    whole, whole_report = _in_memory(tmp_path, source, 3.0, "--scheme", "quintic")
    report = fit(source, tmp_path / "tiled.ply", replace(FitOptions(classes=[2], level=1, smooth=3.0, scheme="quintic"), memory=10**9), tiles=TiledRun(per_tile=4000)).report
    assert report["tiles"] == 1
    vertices = trimesh.load(tmp_path / "tiled.ply", process=False).vertices
    difference = np.abs(vertices[:, 2] - _heights_at(whole, vertices))
    assert difference.max() < 1e-6 * whole_report["smoothing"]["residual_rms"]


@pytest.mark.slow
def test_the_tiled_difference_shrinks_with_the_halo(tmp_path, monkeypatch):
    """A halo too short to hold the fit's reach shows: the differences fall as it grows."""
    source = tmp_path / "terrain.las"
    _terrain_las(source, 12000, seed=2)
    whole, whole_report = _in_memory(tmp_path, source, 100.0)
    largest = []
    for lengths in (8.0, 16.0, 24.0, 32.0):
        monkeypatch.setattr(smoothing, "HALO_LENGTHS", lengths)
        fit(source, tmp_path / "tiled.ply", replace(FitOptions(classes=[2], level=1, smooth=100.0), memory=10**9), tiles=TiledRun(per_tile=1500)).report
        vertices = trimesh.load(tmp_path / "tiled.ply", process=False).vertices
        largest.append(np.abs(vertices[:, 2] - _heights_at(whole, vertices)).max())
    rms = whole_report["smoothing"]["residual_rms"]
    assert largest[0] > 0.05 * rms                 # the cut is felt at 8 smoothing lengths
    assert all(a > b for a, b in zip(largest, largest[1:]))
    assert largest[-1] < 0.001 * rms


def test_tiles_reproduce_a_plane_whatever_their_halo(tmp_path, monkeypatch):
    source = tmp_path / "plane.las"
    _terrain_las(source, 6000, plane=True)
    monkeypatch.setattr(smoothing, "HALO_LENGTHS", 0.5)    # the least halo: 4 final edges
    report = fit(source, tmp_path / "tiled.ply", replace(FitOptions(classes=[2], level=2, smooth=1000.0), memory=10**9), tiles=TiledRun(per_tile=700)).report
    assert report["tiles"] == 9
    mesh = trimesh.load(tmp_path / "tiled.ply", process=False)
    x, y = mesh.vertices[:, 0] - 500000, mesh.vertices[:, 1] - 4000000
    assert np.abs(mesh.vertices[:, 2] - (100 + 0.3 * x - 0.2 * y)).max() < 1e-9
    normal = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
    assert np.abs(mesh.vertex_normals @ normal - 1).max() < 1e-9


@pytest.mark.slow
def test_cli_smooths_auto_in_tiles_and_the_workers_do_not_change_a_byte(tmp_path, monkeypatch):
    import c1mesh.pipeline.bounded_fit as bounded_fit

    monkeypatch.setattr(bounded_fit, "tiles_at_once", lambda memory, jobs, per_point=None: jobs)  # -j 2 under 1M
    source = tmp_path / "terrain.las"
    _terrain_las(source, 24000, seed=4)
    args = ["fit", str(source), "--classes", "2", "--level", "1", "--smooth", "auto", "--memory", "1M"]
    here = CliRunner().invoke(main, args + ["-o", str(tmp_path / "here.ply"), "--report", str(tmp_path / "r.json")])
    assert here.exit_code == 0, here.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["tiles"] == 4
    smoothing = report["smoothing"]
    assert len(smoothing["cv_curve"]) >= 4 and smoothing["strength"] > 0
    scores = dict((s, r) for s, r in smoothing["cv_curve"])
    assert scores[smoothing["strength"]] == min(scores.values())
    assert interior_or_at_limit(SimpleNamespace(**smoothing)) == "interior"   # 2 cm noise on a terrain
    assert smoothing["edf"] < 0.8 * report["points"]["kept"]          # it smooths
    assert smoothing["residual_rms"] == pytest.approx(0.02, rel=0.25)   # about the noise it removed
    assert report["overshoot"]["gradients_limited"] == 0
    assert "noise floors" not in report["seconds"] and "smoothing" in report["seconds"]
    pool = CliRunner().invoke(main, args + ["-o", str(tmp_path / "pool.ply"), "-j", "2",
                                            "--report", str(tmp_path / "pool.json")])
    assert pool.exit_code == 0, pool.output
    assert json.loads((tmp_path / "pool.json").read_text())["scheduler"] == "2 local processes"
    assert (tmp_path / "pool.ply").read_bytes() == (tmp_path / "here.ply").read_bytes()
    whole = CliRunner().invoke(main, args[:-2] + ["-o", str(tmp_path / "whole.ply"),
                                                  "--report", str(tmp_path / "whole.json")])
    assert whole.exit_code == 0, whole.output
    in_memory = json.loads((tmp_path / "whole.json").read_text())["smoothing"]
    # the search ran on the same windows of the survey: the same strengths tried, the same
    # choice, the same held-out RMS in height units but for rounding (the two normalise
    # their heights by another plane and scale; measured 1e-8 to 3e-5 apart)
    assert [s for s, _ in in_memory["cv_curve"]] == [s for s, _ in smoothing["cv_curve"]]
    assert in_memory["strength"] == smoothing["strength"]
    assert np.allclose([r for _, r in in_memory["cv_curve"]], [r for _, r in smoothing["cv_curve"]], rtol=1e-4)


def test_tiles_report_a_search_that_reached_its_limit(tmp_path):
    """Noise alone on a plane (σ 0.3, the points 0.5 apart), fitted in tiles: the truth
    is the plane, which only s → ∞ gives, so the search tile's CV curve falls up to the
    search's limit, and the tiled report says so, as the in-memory one does (test_smoothing)."""
    source = tmp_path / "noisy_plane.las"
    _terrain_las(source, 24000, seed=2, plane=True, plane_noise=0.3)
    result = CliRunner().invoke(main, ["fit", str(source), "--classes", "2", "--level", "1", "--smooth", "auto",
                                       "--memory", "1M", "-o", str(tmp_path / "out.ply"),
                                       "--report", str(tmp_path / "r.json")])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["tiles"] == 4
    assert interior_or_at_limit(SimpleNamespace(**report["smoothing"])) == "high limit"


def test_lattice_search_in_tiles_keeps_the_whole_fits_least_strength(tmp_path):
    """--smooth auto --spacing beyond --memory: the tiled search starts at the same least
    strength as the in-memory one (stages.lattice_mesh.least_strength, from the support's
    cells and the survey's points) and chooses the same s."""
    source = tmp_path / "terrain.las"
    _terrain_las(source, 12000, seed=2)
    _, whole_report = _in_memory(tmp_path, source, "auto", "--spacing", "1")
    options = FitOptions(classes=[2], level=1, smooth="auto", spacing=1.0, memory=10**9)
    report = fit(source, tmp_path / "tiled.ply", options, tiles=TiledRun(per_tile=1500)).report
    assert report["tiles"] == 9
    least = [min(s for s, _ in r["smoothing"]["cv_curve"]) for r in (report, whole_report)]
    assert least[0] == least[1] > 1e-6
    assert report["smoothing"]["strength"] == whole_report["smoothing"]["strength"]


@pytest.mark.parametrize("multigrid", [False, True])
def test_lattice_vertices_in_tiles_are_the_whole_fits(tmp_path, monkeypatch, multigrid):
    """--spacing beyond --memory (survey.lattice_runs): each tile decides the lattice cells
    and nodes of its cell from the heights around it, so the vertices are the in-memory
    fit's, node for node (9 tiles; cells straddle the tiles' borders), and each tile fits
    every height in its halo, so the surface is the whole fit's within the tiled solve's
    difference (as test_tiled_smoothing_matches_the_whole_fit bounds it). The nodes are no
    unused points: the warning counts the data the triangles cover, as in memory.
    multigrid: the tiles solve by the lattice's multigrid (MULTIGRID_FROM lowered to 0 for
    the tiled fit), as the in-memory fit does from MULTIGRID_FROM nodes."""
    from c1mesh.stages import lattice_mesh
    from c1mesh.survey import smoothing_runs

    source = tmp_path / "terrain.las"
    _terrain_las(source, 12000, seed=2)
    whole, whole_report = _in_memory(tmp_path, source, 3.0, "--spacing", "1")
    options = FitOptions(classes=[2], level=1, smooth=3.0, spacing=1.0, memory=10**9)
    solvers = []
    solve = smoothing_runs.smooth_tile
    monkeypatch.setattr(smoothing_runs, "smooth_tile",
                        lambda *a, **k: solvers.append(k["lattice"] is not None) or solve(*a, **k))
    if multigrid:
        monkeypatch.setattr(lattice_mesh, "MULTIGRID_FROM", 0)
    report = fit(source, tmp_path / "tiled.ply", options, tiles=TiledRun(per_tile=1500)).report
    assert report["tiles"] == 9
    assert solvers == [multigrid] * 9
    vertices = trimesh.load(tmp_path / "tiled.ply", process=False).vertices
    assert len(vertices) == len(whole) == whole_report["points"]["kept"] == report["points"]["kept"]
    assert len(whole) < 12000 / 3                  # about one node per four points at 0.5 spacing
    difference = np.abs(vertices[:, 2] - _heights_at(whole, vertices))     # the same positions
    rms = whole_report["smoothing"]["residual_rms"]
    assert difference.max() < 0.01 * rms
    assert report["smoothing"]["lam"] == pytest.approx(whole_report["smoothing"]["lam"], rel=1e-12)
    # the lattice reaches the support's reach beyond the data: none is outside
    assert report["smoothing"]["outside"] == whole_report["smoothing"]["outside"] == 0
    assert report["smoothing"]["residual_rms"] == pytest.approx(rms, rel=1e-3)      # over the data points
    assert report["smoothing"]["lattice"] == whole_report["smoothing"]["lattice"]
    assert report["smoothing"]["lattice"]["spacing"] == 1.0 and report["smoothing"]["lattice"]["nodes"] >= len(whole)
    assert report["warnings"] == whole_report["warnings"] == []


def _pairs_las(path, seed: int) -> None:
    """Class-2 points in pairs 0.1 m apart, the pairs 10 m apart: the points' spacing h is
    about 0.1, and no 0.9 m square holds 3 of them."""
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(12) * 10.0, np.arange(12) * 10.0)
    first = np.column_stack([i.ravel(), j.ravel()]) + rng.uniform(0, 1, (144, 2))
    xy = np.concatenate([first, first + [0.1, 0.0]])
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = np.array([0.001] * 3), np.array([500000.0, 4000000.0, 0.0])
    las = laspy.LasData(header)
    las.x, las.y = xy[:, 0] + 500000.0, xy[:, 1] + 4000000.0
    las.z = 100.0 + 0.05 * xy[:, 0] + rng.normal(0, 0.01, len(xy))
    las.classification = np.full(len(xy), 2, dtype=np.uint8)
    las.write(str(path))


@pytest.mark.parametrize("memory", [[], ["--memory", "1M"]])
@pytest.mark.parametrize("spacing, words", [
    ("0.1", "no cell of the --spacing 0.1 lattice has 3 points"),
    ("0.001", "--spacing 0.001 is finer than a quarter of the points' spacing")])
def test_a_lattice_too_fine_for_the_points_is_one_line_and_no_output(tmp_path, memory, spacing, words):
    """--spacing finer than h/4, or a lattice where no cell has 3 points within its
    (2R + 1)^2 cells: one line that says so, in memory and beyond --memory, no output."""
    source = tmp_path / "pairs.las"
    _pairs_las(source, 4)
    out = tmp_path / "out.ply"
    run = CliRunner().invoke(main, ["fit", str(source), "-o", str(out), "--smooth", "1", "--spacing", spacing, *memory])
    assert run.exit_code == 1, run.output
    assert words in run.output
    assert len(run.output.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.parametrize("spacing", [None, 1.0])
def test_tiled_smoothing_on_a_dask_cluster_writes_the_same_bytes(tmp_path, spacing):
    """The tiled smoothing fit on Dask writes the bytes the local processes write: vertices
    at the points, and on the --spacing lattice (survey.lattice_runs)."""
    distributed = pytest.importorskip("distributed")
    source = tmp_path / "terrain.las"
    _terrain_las(source, 4000, seed=3)
    options = FitOptions(classes=[2], level=2, smooth=10.0, spacing=spacing)
    here = fit(source, tmp_path / "here.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=450)).report
    assert here["tiles"] == 9
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        dask = fit(source, tmp_path / "dask.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=450, scheduler=cluster.scheduler_address)).report
    assert (tmp_path / "dask.ply").read_bytes() == (tmp_path / "here.ply").read_bytes()
    assert dask["smoothing"] == {**here["smoothing"], "seconds": dask["smoothing"]["seconds"]}


def _two_inputs(tmp_path) -> list:
    """Two terrain LAS files of 3,000 points each, the second east of the first."""
    sources = [tmp_path / f"part{i}.las" for i in range(2)]
    for i, source in enumerate(sources):
        _terrain_las(source, 3000, seed=10 + i)
    with laspy.open(str(sources[1])) as reader:
        points = reader.read()
    points.x = points.x + np.sqrt(3000 / 4.0)
    points.write(str(sources[1]))
    return sources


@pytest.mark.parametrize("spacing", [[], ["--spacing", "1"]])
def test_seamless_tiles_of_a_smoothing_fit_join_into_its_whole_mesh(tmp_path, spacing):
    """`--seamless -O` with --smooth: each input's part is cut from the one fitted surface,
    so the parts' vertices are the whole survey fit's, bit for bit; with --spacing (lattice
    nodes, each owned by the input of its nearest point) too, and beyond --memory each
    input gets the same triangles (as many faces) as in memory."""
    sources = _two_inputs(tmp_path)
    args = ["fit", *map(str, sources), "--seamless", "--classes", "2", "--level", "2", "--smooth", "5", *spacing]
    whole = CliRunner().invoke(main, args + ["-o", str(tmp_path / "whole.ply")])
    assert whole.exit_code == 0, whole.output
    parts = CliRunner().invoke(main, args + ["-O", str(tmp_path / "out"), "--report", str(tmp_path / "r.json")])
    assert parts.exit_code == 0, parts.output
    assert json.loads((tmp_path / "r.json").read_text())["smoothing"]["strength"] == 5.0
    whole_rows = {row.tobytes() for row in trimesh.load(tmp_path / "whole.ply", process=False).vertices}
    part_rows = set()
    for source in sources:
        part_rows |= {row.tobytes() for row in
                      trimesh.load(tmp_path / "out" / (source.stem + ".c1.ply"), process=False).vertices}
    assert part_rows == whole_rows
    if spacing:
        (tmp_path / "tiled").mkdir()
        outputs = [tmp_path / "tiled" / (source.stem + ".c1.ply") for source in sources]
        options = FitOptions(classes=[2], level=2, smooth=5.0, spacing=1.0, memory=10**9)
        report = fit([str(s) for s in sources], None, options, outputs=outputs, tiles=TiledRun(per_tile=1500)).report
        assert report["tiles"] > 1
        for source in sources:
            name = source.stem + ".c1.ply"
            faces = [len(trimesh.load(tmp_path / d / name, process=False).faces) for d in ("out", "tiled")]
            assert faces[0] == faces[1] > 0


def test_the_smoothing_fit_has_the_same_bits_on_one_blas_thread_and_on_two():
    """Its bytes must not depend on the machine's cores or where a tile ran (CHOLMOD's
    supernodal kernels round differently on two BLAS threads)."""
    from c1mesh.core.threads import blas_threads
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.stages.smoothing import SmoothingControl, SmoothingData, smooth_fit

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 120, (20000, 2))
    z = np.sin(xy[:, 0] / 20) + rng.normal(0, 0.02, len(xy))
    triangles = delaunay(xy)
    fits = []
    for threads in (1, 2):
        with blas_threads(threads):
            fits.append(smooth_fit(xy, triangles, SmoothingData(z, spacing=0.5), SmoothingControl(strength=3.0)))
    assert fits[0].values.tobytes() == fits[1].values.tobytes()
    assert fits[0].gradients.tobytes() == fits[1].gradients.tobytes()


def test_a_smoothing_fit_is_sized_by_its_own_memory_per_point():
    """The Cholesky factor makes a smoothing fit about 4x the exact fit's memory a point
    (sizing.SMOOTHING_BYTES_PER_POINT): the same budget tiles it sooner, in smaller tiles."""
    from c1mesh.core.plan import SurfaceSettings
    from c1mesh.survey.sizing import (BYTES_PER_POINT, SMOOTHING_BYTES_PER_POINT, fits_in_memory,
                                          point_bytes, points_per_tile)

    exact, smooth = SurfaceSettings(), SurfaceSettings(strength="auto")
    assert point_bytes(exact) == BYTES_PER_POINT and point_bytes(smooth) == SMOOTHING_BYTES_PER_POINT
    assert point_bytes(SurfaceSettings(strength=3.0, spacing=2.0)) == BYTES_PER_POINT
    assert fits_in_memory(1_000_000, 2 * 10**9, point_bytes(exact))
    assert not fits_in_memory(1_000_000, 2 * 10**9, point_bytes(smooth))
    assert points_per_tile(2 * 10**9, SMOOTHING_BYTES_PER_POINT) * SMOOTHING_BYTES_PER_POINT * 4 <= 2 * 10**9


def test_each_tile_reports_its_smoothing_solve(tmp_path):
    source = tmp_path / "terrain.las"
    _terrain_las(source, 4000, seed=3)
    passes = []
    report = fit(source, tmp_path / "out.ply", replace(FitOptions(classes=[2], level=1, smooth=10.0), memory=10**9), tiles=TiledRun(per_tile=450, on_tile=lambda name, done, tiles: passes.append(name))).report
    assert passes.count("smoothing") == report["tiles"] == 9
    for row in report["tile_tasks"]:
        assert row["passes"]["smoothing"]["seconds"] >= 0 and row["passes"]["smoothing"]["worker"]


def test_the_smoothing_totals_do_not_depend_on_the_order_the_tiles_finish_in():
    """A pool or Dask hands the tiles' solves back in completion order; the report's edf and
    residual RMS must be the same bits in any order (the Dask bytes test once failed on the
    last bit of a plain sum of edfs)."""
    from c1mesh.stages.smoothing import TileSolve, solve_totals

    rng = np.random.default_rng(8)
    solves = [TileSolve(own=int(n), squares=float(q), largest=1.0, halo_vertices=int(n) + 37,
                        edf=float(e), turned=0)
              for n, q, e in zip(rng.integers(100, 900, 40), rng.random(40) * 1e-3, rng.random(40) * 300)]
    plain = {sum(s.edf * s.own / s.halo_vertices for s in order)
             for order in (solves, solves[::-1], [solves[i] for i in rng.permutation(40)])}
    assert len(plain) > 1                      # these data do expose a plain sum's order
    totals = {solve_totals([solves[i] for i in rng.permutation(40)]) for _ in range(6)}
    assert len(totals) == 1
    assert totals.pop()[0] == sum(s.own for s in solves)


def _hidden_leftovers(*folders) -> list[str]:
    """Every `.c1mesh*` entry in the temporary folder and every hidden entry beside the
    outputs: the spill, halo and fitted files a tiled fit makes start with '.'."""
    return sorted(str(p) for folder in folders for p in Path(folder).iterdir() if p.name.startswith("."))


@pytest.mark.parametrize("runner", ["here", "processes", "dask-threads", "dask-processes"])
def test_tiled_smoothing_leaves_no_temporary_file(tmp_path, monkeypatch, runner):
    """Every tile's solve runs where the runner puts it; a worker process must not make
    temporary files that only it would know to remove (the .smooth-halo files once did)."""
    import tempfile

    import c1mesh.pipeline.bounded_fit as bounded_fit

    temporary, out = tmp_path / "tmp", tmp_path / "out"
    temporary.mkdir(), out.mkdir()
    monkeypatch.setenv("TMPDIR", str(temporary))
    monkeypatch.setattr(tempfile, "tempdir", None)
    source = tmp_path / "terrain.las"
    _terrain_las(source, 24000, seed=4)
    options = FitOptions(classes=[2], level=1, smooth=10.0)
    if runner.startswith("dask"):
        distributed = pytest.importorskip("distributed")
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=runner == "dask-processes",
                                      dashboard_address=None) as cluster:
            report = fit(source, out / "fit.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=6000, scheduler=cluster.scheduler_address)).report
    else:
        monkeypatch.setattr(bounded_fit, "tiles_at_once", lambda memory, jobs, per_point=None: jobs)
        args = ["fit", str(source), "--classes", "2", "--level", "1", "--smooth", "10", "--memory", "1M",
                "--report", str(tmp_path / "r.json")] + (["-j", "2"] if runner == "processes" else [])
        result = CliRunner().invoke(main, args + ["-o", str(out / "fit.ply")])
        assert result.exit_code == 0, result.output
        report = json.loads((tmp_path / "r.json").read_text())
        if runner == "here":                   # a stream, as -o -: the temporary files go to $TMPDIR
            fit(source, io.BytesIO(), replace(options, output_format="ply", memory=10**9), tiles=TiledRun(per_tile=6000)).report
    assert report["tiles"] > 1 and (out / "fit.ply").stat().st_size > 0
    assert _hidden_leftovers(temporary, out) == []


def _cut_into_tiles(xy, z, gradients, triangles, side: float, reach: float):
    """Brute force, as survey/ cuts a survey: the Tiles (core.tile) of square cells of
    `side` over xy, each reading the vertices within `reach` of its cell (its halo) and
    the triangles with every corner read; and each tile's own triangles (survey numbers),
    a triangle owned by the cell of its centroid."""
    from c1mesh.core.tile import VERTEX, Tile

    cell = np.floor(xy / side).astype(int)
    owner = np.floor(xy[triangles].mean(axis=1) / side).astype(int)
    tiles = []
    for i, j in sorted({tuple(c) for c in cell}):
        low, high = np.array([i, j]) * side - reach, np.array([i + 1, j + 1]) * side + reach
        read = np.flatnonzero(((xy >= low) & (xy < high)).all(axis=1))
        rows = np.full(len(xy), -1)
        rows[read] = np.arange(len(read))
        inside = (rows[triangles] >= 0).all(axis=1)
        records = np.empty(len(read), VERTEX)
        records["index"], records["x"], records["y"], records["z"] = read, xy[read, 0], xy[read, 1], z[read]
        records["gx"], records["gy"] = gradients[read, 0], gradients[read, 1]
        own = (cell[read] == [i, j]).all(axis=1)
        tiles.append((Tile(records, rows[triangles[inside]], own), triangles[(owner == [i, j]).all(axis=1)]))
    return tiles


@pytest.mark.parametrize("strength", [1.0, 10.0])
def test_tiles_with_a_generous_halo_give_the_one_tile_solve(strength):
    """The stage's run (smoothing.smooth_tile) on a small survey cut into 3 x 3 tiles, each
    reading HALO_LENGTHS smoothing lengths beyond its cell, against the same run on the
    survey's one tile (the in-memory fit): every vertex gets one height and gradient, from
    its own tile, within 1e-3 of the noise σ of the one-tile fit's (the fit's influence
    decays over a few smoothing lengths; docs/smoothing.md measured 7e-4 of the residual
    RMS at 24 lengths); every own edge has the one-tile fit's direction, up to its sign
    (limiter.edge_directions is local); and the report's reduce over the tiles
    (smoothing.combined_fit) is the same in any order of the tiles, with the one-tile
    fit's residual RMS over every vertex."""
    from c1mesh.core.tile import Tile
    from c1mesh.engine.topology import edge_table
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.pipeline.steps import compact_vertices
    from c1mesh.stages.smoothing import (SmoothingControl, SmoothingRun, combined_fit, smooth_tile,
                                         smoothing_reach)
    from c1mesh.stages.trim import trim_mesh

    rng = np.random.default_rng(5)
    spacing, sigma = 0.5, 0.02
    xy = rng.uniform(0, 45, (8100, 2))
    used, triangles = compact_vertices(xy, trim_mesh(xy, delaunay(xy))[0].triangles)   # no long hull slivers
    xy = xy[used]
    slope = np.column_stack([0.3 * np.cos(xy[:, 0] / 5), -0.2 * np.sin(xy[:, 1] / 7)])
    z = 1.5 * np.sin(xy[:, 0] / 5) + 1.4 * np.cos(xy[:, 1] / 7) + rng.normal(0, sigma, len(xy))
    run = SmoothingRun(SmoothingControl(strength), spacing, "limit", 0.5)
    whole = smooth_tile(Tile.whole(xy, z, slope, triangles), run)
    table = edge_table(triangles, len(xy))
    values, gradients, count = np.full(len(xy), np.nan), np.full((len(xy), 2), np.nan), 0
    solves = []
    for tile, owned in _cut_into_tiles(xy, z, slope, triangles, 15.0, smoothing_reach(strength, spacing)):
        assert not tile.own.all()
        smoothed = smooth_tile(tile, run, owned)
        survey = tile.records["index"][tile.own]
        assert np.isnan(values[survey]).all()           # one value a vertex: from its own tile
        values[survey], gradients[survey] = smoothed.values, smoothed.gradients
        solves.append(smoothed.solve)
        corners = np.unique(owned)                      # the run's edge order: its own triangles by corner
        local = np.searchsorted(corners, owned)
        pairs = corners[edge_table(local, len(corners)).edges]
        at = np.searchsorted(table.edges[:, 0] * len(xy) + table.edges[:, 1], pairs[:, 0] * len(xy) + pairs[:, 1])
        expected = whole.directions[at]
        assert ((smoothed.directions == expected).all(axis=1) | (smoothed.directions == -expected).all(axis=1)).all()
        count += len(pairs)
    assert count >= len(table.edges)                    # every edge, once or from both its tiles
    assert min(s.halo_vertices for s in solves) < 0.8 * len(xy)     # a corner tile's halo, not the survey
    assert np.abs(values - whole.values).max() < 1e-3 * sigma    # measured 1.5e-4 σ (s = 1), 3e-5 σ (s = 10)
    assert np.abs(gradients - whole.gradients).max() < 1e-3 * sigma / spacing

    reports = {json.dumps(combined_fit([solves[i] for i in rng.permutation(len(solves))], run, None, {}).as_dict())
               for _ in range(5)}
    assert len(reports) == 1
    report = json.loads(reports.pop())
    assert sum(s.own for s in solves) == len(xy)
    assert report["residual_rms"] == pytest.approx(np.sqrt(np.mean((z - values) ** 2)), rel=1e-12)
    assert report["residual_max"] == np.abs(z - values).max()
    assert report["residual_rms"] == pytest.approx(np.sqrt(np.mean((z - whole.values) ** 2)), rel=1e-6)
    assert report["edf"] == pytest.approx(whole.fit.edf, rel=0.1)


def test_seamless_dems_of_a_lattice_fit_in_tiles_are_the_in_memory_ones(tmp_path):
    """`--seamless -O DIR --suffix .tif` with --spacing: each input's DEM window is set by the
    triangles it owns, those whose lowest-numbered node's nearest point is its, in memory
    and in tiles (the tiles' records number nodes, not points: their `source` decides), so
    both write the same windows and cells."""
    rasterio = pytest.importorskip("rasterio")
    sources = _two_inputs(tmp_path)
    run = CliRunner().invoke(main, ["fit", *map(str, sources), "--seamless", "--classes", "2", "--smooth", "5",
                                    "--spacing", "1", "--suffix", ".tif", "--resolution", "1",
                                    "-O", str(tmp_path / "memory")])
    assert run.exit_code == 0, run.output
    (tmp_path / "tiled").mkdir()
    outputs = [tmp_path / "tiled" / (source.stem + ".tif") for source in sources]
    options = FitOptions(classes=[2], smooth=5.0, spacing=1.0, resolution=1.0, memory=10**9)
    assert fit([str(s) for s in sources], None, options, outputs=outputs,
               tiles=TiledRun(per_tile=1500)).report["tiles"] > 1
    for source in sources:
        with rasterio.open(tmp_path / "memory" / (source.stem + ".tif")) as a, \
                rasterio.open(tmp_path / "tiled" / (source.stem + ".tif")) as b:
            assert a.transform == b.transform and a.shape == b.shape
            here, there = a.read(1, masked=True), b.read(1, masked=True)
            np.testing.assert_array_equal(here.mask, there.mask)
            assert np.abs(here - there).max() < 1e-3
