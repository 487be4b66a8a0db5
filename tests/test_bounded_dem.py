"""The DEM of a survey fitted in tiles (c1mesh.pipeline.bounded_dem, `fit BIG.laz -o dem.tif
--resolution R --memory M`) against the in-memory fit's DEM of the same input.

Ground truth: the in-memory fit (pipeline.driver, geo.raster), which samples one spline
over the whole survey. The tiled DEM must be the same raster: the same grid (transform,
shape, CRS), the same cells with data, the same values (float32, to the last bit: each
tile's spline is the in-memory spline on its triangles, evaluated at the same centres by
the same arithmetic; _assert_same_raster says where a last bit may turn), the same
support distances, and a valid Cloud-Optimised GeoTIFF by rio-cogeo's validator.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

rasterio = pytest.importorskip("rasterio")
laspy = pytest.importorskip("laspy")

from c1mesh.cli import main
from c1mesh.core.plan import TiledRun
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit
from terrain_scenes import write_terrain_las

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
KINDS = ("dem", "slope", "aspect", "hillshade", "support")


def _paths(directory: Path, tag: str) -> dict:
    return {kind: str(directory / f"{tag}.{kind}.tif") for kind in KINDS}


def _options(paths: dict, resolution: float, fill: str = "off", **more) -> FitOptions:
    return FitOptions(classes=(2,), resolution=resolution, fill=fill, slope=paths["slope"],
                      aspect=paths["aspect"], hillshade=paths["hillshade"], support=paths["support"],
                      **{"smooth": "off", **more})


def _assert_same_raster(tiled: str, whole: str) -> None:
    """The two GeoTIFFs have one grid, CRS and nodata mask, and equal cells to the last
    bit of float32 (hillshade: of its uint8 shade). A cell whose centre lies on an edge
    of two triangles, or equally near two, takes either triangle's spline, which the
    tiles and the whole sampler may order differently: the two agree to float64 rounding
    (C1 continuity), which can turn a float32 value's last bit."""
    with rasterio.open(tiled) as a, rasterio.open(whole) as b:
        assert a.transform == b.transform and a.shape == b.shape and a.crs == b.crs
        assert a.nodata == b.nodata and a.dtypes == b.dtypes
        x, y = a.read(1), b.read(1)
    assert np.array_equal(x == a.nodata, y == b.nodata)
    assert (x != a.nodata).sum() > 100
    if x.dtype == np.uint8:
        assert np.abs(x.astype(int) - y).max() <= 1
    else:
        np.testing.assert_array_max_ulp(x, y, maxulp=1)


def _assert_cog(path: str) -> None:
    from rio_cogeo.cogeo import cog_validate
    valid, errors, _ = cog_validate(path, strict=True)
    assert valid, (path, errors)


@pytest.mark.parametrize("source,resolution,fill,per_tile,tiles", [("autzen_trim.laz", 2.0, "off", 7000, 4),
                                                                    ("autzen_trim.laz", 2.0, "hull", 1800, 16),
                                                                    ("4_6_crop.las", 1.0, "3", 1000, 16)])
def test_bounded_dem_equals_the_in_memory_dem(tmp_path, source, resolution, fill, per_tile, tiles):
    """Autzen ground (26k points: bow-ties, curtains, cells holding ground points outside
    the trimmed triangles; with the default fill, 34% of its hull in holes under
    buildings and trees, spanned by 1,547 long triangles across tiles) and 4_6_crop
    ground, its fill within 3 m of a point (--fill 3): DEM, slope, aspect, hillshade and
    support equal the in-memory fit's cell for cell, and every raster is a valid COG."""
    whole, tiled = _paths(tmp_path, "whole"), _paths(tmp_path, "tiled")
    report = fit(str(SAMPLES / source), whole["dem"], _options(whole, resolution, fill)).report
    facts = fit(str(SAMPLES / source), tiled["dem"], replace(_options(tiled, resolution, fill), memory=10**9),
                tiles=TiledRun(per_tile=per_tile)).report
    assert facts["tiles"] == tiles
    assert (facts["raster"]["fill"]["triangles_spanning_holes"] > 100) == (fill != "off")
    for kind in KINDS:
        _assert_same_raster(tiled[kind], whole[kind])
        _assert_cog(tiled[kind])
    for key in ("grid", "cells", "cells_with_data", "slope_method", "support_max", "fill"):
        assert facts["raster"][key] == report["raster"][key], key
    assert facts["raster"]["point_spacing"] == pytest.approx(report["raster"]["point_spacing"], rel=1e-12)
    assert facts["points"]["kept"] == report["points"]["kept"]
    assert facts["triangles"]["after_trim"] == report["triangles"]["after_trim"]
    assert facts["output_mesh"] is None and facts["level"] is None
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(Path(p).name for p in [*whole.values(),
                                                                                         *tiled.values()])


def test_bounded_dem_without_max_edge_continues_into_the_peeled_rim(tmp_path):
    """--max-edge none: the cells holding points past the peeled hull slivers take the
    nearest triangle at any distance, found over every tile's triangles; --overshoot off
    and the spline's own slope (--slope-method spline)."""
    whole, tiled = _paths(tmp_path, "whole"), _paths(tmp_path, "tiled")
    options = _options(whole, 0.5, max_edge=None, overshoot="off", slope_method="spline")
    report = fit(str(SAMPLES / "4_6_crop.las"), whole["dem"], options).report
    options = replace(_options(tiled, 0.5, max_edge=None, overshoot="off", slope_method="spline"), memory=10**9)
    facts = fit(str(SAMPLES / "4_6_crop.las"), tiled["dem"], options, tiles=TiledRun(per_tile=1000)).report
    assert report["triangles"]["removed"]["sliver"] > 0
    assert facts["raster"]["slope_method"] == report["raster"]["slope_method"] == "spline"
    for kind in KINDS:
        _assert_same_raster(tiled[kind], whole[kind])


def test_cli_writes_a_dem_in_tiles_beyond_memory(tmp_path):
    """`fit BIG.las -o dem.tif --resolution R --fill off --memory 1M` with side rasters: the
    tiled fit (4 tiles) writes the in-memory fit's rasters and reports them; no temporary
    file is left."""
    source = tmp_path / "terrain.las"
    write_terrain_las(source, 48000, classes=(2, 5))
    whole, tiled = _paths(tmp_path, "whole"), _paths(tmp_path, "tiled")

    def args(paths):
        return ["fit", "--smooth", "off", str(source), "--classes", "2", "-o", paths["dem"], "--resolution", "0.5", "--fill", "off",
                "--slope", paths["slope"], "--aspect", paths["aspect"], "--hillshade", paths["hillshade"],
                "--support", paths["support"]]
    result = CliRunner().invoke(main, args(whole))
    assert result.exit_code == 0, result.output
    result = CliRunner().invoke(main, args(tiled) + ["--memory", "1M", "--report", str(tmp_path / "r.json")])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["tiles"] == 4 and report["output"] == tiled["dem"]
    assert report["raster"]["files"] == {kind: path for kind, path in tiled.items()}
    assert report["overshoot"]["gradients_limited"] > 0
    for kind in KINDS:
        _assert_same_raster(tiled[kind], whole[kind])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["terrain.las", "r.json", *(Path(p).name for p in [*whole.values(), *tiled.values()])])


@pytest.mark.parametrize("per_tile,tiles", [(7000, 4), pytest.param(10**6, 1, marks=pytest.mark.slow)])
def test_the_smoothing_fits_fill_in_tiles_is_the_in_memory_fill(tmp_path, per_tile, tiles):
    """--smooth 3 with the default fill: the smoothing fits the trimmed triangles, and the
    limiter, over the filled triangulation with the fitted data, gives the gradients at
    the corners of the triangles that span holes (pipeline.driver._smoothed). In one tile
    the tiled fit is the in-memory one, byte for byte; in 4 each tile solves on its halo,
    so the heights differ by the tiled solve's tolerance (within 1% of the fit's residual
    RMS, tests/test_tiled_smoothing.py), on the same cells, with the same support."""
    whole, tiled = _paths(tmp_path, "whole"), _paths(tmp_path, "tiled")
    report = fit(str(SAMPLES / "autzen_trim.laz"), whole["dem"], _options(whole, 2.0, "hull", smooth=3.0)).report
    facts = fit(str(SAMPLES / "autzen_trim.laz"), tiled["dem"], replace(_options(tiled, 2.0, "hull", smooth=3.0),
                memory=10**9), tiles=TiledRun(per_tile=per_tile)).report
    assert facts["tiles"] == tiles and facts["raster"]["fill"] == report["raster"]["fill"]
    assert facts["raster"]["fill"]["triangles_spanning_holes"] > 1000
    assert Path(tiled["support"]).read_bytes() == Path(whole["support"]).read_bytes()
    with rasterio.open(tiled["dem"]) as a, rasterio.open(whole["dem"]) as b:
        x, y, nodata = a.read(1).astype(float), b.read(1).astype(float), a.nodata
    assert np.array_equal(x == nodata, y == nodata)
    difference = np.abs(x - y)[x != nodata]
    if tiles == 1:
        assert difference.max() == 0
    else:
        assert difference.max() < 0.01 * report["smoothing"]["residual_rms"]


def _lake_las(path, seed: int = 3) -> None:
    """A LAS 1.2 ground survey of 40,000 uniform points over 100 x 100 m less a round lake
    56 m wide and a bay 20 m wide on the east side: z = 100 + 3 sin(x/17) cos(y/23) with
    2 cm noise, millimetre scales, class 2."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, 100, 40000), rng.uniform(0, 100, 40000)
    keep = ~((np.hypot(x - 45, y - 50) < 28) | ((x > 80) & (y > 55) & (y < 85)))
    x, y = x[keep], y[keep]
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [500000, 4000000, 0]
    record = laspy.ScaleAwarePointRecord.zeros(len(x), header=header)
    record.x, record.y = x + 500000, y + 4000000
    record.z = 100 + 3 * np.sin(x / 17) * np.cos(y / 23) + rng.normal(0, 0.02, len(x))
    record.classification = np.full(len(x), 2, np.uint8)
    with laspy.open(str(path), mode="w", header=header) as writer:
        writer.write_points(record)


def test_a_lake_wider_than_a_tile_is_filled_as_in_memory(tmp_path):
    """The default fill over a lake that spans three of 16 tiles (25 m cells, the lake
    56 m wide) and a bay: its long triangles are found from the tiles' short ones and
    every tile's halo reaches across them, so the DEM and its support equal the in-memory
    fit's bit for bit, the lake has no nodata cell, and its support reaches half the lake."""
    source = tmp_path / "lake.las"
    _lake_las(source)
    whole, tiled = _paths(tmp_path, "whole"), _paths(tmp_path, "tiled")
    report = fit(str(source), whole["dem"], _options(whole, 0.5, "hull")).report
    facts = fit(str(source), tiled["dem"], replace(_options(tiled, 0.5, "hull"), memory=10**9),
                tiles=TiledRun(per_tile=2000)).report
    assert facts["tiles"] == 16 and facts["raster"]["fill"] == report["raster"]["fill"]
    for kind in ("dem", "support"):
        assert Path(tiled[kind]).read_bytes() == Path(whole[kind]).read_bytes()
    with rasterio.open(tiled["dem"]) as dem, rasterio.open(tiled["support"]) as support:
        row, col = dem.index(500045.0, 4000050.0)                     # the lake's centre
        assert dem.read(1)[row, col] != dem.nodata and support.read(1)[row, col] > 25


def _contour_lines(path) -> tuple[list, np.ndarray]:
    """The LineStrings' vertices ((n, 2) each) and levels of a contour file, read by
    pyogrio (GDAL), in file order."""
    import pyogrio.raw

    _, _, geometry, fields = pyogrio.raw.read(path)
    lines = []
    for wkb in geometry:
        wkb = bytes(wkb)
        count = int(np.frombuffer(wkb[5:9], "<u4")[0])
        lines.append(np.frombuffer(wkb[9:9 + 16 * count], "<f8").reshape(-1, 2))
    return lines, np.asarray(fields[0])


@pytest.mark.parametrize("source,resolution,interval,per_tile,tiles", [("autzen_trim.laz", 2.0, 2.0, 7000, 4),
                                                                         ("4_6_crop.las", 1.0, 0.5, 1000, 16)])
def test_contours_in_tiles_are_the_in_memory_fits(tmp_path, source, resolution, interval, per_tile, tiles):
    """--contours with a DEM fitted in tiles: the tiles' splines snap the lines traced on
    the tiles' DEM nodes. Truth: the in-memory fit's contours of one spline. The same
    lines in the same order, with the same levels and vertex counts; each vertex is the
    root of the same spline on the same grid edge, and the tiles' splines equal the whole
    one to float64 rounding, so vertices may differ by the snapping's tolerance only
    (NEWTON_TOLERANCE x the interval in height: far below 1e-6 of a cell in position)."""
    runs = {}
    for name, memory, run in (("whole", None, None), ("tiled", 10**9, TiledRun(per_tile=per_tile))):
        paths = _paths(tmp_path, name)
        options = replace(_options(paths, resolution, memory=memory), contours=str(tmp_path / f"{name}.gpkg"),
                          interval=interval)
        runs[name] = fit(str(SAMPLES / source), paths["dem"], options, tiles=run).report
    assert runs["tiled"]["tiles"] == tiles and "tiles" not in runs["whole"]
    whole, tiled = runs["whole"]["contours"], runs["tiled"]["contours"]
    for key in ("interval", "lines", "closed", "vertices", "levels", "dropped_vertices", "grid_resolution"):
        assert tiled[key] == whole[key], key
    assert tiled["lines"] > 50 and tiled["max_level_error"] <= 1e-6 * interval
    (a, a_levels), (b, b_levels) = _contour_lines(tmp_path / "whole.gpkg"), _contour_lines(tmp_path / "tiled.gpkg")
    assert np.array_equal(a_levels, b_levels) and [x.shape for x in a] == [y.shape for y in b]
    assert max(np.abs(x - y).max() for x, y in zip(a, b)) <= 1e-6 * resolution
    rasters = [Path(p).name for name in ("whole", "tiled") for p in _paths(tmp_path, name).values()]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(rasters + ["tiled.gpkg", "whole.gpkg"])


def test_the_preview_of_a_dem_in_tiles_is_the_in_memory_fits_picture(tmp_path):
    """--preview of a DEM fitted in 4 tiles draws the cells the tiles sampled, shaded by the
    spline's gradient there, the default fill's cells hatched: the same PNG, byte for
    byte, as the in-memory fit's, whose cells come from one spline
    (geo.preview.render_dem_fit)."""
    pngs = {}
    for name, extra in (("whole", []), ("tiled", ["--memory", "1M"])):
        pngs[name] = tmp_path / f"{name}.png"
        result = CliRunner().invoke(main, ["fit", "--smooth", "off", str(SAMPLES / "autzen_trim.laz"), "-o", str(tmp_path / f"{name}.tif"),
                                           "--resolution", "2", "--preview", str(pngs[name]),
                                           "--report", str(tmp_path / f"{name}.json"), *extra])
        assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "tiled.json").read_text())["tiles"] == 4
    assert "tiles" not in json.loads((tmp_path / "whole.json").read_text())
    assert pngs["whole"].read_bytes() == pngs["tiled"].read_bytes()


def test_a_mesh_preview_and_contours_in_tiles_are_the_in_memory_fits(tmp_path):
    """A mesh output's --preview and --contours beyond --memory: the tiles sample the
    preview's pixels and the contours' grid (at the mean output edge) as they sample a
    DEM's cells. Truth: the in-memory fit's, which samples its one spline: the same PNG,
    byte for byte, and the same contour lines (vertices within the snapping's tolerance,
    as test_contours_in_tiles_are_the_in_memory_fits says why)."""
    runs = {}
    for name, extra in (("whole", []), ("tiled", ["--memory", "4M"])):        # 4 tiles; room for the contours
        result = CliRunner().invoke(main, ["fit", "--smooth", "off", str(SAMPLES / "autzen_trim.laz"), "-o", str(tmp_path / f"{name}.ply"),
                                           "--preview", str(tmp_path / f"{name}.png"),
                                           "--contours", str(tmp_path / f"{name}.gpkg"), "--interval", "2",
                                           "--level", "1", "--report", str(tmp_path / f"{name}.json"), *extra])
        assert result.exit_code == 0, result.output
        runs[name] = json.loads((tmp_path / f"{name}.json").read_text())
    assert runs["tiled"]["tiles"] == 4 and "tiles" not in runs["whole"]
    assert (tmp_path / "whole.png").read_bytes() == (tmp_path / "tiled.png").read_bytes()
    whole, tiled = runs["whole"]["contours"], runs["tiled"]["contours"]
    assert whole["grid_resolution"] == pytest.approx(tiled["grid_resolution"], rel=1e-12)
    for key in ("lines", "closed", "vertices", "levels", "dropped_vertices"):
        assert tiled[key] == whole[key], key
    (a, a_levels), (b, b_levels) = _contour_lines(tmp_path / "whole.gpkg"), _contour_lines(tmp_path / "tiled.gpkg")
    assert np.array_equal(a_levels, b_levels) and [x.shape for x in a] == [y.shape for y in b]
    assert max(np.abs(x - y).max() for x, y in zip(a, b)) <= 1e-6 * whole["grid_resolution"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"{name}.{suffix}" for name in ("whole", "tiled") for suffix in ("ply", "prj", "png", "gpkg", "json"))


@pytest.mark.slow
def test_contours_and_previews_in_tiles_on_a_dask_cluster_are_the_local_tiles(tmp_path):
    """The tiles' sampling tasks for a DEM's contours and a mesh's preview and contours run
    on a Dask cluster (LocalCluster) as on local processes: the same PNG and the same
    contour features, to the bit (the tasks write the same cells; the parent traces and
    snaps them)."""
    distributed = pytest.importorskip("distributed")
    import pyogrio.raw

    def features(path):
        return [bytes(g) for g in pyogrio.raw.read(path)[2]]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        for output, extra in (("dem.tif", ["--resolution", "2"]), ("mesh.ply", ["--level", "1"])):
            for name, where in (("local", []), ("dask", ["--scheduler", cluster.scheduler_address])):
                stem = tmp_path / f"{name}-{output}"
                result = CliRunner().invoke(main, ["fit", "--smooth", "off", str(SAMPLES / "autzen_trim.laz"), "-o", str(stem), *extra,
                                                   "--preview", f"{stem}.png", "--contours", f"{stem}.gpkg",
                                                   "--interval", "2", "--memory", "16M", *where])
                assert result.exit_code == 0, result.output
            local, dask = tmp_path / f"local-{output}", tmp_path / f"dask-{output}"
            assert Path(f"{local}.png").read_bytes() == Path(f"{dask}.png").read_bytes()
            assert features(f"{local}.gpkg") == features(f"{dask}.gpkg") != []


def test_contours_beyond_the_budget_are_refused_before_the_fit(tmp_path):
    """Contours are traced in one piece (geo.contours.BYTES_PER_NODE a grid node): a grid
    whose tracing needs more than --memory is refused in one line naming the input, right
    after the frame pass, with nothing written. Truth: 24,000 points over 77 x 77 m at
    0.02 m cells are 15M nodes, about 890 MB, against a 1 MB budget."""
    source = tmp_path / "terrain.las"
    write_terrain_las(source, 24000, classes=(2,))
    result = CliRunner().invoke(main, ["fit", "--smooth", "off", str(source), "-o", str(tmp_path / "dem.tif"), "--resolution", "0.02",
                                       "--fill", "off", "--contours", str(tmp_path / "c.gpkg"), "--interval", "1",
                                       "--memory", "1M"])
    assert result.exit_code == 1 and result.output.count("\n") == 1
    assert "terrain.las" in result.output and "contours" in result.output and "--memory" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["terrain.las"]
