"""The smoothing fit (c1mesh.stages.smoothing) on a survey fitted in tiles: one solve per tile
on its cell grown by a halo (one sweep of restricted overlapping Schwarz), each tile keeping
the vertex data of the vertices in its own cell.

What runs where, after the trim (c1mesh.survey.tiled_fit):

- the spacing h, the strength's length unit: the stacking test's (tiled_heights.survey_stacking),
  the median 3D distance from a height-field position to its nearest other one over the
  positions height_field.spacing_sample picks, as the in-memory fit measures it (equal
  but for the last bit of the frames' local coordinates); so λ is the in-memory fit's;
- the strength s: given, or with --smooth auto chosen by the in-memory search
  (smoothing.smooth_fit's block cross-validation) on the halo of the tile holding the most
  points, then used by every tile;
- per tile (a task, `tile_solve`): the smoothing fit of the vertices and final triangles
  within `smoothing_reach` of its cell, with the survey's h and s and the edge directions
  of limiter.edge_directions on that halo (as smoothed_interpolator takes them in memory);
  it writes the fitted height and gradient of every vertex in its cell, and the
  directions of its own triangles' edges;
- the refinement task of a tile (c1mesh.survey.tiled_refine) reads the fitted data of its
  triangles' corners from the files of the tiles whose cells hold them.

So every vertex has one value and one gradient, from the one tile whose cell holds it, and
every edge one direction, whichever tile refines its triangles: the union is the C1 spline
of those vertex data. It differs from the whole-survey fit only through the halo's cut:
the fit's influence decays over a few smoothing lengths ℓ = s^(1/4) h (the length at which
the energy λ ∫|D²F|² and the data term per area h⁻² balance), and the halo reaches
HALO_LENGTHS of them (docs/smoothing.md shows the difference against the halo width).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from c1mesh.engine.topology import edge_table
from c1mesh.stages.limiter import edge_directions
from c1mesh.stages.smoothing import GradientPrior, SmoothingControl, SmoothingData, smooth_fit
from c1mesh.stages.smoothing_system import available_solvers
from c1mesh.core.tile import corner_rows
from c1mesh.engine.topology import own_triangles_in
from c1mesh.survey.tiled_halo import HALO_EDGES, HaloCache
from c1mesh.stages.limiter import TileLimits
from c1mesh.survey.tiles import task_row

HALO_LENGTHS = 28.0
"""A tile's smoothing halo, in smoothing lengths s^(1/4) h beyond its cell, and never less
than the limiter's halo (HALO_EDGES longest final edges: near holes and borders, where the
edges are long, the gradients reach further). On a 12,000-point terrain with 2 cm noise in
9 tiles, the largest height difference from the one-tile fit, relative to the residual
RMS, was 1.6e-2 at 20 lengths and 5.7e-3 at 24 for s = 10, 7.3e-4 at 24 for s = 100, and
below 1.4e-4 at 32 for both (docs/smoothing.md, "In tiles")."""
FITTED = np.dtype([("index", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("gx", "<f8"), ("gy", "<f8")])
"""One fitted vertex in a tile's file: the height spill's record (survey number, frame
position) with the fitted height and gradient."""


def smoothing_reach(strength: float, spacing: float, longest_edge: float,
                    lengths: float = HALO_LENGTHS) -> float:
    """How far beyond its cell a tile's smoothing solve reads (frame units): `lengths`
    smoothing lengths s^(1/4) h, and never less than the limiter's halo."""
    return max(lengths * float(strength) ** 0.25 * spacing, HALO_EDGES * longest_edge) * (1 + 1e-9)


@dataclass
class TileSolve:
    """What one tile's solve reports: its own vertices, the sum of squares and the largest
    of their residuals (height units), its halo's vertex count and effective degrees of
    freedom (Hutchinson), its own edges whose direction is not the unit normal."""

    own: int
    squares: float
    largest: float
    halo_vertices: int
    edf: float | None
    turned: int


def solve_totals(solves: list[TileSolve]) -> tuple[int, float, float | None]:
    """(own vertices, sum of their squared residuals, edf) over the tiles' solves, the same
    in any order of the list: the float sums are math.fsum's, exactly rounded. edf sums each
    halo's estimate scaled by its share of own vertices (None: no solve had one)."""
    edfs = [s.edf * s.own / s.halo_vertices for s in solves if s.edf is not None and s.halo_vertices]
    return (sum(s.own for s in solves), math.fsum(s.squares for s in solves),
            math.fsum(edfs) if edfs else None)


@dataclass(frozen=True)
class TiledSmoothing:
    """What the smoothing fit over the tiles is asked for: strength ("auto" or s > 0),
    spacing h (the survey's, tiled_heights.survey_stacking), longest_edge (the longest
    final edge, frame units), overshoot ("limit": edge directions; "off": unit normals),
    gradient_weight (of the spill's gradients as data: smoothing.gradient_data_weight; 0:
    none), lengths (the halo in smoothing lengths; None: HALO_LENGTHS)."""

    strength: object
    spacing: float
    longest_edge: float
    overshoot: str
    gradient_weight: float = 0.0
    lengths: float | None = None


class TiledSmoother:
    """The smoothing fit over the tiles (module docstring): construct with the trimmed
    survey (tiled_refine.TiledMesh: its height spill, triangle files and grid), the
    TiledSmoothing asked for, temps, a runner (distributed.TaskRunner) and name(t); it
    chooses s and runs every tile's solve. A refinement task (tiled_refine) then takes its
    tile's vertex data through `tile`, as it takes the limiter's. on_done(t, row) gets each
    solve's report row (tiles.task_row: points, seconds, worker, its peak) as it finishes
    (progress)."""

    def __init__(self, mesh, fit: TiledSmoothing, temps, runner, name=str, on_done=None):
        heights, triangle_files, grid = mesh.heights, mesh.files, mesh.grid
        lengths = HALO_LENGTHS if fit.lengths is None else fit.lengths
        self.grid, self.files, self.overshoot = grid, triangle_files, fit.overshoot
        self.gradient_weight = float(fit.gradient_weight)
        self.limited = self.turned = self.lifted = 0         # tiled_refine adds its rows' counts
        self.seconds: dict = {}
        self.spacing = float(fit.spacing)
        self.search = None
        strength = fit.strength
        if strength == "auto":
            start = time.perf_counter()
            self.search = _search_tile(heights, triangle_files, grid, fit.longest_edge, self.spacing, fit.overshoot,
                                       self.gradient_weight, temps)
            strength = self.search["strength"]
            self.seconds["search"] = time.perf_counter() - start
        self.strength = float(strength)
        self.reach = smoothing_reach(self.strength, self.spacing, fit.longest_edge, lengths)
        self.halos = HaloCache(heights, triangle_files, grid, self.reach, temps, label="smooth-halo")
        tiles = self.halos.tiles()
        self.paths = {t: (temps.new(f"fitted-{t}.bin"), temps.new(f"directions-{t}.npy")) for t in tiles}
        start = time.perf_counter()
        self.solves: list[TileSolve] = []
        for i, (solved, row) in runner.map(tile_solve, len(tiles), lambda i: (self, tiles[i]),
                                           lambda i: name(tiles[i])):
            self.solves.append(solved)
            if on_done:
                on_done(tiles[i], row)
        self.seconds["solve"] = time.perf_counter() - start

    def tile(self, tile: int, triangles: np.ndarray):
        """limiter.TileLimits of tile's own triangles (k, 3) survey numbers: their
        corners' fitted heights and gradients, from the files of the tiles whose cells
        hold them, and the directions of their edges (tile_solve's)."""
        fitted = self._fitted_near(tile)
        rows, local = corner_rows(fitted["index"], triangles)
        if np.any(rows < 0):
            raise RuntimeError(f"tile {tile}: a corner of its triangles has no fitted data")
        records = np.empty(len(rows), self.halos.heights.record)
        fitted = fitted[rows]
        for column in FITTED.names:
            records[column] = fitted[column]
        directions = None if self.overshoot == "off" else np.load(self.paths[tile][1])
        gradients = np.column_stack([records["gx"], records["gy"]])
        return TileLimits(records, local, gradients, directions, 0, 0, 0)

    def _fitted_near(self, tile: int) -> np.ndarray:
        """The fitted vertices of every tile whose cell meets tile's cell grown by its reach,
        ascending survey numbers."""
        parts = [np.fromfile(self.paths[t][0], dtype=FITTED)
                 for t in self.halos.heights.touching(self.grid.grown(tile, self.reach)) if t in self.paths]
        fitted = np.concatenate(parts) if parts else np.empty(0, FITTED)
        return fitted[np.argsort(fitted["index"], kind="stable")]

    def report(self) -> dict:
        """The overshoot section: only edge directions apply to a smoothing fit."""
        return {"gradients_limited": 0, "directions_changed": sum(s.turned for s in self.solves),
                "heights_reconciled": 0}

    def smoothing(self) -> dict:
        """The report's "smoothing" section, of SmoothFit.as_dict's keys, plus the tiled
        solve's halo: residuals over every vertex, edf the sum of each halo's estimate
        scaled by its share of own vertices, the CV curve (and search_limit_reached) of the
        search tile. The solves arrive in completion order on a pool or on Dask, so their
        totals must not depend on the order (solve_totals)."""
        own, squares, edf = solve_totals(self.solves)
        seconds = dict(self.seconds)
        if self.search is not None:
            seconds.update({f"search_{k}": v for k, v in self.search["seconds"].items()})
        return {"strength": self.strength, "lam": self.strength * self.spacing ** 2,
                "cv_curve": [] if self.search is None else [[float(s), float(r)] for s, r in self.search["cv_curve"]],
                "search_limit_reached": None if self.search is None else self.search["search_limit_reached"],
                "edf": edf,
                "residual_rms": math.sqrt(squares / own) if own else 0.0,
                "residual_max": max((s.largest for s in self.solves), default=0.0),
                "solver": self.search["solver"] if self.search is not None else _solver(),
                "seconds": {k: round(float(v), 4) for k, v in seconds.items()}, "outside": 0,
                "gradient_weight": self.gradient_weight,
                "spacing": self.spacing,
                "tiled": {"halo": self.reach, "halo_smoothing_lengths": self.reach / (
                    self.strength ** 0.25 * self.spacing),
                    "search_tile": None if self.search is None else self.search["tile"]}}


def _solver() -> str:
    return available_solvers()[0]


def _search_tile(heights, triangle_files, grid, longest_edge, spacing, overshoot, gradient_weight,
                 temps) -> dict:
    """smooth_fit(strength="auto") on the tile holding the most points, with the
    limiter's halo (its cross-validation windows need no more), its tile number as
    "tile" (the search's strength serves every tile); the SmoothFit's strength, cv_curve,
    search_limit_reached, solver and seconds."""
    candidates = [t for t in range(len(grid)) if triangle_files[t] is not None]
    tile = max(candidates, key=lambda t: (int(heights.counts[t]), -t))
    reach = HALO_EDGES * longest_edge * (1 + 1e-9)
    halo = HaloCache(heights, triangle_files, grid, reach, temps, label="search-halo").halo(tile)
    fitted, _ = _fit_halo(halo, "auto", spacing, overshoot, gradient_weight)
    return {"tile": tile, "strength": fitted.strength, "cv_curve": fitted.cv_curve,
            "search_limit_reached": fitted.search_limit_reached, "solver": fitted.solver, "seconds": fitted.seconds}


def _fit_halo(halo, strength, spacing: float, overshoot: str, gradient_weight: float = 0.0):
    """(SmoothFit, (directions (E, 2) in edge_table(halo.triangles) order or None, changed
    (E,) bool or None)) of one halo's vertices and final triangles; their spilled
    gradients enter as data with gradient_weight (0: not), as in memory."""
    table = edge_table(halo.triangles, len(halo.records))
    directions, changed = (None, None) if overshoot == "off" else edge_directions(halo.points, halo.triangles,
                                                                                  table)
    prior = (GradientPrior(np.column_stack([halo.records["gx"], halo.records["gy"]]), gradient_weight)
             if gradient_weight else None)
    fitted = smooth_fit(halo.points, halo.triangles, SmoothingData(halo.records["z"], spacing),
                        SmoothingControl(strength), directions=directions, prior=prior)
    return fitted, (table, directions, changed)


def tile_solve(smoother: TiledSmoother, tile: int) -> tuple[TileSolve, dict]:
    """Solve tile's halo (module docstring); write its own vertices' fitted data (FITTED)
    and its own triangles' edge directions (in the order of edge_table of those triangles
    numbered by ascending corner, as tiled_refine numbers them). Returns the TileSolve and
    the task's report row (tiles.task_row)."""
    start = time.perf_counter()
    halo = smoother.halos.halo(tile)
    if not len(halo.triangles):
        np.empty(0, FITTED).tofile(smoother.paths[tile][0])
        _save(smoother.paths[tile][1], np.empty((0, 2)))
        return TileSolve(0, 0.0, 0.0, 0, None, 0), task_row(0, start)
    fitted, (table, directions, changed) = _fit_halo(halo, smoother.strength, smoother.spacing,
                                                     smoother.overshoot, smoother.gradient_weight)
    own = halo.own
    records = np.empty(int(own.sum()), FITTED)
    for column in ("index", "x", "y"):
        records[column] = halo.records[column][own]
    records["z"] = fitted.values[own]
    records["gx"], records["gy"] = fitted.gradients[own, 0], fitted.gradients[own, 1]
    records.tofile(smoother.paths[tile][0])
    turned = 0
    if directions is not None:
        _, _, at = own_triangles_in(halo, table, np.load(smoother.files[tile]))
        _save(smoother.paths[tile][1], directions[at])
        turned = int(changed[own[table.edges[:, 0]]].sum())
    residual = halo.records["z"][own] - fitted.values[own]
    return TileSolve(own=int(own.sum()), squares=float(np.sum(residual ** 2)),
                     largest=float(np.abs(residual).max()) if residual.size else 0.0,
                     halo_vertices=len(halo.records), edf=fitted.edf, turned=turned), task_row(len(halo.records), start)


def _save(path, array: np.ndarray) -> None:
    """np.save to exactly path (np.save given a name would append .npy)."""
    with open(path, "wb") as file:
        np.save(file, array)
