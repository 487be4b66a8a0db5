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
  in-memory preview draws them (geo.preview.render_dem_cells).

The grids live in temporary files (memory maps) over the grid and its ring: heights
(float64), gradients (2 x float64, only for slope, aspect, hillshade or the preview), support
(float32, only with --support) and the point marks (uint8): 1 to 33 bytes a cell on
disk. Memory holds a tile's spline and a block of cells at a time.

Only --fill off is done in tiles (survey.sizing.needs_tiles refuses the fill): the
in-memory fill spans the holes with the triangles the trim removed, limited over the
filled triangulation, which the tiles do not keep.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from c1mesh.core.plan import DemPlan
from c1mesh.core.threads import limit
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.geo.raster import (
    BLOCK_CELLS,
    RasterStyle,
    RasterTargets,
    choose_slope_method,
    horn_gradient,
    write_blocks,
)
from c1mesh.geo.preview import DemCells, preview_stride, render_dem_cells
from c1mesh.geo.raster_grid import RasterGrid, SplineSampler
from c1mesh.survey.tiles import task_row

CELL = np.dtype([("cell", "<i8"), ("z", "<f8"), ("g", "<f8", 2)])
"""A sampled cell in a tile's part file: its flat index in the grid with its ring
(DemGrid.flat), height (world z) and the spline's gradient (dz/dx, dz/dy)."""


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
    in-memory interpolator's points. mesh: the survey's refine_runs.TiledMesh; each tile's
    own triangles' corners are read from the height spill (a tile at a time)."""
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for t, path in enumerate(mesh.files):
        if path is None:
            continue
        triangles = np.load(path)
        if not len(triangles):
            continue
        records = mesh.heights.records(mesh.grid.grown(t, mesh.buffers[t] * (1 + 1e-9)))
        corners = np.compress(np.isin(records["index"], triangles), records)
        xy = np.column_stack([corners["x"], corners["y"]])
        lo, hi = np.minimum(lo, xy.min(axis=0)), np.maximum(hi, xy.max(axis=0))
    origin = np.asarray(mesh.frame.origin, dtype=np.float64)
    return DemGrid(RasterGrid.covering(lo + origin[:2], hi + origin[:2], resolution), origin)


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


class DemJob:
    """What every tile's DEM task shares (picklable; the files it names are read by the
    tasks): surfaces (refine_runs.RefineJob: each tile's spline), halos (halos.HaloCache
    of the trim, pruned), dem (DemGrid), reach (the nearest-triangle rule's, the trim's
    max_edge; None: any distance), longest (the longest final edge, frame units), gradients
    (whether slope, aspect or hillshade need the spline's gradients), threads per task,
    heights_path (the grid of heights, for the support pass)."""

    def __init__(self, surfaces, halos, dem: DemGrid, reach: float | None, longest: float, gradients: bool,
                 threads=None):
        self.surfaces, self.halos, self.dem, self.reach, self.longest = surfaces, halos, dem, reach, longest
        self.gradients, self.threads = gradients, threads
        self.heights_path = None

    def sampler(self, spline_path) -> SplineSampler:
        """The SplineSampler of a tile's spline saved by _sample_tile (no data points: the
        nearest-triangle rule is asked through SplineSampler.continued)."""
        with np.load(spline_path) as saved:
            interp = RSDInterpolator(saved["points"], saved["values"], saved["gradients"],
                                     triangles=saved["triangles"], scheme=self.surfaces.scheme,
                                     directions=saved["directions"])
        return SplineSampler(interp, self.dem.origin, reach=self.reach)


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
                     triangles=interp.triangles, directions=interp.directions)
        sampler = SplineSampler(interp, job.dem.origin)
        lo, hi = interp.points.min(axis=0), interp.points.max(axis=0)
        rows, cols = job.dem.span(lo, hi, 0.0)
        count = 0
        with open(files.cells, "wb") as out:
            for block in row_blocks(rows, len(cols)):
                cell, tri, l0, l1, shift = sampler.cells(job.dem.grid, block, cols)
                values, grads = sampler.evaluate(tri, l0, l1, job.gradients, shift)
                i, j = np.divmod(cell, len(cols))
                part = np.zeros(cell.size, CELL)
                part["cell"] = job.dem.flat(block.start + i, cols.start + j)
                part["z"] = values + sampler.origin[2]
                if grads is not None:
                    part["g"] = grads
                part.tofile(out)
                count += cell.size
    a, b, c = (interp.points[interp.triangles[:, k]] for k in range(3))
    u, v = b - a, c - a
    area = float(0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).sum())
    return {"triangles": len(triangles), "area": area, "box": (lo, hi), "limited": limited, "turned": turned,
            "lifted": lifted, "cells": count, **task_row(len(records), start)}


def _continue_tile(job: DemJob, t: int, spline_path, cells: np.ndarray):
    """For the cells (flat) that hold points but lie in no triangle: the nearest of tile
    t's own triangles within the reach, the spline continued from it (SplineSampler.continued,
    .evaluate). Returns (cells (k,), distance (k,), height (k,), gradient (k, 2)) of those
    that have one."""
    with limit(job.threads):
        sampler = job.sampler(spline_path)
        has, tri, l0, l1, shift = sampler.continued(job.dem.centres(cells))
        values, grads = sampler.evaluate(tri, l0, l1, True, shift)
    return cells[has], np.hypot(shift[:, 0], shift[:, 1]), values + sampler.origin[2], grads


def _support_tile(job: DemJob, t: int, path) -> int:
    """The support of the cells with a height whose centres lie in tile t's cell (the
    tile grid's tile_of): the distance to the nearest vertex of the spline, by a k-d tree
    of the tile's halo (module docstring), as SplineSampler.distances measures it. Writes
    (flat cell int64, distance float32) pairs to path; returns how many."""
    dem, grid = job.dem, job.surfaces.grid
    heights = np.load(job.heights_path, mmap_mode="r").reshape(-1)
    vertices = halo_vertices(job.halos.halo(t))
    tree = cKDTree(np.column_stack([vertices["x"], vertices["y"]])) if len(vertices) else None
    nx, ny = grid.nx, grid.ny
    i, j = t % nx, t // nx
    x0, y0, x1, y1 = grid.cell(t)
    lo = np.array([-np.inf if i == 0 else x0, -np.inf if j == 0 else y0])
    hi = np.array([np.inf if i == nx - 1 else x1, np.inf if j == ny - 1 else y1])
    rows, cols = dem.span(np.maximum(lo, -1e300), np.minimum(hi, 1e300), 0.0)
    count, bound = 0, 3 * job.longest * (1 + 1e-9)
    with limit(job.threads), open(path, "wb") as out:
        for block in row_blocks(rows, len(cols)):
            ii, jj = np.divmod(np.arange(len(block) * len(cols)), len(cols))
            flat = dem.flat(block.start + ii, cols.start + jj)
            flat = flat[np.isfinite(heights[flat])]
            centre = dem.centres(flat)
            mine = grid.tile_of(centre) == t
            flat, centre = flat[mine], centre[mine]
            if not flat.size:
                continue
            if tree is None:
                raise RuntimeError(f"tile {t}: DEM cells with heights but no vertex in its halo")
            distance = tree.query(centre)[0]
            if distance.max() > bound:
                raise RuntimeError(f"tile {t}: a DEM cell's nearest vertex lies {distance.max():g} from it, "
                                   "beyond the halo (3 longest edges); give --max-edge")
            pairs = np.zeros(flat.size, [("cell", "<i8"), ("d", "<f4")])
            pairs["cell"], pairs["d"] = flat, distance
            pairs.tofile(out)
            count += flat.size
    return count


def halo_vertices(halo) -> np.ndarray:
    """The records of a halo (core.tile.Tile) that its triangles use: the spline's
    vertices (the cached halo keeps the points of triangles the trim removed since it was
    read)."""
    return halo.records.take(np.unique(halo.triangles)) if len(halo.triangles) else halo.records[:0]


class TiledDem:
    """The schedule of a tiled DEM (module docstring): construct with the DemJob, temps
    (inputs.Temps), runner (distributed.TaskRunner), rows (task_rows.TileRows); `write`
    runs the passes and writes the rasters."""

    def __init__(self, job: DemJob, temps, runner, rows):
        self.job, self.temps, self.runner, self.rows = job, temps, runner, rows

    def write(self, plan: DemPlan, chunks, crs: str | None, smoothed: bool) -> dict:
        """Sample every tile, continue the spline into the marked cells, measure the
        support, and write plan's rasters (geo.raster.write_blocks); returns {"kept",
        "triangles_per_tile", "raster", counts of the limiter}."""
        job, dem = self.job, self.job.dem
        shape = dem.shape
        heights_path = self.temps.new("dem-heights.npy")
        heights = np.lib.format.open_memmap(heights_path, mode="w+", dtype=np.float64, shape=shape)
        for block in row_blocks(range(shape[0]), shape[1]):
            heights[block.start:block.stop] = np.nan
        gradients = None
        if job.gradients:
            gradients = np.lib.format.open_memmap(self.temps.new("dem-gradients.npy"), mode="w+",
                                                  dtype=np.float64, shape=shape + (2,))
        marks = mark_points(chunks, dem, self.temps.new("dem-marks.npy"))
        tiles = [t for t in range(len(job.surfaces.grid)) if job.surfaces.files[t] is not None]
        files = {t: _TileFiles(self.temps.new(f"dem-cells-{t}.bin"), self.temps.new(f"dem-spline-{t}.npz"))
                 for t in tiles}
        sampled = self._sample(tiles, files, heights, gradients)
        self._continue(sampled, files, heights, gradients, marks)
        for t in tiles:
            files[t].cells.unlink(missing_ok=True)
            files[t].spline.unlink(missing_ok=True)
        heights.flush()
        support = self._support(tiles, heights_path, shape) if plan.support else None
        area = sum(row["area"] for row in sampled.values())
        kept = sum(_own_vertices(self.job.halos.halo(t)) for t in tiles)
        spacing = float(math.sqrt(area / kept))
        method = choose_slope_method(plan.slope_method, plan.resolution, spacing, smoothed)
        targets = RasterTargets(plan.dem, plan.slope, plan.aspect, plan.hillshade, plan.support)
        z_factor = 1.0 if plan.z_factor is None else float(plan.z_factor)
        blocks = grid_blocks(dem, heights, gradients, support, method if job.gradients else None)
        raster = write_blocks(targets, dem.grid, blocks, RasterStyle(method, crs, "float32", z_factor))
        if plan.preview:
            render_preview(dem, heights, gradients, plan, crs)
        raster["point_spacing"] = spacing
        return {"kept": kept, "raster": raster,
                "triangles_per_tile": {t: row["triangles"] for t, row in sampled.items()},
                **{k: sum(row[k] for row in sampled.values()) for k in ("limited", "turned", "lifted")}}

    def _sample(self, tiles, files, heights, gradients) -> dict:
        """Every tile's _sample_tile, its cells written into the grids in tile order."""
        rows, ready, sampled, next_tile = self.rows, {}, {}, 0
        flat_heights = heights.reshape(-1)
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
                for part in _cell_blocks(files[t].cells):
                    flat_heights[part["cell"]] = part["z"]
                    if flat_gradients is not None:
                        flat_gradients[part["cell"]] = part["g"]
                rows.add(t, "dem", {k: row[k] for k in ("seconds", "worker", "worker_peak_mb")})
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
            _continue_tile, len(tiles), lambda i: (self.job, tiles[i], files[tiles[i]].spline, asked[i]),
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
                pairs = np.fromfile(file, dtype=[("cell", "<i8"), ("d", "<f4")])
            flat[pairs["cell"]] = pairs["d"]
            paths[tiles[i]].unlink()
        return support


def render_preview(dem: DemGrid, heights, gradients, plan: DemPlan, crs: str | None) -> None:
    """The DEM's --preview (plan.preview) from the cells the tiles sampled: every stride-th
    cell of the grid (geo.preview.preview_stride; not the ring), heights rounded to float32
    as the DEM stores them, shaded by the spline's gradient there, so the picture is the
    in-memory fit's (geo.preview.render_dem_cells); at most PIXELS² cells are read from the
    memory maps. --fill off: no cell spans a hole, none is hatched."""
    grid = dem.grid
    stride = preview_stride(grid)
    rows, cols = slice(1, grid.height + 1, stride), slice(1, grid.width + 1, stride)
    z = np.asarray(heights[rows, cols]).astype(np.float32).astype(np.float64)
    g = np.array(gradients[rows, cols])
    g[np.isnan(z)] = np.nan
    render_dem_cells(DemCells(z, g), grid, stride, plan.preview, crs, 1.0 if plan.z_factor is None else plan.z_factor)


def _own_vertices(halo) -> int:
    """How many of the spline's vertices lie in the halo's tile's cell (each vertex is
    counted by one tile: the survey's count is their sum)."""
    used = np.unique(halo.triangles)
    return int(halo.own[used].sum()) if used.size else 0


def _cell_blocks(path, block: int = 1 << 16):
    """The CELL records of a tile's cells file, in blocks."""
    with open(path, "rb") as file:
        while True:
            part = np.fromfile(file, dtype=CELL, count=block)
            if not part.size:
                return
            yield part


def grid_blocks(dem: DemGrid, heights, gradients, support, method: str | None):
    """geo.raster.write_blocks' blocks of the grid's rows from the grids on disk (each with
    the ring): heights; gradients (Horn's differences of the heights with the ring, the
    spline's gradient where a neighbour is nodata, as geo.raster.grid_blocks does; or the
    spline's, method "spline"; None: heights only); support distances (None: none)."""
    grid = dem.grid
    step = max(1, min(256, BLOCK_CELLS // grid.width))
    for start in range(0, grid.height, step):
        rows = range(start, min(start + step, grid.height))
        z = np.asarray(heights[rows.start + 1:rows.stop + 1, 1:-1])
        g = None
        if method == "spline":
            g = np.asarray(gradients[rows.start + 1:rows.stop + 1, 1:-1])
        elif method == "horn":
            g = horn_gradient(np.asarray(heights[rows.start:rows.stop + 2]), grid.resolution)
            edge = np.isfinite(z) & ~np.isfinite(g).all(axis=2)
            g[edge] = np.asarray(gradients[rows.start + 1:rows.stop + 1, 1:-1])[edge]
        d = None if support is None else np.asarray(support[rows.start + 1:rows.stop + 1, 1:-1], dtype=np.float64)
        yield rows, z, g, d
