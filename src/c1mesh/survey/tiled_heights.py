"""The memory-bounded fit's height field, a task per tile (c1mesh.survey.tiled_fit): each
tile's normals from its buffer (c1mesh.survey.tile_normals: fitted to the heights, as in
memory, or by PCA), then its usable points as HEIGHT records in a new TileSpill."""
from __future__ import annotations

import math
import time

import numpy as np

from c1mesh.survey.tiles import task_row

HEIGHT = np.dtype([("index", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                   ("gx", "<f8"), ("gy", "<f8")])
"""One height-field point in a spill: survey number, frame position, height, gradient."""


def height_spill(raw, grid, count: int, options, directory, stem: str, runner, rows):
    """Per tile: normals of its own points (tile_normals), then its height-field points
    (usable, not too steep, exact duplicate positions dropped), spilled to a new TileSpill
    of HEIGHT records (entered; the caller closes it). Each tile is a task (`_tile_heights`)
    that reads the raw spill and writes its own height file, run by runner
    (distributed.TaskRunner); rows: the tiled_report.TileRows."""
    from c1mesh.survey.buffered_delaunay import INITIAL_SPACINGS, mean_spacing
    from c1mesh.stages.height_gradients import height_neighbours, use_height_gradients
    from c1mesh.survey.tile_spill import TileSpill

    heights = TileSpill(grid, directory, stem + ".height", record=HEIGHT).__enter__()
    try:
        job = _HeightJob(raw, grid, options.k, height_neighbours(options.k), math.cos(math.radians(options.max_slope)),
                         INITIAL_SPACINGS * mean_spacing(grid.box, count),
                         use_height_gradients(getattr(options, "gradients", "auto"), "estimated"),
                         rows.threads)
        tiles = [t for t in range(len(grid)) if raw.counts[t]]
        for i, row in runner.map(_tile_heights, len(tiles), lambda i: (job, tiles[i], heights.paths[tiles[i]]),
                                 lambda i: rows.name(tiles[i])):
            heights.counts[tiles[i]] = row.pop("points")
            rows.add(tiles[i], "normals", row)
    except BaseException:
        heights.close()
        raise
    return heights


class _HeightJob:
    """What every tile's normals task shares (picklable): raw the raw TileSpill, the grid,
    k (PCA neighbours), height_k (height-fit neighbours), cos_max (steepest normal
    allowed), buffer (first read buffer, frame units), from_heights (normals fitted to the
    heights, else PCA), threads per task (None: the process's setting)."""

    def __init__(self, raw, grid, k, height_k, cos_max, buffer, from_heights, threads):
        self.raw, self.grid, self.k, self.height_k, self.cos_max = raw, grid, k, height_k, cos_max
        self.buffer, self.from_heights, self.threads = buffer, from_heights, threads

    def read3(self, rect):
        records = self.raw.records(rect)
        return records["index"], np.column_stack([records["x"], records["y"], records["z"]])


def _tile_heights(job: _HeightJob, t: int, path) -> dict:
    """One tile's height-field records (HEIGHT) written to path; returns its report row
    (points written, seconds, worker)."""
    from c1mesh.stages.height_field import normal_gradients
    from c1mesh.core.threads import limit
    from c1mesh.survey.tile_normals import tile_height_normals, tile_normals

    start = time.perf_counter()
    with limit(job.threads):
        if job.from_heights:
            result = tile_height_normals(job.read3, job.grid, t, job.height_k, job.buffer)
        else:
            result = tile_normals(job.read3, job.grid, t, job.k, job.buffer, towards=(0.0, 0.0, 1.0))
        own = job.raw.tile(t)                                     # survey order, as result.index
        normals = result.normals
        length = np.linalg.norm(normals, axis=1)
        usable = np.isfinite(length) & (length > 0)
        usable[usable] &= np.abs(normals[usable, 2] / length[usable]) >= job.cos_max
        own, normals = own[usable], normals[usable]
        first = _first_of_positions(own["x"], own["y"])
        own, normals = own[first], normals[first]
        gradients, _ = normal_gradients(normals)
        records = np.empty(len(own), HEIGHT)
        for name in ("index", "x", "y", "z"):
            records[name] = own[name]
        records["gx"], records["gy"] = gradients[:, 0], gradients[:, 1]
        with open(path, "wb") as file:
            records.tofile(file)
    return task_row(len(records), start)


def _first_of_positions(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Ascending indices of the first point (lowest index) at each distinct (x, y)."""
    order = np.lexsort((np.arange(len(x)), y, x))
    new = np.ones(len(x), dtype=bool)
    new[1:] = (x[order][1:] != x[order][:-1]) | (y[order][1:] != y[order][:-1])
    return np.sort(order[new])
