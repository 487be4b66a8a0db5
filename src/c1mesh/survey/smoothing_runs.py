"""The smoothing stage (c1mesh.stages.smoothing: `smooth_tile` on every tile, the strength
and the report's totals) scheduled over a survey fitted in tiles: which tile the strength
search runs on, the halos the tiles read, the files each tile's run writes, and the reads
of its neighbours' files by each tile's refinement.

What runs where, after the trim (c1mesh.pipeline.bounded_fit):

- the spacing h, the strength's length unit: the stacking test's (height_runs.survey_stacking),
  the median 3D distance from a height-field position to its nearest other one over the
  positions height_field.spacing_sample picks, as the in-memory fit measures it (equal
  but for the last bit of the frames' local coordinates); so λ is the in-memory fit's;
- the strength s: given, or with --smooth auto the stage's search (smoothing.search_strength)
  on the survey's search windows (smoothing.SearchWindows: two reduces over the spill's
  tiles find them, `survey_windows`; `window_tile` reads the vertices in them and the
  final triangles among those), the in-memory fit's windows, then used by every tile;
- per tile (a task, `tile_solve`): smoothing.smooth_tile on its cell grown by the reach
  (smoothing.smoothing_reach, and never less than the limiter's halo, HALO_EDGES longest
  final edges); it writes the fitted height and gradient of every vertex in its cell,
  and the directions of its own triangles' edges;
- the refinement task of a tile (c1mesh.survey.refine_runs) reads the fitted data of its
  triangles' corners from the files of the tiles whose cells hold them (`TiledSmoother.tile`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from c1mesh.core.tile import Tile, compact, corner_rows, tile_rows
from c1mesh.stages.lattice_mesh import NodeGrid, multigrid_lattice
from c1mesh.stages.limiter import TileLimits, tile_limits
from c1mesh.stages.smoothing import (LATTICE_HALO_LENGTHS, LATTICE_HALO_SPACINGS, SearchWindows, SmoothingData,
                                     SmoothingRun, StrengthSearch,
                                     TileSolve, combined_fit, search_strength, smooth_tile,
                                     smoothing_reach, windows_of_parts)
from c1mesh.stages.trim import connected_sets, triangles_among
from c1mesh.survey.halos import HALO_EDGES, HaloCache, noise_floors
from c1mesh.survey.tile_spill import save_array
from c1mesh.survey.tiles import task_row


@dataclass(frozen=True)
class TiledSmoothing:
    """What the smoothing fit over the tiles is asked for: run (the stage's
    smoothing.SmoothingRun: strength "auto" or s > 0, scheme, the survey's spacing h
    (height_runs.survey_stacking), overshoot, the weight of the spill's gradients as
    data), longest_edge (the longest final edge, frame units: the least halo); data: the
    height spill whose every height is fitted when the vertices are lattice nodes
    (--spacing: survey.lattice_runs; None: the vertices' own heights); least_halo (frame
    units): the halo the mesh asks for besides (the lattice's: lattice_runs.lattice_halo);
    nodes: the NodeGrid the vertices are nodes of (their records' `index` its node
    numbers), whose tiles of MULTIGRID_FROM nodes or more solve by its multigrid as the
    in-memory fit does (lattice_mesh.multigrid_lattice); None: any mesh."""

    run: SmoothingRun
    longest_edge: float
    data: object = None
    least_halo: float = 0.0
    nodes: NodeGrid | None = None


class TiledSmoother:
    """The smoothing fit over the tiles (module docstring): construct with the trimmed
    survey (refine_runs.TiledMesh: its height spill, triangle files and grid), the
    TiledSmoothing asked for, temps, a runner (distributed.TaskRunner) and name(t); it
    chooses s and runs every tile's solve. A refinement task (refine_runs) then takes its
    tile's vertex data through `tile`, as it takes the limiter's. on_done(t, row) gets each
    solve's report row (tiles.task_row: points, seconds, worker, its peak) as it finishes
    (progress)."""

    def __init__(self, mesh, fit: TiledSmoothing, temps, runner, name=str, on_done=None):
        heights, triangle_files, grid = mesh.heights, mesh.files, mesh.grid
        self.grid, self.files, self.overshoot = grid, triangle_files, fit.run.overshoot
        self.limited = self.turned = self.lifted = 0         # refine_runs adds its rows' counts
        self.seconds: dict = {}
        self.search: StrengthSearch | None = None
        self.run, self.data, self.nodes = fit.run, fit.data, fit.nodes
        if self.run.control.strength == "auto":
            start = time.perf_counter()
            windows = survey_windows(heights if self.data is None else self.data)
            searched = replace(self.run, control=replace(self.run.control, windows=windows))
            self.search = search_strength(window_tile(heights, triangle_files, windows, fit.longest_edge),
                                          searched, self.data_in(windows, fit.longest_edge))
            self.run = replace(self.run, control=replace(self.run.control, strength=self.search.strength))
            self.seconds["search"] = time.perf_counter() - start
        self.reach = max(self._smoothing_reach(), HALO_EDGES * fit.longest_edge, fit.least_halo) * (1 + 1e-9)
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

    def _smoothing_reach(self) -> float:
        """The halo the strength asks for: smoothing_reach, or with --spacing's lattice nodes
        (self.data: every height fitted) the larger LATTICE_HALO_LENGTHS, LATTICE_HALO_SPACINGS."""
        strength, spacing = self.run.control.strength, self.run.spacing
        if self.data is None:
            return smoothing_reach(strength, spacing)
        return max(smoothing_reach(strength, spacing, LATTICE_HALO_LENGTHS), LATTICE_HALO_SPACINGS * spacing)

    def data_near(self, tile: int, reach: float, own: bool = True) -> SmoothingData | None:
        """The heights fitted on tile's cell grown by reach: those of the data spill there
        (at their own positions), those in its cell marked its own (own=True: the solve
        counts which of them lie outside the triangles), or None (the vertices' own
        heights)."""
        if self.data is None:
            return None
        records = self.data.records(self.grid.grown(tile, reach))
        xy = np.column_stack([records["x"], records["y"]])
        return SmoothingData(records["z"], self.run.spacing, xy, own=self.grid.tile_of(xy) == tile if own else None)

    def data_in(self, windows: SearchWindows, reach: float) -> SmoothingData | None:
        """The heights fitted in the search windows, each grown by reach (the longest final
        edge: every data point in a triangle with its corners in a window), or None (the
        vertices' own heights)."""
        if self.data is None:
            return None
        records = _records_in(self.data, windows, reach)
        return SmoothingData(records["z"], self.run.spacing, np.column_stack([records["x"], records["y"]]))

    def outside(self) -> int:
        """The data points outside the triangles, each counted by the tile whose cell holds it."""
        return sum(s.outside for s in self.solves)

    def tile(self, tile: int, triangles: np.ndarray):
        """limiter.TileLimits of tile's own triangles (k, 3) survey numbers: their
        corners' fitted heights and gradients, from the files of the tiles whose cells
        hold them, and the directions of their edges (tile_solve's)."""
        fitted = self._fitted_near(tile)
        rows, local = corner_rows(fitted["index"], triangles)
        if np.any(rows < 0):
            raise RuntimeError(f"tile {tile}: a corner of its triangles has no fitted data")
        records = fitted.take(rows)
        directions = None if self.overshoot == "off" else np.load(self.paths[tile][1])
        gradients = np.column_stack([records["gx"], records["gy"]])
        return TileLimits(records, local, gradients, directions, 0, 0, 0)

    def _fitted_near(self, tile: int) -> np.ndarray:
        """The fitted vertices of every tile whose cell meets tile's cell grown by its reach,
        ascending survey numbers."""
        record = self.halos.heights.record                 # tile_solve writes the halo's records
        parts = [np.fromfile(self.paths[t][0], dtype=record)
                 for t in self.halos.heights.touching(self.grid.grown(tile, self.reach)) if t in self.paths]
        fitted = np.concatenate(parts) if parts else np.empty(0, record)
        return fitted.take(np.argsort(fitted["index"], kind="stable"))

    def report(self) -> dict:
        """The overshoot section: only edge directions apply to a smoothing fit."""
        return {"gradients_limited": 0, "directions_changed": sum(s.turned for s in self.solves),
                "heights_reconciled": 0}

    def smoothing(self) -> dict:
        """The report's "smoothing" section: the stage's reduce of the tiles' solves
        (smoothing.combined_fit, in any order: they arrive in completion order on a pool or
        on Dask), with the search tile's CV curve, plus the spacing and the tiled solve's
        halo and search tile. Its residuals are the own vertices' (with --spacing the
        own data points', as the in-memory fit's are every data point's)."""
        seconds = dict(self.seconds)
        if self.search is not None:
            seconds.update({f"search_{k}": v for k, v in self.search.seconds.items()})
        strength, spacing = float(self.run.control.strength), self.run.spacing
        facts = combined_fit(self.solves, self.run, self.search, seconds).as_dict()
        return {**facts, "spacing": spacing,
                "tiled": {"halo": self.reach, "halo_smoothing_lengths": self.reach / (strength ** 0.25 * spacing)}}


class WrappedSmoother:
    """A DEM fill's data over a TiledSmoother's (smoother): a DEM task takes its tile's data
    through the wrapper's `tile`, and the report's facts are the smoother's."""

    smoother: TiledSmoother

    def outside(self) -> int:
        return self.smoother.outside()

    def report(self) -> dict:
        return self.smoother.report()

    def smoothing(self) -> dict:
        return self.smoother.smoothing()


class SmoothedFill(WrappedSmoother):
    """A DEM's fill of a smoothing fit over the tiles, as pipeline.driver._smoothed spans
    the holes in memory: the smoothing fits the trimmed triangles (smoother, a
    TiledSmoother of the trimmed survey); the filled triangulation (halos: its
    halos.HaloCache, survey.hole_runs.TiledFill's files) takes the fitted heights and
    gradients where the smoothing has them and the data's elsewhere, and the limiter runs
    over it with noise floors of its own (overshoot "limit"); a vertex of a triangle that
    spans a hole (spanning: their survey numbers, ascending) takes the limited gradient,
    the others keep the fitted one, and every edge the limiter's direction. A refinement
    or DEM task takes its tile's data through `tile`, as from a TiledSmoother."""

    def __init__(self, smoother: TiledSmoother, halos: HaloCache, spanning: np.ndarray, temps, runner=None,
                 name=str):
        self.smoother, self.spanning = smoother, spanning
        self.halos = FittedHalos(halos, {t: paths[0] for t, paths in smoother.paths.items()})
        self.floors = None
        if smoother.overshoot == "limit":
            self.floors = noise_floors(self.halos, temps, runner, name)
        self.limited = self.turned = self.lifted = 0

    def tile(self, tile: int, triangles: np.ndarray) -> TileLimits:
        """limiter.TileLimits of tile's own triangles (k, 3) survey numbers (class docstring)."""
        halo = self.halos.halo(tile)
        if self.floors is None:                      # --overshoot off: the data as fitted
            rows, local = corner_rows(halo.records["index"], triangles)
            records = halo.records.take(rows)
            return TileLimits(records, local, np.column_stack([records["gx"], records["gy"]]), None, 0, 0, 0)
        limits = tile_limits(halo, triangles, self.floors)
        records = halo.records.take(tile_rows(halo.records["index"], limits.records["index"]))
        spans = np.isin(records["index"], self.spanning)[:, None]
        gradients = np.where(spans, limits.gradients, np.column_stack([records["gx"], records["gy"]]))
        return TileLimits(records, limits.triangles, gradients, limits.directions, 0, 0, 0, limits.table)


class FittedHalos:
    """The halos (halos.HaloCache) of a filled triangulation with the smoothing's fitted
    heights and gradients (fitted: tile -> the file of its own vertices', records of the
    height spill's dtype, tile_solve's) in place of the data's at the vertices it fitted.
    Picklable."""

    def __init__(self, halos: HaloCache, fitted: dict):
        self.cache, self.fitted = halos, fitted

    def tiles(self):
        return self.cache.tiles()

    def halo(self, tile: int) -> Tile:
        halo = self.cache.halo(tile)
        record = self.cache.heights.record                 # tile_solve writes the halo's records
        parts = [np.fromfile(self.fitted[t], dtype=record) for t in self.cache.reads(tile) if t in self.fitted]
        fitted = np.concatenate(parts) if parts else np.empty(0, record)
        fitted = fitted.take(np.argsort(fitted["index"], kind="stable"))
        rows = tile_rows(fitted["index"], halo.records["index"])
        has = rows >= 0
        records = halo.records.copy()
        for name in ("z", "gx", "gy"):
            records[name][has] = fitted[name][rows[has]]
        return Tile(records, halo.triangles, halo.own)


def survey_windows(points) -> SearchWindows:
    """The survey's SearchWindows (smoothing.windows_of_parts) from its points' spill
    (tile_spill.TileSpill: every height fitted), its tiles the parts: the in-memory fit's
    windows."""
    tiles = [t for t in range(len(points.grid)) if points.counts[t]]

    def parts():
        for t in tiles:
            records = points.tile(t)
            yield np.column_stack([records["x"], records["y"]])
    return windows_of_parts(parts, int(points.counts.sum()))


def window_tile(heights, triangle_files, windows: SearchWindows, longest_edge: float) -> Tile:
    """The search's tile: the vertices in the windows grown by the longest final edge
    (every vertex when whole) and the final triangles with all three corners among them;
    every record its own. The search (smoothing._search_problem) keeps the triangles in
    the windows, as the in-memory fit's does; the ring around them gives each of their
    edges both its triangles, so the edge directions (limiter.edge_directions) are the
    whole survey's there too."""
    grow = longest_edge * (1 + 1e-9)
    records = _records_in(heights, windows, grow)
    tiles = sorted({t for rect in _rects(windows, grow) for t in heights.touching(rect)})
    files = (np.load(triangle_files[t]) for t in tiles if triangle_files[t] is not None)
    used, triangles = compact(triangles_among(records["index"], files), len(records))
    records = records.take(used)
    return Tile(records, triangles, np.ones(len(records), dtype=bool))


def _rects(windows: SearchWindows, grow: float) -> list:
    """The windows' rectangles grown by grow, or the whole plane's one when whole."""
    if windows.whole:
        return [(-np.inf, -np.inf, np.inf, np.inf)]
    return windows.rects(grow)


def _records_in(spill, windows: SearchWindows, grow: float) -> np.ndarray:
    """The spill's records in the windows grown by grow, each once, ascending survey numbers."""
    parts = [spill.records(rect) for rect in _rects(windows, grow)]
    records = np.concatenate(parts) if parts else np.empty(0, spill.record)
    _, first = np.unique(records["index"], return_index=True)
    return records.take(first)


def pieces_with_own(halo: Tile) -> Tile:
    """halo with only the triangles of its connected pieces that hold an own record, and
    only the records those triangles use (in their order).

    A lattice mesh's nodes carry no data (--spacing: the data spill's heights are fitted):
    a node on the halo's rim whose triangles reach beyond it is a corner of none, and a
    piece of the halo cut off at the rim may hold fewer than 3 data points; either leaves
    the tile's system singular. Neither shares a vertex with the own ones, so their values
    cannot reach them: dropping them changes none of the tile's own values."""
    triangles = halo.triangles
    if not len(triangles):
        return halo
    piece = connected_sets(len(halo.records), np.concatenate([triangles[:, 0], triangles[:, 1]]),
                           np.concatenate([triangles[:, 1], triangles[:, 2]]))
    with_own = np.zeros(len(halo.records), dtype=bool)
    with_own[piece[halo.own]] = True
    used, triangles = compact(triangles[with_own[piece[triangles[:, 0]]]], len(halo.records))
    return Tile(halo.records.take(used), triangles, halo.own[used])


def tile_solve(smoother: TiledSmoother, tile: int) -> tuple[TileSolve, dict]:
    """smoothing.smooth_tile on tile's halo; writes its own vertices' fitted data (records
    of the height spill's dtype, fitted z, gx, gy) and its own triangles' edge directions (.npy, as
    smooth_tile orders them). Returns the TileSolve and the task's report row (tiles.task_row)."""
    start = time.perf_counter()
    halo = smoother.halos.halo(tile)
    if smoother.data is not None:        # lattice nodes: a piece the halo cuts off may hold no data
        halo = pieces_with_own(halo)
    lattice = None if smoother.nodes is None else multigrid_lattice(smoother.nodes, halo.records["index"])
    smoothed = smooth_tile(halo, smoother.run, np.load(smoother.files[tile]),
                           data=smoother.data_near(tile, smoother.reach), lattice=lattice)
    records = np.compress(halo.own, halo.records)
    records["z"] = smoothed.values
    records["gx"], records["gy"] = smoothed.gradients[:, 0], smoothed.gradients[:, 1]
    records.tofile(smoother.paths[tile][0])
    if smoothed.directions is not None:
        save_array(smoother.paths[tile][1], smoothed.directions)
    return smoothed.solve, task_row(len(halo.records), start)
