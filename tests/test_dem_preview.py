"""Horn's gradient of a DEM at the edges of its data (raster.horn_gradient_at_edges).

Truth: a plane's exact gradient, and raster.horn_gradient (the plain 3x3 formula) where
the whole window is data.
"""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.geo.raster import horn_gradient, horn_gradient_at_edges


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
