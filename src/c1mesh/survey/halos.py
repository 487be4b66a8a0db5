"""A tile's halo: the height-field points and final triangles around its cell that the
survey-wide passes of the memory-bounded fit read (c1mesh.survey.trim_runs, the
limiter), cached once in temporary files (`HaloCache`); the scheduling of the survey's
noise floors over them (`edge_floor`, `noise_floors`: c1mesh.stages.limiter's summary per
tile and reduce) and of the limiter's run per tile (`TiledLimiter`).

The halo rule. Every final triangle has edges at most L long (the long-edge trim's
max_edge, or the longest edge of the untrimmed triangulation). A tile reads the height
field in its cell grown by 4L (its halo) and the final triangles of every tile that cell
meets, and keeps the triangles whose three corners it read. Then it holds the whole star
of every vertex within 3L of its cell (what the limiter needs, `TiledLimiter`;
the trim's peel and bow-ties need 2L), and every edge whose lower-numbered end lies in its
cell, each edge of the survey in exactly one tile.

The limiter on such halos: a vertex's reconciled height needs its star, its reconciled
gradient the reconciled heights of its neighbours, its limited gradient their reconciled
gradients, an edge's direction both its triangles. A halo therefore has, as the whole
survey has them, the reconciled heights within 3L of the cell, the reconciled gradients
within 2L, and the limited gradients, heights and directions of every corner of its own
triangles; and the residuals (input or reconciled) of the edges whose lower end it owns,
which its floor_summary holds. The limiter's arithmetic at a vertex runs over its edges
in survey-number order whatever else the tile holds, so the tiles give the whole
survey's bits (directions up to the sign of a line through two opposite vertices, which
the spline does not see). Three passes: the first floor, the second, then the run per
tile in the refinement task.

A DEM's fill adds the long triangles that span the trim's holes (survey.hole_runs): a
halo then also reads the neighbourhood (within the same reach) of the far corners of the
long triangles its three rings reach (`far`), so the rule above holds across them.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from c1mesh.core.threads import map_in_threads
from c1mesh.core.tile import Tile, compact, tile_rows
from c1mesh.stages.limiter import (NoiseFloors, Reconciliation, TileLimits, floor_summary, floor_summary_after,
                                   reconciled_summary, reduce_floor, tile_limits)
from c1mesh.stages.streamed_median import streamed_median
from c1mesh.stages.trim import edge_lengths, kept_triangles, triangles_among
from c1mesh.survey.distributed import TaskRunner
from c1mesh.survey.tile_spill import file_blocks
from c1mesh.survey.tiles import task_row

HALO_EDGES = 4
"""A tile's halo, in longest final edges (module docstring)."""


def halo_reach(longest_edge: float) -> float:
    """How far beyond its cell a tile reads (frame units), for final edges at most
    longest_edge long; a relative margin keeps rounding on the safe side."""
    return HALO_EDGES * float(longest_edge) * (1 + 1e-9)


def read_halo(heights, triangle_files, grid, tile: int, reach: float, far: np.ndarray | None = None) -> Tile:
    """The halo of `tile` (module docstring). heights: a tile_spill.TileSpill of height
    records; triangle_files: per tile a .npy of its owned final triangles (survey numbers)
    or None; far (m, 3): x, y and radius of the neighbourhoods it reads too, around a
    DEM's fill's long triangles' far corners (survey.hole_runs.far_centres; None: none)."""
    return read_halo_and_homes(heights, triangle_files, grid, tile, reach, far)[0]


def read_halo_and_homes(heights, triangle_files, grid, tile: int, reach: float,
                        far: np.ndarray | None = None) -> tuple[Tile, np.ndarray]:
    """`read_halo`'s Tile and (m,) int32 the tile whose cell holds each of its vertices
    (buffered_delaunay.TileGrid.tiles_of), which its own mask is made from."""
    records, tiles = heights.records_near(grid.grown(tile, reach), far)
    files = (np.load(triangle_files[other]) for other in tiles if triangle_files[other] is not None)
    used, triangles = compact(triangles_among(records["index"], files), len(records))
    records = records.take(used)                         # structured rows: take, not [used]
    home = grid.tiles_of(records["x"], records["y"]).astype(np.int32)
    return Tile(records, triangles, home == tile), home


class HaloCache:
    """Every tile's halo, read from the spills once and kept in temporary files for the
    later passes (a halo read costs a filter of up to nine tiles' points and triangles;
    a cached one, one file read). Triangles removed after the first read (the peel) are
    dropped as each halo is loaded: `removed` maps a tile to the removed triangles it
    owns (appended to, never reordered), so a halo compares its triangles with those of
    the tiles it reads, not with the survey's whole list; and the driver's cache writes
    the halo back without them, noting in `applied` (tile -> {owner: rows of
    removed[owner]}) which it is without, so a later load drops only what was removed
    since. temps: inputs.Temps; label: names its files (two caches of different reach
    share one Temps); far: {tile: (m, 3) far reads} its halo also reads (read_halo;
    a DEM's fill, survey.hole_runs.far_centres)."""

    def __init__(self, heights, triangle_files, grid, reach: float, temps, label: str = "halo",
                 far: dict | None = None):
        self.heights, self.files, self.grid, self.reach = heights, triangle_files, grid, reach
        self.temps, self.paths, self.label, self.far = temps, {}, label, far or {}
        self._reads: dict[int, list] = {}          # tile -> the spill tiles its halo reads
        self.removed: dict[int, np.ndarray] = {}
        self.applied: dict[int, dict[int, int]] = {}

    def tiles(self):
        """The tiles that own triangles."""
        return [t for t in range(len(self.grid)) if self.files[t] is not None]

    def halo(self, tile: int) -> Tile:
        """tile's halo, from the cache, else read from the spills: cached by the driver's
        cache, not by a copy sent with a task (inputs.Temps.owned_here: a file a copy
        made would be removed by nobody)."""
        return self.halo_and_homes(tile)[0]

    def halo_and_homes(self, tile: int) -> tuple[Tile, np.ndarray]:
        """`halo`'s Tile and (m,) int32 the tile whose cell holds each of its vertices
        (buffered_delaunay.TileGrid.tiles_of; the trim's Place), kept in the cache beside
        the halo: finding them was 5 ms of each of the 12M survey's 400 halo loads."""
        if tile not in self.paths:
            halo, home = read_halo_and_homes(self.heights, self.files, self.grid, tile, self.reach,
                                             self.far.get(tile))
            if self.temps.owned_here():
                self.paths[tile] = self._new_paths(tile)
                _write_halo(halo, home, self.paths[tile])
            records, triangles = halo.records, halo.triangles
        else:
            records = np.fromfile(self.paths[tile][0], dtype=self.heights.record)
            triangles = np.fromfile(self.paths[tile][1], dtype="<i8").reshape(-1, 3)
            home = np.fromfile(self.paths[tile][2], dtype="<i4")
        return Tile(records, self._drop(tile, records["index"], triangles), home == tile), home

    def prefetch(self, runner, name=str, on_done=None) -> None:
        """Read every tile's halo and cache it, each tile a task on runner
        (distributed.TaskRunner; `cache_halo`), before the passes that use them.
        name(t) names tile t in errors; on_done(t, row) gets each task's report row."""
        tiles = [t for t in self.tiles() if t not in self.paths]
        paths = {t: self._new_paths(t) for t in tiles}
        for i, row in runner.map(cache_halo, len(tiles), lambda i: (self, tiles[i], paths[tiles[i]]),
                                 lambda i: name(tiles[i])):
            self.paths[tiles[i]] = paths[tiles[i]]
            if on_done:
                on_done(tiles[i], row)

    def _new_paths(self, tile: int):
        return (self.temps.new(f"{self.label}-{tile}.records"), self.temps.new(f"{self.label}-{tile}.triangles"),
                self.temps.new(f"{self.label}-{tile}.homes"))

    def prune(self) -> None:
        """Write the cached halos without the removed triangles they still hold, once the
        trim is done (and the tiles' triangle files without them), so later passes (and
        the copies sent with their tasks) need not drop them; in the thread knob's threads."""
        def prune_one(tile: int) -> None:
            if self._pending(tile):
                records = np.fromfile(self.paths[tile][0], dtype=self.heights.record)
                self._drop(tile, records["index"], np.fromfile(self.paths[tile][1], dtype="<i8").reshape(-1, 3))
        map_in_threads(prune_one, list(self.paths))
        self.removed, self.applied = {}, {}

    def halos(self):
        """A fresh iterator over the halos of all tiles that own triangles."""
        return (self.halo(t) for t in self.tiles())

    def reads(self, tile: int) -> list[int]:
        """The spill tiles tile's halo reads (its rectangle's and its far reads')."""
        if tile not in self._reads:
            self._reads[tile] = self.heights.reading(self.grid.grown(tile, self.reach), self.far.get(tile))
        return self._reads[tile]

    def _pending(self, tile: int) -> dict[int, int]:
        """{owner: rows of removed[owner] already dropped} for the tiles near `tile`
        (those its halo reads) that removed triangles since its cached file was written."""
        applied = self.applied.get(tile, {})
        return {t: applied.get(t, 0) for t in self.reads(tile) if len(self.removed.get(t, ())) > applied.get(t, 0)}

    def _drop(self, tile: int, numbers: np.ndarray, triangles: np.ndarray) -> np.ndarray:
        """triangles (k, 3) (rows of the halo's survey numbers `numbers`) without the
        removed ones not yet dropped from tile's cached file, which the driver's cache
        then rewrites without them."""
        pending = self._pending(tile)
        if not pending or not len(triangles):
            return triangles
        kept = kept_triangles(triangles, np.concatenate([self.removed[t][done:] for t, done in pending.items()]),
                              numbers)
        triangles = np.compress(kept, triangles, axis=0)     # rows whole: 2.5x numpy's boolean index
        if tile in self.paths and self.temps.owned_here():
            if not kept.all():
                triangles.astype("<i8", copy=False).tofile(self.paths[tile][1])
            self.applied[tile] = {**self.applied.get(tile, {}), **{t: len(self.removed[t]) for t in pending}}
        return triangles


def cache_halo(cache: HaloCache, tile: int, paths) -> dict:
    """Read tile's halo (read_halo) and write it to paths (records, triangles, the
    vertices' tiles), as HaloCache.halo caches it; returns a report row (points,
    seconds, worker)."""
    start = time.perf_counter()
    halo, home = read_halo_and_homes(cache.heights, cache.files, cache.grid, tile, cache.reach, cache.far.get(tile))
    _write_halo(halo, home, paths)
    return task_row(len(halo.records), start)


def _write_halo(halo: Tile, home: np.ndarray, paths) -> None:
    """A halo's records, triangles and vertices' tiles to its cache files, paths (3,)."""
    halo.records.tofile(paths[0])
    halo.triangles.astype("<i8", copy=False).tofile(paths[1])
    home.astype("<i4", copy=False).tofile(paths[2])


def longest_final_edge(heights, triangle_files, grid, buffers) -> float:
    """The longest edge of the survey's final triangles (as trim.trim measures
    edges), tile by tile: tile t's own triangles have their corners within buffers[t]."""
    longest = 0.0
    for t, path in enumerate(triangle_files):
        if path is None:
            continue
        triangles = np.load(path)
        if not len(triangles):
            continue
        records = heights.records(grid.grown(t, buffers[t] * (1 + 1e-9)))
        rows = tile_rows(records["index"], triangles)
        xy = np.column_stack([records["x"], records["y"]])
        longest = max(longest, float(edge_lengths(xy, rows).max()))
    return longest


@dataclass(frozen=True)
class KeptSummaries:
    """The curtains' noise floor summaries (trim_runs.trim_tiles), kept for the limiter's
    first floor: both are floor_summary with the data as read, of each tile's own edges,
    so the first floor's summary of a tile is its curtains' one, without the edges that
    only triangles removed since held (limiter.floor_summary_after). paths: tile -> its
    file; removed: tile -> (r, 3) survey numbers of the triangles removed since (by the
    curtains and the slivers and bow-ties their holes exposed) with a corner in its
    cell, absent where there are none. The files are removed with the first floor's."""

    paths: dict
    removed: dict


def floor_files(halos: HaloCache, temps, label: str, first: float | None = None, runner=None,
                name=str, kept: KeptSummaries | None = None, reconciled: dict | None = None) -> dict:
    """{tile: the file of its floor_summary} for every tile of the halos (the summaries of
    a noise floor, c1mesh.stages.limiter: with the height field's data, first None, or
    with the data reconciled with the first floor). Each tile's summary is a task on
    runner (distributed.TaskRunner; None: in this process, `write_floor_summary`) writing
    its own file, so the floor does not depend on where or in which order they ran;
    kept: the curtains' summaries, from which the first floor's are taken
    (KeptSummaries, first None only). halos: the HaloCache (after prune); name(t) names
    tile t in errors; label names the files. reconciled (with first only): {tile: paths}
    where each tile's task also writes its data reconciled with first
    (`write_reconciled`), for the refinement."""
    paths = {}
    if kept is not None:
        paths = {t: path for t, path in kept.paths.items() if t not in kept.removed}
    tiles = [t for t in halos.tiles() if t not in paths]
    new = {t: temps.new(f"{label}-{t}.bin") for t in tiles}
    keep = reconciled or {}

    def earlier(t: int):
        if kept is None or t not in kept.paths:
            return None
        return kept.paths[t], kept.removed[t]
    for _ in (runner or TaskRunner()).map(write_floor_summary, len(tiles),
                                          lambda i: (halos, tiles[i], first, new[tiles[i]], keep.get(tiles[i]),
                                                     earlier(tiles[i])),
                                          lambda i: name(tiles[i])):
        pass
    return {**paths, **new}


def edge_floor(halos: HaloCache, temps, label: str, first: float | None = None, runner=None,
               name=str, kept: KeptSummaries | None = None, reconciled: dict | None = None) -> float:
    """A noise floor of the survey, exactly: reduce_floor over floor_files' summaries,
    whose files it then removes."""
    floor = median_of_files(list(floor_files(halos, temps, label, first, runner, name, kept, reconciled).values()),
                            reduce_floor)
    for path in (kept.paths.values() if kept is not None else ()):
        path.unlink(missing_ok=True)            # those not taken as they were: replaced by new files
    return floor


def write_floor_summary(halos: HaloCache, tile: int, first: float | None, path, reconciled_paths=None,
                        earlier=None) -> None:
    """Write tile's limiter.floor_summary (float64) to path; with reconciled_paths (and the
    first floor), its data reconciled with the first floor there too (`write_reconciled`);
    earlier: (the file of its summary before some triangles were removed, those
    triangles (r, 3) survey numbers with a corner in its cell), from which the first
    floor's summary is taken (limiter.floor_summary_after; first None only)."""
    halo = halos.halo(tile)
    if earlier is not None:
        summary = np.fromfile(earlier[0], dtype="<f8")
        removed = tile_rows(halo.records["index"], earlier[1])
        if (removed >= 0).all():           # the halo rule: every corner lies within 4 edges of the cell
            floor_summary_after(halo, summary, removed).astype("<f8", copy=False).tofile(path)
            return
    if reconciled_paths is None:
        floor_summary(halo, first).astype("<f8", copy=False).tofile(path)
        return
    summary, reconciled = reconciled_summary(halo, first)
    summary.astype("<f8", copy=False).tofile(path)
    write_reconciled(reconciled, reconciled_paths)


RECONCILED = np.dtype([("z", "<f8"), ("gx", "<f8"), ("gy", "<f8"), ("lifted", "?"), ("moved", "?")])
"""A halo vertex's data reconciled with the first noise floor, a row per vertex in halo order."""


def write_reconciled(reconciled: Reconciliation, paths) -> None:
    """Write a limiter.Reconciliation to paths: its vertices as RECONCILED rows (26 bytes a
    halo vertex), and its edges (topology.edge_slots, 8 bytes an edge) as int32."""
    rows = np.empty(len(reconciled.values), dtype=RECONCILED)
    rows["z"], rows["lifted"], rows["moved"] = reconciled.values, reconciled.lifted, reconciled.moved
    rows["gx"], rows["gy"] = reconciled.gradients[:, 0], reconciled.gradients[:, 1]
    rows.tofile(paths[0])
    reconciled.edges.astype("<i4", copy=False).tofile(paths[1])


def read_reconciled(paths) -> Reconciliation:
    """The limiter.Reconciliation write_reconciled wrote to paths."""
    rows = np.fromfile(paths[0], dtype=RECONCILED)
    return Reconciliation(np.ascontiguousarray(rows["z"]), np.column_stack([rows["gx"], rows["gy"]]),
                          np.ascontiguousarray(rows["lifted"]), np.ascontiguousarray(rows["moved"]),
                          np.fromfile(paths[1], dtype="<i4").reshape(-1, 2))


def noise_floors(halos: HaloCache, temps, runner=None, name=str, kept: KeptSummaries | None = None,
                 reconciled: dict | None = None) -> NoiseFloors:
    """The limiter's two noise floors of the survey (edge_floor twice: the second with
    the data reconciled with the first); kept: the curtains' summaries (floor_files);
    reconciled: {tile: paths} where the second floor's tasks also write each tile's data
    reconciled with the first (`write_reconciled`; None: not kept)."""
    first = edge_floor(halos, temps, "residuals-first", None, runner, name, kept)
    return NoiseFloors(first, edge_floor(halos, temps, "residuals-second", first, runner, name,
                                         reconciled=reconciled))


class TiledLimiter:
    """The overshoot limiter over the tiles: the survey's noise floors, found on
    construction; a refinement task (refine_runs, through `tile`) limits its tile's
    data from the cached halo (halos, picklable) and these floors (limiter.tile_limits)."""

    def __init__(self, halos: HaloCache, temps, runner=None, name=str, kept: KeptSummaries | None = None):
        self.halos = halos
        # each tile's data reconciled with the first floor, as its second floor's task left it
        self.reconciled = {t: (temps.new(f"reconciled-{t}.bin"), temps.new(f"edges-{t}.bin")) for t in halos.tiles()}
        self.floors = noise_floors(halos, temps, runner, name, kept, self.reconciled)
        self.limited = self.turned = self.lifted = 0

    def tile(self, tile: int, triangles: np.ndarray) -> TileLimits:
        """limiter.TileLimits of the tile's own triangles (survey numbers), from the tile's
        halo and its data reconciled by the second floor's task (not reconciled again)."""
        return tile_limits(self.halos.halo(tile), triangles, self.floors, read_reconciled(self.reconciled[tile]))

    def report(self) -> dict:
        return {"gradients_limited": self.limited, "directions_changed": self.turned,
                "heights_reconciled": self.lifted,
                "noise_floors": [self.floors.first, self.floors.second]}


FLOAT_BLOCK = 1 << 20
"""Residuals read per block (8 MB): streamed_median makes a few block-sized temporaries
per pass (bit patterns, shifted digits, masks), so the block bounds the noise floors' peak."""


def median_of_files(paths, reduce=streamed_median, remove: bool = True) -> float:
    """The exact median of the float64 values in the files `paths` (reduce's of their
    blocks: streamed_median's, as np.median gives it; edge_floor passes the limiter's
    reduce_floor), which it then removes (remove=False: keeps, for another floor)."""
    def blocks():
        for path in paths:
            with open(path, "rb") as file:
                yield from file_blocks(file, "<f8", FLOAT_BLOCK)
    median = reduce(blocks)
    for path in paths if remove else ():
        path.unlink()
    return median
