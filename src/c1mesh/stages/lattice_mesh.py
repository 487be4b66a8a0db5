"""The smoothing fit's vertices on a lattice (`--smooth` with `--spacing D`; issue 38,
docs/smoothing.md "The lattice route").

A smoothing fit needs no vertex at every data point: its spline is fitted to all of them.
With its vertices at the nodes of a regular lattice and every cell split by the same
diagonal, its system is a stencil that multigrid solves in a few iterations
(stages.lattice_solver), where the Delaunay system of the points needs a direct
factorisation (41-48 s and 6.7 GB at 1M vertices). Held out, the lattice spline at the
mean spacing is as good as the Delaunay one (docs/smoothing.md).

Where the surface is (`kept_cells`): a cell of the lattice is *supported* when it holds a
data point and its (2R + 1)² block of cells holds at least MIN_BLOCK_POINTS; the mesh is
every cell within R cells of a supported cell. R (`support_reach`) is SUPPORT_SPACINGS
point spacings h in cells, so the rule asks the same of the data at any D: about the reach
of the exact fit's trimmed Delaunay triangles (autzen_trim ground: R = 4 cells of 2 ft,
against triangles whose edges the trim holds to 15 ft). So the mesh reaches R cells beyond
the data (a spline cut at the data's border is poorly held there: 1.048× GMT's held-out RMS
on autzen ground, against 0.969× grown by 1-2 cells), closes gaps narrower than about 2R
cells, and leaves larger holes open; and each connected piece holds a whole block of at
least MIN_BLOCK_POINTS points, so its system is not singular. No Delaunay triangulation is
needed, and the rule is local: a tile decides its own cells from the points within 2R + 1
cells of them.

The lattice is the survey's: node (i, j) sits at (ox + (i0 + i) D, oy + (j0 + j) D) in the
frame's plane, for integers i0, j0 fixed by the data's bounding box, and is number j nx + i;
cell (i, j) has corners (i, j) .. (i + 1, j + 1) and is number j (nx − 1) + i. The offset
(ox, oy) (`lattice_offset`) puts the nodes at world x, y = (k + ½) D when the frame's plane
axes are the world's: at the cell centres of a DEM of resolution D, which then reads its
heights and gradients straight off the nodes (geo.raster_grid.NodeCells). Every tile of a
survey and the survey in memory make the same node at the same bits with the same number.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.threads import parallel_blocks
from c1mesh.core.tile import bounds, compact
from c1mesh.stages import _lattice_mesh as _kernel
from c1mesh.stages.lattice_solver import Lattice

MULTIGRID_FROM = 20_000
"""Nodes from which the lattice's system is solved by multigrid (stages.lattice_solver)
rather than factored by CHOLMOD. Measured since the solve keeps whole KEPT_BLOCK blocks
(2026-12-05, a loaded 2-core machine, whole smoothing fit, CHOLMOD / multigrid, two runs
each): 4_6_crop ground at --spacing 2.5 (7.9k nodes) 0.31-0.70 / 0.35-0.42 s, at 1.5 (21k)
0.72-1.11 / 0.60-0.62 s, at 1 (43k) 1.35-2.27 / 0.96-1.10 s; autzen_trim ground at --spacing
3, s = 0.01 (64k nodes, sparse patches) 2.52-4.29 / 1.60-3.04 s, at 2 (133k) 4.45-7.6 /
1.8-2.9 s; a uniform survey's 209k nodes 10.8 / 2.8 s. Before the blocks (borders on odd
nodes, 3-5 times the CG iterations) CHOLMOD was the faster up to about 200k nodes."""
SUPPORT_SPACINGS = 4.0
"""R, the support's reach, in point spacings h (rounded up to whole cells)."""
REACH_CELLS = (2, 8)
"""The least and the most cells R may be: 2 (a spline cut at the data is poorly held
there), 8 (a tiled survey grows its tile grid's box by REACH_CELLS[1] + 2 cells before h
is known: survey.lattice_runs)."""
KEPT_BLOCK = 8
"""The smoothing solves on a union of KEPT_BLOCK × KEPT_BLOCK blocks of cells, aligned at
the lattice's node (0, 0), each block kept whole when the support rule keeps one of its
cells; the output keeps the support's cells (the spline on them is the same). So the
solve's borders fall on nodes that the multigrid's first three coarse grids share
(stages.lattice_solver coarsens (2I, 2J) -> (I, J)); at a border on odd nodes its coarse
grids stand in with partial nodes and CG needed 3-5 times the iterations (the DTM job's 1M
nodes at s = 11.4: 34 instead of 7, and 13 instead of 3 for the edf's probes)."""
MIN_BLOCK_POINTS = 3
"""The points a supported cell's (2R + 1)² block must hold (a plane needs 3)."""


@dataclass(frozen=True)
class NodeGrid:
    """The survey's lattice: spacing D (frame units), first (i0, j0) the integer multiples of D
    of node (0, 0), shape (ny, nx) its nodes, reach R the support's (cells), offset (ox, oy)
    where the multiples start (frame units, `lattice_offset`): node (i, j) sits at
    (ox + (i0 + i) D, oy + (j0 + j) D)."""

    spacing: float
    first: tuple
    shape: tuple
    reach: int
    offset: tuple = (0.0, 0.0)

    @property
    def cells(self) -> tuple:
        """(ny − 1, nx − 1): the cells' rows and columns."""
        return self.shape[0] - 1, self.shape[1] - 1

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(i, j) int64 (m,) each: the cell holding each point of xy (m, 2)."""
        i = np.floor((xy[:, 0] - self.offset[0]) / self.spacing).astype(np.int64) - self.first[0]
        j = np.floor((xy[:, 1] - self.offset[1]) / self.spacing).astype(np.int64) - self.first[1]
        return i, j

    def positions(self, nodes: np.ndarray) -> np.ndarray:
        """(n, 2) the plane positions of node numbers (n,): ox + (i0 + i) D, oy + (j0 + j) D."""
        j, i = np.divmod(np.asarray(nodes, dtype=np.int64), self.shape[1])
        return np.column_stack([self.offset[0] + (self.first[0] + i) * self.spacing,
                                self.offset[1] + (self.first[1] + j) * self.spacing])

    def centres(self, cells: np.ndarray) -> np.ndarray:
        """(k, 2) the plane positions of the centres of cell numbers (k,)."""
        j, i = np.divmod(np.asarray(cells, dtype=np.int64), self.shape[1] - 1)
        return np.column_stack([self.offset[0] + (self.first[0] + i + 0.5) * self.spacing,
                                self.offset[1] + (self.first[1] + j + 0.5) * self.spacing])

    def solver_lattice(self, nodes: np.ndarray) -> Lattice:
        """The stages.lattice_solver.Lattice of vertices at these node numbers (n,)."""
        return Lattice(self.shape, (self.spacing, self.spacing),
                       (self.offset[0] + self.first[0] * self.spacing,
                        self.offset[1] + self.first[1] * self.spacing), nodes)


def check_spacing(spacing: float | str | None) -> None:
    """InputError unless spacing is None, "auto" (`auto_spacing`) or a finite positive length
    (checked before any work)."""
    if spacing is None or is_auto(spacing):
        return
    if not (isinstance(spacing, (int, float)) and math.isfinite(spacing) and spacing > 0):
        raise InputError(f"--spacing must be a positive length, got {spacing!r}")



def is_auto(spacing) -> bool:
    """Whether --spacing asks for auto_spacing."""
    return isinstance(spacing, str) and spacing.strip().lower() == "auto"


def auto_spacing(lower, upper, count: int) -> float:
    """--spacing auto: the lattice at the points' mean spacing sqrt(box area / n) over their
    bounding box lower (2,) .. upper (2,) (frame units) and count n, to AUTO_DIGITS
    significant digits, whatever the DEM's resolution: vertices as dense as the data.
    Rounded so that a tiled survey (its box and count from the spill's pass) and the same
    survey in memory choose the same D though their boxes differ in the last bits.
    InputError when the points span no area.

    Why the mean spacing (docs/smoothing.md, "The lattice's spacing"): held out on
    autzen_trim ground, a lattice 1.6x and 2.5x finer was as accurate (0.99-1.03x its RMS
    over 3 splits) and cost 3-7x the time; the finer one's search factors windows of 5x the
    nodes. Why not coarser where the DEM is (the rule until the nineteenth stop, D = the
    resolution when that was coarser): a lattice coarser than the data fits the terrain
    coarser, and the DEM's slope shows it. With 2 cm noise on benchmarks.geo's terrain, at a
    resolution of 4 spacings the spline's slope was 0.84° from the truth at D = the
    resolution, 0.30° at D = the spacing (Horn's 0.56° and 0.45°)."""
    extent = np.asarray(upper, dtype=float) - np.asarray(lower, dtype=float)
    area = float(extent[0] * extent[1])
    if not (count > 0 and area > 0 and math.isfinite(area)):
        raise InputError("--spacing auto: the points span no area in the frame's plane; give --spacing D")
    return float(f"{math.sqrt(area / count):.{AUTO_DIGITS}g}")


AUTO_DIGITS = 2
"""Significant digits of auto_spacing's mean spacing."""

FINEST_SPACINGS = 0.25
"""The finest lattice, in point spacings h: below h/4 it would hold over 16 nodes a point,
which no data can steer (and the support's reach, capped at REACH_CELLS[1] cells, would
need more points in a cell's block than it can hold)."""


BENDING_CELLS = 0.25
"""The least smoothing length of a fit on the lattice, in lattice spacings D (`least_strength`).
Below it the fit follows detail the points show but the cells cannot carry (a bank 1 m wide
in cells of 1.3 m), and the cells ring around it: folded faces beside steep steps (issue 38),
which the cross-validation does not see, as it scores heights at points, not slopes between
them, and its score there is held by the points on the banks, which no s predicts (flat
within 0.02 % from s = 1e-6 to 1e-5). Measured on 10 samples of issue 38's banks and ditches
(2 cm noise, one point a 1.3 m square, jittered grid or random; docs/smoothing.md, "Folds at
steps"), the lattice of 1.3 m folded no face from a smoothing length of 0.15-0.25 D on, each
sample its own (the last, a jittered one, folded one face at 0.23 D). On a lattice of 0.65 m,
finer than that detail, the five of them tried folded no face even at s = 1e-6."""


def least_strength(spacing: float, point_spacing: float, area_per_point: float) -> float:
    """The least strength s the search may choose on the lattice of `spacing` D, for points
    of spacing h = point_spacing (the strength's length unit: smoothing module doc) that
    cover area_per_point a² each (frame units): the s whose smoothing length ℓ is
    BENDING_CELLS D, rounded to 2 significant digits (the in-memory and the tiled fit count
    their points a few apart: the same rule as the search windows' side).

    ℓ is the smoothing module's length s^¼ h with the points' own density: the data weigh
    Σw/M a point, 1/a² points an area, against λ = s h² Σw/M times the energy, which
    balance at ℓ⁴ = s h² a² (the module takes a = h); so s = (BENDING_CELLS D)⁴ / (h a)².
    The area a² is the caller's: the support's cells over the points. 0 where h or a² is
    not positive. (A wave 2π ℓ long keeps about 1/5 of its height, where the module's
    1 / (1 + (2π ℓ / L)⁴) says 1/2: the RSD spline of a smooth function bends more than the
    function; tests/test_lattice_steps.py.)"""
    if point_spacing <= 0 or area_per_point <= 0:
        return 0.0
    least = (BENDING_CELLS * spacing) ** 4 / (point_spacing ** 2 * area_per_point)
    return float(f"{least:.2g}")


def support_least_strength(spacing: float, point_spacing: float, support_triangles: int, points: int) -> float:
    """least_strength of a fit whose support holds support_triangles lattice triangles (two a
    cell of spacing D) over `points` data points: their area per point is the support's
    cells over the points. The in-memory fit's one rule and the tiled fit's."""
    cells = support_triangles // 2
    return least_strength(spacing, point_spacing, cells * spacing ** 2 / points)


def check_lattice_spacing(spacing: float, point_spacing: float) -> None:
    """InputError when spacing D is finer than FINEST_SPACINGS point spacings h (frame units)."""
    if point_spacing > 0 and spacing < FINEST_SPACINGS * point_spacing:
        raise InputError(f"--spacing {spacing:g} is finer than a quarter of the points' spacing "
                         f"({point_spacing:.3g}): the lattice would hold over 16 nodes a point; give at least "
                         f"{FINEST_SPACINGS * point_spacing:.3g}")


def check_cells_left(count: int, grid: NodeGrid) -> None:
    """InputError when the lattice keeps no cell (`count` triangles 0): no cell holds a point
    whose block of (2R + 1)² cells holds MIN_BLOCK_POINTS. Every path says it before the fit."""
    if count == 0:
        side = (2 * grid.reach + 1) * grid.spacing
        raise InputError(f"no cell of the --spacing {grid.spacing:g} lattice has {MIN_BLOCK_POINTS} points within "
                         f"a {side:g} x {side:g} square around it; give a larger --spacing")


def support_reach(spacing: float, point_spacing: float) -> int:
    """R in cells of `spacing`: SUPPORT_SPACINGS point spacings h, rounded up, within REACH_CELLS."""
    reach = math.ceil(SUPPORT_SPACINGS * point_spacing / spacing) if point_spacing > 0 else REACH_CELLS[0]
    return int(min(max(reach, REACH_CELLS[0]), REACH_CELLS[1]))


def lattice_offset(origin, spacing: float) -> tuple[float, float]:
    """(ox, oy), each in [0, D): the NodeGrid offset that puts the nodes of the lattice of
    `spacing` D at world x, y = (k + ½) D in a frame whose plane axes are the world's and
    whose origin is at world x, y = origin (2,): the cell centres of a DEM of resolution D,
    whose cells are aligned at multiples of D (geo.raster_grid.RasterGrid.covering). The
    same for every tile of a survey (the frame is the survey's)."""
    return tuple(float((0.5 * spacing - float(o)) % spacing) for o in np.asarray(origin, dtype=float)[:2])


def node_grid(lower, upper, spacing: float, point_spacing: float, offset=(0.0, 0.0)) -> NodeGrid:
    """The lattice of `spacing` for data within lower (2,) .. upper (2,) (frame units) whose
    point spacing is h = point_spacing, its nodes at the multiples of D from `offset`
    (NodeGrid): its cells cover the data's cells and R (support_reach) more on every side."""
    check_spacing(spacing)
    R = support_reach(spacing, point_spacing)
    shift = np.asarray(offset, dtype=float)
    low = np.floor((np.asarray(lower, dtype=float) - shift) / spacing).astype(np.int64) - R - KEPT_BLOCK
    high = np.floor((np.asarray(upper, dtype=float) - shift) / spacing).astype(np.int64) + R + KEPT_BLOCK + 1
    nx, ny = int(high[0] - low[0]) + 1, int(high[1] - low[1]) + 1
    if nx * ny > 2 ** 62 // 4:
        raise InputError(f"--spacing {spacing:g} makes a lattice of {nx} × {ny} nodes; give a larger spacing")
    return NodeGrid(float(spacing), (int(low[0]), int(low[1])), (ny, nx), R, (float(shift[0]), float(shift[1])))


def _box_sum(counts: np.ndarray, reach: int) -> np.ndarray:
    """The sum of counts (h, w) over each (2 reach + 1)² box, for the cells at least reach
    from the border: shape (h − 2 reach, w − 2 reach); exact in int64 (summed-area table)."""
    table = np.zeros((counts.shape[0] + 1, counts.shape[1] + 1), dtype=np.int64)
    np.cumsum(np.cumsum(counts, axis=0, dtype=np.int64), axis=1, out=table[1:, 1:])
    k = 2 * reach + 1
    return table[k:, k:] - table[:-k, k:] - table[k:, :-k] + table[:-k, :-k]


def kept_cells(grid: NodeGrid, xy: np.ndarray, window: tuple | None = None,
               blocks: bool = False) -> np.ndarray:
    """(k,) ascending numbers of the mesh's cells (module doc) in window (i0, i1, j0, j1),
    the cells i0 <= i < i1, j0 <= j < j1 (None: all of the grid's). blocks: the solve's
    cells instead, every KEPT_BLOCK × KEPT_BLOCK block that holds a mesh cell.

    xy (m, 2), frame units: the data points, at least every one within 2R + KEPT_BLOCK
    cells of the window (grid.reach; a tile passes those of its halo); others are ignored."""
    rows, cols = grid.cells
    i0, i1, j0, j1 = (0, cols, 0, rows) if window is None else window
    if i1 <= i0 or j1 <= j0:
        return np.empty(0, dtype=np.int64)
    if blocks:                                            # the window widened to whole blocks
        B = KEPT_BLOCK
        a0, b0, a1, b1 = (i0 // B) * B, (j0 // B) * B, -(-i1 // B) * B, -(-j1 // B) * B
        near = _near_supported(grid, xy, (a0, a1, b0, b1))
        whole = near.reshape((b1 - b0) // B, B, (a1 - a0) // B, B).any(axis=(1, 3))
        kept = np.repeat(np.repeat(whole, B, axis=0), B, axis=1)[j0 - b0:j1 - b0, i0 - a0:i1 - a0]
    else:
        kept = _near_supported(grid, xy, (i0, i1, j0, j1))
    cj, ci = np.nonzero(kept)
    cj, ci = cj + j0, ci + i0
    on_grid = (ci >= 0) & (ci < cols) & (cj >= 0) & (cj < rows)
    return cj[on_grid] * cols + ci[on_grid]


def _near_supported(grid: NodeGrid, xy: np.ndarray, window: tuple) -> np.ndarray:
    """(h, w) bool over the window's cells (i0, i1, j0, j1): within R cells of a supported
    cell (module doc), from the points xy within 2R cells of the window."""
    R = grid.reach
    i0, i1, j0, j1 = window
    e = 2 * R                                             # the counts' margin around the window
    w, h = i1 - i0 + 2 * e, j1 - j0 + 2 * e
    i, j = grid.cell_of(xy)
    i, j = i - (i0 - e), j - (j0 - e)
    inside = (i >= 0) & (i < w) & (j >= 0) & (j < h)
    counts = np.bincount(j[inside] * w + i[inside], minlength=w * h).reshape(h, w)
    blocks = _box_sum(counts, R)                          # cells from the window's corner − R
    supported = (counts[R:h - R, R:w - R] > 0) & (blocks >= MIN_BLOCK_POINTS)
    return _box_sum(supported.astype(np.int64), R) > 0


def cell_triangles(grid: NodeGrid, cells: np.ndarray) -> np.ndarray:
    """(2k, 3) node numbers of the cells' two triangles each, counter-clockwise, split along
    the diagonal from node (i, j) to (i + 1, j + 1): (a, b, d) then (a, d, c) for a = (i, j),
    b = (i + 1, j), c = (i, j + 1), d = (i + 1, j + 1), in the cells' order."""
    nx = grid.shape[1]
    j, i = np.divmod(np.asarray(cells, dtype=np.int64), nx - 1)
    a = j * nx + i
    b, c, d = a + 1, a + nx, a + nx + 1
    return np.stack([np.stack([a, b, d], axis=1), np.stack([a, d, c], axis=1)], axis=1).reshape(-1, 3)


def nearest_points(positions: np.ndarray, xy: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(n,) the `index` (m,) of the point of xy (m, 2) nearest each position (n, 2), ties
    (equal squared distances) to the lower index, so that the answer depends on no order (a
    tile's candidates are a subset of the survey's holding the nearest). The points are
    sorted into square buckets of about NEAREST_BUCKET_POINTS each, and each position
    searches the buckets ring by ring around its own (stages/_lattice_mesh.pyx), positions
    in fixed blocks in the thread knob's threads: 0.21 s at 1M nodes and points, where
    cKDTree's two-neighbour queries took 0.85 s."""
    positions = np.ascontiguousarray(positions, dtype=float)
    xy = np.ascontiguousarray(xy, dtype=float)
    index = np.ascontiguousarray(index, dtype=np.int64)
    out = np.empty(positions.shape[0], dtype=np.int64)
    if not len(positions):
        return out
    lower, upper = bounds(xy)
    size, cols, rows, ci, cj = _buckets(xy, lower, np.maximum(upper - lower, 0.0))
    start = np.empty(cols * rows + 1, dtype=np.int64)
    held, ids = np.empty_like(xy), np.empty_like(index)
    _kernel.bucket_points(xy, index, cj * cols + ci, cols * rows, start, held, ids)
    parallel_blocks(lambda part: _kernel.nearest_in_buckets(positions, part.start, part.stop, start, held, ids,
                                                             float(lower[0]), float(lower[1]), size, cols, rows, out),
                    positions.shape[0], NEAREST_BLOCK)
    return out


def _buckets(xy: np.ndarray, lower: np.ndarray, extent: np.ndarray) -> tuple:
    """(size, cols, rows, ci (m,), cj (m,)): nearest_points' square buckets over the box
    lower + extent of the points xy (m, 2) and each point's bucket. The side starts from the
    box's area over m / NEAREST_BUCKET_POINTS buckets and halves while the occupied buckets
    hold more than twice that on average (a far outlier widens the box and crowds the rest:
    at 100 km from 200k points in a 450 m square the query took 20 s, at 0.03 s without
    it), never below the longer side over NEAREST_BUCKET_SIDE (the table's bound), and not
    at all where the points are one position."""
    least = float(extent.max()) / NEAREST_BUCKET_SIDE
    size = max(math.sqrt(float(extent[0] * extent[1]) * NEAREST_BUCKET_POINTS / xy.shape[0]), least) or 1.0
    while True:                                     # 1.0 above: the points are one
        cols, rows = (np.floor(extent / size).astype(np.int64) + 1).tolist()
        ci = np.minimum(((xy[:, 0] - lower[0]) / size).astype(np.int64), cols - 1)
        cj = np.minimum(((xy[:, 1] - lower[1]) / size).astype(np.int64), rows - 1)
        occupied = np.count_nonzero(np.bincount(cj * cols + ci, minlength=cols * rows))
        if xy.shape[0] <= 2 * NEAREST_BUCKET_POINTS * occupied or size / 2 < least or least == 0:
            return size, cols, rows, ci, cj
        size /= 2


NEAREST_BUCKET_POINTS = 2.0
"""Points per bucket of nearest_points on evenly spread points (a node's nearest then lies
in its own bucket or the ring around it)."""
NEAREST_BUCKET_SIDE = 1 << 12
"""The most buckets along the longer side (16.8M at most: 0.13 GB of int64 starts)."""
NEAREST_BLOCK = 1 << 15
"""Positions per block of nearest_points (the thread knob's threads)."""


@dataclass(frozen=True)
class LatticeMesh:
    """A smoothing fit's vertices and triangles on the lattice: grid (NodeGrid); nodes (n,)
    ascending node numbers, points (n, 2) their positions (frame units), triangles (T, 3)
    into them (cell_triangles' order of the solve's cells, kept_cells with blocks); sources
    (n,) the data point nearest each node (its index: colours, and the input that owns it
    with -O); shown (T,) bool: the triangles of the support's cells, the output's."""

    grid: NodeGrid
    nodes: np.ndarray
    points: np.ndarray
    triangles: np.ndarray
    sources: np.ndarray
    shown: np.ndarray

    def shown_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(used (u,) ascending rows of the nodes the shown triangles use, their triangles
        (S, 3) into those rows): the output's mesh."""
        return compact(self.triangles[self.shown], self.nodes.size)

    def facts(self) -> dict:
        """The report's smoothing.lattice: spacing D, reach R (cells), nodes."""
        return lattice_facts(self.grid, int(self.nodes.size))

    def solver_lattice(self) -> Lattice | None:
        """smooth_fit's `lattice` for these vertices (multigrid_lattice)."""
        return multigrid_lattice(self.grid, self.nodes)


def multigrid_lattice(grid: NodeGrid, nodes: np.ndarray) -> Lattice | None:
    """smooth_fit's `lattice` for vertices at these node numbers (n,) of grid, in their
    order (its multigrid solve), or None below MULTIGRID_FROM nodes (a direct solve): the
    in-memory fit's one rule and every tile's of a tiled one."""
    return grid.solver_lattice(nodes) if len(nodes) >= MULTIGRID_FROM else None


def lattice_facts(grid: NodeGrid, nodes: int) -> dict:
    """The report's smoothing.lattice of a fit on grid with this many nodes (every path)."""
    return {"spacing": grid.spacing, "reach_cells": grid.reach, "nodes": nodes}


def lattice_mesh(xy: np.ndarray, spacing: float, point_spacing: float, offset=(0.0, 0.0)) -> LatticeMesh:
    """The in-memory fit's one tile of the lattice route: the mesh (module doc) of data
    points xy (m, 2, frame units) at `spacing`, their point spacing h = point_spacing, the
    nodes at the multiples of D from `offset` (lattice_offset), sources numbering xy's rows."""
    grid = node_grid(*bounds(xy), spacing, point_spacing, offset)
    solve = _kept_in_bands(grid, xy, blocks=True)
    nodes, triangles = numbered_triangles(grid, solve)
    points = grid.positions(nodes)
    shown = np.repeat(np.isin(solve, _kept_in_bands(grid, xy), assume_unique=True), 2)
    return LatticeMesh(grid, nodes, points, triangles, nearest_points(points, xy, np.arange(xy.shape[0])), shown)


BAND_CELLS = 1 << 24
"""Cells of the lattice kept_cells counts at once in memory (int64 counts and two summed-
area tables: 24 bytes a cell): a survey whose box holds more, such as distant inputs of one
--seamless survey, is decided in bands of rows."""


def _kept_in_bands(grid: NodeGrid, xy: np.ndarray, blocks: bool = False) -> np.ndarray:
    """kept_cells over the whole grid, BAND_CELLS at a time: each band of rows (whole
    blocks) with the points within 2R + KEPT_BLOCK rows of it."""
    rows, cols = grid.cells
    band = max(1, BAND_CELLS // (cols + 4 * grid.reach + 2 * KEPT_BLOCK) // KEPT_BLOCK) * KEPT_BLOCK
    if band >= rows:
        return kept_cells(grid, xy, blocks=blocks)
    j = grid.cell_of(xy)[1]
    order = np.argsort(j, kind="stable")
    j = j[order]
    parts = []
    for j0 in range(0, rows, band):
        j1 = min(rows, j0 + band)
        reach = 2 * grid.reach + KEPT_BLOCK
        lo, hi = np.searchsorted(j, [j0 - reach, j1 + reach])
        if hi > lo:
            parts.append(kept_cells(grid, xy[order[lo:hi]], (0, cols, j0, j1), blocks=blocks))
    return np.concatenate(parts) if parts else np.empty(0, dtype=np.int64)


MARKED_NODES = 1 << 26
"""Node number spans up to which numbered_triangles marks the nodes in a table
(core.tile.compact: a byte and an int64 a node of the span) instead of sorting the corners."""


def numbered_triangles(grid: NodeGrid, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nodes (n,) ascending node numbers of the cells' corners, triangles (2k, 3) into
    them: cell_triangles' order) of cells (k,) ascending cell numbers."""
    corners = cell_triangles(grid, cells)
    if not len(corners):
        return np.empty(0, dtype=np.int64), corners
    first, last = int(corners.min()), int(corners.max())
    if last - first >= MARKED_NODES:
        nodes, local = np.unique(corners, return_inverse=True)
        return nodes, local.reshape(-1, 3).astype(np.int64)
    used, local = compact(corners - first, last - first + 1)
    return used + first, local


__all__ = ["AUTO_DIGITS", "FINEST_SPACINGS", "auto_spacing", "is_auto", "BENDING_CELLS", "KEPT_BLOCK", "LatticeMesh", "MIN_BLOCK_POINTS", "MULTIGRID_FROM",
           "NodeGrid", "REACH_CELLS", "SUPPORT_SPACINGS", "cell_triangles", "check_cells_left",
           "check_lattice_spacing", "check_spacing", "kept_cells", "lattice_facts", "lattice_mesh", "lattice_offset",
           "least_strength", "support_least_strength",
           "multigrid_lattice", "nearest_points", "node_grid", "numbered_triangles", "support_reach"]
