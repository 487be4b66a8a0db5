"""A tile: the unit every stage of a fit runs on (docs/tiles.md, ../one-engine sketch).

A tile is the height-field vertices a stage may read — the ones in its cell (owned) and a
halo around it — with the final triangles whose three corners it holds. The in-memory fit
is one tile whose every vertex is owned and whose halo is empty (`Tile.whole`); a survey
fitted in tiles reads one per cell from its spill files (c1mesh.survey). A stage written
as a function of a Tile therefore runs unchanged in both, and so gives the same answer in
both: what must be the same across the survey (a noise floor, a strength) is a summary
per tile and one reduce, declared beside the stage.

The bookkeeping here — finding survey numbers among a tile's, renumbering the corners a
set of triangles uses — is what every tile stage and the join share.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

VERTEX = np.dtype([("index", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                   ("gx", "<f8"), ("gy", "<f8")])
"""One height-field vertex: its survey number, position in the frame's plane, height, and
gradient (dz/dx, dz/dy), all in frame units."""


@dataclass
class Tile:
    """What one stage run reads: records (m,) VERTEX records in ascending survey numbers;
    triangles (k, 3) final triangles into records, every corner read; own (m,) bool, the
    records in the tile's cell (every record, for the in-memory fit's one tile)."""

    records: np.ndarray
    triangles: np.ndarray
    own: np.ndarray

    @classmethod
    def whole(cls, points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
              triangles: np.ndarray) -> "Tile":
        """The in-memory fit's one tile: points (n, 2), values (n,), gradients (n, 2) in
        the frame; triangles (k, 3) into them; every vertex owned, survey numbers 0..n-1."""
        records = np.empty(len(points), VERTEX)
        records["index"] = np.arange(len(points))
        records["x"], records["y"] = points[:, 0], points[:, 1]
        records["z"] = values
        records["gx"], records["gy"] = gradients[:, 0], gradients[:, 1]
        return cls(records, np.asarray(triangles, dtype=np.int64), np.ones(len(points), dtype=bool))

    @property
    def points(self) -> np.ndarray:
        """(m, 2) positions in the frame's plane."""
        return np.column_stack([self.records["x"], self.records["y"]])

    @property
    def values(self) -> np.ndarray:
        """(m,) heights."""
        return self.records["z"]

    @property
    def gradients(self) -> np.ndarray:
        """(m, 2) gradients."""
        return np.column_stack([self.records["gx"], self.records["gy"]])


def tile_rows(index: np.ndarray, numbers: np.ndarray) -> np.ndarray:
    """The row of each of `numbers` (survey numbers, any shape) among `index` (a tile's
    survey numbers, ascending and distinct), -1 where absent. A binary search over the
    tile: its memory is the tile's and the query's, whatever the survey's size (a dense
    table over the survey cost 4 bytes a survey point in every process). The distinct
    numbers are searched in ascending order: a triangle list repeats each corner about six
    times, and a sorted query walks the tile instead of jumping through it, which made
    the halo reads 2.5x faster than a search per number."""
    numbers = np.asarray(numbers, dtype=np.int64)
    if not len(index):
        return np.full(numbers.shape, -1, dtype=np.int64)
    distinct, where = np.unique(numbers.ravel(), return_inverse=True)
    rows = np.searchsorted(index, distinct)
    np.minimum(rows, len(index) - 1, out=rows)
    rows[index[rows] != distinct] = -1
    return rows[where.ravel()].reshape(numbers.shape)


def compact(triangles: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(used (u,) ascending rows that triangles use, triangles renumbered into used)."""
    mark = np.zeros(count, dtype=bool)
    mark[triangles] = True
    new = np.cumsum(mark) - 1
    return np.flatnonzero(mark), new[triangles]


def corner_rows(index: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tile triangles (k, 3) of survey numbers against `index` (ascending survey numbers of
    the records a tile read): (rows (c,) of their distinct corners among index, -1 where
    absent; triangles (k, 3) numbering those corners)."""
    corners, local = np.unique(triangles, return_inverse=True)
    return tile_rows(index, corners), local.reshape(triangles.shape)


def bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper), each (d,): the least and the largest value of each column of points
    (n, d), n >= 1; the values of points.min(axis=0) and points.max(axis=0), found column
    by column, because numpy's reduction over the rows of an (n, 2) C-ordered array walks
    them two values at a time: 25 ms each at 1M points, a column's 1-2 ms."""
    columns = range(points.shape[1])
    return (np.array([points[:, k].min() for k in columns]), np.array([points[:, k].max() for k in columns]))


def finite_rows(points: np.ndarray) -> np.ndarray:
    """(n,) bool: the rows of points (n, d) whose every value is finite, as
    np.isfinite(points).all(axis=1) gives them, column by column (15 ms against 1.7 ms at
    1M rows of 3, for `bounds`' reason)."""
    good = np.isfinite(points[:, 0])
    for k in range(1, points.shape[1]):
        good &= np.isfinite(points[:, k])
    return good


def row_min(values: np.ndarray) -> np.ndarray:
    """(n,) the least value of each row of values (n, k), k >= 1, as values.min(axis=1)
    gives it, column by column: numpy's reduction over short rows walks them a few values
    at a time (a triangle list's lowest corners: 19 ms against 2.7 ms at 560k rows)."""
    least = values[:, 0].copy()
    for k in range(1, values.shape[1]):
        np.minimum(least, values[:, k], out=least)
    return least


def row_any(flags: np.ndarray) -> np.ndarray:
    """(n,) bool whether any value of each row of flags (n, k) bool is set, as
    flags.any(axis=1) gives it, column by column (`row_min`'s reason)."""
    found = flags[:, 0].copy()
    for k in range(1, flags.shape[1]):
        found |= flags[:, k]
    return found


def plane_bounds(parts) -> tuple[np.ndarray, np.ndarray]:
    """((2,), (2,)): the least and the largest x and y over the parts (an iterable of (m, 2)
    plane positions: a survey's tiles, or the in-memory fit's one part), the reduce a
    survey-wide box needs; (inf, inf), (-inf, -inf) when every part is empty."""
    lower, upper = np.full(2, np.inf), np.full(2, -np.inf)
    for xy in parts:
        if xy.shape[0]:
            low, high = bounds(xy)
            lower, upper = np.minimum(lower, low), np.maximum(upper, high)
    return lower, upper
