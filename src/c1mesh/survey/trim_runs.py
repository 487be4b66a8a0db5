"""The fit's trim stage on a survey fitted in tiles: the scheduling of the rules of
c1mesh.stages.trim (sliver peel, bow-ties) and c1mesh.stages.curtains over the survey's
halos, as pipeline.build_surface runs them on its one tile, with the same result
(tests/test_tiled_fit.py). The rules, the peel's reduce and the loop are the stages';
what is here is which halo a tile step reads, where the removed triangles go, and the
tiles' triangle files rewritten without them.

A tile's halo (halos.HaloCache: its cell grown by 4 longest final edges) holds both
triangles of every edge of its own triangles and the whole star of every vertex in its
cell, which is what its steps read: its thin triangles with their boundary flags, its
bow-tie fans, its curtains. The long edges are gone already (buffered_delaunay.tile_pass;
an "auto" max_edge is survey-wide, c1mesh.survey.delaunay_runs), and the curtains'
noise floor is found survey-wide from every tile's summary (halos.floor_files), whose files the
limiter's first floor takes again, without the edges that only the triangles removed since
held (halos.KeptSummaries).
"""
from __future__ import annotations

from functools import cached_property
from typing import Any, Callable

import numpy as np

from c1mesh.core.threads import map_in_threads
from c1mesh.stages.curtains import record_rows, remove_curtain_run
from c1mesh.stages.trim import MIN_CIRCLE_RATIO, Cuts, Place, TrimTile, drop_triangles, trim_run
from c1mesh.stages.limiter import reduce_floor
from c1mesh.survey.halos import KeptSummaries, floor_files, median_of_files
from c1mesh.survey.tile_spill import save_array


class TrimRuns:
    """A survey's tiles as the trim's TrimRun: each step reads its tile's halo from the
    cache (halos: halos.HaloCache, which drops the removed triangles as it loads a
    halo), in the thread knob's threads, results in tile order; removed triangles are kept
    by the tile that owns them (the tile of their lowest-numbered corner) in halos.removed.
    grid: the buffered_delaunay.TileGrid."""

    def __init__(self, halos, grid):
        self.halos, self.grid = halos, grid
        # once recording: tile -> the removed triangles with a corner in its cell, since then
        self.since: dict[int, list[np.ndarray]] | None = None

    def map(self, step: Callable[[TrimTile], Any], tiles: set[int] | None = None) -> list:
        chosen = self.halos.tiles() if tiles is None else sorted(set(tiles) & set(self.halos.tiles()))
        return map_in_threads(lambda t: step(self.tile(t)), chosen)

    def tile(self, t: int) -> TrimTile:
        """Tile t's halo as a TrimTile, every triangle alive, its point rows made when a
        rule first reads them (HaloTrimTile)."""
        halo, home = self.halos.halo_and_homes(t)
        return HaloTrimTile(halo.records, halo.triangles, Place(halo.records["index"], home.astype(np.int64), t))

    def remove(self, cuts: Cuts) -> None:
        if self.since is not None:
            for t in cuts.tile_set():
                self.since.setdefault(t, []).append(cuts.corners[(cuts.tiles == t).any(axis=1)])
        owners = cuts.tiles[np.arange(len(cuts)), np.argmin(cuts.corners, axis=1)]
        order = np.argsort(owners, kind="stable")
        tile_numbers, starts = np.unique(owners[order], return_index=True)
        for t, group in zip(tile_numbers.tolist(), np.split(cuts.corners[order], starts[1:])):
            earlier = self.halos.removed.get(t)
            self.halos.removed[t] = group if earlier is None else np.concatenate([earlier, group])

    def write_files(self) -> None:
        """Drop the removed triangles from their owners' triangle files and the cached
        halos, in the thread knob's threads (each tile its own file)."""
        def write(t: int) -> None:
            triangles = np.load(self.halos.files[t])
            save_array(self.halos.files[t], drop_triangles(triangles, self.halos.removed[t]))
        map_in_threads(write, list(self.halos.removed))
        self.halos.prune()


class HaloTrimTile(TrimTile):
    """A survey's halo as a TrimTile (records: its VERTEX records; triangles into them;
    place: its trim.Place), every triangle alive, whose points, curtains.point_rows'
    (x, y, z, gx, gy) rows, are made when a rule first reads them: the bow-tie rounds
    never do, and the rows cost a third of a halo load (1.85 s of the parent's CPU over
    the 12M survey's 240 loads)."""

    def __init__(self, records: np.ndarray, triangles: np.ndarray, place: Place):
        super().__init__(triangles, np.ones(len(triangles), dtype=bool), len(records), None, place)
        self.records = records

    @cached_property
    def points(self) -> np.ndarray:
        return record_rows(self.records)


def trim_tiles(halos, grid, temps, view_rules: bool = True, runner=None,
               name=str) -> tuple[dict[str, int], KeptSummaries]:
    """The in-memory default trim after the long-edge rule, over the tiles: trim.trim_run
    (slivers, bow-ties), then curtains.remove_curtain_run with the survey's noise floor,
    as pipeline.build_surface runs them. halos: the halos.HaloCache; grid: the
    buffered_delaunay.TileGrid; temps: inputs.Temps; view_rules:
    curtains.view_rules_apply; runner (distributed.TaskRunner; None: this process) runs
    the noise floor's summary per tile, name(t) names tile t in its errors. The removed
    triangles leave their tiles' files. Returns the removed counts by reason (as
    TrimReport.removed) and the curtains' floor summaries, kept for the limiter's first
    floor (halos.KeptSummaries)."""
    run = TrimRuns(halos, grid)
    thin, counts = trim_run(run, MIN_CIRCLE_RATIO)
    paths = floor_files(halos, temps, "residuals-curtains", runner=runner, name=name)
    floor = median_of_files(list(paths.values()), reduce_floor, remove=False)
    run.since = {}
    curtains, cleanup = remove_curtain_run(run, floor, view_rules, thin)
    run.write_files()
    removed = {t: np.concatenate(parts) for t, parts in run.since.items()}
    return ({"sliver": counts["sliver"] + cleanup["sliver"], "bowtie": counts["bowtie"] + cleanup["bowtie"],
             **curtains}, KeptSummaries(paths, removed))
