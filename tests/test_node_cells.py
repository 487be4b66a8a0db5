"""A lattice fit's DEM read off its nodes (geo.raster_grid.NodeCells): the lattice route
puts its nodes at the DEM's cell centres (stages.lattice_mesh.lattice_offset) when
--spacing is --resolution, and the rasters then take the nodes' heights and gradients
instead of evaluating the spline there. They must be the evaluated spline's rasters."""
from __future__ import annotations

import numpy as np
import pytest
import rasterio

from c1mesh.geo import raster_grid
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit
from terrain_scenes import write_points_las
from test_tiled_smoothing import _terrain_las


def _survey_with_lone_points(path) -> None:
    """6,000 class-2 points of a smooth terrain over 40 × 40 m (one a 0.5 m square) with a
    hole 16 m across, and 3 lone points inside the hole, 4 m apart: their cells hold data
    but no kept lattice cell (stages.lattice_mesh), so no node."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(0.0, 40.0, (6400, 2))
    xy = xy[np.hypot(*(xy - 20.0).T) > 8.0][:6000]
    xy = np.vstack([xy, [[16.3, 20.2], [20.4, 19.6], [23.9, 20.8]]])
    z = 100.0 + 3.0 * np.sin(xy[:, 0] / 7.0) * np.cos(xy[:, 1] / 9.0) + rng.normal(0.0, 0.02, len(xy))
    write_points_las(path, np.column_stack([xy, z]), z_scale=0.0001)


def _rasters(tmp_path, name: str, source, resolution: float, spacing: float, fill: str = "off") -> dict:
    """The DEM, spline slope and support of `c1mesh fit --smooth 3 --spacing S --resolution R
    --fill F`."""
    dem = tmp_path / f"{name}.tif"
    fit(source, dem, FitOptions(classes=(2,), smooth=3.0, spacing=spacing, resolution=resolution, fill=fill,
                                slope=str(tmp_path / f"{name}-slope.tif"), slope_method="spline",
                                support=str(tmp_path / f"{name}-support.tif")))
    out = {kind: rasterio.open(tmp_path / f"{name}{kind}.tif").read(1).astype(float)
           for kind in ("", "-slope", "-support")}
    with rasterio.open(dem) as ds:                       # the cells' distances from the hole's centre
        rows, cols = np.indices(ds.shape)
        x, y = rasterio.transform.xy(ds.transform, rows.ravel(), cols.ravel())
        out["hole"] = (np.hypot(np.asarray(x) - 500020.0, np.asarray(y) - 4000020.0) < 4.0).reshape(ds.shape)
    return out


@pytest.mark.parametrize("fill", ["off", "hull", "2.5"])
def test_the_dem_off_the_nodes_is_the_evaluated_splines(tmp_path, monkeypatch, fill):
    """A survey with a few lone points in a hole: without a fill, cells with data and no
    node (the nearest-triangle rule's); with the hull's fill (stages.hole_fill), nodes in
    the hole, all of them or those within 2.5 m of a point. The DEM and the support are
    the evaluated spline's to the bit, the slope from the nodes' gradients to float32's
    last bit; the nodes were read, and without a fill the lone points' cells continued."""
    source = tmp_path / "terrain.las"
    _survey_with_lone_points(source)
    windows, bare = [], []
    read, continued = raster_grid.NodeCells.window, raster_grid.NodeCells.bare
    monkeypatch.setattr(raster_grid.NodeCells, "window", lambda self, *a: windows.append(1) or read(self, *a))
    monkeypatch.setattr(raster_grid.NodeCells, "bare",
                        lambda self, *a: (lambda out: bare.append(out[0].size) or out)(continued(self, *a)))
    nodes = _rasters(tmp_path, "nodes", source, 1.0, 1.0, fill)
    assert windows and (sum(bare) >= 3 if fill == "off" else sum(bare) == 0)
    monkeypatch.setattr(raster_grid.NodeCells, "of", classmethod(lambda cls, *a: None))
    spline = _rasters(tmp_path, "spline", source, 1.0, 1.0, fill)
    held = np.isfinite(spline[""]) & (spline[""] > -9000.0)
    assert held[spline["hole"]].all() if fill == "hull" else not held[spline["hole"]].all()
    np.testing.assert_array_equal(nodes[""], spline[""])
    np.testing.assert_array_equal(nodes["-support"], spline["-support"])
    slope = np.isfinite(spline["-slope"]) & (spline["-slope"] != -9999.0)
    np.testing.assert_array_equal(np.isfinite(nodes["-slope"]), np.isfinite(spline["-slope"]))
    assert np.abs(nodes["-slope"][slope] - spline["-slope"][slope]).max() <= 1e-5 * spline["-slope"][slope].max()


def test_a_lattice_finer_than_the_cells_is_evaluated(tmp_path, monkeypatch):
    """--spacing half the --resolution: the nodes are not the cells' centres, and every cell
    is evaluated (NodeCells.of gives none)."""
    source = tmp_path / "terrain.las"
    _terrain_las(source, 3000, seed=5)
    made = []
    of = raster_grid.NodeCells.of.__func__
    monkeypatch.setattr(raster_grid.NodeCells, "of", classmethod(lambda cls, *a: made.append(of(cls, *a)) or made[-1]))
    fit(source, tmp_path / "half.tif", FitOptions(classes=(2,), smooth=3.0, spacing=0.5, resolution=1.0))
    fit(source, tmp_path / "same.tif", FitOptions(classes=(2,), smooth=3.0, spacing=1.0, resolution=1.0))
    assert made[0] is None and made[1] is not None


def test_a_tiled_dem_reads_its_lattice_tiles_nodes_too(tmp_path, monkeypatch):
    """Beyond --memory (9 tiles), a lattice fit at the DEM's resolution: each tile's cells
    read its vertices' data (bounded_dem._NodeValues) and are the evaluated spline's DEM and
    spline slope, as in memory."""
    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline import bounded_dem

    source = tmp_path / "terrain.las"
    _survey_with_lone_points(source)
    reads = []
    at = bounded_dem._NodeValues.at
    monkeypatch.setattr(bounded_dem._NodeValues, "at", lambda self, *a: reads.append(1) or at(self, *a))

    def rasters(name):
        dem = tmp_path / f"{name}.tif"
        options = FitOptions(classes=(2,), smooth=3.0, spacing=1.0, resolution=1.0, memory=10**9,
                             slope=str(tmp_path / f"{name}-slope.tif"), slope_method="spline")
        assert fit(source, dem, options, tiles=TiledRun(per_tile=800)).report["tiles"] == 9
        return [rasterio.open(path).read(1).astype(float) for path in (dem, tmp_path / f"{name}-slope.tif")]

    nodes = rasters("nodes")
    assert len(reads) >= 9
    monkeypatch.setattr(bounded_dem._NodeValues, "of", classmethod(lambda cls, *a: None))
    spline = rasters("spline")
    np.testing.assert_array_equal(nodes[0], spline[0])
    slope = np.isfinite(spline[1]) & (spline[1] != -9999.0)
    np.testing.assert_array_equal(np.isfinite(nodes[1]), np.isfinite(spline[1]))
    assert np.abs(nodes[1][slope] - spline[1][slope]).max() <= 1e-5 * spline[1][slope].max()
