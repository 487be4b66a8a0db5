"""Issue 21: a DEM cell that holds input points has a value; curtain rules and LAS ground.

Truth: the analytic surface and its exact normals, rasterio reading the written GeoTIFF,
RSDInterpolator's own evaluation of the spline and its gradient (not the raster's
polynomial form), and a brute-force nearest triangle and closest point (every kept
triangle's, computed here).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from c1mesh.core.cloud import PointCloud
from c1mesh.pipeline.driver import FitOptions, build_surface, load_cloud
from c1mesh.pipeline.run import fit

rasterio = pytest.importorskip("rasterio")

DATA = Path(__file__).resolve().parent.parent / "data_samples"
TILE = DATA / "4_6_crop.las"


# ------------------------------------------------------------------------------ helpers
def _plane_cloud(rows_y, step=1.0, width=21, jitter=0.02, seed=3, classification=None):
    """Points on rows y in rows_y (x = 0, step, ...) of z = 0.1 x + 0.02 y² + 5, jittered,
    with the exact normals."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(width) * step, np.asarray(rows_y, float))
    xy = np.column_stack([x.ravel(), y.ravel()]) + rng.uniform(-jitter, jitter, (x.size, 2))
    z = 0.1 * xy[:, 0] + 0.02 * xy[:, 1] ** 2 + 5.0
    normals = np.column_stack([-0.1 * np.ones(len(z)), -0.04 * xy[:, 1], np.ones(len(z))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cls = None if classification is None else np.full(len(z), classification, np.uint8)
    return PointCloud(np.column_stack([xy, z]), normals, classification=cls)


def _read_dem(path):
    with rasterio.open(path) as ds:
        return ds.read(1).astype(np.float64), ds.transform, ds.nodata


def _cells_of(points, transform):
    """(row, col) of the cell holding each world point (a point on a west/north edge belongs to it)."""
    col = np.floor((points[:, 0] - transform.c) / transform.a).astype(np.int64)
    row = np.floor((points[:, 1] - transform.f) / transform.e).astype(np.int64)
    return row, col


def _distance(p, corners):
    """Distance from p (2,) to each triangle corners (T, 3, 2), and the closest point of
    each (T, 2), by brute force."""
    out, closest = np.full(len(corners), np.inf), np.repeat(p[None], len(corners), axis=0)
    for k in range(3):
        a, b = corners[:, k], corners[:, (k + 1) % 3]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
        foot = a + t[:, None] * ab
        d = np.linalg.norm(foot - p, axis=1)
        closer = d < out
        out[closer], closest[closer] = d[closer], foot[closer]
    sides = []
    for k in range(3):
        e, q = corners[:, (k + 1) % 3] - corners[:, k], p - corners[:, k]
        sides.append(e[:, 0] * q[:, 1] - e[:, 1] * q[:, 0])
    inside = np.all(np.array(sides) >= 0, axis=0) | np.all(np.array(sides) <= 0, axis=0)
    closest[inside] = p
    return np.where(inside, 0.0, out), closest


def _trifinder(interp):
    """matplotlib's point location in the kept triangles (independent of c1mesh.engine.locate)."""
    from matplotlib.tri import Triangulation

    return Triangulation(interp.points[:, 0], interp.points[:, 1], interp.triangles).get_trifinder()


def _continued(interp, q, p):
    """The spline at q (a point of the mesh, RSDInterpolator's own evaluation) continued
    linearly to p: value + gradient · (p − q)."""
    value, gradient = interp(q[None])[0], interp.gradient(q[None])[0]
    assert np.isfinite(value)
    return float(value + gradient @ (p - q))


def _check_dem(cloud, options, dem_path):
    """Every cell holding a point has a value; cells whose centre is in no kept triangle
    hold the nearest kept triangle's spline at its point closest to the centre, continued
    linearly, when that triangle is within max_edge (else nodata). Returns the number of
    such filled cells."""
    dem, transform, nodata = _read_dem(dem_path)
    model = build_surface(cloud, replace(options, axis="z"))
    interp, origin, reach = model.interp, model.frame.origin, model.trim_report.max_edge
    corners = interp.points[interp.triangles]
    row, col = _cells_of(cloud.points, transform)
    cells = np.array(sorted(set(zip(row.tolist(), col.tolist()))))
    centres = np.column_stack([transform.c + (cells[:, 1] + 0.5) * transform.a,
                               transform.f + (cells[:, 0] + 0.5) * transform.e]) - origin[:2]
    inside = _trifinder(interp)(centres[:, 0], centres[:, 1]) >= 0
    assert np.all(dem[tuple(cells[inside].T)] != nodata)
    filled = 0
    for (i, j), centre in zip(cells[~inside].tolist(), centres[~inside]):
        distance, closest = _distance(centre, corners)
        nearest = int(np.flatnonzero(distance == distance.min()).min())
        on_grid = 0 <= i < dem.shape[0] and 0 <= j < dem.shape[1]
        if reach is not None and distance[nearest] > reach:
            assert not on_grid or dem[i, j] == nodata, (i, j)
            continue
        assert on_grid, f"cell {(i, j)} holds points within max_edge of the mesh, off the grid"
        assert dem[i, j] != nodata, f"cell {(i, j)} holds points and is nodata"
        if distance[nearest] > 0:
            filled += 1
            expected = _continued(interp, closest[nearest], centre) + origin[2]
            assert dem[i, j] == pytest.approx(expected, abs=2e-6 * max(1.0, abs(expected)))
    return filled


# -------------------------------------------------------------------------------- tests
def test_cells_with_points_in_a_trimmed_gap_get_the_nearest_triangles_spline(tmp_path):
    """Rows 1 m apart with one 1.6 m gap and --max-edge 1.5: the trim removes the
    triangles across the gap, over cells that hold the points of its two rims."""
    rows = [*np.arange(10.0), *(np.arange(10.0) + 10.6)]
    cloud = _plane_cloud(rows)
    options = FitOptions(smooth="off", axis="z", max_edge=1.5, resolution=0.5, fill="off")
    fit(cloud, tmp_path / "dem.tif", options)
    assert _check_dem(cloud, options, tmp_path / "dem.tif") > 0       # the case is there


def test_points_beyond_max_edge_from_every_kept_triangle_stay_nodata(tmp_path):
    """An isolated point 6 m beyond the mesh (in a gap wider than --max-edge): no value."""
    cloud = _plane_cloud(np.arange(10.0))
    lone = np.array([[10.0, 15.0, 5.0 + 1.0 + 0.02 * 225]])
    cloud = PointCloud(np.vstack([cloud.points, lone]), np.vstack([cloud.normals, [[0, 0, 1.0]]]))
    options = FitOptions(smooth="off", axis="z", max_edge=1.5, resolution=0.5, fill="off")
    fit(cloud, tmp_path / "dem.tif", options)
    dem, transform, nodata = _read_dem(tmp_path / "dem.tif")
    row, col = _cells_of(lone, transform)
    assert not (0 <= row[0] < dem.shape[0] and 0 <= col[0] < dem.shape[1]) or dem[row[0], col[0]] == nodata
    _check_dem(cloud, options, tmp_path / "dem.tif")


def test_las_ground_tile_has_a_value_in_every_cell_with_ground_points(tmp_path):
    options = FitOptions(smooth="off", classes=(2,), resolution=1.0, fill="off")
    fit(TILE, tmp_path / "dem.tif", options)
    cloud = load_cloud(TILE, options)
    assert _check_dem(cloud, options, tmp_path / "dem.tif") > 0


def test_seamless_dem_equals_the_in_memory_dem(tmp_path):
    from c1mesh.pipeline.run import fit

    options = FitOptions(smooth="off", classes=(2,), resolution=1.0)          # the default fill
    fit(TILE, tmp_path / "fit.tif", options)
    fit([str(TILE)], str(tmp_path / "seamless.tif"), options).report
    one, two = _read_dem(tmp_path / "fit.tif")[0], _read_dem(tmp_path / "seamless.tif")[0]
    assert np.array_equal(one, two)


# ---------------------------------------------------------------- curtain rules on ground
def test_view_rules_apply_only_off_las_ground():
    from c1mesh.stages.curtains import view_rules_apply

    eye = np.eye(3)
    assert not view_rules_apply((2,), eye)
    assert not view_rules_apply((2, 9), eye)
    assert view_rules_apply(None, eye)                 # all classes: walls, trees
    assert view_rules_apply((2, 6), eye)               # buildings too
    tilted = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])   # e3 = world y
    assert view_rules_apply((2,), tilted)


def _bank_cloud(classification=None):
    """Ground with a 10 m bank 0.1 m wide (an 84° step across the dropped steep row) on a 0.5 m grid: a height field
    whose steep triangles the view rules take for curtains."""
    x, y = np.meshgrid(np.arange(0.0, 20.0, 0.5), np.arange(0.0, 10.0, 0.5))
    rng = np.random.default_rng(5)
    xy = np.column_stack([x.ravel(), y.ravel()]) + rng.uniform(-0.05, 0.05, (x.size, 2))
    u = (xy[:, 0] - 10.0) / 0.1
    z = 5.0 * np.tanh(u)
    dz = 5.0 / 0.1 / np.cosh(u) ** 2
    normals = np.column_stack([-dz, np.zeros_like(dz), np.ones_like(dz)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cls = None if classification is None else np.full(len(z), classification, np.uint8)
    return PointCloud(np.column_stack([xy, z]), normals, classification=cls)


def test_ground_class_keeps_the_steep_triangles_the_view_rules_remove():
    view = ("shadow_edge", "grazing", "facing_away")
    cloud = _bank_cloud(classification=2)
    scan = fit(cloud, None, FitOptions(smooth="off", axis="z", level=1)).report["triangles"]
    assert sum(scan["removed"][r] for r in view) > 0                 # as a range scan: curtains
    ground = fit(cloud, None, FitOptions(smooth="off", axis="z", classes=(2,), level=1)).report["triangles"]
    assert all(ground["removed"][r] == 0 for r in view)
    assert ground["after_trim"] > scan["after_trim"]


def test_nearest_triangle_among_the_rim_triangles_is_the_nearest_among_all():
    """geo.raster_grid.rim_triangles: for points outside a triangulated region with holes,
    the nearest triangle (ties to the lowest number) searched among the triangles with a
    corner on the region's boundary is the one a search of every triangle finds; on a
    jittered grid, where many distances tie, and with a reach."""
    from c1mesh.engine.topology import edge_table
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.geo.raster_grid import NearestTriangles, rim_triangles

    rng = np.random.default_rng(5)
    x, y = np.meshgrid(np.arange(30.0), np.arange(30.0))
    points = np.column_stack([x.ravel(), y.ravel()]) + rng.uniform(-0.1, 0.1, (900, 2)) * (rng.random((900, 1)) < 0.5)
    triangles = delaunay(points)
    centre = points[triangles].mean(axis=1)
    holes = (np.hypot(*(centre - [10, 10]).T) < 4) | (np.hypot(*(centre - [20, 18]).T) < 3)
    searched = np.flatnonzero(~holes)
    table = edge_table(triangles, len(points))
    rim = rim_triangles(table, searched)
    assert 0 < len(rim) < len(searched) / 2
    query = np.concatenate([rng.uniform(-5, 35, (400, 2)), rng.uniform(6, 14, (200, 2)),
                            np.array([[10.0, 10.0], [20.0, 18.0], [-3.0, 15.0]])])
    outside = ~_in_any(query, points[triangles[searched]])
    assert outside.sum() > 150
    for reach in (None, 2.0):
        every = NearestTriangles(points, triangles[searched], reach).of(query)
        among_rim = NearestTriangles(points, triangles[rim], reach).of(query)
        expected = np.where(every >= 0, searched[np.maximum(every, 0)], -1)
        got = np.where(among_rim >= 0, rim[np.maximum(among_rim, 0)], -1)
        np.testing.assert_array_equal(got[outside], expected[outside])


def _in_any(query, corners, tol=1e-12):
    """(q,) whether each point lies in (or on) any of the triangles corners (T, 3, 2)."""
    p = query[:, None, :]
    a, b, c = (corners[None, :, k, :] for k in range(3))
    d1 = (b[..., 0] - a[..., 0]) * (p[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (p[..., 0] - a[..., 0])
    d2 = (c[..., 0] - b[..., 0]) * (p[..., 1] - b[..., 1]) - (c[..., 1] - b[..., 1]) * (p[..., 0] - b[..., 0])
    d3 = (a[..., 0] - c[..., 0]) * (p[..., 1] - c[..., 1]) - (a[..., 1] - c[..., 1]) * (p[..., 0] - c[..., 0])
    inside = ((d1 >= -tol) & (d2 >= -tol) & (d3 >= -tol)) | ((d1 <= tol) & (d2 <= tol) & (d3 <= tol))
    return inside.any(axis=1)
