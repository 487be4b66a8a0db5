"""The overshoot limiter (c1mesh.stages.limiter) on a survey fitted in tiles, with its whole-survey result.

The limiter is not tile-local in two ways:

- its noise floors are survey-wide: the median |trapezoid residual| over every edge of the
  final triangulation, once with the input heights and gradients (for `reconcile_heights`
  and `reconcile_gradients`) and once with the reconciled ones (for `limit_gradients`);
- a vertex's reconciled height needs its star (its edges and their triangles), its
  reconciled gradient the reconciled heights of all its neighbours, its limited gradient
  the reconciled gradients of all its neighbours, and an edge's direction both of its
  triangles (`edge_directions`).

The halo rule. Every final triangle has edges at most L long (the long-edge trim's
max_edge, or the longest edge of the untrimmed triangulation). A tile reads the height
field in its cell grown by 4L (its halo) and the final triangles of every tile that cell
meets, and keeps the triangles whose three corners it read. Then it holds the whole star
of every vertex within 3L of its cell, so it has, exactly as the whole survey has them:

- the reconciled height of every vertex within 3L of the cell (its star is inside), and
  the reconciled gradient of every vertex within 2L;
- the limited gradient, the reconciled height and the edge directions of every corner of
  its own triangles (those lie within L of the cell, their neighbours within 2L);
- the residuals of the edges whose lower-numbered end lies in its cell (both ends within
  L), each edge of the survey in exactly one tile.

The two noise floors take a pass over the tiles each: every tile appends its edges'
residuals to a file, and c1mesh.survey.streamed_median finds their median to the bit. The third
pass (the caller's) limits each tile's gradients with the floors passed in. The limiter's
arithmetic on one vertex or edge does not depend on the rest of the mesh (its sums run
over the vertex's edges in the same order, its local numbering follows the survey
numbers), so the gradients come out with the bits of the whole-survey limiter given the
same height field; directions too, up to the sign of a direction through two opposite
vertices (which triangle of an edge is its "owner" depends on triangle order; the spline
does not depend on that sign).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

HALO_EDGES = 4
"""A tile's halo, in longest final edges (module docstring)."""


@dataclass
class Halo:
    """What one tile reads for the limiter: records (m,) height-field records (fields index,
    x, y, z, gx, gy; ascending survey numbers) that are corners of `triangles`; triangles
    (k, 3) the final triangles with all corners read, into records; own (m,) bool: the
    records in the tile's cell."""

    records: np.ndarray
    triangles: np.ndarray
    own: np.ndarray

    @property
    def points(self) -> np.ndarray:
        return np.column_stack([self.records["x"], self.records["y"]])

    @property
    def gradients(self) -> np.ndarray:
        return np.column_stack([self.records["gx"], self.records["gy"]])


@dataclass(frozen=True)
class NoiseFloors:
    """The survey's median |trapezoid residual| over all final edges, with the input heights
    and gradients (first) and with the reconciled ones (second); height units."""

    first: float
    second: float


@dataclass
class TileLimits:
    """The limiter's result for the corners of one tile's triangles: records (c,) the
    corners (ascending survey numbers; their z reconciled), triangles (k, 3) into them,
    gradients (c, 2) limited, directions (E, 2) in the order of
    topology.edge_table(triangles, c).edges; limited: own vertices whose gradient changed,
    turned: own edges whose direction is not the unit normal, lifted: own vertices whose
    height moved (own: in the tile's cell; lower end, for an edge)."""

    records: np.ndarray
    triangles: np.ndarray
    gradients: np.ndarray
    directions: np.ndarray
    limited: int
    turned: int
    lifted: int = 0


def halo_reach(longest_edge: float) -> float:
    """How far beyond its cell a tile reads (frame units), for final edges at most
    longest_edge long; a relative margin keeps rounding on the safe side."""
    return HALO_EDGES * float(longest_edge) * (1 + 1e-9)


def halo_rows(index: np.ndarray, numbers: np.ndarray) -> np.ndarray:
    """The row of each of `numbers` (survey numbers, any shape) among `index` (a halo's
    survey numbers, ascending and distinct), -1 where absent. A binary search over the
    halo: its memory is the halo's and the query's, whatever the survey's size (a dense
    table over the survey cost 4 bytes a survey point in every process). The distinct
    numbers are searched in ascending order: a triangle list repeats each corner about six
    times, and a sorted query walks the halo instead of jumping through it, which made
    the halo reads 2.5x faster than a search per number."""
    numbers = np.asarray(numbers, dtype=np.int64)
    if not len(index):
        return np.full(numbers.shape, -1, dtype=np.int64)
    distinct, where = np.unique(numbers.ravel(), return_inverse=True)
    rows = np.searchsorted(index, distinct)
    np.minimum(rows, len(index) - 1, out=rows)
    rows[index[rows] != distinct] = -1
    return rows[where.ravel()].reshape(numbers.shape)


def read_halo(heights, triangle_files, grid, tile: int, reach: float) -> Halo:
    """The halo of `tile` (module docstring). heights: a tile_spill.TileSpill of height
    records; triangle_files: per tile a .npy of its owned final triangles (survey numbers)
    or None."""
    rect = grid.grown(tile, reach)
    records = heights.records(rect)
    parts = [np.empty((0, 3), np.int64)]
    for other in heights.touching(rect):
        if triangle_files[other] is None or not len(records):
            continue
        parts.append(_rows_inside(records["index"], np.load(triangle_files[other])))
    used, triangles = _compact(np.concatenate(parts), len(records))
    records = records[used]
    own = grid.tile_of(np.column_stack([records["x"], records["y"]])) == tile
    return Halo(records, triangles, own)


def _rows_inside(index: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The triangles (k, 3) (survey numbers) whose three corners are among `index` (a
    halo's survey numbers, ascending), as rows of index. A neighbour tile shares only a
    band of its triangles with the halo, so the lowest corners sift them first."""
    inside = halo_rows(index, triangles.min(axis=1)) >= 0
    rows = halo_rows(index, triangles[inside])
    return rows[(rows >= 0).all(axis=1)]


class HaloCache:
    """Every tile's halo, read from the spills once and kept in temporary files for the
    later passes (a halo read costs a filter of up to nine tiles' points and triangles;
    a cached one, one file read). Triangles removed after the first read (the peel) are
    dropped as each halo is loaded: `removed` maps a tile to the removed triangles it
    owns, so a halo compares its triangles with those of the tiles it reads, not with
    the survey's whole list. temps: tiled_fit._Temps."""

    def __init__(self, heights, triangle_files, grid, reach: float, temps):
        self.heights, self.files, self.grid, self.reach = heights, triangle_files, grid, reach
        self.temps, self.paths = temps, {}
        self.removed: dict[int, np.ndarray] = {}

    def tiles(self):
        """The tiles that own triangles."""
        return [t for t in range(len(self.grid)) if self.files[t] is not None]

    def halo(self, tile: int) -> Halo:
        if tile not in self.paths:
            halo = read_halo(self.heights, self.files, self.grid, tile, self.reach)
            self.paths[tile] = (self.temps.new(f"halo-{tile}.records"), self.temps.new(f"halo-{tile}.triangles"))
            halo.records.tofile(self.paths[tile][0])
            halo.triangles.astype("<i8").tofile(self.paths[tile][1])
            return self._drop(tile, halo)
        records = np.fromfile(self.paths[tile][0], dtype=self.heights.record)
        triangles = np.fromfile(self.paths[tile][1], dtype="<i8").reshape(-1, 3)
        own = self.grid.tile_of(np.column_stack([records["x"], records["y"]])) == tile
        return self._drop(tile, Halo(records, triangles, own))

    def prefetch(self, runner, name=str, on_done=None) -> None:
        """Read every tile's halo and cache it, each tile a task on runner
        (distributed.TaskRunner; `cache_halo`), before the passes that use them.
        name(t) names tile t in errors; on_done(t, row) gets each task's report row."""
        tiles = [t for t in self.tiles() if t not in self.paths]
        paths = {t: (self.temps.new(f"halo-{t}.records"), self.temps.new(f"halo-{t}.triangles")) for t in tiles}
        for i, row in runner.map(cache_halo, len(tiles), lambda i: (self, tiles[i], paths[tiles[i]]),
                                 lambda i: name(tiles[i])):
            self.paths[tiles[i]] = paths[tiles[i]]
            if on_done:
                on_done(tiles[i], row)

    def prune(self) -> None:
        """Rewrite the cached halos without the removed triangles, once the trim is done
        (and the tiles' triangle files without them), so later passes need not drop them."""
        for tile, (_, triangles_path) in self.paths.items():
            self.halo(tile).triangles.astype("<i8").tofile(triangles_path)
        self.removed = {}

    def halos(self):
        """A fresh iterator over the halos of all tiles that own triangles."""
        return (self.halo(t) for t in self.tiles())

    def _drop(self, tile: int, halo: Halo) -> Halo:
        near = [self.removed[t] for t in self.heights.touching(self.grid.grown(tile, self.reach))
                if t in self.removed]
        if not near or not len(halo.triangles):
            return halo
        from c1mesh.survey.tiled_trim import drop_triangles

        survey = halo.records["index"][halo.triangles]
        kept = drop_triangles(np.column_stack([survey, np.arange(len(survey))]), np.concatenate(near), columns=3)
        return Halo(halo.records, halo.triangles[kept[:, 3]], halo.own)


def cache_halo(cache: HaloCache, tile: int, paths) -> dict:
    """Read tile's halo (read_halo) and write it to paths (records, triangles), as
    HaloCache.halo caches it; returns a report row (points, seconds, worker)."""
    from c1mesh.survey.tiles import task_row

    start = time.perf_counter()
    halo = read_halo(cache.heights, cache.files, cache.grid, tile, cache.reach)
    halo.records.tofile(paths[0])
    halo.triangles.astype("<i8").tofile(paths[1])
    return task_row(len(halo.records), start)


def _compact(triangles: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(used (u,) ascending rows that triangles use, triangles renumbered into used)."""
    mark = np.zeros(count, dtype=bool)
    mark[triangles] = True
    new = np.cumsum(mark) - 1
    return np.flatnonzero(mark), new[triangles]


def edge_residuals(points, values, gradients, edges) -> np.ndarray:
    """(E,) |trapezoid residual| of each edge, with the limiter's own arithmetic."""
    from c1mesh.stages.limiter import trapezoid_residuals

    return np.abs(trapezoid_residuals(points, values, gradients, edges))


def edge_floor(halos: Callable[[], object], temps, name: str, data_of=None) -> float:
    """The median |trapezoid residual| over every final edge of the survey, exactly (each
    edge from the tile holding its lower end). halos: a callable giving a fresh iterator
    of every tile's Halo; data_of(halo, table): the heights (m,) and gradients (m, 2) to
    use (None: the height field's); temps: tiled_fit._Temps for the residual file."""
    from c1mesh.survey.streamed_median import streamed_median
    from c1mesh.engine.topology import edge_table

    path = temps.new(f"residuals-{name}.bin")
    with open(path, "wb") as file:
        for halo in halos():
            if not len(halo.triangles):
                continue
            table = edge_table(halo.triangles, len(halo.records))
            mine = table.edges[halo.own[table.edges[:, 0]]]  # lower end in the cell
            values, gradients = (halo.records["z"], halo.gradients) if data_of is None else data_of(halo, table)
            residuals = edge_residuals(halo.points, values, gradients, mine)
            residuals.astype("<f8").tofile(file)
    median = streamed_median(lambda: _float_blocks(path))
    path.unlink()
    return median


def noise_floors(halos: Callable[[], object], temps) -> NoiseFloors:
    """The survey's two noise floors, exactly. halos: a callable giving a fresh iterator
    of every tile's Halo; temps: tiled_fit._Temps for the residual files."""
    first = edge_floor(halos, temps, "first")
    second = edge_floor(halos, temps, "second", lambda halo, table: reconciled(halo, table, first)[:2])
    return NoiseFloors(first, second)


def noise_floors_on(cache: HaloCache, temps, runner, name=str) -> NoiseFloors:
    """noise_floors with each tile's residuals a task on runner (distributed.TaskRunner;
    `tile_residuals`) writing its own file: the same two medians, to the bit (the median
    does not depend on the order of the values). cache: a HaloCache holding every halo
    (after prune); name(t) names tile t in errors."""
    first = _floor_on(cache, temps, runner, name, "first", None)
    return NoiseFloors(first, _floor_on(cache, temps, runner, name, "second", first))


def _floor_on(cache: HaloCache, temps, runner, name, label: str, reconciled_with: float | None) -> float:
    from c1mesh.survey.streamed_median import streamed_median

    tiles = cache.tiles()
    paths = [temps.new(f"residuals-{label}-{t}.bin") for t in tiles]
    for _ in runner.map(tile_residuals, len(tiles), lambda i: (cache, tiles[i], reconciled_with, paths[i]),
                        lambda i: name(tiles[i])):
        pass

    def blocks():
        for path in paths:
            yield from _float_blocks(path)
    median = streamed_median(blocks)
    for path in paths:
        path.unlink()
    return median


def tile_residuals(cache: HaloCache, tile: int, reconciled_with: float | None, path) -> None:
    """Write to path the |trapezoid residual| of every final edge whose lower end lies in
    tile's cell (edge_floor's values for that tile): with the height field's heights and
    gradients, or, given the first noise floor, with both reconciled with it."""
    from c1mesh.engine.topology import edge_table

    halo = cache.halo(tile)
    residuals = np.empty(0)
    if len(halo.triangles):
        table = edge_table(halo.triangles, len(halo.records))
        mine = table.edges[halo.own[table.edges[:, 0]]]      # lower end in the cell
        values, gradients = halo.records["z"], halo.gradients
        if reconciled_with is not None:
            values, gradients, _, _ = reconciled(halo, table, reconciled_with)
        residuals = edge_residuals(halo.points, values, gradients, mine)
    residuals.astype("<f8").tofile(path)


def tile_limits(halo: Halo, owned: np.ndarray, floors: NoiseFloors) -> TileLimits:
    """The limited gradients and edge directions of one tile's own triangles, `owned`
    (k, 3) survey numbers, all inside its halo."""
    from c1mesh.stages.limiter import edge_directions
    from c1mesh.engine.topology import edge_table

    points = halo.points
    table = edge_table(halo.triangles, len(halo.records))
    values, gradients, lifted, moved = reconciled(halo, table, floors.first)
    limited, changed = limit(points, values, gradients, table.edges, floors.second)
    directions, turned = edge_directions(points, halo.triangles, table)
    rows = halo_rows(halo.records["index"], owned)
    if np.any(rows < 0):
        raise RuntimeError("a tile's own triangle has a corner outside its halo")
    corners, triangles = _compact(rows, len(halo.records))
    n = len(halo.records)
    keys = table.edges[:, 0] * n + table.edges[:, 1]
    sub = corners[edge_table(triangles, len(corners)).edges]
    at = np.searchsorted(keys, sub[:, 0] * n + sub[:, 1])
    records = halo.records[corners]
    records["z"] = values[corners]
    return TileLimits(records, triangles, limited[corners], directions[at],
                      int(((moved | changed) & halo.own).sum()),
                      int((turned & halo.own[table.edges[:, 0]]).sum()), int((lifted & halo.own).sum()))


def longest_final_edge(heights, triangle_files, grid, buffers) -> float:
    """The longest edge of the survey's final triangles (as trim.trim measures
    edges), tile by tile: tile t's own triangles have their corners within buffers[t]."""
    from c1mesh.stages.trim import edge_lengths

    longest = 0.0
    for t, path in enumerate(triangle_files):
        if path is None:
            continue
        triangles = np.load(path)
        if not len(triangles):
            continue
        records = heights.records(grid.grown(t, buffers[t] * (1 + 1e-9)))
        rows = halo_rows(records["index"], triangles)
        xy = np.column_stack([records["x"], records["y"]])
        longest = max(longest, float(edge_lengths(xy, rows).max()))
    return longest


def reconciled(halo: Halo, table, noise: float):
    """The halo's heights and gradients reconciled as limiter.control_overshoot does, with
    the survey's first noise floor: (values (m,), gradients (m, 2), heights moved (m,) bool,
    gradients changed (m,) bool). Exact for vertices within 3L (heights) and 2L
    (gradients) of the cell (module docstring)."""
    from c1mesh.stages.limiter import reconcile_gradients, reconcile_heights

    points = halo.points
    values, lifted = reconcile_heights(points, halo.records["z"], halo.gradients, halo.triangles,
                                       table, noise_floor=noise)
    gradients, moved = reconcile_gradients(points, values, halo.gradients, table.edges, noise_floor=noise)
    return values, gradients, lifted, moved


def limit(points, values, gradients, edges, noise: float):
    """limiter.limit_gradients with the survey's noise floor."""
    from c1mesh.stages.limiter import limit_gradients

    return limit_gradients(points, values, gradients, edges, noise_floor=noise)


FLOAT_BLOCK = 1 << 20
"""Residuals read per block (8 MB): streamed_median makes a few block-sized temporaries
per pass (bit patterns, shifted digits, masks), so the block bounds the noise floors' peak."""


def _float_blocks(path, block: int = FLOAT_BLOCK):
    from c1mesh.survey.tile_spill import file_blocks

    with open(path, "rb") as file:
        yield from file_blocks(file, "<f8", block)
