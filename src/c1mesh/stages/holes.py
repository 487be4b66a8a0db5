"""The triangles that span the holes the long-edge trim opens, found from the short ones.

A DEM's fill (pipeline.driver.filled_mesh) spans the holes under buildings, trees and
water with the Delaunay triangles the trim's max_edge removed: the long triangles, those
with an edge longer than max_edge. A survey fitted in tiles never has them: each tile
certifies only its short triangles (survey.buffered_delaunay), and a long triangle is as
wide as its hole, wider than any halo. This stage finds them from the short ones alone,
so the tiles can too:

- the *rim points* are the points whose star of short triangles is not closed: a point in
  no short triangle, or an end of an edge that only one short triangle has. They are the
  corners of the long triangles (and the hull's points), a few percent of a survey;
- the long triangles are exactly the triangles of Del(rim points) with an edge longer
  than max_edge whose centroid no short triangle holds. (A long triangle's circumcircle
  holds no point of the survey, so none of the rim points: it is a triangle of their
  Delaunay triangulation too. The long triangles tile the hull minus the short ones, so
  a triangle of Del(rim points) whose centroid no short triangle holds lies in one of
  them, and the two triangulations' triangles do not overlap: it is that one.)

Where points are cocircular (grids) a Delaunay triangulation is not unique; the fill's
long triangles are always Del(rim points)'s, in memory and in tiles, so both paths make
the same choice. As a stage of tiles (core.tile.Tile): `rim_points` of a tile's owned
points, then one reduce, `spanning_triangles`, over the survey's rim points, asking the
tiles which centroids their short triangles hold (`covered`).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from c1mesh.core.tile import Tile
from c1mesh.engine.locate import TriangleLocator
from c1mesh.engine.rsd import barycentric_gradients
from c1mesh.engine.topology import unique_edges
from c1mesh.engine.triangulation import delaunay
from c1mesh.stages.trim import TrimmedMesh, edge_lengths


def rim_points(tile: Tile) -> np.ndarray:
    """(m,) bool over tile.records: the owned points whose star of short triangles
    (tile.triangles, every short triangle around each owned point) is not closed: in no
    triangle, or with more neighbours (topology.unique_edges) than triangles."""
    count = len(tile.records)
    triangles = tile.triangles
    # a fan of m triangles around a point has m neighbours when it closes, m + 1 when open
    fans = np.bincount(triangles.ravel(), minlength=count)
    neighbours = np.bincount(unique_edges(triangles, count).ravel(), minlength=count)
    return tile.own & ((fans == 0) | (neighbours != fans))


def spanning_triangles(xy: np.ndarray, numbers: np.ndarray, max_edge: float,
                       covered: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The long triangles (k, 3) of the survey, in survey numbers, lowest corner first,
    counter-clockwise, sorted by corners (module docstring).

    xy (r, 2): the rim points (frame plane), numbers (r,) their survey numbers, ascending;
    max_edge: the trim's limit; covered(centroids (c, 2)) -> (c,) bool: whether a short
    triangle holds each point."""
    if len(xy) < 3:
        return np.empty((0, 3), dtype=np.int64)
    triangles = delaunay(xy)
    candidates = triangles[(edge_lengths(xy, triangles) > max_edge).any(axis=1)]   # trim's bits
    if not len(candidates):
        return np.empty((0, 3), dtype=np.int64)
    found = numbers[candidates[~covered(xy[candidates].mean(axis=1))]]
    return _lowest_first(found)


def _lowest_first(triangles: np.ndarray) -> np.ndarray:
    """Each triangle's corners rotated so that its lowest number comes first (the order,
    and so the orientation, kept), the rows sorted: one form whatever the library's."""
    shift = np.argmin(triangles, axis=1)
    rows = np.arange(len(triangles))[:, None]
    rotated = triangles[rows, (shift[:, None] + np.arange(3)) % 3]
    return rotated[np.lexsort(rotated.T[::-1])]


def short_cover(points: np.ndarray, triangles: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """covered() for spanning_triangles over short triangles (k, 3) into points (m, 2)."""
    if not len(triangles):
        return lambda xy: np.zeros(len(xy), dtype=bool)
    locator = TriangleLocator(points, triangles, barycentric_gradients(points[triangles])[0])
    return lambda xy: locator.find(xy)[0] >= 0


def with_spanning_triangles(xy: np.ndarray, mesh: TrimmedMesh, max_edge: float | None) -> TrimmedMesh:
    """The trimmed mesh (stages.trim.TrimmedMesh over the Delaunay triangulation of xy
    (n, 2), trimmed with the limit max_edge) over a source whose long triangles are
    spanning_triangles', the tiles' (module docstring: they differ only where rim points
    are cocircular); the kept triangles stay, in their order. The same mesh when they do
    not differ, or without a limit."""
    if max_edge is None:
        return mesh
    long = (mesh.lengths > max_edge).any(axis=1)
    short = mesh.source[~long]
    tile = Tile(np.zeros(mesh.n_points, dtype=[("index", "<i8")]), short, np.ones(mesh.n_points, dtype=bool))
    rim = np.flatnonzero(rim_points(tile))
    spanning = spanning_triangles(xy[rim], rim, max_edge, short_cover(xy, short))
    if np.array_equal(spanning, _lowest_first(mesh.source[long])):
        return mesh
    alive = np.concatenate([mesh.alive[~long], np.zeros(len(spanning), dtype=bool)])
    return TrimmedMesh.of(xy, np.concatenate([short, spanning])).with_alive(alive)
