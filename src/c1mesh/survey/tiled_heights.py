"""The memory-bounded fit's height field, a task per tile (c1mesh.survey.tiled_fit): each
tile's normals from its buffer (c1mesh.survey.tile_normals: fitted to the heights, as in
memory, or by PCA), then its usable points as HEIGHT records in a new TileSpill; then the
in-memory fit's stacking test over the survey (`survey_stacking`: the spacing h and the
stacked count as c1mesh.stages.height_field measures them, a task per tile and a sum)."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from c1mesh.core.plan import HeightSettings
from c1mesh.core.threads import limit
from c1mesh.stages.height_field import SPACING_SAMPLES, Positions, check_stacking, kd_tree, normal_gradients, stacked_positions
from c1mesh.stages.height_gradients import height_neighbours, use_height_gradients
from c1mesh.survey.buffered_delaunay import INITIAL_SPACINGS, mean_spacing
from c1mesh.survey.tile_normals import tile_height_normals, tile_normals
from c1mesh.survey.tile_spill import TileSpill
from c1mesh.core.tile import VERTEX, tile_rows
from c1mesh.survey.tiled_halo import median_of_files
from c1mesh.survey.tiles import task_row

HEIGHT = VERTEX
"""One height-field point in a spill: a core.tile VERTEX record."""
GROUP = np.dtype([("index", "<i8"), ("x", "<f8"), ("y", "<f8"), ("size", "<i8"), ("z_range", "<f8")])
"""A plane position that several usable points share, in a spill beside the heights: the
survey number of its first point (the HEIGHT record kept), the position, how many points
share it and the spread of their heights (for the stacking test, `survey_stacking`)."""


@dataclass(frozen=True)
class HeightSpill:
    """What the height pass leaves (height_spill): heights, a TileSpill of HEIGHT records
    (one per distinct usable position); groups, a TileSpill of GROUP records (the positions
    several points share); usable, the usable points that are not too steep, duplicates
    included (the stacking test's denominator, as height_field counts them). Close both
    with close()."""

    heights: object
    groups: object
    usable: int

    def close(self) -> None:
        self.heights.close()
        self.groups.close()


def height_spill(raw, grid, count: int, settings: HeightSettings, directory, stem: str, runner, rows):
    """Per tile: normals of its own points (tile_normals), then its height-field points
    (usable, not too steep, exact duplicate positions dropped), spilled to a new TileSpill
    of HEIGHT records, and the positions several points share to one of GROUP records: a
    HeightSpill, which the caller closes. Each tile is a task (`_tile_heights`)
    that reads the raw spill and writes its own height and group files, run by runner
    (distributed.TaskRunner); rows: the tiled_report.TileRows."""
    heights = TileSpill(grid, directory, stem + ".height", record=HEIGHT).__enter__()
    groups = TileSpill(grid, directory, stem + ".groups", record=GROUP).__enter__()
    usable = 0
    try:
        job = _HeightJob(raw, grid, settings.k, height_neighbours(settings.k), math.cos(math.radians(settings.max_slope)),
                         INITIAL_SPACINGS * mean_spacing(grid.box, count),
                         use_height_gradients(settings.gradients, "estimated"),
                         rows.threads)
        tiles = [t for t in range(len(grid)) if raw.counts[t]]
        for i, row in runner.map(_tile_heights, len(tiles),
                                 lambda i: (job, tiles[i], heights.paths[tiles[i]], groups.paths[tiles[i]]),
                                 lambda i: rows.name(tiles[i])):
            heights.counts[tiles[i]] = row.pop("points")
            groups.counts[tiles[i]] = row.pop("groups")
            usable += row.pop("usable")
            rows.add(tiles[i], "normals", row)
    except BaseException:
        heights.close()
        groups.close()
        raise
    return HeightSpill(heights, groups, usable)


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


def _tile_heights(job: _HeightJob, t: int, path, group_path) -> dict:
    """One tile's height-field records (HEIGHT) written to path, its shared positions
    (GROUP) to group_path; returns its report row (points written, groups written, usable
    points, seconds, worker)."""
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
        first, size, z_range = _positions(own["x"], own["y"], own["z"])
        shared = first[size > 1]
        groups = np.empty(len(shared), GROUP)
        for name in ("index", "x", "y"):
            groups[name] = own[name][shared]
        groups["size"], groups["z_range"] = size[size > 1], z_range[size > 1]
        with open(group_path, "wb") as file:
            groups.tofile(file)
        usable_count = len(own)
        own, normals = own[first], normals[first]
        gradients, _ = normal_gradients(normals)
        records = np.empty(len(own), HEIGHT)
        for name in ("index", "x", "y", "z"):
            records[name] = own[name]
        records["gx"], records["gy"] = gradients[:, 0], gradients[:, 1]
        with open(path, "wb") as file:
            records.tofile(file)
    return {**task_row(len(records), start), "groups": len(groups), "usable": usable_count}


def _positions(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct (x, y) of points (n,): (first (g,) ascending indices of the first point
    (lowest index) at each, size (g,) how many points are there, z_range (g,) the spread
    of their heights)."""
    order = np.lexsort((np.arange(len(x)), y, x))
    new = np.ones(len(x), dtype=bool)
    new[1:] = (x[order][1:] != x[order][:-1]) | (y[order][1:] != y[order][:-1])
    starts = np.flatnonzero(new)
    size = np.diff(np.append(starts, len(x)))
    zs = z[order]
    z_range = (np.maximum.reduceat(zs, starts) - np.minimum.reduceat(zs, starts)) if len(x) else np.empty(0)
    ascending = np.argsort(order[new], kind="stable")
    return order[new][ascending], size[ascending], z_range[ascending]


def survey_stacking(spill: HeightSpill, grid, axis: np.ndarray, runner, name, temps,
                    max_stacked: float = 0.10) -> tuple[float, int]:
    """The stacking test of c1mesh.stages.height_field over the survey, tile by tile, with
    the same numbers as the in-memory fit: the spacing h is the median 3D nearest-neighbour
    distance over the positions that spacing_sample picks by survey number (a task per
    tile, `tile_sample_spacings`), then each tile counts the stacked points among its own
    positions with stacked_positions on the positions within h of its cell
    (`tile_stacked`), and the sum against spill.usable decides (check_stacking raises
    NotAHeightFieldError). axis: the frame's height axis (3,). Returns (h, stacked points),
    the in-memory report's points.spacing and points.stacked."""
    heights = spill.heights
    positions = int(heights.counts.sum())
    tiles = [t for t in range(len(grid)) if heights.counts[t]]
    first_reach = INITIAL_SPACINGS * mean_spacing(grid.box, positions)
    spacing = _sampled_median(heights, grid, tiles, positions, first_reach, runner, name, temps)
    stacked = sum(count for _, count in runner.map(tile_stacked, len(tiles),
                                                     lambda i: (spill, grid, tiles[i], spacing),
                                                     lambda i: name(tiles[i])))
    check_stacking(stacked, spill.usable, max_stacked, axis)
    return spacing, int(stacked)


def _sampled_median(heights, grid, tiles, positions: int, first_reach: float, runner, name, temps) -> float:
    """The median of tile_sample_spacings over every tile (spacing_sample's rule, which
    takes every position when none is picked)."""
    paths = [temps.new(f"spacings-{t}.bin") for t in tiles]
    for every in (False, True):
        picked = sum(n for _, n in runner.map(tile_sample_spacings, len(tiles),
                                              lambda i: (heights, grid, tiles[i], positions, every, first_reach,
                                                         paths[i]),
                                              lambda i: name(tiles[i])))
        if picked:
            break
    return median_of_files(paths)


def tile_sample_spacings(heights, grid, tile: int, positions: int, every: bool, first_reach: float, path) -> int:
    """Write to path the 3D distance from each of tile's own height-field positions that
    spacing_sample picks (every one with every=True) to its nearest other position in the
    survey: read in its cell grown by a reach that doubles until the distance found is
    within the reach (no position outside can then be nearer). Returns how many."""
    own = heights.tile(tile)
    step = 1 if every else max(1, positions // SPACING_SAMPLES)
    mine = own[own["index"] % step == 0]
    query = np.column_stack([mine["x"], mine["y"], mine["z"]])
    distances, todo, reach = np.empty(len(mine)), np.arange(len(mine)), first_reach
    while todo.size:
        rect = grid.grown(tile, reach)
        records = heights.records(rect)
        xyz = np.column_stack([records["x"], records["y"], records["z"]])
        nearest = kd_tree(xyz).query(query[todo], k=2)[0][:, 1]
        x0, y0, x1, y1 = grid.box
        whole = rect[0] <= x0 and rect[1] <= y0 and rect[2] >= x1 and rect[3] >= y1
        done = (nearest <= reach) | whole
        distances[todo[done]] = nearest[done]
        todo, reach = todo[~done], 2 * reach
    distances.astype("<f8").tofile(path)
    return len(mine)


def tile_stacked(spill: HeightSpill, grid, tile: int, spacing: float) -> int:
    """How many usable points (duplicates included) at tile's own positions are stacked
    (stacked_positions on every position within the spacing of tile's cell)."""
    rect = grid.grown(tile, spacing * (1 + 1e-9))
    records = spill.heights.records(rect)
    if not len(records):
        return 0
    shared = spill.groups.records(rect)
    size, z_range = np.ones(len(records), np.int64), np.zeros(len(records))
    rows = tile_rows(records["index"], shared["index"])
    size[rows[rows >= 0]], z_range[rows[rows >= 0]] = shared["size"][rows >= 0], shared["z_range"][rows >= 0]
    bad, _ = stacked_positions(Positions(records["x"], records["y"], records["z"], records["gx"], records["gy"],
                                         z_range), spacing)
    own = grid.tile_of(np.column_stack([records["x"], records["y"]])) == tile
    return int(size[bad & own].sum())
