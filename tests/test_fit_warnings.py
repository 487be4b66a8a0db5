"""Issue 21: fit warnings only when the result is probably wrong (a wrong height axis, a
--max-edge that removes triangles between dense points), the same on every path.

Truth: the README's own LiDAR sample (its holes are buildings and trees, right for
ground), analytic terrain with a known right axis, and a --max-edge below the spacing of
points laid out by the test.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from click.testing import CliRunner

from c1mesh.cli import main
from c1mesh.core.cloud import PointCloud
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit

DATA = Path(__file__).resolve().parent.parent / "data_samples"
AUTZEN = DATA / "autzen_trim.laz"
TILE = DATA / "4_6_crop.las"


def _terrain(n, side, seed=1, normals=True):
    """n uniform points on [0, side]² of z = 3 sin(x/9) cos(y/7) + 0.05 x (exact normals)."""
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2)) * side
    z = 3 * np.sin(xy[:, 0] / 9) * np.cos(xy[:, 1] / 7) + 0.05 * xy[:, 0]
    gx = 3 / 9 * np.cos(xy[:, 0] / 9) * np.cos(xy[:, 1] / 7) + 0.05
    gy = -3 / 7 * np.sin(xy[:, 0] / 9) * np.sin(xy[:, 1] / 7)
    n3 = np.column_stack([-gx, -gy, np.ones_like(gx)])
    n3 /= np.linalg.norm(n3, axis=1, keepdims=True)
    return PointCloud(np.column_stack([xy, z]), n3 if normals else None)


def _stderr(result):
    return getattr(result, "stderr", None) or result.output


def test_readme_autzen_ground_sample_prints_no_warning(tmp_path):
    """`c1mesh fit data_samples/autzen_trim.laz --classes 2 -o ground.glb` (the README's)
    and its --seamless forms: no warning (it was "32 pieces" and "covers only 66%")."""
    runner = CliRunner()
    for args in (["-o", str(tmp_path / "ground.glb")],
                 ["-o", str(tmp_path / "dem.tif"), "--resolution", "3"],
                 ["--seamless", "-o", str(tmp_path / "seamless.ply")],
                 ["--seamless", "-O", str(tmp_path / "out")]):
        result = runner.invoke(main, ["fit", "--smooth", "off", str(AUTZEN), "--classes", "2", *args])
        assert result.exit_code == 0, _stderr(result)
        assert "warning" not in _stderr(result), args


def test_a_max_edge_below_the_point_spacing_warns_and_auto_does_not(tmp_path):
    cloud = _terrain(4000, 60.0)                       # spacing √(3600 / 4000) = 0.95
    assert fit(cloud, None, FitOptions(smooth="off", axis="z", level=1)).report["warnings"] == []
    warnings = fit(cloud, None, FitOptions(smooth="off", axis="z", level=1, max_edge=0.8)).report["warnings"]
    assert len(warnings) == 1 and warnings[0].startswith("--max-edge 0.8 removed")
    raster = fit(cloud, tmp_path / "dem.tif", FitOptions(smooth="off", axis="z", max_edge=0.8, resolution=1.0))
    assert raster.report["warnings"] == [warnings[0].split(" (the surface fell")[0]]   # DEMs too


def test_a_wrong_height_axis_warns_and_the_right_one_does_not():
    """52 points of terrain with a steep relief, normals estimated: seen along x most
    points fold over others; along z (the right axis, heights in the units of x and y)
    the fit is clean."""
    rng = np.random.default_rng(0)
    xy = rng.random((52, 2)) * 6.5
    z = 850 + 60 * np.sin(xy[:, 0]) * np.cos(0.8 * xy[:, 1]) - 20 * xy[:, 1]
    right = PointCloud(np.column_stack([xy, (z - 850) / 50]))
    assert fit(right, None, FitOptions(smooth="off", axis="z", level=1)).report["warnings"] == []
    cloud = PointCloud(np.column_stack([xy, z]))
    report = fit(cloud, None, FitOptions(smooth="off", axis="x", level=1)).report
    assert report["points"]["kept"] < 0.8 * 52                       # the case is there
    assert len(report["warnings"]) == 1 and report["warnings"][0].endswith("check --axis (and --classes)")


def test_the_in_memory_seamless_and_tiled_fits_warn_alike(tmp_path):
    """--max-edge 2.5 on the 0.75 m ground tile: one warning, the same rule and numbers in
    the in-memory fit, --seamless -O and the tiled fit (which cannot count pieces)."""
    from dataclasses import replace

    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline.run import fit

    options = FitOptions(smooth="off", classes=(2,), level=1, max_edge=2.5)
    whole = fit(TILE, None, options).report["warnings"]
    seamless = fit([str(TILE)], None, options, outputs=[str(tmp_path / "o.ply")]).report["warnings"]
    tiled = fit(TILE, tmp_path / "t.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=1000)).report["warnings"]
    assert len(whole) == 1 and whole[0].startswith("--max-edge 2.5 removed")
    assert seamless == [w.split(" (the surface fell")[0] for w in whole]
    assert tiled == seamless


def test_a_fit_in_tiles_of_autzen_ground_warns_nothing(tmp_path):
    """Beyond --memory the same rule: no warning (the tile count is a note, not a warning)."""
    from dataclasses import replace

    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline.run import fit

    report = fit(AUTZEN, tmp_path / "t.ply", replace(FitOptions(smooth="off", classes=(2,), level=1), memory=10**9), tiles=TiledRun(per_tile=7000)).report
    assert report["warnings"] == [] and report["note"].startswith("fitted in 4 tiles")


def test_duplicated_points_draw_no_wrong_axis_warning(tmp_path):
    """A scan holding every point twice (overlapping tiles merged, an export run twice): the
    height field merges the copies into one vertex, and the fit is right, so no "check
    --axis" warning, in memory and in tiles. Counted as points in no triangle, the copies
    made half the points look folded over others."""
    import laspy
    from dataclasses import replace

    from c1mesh.core.plan import TiledRun

    source = laspy.read(TILE)
    ground = source.points[source.classification == 2]
    doubled = laspy.LasData(source.header)
    doubled.points = ground[np.r_[np.arange(len(ground)), np.arange(len(ground))]]
    path = tmp_path / "doubled.las"
    doubled.write(path)
    options = FitOptions(smooth="off", level=1)
    whole = fit(path, None, options).report
    assert whole["points"]["dropped"]["duplicate"] == len(ground)      # the case is there
    assert whole["warnings"] == []
    tiled = fit(path, tmp_path / "t.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=3000)).report
    assert tiled["tiles"] > 1 and tiled["warnings"] == []
    cloud = _terrain(1500, 40.0)
    twice = PointCloud(np.r_[cloud.points, cloud.points], np.r_[cloud.normals, cloud.normals])
    assert fit(twice, None, FitOptions(smooth="off", axis="z", level=1)).report["warnings"] == []
