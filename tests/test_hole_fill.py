"""The lattice fit's hole fill (stages.hole_fill), against independent truth: qhull's hull
of every point, a brute-force point-in-polygon test, the holes counted cell by cell, and
the fill of a hole whose rim lies on a plane or a quadratic (the RSD spline holds both, so
the energy's minimiser is that polynomial: it has the least energy of any C1 function
with its data on a closed rim, being biharmonic)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from c1mesh.stages.hole_fill import (Holes, LatticeVertices, cell_corners, fill_holes, filled_lattice,
                                     find_holes, hull_cells, joined_hull, point_hull, support_cells)
from c1mesh.stages.lattice_mesh import cell_triangles, lattice_mesh, node_grid


def _inside(points: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """Brute force: on or left of every counter-clockwise edge of hull."""
    inside = np.ones(len(points), dtype=bool)
    for a, b in zip(hull, np.roll(hull, -1, axis=0)):
        inside &= (b[0] - a[0]) * (points[:, 1] - a[1]) - (b[1] - a[1]) * (points[:, 0] - a[0]) >= 0
    return inside


@pytest.mark.parametrize("kind", ["uniform", "disc", "grid", "few"])
def test_point_hull_is_qhulls_hull_of_every_point(kind):
    rng = np.random.default_rng(3)
    if kind == "uniform":
        xy = rng.uniform(-50.0, 80.0, (20000, 2))
    elif kind == "disc":
        angle = rng.uniform(0, 2 * np.pi, 5000)
        xy = np.column_stack([np.cos(angle), np.sin(angle)]) * rng.uniform(0, 30, (5000, 1)) ** 0.5
    elif kind == "grid":                    # the corners are extreme in several directions at once
        xy = np.stack(np.meshgrid(np.arange(60.0), np.arange(40.0)), -1).reshape(-1, 2)
    else:
        xy = rng.uniform(0, 1, (4, 2))
    hull = point_hull(xy)
    expected = xy[ConvexHull(xy).vertices]
    assert sorted(map(tuple, hull)) == sorted(map(tuple, expected))
    area = 0.5 * np.sum(hull[:, 0] * np.roll(hull[:, 1], -1) - np.roll(hull[:, 0], -1) * hull[:, 1])
    assert area > 0                           # counter-clockwise


def test_points_without_area_have_no_hull():
    line = np.column_stack([np.arange(10.0), 2 * np.arange(10.0)])
    assert point_hull(line).shape == (0, 2)
    assert point_hull(line[:2]).shape == (0, 2)
    assert point_hull(np.ones((7, 2))).shape == (0, 2)


def test_the_hull_of_parts_is_the_hull_of_the_whole():
    rng = np.random.default_rng(8)
    xy = rng.normal(0.0, 10.0, (9000, 2))
    parts = [point_hull(xy[k::3]) for k in range(3)] + [point_hull(xy[:1])]
    assert sorted(map(tuple, joined_hull(parts))) == sorted(map(tuple, point_hull(xy)))


@pytest.mark.parametrize("seed", range(4))
def test_hull_cells_are_the_cells_whose_centres_lie_in_the_hull(seed):
    rng = np.random.default_rng(seed)
    xy = rng.normal(0.0, 1.0, (30, 2)) * rng.uniform(5, 40, 2) + rng.uniform(-10, 10, 2)
    grid = node_grid(xy.min(axis=0), xy.max(axis=0), rng.uniform(0.7, 2.0), 1.0,
                     tuple(rng.uniform(0, 0.5, 2)))
    hull = point_hull(xy)
    rows, cols = grid.cells
    every = np.arange(rows * cols)
    expected = every[_inside(grid.centres(every), hull)]
    assert expected.size > 20
    np.testing.assert_array_equal(hull_cells(grid, hull), expected)


def test_support_cells_of_triangles_in_any_order():
    grid = node_grid((0.0, 0.0), (20.0, 15.0), 1.0, 1.0)
    cells = np.array([3, 4, 17, 90, 91, 200])
    triangles = cell_triangles(grid, cells)
    np.testing.assert_array_equal(support_cells(grid, triangles[:, 0]), cells)
    np.testing.assert_array_equal(support_cells(grid, triangles[::-1, 0]), cells)


def _ring_survey(seed: int = 1):
    """Points over 100 × 100 m but a disc 20 m across and a bay cut into the east edge:
    a closed hole and an open one."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 100, (20000, 2))
    disc = np.hypot(xy[:, 0] - 40.0, xy[:, 1] - 50.0) < 20.0
    bay = (xy[:, 0] > 75.0) & (np.abs(xy[:, 1] - 50.0) < 10.0)
    return xy[~disc & ~bay]


def _holes_of(xy: np.ndarray):
    """(grid, support cells, Holes) of the lattice mesh of xy at D = 1, h = 0.7."""
    mesh = lattice_mesh(xy, 1.0, 0.7)
    support = support_cells(mesh.grid, mesh.nodes[mesh.triangles[mesh.shown][:, 0]])
    return mesh.grid, support, find_holes(mesh.grid, support, point_hull(xy))


def test_the_holes_are_the_hull_cells_the_support_leaves_counted_cell_by_cell():
    xy = _ring_survey()
    grid, support, holes = _holes_of(xy)
    inside = set(hull_cells(grid, point_hull(xy)).tolist())
    expected = sorted(inside - set(support.tolist()))
    np.testing.assert_array_equal(holes.cells, expected)
    held = set(cell_corners(grid, support).ravel().tolist())
    corners = set(cell_corners(grid, holes.cells).ravel().tolist())
    np.testing.assert_array_equal(holes.rim, sorted(corners & held))
    np.testing.assert_array_equal(holes.free, sorted(corners - held))
    centres = grid.centres(holes.cells)
    in_disc = np.hypot(centres[:, 0] - 40.0, centres[:, 1] - 50.0) < 20.0
    in_bay = (centres[:, 0] > 75.0) & (np.abs(centres[:, 1] - 50.0) < 10.0)
    assert in_disc.sum() > 300 and in_bay.sum() > 100 and (in_disc | in_bay).all()


def _quadratic(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y = p[:, 0], p[:, 1]
    return 2.0 + 0.01 * x * x - 0.02 * x * y + 0.005 * y * y + 0.3 * x, \
        np.column_stack([0.02 * x - 0.02 * y + 0.3, -0.02 * x + 0.01 * y])


def _plane(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return 7.0 + 0.2 * p[:, 0] - 0.1 * p[:, 1], np.tile([0.2, -0.1], (len(p), 1))


@pytest.mark.parametrize("surface", [_plane, _quadratic])
def test_a_closed_hole_on_a_polynomial_rim_is_filled_with_it(surface):
    xy = _ring_survey()
    xy = xy[xy[:, 0] < 70.0]                                 # the disc alone
    grid, _, holes = _holes_of(xy)
    assert holes.free.size > 500
    values, gradients = fill_holes(grid, holes, *surface(grid.positions(holes.rim)))
    truth, slope = surface(grid.positions(holes.free))
    assert np.abs(values - truth).max() < 1e-8 * np.abs(truth).max()
    assert np.abs(gradients - slope).max() < 1e-8


def test_an_open_bay_on_a_plane_is_the_plane():
    xy = _ring_survey()
    grid, _, holes = _holes_of(xy)
    values, gradients = fill_holes(grid, holes, *_plane(grid.positions(holes.rim)))
    truth, slope = _plane(grid.positions(holes.free))
    assert np.abs(values - truth).max() < 1e-8 * np.abs(truth).max()
    assert np.abs(gradients - slope).max() < 1e-8


def test_the_fill_has_the_least_energy_of_any_nearby_fill():
    """Moving the fill's unknowns along random directions raises the energy of the
    holes' spline, by the quadratic form's own second-order term (a minimum, not a saddle
    or a wrong stationary point)."""
    from c1mesh.engine.schemes import DEFAULT_SCHEME, get_scheme
    from c1mesh.stages.smoothing import lattice_shapes, shared_directions
    from c1mesh.stages.smoothing_system import assemble_energy

    xy = _ring_survey()
    grid, _, holes = _holes_of(xy)
    rng = np.random.default_rng(0)
    rim_positions = grid.positions(holes.rim)
    rim_values = np.sin(rim_positions[:, 0] / 9.0) * np.cos(rim_positions[:, 1] / 7.0)
    rim_gradients = rng.normal(0.0, 0.05, (holes.rim.size, 2))
    values, gradients = fill_holes(grid, holes, rim_values, rim_gradients)
    nodes = np.union1d(holes.free, holes.rim)
    triangles = np.searchsorted(nodes, cell_triangles(grid, holes.cells))
    points = grid.positions(nodes)
    shapes = lattice_shapes(grid.solver_lattice(nodes), triangles)
    K = assemble_energy(points, triangles, shared_directions(points, triangles, shapes),
                        get_scheme(DEFAULT_SCHEME), shapes)
    u = np.zeros((nodes.size, 3))
    free = np.searchsorted(nodes, holes.free)
    rim = np.searchsorted(nodes, holes.rim)
    u[free] = np.column_stack([values, gradients])
    u[rim] = np.column_stack([rim_values, rim_gradients])
    u = u.ravel()
    energy = u @ (K @ u)
    for _ in range(5):
        step = np.zeros((nodes.size, 3))
        step[free] = rng.normal(0.0, 1e-3, (free.size, 3))
        step = step.ravel()
        second = step @ (K @ step)
        assert second > 0
        moved = (u + step) @ (K @ (u + step))
        assert moved - energy == pytest.approx(second, rel=1e-6, abs=1e-12 * energy)


def test_free_nodes_out_of_reach_of_the_rim_are_refused():
    grid = node_grid((0.0, 0.0), (30.0, 30.0), 1.0, 1.0)
    cells = np.array([5, 6])
    corners = np.unique(cell_corners(grid, cells))
    with pytest.raises(ValueError, match="no fitted node"):
        fill_holes(grid, Holes(cells, corners, np.empty(0, np.int64)), np.empty(0), np.empty((0, 2)))


def test_filled_lattice_keeps_the_fitted_rows_and_adds_the_holes():
    xy = _ring_survey()
    mesh = lattice_mesh(xy, 1.0, 0.7)
    grid = mesh.grid
    shown, triangles = mesh.shown_mesh()
    nodes = mesh.nodes[shown]
    values, gradients = _plane(grid.positions(nodes))
    fitted = LatticeVertices(nodes, values, gradients, triangles)
    filled, kept = filled_lattice(grid, fitted, point_hull(xy))
    count = triangles.shape[0]
    assert kept[:count].all() and not kept[count:].any() and kept.size > count
    np.testing.assert_array_equal(filled.triangles[:count], triangles)
    np.testing.assert_array_equal(filled.nodes[:nodes.size], nodes)
    corners = filled.nodes[filled.triangles[count:]]
    holes = find_holes(grid, support_cells(grid, nodes[triangles[:, 0]]), point_hull(xy))
    np.testing.assert_array_equal(corners, cell_triangles(grid, holes.cells))
    truth, slope = _plane(grid.positions(filled.nodes))
    assert np.abs(filled.values - truth).max() < 1e-8 * np.abs(truth).max()
    full = LatticeVertices(nodes, values, gradients, triangles)
    again, kept = filled_lattice(grid, full, np.empty((0, 2)))         # no hull: nothing to fill
    assert again is full and kept.all()


# ------------------------------------------------------------------ the fill in the fits
def _holed_quadratic_las(path, noise: float = 0.02):
    """Class-2 points over 40 × 40 m of the quadratic q (below) with Gaussian noise of σ
    `noise`, but a disc 14 m across and a bay cut into the east edge: the points' hull
    spans both."""
    from terrain_scenes import write_points_las

    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 40, (8000, 2))
    disc = np.hypot(*(xy - [18.0, 21.0]).T) < 7.0
    bay = (xy[:, 0] > 32.0) & (np.abs(xy[:, 1] - 20.0) < 5.0)
    xy = xy[~disc & ~bay]
    z = _q(xy[:, 0], xy[:, 1]) + rng.normal(0.0, noise, len(xy))
    write_points_las(path, np.column_stack([xy, z]), z_scale=0.0001)
    return xy


def _q(x, y):
    return 100 + 0.02 * (x - 20) ** 2 - 0.015 * (x - 20) * (y - 20) + 0.01 * (y - 20) ** 2 + 0.1 * x


def _dem(path):
    """(heights, masked; x, y of the cell centres in the survey's frame) of a DEM."""
    import rasterio

    with rasterio.open(path) as ds:
        z = ds.read(1, masked=True)
        rows, cols = np.indices(z.shape)
        x, y = rasterio.transform.xy(ds.transform, rows.ravel(), cols.ravel())
    return z, np.asarray(x).reshape(z.shape) - 500000.0, np.asarray(y).reshape(z.shape) - 4000000.0


def test_the_lattice_dem_fills_the_hull_within_the_noise(tmp_path):
    """--smooth auto --spacing 1 --resolution 1 (the default --fill hull): every cell of the
    disc and the bay inside the points' hull holds a height, within the noise σ of the
    true quadratic in RMS and 4σ at most (with exact rim data the fill would be the
    quadratic: test_a_closed_hole_on_a_polynomial_rim_is_filled_with_it); --fill off keeps
    them open."""
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    xy = _holed_quadratic_las(tmp_path / "q.las")
    hull = point_hull(xy)
    report = fit(tmp_path / "q.las", tmp_path / "q.tif", FitOptions(classes=(2,), smooth="auto", spacing=1.0,
                                                                   resolution=1.0)).report
    z, x, y = _dem(tmp_path / "q.tif")
    centres = np.column_stack([x.ravel(), y.ravel()])
    hole = ((np.hypot(x - 18.0, y - 21.0) < 5.0) | ((x > 34.0) & (np.abs(y - 20.0) < 3.0))) & \
        _inside(centres, hull).reshape(z.shape)
    assert hole.sum() > 100 and not z.mask[hole].any()
    error = np.asarray(z[hole]) - _q(x[hole], y[hole])
    assert np.sqrt(np.mean(error ** 2)) < 0.02 and np.abs(error).max() < 0.08
    assert report["raster"]["fill"]["triangles_spanning_holes"] > 0
    fit(tmp_path / "q.las", tmp_path / "off.tif", FitOptions(classes=(2,), smooth="auto", spacing=1.0,
                                                             resolution=1.0, fill="off"))
    off, x, y = _dem(tmp_path / "off.tif")
    assert off.mask[np.hypot(x - 18.0, y - 21.0) < 2.0].all()    # beyond the support's reach into the disc


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as local:
        yield local


@pytest.mark.parametrize("fill, where", [("hull", "processes"), ("off", "processes"), ("2.5", "processes"),
                                         ("hull", "dask")])
def test_the_lattice_fill_in_tiles_is_the_whole_fits(tmp_path, request, fill, where):
    """The same DEM and support (distances to the data points) in memory and in 9 tiles,
    for each fill, the tiles here or on a Dask cluster: a hole's fill is solved whole in
    tiles too (survey.lattice_runs.LatticeFill), and --fill D drops the same cells (those in
    the holes' triangles only)."""
    import rasterio

    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    scheduler = request.getfixturevalue("cluster").scheduler_address if where == "dask" else None
    _holed_quadratic_las(tmp_path / "q.las")
    options = FitOptions(classes=(2,), smooth=3.0, spacing=1.0, resolution=1.0, fill=fill,
                         support=str(tmp_path / "whole-support.tif"))
    whole = fit(tmp_path / "q.las", tmp_path / "whole.tif", options).report
    options = FitOptions(classes=(2,), smooth=3.0, spacing=1.0, resolution=1.0, fill=fill, memory=10**9,
                         support=str(tmp_path / "tiled-support.tif"))
    tiled = fit(tmp_path / "q.las", tmp_path / "tiled.tif", options,
                tiles=TiledRun(per_tile=900, scheduler=scheduler)).report
    assert tiled["tiles"] == 9
    rasters = {name: [rasterio.open(tmp_path / f"{path}{name}.tif").read(1, masked=True) for path in ("whole", "tiled")]
               for name in ("", "-support")}
    for a, b in rasters.values():
        np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_array_equal(*rasters["-support"])
    # within the tiled lattice fit's bound (test_tiled_smoothing: 1 % of the residual RMS)
    dem = rasters[""]
    assert np.abs(dem[0] - dem[1]).max() < 0.01 * whole["smoothing"]["residual_rms"]
    assert tiled["raster"]["fill"] == whole["raster"]["fill"]
    assert tiled["smoothing"]["lattice"] == whole["smoothing"]["lattice"]        # the solve's nodes
    assert tiled["triangles"]["after_trim"] == whole["triangles"]["after_trim"]   # the support's
    if fill != "off":
        assert whole["raster"]["fill"]["triangles_spanning_holes"] > 0


def test_a_tiled_report_counts_the_solves_nodes_and_the_supports_triangles(tmp_path, monkeypatch):
    """A hole wider than the solve's blocks (a disc 32 m across in 60 m): some of its free
    corners are nodes of the tiles' spill only for the fill. The report's lattice nodes and
    kept triangles are the solve's and the support's, as in memory."""
    from terrain_scenes import write_points_las

    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline import bounded_fit
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 60, (9000, 2))
    xy = xy[np.hypot(*(xy - 30.0).T) > 16.0]
    write_points_las(tmp_path / "q.las", np.column_stack([xy, _q(xy[:, 0], xy[:, 1])]), z_scale=0.0001)
    made = []
    tiles = bounded_fit.lattice_tiles
    monkeypatch.setattr(bounded_fit, "lattice_tiles", lambda *a, **k: made.append(tiles(*a, **k)) or made[-1])
    options = dict(classes=(2,), smooth=3.0, spacing=1.0, resolution=1.0)
    whole = fit(tmp_path / "q.las", tmp_path / "whole.tif", FitOptions(**options)).report
    tiled = fit(tmp_path / "q.las", tmp_path / "tiled.tif", FitOptions(**options, memory=10**9),
                tiles=TiledRun(per_tile=1000)).report
    assert tiled["tiles"] == 9 and made[0].fill_nodes > 0
    assert tiled["smoothing"]["lattice"] == whole["smoothing"]["lattice"]
    assert tiled["triangles"]["after_trim"] == whole["triangles"]["after_trim"]
    assert tiled["raster"]["fill"] == whole["raster"]["fill"]
