"""Georeferenced terrain: CRS in and out, GeoTIFF DEM/slope/aspect/hillshade, previews, GLB.

Truth comes from outside the code under test: EPSG codes of the bundled PDAL tiles,
analytic terrains with exact normals, matplotlib's TrapezoidMapTriFinder for "inside the
trimmed mesh", rasterio for reading the files, GDAL's hillshade formula.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from c1mesh.cli import main
from c1mesh.core.cloud import PointCloud, SurfaceMesh
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.formats import read_cloud, write_mesh
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit

pyproj = pytest.importorskip("pyproj")
rasterio = pytest.importorskip("rasterio")

DATA = Path(__file__).resolve().parent.parent / "data_samples"
TILE = DATA / "4_6_crop.las"            # EPSG:2903, NAD83(HARN) / New Mexico Central (ftUS)
AUTZEN = DATA / "autzen_trim.laz"        # WKT VLR: Lambert Conformal Conic, international feet
OFFSET = np.array([640000.0, 850000.0, 120.0])


def _crs(text):
    return pyproj.CRS.from_user_input(text)


def _terrain(n=3000, seed=1):
    """Points of z = 0.4 sin(x) cos(0.7 y) + 0.1 x on [0, 6]², with the exact gradient."""
    xy = np.random.default_rng(seed).random((n, 2)) * 6.0
    x, y = xy[:, 0], xy[:, 1]
    z = 0.4 * np.sin(x) * np.cos(0.7 * y) + 0.1 * x
    g = np.column_stack([0.4 * np.cos(x) * np.cos(0.7 * y) + 0.1, -0.28 * np.sin(x) * np.sin(0.7 * y)])
    return xy, z, g


def _terrain_slope(x, y):
    gx = 0.4 * np.cos(x) * np.cos(0.7 * y) + 0.1
    gy = -0.28 * np.sin(x) * np.sin(0.7 * y)
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def _terrain_file(path, n=3000):
    xy, z, g = _terrain(n)
    normals = np.column_stack([-g, np.ones(n)])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    write_mesh(SurfaceMesh(np.column_stack([xy, z]) + OFFSET, np.empty((0, 3), np.int64), normals), path)
    return path


def _cells(path):
    """Band 1 (masked) and world x, y of every cell centre, from the file's own transform."""
    ds = rasterio.open(path)
    band = ds.read(1, masked=True)
    rows, cols = np.indices(band.shape)
    x, y = ds.transform @ (cols + 0.5, rows + 0.5)
    return band, np.asarray(x), np.asarray(y), ds


# ------------------------------------------------------------------------------- CRS in
def test_las_geokeys_crs_is_read():
    assert _crs(read_cloud(TILE).crs).to_epsg() == 2903


def test_las_wkt_vlr_crs_is_read():
    crs = _crs(read_cloud(AUTZEN).crs)
    assert crs.is_projected and "Lambert_Conformal_Conic" in crs.to_wkt("WKT1_ESRI")
    assert crs.axis_info[0].unit_name == "foot"


def _info(path) -> dict:
    """`c1mesh info PATH` in a child process (info needs a real stdout)."""
    import os
    import subprocess
    import sys
    src = str(Path(__file__).resolve().parent.parent / "src")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [src, os.environ.get("PYTHONPATH")])))
    done = subprocess.run([sys.executable, "-m", "c1mesh.cli", "info", str(path)], capture_output=True,
                          text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_info_shows_the_crs_of_las_and_of_our_ply(tmp_path):
    runner = CliRunner()
    assert _info(TILE)["crs"]["epsg"] == 2903
    out = tmp_path / "ground.ply"
    done = runner.invoke(main, ["fit", "--smooth", "off", str(TILE), "--classes", "2", "--level", "1", "-o", str(out)])
    assert done.exit_code == 0, done.output
    assert _info(out)["crs"]["epsg"] == 2903
    assert _crs((tmp_path / "ground.prj").read_text()).equals(_crs("EPSG:2903"))


# ------------------------------------------------------------------------------ CRS out
@pytest.mark.parametrize("ext", ["ply", "obj", "stl", "off", "glb"])
def test_every_mesh_format_carries_the_crs(tmp_path, ext):
    crs = _crs("EPSG:32633").to_wkt()
    mesh = SurfaceMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.5]]) + OFFSET, np.array([[0, 1, 2]]),
                       np.tile([0.0, 0.0, 1.0], (3, 1)))
    out = tmp_path / f"m.{ext}"
    write_mesh(mesh, out, crs=crs)
    if ext == "glb":
        data = out.read_bytes()
        length = int.from_bytes(data[12:16], "little")
        document = json.loads(data[20:20 + length])
        assert _crs(document["asset"]["extras"]["crs"]).to_epsg() == 32633
        assert not (tmp_path / "m.prj").exists()
    else:
        assert _crs((tmp_path / "m.prj").read_text()).to_epsg() == 32633
    if ext == "ply":
        assert _crs(read_cloud(out).crs).to_epsg() == 32633


def test_crs_option_assigns_where_the_input_has_none(tmp_path):
    src = _terrain_file(tmp_path / "t.ply", 400)
    out = tmp_path / "out.ply"
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(src), "-o", str(out), "--level", "1",
                                     "--crs", "EPSG:32633", "--report", str(tmp_path / "r.json")])
    assert done.exit_code == 0, done.output
    assert _crs(read_cloud(out).crs).to_epsg() == 32633
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["crs"]["epsg"] == 32633 and report["crs"]["source"] == "option"


def test_crs_option_that_contradicts_the_file_is_an_error(tmp_path):
    out = tmp_path / "out.ply"
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(TILE), "--classes", "2", "-o", str(out),
                                     "--crs", "EPSG:4326"])
    assert done.exit_code == 1 and "does not reproject" in done.output
    assert not out.exists()
    same = CliRunner().invoke(main, ["fit", "--smooth", "off", str(TILE), "--classes", "2", "-o", str(out), "--level", "1",
                                     "--crs", "EPSG:2903"])
    assert same.exit_code == 0, same.output


def test_crs_from_a_prj_file(tmp_path):
    prj = tmp_path / "a.prj"
    prj.write_text(_crs("EPSG:2903").to_wkt("WKT1_ESRI"))
    from c1mesh.core.crs import parse_crs
    assert _crs(parse_crs(str(prj))).equals(_crs("EPSG:2903"))


# --------------------------------------------------------------------- fail before work
@pytest.mark.parametrize("args, code, words", [
    (["-o", "{tmp}/x.ply", "--crs", "EPSG:99999999"], 1, "cannot parse the CRS"),
    (["-o", "{tmp}/x.dem"], 2, "Unsupported output format 'dem'"),
    (["-o", "{tmp}/missing/x.tif", "--resolution", "1"], 1, "does not exist"),
    (["-o", "{tmp}/x.tif"], 2, "need --resolution"),
    (["-o", "{tmp}/x.ply", "--slope", "{tmp}/s.tif", "--resolution", "1"], 2, "come with a DEM"),
    (["-o", "{tmp}/x.tif", "--resolution", "1", "--slope", "{tmp}/s.png"], 2, "must be a GeoTIFF"),
    (["-o", "{tmp}/x.tif", "--resolution", "1", "--preview", "{tmp}/p.jpg"], 2, "must be a .png"),
    (["-o", "{tmp}/x.tif", "--resolution", "1", "--axis", "x"], 2, "--axis x cannot be used"),
])
def test_bad_outputs_fail_before_the_input_is_read(tmp_path, args, code, words):
    """Conflicts the command line alone shows are usage errors (exit 2); a bad CRS or a
    missing directory exit 1; all before the input is read."""
    # the input does not exist: an error about it would mean the input was looked at first
    argv = ["fit", "--smooth", "off", str(tmp_path / "no-such-input.las")] + [a.format(tmp=tmp_path) for a in args]
    done = CliRunner().invoke(main, argv)
    assert done.exit_code == code and words in done.output, done.output
    assert list(tmp_path.iterdir()) == []


def test_level_and_resolution_conflict_is_a_usage_error(tmp_path):
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(TILE), "-o", str(tmp_path / "x.ply"), "--level", "3",
                                     "--resolution", "2"])
    assert done.exit_code == 2 and "--level or --resolution" in done.output


# ------------------------------------------------------------------------------- rasters
def _fitted(n=3000):
    """The interpolator on the triangulation the fit pipeline uses (Delaunay, hull slivers
    trimmed: they make the spline's gradient wrong by tens of degrees near the hull)."""
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.stages.trim import trim
    xy, z, g = _terrain(n)
    triangles, _ = trim(xy, delaunay(xy), max_edge="auto")
    return RSDInterpolator(xy, z, g, triangles=triangles)


def test_dem_cells_are_the_interpolator_at_cell_centres(tmp_path):
    from c1mesh.geo.raster import RasterTargets, write_rasters
    from c1mesh.geo.raster_grid import RasterGrid, SplineSampler
    interp = _fitted()
    origin = OFFSET
    res = 0.05                                  # point spacing is 6 / √3000 ≈ 0.11
    grid = RasterGrid.covering(interp.points.min(0) + origin[:2], interp.points.max(0) + origin[:2], res)
    assert grid.west / res == round(grid.west / res) and grid.north / res == round(grid.north / res)
    targets = RasterTargets(dem=str(tmp_path / "dem.tif"), slope=str(tmp_path / "slope.tif"))
    write_rasters(targets, grid, SplineSampler(interp, origin), "spline", block_rows=37,
                  dem_dtype="float64")
    band, x, y, _ = _cells(tmp_path / "dem.tif")
    expected = interp(np.column_stack([x.ravel() - origin[0], y.ravel() - origin[1]])).reshape(x.shape)
    inside = np.isfinite(expected)
    assert np.array_equal(~np.ma.getmaskarray(band), inside)
    assert np.abs(band.data[inside] - (expected[inside] + origin[2])).max() < 1e-9
    slope, *_ = _cells(tmp_path / "slope.tif")
    err = slope.data[inside] - _terrain_slope(x[inside] - origin[0], y[inside] - origin[1])
    assert math.sqrt(np.mean(err ** 2)) <= 1.0


def test_slope_and_hillshade_from_the_cli_match_the_analytic_terrain(tmp_path):
    src = _terrain_file(tmp_path / "t.ply")
    runner = CliRunner()
    for method in ("spline", "horn"):
        done = runner.invoke(main, ["fit", "--smooth", "off", str(src), "-o", str(tmp_path / f"dem_{method}.tif"),
                                    "--resolution", "0.05", "--slope", str(tmp_path / f"s_{method}.tif"),
                                    "--aspect", str(tmp_path / f"a_{method}.tif"), "--slope-method", method,
                                    "--hillshade", str(tmp_path / f"h_{method}.tif"), "--crs", "EPSG:32633",
                                    "--fill", "off"])   # the trimmed surface; the fill: test_dem_fill.py
        assert done.exit_code == 0, done.output
        slope, x, y, ds = _cells(tmp_path / f"s_{method}.tif")
        assert ds.crs.to_epsg() == 32633
        ok = ~np.ma.getmaskarray(slope)
        lx, ly = x[ok] - OFFSET[0], y[ok] - OFFSET[1]
        err = slope.data[ok] - _terrain_slope(lx, ly)
        assert math.sqrt(np.mean(err ** 2)) <= 1.0, method
        # GDAL's hillshade formula (gdaldem, azimuth 315, altitude 45) on the analytic terrain
        aspect, *_ = _cells(tmp_path / f"a_{method}.tif")
        shade, *_ = _cells(tmp_path / f"h_{method}.tif")
        gx = 0.4 * np.cos(lx) * np.cos(0.7 * ly) + 0.1
        gy = -0.28 * np.sin(lx) * np.sin(0.7 * ly)
        s, a = np.arctan(np.hypot(gx, gy)), np.arctan2(-gx, -gy)   # aspect: downhill, from north
        gdal = np.sin(np.radians(45)) * np.cos(s) + np.cos(np.radians(45)) * np.sin(s) * np.cos(np.radians(315) - a)
        assert np.abs(shade.data[ok] - (1 + 254 * np.clip(gdal, 0, 1))).mean() < 2.0
        # slope and aspect together give back the gradient: −tan(slope)·(sin, cos)(aspect)
        t, rad = np.tan(np.radians(slope.data[ok])), np.radians(aspect.data[ok])
        error = np.hypot(-t * np.sin(rad) - gx, -t * np.cos(rad) - gy)
        assert math.sqrt(np.mean(error ** 2)) <= math.tan(math.radians(1.0)), method


def test_aspect_of_planes_points_downhill():
    from c1mesh.geo.raster import aspect_degrees, slope_degrees
    g = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])    # rising east, north, west, south
    assert np.allclose(aspect_degrees(g), [270, 180, 90, 0])
    assert np.allclose(slope_degrees(g), 45)
    assert aspect_degrees(np.array([[0.0, 0.0], [-0.0, -0.0]])).tolist() == [0.0, 0.0]


def test_lidar_ground_dem_slope_hillshade(tmp_path):
    from matplotlib.tri import Triangulation
    dem, slope, shade = tmp_path / "dem.tif", tmp_path / "slope.tif", tmp_path / "hs.tif"
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(TILE), "--classes", "2", "-o", str(dem),
                                     "--resolution", "3", "--slope", str(slope), "--hillshade", str(shade),
                                     "--fill", "off"])       # the trimmed DEM (the fill: test_dem_fill.py)
    assert done.exit_code == 0, done.output
    band, x, y, ds = _cells(dem)
    assert ds.crs == rasterio.crs.CRS.from_epsg(2903)
    assert ds.res == (3.0, 3.0) and ds.transform.c % 3 == 0 and ds.transform.f % 3 == 0
    assert ds.block_shapes[0] == (256, 256) and ds.dtypes[0] == "float32"
    # nodata exactly where the cell centre is outside the trimmed triangulation (the level-1
    # mesh) and the cell holds no ground point (issue 21; every point of this tile lies
    # within --max-edge of a kept triangle: tests/test_dem_holes.py checks the reach)
    mesh = fit(str(TILE), None, FitOptions(smooth="off", classes=(2,), level=1, axis="z")).mesh   # DEMs use --axis z
    tri = Triangulation(mesh.vertices[:, 0], mesh.vertices[:, 1], mesh.faces)
    from c1mesh.pipeline.driver import load_cloud
    points = load_cloud(str(TILE), FitOptions(smooth="off", classes=(2,))).points
    rows = np.floor((points[:, 1] - ds.transform.f) / ds.transform.e).astype(int)
    cols = np.floor((points[:, 0] - ds.transform.c) / ds.transform.a).astype(int)
    holds_points = np.zeros(x.shape, bool)
    holds_points[rows, cols] = True
    outside = tri.get_trifinder()(x.ravel(), y.ravel()).reshape(x.shape) < 0
    assert outside.any() and (~outside).sum() > 0.9 * outside.size
    assert (outside & holds_points).any()                          # cells the rule fills
    outside &= ~holds_points
    assert np.array_equal(np.ma.getmaskarray(band), outside)
    for path in (slope, shade):
        other = rasterio.open(path)
        assert other.crs == ds.crs and other.transform == ds.transform
        assert np.array_equal(np.ma.getmaskarray(other.read(1, masked=True)), outside)


def test_dem_has_overviews_and_is_tiled(tmp_path):
    src = _terrain_file(tmp_path / "t.ply")
    dem = tmp_path / "dem.tif"
    assert CliRunner().invoke(main, ["fit", "--smooth", "off", str(src), "-o", str(dem), "--resolution", "0.01"]).exit_code == 0
    with rasterio.open(dem) as ds:
        assert ds.width >= 512 and ds.block_shapes[0] == (256, 256)
        assert ds.overviews(1)[:2] == [2, 4]
        assert ds.dtypes[0] == "float32" and ds.compression is not None


def test_every_raster_is_a_valid_cog_with_overviews_and_a_predictor(tmp_path):
    """rio-cogeo's validator (a peer of GDAL's own validate_cloud_optimized_geotiff.py)
    accepts every raster a fit writes; each is deflated with a predictor and has internal
    overviews; no staging file is left beside them."""
    cogeo = pytest.importorskip("rio_cogeo.cogeo")
    src = _terrain_file(tmp_path / "t.ply")
    out = tmp_path / "out"
    out.mkdir()
    names = {"dem": "dem.tif", "slope": "slope.tif", "aspect": "aspect.tif", "hillshade": "hs.tif",
             "support": "support.tif"}
    args = ["fit", "--smooth", "off", str(src), "-o", str(out / names["dem"]), "--resolution", "0.01"]
    for kind in ("slope", "aspect", "hillshade", "support"):
        args += [f"--{kind}", str(out / names[kind])]
    done = CliRunner().invoke(main, args)
    assert done.exit_code == 0, done.output
    assert sorted(p.name for p in out.iterdir()) == sorted(names.values())
    for kind, name in names.items():
        valid, errors, _ = cogeo.cog_validate(str(out / name), strict=True)
        assert valid and not errors, (kind, errors)
        with rasterio.open(out / name) as ds:
            assert ds.overviews(1)[:2] == [2, 4], kind
            assert ds.compression.name.lower() == "deflate", kind
            predictor = ds.tags(ns="IMAGE_STRUCTURE").get("PREDICTOR")
            assert predictor == ("2" if kind == "hillshade" else "3"), (kind, predictor)


def test_a_failing_cog_copy_leaves_no_raster_and_no_staging_file(tmp_path, monkeypatch):
    """Atomic outputs: when GDAL's copy into the COG fails after the blocks were staged,
    nothing is left in the output folder (no DEM, no side raster, no staging file)."""
    import c1mesh.geo.raster as raster

    src = _terrain_file(tmp_path / "t.ply")
    out = tmp_path / "out"
    out.mkdir()
    copies = []

    def failing(source, target, kind):
        copies.append(kind)
        if len(copies) == 2:
            raise OSError("disk full")
        return original(source, target, kind)
    original = raster.cog_copy
    monkeypatch.setattr(raster, "cog_copy", failing)
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(src), "-o", str(out / "dem.tif"), "--resolution", "0.05",
                                     "--slope", str(out / "slope.tif"), "--support", str(out / "support.tif")])
    assert done.exit_code == 1 and "disk full" in done.output
    assert len(copies) == 2 and list(out.iterdir()) == []


def test_resolution_picks_the_level_for_a_mean_edge(tmp_path):
    src = _terrain_file(tmp_path / "t.ply", 800)
    mesh_l1 = fit(str(src), None, FitOptions(smooth="off", level=1, axis="z")).mesh

    def mean_edge(m):
        v, f = m.vertices, m.faces
        return np.mean([np.linalg.norm(v[f[:, a]] - v[f[:, b]], axis=1).mean() for a, b in ((0, 1), (1, 2), (2, 0))])
    target = mean_edge(mesh_l1) / 3.2
    result = fit(str(src), None, FitOptions(smooth="off", resolution=target, axis="z"))
    assert result.report["level"] == 3
    assert abs(mean_edge(result.mesh) / target - 1) < 0.15


# ------------------------------------------------------------------------------- GLB
def test_glb_world_positions_match_the_ply_on_a_lidar_tile(tmp_path):
    from c1mesh.formats.meshes import read_glb_vertices
    options = FitOptions(smooth="off", classes=(2,), level=2)
    fit(str(TILE), str(tmp_path / "g.ply"), options, keep_mesh=False)
    fit(str(TILE), str(tmp_path / "g.glb"), options, keep_mesh=False)
    ply = read_cloud(tmp_path / "g.ply").points
    glb = read_glb_vertices((tmp_path / "g.glb").read_bytes())[0]
    assert np.abs(glb - ply).max() <= 1e-4
    import trimesh  # a peer reader applies the node translation
    scene = trimesh.load(tmp_path / "g.glb")
    peer = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
    assert np.abs(np.asarray(peer.vertices) - ply).max() <= 1e-4
    faces = np.asarray(peer.faces)
    v = np.asarray(peer.vertices)
    area = np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)
    assert (area > 0).all()


# ------------------------------------------------------------------------------- previews
def _png_ok(path):
    import matplotlib.image
    img = matplotlib.image.imread(path)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 200
    assert img[..., :3].std() > 0.05                     # not blank


def test_preview_of_a_fit_and_of_its_outputs(tmp_path):
    dem, ply = tmp_path / "dem.tif", tmp_path / "g.ply"
    runner = CliRunner()
    done = runner.invoke(main, ["fit", "--smooth", "off", str(TILE), "--classes", "2", "-o", str(dem), "--resolution", "3",
                                "--preview", str(tmp_path / "fit.png")])
    assert done.exit_code == 0, done.output
    _png_ok(tmp_path / "fit.png")
    glb = tmp_path / "g.glb"
    for out in (ply, glb):
        assert runner.invoke(main, ["fit", "--smooth", "off", str(TILE), "--classes", "2", "-o", str(out), "--level", "2"]).exit_code == 0
    for source, png in ((dem, "dem.png"), (ply, "ply.png"), (glb, "glb.png")):
        done = runner.invoke(main, ["preview", str(source), "-o", str(tmp_path / png)])
        assert done.exit_code == 0, done.output
        _png_ok(tmp_path / png)
    bad = runner.invoke(main, ["preview", str(tmp_path / "none.tif"), "-o", str(tmp_path / "x.png")])
    assert bad.exit_code == 1 and "does not exist" in bad.output


def test_point_cloud_crs_survives_subset():
    cloud = PointCloud(points=np.zeros((3, 3)), crs="X")
    assert cloud.subset(np.array([True, False, True])).crs == "X"


# ------------------------------------------------------------------- DEMs and the perspective frame
@pytest.mark.parametrize("args", [
    ["-o", "{tmp}/x.tif", "--resolution", "1", "--frame", "perspective"],
    ["-o", "{tmp}/x.ply", "--slope", "{tmp}/s.tif", "--resolution", "1", "--frame", "perspective"],
    ["-O", "{tmp}/out", "--suffix", ".tif", "--resolution", "1", "--frame", "perspective"],
])
def test_geotiff_outputs_of_a_perspective_frame_are_a_usage_error_before_any_work(tmp_path, args):
    # the input does not exist: an error about it would mean the input was looked at first
    argv = ["fit", "--smooth", "off", str(tmp_path / "no-such-input.pcd")] + [a.format(tmp=tmp_path) for a in args]
    done = CliRunner().invoke(main, argv)
    assert done.exit_code == 2 and "perspective frame" in done.output, done.output
    assert list(tmp_path.iterdir()) == []


def test_organised_height_raster_with_auto_frame_is_fitted_as_a_dem(tmp_path):
    """An organised PCD (a grid of heights, HEIGHT > 1) would be a perspective fit; asked
    for a DEM, --frame auto fits it in the axis frame: the cells are the plane's heights."""
    from c1mesh.testing.samples import write_organised_pcd

    x, y = np.meshgrid(np.linspace(0.0, 6.0, 25), np.linspace(0.0, 6.0, 25))
    z = 0.3 * x - 0.2 * y + 1.0
    normal = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
    points = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    write_organised_pcd(points, np.tile(normal, (len(points), 1)), (25, 25), tmp_path / "grid.pcd")
    dem = tmp_path / "dem.tif"
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(tmp_path / "grid.pcd"), "-o", str(dem), "--resolution", "0.5"])
    assert done.exit_code == 0, done.output
    band, cx, cy, _ = _cells(dem)
    assert band.count() > 100
    np.testing.assert_allclose(band.compressed(), (0.3 * cx - 0.2 * cy + 1.0)[~band.mask], atol=1e-9)


# --------------------------------------------- heights in units of their own (issue 21)
GRADIENT_M_PER_KM = (30.0, -40.0)          # a plane rising 30 m per km east, falling 40 m per km north


def _km_m_plane_csv(path, n=400, seed=3):
    """A CSV `x,y,z`: x, y in km on [0, 10]², z = 200 m + 30 m/km x − 40 m/km y in metres.
    Its header names z, so the fit takes z as heights in units of their own."""
    xy = np.random.default_rng(seed).random((n, 2)) * 10.0
    z = 200.0 + GRADIENT_M_PER_KM[0] * xy[:, 0] + GRADIENT_M_PER_KM[1] * xy[:, 1]
    path.write_text("x,y,z\n" + "".join(f"{x:.17g},{y:.17g},{h:.17g}\n" for (x, y), h in zip(xy, z)))
    return path


def test_height_column_slope_and_hillshade_take_the_z_factor(tmp_path):
    """Issue 21 leftover: with a header height column the slope came out as if metres were
    km (topo: ~88°). With --z-factor 0.001 (km per m) slope = atan(|∇z| · 0.001) on every
    cell, the hillshade is GDAL's formula at that slope, and aspect is the plan direction
    downhill, the same without a z-factor."""
    src = _km_m_plane_csv(tmp_path / "plane.csv")
    out = {k: tmp_path / f"{k}.tif" for k in ("dem", "slope", "aspect", "hillshade")}
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(src), "-o", str(out["dem"]), "--resolution", "0.25",
                                     "--slope", str(out["slope"]), "--aspect", str(out["aspect"]),
                                     "--hillshade", str(out["hillshade"]), "--z-factor", "0.001"])
    assert done.exit_code == 0, done.output
    gx, gy = GRADIENT_M_PER_KM
    s = math.atan(math.hypot(gx, gy) * 0.001)                     # 2.862°
    a = math.atan2(-gx, -gy)                                      # downhill azimuth from north
    slope = _cells(out["slope"])[0]
    assert slope.count() > 1000
    np.testing.assert_allclose(slope.compressed(), math.degrees(s), rtol=0, atol=1e-4)
    aspect = _cells(out["aspect"])[0]
    np.testing.assert_allclose(aspect.compressed(), math.degrees(a) % 360, rtol=0, atol=1e-4)
    gdal = math.sin(math.radians(45)) * math.cos(s) + \
        math.cos(math.radians(45)) * math.sin(s) * math.cos(math.radians(315) - a)
    shade = _cells(out["hillshade"])[0]
    assert set(shade.compressed().tolist()) == {round(1 + 254 * gdal)}


@pytest.mark.parametrize("asked", [["--slope", "slope.tif"], ["--hillshade", "shade.tif"]], ids=["slope", "hillshade"])
def test_height_column_angles_without_z_factor_are_refused_before_any_output(tmp_path, asked):
    """Without --z-factor the angle of metres over km is unknown: one line naming the fix,
    exit 1, and no file written (no DEM either). --aspect alone needs no factor."""
    src = _km_m_plane_csv(tmp_path / "plane.csv")
    before = sorted(p.name for p in tmp_path.iterdir())
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(src), "-o", str(tmp_path / "dem.tif"), "--resolution", "0.25",
                                     asked[0], str(tmp_path / asked[1])])
    assert done.exit_code == 1
    lines = done.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("c1mesh: error: ") and "--z-factor" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    done = CliRunner().invoke(main, ["fit", "--smooth", "off", str(src), "-o", str(tmp_path / "dem.tif"), "--resolution", "0.25",
                                     "--aspect", str(tmp_path / "aspect.tif")])
    assert done.exit_code == 0, done.output


@pytest.mark.parametrize("z_factor, shading", [(0.001, (0.03, -0.04)), (None, (0.0, 0.0))],
                         ids=["z-factor", "unknown"])
def test_preview_of_a_height_column_shades_with_the_z_factor(tmp_path, monkeypatch, z_factor, shading):
    """The preview's light sees the gradient in height per x, y unit times --z-factor (the
    km/m plane: (30, −40) m/km · 0.001); without a factor the slopes are unknown and the
    picture is unshaded (zero gradient) instead of lit as if metres were km."""
    import c1mesh.geo.preview as preview

    seen = []
    monkeypatch.setattr(preview, "render_arrays", lambda z, g, *rest: seen.append(g))
    src = _km_m_plane_csv(tmp_path / "plane.csv")
    fit(src, None, FitOptions(smooth="off", level=1, preview=str(tmp_path / "p.png"), z_factor=z_factor))
    (gradient,) = seen
    inside = np.isfinite(gradient).all(axis=-1)
    assert inside.sum() > 1000
    # the heights' least-squares gradients of a plane are exact to rounding (~1e-8 here);
    # one level of the 8-bit shading is a gradient change of ~4e-3
    np.testing.assert_allclose(gradient[inside], np.broadcast_to(shading, gradient[inside].shape),
                               rtol=0, atol=1e-6)


@pytest.mark.parametrize("smoothed, horn_below", [(False, 8.0), (True, 4.0)])
def test_auto_slope_method_crossover_is_4_spacings_for_a_smoothing_fit_and_8_for_the_exact(smoothed, horn_below):
    """Issue 38: the smoothing fit's analytic slope beats Horn's from 4 point spacings on
    (benchmarks.geo noisy-slope); the exact fit's from 8 (with exact normals)."""
    from c1mesh.geo.raster import choose_slope_method

    for factor in (1.0, 2.0, 3.0, 3.99, 4.0, 6.0, 7.99, 8.0, 16.0):
        chosen = choose_slope_method("auto", factor * 1.5, 1.5, smoothed)
        assert chosen == ("horn" if factor < horn_below else "spline"), factor
    assert choose_slope_method("horn", 100.0, 1.0, smoothed) == "horn"
    assert choose_slope_method("spline", 0.1, 1.0, smoothed) == "spline"


def test_a_smoothing_fit_at_5_spacings_writes_the_spline_slope_and_the_exact_fit_horns(tmp_path):
    """End to end: the report's slope method follows the fit (--smooth auto: spline at 5
    spacings; --smooth off: Horn's there)."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 60, (3600, 2))
    z = np.sin(xy[:, 0] / 9) * 3 + 0.02 * xy[:, 1] + rng.normal(0, 0.02, len(xy))
    src = tmp_path / "noisy.xyz"
    np.savetxt(src, np.column_stack([xy, z]), fmt="%.5f")
    methods = {}
    for smooth in ("auto", "off"):
        report = tmp_path / f"{smooth}.json"
        done = CliRunner().invoke(main, ["fit", str(src), "-o", str(tmp_path / f"{smooth}.tif"), "--axis", "z",
                                         "--resolution", "5", "--slope", str(tmp_path / f"s_{smooth}.tif"),
                                         "--smooth", smooth, "--report", str(report)])
        assert done.exit_code == 0, done.output
        raster = json.loads(report.read_text())["raster"]
        assert 4.0 < 5 / raster["point_spacing"] < 8.0          # 5 m is between the two crossovers
        methods[smooth] = raster["slope_method"]
    assert methods == {"auto": "spline", "off": "horn"}


def test_mean_spacing_in_blocks_has_the_one_pass_bits(monkeypatch):
    """raster.mean_spacing forms the twice-areas in blocks (a memory bound) but sums them
    whole: the bits of the one-pass numpy expression, for blocks that do and do not
    divide the triangles."""
    from c1mesh.geo import raster
    rng = np.random.default_rng(3)
    points = rng.random((5000, 3)) * 100.0
    triangles = rng.integers(0, 5000, (12345, 3))
    a, b, c = (points[triangles[:, k]] for k in range(3))
    u, v = b - a, c - a
    want = math.sqrt(0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).sum() / points.shape[0])
    for block in (1000, 12345, 1 << 16):
        monkeypatch.setattr(raster, "SPACING_BLOCK", block)
        assert raster.mean_spacing(points, triangles) == want
