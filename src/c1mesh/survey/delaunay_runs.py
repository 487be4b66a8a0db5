"""The memory-bounded fit's Delaunay triangulation with the long-edge trim, a task per tile
(c1mesh.pipeline.bounded_fit): each tile writes the triangles it owns to a file
(c1mesh.survey.buffered_delaunay: tile_triangles without a max_edge, else tile_pass and
the survey-wide auto max_edge of trimmed_delaunay)."""
from __future__ import annotations

import time
from functools import partial

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.threads import limit
from c1mesh.survey.buffered_delaunay import (
    INITIAL_SPACINGS,
    mean_spacing,
    hull_of_parts,
    tile_pass,
    tile_triangles,
    trimmed_delaunay,
)
from c1mesh.survey.task_rows import TileRows
from c1mesh.survey.tile_spill import save_array
from c1mesh.survey.tiles import task_row


def triangulate_tiles(heights, grid, max_edge, temps, runner, rows: TileRows, most: int | None = None):
    """The survey's Delaunay triangulation with the long-edge trim, each tile a task
    (`_tile_delaunay`, `_tile_trimmed`) that reads the height spill and writes its owned
    triangles to a file: (max_edge or None, per tile a .npy file of its owned triangles
    (survey numbers), per tile the buffer its corners lie within, the triangle count of
    the whole Delaunay triangulation: 2n - 2 - h by Euler's formula, n points and h hull
    corners, exact unless points lie on the hull between its corners). most: the most
    points a tile's read may hold without a max_edge (buffered_delaunay.tile_triangles)."""
    count = int(heights.counts.sum())
    if count < 3:
        raise InputError(f"only {count} points are left for the height field; need at least 3")
    hull = hull_of_parts([partial(_tile_points, heights, t) for t in range(len(grid))])
    files = [temps.new(f"triangles-{t}.npy") for t in range(len(grid))]
    buffers = np.zeros(len(grid))
    if max_edge is None:
        first = INITIAL_SPACINGS * mean_spacing(grid.box, count)
        for t, (buffer, row) in runner.map(_tile_delaunay, len(grid),
                                           lambda t: (heights, grid, t, first, (hull, most), files[t], rows.threads),
                                           rows.name):
            buffers[t] = buffer
            rows.add(t, "triangulate", row)
        return None, files, buffers, 2 * count - 2 - len(hull.index)
    longest = [temps.new(f"longest-{t}.npy") for t in range(len(grid))]
    shorts = [temps.new(f"short-{t}.npy") for t in range(len(grid))]

    def passes(bound):
        for t, (buffer, row) in runner.map(
                _tile_trimmed, len(grid),
                lambda t: (heights, grid, t, bound, hull, (files[t], longest[t], shorts[t]), rows.threads),
                rows.name):
            buffers[t] = buffer
            rows.add(t, "triangulate", row)
            yield shorts[t], t
    limit, _ = trimmed_delaunay(heights.read, grid, count, hull, max_edge, passes=passes)
    for t in range(len(grid)):
        triangles = np.load(files[t])
        short = np.load(longest[t]) <= limit
        if not short.all():
            save_array(files[t], triangles[short])
    return limit, files, buffers, 2 * count - 2 - len(hull.index)


def _tile_points(heights, t: int) -> tuple[np.ndarray, np.ndarray]:
    """(survey numbers (m,), xy (m, 2)) of the height spill's tile t."""
    records = heights.tile(t)
    return records["index"], np.column_stack([records["x"], records["y"]])


def _tile_delaunay(heights, grid, t: int, buffer: float, bounds, path, threads) -> tuple[float, dict]:
    """Tile t's final triangles (buffered_delaunay.tile_triangles) saved to path (.npy);
    bounds: (the survey's hull, the most points a read may hold); returns (its buffer,
    its report row)."""
    hull, most = bounds
    start = time.perf_counter()
    with limit(threads):
        result = tile_triangles(heights.read, grid, t, buffer, hull, most=most)
    save_array(path, result.triangles)
    return result.buffer, task_row(result.read, start)


def _tile_trimmed(heights, grid, t: int, bound: float, hull, paths, threads):
    """Tile t's triangles with edges up to bound (buffered_delaunay.tile_pass) saved to
    paths[0], their longest edges to paths[1], its certified short edge lengths to
    paths[2] (the survey's would grow the parent by 24 bytes a point:
    buffered_delaunay.short_median reads them back a tile at a time); returns (its
    buffer, its report row)."""
    path, longest_path, short_path = paths
    start = time.perf_counter()
    with limit(threads):
        result = tile_pass(heights.read, grid, t, bound, hull)
    save_array(path, result.triangles)
    save_array(longest_path, result.longest)
    save_array(short_path, result.short)
    return result.buffer, task_row(result.read, start)
