"""The long triangles of a DEM's fill found from the short ones (c1mesh.stages.holes).

Truth: scipy's Delaunay (qhull, an independent implementation) of the same points, whose
triangles with an edge longer than the limit are the long ones where the points are in
general position; brute-force loops for the rim points; on a grid with a square hole,
where cocircular points make the triangulation not unique, the properties any Delaunay
fill must have: the long triangles and the short ones tile the convex hull without
overlap, and no point lies strictly inside a long triangle's circumcircle.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull, Delaunay

from c1mesh.core.tile import Tile
from c1mesh.engine.topology import edge_table
from c1mesh.engine.triangulation import delaunay
from c1mesh.stages.holes import rim_points, short_cover, spanning_triangles, with_spanning_triangles
from c1mesh.stages.trim import trim_mesh


def _longest(xy, triangles):
    p = xy[triangles]
    return np.sqrt(((p - np.roll(p, -1, axis=1)) ** 2).sum(axis=2)).max(axis=1)


def _cross(u, v):
    return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]


def _rows(triangles):
    return {tuple(sorted(t)) for t in np.asarray(triangles).tolist()}


def _lake(seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.random((20000, 2)) * 100
    hole = (np.hypot(xy[:, 0] - 50, xy[:, 1] - 50) < 20) | ((xy[:, 0] > 75) & (xy[:, 1] > 60))
    return xy[~hole]


def _long_of(xy, limit):
    """(rim points, long triangles) by this module's rule: the short ones alone given."""
    triangles = delaunay(xy)
    short = triangles[_longest(xy, triangles) <= limit]
    rim = np.flatnonzero(rim_points(Tile.whole(xy, np.zeros(len(xy)), np.zeros((len(xy), 2)), short)))
    return rim, short, spanning_triangles(xy[rim], rim, limit, short_cover(xy, short))


def test_rim_points_are_the_points_whose_short_star_is_open():
    """Brute force: a point is a rim point when it is in no short triangle or one of its
    short triangles' edges at it belongs to no other short triangle; of a tile, its owned
    points only."""
    xy = _lake()
    triangles = Delaunay(xy).simplices
    short = triangles[_longest(xy, triangles) <= 3.0]
    own = xy[:, 0] < 60                                   # a tile's cell: its own points only
    whole = Tile.whole(xy, np.zeros(len(xy)), np.zeros((len(xy), 2)), short)
    rim = rim_points(Tile(whole.records, short, own))
    count = {}
    for t in short.tolist():
        for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
            count[min(a, b), max(a, b)] = count.get((min(a, b), max(a, b)), 0) + 1
    expected = np.ones(len(xy), dtype=bool)
    expected[short.ravel()] = False
    for (a, b), times in count.items():
        if times == 1:
            expected[[a, b]] = True
    assert rim.sum() > 50 and np.array_equal(rim, expected & own)


def test_the_long_triangles_are_qhulls_on_points_in_general_position():
    """A lake and a bay wider than the limit: the triangles found from the rim points are
    exactly qhull's triangles with an edge longer than the limit."""
    xy = _lake()
    rim, _, found = _long_of(xy, 3.0)
    qhull = Delaunay(xy).simplices
    expected = qhull[_longest(xy, qhull) > 3.0]
    assert len(expected) > 100 and len(rim) < 0.2 * len(xy)
    assert _rows(found) == _rows(expected)
    assert np.all(found[:, 0] == found.min(axis=1))                 # lowest corner first


def test_cocircular_rims_give_a_delaunay_fill_that_tiles_the_hull():
    """A 0.5 m grid with a square hole: the short and long triangles cover the convex hull
    once (their areas add up to its area, every edge has at most two triangles), and
    every long triangle's circumcircle holds no point strictly inside."""
    g = np.arange(0, 30, 0.5)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = xy[~((xy[:, 0] > 8) & (xy[:, 0] < 21) & (xy[:, 1] > 8) & (xy[:, 1] < 21))]
    _, short, found = _long_of(xy, 0.75)
    both = np.concatenate([short, found])
    edge_table(both, len(xy))                                        # raises on an edge with 3 triangles
    p = xy[both]
    area = 0.5 * np.abs(_cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])).sum()
    assert len(found) > 20 and area == pytest.approx(ConvexHull(xy).volume, rel=1e-12)
    a, b, c = (xy[found[:, k]] for k in range(3))
    d = 2 * _cross(b - a, c - a)
    ux = ((a ** 2).sum(1) * (b - c)[:, 1] + (b ** 2).sum(1) * (c - a)[:, 1] + (c ** 2).sum(1) * (a - b)[:, 1]) / d
    uy = ((a ** 2).sum(1) * (c - b)[:, 0] + (b ** 2).sum(1) * (a - c)[:, 0] + (c ** 2).sum(1) * (b - a)[:, 0]) / d
    centre = np.column_stack([ux, uy])
    radius = np.hypot(*(a - centre).T)
    for k in range(len(found)):
        assert (np.hypot(*(xy - centre[k]).T) >= radius[k] * (1 - 1e-9)).all()


def test_the_in_memory_fill_takes_the_same_long_triangles():
    """with_spanning_triangles rebases a trimmed mesh on the rule's long triangles: the
    same mesh object where the library's triangulation agrees (general position), a new
    source with the same kept triangles where cocircular rims let it choose."""
    xy = _lake()
    mesh, report = trim_mesh(xy, delaunay(xy), max_edge=3.0)
    assert with_spanning_triangles(xy, mesh, report.max_edge) is mesh
    g = np.arange(0, 30, 0.5)
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    grid = grid[~((grid[:, 0] > 8) & (grid[:, 0] < 21) & (grid[:, 1] > 8) & (grid[:, 1] < 21))]
    mesh, report = trim_mesh(grid, delaunay(grid), max_edge=0.75)
    rebased = with_spanning_triangles(grid, mesh, report.max_edge)
    long = rebased.source[~(rebased.lengths <= 0.75).all(axis=1)]
    assert np.array_equal(rebased.triangles, mesh.triangles)
    assert _rows(long) == _rows(_long_of(grid, 0.75)[2])
