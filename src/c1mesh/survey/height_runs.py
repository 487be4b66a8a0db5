"""The memory-bounded fit's height field, scheduled tile by tile (c1mesh.pipeline.bounded_fit).
The algorithms are c1mesh.stages.height_field's; here is what each tile reads and where
its results go:

- a task per tile (`height_spill`): its normals from its buffer (c1mesh.survey.tile_normals:
  fitted to the heights, as in memory, or by PCA), then its height-field vertices
  (height_field.tile_heights) as HEIGHT records in a new TileSpill, and the positions
  several of its points share as GROUP records beside them;
- the stacking test over the survey (`survey_stacking`): the spacing h, a task per tile
  (height_field.sample_spacings, each tile reading its cell grown by a reach that doubles
  until every distance found is within it) and the median; then a task per tile counting
  its stacked points (height_field.stacked_points on its cell grown by h), a sum, and
  height_field.check_stacking, as the in-memory fit runs them on its one tile."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from c1mesh.core.plan import HeightSettings
from c1mesh.core.threads import limit
from c1mesh.core.tile import VERTEX, tile_rows
from c1mesh.stages.height_field import (
    Positions,
    PositionTile,
    TileHeights,
    check_stacking,
    sample_spacings,
    spacing_sample,
    spacing_steps,
    stacked_points,
    tile_heights,
)
from c1mesh.stages.height_gradients import height_neighbours, use_height_gradients
from c1mesh.survey.buffered_delaunay import INITIAL_SPACINGS, mean_spacing
from c1mesh.survey.tile_normals import tile_height_normals, tile_normals
from c1mesh.survey.tile_spill import RIM_SPACINGS, TileSpill
from c1mesh.survey.halos import median_of_files
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
    (height_field.tile_heights: usable, not too steep, one per exact position), spilled to a new TileSpill
    of HEIGHT records, and the positions several points share to one of GROUP records: a
    HeightSpill, which the caller closes. Each tile is a task (`_tile_heights`)
    that reads the raw spill and writes its own height and group files, run by runner
    (distributed.TaskRunner); rows: the task_rows.TileRows."""
    rim = RIM_SPACINGS * mean_spacing(grid.box, count)
    heights = TileSpill(grid, directory, stem + ".height", record=HEIGHT, rim=rim).__enter__()
    groups = TileSpill(grid, directory, stem + ".groups", record=GROUP, rim=rim).__enter__()
    usable = 0
    try:
        job = _HeightJob(raw, grid, settings.k, height_neighbours(settings.k), math.cos(math.radians(settings.max_slope)),
                         INITIAL_SPACINGS * mean_spacing(grid.box, count),
                         use_height_gradients(settings.gradients, "estimated"),
                         rows.threads)
        tiles = [t for t in range(len(grid)) if raw.counts[t]]
        for i, row in runner.map(_tile_heights, len(tiles), lambda i: (job, tiles[i], heights, groups),
                                 lambda i: rows.name(tiles[i])):
            heights.set_tile(tiles[i], row.pop("points"), row.pop("rims"))
            groups.set_tile(tiles[i], row.pop("groups"), row.pop("group_rims"))
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


def _tile_heights(job: _HeightJob, t: int, heights_spill, groups_spill) -> dict:
    """One tile's height-field records (HEIGHT, height_field.tile_heights) written to the
    heights TileSpill, the positions several of its points share (GROUP) to the groups
    one; returns its report row (points written, groups written, usable points, seconds,
    worker, and the two rims' counts for TileSpill.set_tile)."""
    start = time.perf_counter()
    with limit(job.threads):
        if job.from_heights:
            result = tile_height_normals(job.read3, job.grid, t, job.height_k, job.buffer)
        else:
            result = tile_normals(job.read3, job.grid, t, job.k, job.buffer, towards=(0.0, 0.0, 1.0))
        heights = tile_heights(job.raw.tile(t), result.normals, job.cos_max)   # survey order, as result.index
        rims, groups, group_rims = write_heights(heights, heights_spill, groups_spill, t)
    return {**task_row(len(heights.records), start), "groups": groups, "usable": heights.usable,
            "rims": rims, "group_rims": group_rims}


def write_heights(heights: TileHeights, heights_spill, groups_spill, t: int) -> tuple[np.ndarray, int, np.ndarray]:
    """Write tile t's height-field records (HEIGHT) to the heights TileSpill and the
    positions several of its points share (GROUP) to the groups one: (the heights' rim
    counts, how many groups, their rim counts), which the reading process gives each
    spill's set_tile."""
    shared = heights.size > 1
    groups = np.empty(int(shared.sum()), GROUP)
    for name in ("index", "x", "y"):
        groups[name] = heights.records[name][shared]
    groups["size"], groups["z_range"] = heights.size[shared], heights.z_range[shared]
    group_rims = groups_spill.write_tile(t, groups)
    return heights_spill.write_tile(t, heights.records), len(groups), group_rims


def survey_stacking(spill: HeightSpill, grid, axis: np.ndarray, runner, name, temps,
                    max_stacked: float = 0.10) -> tuple[float, int]:
    """The stacking test of c1mesh.stages.height_field over the survey, tile by tile, with
    the same numbers as the in-memory fit: the spacing h is the median of every tile's
    sample_spacings (a task per tile, `tile_sample_spacings`), then each tile counts the
    stacked points at its own positions (stacked_points, `tile_stacked`), and the sum
    against spill.usable decides (check_stacking raises NotAHeightFieldError). axis: the
    frame's height axis (3,). Returns (h, stacked points), the in-memory report's
    points.spacing and points.stacked."""
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
    """The median of every tile's tile_sample_spacings at the first of spacing_steps that
    picks a position in some tile, streamed from one file per tile (median_of_files)."""
    paths = [temps.new(f"spacings-{t}.bin") for t in tiles]
    for step in spacing_steps(positions):
        picked = sum(n for _, n in runner.map(tile_sample_spacings, len(tiles),
                                              lambda i: (heights, grid, tiles[i], step, first_reach, paths[i]),
                                              lambda i: name(tiles[i])))
        if picked:
            break
    return median_of_files(paths)


def tile_sample_spacings(heights, grid, tile: int, step: int, first_reach: float, path) -> int:
    """Write to path tile's sample_spacings at step: the 3D distance from each of its own
    height-field positions that spacing_sample picks to its nearest other position in the
    survey. Each is read in the cell grown by a reach that doubles until the distance
    found is within the reach (no position outside can then be nearer). Returns how many."""
    mine = heights.tile(tile)["index"]
    todo = mine[spacing_sample(mine, step)]               # survey numbers, ascending
    parts, reach = [], first_reach
    while todo.size:
        rect = grid.grown(tile, reach)
        records = heights.records(rect)
        own = np.zeros(len(records), dtype=bool)
        own[tile_rows(records["index"], todo)] = True   # the cell's positions lie in rect
        nearest = sample_spacings(_position_tile(records, own), step)            # todo's order
        x0, y0, x1, y1 = grid.box
        whole = rect[0] <= x0 and rect[1] <= y0 and rect[2] >= x1 and rect[3] >= y1
        done = (nearest <= reach) | whole
        parts.append(nearest[done])
        todo, reach = todo[~done], 2 * reach
    distances = np.concatenate(parts) if parts else np.empty(0)
    distances.astype("<f8", copy=False).tofile(path)
    return len(distances)


def tile_stacked(spill: HeightSpill, grid, tile: int, spacing: float) -> int:
    """How many usable points (duplicates included) at tile's own positions are stacked:
    stacked_points on every position within the spacing of tile's cell."""
    rect = grid.grown(tile, spacing * (1 + 1e-9))
    records = spill.heights.records(rect)
    own = grid.tiles_of(records["x"], records["y"]) == tile
    return stacked_points(_position_tile(records, own, spill.groups.records(rect)), spacing)[0]


def _position_tile(records: np.ndarray, own: np.ndarray, shared: np.ndarray | None = None) -> PositionTile:
    """The PositionTile of HEIGHT records (m,) with own (m,) bool; shared: the GROUP records
    of the positions among them that several points share (None: every size 1, no
    spread, which the spacing does not read)."""
    size, z_range = np.ones(len(records), np.int64), np.zeros(len(records))
    if shared is not None:
        rows = tile_rows(records["index"], shared["index"])
        size[rows[rows >= 0]], z_range[rows[rows >= 0]] = shared["size"][rows >= 0], shared["z_range"][rows >= 0]
    positions = Positions(records["x"], records["y"], records["z"], records["gx"], records["gy"], z_range)
    return PositionTile(positions, records["index"], size, own)
