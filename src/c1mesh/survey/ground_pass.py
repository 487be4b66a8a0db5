"""The ground filter (c1mesh.stages.ground) over a survey larger than memory, tile by tile.

The filter is a tile kernel: `classify_ground(points, owned)` gives a tile's own points the
classes the whole survey gives them when the tile reads `halo_width` metres of the
survey around its cell. This module only schedules it:

    one pass over the inputs (every point inside --bounds, in survey order) → a spill of
    world points to the tiles of a grid sized by the memory budget → per tile: its cell
    grown by the halo, in metres as filter_file_points converts them, classified with its
    own points marked → the survey numbers of the ground points → one bool per point.

The fit then reads the inputs again keeping those points (inputs.las_chunks' keep),
so everything after the filter sees exactly the points the in-memory fit keeps.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.core.crs import metres_per_unit
from c1mesh.stages.frame import ScanFrame
from c1mesh.stages.ground import FILTER_NAME, GroundParameters, classify_ground, halo_width
from c1mesh.survey.buffered_delaunay import TileGrid
from c1mesh.survey.tile_spill import spill
from c1mesh.survey.inputs import las_chunks
from c1mesh.survey.sizing import BYTES_PER_POINT, grid_side

WORLD = ScanFrame(origin=np.zeros(3), axes=np.eye(3))
"""The spill's frame: world coordinates as they are (an identity product is exact)."""


@dataclass(frozen=True)
class GroundPass:
    """Where and how the filter's tiles run: memory, the budget in bytes that sizes them
    (sizing.grid_side); per_tile, points per tile (overrides the budget; tests);
    directory, where the spill files go; stem, their name's start; params, the filter's."""

    memory: int
    per_tile: int | None
    directory: object
    stem: str
    params: GroundParameters = GroundParameters()


def ground_mask(source, bounds, crs: str | None, run: GroundPass) -> tuple[np.ndarray, dict]:
    """((N,) bool, the filter's report facts): which of the survey's N points inside
    `bounds` (in survey order, as las_chunks reads them without classes) are ground, by
    the filter in metres (crs's linear units; metres without a CRS), and the facts
    stages.ground.filter_file_points reports for the same points."""
    xy_unit, z_unit, unit = metres_per_unit(crs)
    scale = np.array([xy_unit, xy_unit, z_unit])
    chunks = las_chunks(source, None, bounds=bounds)
    count, box = _extent(chunks)
    ground = np.zeros(count, dtype=bool)
    if count:                                  # none inside --bounds: the fit says so, as in memory
        _classify_tiles(chunks, count, box, scale, run, ground)
    facts = {"name": FILTER_NAME, "parameters": run.params.as_dict(), "units": unit if crs else "metre (no CRS)",
             "metres_per_unit": [xy_unit, z_unit], "halo_m": halo_width(run.params),
             "points": int(count), "ground": int(ground.sum())}
    return ground, facts


def _classify_tiles(chunks, count: int, box, scale: np.ndarray, run: GroundPass, ground: np.ndarray) -> None:
    """Set ground[i] for the survey's ground points: a spill of the chunks' count points
    to a grid over box sized by run, then each tile's own points classified from its cell
    grown by the halo (in file units: halo_width's metres over scale's x, y factor), the
    points in metres (times scale)."""
    side = grid_side(count, run.memory, run.per_tile, BYTES_PER_POINT)
    grid, halo = TileGrid(box, side, side), halo_width(run.params) / scale[0]
    with spill((points for points, _ in chunks()), WORLD, grid, run.directory, run.stem + ".ground") as raw:
        for t in range(len(grid)):
            own = raw.tile(t)
            if not len(own):
                continue
            records = raw.records(grid.grown(t, halo))
            points = np.column_stack([records["x"], records["y"], records["z"]]) * scale
            owned = np.isin(records["index"], own["index"], assume_unique=True)
            ground[records["index"][owned][classify_ground(points, owned, run.params)]] = True


def _extent(chunks) -> tuple[int, tuple[float, float, float, float]]:
    """(points, (x0, y0, x1, y1) world box) of the chunks (one pass)."""
    count, low, high = 0, np.full(2, np.inf), np.full(2, -np.inf)
    for points, _ in chunks():
        if len(points):
            low, high = np.minimum(low, points[:, :2].min(axis=0)), np.maximum(high, points[:, :2].max(axis=0))
            count += len(points)
    return count, (float(low[0]), float(low[1]), float(high[0]), float(high[1]))
