"""Issue 35: `c1mesh preview DEM.tif` draws the same cells as the fit's `--preview`.

Both pictures of a DEM draw every cell that holds a height (only their shading differs:
Horn's gradient of the cells against the spline's); Horn's gradient falls back to
one-sided differences next to nodata and at the border instead of dropping the cell.

Truth: a plane's exact gradient, raster.horn_gradient (the plain 3x3 formula) where the
whole window is data, rasterio reading the written DEM, and the pixels of the two PNGs.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from c1mesh.cli import main
from c1mesh.core.cloud import PointCloud
from c1mesh.geo.raster import horn_gradient, horn_gradient_at_edges
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit

rasterio = pytest.importorskip("rasterio")

AUTZEN = Path(__file__).resolve().parent.parent / "data_samples" / "autzen_trim.laz"


# ------------------------------------------------------------------------------ helpers
def _drawn(png) -> np.ndarray:
    """The map's pixels that are not the white background (h, w) bool, in a preview PNG
    (preview.render_arrays' layout: 100 dpi, the map 5.6 in wide at 1.1 in from the left
    and 0.4 in from the bottom, 0.9 in of margins in height), 3 pixels inside its frame.
    No drawn cell is white: the colours are gist_earth 0.1-0.95 (at most 240 of 255)."""
    from PIL import Image

    with Image.open(png) as image:
        pixels = np.asarray(image.convert("RGB"))
    height = pixels.shape[0]
    top, bottom = 50, height - 40
    return (pixels[top + 3:bottom - 3, 110 + 3:670 - 3] != 255).any(axis=-1)


def _dem_cells(path) -> np.ndarray:
    """(h, w) bool: the cells of a GeoTIFF DEM that hold a height (rasterio's mask)."""
    with rasterio.open(path) as ds:
        return ~np.ma.getmaskarray(ds.read(1, masked=True))


def _both_previews(tmp_path, fit_previews, monkeypatch):
    """Run fit_previews(dem, png) (a fit writing dem and its --preview png), then
    `c1mesh preview dem`; the two PNGs and the (heights, gradients) each drew."""
    import c1mesh.geo.preview as preview

    drawn, draw = [], preview.render_arrays

    def seen(z, gradient, *rest):
        drawn.append((z, gradient))
        draw(z, gradient, *rest)

    monkeypatch.setattr(preview, "render_arrays", seen)
    dem, fitted, alone = tmp_path / "dem.tif", tmp_path / "fit.png", tmp_path / "alone.png"
    fit_previews(dem, fitted)
    done = CliRunner().invoke(main, ["preview", str(dem), "-o", str(alone)])
    assert done.exit_code == 0, done.output
    assert len(drawn) == 2
    return dem, fitted, alone, drawn


def _assert_same_cells(dem, fitted, alone, drawn, stride):
    """Both pictures draw exactly the DEM's cells (every stride-th: rasterio's mask), and
    the same pixels of the PNG; and among those cells are many that a plain 3x3 Horn
    gradient would drop (a neighbour is nodata or off the grid)."""
    cells = _dem_cells(dem)
    for z, g in drawn:
        assert z.shape == cells[::stride, ::stride].shape
        np.testing.assert_array_equal(np.isfinite(z) & np.isfinite(g).all(axis=-1), cells[::stride, ::stride])
    padded, whole = np.pad(cells, 1), cells.copy()
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            whole &= padded[di:di + cells.shape[0], dj:dj + cells.shape[1]]
    assert (cells & ~whole)[::stride, ::stride].sum() > 100
    a, b = _drawn(alone), _drawn(fitted)
    assert a.shape == b.shape and a.sum() > 10_000
    np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------- Horn at the edges
def _plane_with_holes(a: float, b: float, resolution: float):
    """z = a x + b y + 100 at the cell centres of a 14 x 17 grid (x east, y north, west =
    0, north = 40), NaN in holes: inside, at the border, a corner, and an L. Every data
    cell keeps a data neighbour east or west and one north or south (no 1-cell strip)."""
    rows, cols = np.mgrid[0:14, 0:17]
    x, y = (cols + 0.5) * resolution, 40.0 - (rows + 0.5) * resolution
    z = a * x + b * y + 100.0
    holes = np.zeros(z.shape, bool)
    holes[4:7, 5:8] = True            # inside
    holes[0:2, 10:13] = True          # at the north border
    holes[11:, 0:3] = True            # the south-west corner
    holes[8:10, 10:15] = True         # an L: a bar and a foot, 2 cells from the east border
    holes[10:13, 13:15] = True
    holes[5:7, 16:] = True            # at the east border
    z[holes] = np.nan
    return z, holes


@pytest.mark.parametrize("a, b", [(0.5, -0.25), (-1.5, 0.75)])
def test_horn_at_edges_gives_a_plane_exactly_at_every_data_cell(a, b):
    """Dyadic slopes and cell size: every difference and weighted mean is exact in binary,
    so the gradient is (a, b) to the last bit, at the border and next to every hole too."""
    z, holes = _plane_with_holes(a, b, resolution=2.0)
    g = horn_gradient_at_edges(z, 2.0)
    plain = horn_gradient(np.pad(z, 1, constant_values=np.nan), 2.0)
    edge = ~holes & ~np.isfinite(plain).all(axis=-1)
    assert edge.sum() > 60 and edge[0].any() and edge[-1].any() and edge[:, 0].any() and edge[:, -1].any()
    assert np.isnan(g[holes]).all()
    np.testing.assert_array_equal(g[~holes], np.broadcast_to((a, b), g[~holes].shape))


def test_horn_at_edges_is_a_plane_to_rounding_with_any_slope_and_cell():
    z, holes = _plane_with_holes(0.3141, -0.0271, resolution=0.7)
    g = horn_gradient_at_edges(z, 0.7)
    np.testing.assert_allclose(g[~holes], np.broadcast_to((0.3141, -0.0271), g[~holes].shape), rtol=0, atol=1e-12)


def test_horn_at_edges_is_horn_where_the_window_is_whole():
    """Rough heights: where all nine cells are data, the same numbers as horn_gradient."""
    z, holes = _plane_with_holes(0.2, 0.1, resolution=1.5)
    z = z + np.random.default_rng(5).normal(0, 1, z.shape)
    plain = horn_gradient(np.pad(z, 1, constant_values=np.nan), 1.5)
    whole = np.isfinite(plain).all(axis=-1)
    assert whole.sum() > 80
    np.testing.assert_allclose(horn_gradient_at_edges(z, 1.5)[whole], plain[whole], rtol=1e-13, atol=1e-13)


def test_horn_at_edges_one_sided_difference_of_a_curved_row():
    """A cell whose east neighbours are all nodata takes (centre − west) / R in each row,
    weighted 1-2-1: on z = x² along rows, x the column's centre."""
    x = np.arange(4) + 0.5                      # R = 1
    z = np.tile(x ** 2, (3, 1))
    z[:, 3] = np.nan
    g = horn_gradient_at_edges(z, 1.0)
    assert g[1, 2, 0] == x[2] ** 2 - x[1] ** 2         # one-sided, not the central 2 x
    assert g[1, 1, 0] == (x[2] ** 2 - x[0] ** 2) / 2   # central where both sides are data
    assert g[1, 2, 1] == 0.0                             # the same height north and south


def test_horn_at_edges_is_flat_across_a_strip_one_cell_wide():
    """A north-south strip one cell wide has no east-west difference: 0 there, the
    north-south slope exact."""
    z = np.full((5, 3), np.nan)
    z[:, 1] = 10.0 - 0.5 * np.arange(5)         # rows go south: z rises 0.5 per cell to the north
    g = horn_gradient_at_edges(z, 1.0)
    np.testing.assert_array_equal(g[:, 1], np.tile((0.0, 0.5), (5, 1)))
    assert np.isnan(g[:, [0, 2]]).all()


# ---------------------------------------------------------------------- the two previews
def test_preview_of_a_dem_draws_the_cells_of_the_fit_preview_autzen(tmp_path, monkeypatch):
    """The bundled autzen ground at 6 ft: both PNGs draw the same pixels, both pictures
    exactly the DEM's cells (before the fix the DEM's own preview dropped every cell next
    to nodata: ~14% at 3 ft)."""
    def fitted(dem, png):
        done = CliRunner().invoke(main, ["fit", str(AUTZEN), "--classes", "2", "-o", str(dem),
                                         "--resolution", "6", "--preview", str(png)])
        assert done.exit_code == 0, done.output

    _assert_same_cells(*_both_previews(tmp_path, fitted, monkeypatch), stride=1)


def _terrain_with_holes(seed: int = 4) -> PointCloud:
    """Jittered points 1 apart on 400 x 160 of z = 0.002 x² + 0.3 sin(y / 9), exact
    normals, with three holes far wider than the spacing (trimmed: nodata inside) and a
    notch cut in from the south border."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(0, 400.5), np.arange(0, 160.5))
    xy = np.column_stack([x.ravel(), y.ravel()]) + rng.uniform(-0.2, 0.2, (x.size, 2))
    keep = np.ones(len(xy), bool)
    for cx, cy, r in ((80, 80, 20), (200, 110, 12), (310, 60, 25)):
        keep &= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) > r
    keep &= ~((np.abs(xy[:, 0] - 250) < 8) & (xy[:, 1] < 50))
    xy = xy[keep]
    z = 0.002 * xy[:, 0] ** 2 + 0.3 * np.sin(xy[:, 1] / 9)
    normals = np.column_stack([-0.004 * xy[:, 0], -0.3 / 9 * np.cos(xy[:, 1] / 9), np.ones(len(z))])
    return PointCloud(np.column_stack([xy, z]), normals / np.linalg.norm(normals, axis=1, keepdims=True))


def test_preview_of_a_dem_draws_the_cells_of_the_fit_preview_with_holes(tmp_path, monkeypatch):
    """A synthetic terrain with holes on a grid ~1600 cells wide: both previews draw every
    third cell (preview_stride), the same ones, and the same PNG pixels."""
    from c1mesh.geo.preview import preview_stride
    from c1mesh.geo.raster_grid import RasterGrid

    def fitted(dem, png):
        fit(_terrain_with_holes(), str(dem), FitOptions(resolution=0.25, preview=str(png), fill="off"))

    dem, fitted_png, alone, drawn = _both_previews(tmp_path, fitted, monkeypatch)
    with rasterio.open(dem) as ds:
        stride = preview_stride(RasterGrid(0.0, 0.0, 0.25, ds.width, ds.height))
        assert 1400 < ds.width <= 2100 and stride == 3
    holes = ~_dem_cells(dem)
    assert holes[270:370, 270:370].all()                 # the hole at (80, 80) is nodata
    _assert_same_cells(dem, fitted_png, alone, drawn, stride)


def test_fit_preview_hatches_the_cells_the_fill_spans_and_only_those(tmp_path, monkeypatch):
    """Issue 40: the fit's preview draws hatched the cells that the default fill spans across
    the trim's holes. On the terrain with three round holes (radii 20, 12, 25) and a notch,
    the cells well inside a hole are hatched and the cells well away from every hole are
    not; with --fill off nothing is (the holes are nodata then)."""
    import c1mesh.geo.preview as preview

    seen = {}
    draw = preview.render_arrays

    def capture(z, gradient, extent, path, units, title, hatched=None):
        seen.update(z=z, hatched=hatched, extent=extent)
        draw(z, gradient, extent, path, units, title, hatched)

    monkeypatch.setattr(preview, "render_arrays", capture)
    fit(_terrain_with_holes(), str(tmp_path / "dem.tif"), FitOptions(resolution=1.0, preview=str(tmp_path / "p.png")))
    z, hatched, (left, right, bottom, top) = seen["z"], seen["hatched"], seen["extent"]
    h, w = z.shape
    x = left + (np.arange(w) + 0.5) * (right - left) / w
    y = top - (np.arange(h) + 0.5) * (top - bottom) / h
    X, Y = np.meshgrid(x, y)
    holes = ((80, 80, 20), (200, 110, 12), (310, 60, 25))
    deep = np.zeros(z.shape, bool)
    away = np.ones(z.shape, bool)
    for cx, cy, r in holes:
        d = np.hypot(X - cx, Y - cy)
        deep |= d < r - 3
        away &= d > r + 3
    away &= ~((np.abs(X - 250) < 11) & (Y < 53)) & (X > 3) & (X < 397) & (Y > 3) & (Y < 157)
    assert np.isfinite(z[deep]).all() and hatched[deep].all()       # filled, and drawn hatched
    assert not hatched[away].any()
    assert (tmp_path / "p.png").stat().st_size > 0

    seen.clear()
    fit(_terrain_with_holes(), str(tmp_path / "off.tif"),
        FitOptions(resolution=1.0, preview=str(tmp_path / "off.png"), fill="off"))
    assert not seen["hatched"].any() and np.isnan(seen["z"][deep]).all()


@pytest.mark.parametrize("width", [40, 67, 300, 1400])
def test_hatching_of_one_cell_is_stripes_not_a_dark_speck(width):
    """A lone filled cell must not read as a pit: whatever the grid's width, its pixels on
    the map hold both darkened and untouched ones (stripes finer than the cell), and no
    pixel outside the hatched cells changes."""
    from c1mesh.geo.preview import _hatched

    rgba = np.full((width, width, 4), 0.8)
    mask = np.zeros((width, width), bool)
    block = max(1, width // 100) * 4                     # a hatched patch of a few map pixels
    mask[10:10 + block, 20:20 + block] = True
    out = _hatched(rgba.copy(), mask, 560)
    k = out.shape[0] // width
    cells = np.repeat(np.repeat(mask, k, axis=0), k, axis=1)
    darker = out[..., 0] < 0.8
    assert darker[cells].any() and not darker[cells].all()
    assert not darker[~cells].any()
    if width < 280:
        lone = np.zeros((width, width), bool)
        lone[5, 7] = True
        one = _hatched(rgba.copy(), lone, 560)[5 * k:6 * k, 7 * k:8 * k, 0] < 0.8
        assert one.any() and not one.all()
