"""The smoothing fit through the pipeline and the CLI (--smooth, --spacing), against truth
that does not come from c1mesh: analytic terrains and planes, and the recorded bytes of the
exact fit."""
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from c1mesh.core.cloud import PointCloud
from c1mesh.pipeline.driver import FitOptions, build_surface
from c1mesh.pipeline.run import fit
from test_smoothing import interior_or_at_limit

ROOT = Path(__file__).resolve().parent.parent
SAMPLES = ROOT / "data_samples"
CLI = [sys.executable, "-m", "c1mesh.cli"]


def terrain(x, y):
    """A smooth terrain (metres) with features a few point spacings wide."""
    return 2.0 * np.sin(x / 7.0) * np.cos(y / 9.0) + 0.05 * x


def noisy_cloud(n=4000, noise=0.05, seed=1):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 60, (n, 2))
    z = terrain(xy[:, 0], xy[:, 1]) + rng.normal(0, noise, n)
    return PointCloud(points=np.column_stack([xy, z]))


def held_out_rms(model, xy, z_true):
    """RMS of the model's heights at world (x, y) against the truth (frame axis z: the
    frame is the world's up to an origin shift and a sign of the axis)."""
    frame = model.frame
    assert np.allclose(np.abs(frame.axes[2]), [0, 0, 1])
    local = np.column_stack([xy, np.zeros(len(xy))]) - frame.origin
    uv = local @ frame.axes[:2].T
    height = model.interp(uv) * frame.axes[2, 2] + frame.origin[2]
    ok = np.isfinite(height)
    assert ok.mean() > 0.9
    return float(np.sqrt(np.mean((height[ok] - z_true[ok]) ** 2)))


@pytest.fixture(scope="module")
def probes():
    rng = np.random.default_rng(7)
    xy = rng.uniform(5, 55, (3000, 2))
    return xy, terrain(xy[:, 0], xy[:, 1])


def test_auto_smoothing_is_closer_to_the_terrain_than_the_exact_fit(probes):
    cloud = noisy_cloud()
    exact = build_surface(cloud, FitOptions(axis="z", smooth="off"))
    smooth = build_surface(cloud, FitOptions(axis="z", smooth="auto"))
    e_exact, e_smooth = held_out_rms(exact, *probes), held_out_rms(smooth, *probes)
    # the noise is 5 cm: an interpolant carries about all of it, a good smoother well under half
    assert e_exact > 0.04
    assert e_smooth < 0.5 * e_exact
    assert smooth.smoothing.strength > 0 and smooth.smoothing.edf < len(cloud)
    assert 0.04 < smooth.smoothing.residual_rms < 0.06      # the residuals are the noise


def test_spacing_fits_a_lattice_to_all_points(probes, monkeypatch):
    """--spacing 2: the vertices are the nodes of the 2 x 2 lattice (at world x, y = (k + ½) 2,
    the centres of a 2 m DEM's cells), its cells the 30 x 30 the 60 x 60 survey occupies and the support's
    reach more on every side, each split into two triangles of area 2; the spline of all 6,000 points.
    Solved by multigrid (MULTIGRID_FROM lowered to 0), the same heights as CHOLMOD's within
    the multigrid's stopping step."""
    from c1mesh.stages import lattice_mesh
    cloud = noisy_cloud(n=6000)
    direct = build_surface(cloud, FitOptions(axis="z", smooth=1.0, spacing=2.0))
    monkeypatch.setattr(lattice_mesh, "MULTIGRID_FROM", 0)
    model = build_surface(cloud, FitOptions(axis="z", smooth=1.0, spacing=2.0))
    assert (direct.smoothing.solver, model.smoothing.solver) == ("cholmod", "lattice-pcg")
    np.testing.assert_array_equal(direct.interp.points, model.interp.points)
    assert np.abs(direct.interp.values - model.interp.values).max() < 1e-3 * model.smoothing.residual_rms
    points, triangles = model.interp.points, model.interp.triangles
    world = (points + model.frame.origin[:2]) / 2.0 - 0.5
    np.testing.assert_allclose(world, np.round(world), rtol=0, atol=1e-12)
    side = 30 + 2 * lattice_mesh.support_reach(2.0, model.hf.spacing)
    assert side ** 2 <= len(triangles) // 2 <= (side + 1) ** 2
    corners = points[triangles]
    a, b = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    area = (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]) / 2
    np.testing.assert_allclose(area, 2.0, rtol=1e-12)         # counter-clockwise halves of 2 x 2 cells
    assert model.smoothing.outside == 0
    assert held_out_rms(model, *probes) < 0.05               # below the 5 cm noise of the points


def test_the_edf_is_estimated_only_when_a_report_is_written(tmp_path, monkeypatch):
    """The edf is a reported diagnostic that costs one more solve (on the lattice a whole
    multigrid CG): FitOptions(edf=False) skips it and changes no height; the CLI asks
    for it exactly when it writes a report. hat_trace is made to fail, so a run that
    calls it without a report cannot pass."""
    from click.testing import CliRunner
    from c1mesh.cli import main
    from c1mesh.stages import smoothing
    cloud = noisy_cloud(n=3000)
    for spacing in (None, 2.0):
        asked = build_surface(cloud, FitOptions(axis="z", smooth=1.0, spacing=spacing))
        skipped = build_surface(cloud, FitOptions(axis="z", smooth=1.0, spacing=spacing, edf=False))
        assert 3 < asked.smoothing.edf < len(cloud.points) and skipped.smoothing.edf is None
        np.testing.assert_array_equal(asked.interp.values, skipped.interp.values)
    source = tmp_path / "terrain.xyz"
    np.savetxt(source, cloud.points)
    monkeypatch.setattr(smoothing, "hat_trace", lambda *a: (_ for _ in ()).throw(AssertionError("edf estimated")))
    args = ["fit", str(source), "--smooth", "1", "--spacing", "2"]
    quiet = CliRunner().invoke(main, args + ["-o", str(tmp_path / "quiet.ply")])
    assert quiet.exit_code == 0, quiet.output
    reported = CliRunner().invoke(main, args + ["-o", str(tmp_path / "r.ply"), "--report", str(tmp_path / "r.json")])
    assert reported.exit_code != 0 and not (tmp_path / "r.ply").exists()


@pytest.mark.parametrize("smooth", ["auto", 30.0])
def test_a_plane_comes_through_any_strength_unchanged(smooth):
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 40, (1500, 2))
    z = 3.0 + 0.2 * xy[:, 0] - 0.1 * xy[:, 1]
    result = fit(PointCloud(points=np.column_stack([xy, z])), None, FitOptions(axis="z", smooth=smooth))
    v = result.mesh.vertices
    np.testing.assert_allclose(v[:, 2], 3.0 + 0.2 * v[:, 0] - 0.1 * v[:, 1], atol=1e-8)
    assert result.report["smoothing"]["residual_max"] < 1e-8


def test_smooth_off_is_the_exact_fit_byte_for_byte(tmp_path):
    recorded = json.loads((ROOT / "tests" / "sample_outputs.sha256").read_text())
    key = next(k for k in recorded if k.startswith("hill"))
    out = tmp_path / "hill.ply"
    subprocess.run(CLI + ["fit", str(SAMPLES / "hill.ply"), "-o", str(out), "--smooth", "off"], check=True,
                   env={"OPENBLAS_CORETYPE": "Haswell", "PATH": "/usr/bin:/bin"})
    import hashlib
    assert hashlib.sha256(out.read_bytes()).hexdigest() == recorded[key]["hill.ply"]


def _cli(*args, cwd):
    return subprocess.run(CLI + list(args), capture_output=True, text=True, cwd=cwd)


@pytest.mark.parametrize("args, words", [
    (["--smooth", "maybe"], "--smooth"),
    (["--smooth", "-1"], "--smooth"),
    (["--smooth", "off", "--spacing", "2"], "--spacing thins the vertices"),
    (["--smooth", "auto", "--spacing", "0"], "expected auto or a positive finite length"),
    (["--smooth", "auto", "--spacing", "2", "--frame", "perspective"], "perspective frame's smoothing fit"),
])
def test_bad_smoothing_options_are_one_usage_line(tmp_path, args, words):
    run = _cli("fit", str(SAMPLES / "hill.ply"), "-o", "out.ply", *args, cwd=tmp_path)
    assert run.returncode == 2
    assert words in run.stderr and len(run.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out.ply").exists()


def test_the_chosen_strength_is_a_note_on_a_terminal_only(tmp_path):
    """--smooth auto's choice goes in the report (strength, the strengths tried, where it
    searched) and, on a terminal only, in one `c1mesh: note:` line that says the same."""
    from stderr_lines import stderr_on_a_terminal

    args = ["fit", str(SAMPLES / "hill.ply"), "--smooth", "auto", "--level", "1"]
    shown = stderr_on_a_terminal(args + ["-o", str(tmp_path / "t.ply"), "--report", str(tmp_path / "r.json")])
    facts = json.loads((tmp_path / "r.json").read_text())["smoothing"]
    notes = [line for line in shown.splitlines() if "--smooth auto chose strength" in line]
    assert len(notes) == 1 and notes[0].startswith("c1mesh: note: ")
    assert f"strength {facts['strength']:.3g}:" in notes[0]
    assert f"of {len(facts['cv_curve'])} tried, on the whole mesh" in notes[0]     # hill.ply: 3,000 points
    assert facts["search_windows"] == {"side": 0.0, "centres": []}
    piped = _cli(*args, "-o", "p.ply", cwd=tmp_path)
    assert piped.returncode == 0 and "note:" not in piped.stderr


def test_the_report_records_the_fit_and_suggests_smoothing_only_for_noisy_heights(tmp_path):
    noisy = noisy_cloud(n=3000)
    exact = fit(noisy, None, FitOptions(axis="z", smooth="off")).report
    assert "--smooth auto" in exact["suggestion"]
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 60, (3000, 2))
    clean = fit(PointCloud(points=np.column_stack([xy, terrain(xy[:, 0], xy[:, 1])])), None,
                FitOptions(axis="z", smooth="off")).report
    assert "suggestion" not in clean
    smoothed = fit(noisy, None, FitOptions(axis="z", smooth="auto")).report
    facts = smoothed["smoothing"]
    assert {"strength", "lam", "cv_curve", "edf", "residual_rms", "residual_max"} <= set(facts)
    best = min(facts["cv_curve"], key=lambda pair: pair[1])
    assert best[0] == facts["strength"]
    assert interior_or_at_limit(SimpleNamespace(**facts)) == "interior"   # 5 cm noise on a terrain
    assert "suggestion" not in smoothed
    given = fit(noisy, None, FitOptions(axis="z", smooth=2.0)).report["smoothing"]
    assert given["cv_curve"] == [] and given["search_limit_reached"] is None


def test_thinned_vertices_draw_no_unused_points_warning():
    """With --spacing most points are data, not vertices; they are on the surface all the same."""
    report = fit(noisy_cloud(n=4000), None, FitOptions(axis="z", smooth=1.0, spacing=3.0)).report
    assert report["points"]["kept"] < 0.3 * 4000
    assert report["warnings"] == []


def test_file_normals_enter_the_smoothing_fit_as_gradient_data():
    """Exact gradients are information the heights lack: fitted as data (the pipeline's
    weight for normals read from a file) they bring the noisy terrain's fit closer to the
    true heights and slopes than the heights alone, at the same strength."""
    from c1mesh.engine.topology import edge_table
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.core.tile import Tile
    from c1mesh.pipeline.steps import compact_vertices, smoothed_interpolator
    from c1mesh.stages.smoothing import FILE_NORMALS_WEIGHT, SmoothingControl, SmoothingRun
    from c1mesh.stages.trim import trim_mesh

    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 60, (6000, 2))
    truth = 3 * np.sin(xy[:, 0] / 10) * np.cos(xy[:, 1] / 15)
    slope = np.column_stack([0.3 * np.cos(xy[:, 0] / 10) * np.cos(xy[:, 1] / 15),
                             -0.2 * np.sin(xy[:, 0] / 10) * np.sin(xy[:, 1] / 15)])
    mesh, _ = trim_mesh(xy, delaunay(xy))
    used, triangles = compact_vertices(xy, mesh.triangles)
    xy, truth, slope = xy[used], truth[used], slope[used]
    z = truth + rng.normal(0, 0.02, len(xy))
    errors = {}
    for label, gradients in (("heights", None), ("normals", slope)):
        weight = 0.0 if gradients is None else FILE_NORMALS_WEIGHT
        tile = Tile.whole(xy, z, np.zeros_like(xy) if gradients is None else gradients, triangles)
        interp, _, fitted = smoothed_interpolator(tile, SmoothingRun(SmoothingControl(1.0, "sextic"), 0.77, "limit", weight),
                                                  table=edge_table(triangles, len(xy)))
        assert fitted.gradient_weight == (0.0 if gradients is None else FILE_NORMALS_WEIGHT)
        errors[label] = (np.sqrt(np.mean((fitted.values - truth) ** 2)),
                         np.sqrt(np.mean(np.sum((fitted.gradients - slope) ** 2, axis=1))))
    assert errors["normals"][0] < errors["heights"][0]
    assert errors["normals"][1] < errors["heights"][1]


@pytest.mark.slow
@pytest.mark.parametrize("sample", ["autzen_trim.laz", "4_6_crop.las"])
def test_auto_smoothing_leaves_no_folded_face_on_lidar_ground(sample):
    """Issue 24's target: 0 folded faces at --smooth auto on the LiDAR ground samples, at
    level 4 (the exact fit folds 9 of Autzen's 808,096 faces, in two needles), counted
    against every corner's written normal (c1mesh.testing.quality.folded_faces)."""
    from c1mesh.testing.quality import folded_faces

    mesh = fit(SAMPLES / sample, None, FitOptions(classes=(2,), level=4, smooth="auto")).mesh
    assert len(mesh.faces) > 100_000
    assert folded_faces(mesh.vertices, mesh.faces, mesh.vertex_normals) == 0


@pytest.mark.slow
def test_auto_smoothing_of_exact_data_keeps_the_value_convergence_order():
    """Issue 24: on noise-free samples `--smooth auto` chooses a strength so small that the
    convergence orders hold. Franke's function on jittered grids of 40² and 80² points:
    the CV goes below its grid's smallest strength (10**GRID[0]) to an interior minimum of
    its curve or its limit (docs/smoothing.md), and the value error at interior points
    falls with the sextic's order 2 per halving of the spacing (RESULTS.md Accuracy: 2.06
    for the exact fit), here at least 1.8."""
    from test_engine import franke
    from test_smoothing import interior_or_at_limit

    from c1mesh.stages.smoothing import GRID

    grid = np.linspace(0.1, 0.9, 120)
    probes = np.column_stack([a.ravel() for a in np.meshgrid(grid, grid)])
    errors = []
    for m in (40, 80):
        rng = np.random.default_rng(0)
        u = (np.arange(m) + 0.5) / m
        x, y = (a.ravel() + rng.uniform(-0.3, 0.3, m * m) / m for a in np.meshgrid(u, u))
        cloud = PointCloud(points=np.column_stack([x, y, franke(np.column_stack([x, y]))]))
        model = build_surface(cloud, FitOptions(smooth="auto", axis="z", max_edge="none"))
        assert model.smoothing.strength < 10.0 ** GRID[0]
        interior_or_at_limit(model.smoothing)
        errors.append(held_out_rms(model, probes, franke(probes)))
    assert np.log2(errors[0] / errors[1]) >= 1.8
