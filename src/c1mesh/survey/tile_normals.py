"""Estimated normals of a survey cut into tiles: how much each tile reads.

The normals are the stage's, run on what a tile read: the PCA of each point's k nearest
distinct neighbours in 3-D (c1mesh.stages.normals.estimate_normals) or the height fit over
its k nearest plane neighbours (c1mesh.stages.height_gradients.fitted_normals); beside
each, the stage gives every own point's reach, its distance to its k-th neighbour
(normals.neighbourhood_reach; fitted_normals). A tile of a buffered_delaunay.TileGrid reads
its cell grown by a buffer. An own point's k nearest neighbours among the points read are
its k nearest in the survey when its reach is shorter than the way to every point not
read: those lie outside the read rectangle, at a plane distance (hence a 3-D distance) at
least the point's distance to the unread part of the survey's box. When that holds for
every own point the tile is done; otherwise its buffer doubles. The normals then agree
with the whole survey's to rounding (the neighbourhoods are the same; only the centring
of the coordinates differs).

read3(rect) -> (index (m,) ascending survey numbers, xyz (m, 3)) gives the points in the
closed rectangle of the plane, in the frame's coordinates (tile_spill.TileSpill.records).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from c1mesh.stages.height_gradients import fitted_normals
from c1mesh.stages.normals import estimate_normals, neighbourhood_reach
from c1mesh.survey.buffered_delaunay import TileGrid, growing_reads
from c1mesh.survey.strip_geometry import unread_strips


@dataclass
class TileNormals:
    """Unit normals (m, 3) of a tile's own points, index (m,) their survey numbers; the
    buffer it ended with and the rounds it took."""

    tile: int
    index: np.ndarray
    normals: np.ndarray
    buffer: float
    rounds: int


def tile_normals(read3: Callable, grid: TileGrid, tile: int, k: int, buffer: float,
                 towards=(0.0, 0.0, 1.0)) -> TileNormals:
    """Normals of one tile's own points (module docstring), oriented to face `towards`."""
    def attempt(xyz, own, read_box, covers):
        if not (covers or _neighbourhoods_inside(xyz, own, k, read_box, grid.box)):
            return None                          # before Open3D's fit: it costs more
        return estimate_normals(xyz, k=k, towards=towards)[own]

    return _grown(read3, grid, tile, buffer, attempt)


def _grown(read3: Callable, grid: TileGrid, tile: int, buffer: float,
           attempt: Callable) -> TileNormals:
    """A tile's normals from the points within `buffer` of its cell, the buffer doubled until
    attempt(xyz, own, read_box, covers) returns the own points' normals: it returns None
    when some own point's neighbourhood was not all read, which cannot happen once the
    read box covers the survey (covers=True)."""
    for reading in growing_reads(read3, grid, tile, buffer):
        index, xyz, own = reading.index, reading.points, reading.own
        if not own.any():
            return TileNormals(tile, index[own], np.empty((0, 3)), reading.buffer, reading.round)
        normals = attempt(xyz, own, reading.box, reading.covers)
        if normals is not None:
            return TileNormals(tile, index[own], normals, reading.buffer, reading.round)


def _neighbourhoods_inside(xyz: np.ndarray, own: np.ndarray, k: int, read_box, box) -> bool:
    """True when every own point's PCA neighbourhood among the points read, xyz (m, 3)
    (stages.normals.neighbourhood_reach), is closer than the unread part of the box."""
    return _closer_than_unread(xyz[own], neighbourhood_reach(xyz, own, k), read_box, box)


def _closer_than_unread(points: np.ndarray, reach: np.ndarray, read_box, box) -> bool:
    """True when each plane point (m, 2) is closer to its farthest neighbour, reach (m,),
    than to the unread part of the box (with a relative margin for rounding)."""
    return bool(_closer_than_unread_each(points, reach, read_box, box).all())


def _closer_than_unread_each(points: np.ndarray, reach: np.ndarray, read_box, box) -> np.ndarray:
    """(m,) bool: `_closer_than_unread` point by point."""
    gap = np.full(len(points), np.inf)
    for x0, y0, x1, y1 in unread_strips(read_box, box, np.zeros(2)):
        dx = np.maximum(np.maximum(x0 - points[:, 0], points[:, 0] - x1), 0.0)
        dy = np.maximum(np.maximum(y0 - points[:, 1], points[:, 1] - y1), 0.0)
        gap = np.minimum(gap, np.hypot(dx, dy))
    return reach * (1 + 1e-9) < gap


def tile_height_normals(read3: Callable, grid: TileGrid, tile: int, k: int, buffer: float) -> TileNormals:
    """Upward unit normals (frame coordinates) of one tile's own points from the heights:
    c1mesh.stages.height_gradients' fit over each point's k nearest neighbours in the plane,
    what the in-memory fit uses for LAS/LAZ (`height_normals`). The buffer grows as for
    `tile_normals` until every own point's k nearest plane neighbours lie in what was read
    (their plane distance is below the unread part's), so each fit sees the survey's
    neighbourhood. A fit does not depend on which other points were read (its neighbours
    and sums are fixed by the coordinates), so a larger read refits only the points whose
    neighbourhood the last one did not hold. k: the fit's neighbours
    (height_gradients.height_neighbours)."""
    normals, pending = None, None
    for reading in growing_reads(read3, grid, tile, buffer):
        index, xyz, own = reading.index, reading.points, reading.own
        if not own.any():
            return TileNormals(tile, index[own], np.empty((0, 3)), reading.buffer, reading.round)
        if len(xyz) <= k + 1 and not reading.covers:
            continue
        rows = np.flatnonzero(own)                       # the own points, ascending survey numbers
        if normals is None:
            normals, pending = np.empty((rows.size, 3)), np.arange(rows.size)
        fitted, reach = fitted_normals(xyz, rows[pending], k)
        held = np.ones(pending.size, dtype=bool) if reading.covers else \
            _closer_than_unread_each(xyz[rows[pending], :2], reach, reading.box, grid.box)
        normals[pending[held]] = fitted[held]
        pending = pending[~held]
        if not pending.size:
            return TileNormals(tile, index[own], normals, reading.buffer, reading.round)
