"""The overshoot limiter (c1mesh.stages.limiter) on a survey fitted in tiles, with its whole-survey result.

What runs where (control_overshoot's steps, in its order, with its noise floors):

- the first noise floor, control_overshoot's `before` (the median |limiter.
  trapezoid_residuals| over every edge): survey-wide, `noise_floors_on` (a task per
  tile, `tile_residuals`, then c1mesh.stages.streamed_median);
- the second, control_overshoot's `after` (the same median once heights and gradients
  are reconciled): survey-wide likewise, each tile reconciling its halo (`reconciled`);
- per tile on its halo, `tile_limits`: limiter.reconcile_heights and
  limiter.reconcile_gradients with the first floor, limiter.limit_gradients with the
  second, limiter.edge_directions. control_overshoot runs exactly these with
  the survey's floors (a SurveyShare); the tile calls them one by one only because
  control_overshoot counts its changes over every vertex it is given, and a tile must
  count its own vertices alone, so that the survey's counts add up.

The limiter is not tile-local in two ways:

- its noise floors are survey-wide: the median |trapezoid residual| over every edge of the
  final triangulation, once with the input heights and gradients (for `reconcile_heights`
  and `reconcile_gradients`) and once with the reconciled ones (for `limit_gradients`);
- a vertex's reconciled height needs its star (its edges and their triangles), its
  reconciled gradient the reconciled heights of all its neighbours, its limited gradient
  the reconciled gradients of all its neighbours, and an edge's direction both of its
  triangles (`edge_directions`).

A tile's halo (c1mesh.survey.tiled_halo: its cell grown by 4L, L the longest final edge)
holds the whole star of every vertex within 3L of its cell, so it has, exactly as the
whole survey has them:

- the reconciled height of every vertex within 3L of the cell (its star is inside), and
  the reconciled gradient of every vertex within 2L;
- the limited gradient, the reconciled height and the edge directions of every corner of
  its own triangles (those lie within L of the cell, their neighbours within 2L);
- the residuals of the edges whose lower-numbered end lies in its cell (both ends within
  L), each edge of the survey in exactly one tile.

The two noise floors take a pass over the tiles each: every tile appends its edges'
residuals to a file, and c1mesh.stages.streamed_median finds their median to the bit. The third
pass (the caller's) limits each tile's gradients with the floors passed in. The limiter's
arithmetic on one vertex or edge does not depend on the rest of the mesh (its sums run
over the vertex's edges in the same order, its local numbering follows the survey
numbers), so the gradients come out with the bits of the whole-survey limiter given the
same height field; directions too, up to the sign of a direction through two opposite
vertices (which triangle of an edge is its "owner" depends on triangle order; the spline
does not depend on that sign).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from c1mesh.engine.topology import edge_table
from c1mesh.stages.limiter import SurveyShare, control_overshoot, reconcile_gradients, reconcile_heights
from c1mesh.survey.distributed import TaskRunner
from c1mesh.core.tile import Tile
from c1mesh.engine.topology import own_triangles_in
from c1mesh.survey.tiled_halo import HaloCache, edge_floor, edge_residuals, median_over_tiles


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


def noise_floors(halos: Callable[[], object], temps) -> NoiseFloors:
    """The survey's two noise floors, exactly. halos: a callable giving a fresh iterator
    of every tile's Halo; temps: tiled_input.Temps for the residual files."""
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
    return median_over_tiles(runner, tile_residuals, cache.tiles(),
                             lambda t, path: (cache, t, reconciled_with, path), name, temps, f"residuals-{label}")


def tile_residuals(cache: HaloCache, tile: int, reconciled_with: float | None, path) -> None:
    """Write to path the |trapezoid residual| of every final edge whose lower end lies in
    tile's cell (edge_floor's values for that tile): with the height field's heights and
    gradients, or, given the first noise floor, with both reconciled with it."""
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


def tile_limits(halo: Tile, owned: np.ndarray, floors: NoiseFloors) -> TileLimits:
    """The limited gradients and edge directions of one tile's own triangles, `owned`
    (k, 3) survey numbers, all inside its halo."""
    table = edge_table(halo.triangles, len(halo.records))
    values, limited, directions, report = control_overshoot(
        halo.points, halo.records["z"], halo.gradients, halo.triangles, "limit", table,
        share=SurveyShare((floors.first, floors.second), halo.own))
    corners, triangles, at = own_triangles_in(halo, table, owned)
    records = halo.records[corners]
    records["z"] = values[corners]
    return TileLimits(records, triangles, limited[corners], directions[at], report.gradients_limited,
                      report.directions_changed, report.heights_reconciled)


def reconciled(halo: Tile, table, noise: float):
    """The halo's heights and gradients reconciled as limiter.control_overshoot does, with
    the survey's first noise floor: (values (m,), gradients (m, 2), heights moved (m,) bool,
    gradients changed (m,) bool). Exact for vertices within 3L (heights) and 2L
    (gradients) of the cell (module docstring)."""
    points = halo.points
    values, lifted = reconcile_heights(points, halo.records["z"], halo.gradients, halo.triangles,
                                       table, noise_floor=noise)
    gradients, moved = reconcile_gradients(points, values, halo.gradients, table.edges, noise_floor=noise)
    return values, gradients, lifted, moved


class TiledLimiter:
    """The overshoot limiter over the tiles: the survey's noise floors, found on
    construction; a refinement task (tiled_refine, through `tile`) limits its tile's
    data from the cached halo (halos, picklable) and these floors."""

    def __init__(self, halos, temps, runner=None, name=str):
        self.halos = halos
        self.floors = noise_floors_on(halos, temps, runner or TaskRunner(), name)
        self.limited = self.turned = self.lifted = 0

    def tile(self, tile: int, triangles: np.ndarray):
        """TileLimits of the tile's own triangles (survey numbers)."""
        return tile_limits(self.halos.halo(tile), triangles, self.floors)

    def report(self) -> dict:
        return {"gradients_limited": self.limited, "directions_changed": self.turned,
                "heights_reconciled": self.lifted,
                "noise_floors": [self.floors.first, self.floors.second]}
