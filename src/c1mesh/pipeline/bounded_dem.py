"""The DEM of a survey fitted in tiles: `c1mesh fit BIG.laz -o dem.tif --resolution R
--memory M` (pipeline.bounded_fit), the in-memory fit's DEM (geo.raster.dem_sampling and
write_fit_rasters), cell for cell, with no tile holding the survey.

The in-memory DEM's rules (geo.raster_grid.SplineSampler), and how the tiles keep them:

- the grid covers the bounding box of the spline's vertices (RasterGrid.covering): here
  the box of every tile's own triangles' corners (`dem_grid`);
- a cell whose centre lies in a triangle holds the spline there: each tile samples the
  cells of its own triangles (`_sample_tile`) with the spline it refines for a mesh
  (survey.refine_runs.RefineJob.spline: the limiter's, or the smoothing's, data), and the
  parent writes them into one grid of heights on disk, in tile order (a cell on an edge
  of two tiles' triangles takes the later tile's value; the spline is continuous, so the
  two agree to rounding, as the in-memory sampler's two triangles do);
- a cell in no triangle that holds a fitted point holds the spline of the nearest
  triangle within reach (the trim's max_edge), continued linearly from its point closest
  to the centre: the cells holding points are marked in one pass over the points
  (`mark_points`); each tile finds, among its own triangles, the nearest to the marked
  cells still empty near them (`_continue_tile`, SplineSampler.continued); the nearest
  over the tiles is kept (equally near: the lower tile; the in-memory rule takes the
  lower triangle number, and both give the spline at the shared corner, to rounding);
- the support layer: each cell's distance to the nearest vertex of the spline, from the
  halo of the tile whose cell holds the centre (`_support_tile`; halos.HaloCache holds
  every vertex within 3 longest final edges of the cell, and a DEM cell's nearest vertex
  lies within 2 of them: its triangle's corners, or the continued triangle's, reach
  being max_edge);
- slope, aspect and hillshade from the spline's gradients (kept per cell) or Horn's
  differences of the heights (with the grid's one-cell ring, as the in-memory blocks
  sample it), written in blocks of rows by geo.raster.write_blocks, the in-memory writer;
- --preview from every s-th cell's height and spline gradient (`render_preview`), as the
  in-memory preview draws them (geo.preview.render_dem_cells);
- --contours traced on the nodes' local heights as the tiles sampled them (before the
  nearest-triangle rule, as the in-memory contours sample the spline without data
  points: `ContourNodes`) and snapped onto the tiles' splines (`TileSplines`), the
  same geo.contours.contour_heights the in-memory fit runs with its one spline.

The grids live in temporary files (memory maps) over the grid and its ring: heights
(float64), gradients (2 x float64, only for slope, aspect, hillshade or the preview), support
(float32, only with --support) and the point marks (uint8): 1 to 33 bytes a cell on
disk. Memory holds a tile's spline and a block of cells at a time.

The default fill (--fill hull) is the in-memory one: the tiles' triangles are the filled
triangulation (survey.hole_runs.TiledFill: the trimmed triangles first in each tile's
file, then those spanning the holes, DemJob.trimmed counts the first), limited over it,
and its halos read across the long triangles (far reads); the nearest-triangle rule
searches the trimmed triangles only, as SplineSampler's fill does; the preview hatches
the cells of the spanning triangles; a cell deep in a hole has its nearest vertex beyond
the halo, asked of the tiles within that distance (`_nearer_vertices`); --fill D drops
the spanning cells farther than D from every vertex (`TiledDem._fill_within`); a
smoothing fit's fill takes its data from survey.smoothing_runs.SmoothedFill.

--seamless -O DIR --suffix .tif writes one DEM per input from the same grids
(`InputWindows`): its window of the grid (`input_windows`, pipeline.driver.dem_windows'
rule) and the VRT mosaics, as pipeline.driver.fit_dem_tiles writes them in memory.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from c1mesh.core.lazy import LazyModule
from c1mesh.core.plan import DemPlan
from c1mesh.core.threads import limit
from c1mesh.core.tile import tile_rows
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.engine.topology import edge_table
from c1mesh.geo.raster import (
    BLOCK_CELLS,
    RasterStyle,
    RasterTargets,
    choose_slope_method,
    grid_facts,
    horn_gradient,
    write_blocks,
    write_input_rasters,
)
from c1mesh.geo.contours import ContourGrid, JoinedSurface, SplineSurface, contour_heights, spline_values
from c1mesh.geo.preview import DemCells, preview_stride, render_dem_cells
from c1mesh.geo.products import ContourRequest, stage_lines
from c1mesh.geo.raster_grid import RasterGrid, SplineSampler, rim_triangles, vertex_cells
from c1mesh.survey.refine_runs import lowest_points
from c1mesh.survey.tile_spill import file_blocks
from c1mesh.survey.tiles import task_row

spatial = LazyModule("scipy.spatial")

CELL = np.dtype([("cell", "<i8"), ("z", "<f8"), ("g", "<f8", 2), ("tri", "<i4"), ("span", "u1")])
"""A sampled cell in a tile's part file: its flat index in the grid with its ring
(DemGrid.flat), height (local: world z − the frame's origin z, which the parent adds, so
the contours trace the local heights the in-memory fit traces), the spline's gradient
(dz/dx, dz/dy) and the tile's triangle holding the centre (where the contours' search
starts, as the in-memory one starts from the node's triangle) and whether that triangle spans a hole (a fill's; the
preview hatches the cell)."""


DISTANCE = np.dtype([("cell", "<i8"), ("d", "<f8")])
"""A cell's distance to the nearest vertex of the spline, in a support task's file."""


@dataclass(frozen=True)
class DemGrid:
    """The DEM's grid (geo.raster_grid.RasterGrid, world units) and the frame's origin
    (3,); its cells with a ring of one cell around it are numbered row by row from the
    ring's north-west corner: grid cell (i, j), i, j from -1 to height, width, is flat
    (i + 1) * (width + 2) + j + 1."""

    grid: RasterGrid
    origin: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.height + 2, self.grid.width + 2

    def flat(self, ii: np.ndarray, jj: np.ndarray) -> np.ndarray:
        return (ii + 1) * (self.grid.width + 2) + (jj + 1)

    def centres(self, flat: np.ndarray) -> np.ndarray:
        """(m, 2) the local plane centres of the cells flat (m,), by the in-memory
        sampler's arithmetic (SplineSampler.cells)."""
        i, j = np.divmod(flat, self.grid.width + 2)
        r = self.grid.resolution
        x0, y0 = self.grid.west - self.origin[0], self.grid.north - self.origin[1]
        return np.column_stack([x0 + (j - 1 + 0.5) * r, y0 - (i - 1 + 0.5) * r])

    def span(self, lo, hi, margin: float) -> tuple[range, range]:
        """The rows and columns (grid indices, -1 to height or width: the ring included)
        of the cells whose centres may lie in the local box lo..hi grown by margin."""
        r = self.grid.resolution
        x0, y0 = self.grid.west - self.origin[0], self.grid.north - self.origin[1]
        cols = (math.floor((lo[0] - margin - x0) / r - 0.5) - 1, math.ceil((hi[0] + margin - x0) / r - 0.5) + 1)
        rows = (math.floor((y0 - hi[1] - margin) / r - 0.5) - 1, math.ceil((y0 - lo[1] + margin) / r - 0.5) + 1)
        return (range(max(rows[0], -1), min(rows[1] + 1, self.grid.height + 1)),
                range(max(cols[0], -1), min(cols[1] + 1, self.grid.width + 1)))


def row_blocks(rows: range, width: int) -> list[range]:
    """rows cut into blocks of about BLOCK_CELLS cells of `width` columns."""
    step = max(1, BLOCK_CELLS // max(width, 1))
    return [range(start, min(start + step, rows.stop)) for start in range(rows.start, rows.stop, step)]


def dem_grid(mesh, resolution: float) -> DemGrid:
    """The DemGrid of the survey's spline at `resolution`: the aligned grid covering the
    bounding box of its vertices (world x, y), as geo.raster.dem_sampling covers the
    in-memory interpolator's points. mesh: the survey's refine_runs.TiledMesh."""
    lo, hi = vertex_box(mesh)
    origin = np.asarray(mesh.frame.origin, dtype=np.float64)
    return DemGrid(RasterGrid.covering(lo + origin[:2], hi + origin[:2], resolution), origin)


def vertex_box(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (2,) each: the box of the survey spline's vertices (local x, y). mesh: the
    survey's refine_runs.TiledMesh; each tile's own triangles' corners are read from the
    height spill (a tile at a time; a fill's long triangles' far corners too, mesh.far)."""
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for t, path in enumerate(mesh.files):
        if path is None:
            continue
        triangles = np.load(path)
        if not len(triangles):
            continue
        reach = mesh.buffers[t] * (1 + 1e-9)
        records, _ = mesh.heights.records_near(mesh.grid.grown(t, reach), mesh.far.get(t))
        corners = np.compress(np.isin(records["index"], triangles), records)
        xy = np.column_stack([corners["x"], corners["y"]])
        lo, hi = np.minimum(lo, xy.min(axis=0)), np.maximum(hi, xy.max(axis=0))
    return lo, hi


def mark_points(chunks, dem: DemGrid, path) -> np.memmap:
    """The point marks (uint8 memory map over the grid with its ring, at path): 1 where a
    cell holds one of the fitted points (chunks(): (world points (m, 3), _) in blocks),
    located as the in-memory sampler locates its data points (_RowSorted.cells: local
    x, y, a point on a cell's west or north edge in that cell)."""
    marks = np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=dem.shape)
    grid, r = dem.grid, dem.grid.resolution
    x0, y0 = grid.west - dem.origin[0], grid.north - dem.origin[1]
    for points, _ in chunks():
        xy = (points - dem.origin)[:, :2]
        xy = xy[np.isfinite(xy).all(axis=1)]
        ii = np.floor((y0 - xy[:, 1]) / r).astype(np.int64)
        jj = np.floor((xy[:, 0] - x0) / r).astype(np.int64)
        inside = (ii >= -1) & (ii <= grid.height) & (jj >= -1) & (jj <= grid.width)
        marks.reshape(-1)[dem.flat(ii[inside], jj[inside])] = 1
    return marks


@dataclass(frozen=True)
class _TileFiles:
    """A tile's temporary files: cells (CELL records of its triangles' cells) and spline
    (.npz of its interpolator's data, for the nearest-triangle pass)."""

    cells: object
    spline: object


@dataclass(frozen=True)
class DemSupport:
    """What a tiled DEM's cells are measured against: reach (the nearest-triangle rule's,
    the trim's max_edge; None: any distance), trimmed (a fill: per tile how many of its own
    triangles, the first rows of its file, the trim kept; the rest span its holes,
    survey.hole_runs.TiledFill; None: no fill), points (the height spill of the data a
    lattice fit fitted, survey.lattice_runs, to which the support and --fill D measure, as
    the in-memory fit's fit points are its data; None: the spline's vertices)."""

    reach: float | None = None
    trimmed: tuple | None = None
    points: object = None


class DemJob:
    """What every tile's DEM task shares (picklable; the files it names are read by the
    tasks): surfaces (refine_runs.RefineJob: each tile's spline), halos (halos.HaloCache
    of the trim, pruned), dem (DemGrid), longest (the longest final edge, frame units),
    gradients (whether slope, aspect or hillshade need the spline's gradients), threads
    per task, support (DemSupport: its reach, trimmed and points become the job's);
    heights_path, spans_path (the grids of heights and of the cells in triangles that span
    holes, for the support pass and --fill D's), set by TiledDem."""

    def __init__(self, surfaces, halos, dem: DemGrid, longest: float, gradients: bool, threads=None,
                 support: DemSupport = DemSupport()):
        self.surfaces, self.halos, self.dem, self.longest = surfaces, halos, dem, longest
        self.gradients, self.threads = gradients, threads
        self.reach, self.trimmed, self.points = support.reach, support.trimmed, support.points
        self.heights_path = self.spans_path = None

    def trimmed_rows(self, t: int, count: int) -> np.ndarray:
        """(count,) bool over tile t's own triangles: those the trim kept (every one
        without a fill)."""
        return np.arange(count) < (count if self.trimmed is None else self.trimmed[t])

    def spline(self, spline_path) -> RSDInterpolator:
        """The interpolator of a tile's own triangles saved by _sample_tile (local frame)."""
        with np.load(spline_path) as saved:
            points, triangles = saved["points"], saved["triangles"]
            return self._rows(saved, points, triangles, np.arange(triangles.shape[0]))

    def spline_part(self, spline_path, box) -> tuple[RSDInterpolator | None, np.ndarray]:
        """(the interpolator of those of a tile's own triangles whose corners' box meets
        `box` (lo, hi; local), None when none does; rows: their numbers in the tile's
        spline, ascending)."""
        with np.load(spline_path) as saved:
            points, triangles = saved["points"], saved["triangles"]
            meets = np.ones(triangles.shape[0], dtype=bool)
            for axis in range(2):
                a, b, c = (points[triangles[:, k], axis] for k in range(3))
                meets &= np.minimum(np.minimum(a, b), c) <= box[1][axis]
                meets &= np.maximum(np.maximum(a, b), c) >= box[0][axis]
            rows = np.flatnonzero(meets)
            return (self._rows(saved, points, triangles[rows], rows) if rows.size else None), rows

    def rim_part(self, spline_path) -> RSDInterpolator:
        """The interpolator of a tile's own triangles with a corner on their boundary
        (geo.raster_grid.rim_triangles), the only ones the nearest-triangle rule can
        choose: the continued cells need no spline of the tile's interior. With a fill,
        of the triangles the trim kept, which that rule searches (SplineSampler)."""
        with np.load(spline_path) as saved:
            points, triangles = saved["points"], saved["triangles"]
            rows = rim_triangles(edge_table(triangles, points.shape[0]), np.flatnonzero(saved["trimmed"]))
            return self._rows(saved, points, triangles[rows], rows)

    def _rows(self, saved, points: np.ndarray, triangles: np.ndarray, rows: np.ndarray) -> RSDInterpolator:
        """The interpolator of the saved spline's (points, its triangles) triangles `rows`
        (ascending; triangles: those rows). Each side keeps its saved edge direction (the
        file keeps each triangle's three, `sides`, so any subset gets its edges' without
        the whole tile's edge table), so they evaluate as the whole tile's do."""
        table = edge_table(triangles, points.shape[0])
        directions = np.zeros((table.edges.shape[0], 2))
        directions[table.tri_edge] = saved["sides"][rows]
        return RSDInterpolator(points, saved["values"], saved["gradients"], triangles=triangles,
                               scheme=self.surfaces.scheme, directions=directions, edge_table=table)


def _sample_tile(job: DemJob, t: int, files: _TileFiles) -> dict | None:
    """Sample the cells whose centres lie in tile t's own triangles (SplineSampler.cells,
    .evaluate) into its cells file, and save its spline; returns its report row (points,
    seconds, worker; triangles, area, box (lo, hi) of its corners, limited, turned,
    lifted, cells), or None for a tile without triangles."""
    start = time.perf_counter()
    triangles = np.load(job.surfaces.files[t])
    if not len(triangles):
        return None
    with limit(job.threads):
        interp, records, (limited, turned, lifted) = job.surfaces.spline(t, triangles)
        with open(files.spline, "wb") as out:
            np.savez(out, points=interp.points, values=interp.values, gradients=interp.gradients,
                     triangles=interp.triangles, sides=interp.directions[interp.edge_table.tri_edge],
                     trimmed=job.trimmed_rows(t, len(triangles)))
        sampler = SplineSampler(interp, job.dem.origin)
        spans = ~job.trimmed_rows(t, len(triangles))
        lo, hi = interp.points.min(axis=0), interp.points.max(axis=0)
        rows, cols = job.dem.span(lo, hi, 0.0)
        nodes = _NodeValues.of(interp, job.dem)
        count = 0
        with open(files.cells, "wb") as out:
            for block in row_blocks(rows, len(cols)):
                cell, tri, l0, l1, shift = sampler.cells(job.dem.grid, block, cols)
                i, j = np.divmod(cell, len(cols))
                flat = job.dem.flat(block.start + i, cols.start + j)
                values, grads = (sampler.evaluate(tri, l0, l1, job.gradients, shift) if nodes is None
                                 else nodes.at(flat, job.gradients))
                part = np.zeros(cell.size, CELL)
                part["cell"] = flat
                part["z"], part["tri"], part["span"] = values, tri, spans[tri]
                if grads is not None:
                    part["g"] = grads
                part.tofile(out)
                count += cell.size
    a, b, c = (interp.points[interp.triangles[:, k]] for k in range(3))
    u, v = b - a, c - a
    area = float(0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).sum())
    return {"triangles": len(triangles), "area": area, "box": (lo, hi), "limited": limited, "turned": turned,
            "lifted": lifted, "cells": count, **task_row(len(records), start)}



class _NodeValues:
    """A tile's spline whose vertices sit at the DEM's cell centres (geo.raster_grid.
    vertex_cells: a lattice fit at the DEM's resolution): its cells read the vertices'
    heights and gradients, as the in-memory fit's NodeCells does, instead of evaluating
    the spline there (the same numbers to rounding; these are the in-memory bits)."""

    def __init__(self, interp, flat: np.ndarray):
        self.interp, self.order = interp, np.argsort(flat, kind="stable")
        self.sorted = flat[self.order]

    @classmethod
    def of(cls, interp, dem: DemGrid) -> "_NodeValues | None":
        cells = vertex_cells(interp, dem.origin, dem.grid)
        return None if cells is None else cls(interp, dem.flat(*cells))

    def at(self, flat: np.ndarray, gradients: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """(heights (m,) local, gradients (m, 2) or None) of the cells flat (m,), each a vertex's."""
        at = np.minimum(np.searchsorted(self.sorted, flat), self.sorted.size - 1)
        if not np.array_equal(self.sorted[at], flat):
            raise RuntimeError("a DEM cell in a triangle of a lattice tile is no vertex's")
        vertex = self.order[at]
        return self.interp.values[vertex], self.interp.gradients[vertex] if gradients else None

def _mark_spans(spans: np.ndarray, part: np.ndarray) -> None:
    """Mark the sampled cells of part (CELL records) in the flat spans grid: bit 1 where a
    triangle that spans a hole holds the centre, bit 2 where a triangle the trim kept does.
    A cell whose value is 1 lies in spanning triangles only: the in-memory fill's rule
    (SplineSampler.cells drops a far centre's spanning entries, and a kept triangle's
    entry still gives it a height), whatever the order the tiles and triangles come in."""
    cells, span = part["cell"], part["span"].astype(bool)
    spans[cells[span]] = spans[cells[span]] | 1
    spans[cells[~span]] = spans[cells[~span]] | 2

def _continue_tile(job: DemJob, spline_path, cells: np.ndarray):
    """For the cells (flat) that hold points but lie in no triangle: the nearest of a tile's
    own triangles (its spline at spline_path) within the reach, the spline continued from
    it (SplineSampler.continued, .evaluate). Returns (cells (k,), distance (k,), height (k,), gradient (k, 2)) of those
    that have one."""
    with limit(job.threads):
        sampler = SplineSampler(job.rim_part(spline_path), job.dem.origin, reach=job.reach)
        has, tri, l0, l1, shift = sampler.continued(job.dem.centres(cells))
        values, grads = sampler.evaluate(tri, l0, l1, True, shift)
    return cells[has], np.hypot(shift[:, 0], shift[:, 1]), values + sampler.origin[2], grads


def _support_tile(job: DemJob, t: int, path, spanning: bool = False) -> int:
    """The support of the cells with a height whose centres lie in tile t's cell (the
    tile grid's tile_of): the distance to the nearest vertex of the spline, by a k-d tree
    of the tile's halo (module docstring), as SplineSampler.distances measures it; a cell
    whose nearest vertex there lies beyond 3 longest edges (in a fill's long triangle)
    asks the tiles within that distance (_nearer_vertices). spanning: of the cells in
    triangles that span holes only (job.spans_path; --fill D). Writes (flat cell int64,
    distance float64) pairs to path; returns how many."""
    dem, grid = job.dem, job.surfaces.grid
    heights = np.load(job.heights_path, mmap_mode="r").reshape(-1)
    spans = np.load(job.spans_path, mmap_mode="r").reshape(-1) if spanning else None
    count, bound = 0, 3 * job.longest * (1 + 1e-9)
    near = halo_vertices(job.halos.halo(t)) if job.points is None else job.points.records(grid.grown(t, bound))
    tree = spatial.cKDTree(np.column_stack([near["x"], near["y"]])) if len(near) else None
    nx, ny = grid.nx, grid.ny
    i, j = t % nx, t // nx
    x0, y0, x1, y1 = grid.cell(t)
    lo = np.array([-np.inf if i == 0 else x0, -np.inf if j == 0 else y0])
    hi = np.array([np.inf if i == nx - 1 else x1, np.inf if j == ny - 1 else y1])
    rows, cols = dem.span(np.maximum(lo, -1e300), np.minimum(hi, 1e300), 0.0)
    with limit(job.threads), open(path, "wb") as out:
        for block in row_blocks(rows, len(cols)):
            ii, jj = np.divmod(np.arange(len(block) * len(cols)), len(cols))
            flat = dem.flat(block.start + ii, cols.start + jj)
            flat = flat[np.isfinite(heights[flat]) if spans is None else np.isfinite(heights[flat]) & (spans[flat] == 1)]
            centre = dem.centres(flat)
            mine = grid.tile_of(centre) == t
            flat, centre = flat[mine], centre[mine]
            if not flat.size:
                continue
            if tree is None and job.points is None:
                raise RuntimeError(f"tile {t}: DEM cells with heights but no vertex in its halo")
            distance = tree.query(centre)[0] if tree is not None else np.full(flat.size, np.inf)
            beyond = np.flatnonzero(distance > bound)      # in a fill's long triangles: search wider
            if beyond.size:
                distance[beyond] = _nearer_vertices(job, centre[beyond], distance[beyond])
            pairs = np.zeros(flat.size, DISTANCE)
            pairs["cell"], pairs["d"] = flat, distance
            pairs.tofile(out)
            count += flat.size
    return count


def _nearer_vertices(job: DemJob, centres: np.ndarray, found: np.ndarray) -> np.ndarray:
    """The distances (m,) from local plane points centres (m, 2) to the nearest vertex of
    the spline, given a vertex at `found` (m,) from each (inf: none yet): the vertices of
    every tile whose cell meets a centre's square of that half-side, each tile's own from
    its halo (a vertex's triangles are all in its tile's halo); with job.points, to the
    nearest data point, each tile's own from the spill."""
    grid, best = job.surfaces.grid, found.copy()
    for u in range(len(grid)):
        x0, y0, x1, y1 = grid.cell(u)
        near = np.flatnonzero((centres[:, 0] + found >= x0) & (centres[:, 0] - found <= x1)
                              & (centres[:, 1] + found >= y0) & (centres[:, 1] - found <= y1))
        if not near.size or (job.points is None and job.surfaces.files[u] is None):
            continue
        if job.points is not None:                          # a lattice fit's data: the tile's own
            vertices = job.points.tile(u)
        else:
            vertices = halo_vertices(job.halos.halo(u))
            vertices = vertices[grid.tiles_of(vertices["x"], vertices["y"]) == u]
        if not len(vertices):
            continue
        tree = spatial.cKDTree(np.column_stack([vertices["x"], vertices["y"]]))
        reach = float(found[near].max()) * (1 + 1e-9)
        distance = tree.query(centres[near], distance_upper_bound=reach if math.isfinite(reach) else np.inf)[0]
        best[near] = np.minimum(best[near], distance)
    return best


def halo_vertices(halo) -> np.ndarray:
    """The records of a halo (core.tile.Tile) that its triangles use: the spline's
    vertices (the cached halo keeps the points of triangles the trim removed since it was
    read)."""
    return halo.records.take(np.unique(halo.triangles)) if len(halo.triangles) else halo.records[:0]


class TiledDem:
    """The schedule of a tiled DEM (module docstring): construct with the DemJob, temps
    (inputs.Temps), runner (distributed.TaskRunner), rows (task_rows.TileRows) and the
    stage its tasks are booked under; `write` runs the passes and writes the rasters, and
    a mesh's preview and contours (pipeline.bounded_fit) sample their grids by `cells` and
    `contours`. windows: --seamless -O's DEMs, one per input (InputWindows; None: one DEM,
    the plan's)."""

    def __init__(self, job: DemJob, temps, runner, rows, stage: str = "dem", windows: "InputWindows | None" = None):
        self.job, self.temps, self.runner, self.rows, self.stage = job, temps, runner, rows, stage
        self.windows = windows

    def write(self, plan: DemPlan, chunks, crs: str | None, smoothed: bool,
              contours: ContourRequest | None = None) -> dict:
        """Sample every tile, continue the spline into the marked cells, trace the contours
        (contours: the request, its CRS resolved; None: none), measure the support, and
        write plan's rasters (geo.raster.write_blocks); the contour file is committed once
        the rasters are written. Returns {"kept", "triangles_per_tile", "raster",
        "contours" (the report's section or None), counts of the limiter}."""
        facts = self._write(plan, chunks, crs, smoothed, contours)
        staged = facts.pop("staged")
        if staged is not None:
            staged.commit()
        return facts

    def _write(self, plan: DemPlan, chunks, crs: str | None, smoothed: bool, contours) -> dict:
        """write's passes; the contours staged (geo.contour_file.StagedContours) in "staged"."""
        grids = self._sampled(contours is not None)
        if plan.fill is not None and math.isfinite(plan.fill):
            self._fill_within(grids, plan.fill)
        marks = mark_points(chunks, self.job.dem, self.temps.new("dem-marks.npy"))
        self._continue(grids.sampled, grids.files, grids.heights, grids.gradients, marks)
        staged, contour_facts = None, None
        try:
            if contours is not None:
                staged, contour_facts = self._trace(grids, contours)
            grids.drop_tile_files()
            return self._finish(plan, grids, crs, smoothed) | {"staged": staged, "contours": contour_facts}
        except BaseException:
            if staged is not None:
                staged.discard()
            raise

    def contours(self, request: ContourRequest):
        """A mesh's contours (its grid: the job's DemGrid) traced on the cells the tiles
        sample, as `write` traces a DEM's: (the StagedContours, the report's section)."""
        grids = self._sampled(True)
        try:
            return self._trace(grids, request)
        finally:
            grids.drop_tile_files()

    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        """(heights (h, w) world z, gradients (h, w, 2)) at the centres of the job's grid
        inside the tiles' triangles, NaN elsewhere: a mesh's preview (geo.preview.SplineView)."""
        grids = self._sampled(False)
        grids.drop_tile_files()
        return np.array(grids.heights[1:-1, 1:-1]), np.array(grids.gradients[1:-1, 1:-1])

    def _sampled(self, nodes: bool) -> "_Grids":
        """Every tile's cells sampled into the grids on disk (_sample): heights, gradients
        when the job asks for them, the contours' nodes when `nodes`."""
        job, shape = self.job, self.job.dem.shape
        path = self.temps.new("dem-heights.npy")
        heights = np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=shape)
        for block in row_blocks(range(shape[0]), shape[1]):
            heights[block.start:block.stop] = np.nan
        gradients = None
        if job.gradients:
            gradients = np.lib.format.open_memmap(self.temps.new("dem-gradients.npy"), mode="w+",
                                                  dtype=np.float64, shape=shape + (2,))
        tiles = [t for t in range(len(job.surfaces.grid)) if job.surfaces.files[t] is not None]
        files = {t: _TileFiles(self.temps.new(f"dem-cells-{t}.bin"), self.temps.new(f"dem-spline-{t}.npz"))
                 for t in tiles}
        contour_nodes = ContourNodes.empty(shape) if nodes else None
        spans, spans_path = None, None  # a fill: the cells in triangles that span holes (hatched)
        if job.trimmed is not None:
            spans_path = self.temps.new("dem-spans.npy")
            spans = np.lib.format.open_memmap(spans_path, mode="w+", dtype=np.uint8, shape=shape)
        sampled = self._sample(tiles, files, (heights, gradients, contour_nodes, spans))
        return _Grids(path, heights, gradients, contour_nodes, tiles, files, sampled, spans, spans_path)

    def _trace(self, grids: "_Grids", request: ContourRequest):
        """(StagedContours, report section) of the contours through grids' nodes, snapped
        onto the tiles' splines (TileSplines)."""
        job, dem, start = self.job, self.job.dem, time.perf_counter()
        splines = TileSplines(job, {t: grids.files[t].spline for t in grids.sampled},
                              {t: row["box"] for t, row in grids.sampled.items()}, grids.nodes)
        lines = contour_heights(grids.nodes.heights[1:-1, 1:-1], ContourGrid.of_raster(dem.grid, dem.origin),
                                request.interval, splines)
        return stage_lines(request, lines, dem.grid, start)

    def _finish(self, plan: DemPlan, grids: "_Grids", crs: str | None, smoothed: bool) -> dict:
        """The support pass and the rasters' writing, from the grids the tiles filled;
        write's facts."""
        job, dem = self.job, self.job.dem
        heights, gradients = grids.heights, grids.gradients
        tiles, sampled = grids.tiles, grids.sampled
        heights.flush()
        support = self._support(tiles, grids.path, dem.shape) if plan.support else None
        area = sum(row["area"] for row in sampled.values())
        kept = sum(_own_vertices(self.job.halos.halo(t)) for t in tiles)
        spacing = float(math.sqrt(area / kept))
        method = choose_slope_method(plan.slope_method, plan.resolution, spacing, smoothed)
        style = RasterStyle(method, crs, "float32", 1.0 if plan.z_factor is None else float(plan.z_factor))
        method = method if job.gradients else None
        if self.windows is not None:       # --seamless -O: a DEM per input, and the mosaics
            raster = self.windows.write(dem, (heights, gradients, support), method, style)
        else:
            targets = RasterTargets(plan.dem, plan.slope, plan.aspect, plan.hillshade, plan.support)
            raster = write_blocks(targets, dem.grid, grid_blocks(dem, heights, gradients, support, method), style)
            raster["point_spacing"] = spacing
        if plan.preview:
            render_preview(dem, (heights, gradients, grids.spans), plan, crs)
        if job.trimmed is not None:         # the report's fill facts (pipeline.bounded_fit.tiles_report)
            raster["fill"] = {"triangles_spanning_holes": sum(row["triangles"] - job.trimmed[t]
                                                              for t, row in sampled.items())}
        return {"kept": kept, "raster": raster,
                "triangles_per_tile": {t: row["triangles"] for t, row in sampled.items()},
                **{k: sum(row[k] for row in sampled.values()) for k in ("limited", "turned", "lifted")}}

    def _sample(self, tiles, files, grids) -> dict:
        """Every tile's _sample_tile, its cells written into the grids in tile order: grids
        (heights (world z), gradients or None, local heights for the contours or None),
        each over the grid with its ring."""
        rows, ready, sampled, next_tile = self.rows, {}, {}, 0
        heights, gradients, nodes, spans = grids
        flat_heights, oz = heights.reshape(-1), self.job.dem.origin[2]
        flat_gradients = None if gradients is None else gradients.reshape(-1, 2)
        for i, row in self.runner.map(_sample_tile, len(tiles), lambda i: (self.job, tiles[i], files[tiles[i]]),
                                      lambda i: rows.name(tiles[i])):
            ready[i] = row
            while next_tile in ready:
                t, row = tiles[next_tile], ready.pop(next_tile)
                next_tile += 1
                if row is None:
                    continue
                sampled[t] = row
                with open(files[t].cells, "rb") as file:        # the tile's CELL records, in blocks
                    for part in file_blocks(file, CELL, 1 << 16):
                        flat_heights[part["cell"]] = part["z"] + oz
                        if nodes is not None:
                            nodes.add(t, part)
                        if flat_gradients is not None:
                            flat_gradients[part["cell"]] = part["g"]
                        if spans is not None:          # 1: in spanning triangles only (as in memory)
                            _mark_spans(spans.reshape(-1), part)
                rows.add(t, self.stage, {k: row[k] for k in ("seconds", "worker", "worker_peak_mb")})
        return sampled

    def _continue(self, sampled: dict, files, heights, gradients, marks) -> None:
        """The nearest-triangle rule over the tiles: the marked cells still without a
        height, each tile's nearest own triangle to those near its triangles
        (_continue_tile), the nearest over the tiles kept."""
        flat_heights, flat_marks = heights.reshape(-1), marks.reshape(-1)
        open_cells = []
        for block in row_blocks(range(heights.shape[0]), heights.shape[1]):
            start, stop = block.start * heights.shape[1], block.stop * heights.shape[1]
            open_cells.append(start + np.flatnonzero((flat_marks[start:stop] == 1)
                                                     & ~np.isfinite(flat_heights[start:stop])))
        cells = np.concatenate(open_cells)
        if not cells.size:
            return
        centres = self.job.dem.centres(cells)
        reach = math.inf if self.job.reach is None else self.job.reach * (1 + 1e-9)
        tiles = list(sampled)
        asked = []
        for t in tiles:
            lo, hi = sampled[t]["box"]
            asked.append(cells[((centres >= lo - reach) & (centres <= hi + reach)).all(axis=1)])
        found = [part for _, part in sorted(self.runner.map(
            _continue_tile, len(tiles), lambda i: (self.job, files[tiles[i]].spline, asked[i]),
            lambda i: self.rows.name(tiles[i])), key=lambda item: item[0])]
        cell = np.concatenate([f[0] for f in found])
        if not cell.size:
            return
        distance = np.concatenate([f[1] for f in found])
        order = np.lexsort((np.repeat(np.arange(len(found)), [len(f[0]) for f in found]), distance, cell))
        first = np.ones(order.size, dtype=bool)
        first[1:] = cell[order[1:]] != cell[order[:-1]]
        best = order[first]
        flat_heights[cell[best]] = np.concatenate([f[2] for f in found])[best]
        if gradients is not None:
            gradients.reshape(-1, 2)[cell[best]] = np.concatenate([f[3] for f in found])[best]

    def _fill_within(self, grids: "_Grids", distance: float) -> None:
        """--fill D: the cells in triangles that span holes whose centres lie farther than
        D (local units) from every vertex of the spline lose their heights, as the
        in-memory sampler's FillRule drops them (before the nearest-triangle rule; the
        contours' nodes keep them, as the in-memory contours do)."""
        grids.heights.flush()
        grids.spans.flush()
        self.job.heights_path, self.job.spans_path = grids.path, grids.spans_path
        tiles = grids.tiles
        paths = {t: self.temps.new(f"dem-fill-{t}.bin") for t in tiles}
        flat_heights, flat_spans = grids.heights.reshape(-1), grids.spans.reshape(-1)
        for i, _ in self.runner.map(_support_tile, len(tiles), lambda i: (self.job, tiles[i], paths[tiles[i]], True),
                                    lambda i: self.rows.name(tiles[i])):
            pairs = np.fromfile(paths[tiles[i]], dtype=DISTANCE)
            far = pairs["cell"][pairs["d"] > distance]
            flat_heights[far], flat_spans[far] = np.nan, 0
            if grids.gradients is not None:
                grids.gradients.reshape(-1, 2)[far] = np.nan
            paths[tiles[i]].unlink()

    def _support(self, tiles, heights_path, shape) -> np.memmap:
        """The support grid (float32 memory map, NaN where no height), from every tile's
        _support_tile."""
        self.job.heights_path = heights_path
        support = np.lib.format.open_memmap(self.temps.new("dem-support.npy"), mode="w+", dtype=np.float32,
                                            shape=shape)
        for block in row_blocks(range(shape[0]), shape[1]):
            support[block.start:block.stop] = np.nan
        paths = {t: self.temps.new(f"dem-support-{t}.bin") for t in tiles}
        flat = support.reshape(-1)
        for i, _ in self.runner.map(_support_tile, len(tiles), lambda i: (self.job, tiles[i], paths[tiles[i]]),
                                    lambda i: self.rows.name(tiles[i])):
            with open(paths[tiles[i]], "rb") as file:
                pairs = np.fromfile(file, dtype=DISTANCE)
            flat[pairs["cell"]] = pairs["d"]
            paths[tiles[i]].unlink()
        return support


@dataclass(frozen=True)
class _Grids:
    """What TiledDem._sampled leaves: the heights' file path and memory map, the gradients'
    (or None), the contours' nodes (or None), the tiles with a triangle file, their
    temporary files, the sampled tiles' rows (_sample_tile's) and, with a fill, which
    cells span a hole (uint8 memory map over the grid with its ring; else None)."""

    path: object
    heights: np.ndarray
    gradients: np.ndarray | None
    nodes: "ContourNodes | None"
    tiles: list
    files: dict
    sampled: dict
    spans: np.ndarray | None = None
    spans_path: object = None

    def drop_tile_files(self) -> None:
        """Remove the tiles' cells and spline files (the grids stay)."""
        for t in self.tiles:
            self.files[t].cells.unlink(missing_ok=True)
            self.files[t].spline.unlink(missing_ok=True)


@dataclass(frozen=True)
class ContourNodes:
    """The contours' grid nodes as the tiles sampled them, over the grid with its ring
    (in memory: 16 bytes a cell): heights (local, NaN outside every triangle), tile and
    triangle (the tile's own triangle holding the node, −1 none)."""

    heights: np.ndarray
    tile: np.ndarray
    triangle: np.ndarray

    @classmethod
    def empty(cls, shape: tuple[int, int]) -> "ContourNodes":
        return cls(np.full(shape, np.nan), np.full(shape, -1, np.int32), np.full(shape, -1, np.int32))

    def add(self, t: int, part: np.ndarray) -> None:
        """Tile t's sampled CELL records."""
        self.heights.reshape(-1)[part["cell"]] = part["z"]
        self.tile.reshape(-1)[part["cell"]] = t
        self.triangle.reshape(-1)[part["cell"]] = part["tri"]


class TileSplines:
    """The splines the contours snap onto (geo.contours.contour_heights; OneSpline's
    interface) when a survey is fitted in tiles: each tile's own triangles' interpolator,
    saved by _sample_tile (splines: tile → .npz; boxes: tile → the (lo, hi) box of its
    spline's vertices, local frame).

    `values` asks the tiles whose box holds a point, in tile order, the first that has a
    triangle there giving the value. `patches` groups the traced vertices by the tile
    holding their grid edge's first node, and gives each group the JoinedSurface of the
    tiles whose boxes meet its edges' box: the tile's own spline and, of its neighbours',
    the triangles that meet the box. Each tile's spline is built three times (its patch
    and the two `values` passes); memory holds a tile's spline and the neighbours' parts."""

    MARGIN = 1e-9
    """Relative growth of the boxes' tests (a point on a triangle's side, to rounding)."""

    def __init__(self, job: DemJob, splines: dict, boxes: dict, nodes: ContourNodes):
        self.job, self.splines, self.boxes, self.nodes = job, splines, boxes, nodes
        self.tiles = sorted(splines)

    def _meeting(self, lo: np.ndarray, hi: np.ndarray) -> list:
        """The tiles whose boxes meet the box lo..hi (local)."""
        return [t for t in self.tiles if (self.boxes[t][0] <= hi).all() and (self.boxes[t][1] >= lo).all()]

    def _grown(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The box of the points xy (m, 2), grown by MARGIN of its coordinates' size."""
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        grow = self.MARGIN * max(1.0, float(np.abs(np.concatenate([lo, hi])).max()))
        return lo - grow, hi + grow

    def _groups(self, xy: np.ndarray):
        """(tile, members) per tile of the tile grid holding some of the points xy (m, 2),
        in tile order: the tile and the points' indices."""
        owner = self.job.surfaces.grid.tile_of(xy)
        for t in np.unique(owner):
            yield int(t), np.flatnonzero(owner == t)

    def _parts(self, t: int, box) -> list:
        """(tile, interpolator, rows) of the tiles whose boxes meet `box`: tile t's whole
        spline (rows: all of its triangles), the others' on the box (DemJob.spline_part)."""
        parts = []
        for u in self._meeting(*box):
            if u == t:
                interp = self.job.spline(self.splines[u])
                parts.append((u, interp, np.arange(interp.triangles.shape[0])))
                continue
            interp, rows = self.job.spline_part(self.splines[u], box)
            if interp is not None:
                parts.append((u, interp, rows))
        return parts

    def values(self, xy: np.ndarray) -> np.ndarray:
        """The spline at local points xy (M, 2), NaN outside every tile's triangles: by the
        first tile, in tile order, that has a triangle there (each tile's spline built once)."""
        out = np.full(xy.shape[0], np.nan)
        if not xy.shape[0]:
            return out
        for t in self._meeting(*self._grown(xy)):
            lo, hi = self.boxes[t]
            ask = np.flatnonzero(np.isnan(out) & (xy >= lo).all(axis=1) & (xy <= hi).all(axis=1))
            if ask.size:
                out[ask] = spline_values(self.job.spline(self.splines[t]), xy[ask])
        return out

    def patches(self, grid: ContourGrid, edges):
        """(vertices, JoinedSurface, hints) per tile holding vertices' first nodes: the
        parts are the splines of the tiles meeting the box of those vertices' edges."""
        start = grid.local(edges.a[:, 1].astype(np.float64), edges.a[:, 0].astype(np.float64))
        end = grid.local(edges.b[:, 1].astype(np.float64), edges.b[:, 0].astype(np.float64))
        near = np.where((edges.t0 < 0.5)[:, None], edges.a, edges.b) + 1      # the nearer node, in the ring
        near_tile = self.nodes.tile[near[:, 0], near[:, 1]]
        near_triangle = self.nodes.triangle[near[:, 0], near[:, 1]].astype(np.int64)
        for t, members in self._groups(start):
            parts = self._parts(t, self._grown(np.concatenate([start[members], end[members]])))
            surface = JoinedSurface([SplineSurface(interp, SplineSampler(interp, self.job.dem.origin))
                                     for _, interp, _ in parts])
            yield members, surface, self._hints(parts, surface, near_tile[members], near_triangle[members])

    @staticmethod
    def _hints(parts: list, surface: JoinedSurface, tile: np.ndarray, triangle: np.ndarray) -> np.ndarray:
        """The JoinedSurface's numbers of the nodes' triangles (tile, triangle: the tile's
        own numbering; −1 where the node has none, or its tile or triangle is not a part's)."""
        hint = np.full(tile.size, -1, np.int64)
        for k, (u, _, rows) in enumerate(parts):
            mine = np.flatnonzero((tile == u) & (triangle >= 0))
            if not rows.size:
                continue
            at = np.minimum(np.searchsorted(rows, triangle[mine]), rows.size - 1)
            held = rows[at] == triangle[mine]
            hint[mine[held]] = surface.offsets[k] + at[held]
        return hint


@dataclass(frozen=True)
class InputWindows:
    """--seamless -O DIR --suffix .tif beyond --memory: one DEM per input, a window of the
    survey's grid, as pipeline.driver.fit_dem_tiles writes them in memory. outputs: the
    inputs' DEM paths; targets: each input's geo.raster.RasterTargets (tile_targets);
    windows: each input's window of the grid (None: no cell, no DEM; input_windows);
    mosaics: {kind: the VRT mosaic path} (geo.raster.mosaic_paths)."""

    outputs: list
    targets: list
    windows: list
    mosaics: dict

    def write(self, dem: DemGrid, grids, method: str | None, style: RasterStyle) -> dict:
        """Write each input's rasters from the grids on disk (heights, gradients, support,
        each with the ring) and the mosaics; the report's raster section (grid, mosaics,
        tiles). On failure every file already written is removed."""
        heights, gradients, support = grids
        tiles = write_input_rasters(
            self.outputs, self.targets, self.windows,
            lambda targets, window: write_blocks(targets, window, grid_blocks(dem, heights, gradients, support,
                                                                               method, window), style),
            dem.grid, self.mosaics, style.crs)
        return {"grid": grid_facts(dem.grid), "mosaics": self.mosaics, "tiles": tiles}


def input_windows(job: DemJob, chunks, owners, inputs: int) -> list:
    """Per input, the window of the DEM grid its DEM covers (pipeline.driver.dem_windows'
    rule: the cells holding its points, chunks() giving the survey's world points in
    blocks, and those of the boxes of the triangles it owns, the input of their
    lowest-numbered corner by owners, split_outputs.InputOwners), or None."""
    lo, hi = np.full((inputs, 2), np.inf), np.full((inputs, 2), -np.inf)

    def extend(which: np.ndarray, xy: np.ndarray) -> None:
        for i in np.unique(which).tolist():
            mine = xy[which == i]
            lo[i], hi[i] = np.minimum(lo[i], mine.min(axis=0)), np.maximum(hi[i], mine.max(axis=0))
    start = 0
    for points, _ in chunks():
        extend(owners.of(np.arange(start, start + len(points))), points[:, :2])
        start += len(points)
    origin = job.dem.origin[:2]
    for t, path in enumerate(job.surfaces.files):
        triangles = np.load(path) if path is not None else np.empty((0, 3), np.int64)
        if not len(triangles):
            continue
        records = job.halos.halo(t).records
        rows = tile_rows(records["index"], triangles)
        xy = np.column_stack([records["x"], records["y"]])[rows] + origin      # (k, 3, 2) world
        extend(np.repeat(owners.of(lowest_points(records, triangles)[:, 0]), 3), xy.reshape(-1, 2))
    return [job.dem.grid.window_over(lo[i], hi[i]) if np.isfinite(lo[i]).all() else None for i in range(inputs)]


def render_preview(dem: DemGrid, grids, plan: DemPlan, crs: str | None) -> None:
    """The DEM's --preview (plan.preview) from the cells the tiles sampled: every stride-th
    cell of the grid (geo.preview.preview_stride; not the ring), heights rounded to float32
    as the DEM stores them, shaded by the spline's gradient there, so the picture is the
    in-memory fit's (geo.preview.render_dem_cells); at most PIXELS² cells are read from the
    memory maps. grids: (heights, gradients, spans: the fill's cells in triangles that
    span holes, hatched, or None: no fill, none is)."""
    heights, gradients, spans = grids
    grid = dem.grid
    stride = preview_stride(grid)
    rows, cols = slice(1, grid.height + 1, stride), slice(1, grid.width + 1, stride)
    z = np.asarray(heights[rows, cols]).astype(np.float32).astype(np.float64)
    g = np.array(gradients[rows, cols])
    g[np.isnan(z)] = np.nan
    hatched = None if spans is None else (np.asarray(spans[rows, cols]) == 1) & np.isfinite(z)
    render_dem_cells(DemCells(z, g, hatched), grid, stride, plan.preview, crs, 1.0 if plan.z_factor is None else plan.z_factor)


def _own_vertices(halo) -> int:
    """How many of the spline's vertices lie in the halo's tile's cell (each vertex is
    counted by one tile: the survey's count is their sum)."""
    used = np.zeros(len(halo.own), dtype=bool)           # a mask, not a sort of 3T corners
    used[halo.triangles.ravel()] = True
    return int(np.count_nonzero(used & halo.own))


def grid_blocks(dem: DemGrid, heights, gradients, support, method: str | None, window: RasterGrid | None = None):
    """geo.raster.write_blocks' blocks of the grid's rows from the grids on disk (each with
    the ring): heights; gradients (Horn's differences of the heights with the ring, the
    spline's gradient where a neighbour is nodata, as geo.raster.grid_blocks does; or the
    spline's, method "spline"; None: heights only); support distances (None: none).
    window: a window of the grid (RasterGrid.window; None: the whole grid), its rows
    counted from its first, Horn's differences taken with the grid's cells around it."""
    grid = dem.grid if window is None else window
    row0, col0 = (0, 0) if window is None else (window.row0, window.col0)
    cols = slice(col0 + 1, col0 + grid.width + 1)
    step = max(1, min(256, BLOCK_CELLS // grid.width))
    for start in range(0, grid.height, step):
        rows = range(start, min(start + step, grid.height))
        inner = slice(row0 + rows.start + 1, row0 + rows.stop + 1)
        z = np.asarray(heights[inner, cols])
        g = None
        if method == "spline":
            g = np.asarray(gradients[inner, cols])
        elif method == "horn":
            g = horn_gradient(np.asarray(heights[row0 + rows.start:row0 + rows.stop + 2,
                                                 col0:col0 + grid.width + 2]), grid.resolution)
            edge = np.isfinite(z) & ~np.isfinite(g).all(axis=2)
            g[edge] = np.asarray(gradients[inner, cols])[edge]
        d = None if support is None else np.asarray(support[inner, cols], dtype=np.float64)
        yield rows, z, g, d
