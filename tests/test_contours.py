"""Contour lines (`fit --contours FILE --interval H`, c1mesh.geo.contours): every vertex on
the spline's level set, no crossings (a brute-force segment test, tests/contour_checks.py),
closed level sets closed, closer to the true function than the linear contours of the same
DEM (what gdal_contour draws), the CRS of the input, usage errors before any input is read,
and no file left behind by a failed fit."""
from __future__ import annotations

import dataclasses
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from c1mesh.cli import main, usage_error
from c1mesh.core.cloud import PointCloud
from c1mesh.core.errors import InputError
from c1mesh.geo.contours import EXACT, MAX_LEVELS, contour_levels
from c1mesh.pipeline import driver
from c1mesh.pipeline.driver import FitOptions, build_surface, load_cloud
from c1mesh.pipeline.run import fit
from c1mesh.pipeline.steps import StageTimer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from contour_checks import crossings  # noqa: E402

pyogrio = pytest.importorskip("pyogrio")
contourpy = pytest.importorskip("contourpy")

AUTZEN = Path(__file__).resolve().parent.parent / "data_samples" / "autzen_trim.laz"


def franke(x, y):
    """Franke's (1979) test function on the unit square."""
    return (0.75 * np.exp(-((9 * x - 2) ** 2 + (9 * y - 2) ** 2) / 4)
            + 0.75 * np.exp(-(9 * x + 1) ** 2 / 49 - (9 * y + 1) / 10)
            + 0.5 * np.exp(-((9 * x - 7) ** 2 + (9 * y - 3) ** 2) / 4)
            - 0.2 * np.exp(-(9 * x - 4) ** 2 - (9 * y - 7) ** 2))


def franke_cloud(n=10_000, seed=40) -> PointCloud:
    """Franke's function at n scattered points (uniform on the unit square, seeded)."""
    xy = np.random.default_rng(seed).random((n, 2))
    return PointCloud(np.column_stack([xy, franke(xy[:, 0], xy[:, 1])]))


def read_lines(path):
    """(lines [(n, 2) arrays], levels (L,), closed (L,) bool, read_info) of a contour file."""
    from pyogrio.raw import read

    _, _, geometry, fields = read(str(path))
    lines = []
    for wkb in geometry:
        assert wkb[0] == 1 and int.from_bytes(wkb[1:5], "little") == 2          # little-endian LineString
        n = int.from_bytes(wkb[5:9], "little")
        lines.append(np.frombuffer(wkb[9:9 + 16 * n], "<f8").reshape(n, 2))
    closed = np.array([bool((line[0] == line[-1]).all()) for line in lines], dtype=bool)
    return lines, fields[0], closed, pyogrio.read_info(str(path))


def spline_errors(model, lines, levels) -> np.ndarray:
    """|spline(v) − level| at every vertex, by the interpolator's own evaluation (NaN off it)."""
    origin = model.frame.origin
    every = np.concatenate(lines)
    wanted = np.repeat(levels, [line.shape[0] for line in lines])
    return np.abs(model.interp(every - origin[:2]) + origin[2] - wanted)


@pytest.fixture(scope="module")
def franke_fit(tmp_path_factory):
    """The DEM (resolution 0.02, two point spacings) and contours (interval 0.1) of Franke's
    function at 10k points, fitted by the library as the CLI does; the surface rebuilt by
    build_surface with the same options and the DEM's default fill (deterministic) to check
    the file against."""
    folder = tmp_path_factory.mktemp("franke")
    cloud = franke_cloud()
    options = FitOptions(smooth="off", axis="z", resolution=0.02, contours=str(folder / "franke.gpkg"), interval=0.1)
    report = fit(cloud, str(folder / "franke.tif"), options).report
    model = build_surface(cloud, options, StageTimer(None), fill=True)
    return report, model, read_lines(folder / "franke.gpkg"), folder


def test_every_vertex_is_on_the_splines_level_set(franke_fit):
    report, model, (lines, levels, _, info), _ = franke_fit
    errors = spline_errors(model, lines, levels)
    assert np.isfinite(errors).all()                     # no vertex off the surface
    assert errors.max() <= 1e-6 * 0.1
    assert report["contours"]["max_level_error"] <= EXACT * 0.1
    assert info["features"] == report["contours"]["lines"] == len(lines) > 10
    assert np.allclose(levels / 0.1, np.round(levels / 0.1), rtol=0, atol=1e-9)   # multiples of the interval
    assert info["fields"].tolist() == ["level"] and info["dtypes"].tolist() == ["float64"]
    assert info["geometry_type"] == "LineString"


def test_no_line_crosses_another_or_itself(franke_fit):
    _, _, (lines, _, closed, _), _ = franke_fit
    assert crossings(lines, closed).size == 0


def test_the_crossing_check_finds_crossings_and_touches():
    """The check of the test above can fail: an X, a figure eight, a line touching another."""
    x = [np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[0.0, 1.0], [1.0, 0.0]])]
    assert len(crossings(x, [False, False])) == 1
    eight = [np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])]
    assert len(crossings(eight, [True])) == 1
    touch = [np.array([[0.0, 0.0], [2.0, 0.0]]), np.array([[1.0, 0.0], [1.0, 1.0], [2.0, 1.0]])]
    assert len(crossings(touch, [False, False])) == 1
    apart = [np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), np.array([[0.0, 1.0], [2.0, 1.0]])]
    assert len(crossings(apart, [False, False])) == 0


def _linear_contours_error(folder, model, levels, resolution) -> float:
    """Largest |f(v) − level| over the vertices of contourpy's linear contours of the DEM
    (float32 GeoTIFF, cell centres; what gdal_contour draws), on the cells whose centre is
    in the triangulation (the cells c1mesh's contours are traced on)."""
    import rasterio

    with rasterio.open(folder / f"franke-{resolution}.tif") as ds:
        dem = ds.read(1).astype(np.float64)
        transform = ds.transform
        dem[dem == ds.nodata] = np.nan
    rows, cols = np.mgrid[0:dem.shape[0], 0:dem.shape[1]]
    x = transform.c + (cols + 0.5) * transform.a
    y = transform.f + (rows + 0.5) * transform.e
    centres = np.column_stack([x.ravel(), y.ravel()]) - model.frame.origin[:2]
    dem[(model.interp.find_simplex(centres) < 0).reshape(dem.shape)] = np.nan
    generator = contourpy.contour_generator(x, y, np.ma.masked_invalid(dem), name="serial", corner_mask=False)
    worst = 0.0
    for level in np.unique(levels):
        for line in generator.lines(level):
            worst = max(worst, float(np.abs(franke(line[:, 0], line[:, 1]) - level).max()))
    return worst


@pytest.mark.parametrize("resolution", [0.05, 0.1])
def test_closer_to_frankes_function_than_the_linear_contours_of_the_dem(tmp_path, resolution):
    """At DEMs of 5 and 10 point spacings the exact contours of the spline are closer to
    the true level sets than the DEM's linear ones. (At 1-3 spacings both are the spline's
    own error, about 3.5e-3 here: benchmarks/RESULTS.md, geo.)"""
    cloud = franke_cloud()
    options = FitOptions(smooth="off", axis="z", resolution=resolution, contours=str(tmp_path / "c.gpkg"), interval=0.1)
    fit(cloud, str(tmp_path / f"franke-{resolution}.tif"), options)
    lines, levels, _, _ = read_lines(tmp_path / "c.gpkg")
    ours = max(float(np.abs(franke(line[:, 0], line[:, 1]) - level).max()) for line, level in zip(lines, levels))
    model = build_surface(cloud, options, StageTimer(None), fill=True)
    linear = _linear_contours_error(tmp_path, model, levels, resolution)
    print(f"resolution {resolution}: c1mesh {ours:.2e}, linear contours of the DEM {linear:.2e}")
    assert ours < linear


def test_closed_level_sets_come_out_closed(tmp_path):
    """A Gaussian bump inside the data: each level from 0.1 to 0.9 is one closed line
    around the summit (its winding number about the centre is ±1)."""
    xy = np.random.default_rng(5).random((4000, 2)) * 2 - 1
    cloud = PointCloud(np.column_stack([xy, np.exp(-(xy ** 2).sum(axis=1) / 0.1)]))
    options = FitOptions(smooth="off", axis="z", resolution=0.05, contours=str(tmp_path / "bump.geojson"), interval=0.1)
    report = fit(cloud, str(tmp_path / "bump.tif"), options).report
    lines, levels, closed, _ = read_lines(tmp_path / "bump.geojson")
    summit = [(line, level, shut) for line, level, shut in zip(lines, levels, closed) if level >= 0.05]
    assert sorted(level for _, level, _ in summit) == pytest.approx(np.arange(1, 10) / 10)
    for line, _, shut in summit:
        assert shut
        angle = np.unwrap(np.arctan2(line[:, 1], line[:, 0]))
        assert abs(angle[-1] - angle[0]) == pytest.approx(2 * np.pi, abs=1e-9)
    assert report["contours"]["closed"] >= 9
    assert crossings(lines, closed).size == 0


def test_lines_are_split_at_a_trimmed_hole(tmp_path):
    """A disk of radius 0.2 without points is trimmed out of the surface: the levels that
    cross it end at its rim (split lines), and no vertex lies in it."""
    rng = np.random.default_rng(3)
    xy = rng.random((6000, 2))
    xy = xy[np.hypot(xy[:, 0] - 0.5, xy[:, 1] - 0.5) > 0.2]
    cloud = PointCloud(np.column_stack([xy, xy[:, 0] + 0.3 * xy[:, 1] ** 2]))
    options = FitOptions(smooth="off", axis="z", resolution=0.02, contours=str(tmp_path / "hole.gpkg"), interval=0.1,
                         fill="off")                 # the DEM keeps the trim's hole (--fill off)
    fit(cloud, str(tmp_path / "hole.tif"), options)
    lines, levels, closed, _ = read_lines(tmp_path / "hole.gpkg")
    every = np.concatenate(lines)
    assert np.hypot(every[:, 0] - 0.5, every[:, 1] - 0.5).min() > 0.19
    crossing_the_hole = [level for level in np.unique(levels) if 0.35 <= level <= 0.65]
    for level in crossing_the_hole:
        assert (levels == level).sum() >= 2                   # one line each side of the hole
    model = build_surface(cloud, options, StageTimer(None))
    assert spline_errors(model, lines, levels).max() <= 1e-6 * 0.1
    assert crossings(lines, closed).size == 0


def test_autzen_contours_carry_the_input_crs_in_every_format(tmp_path):
    """autzen_trim's ground (EPSG:2992 in feet): the GeoPackage, GeoJSON and shapefile open
    with pyogrio and hold the LAS file's CRS; the mesh output's contours too."""
    import laspy
    import pyproj

    file_crs = laspy.read(AUTZEN).header.parse_crs()
    options = FitOptions(smooth="off", classes=(2,), resolution=3.0, contours=str(tmp_path / "autzen.gpkg"), interval=1.0,
                         bounds=(636300.0, 849000.0, 636700.0, 849300.0))
    report = fit(str(AUTZEN), str(tmp_path / "dem.tif"), options).report
    lines, levels, closed, info = read_lines(tmp_path / "autzen.gpkg")
    assert pyproj.CRS(info["crs"]).equals(file_crs, ignore_axis_order=True)
    assert len(lines) == report["contours"]["lines"] > 20 and report["contours"]["grid_resolution"] == 3.0
    model = build_surface(load_cloud(str(AUTZEN), options), dataclasses.replace(options, axis="z"), StageTimer(None),
                          fill=True)
    assert spline_errors(model, lines, levels).max() <= 1e-6 * 1.0
    assert crossings(lines, closed).size == 0
    from c1mesh.geo.contour_file import StagedContours, vector_crs
    wkt = report["crs"]["wkt"]
    with pytest.raises(InputError, match="GeoJSON names its CRS by an EPSG code"):
        vector_crs(tmp_path / "autzen.geojson", wkt)          # autzen's WKT carries no EPSG code
    for name, crs in (("autzen.shp", vector_crs(tmp_path / "autzen.shp", wkt)),
                      ("autzen.geojson", vector_crs(tmp_path / "autzen.geojson", wkt, "EPSG:2994"))):
        with StagedContours(tmp_path / name) as staged:
            staged.write(lines, levels, crs)
            staged.commit()
        again, again_levels, _, again_info = read_lines(tmp_path / name)
        assert pyproj.CRS(again_info["crs"]).equals(file_crs, ignore_axis_order=True)
        assert np.array_equal(again_levels, levels)
        assert all(np.allclose(a, b, rtol=0, atol=1e-9) for a, b in zip(again, lines))
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_an_interval_above_the_relief_writes_an_empty_file_and_warns(tmp_path):
    xy = np.random.default_rng(1).random((500, 2))
    cloud = PointCloud(np.column_stack([xy, 0.5 + 0.01 * xy[:, 0]]))
    report = fit(cloud, str(tmp_path / "dem.tif"), FitOptions(smooth="off", axis="z", resolution=0.05, crs="EPSG:32633",
                                                               contours=str(tmp_path / "c.gpkg"), interval=1.0)).report
    assert report["contours"]["lines"] == 0 and report["contours"]["levels"]["count"] == 0
    assert any("gives no contour level" in text for text in report["warnings"])
    info = pyogrio.read_info(str(tmp_path / "c.gpkg"))
    assert info["features"] == 0 and info["crs"] == "EPSG:32633"


def test_contours_of_a_mesh_fit_are_traced_at_its_resolution(tmp_path):
    """-o x.ply --resolution R --contours: the fit is a height field; its contours are
    traced on a grid of R and lie on the spline."""
    cloud = franke_cloud(3000)
    options = FitOptions(smooth="off", axis="z", resolution=0.05, contours=str(tmp_path / "m.gpkg"), interval=0.1)
    report = fit(cloud, str(tmp_path / "m.ply"), options).report
    assert report["contours"]["grid_resolution"] == 0.05 and report["level"] >= 1
    lines, levels, _, _ = read_lines(tmp_path / "m.gpkg")
    model = build_surface(cloud, options, StageTimer(None))
    assert spline_errors(model, lines, levels).max() <= 1e-6 * 0.1


@pytest.mark.parametrize("args, words", [
    (["--contours", "c.gpkg"], "--contours needs --interval"),
    (["--contours", "c.gpkg", "--interval", "0"], "--interval must be a positive height"),
    (["--contours", "c.gpkg", "--interval", "-2"], "--interval must be a positive height"),
    (["--contours", "c.gpkg", "--interval", "inf"], "--interval must be a positive height"),
    (["--interval", "2"], "give --contours FILE"),
    (["--contours", "c.kml", "--interval", "2"], "must be a .gpkg, .geojson or .shp file"),
    (["--contours", "c.gpkg", "--interval", "2", "--frame", "perspective"], "perspective frame"),
    (["--contours", "c.gpkg", "--interval", "2", "--axis", "x"], "--axis x cannot be used with --contours"),
])
def test_contour_options_are_usage_errors_before_any_input_is_read(tmp_path, args, words):
    argv = ["fit", "--smooth", "off", str(tmp_path / "missing.laz"), "-o", str(tmp_path / "dem.tif"), "--resolution", "2", *args]
    line = usage_error(argv)
    assert line is not None and words in line and "\n" not in line
    done = CliRunner().invoke(main, argv)
    assert done.exit_code == 2
    assert list(tmp_path.iterdir()) == []


def test_contours_with_several_outputs_are_usage_errors(tmp_path):
    common = ["--contours", "c.gpkg", "--interval", "1"]
    assert "single input" in usage_error(["fit", "--smooth", "off", "a.laz", "b.laz", "-O", str(tmp_path), *common])
    assert "not -O" in usage_error(["fit", "--smooth", "off", "a.laz", "b.laz", "--seamless", "-O", str(tmp_path), *common])


def test_geojson_of_a_crs_without_epsg_code_is_refused_before_the_fit(tmp_path, monkeypatch):
    """autzen_trim's CRS has no EPSG code, which GeoJSON needs: refused once the input is
    read, before the surface is built."""
    monkeypatch.setattr(driver, "build_surface", lambda *a, **k: pytest.fail("fitted before refusing"))
    options = FitOptions(smooth="off", classes=(2,), resolution=4.0, contours=str(tmp_path / "c.geojson"), interval=2.0)
    with pytest.raises(InputError, match="write .gpkg or .shp, or give --crs EPSG:XXXX"):
        fit(str(AUTZEN), str(tmp_path / "dem.tif"), options)
    assert list(tmp_path.iterdir()) == []


def test_library_refuses_what_the_cli_refuses(tmp_path):
    cloud = franke_cloud(500)
    for options, words in [(FitOptions(smooth="off", contours=str(tmp_path / "c.gpkg")), "--interval"),
                           (FitOptions(smooth="off", contours=str(tmp_path / "c.gpkg"), interval=-1.0), "positive"),
                           (FitOptions(smooth="off", contours=str(tmp_path / "c.txt"), interval=1.0), ".gpkg"),
                           (FitOptions(smooth="off", contours=str(tmp_path / "c.gpkg"), interval=1.0, frame="perspective"),
                            "perspective")]:
        with pytest.raises(InputError, match=words):
            fit(cloud, str(tmp_path / "m.ply"), options)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="larger --interval"):
        contour_levels(0.0, 1.0, 1.0 / (2 * MAX_LEVELS))


def test_a_failed_fit_leaves_no_contours_and_failed_contours_leave_no_dem(tmp_path, monkeypatch):
    """The contour file is committed with the DEM or not at all; no temporary file stays."""
    cloud = franke_cloud(1500)
    options = FitOptions(smooth="off", axis="z", resolution=0.05, contours=str(tmp_path / "c.shp"), interval=0.1)

    def broken_rasters(*args, **kwargs):
        raise OSError(28, "No space left on device")
    with monkeypatch.context() as patch:
        patch.setattr(driver, "write_fit_rasters", broken_rasters)
        with pytest.raises(OSError):
            fit(cloud, str(tmp_path / "dem.tif"), options)
    assert list(tmp_path.iterdir()) == []

    from c1mesh.geo import contour_file

    def broken_write(self, lines, levels, crs):
        self._reserve()
        raise OSError(28, "No space left on device")
    with monkeypatch.context() as patch:
        patch.setattr(contour_file.StagedContours, "write", broken_write)
        with pytest.raises(OSError):
            fit(cloud, str(tmp_path / "dem.tif"), options)
    assert list(tmp_path.iterdir()) == []


def test_report_of_the_cli(tmp_path):
    """The CLI writes the file and the report's contours section (with -q: nothing on stderr)."""
    src = tmp_path / "franke.xyz"
    cloud = franke_cloud(2000)
    np.savetxt(src, cloud.points)
    out, report = tmp_path / "dem.tif", tmp_path / "r.json"
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(src), "-o", str(out), "--resolution", "0.05", "--contours",
                                     str(tmp_path / "c.geojson"), "--interval", "0.25", "--report", str(report)])
    assert done.exit_code == 0, done.output
    facts = json.loads(report.read_text())["contours"]
    assert facts["file"] == str(tmp_path / "c.geojson") and facts["interval"] == 0.25
    assert facts["levels"]["lowest"] == 0.25 and facts["lines"] == read_lines(tmp_path / "c.geojson")[3]["features"]
    assert facts["max_level_error"] <= 1e-6 * 0.25 and "contours" in json.loads(report.read_text())["seconds"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.geojson", "dem.tif", "franke.xyz", "r.json"]
    assert os.stat(tmp_path / "c.geojson").st_size > 0


def test_a_shapefiles_parts_may_not_overwrite_other_outputs(tmp_path):
    """m.shp writes m.prj, m.dbf, ...: the mesh m.ply's .prj sidecar or a report m.dbf
    would be overwritten, so both are refused before the input is read (exit 1)."""
    src = tmp_path / "flat.xyz"
    np.savetxt(src, franke_cloud(300).points)
    for args, clash in ((["-o", str(tmp_path / "m.ply")], "m.prj"),
                        (["-o", str(tmp_path / "m.tif"), "--resolution", "0.1", "--report", str(tmp_path / "m.dbf")],
                         "m.dbf")):
        done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(src), *args, "--contours", str(tmp_path / "m.shp"),
                                         "--interval", "0.1"])
        assert done.exit_code == 1
        assert clash in done.output and len(done.output.strip().splitlines()) == 1
        assert sorted(p.name for p in tmp_path.iterdir()) == ["flat.xyz"]


def test_a_replaced_shapefile_loses_its_stale_parts(tmp_path):
    """Writing m.shp without a CRS over one that had a .prj and a spatial index removes
    them (they would describe the old file)."""
    from c1mesh.geo.contour_file import StagedContours

    for name in ("m.shp", "m.prj", "m.qix"):
        (tmp_path / name).write_text("old")
    with StagedContours(tmp_path / "m.shp") as staged:
        staged.write([np.array([[0.0, 0.0], [1.0, 1.0]])], np.array([1.0]), None)
        staged.commit()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.cpg", "m.dbf", "m.shp", "m.shx"]
    assert read_lines(tmp_path / "m.shp")[1].tolist() == [1.0]
