"""A DEM's fill of the trim's holes on a survey fitted in tiles (c1mesh.pipeline.bounded_fit):
the scheduling of pipeline.driver.filled_mesh over the tiles, with its result.

In memory the filled triangles are the union of the trimmed mesh and the Delaunay
triangulation trimmed again without max_edge (the sliver peel and bow-ties of
c1mesh.stages.trim), then without curtains by the noise rule alone (no view rules:
c1mesh.stages.curtains). Both are subsets of the one Delaunay triangulation, which the
tiles certify (survey.buffered_delaunay), so here:

- the whole Delaunay triangulation is triangulated again in tiles without a max_edge
  (delaunay_runs.triangulate_tiles: buffered_delaunay.tile_triangles, each tile's buffer
  grown until its own triangles are final);
- its halos (halos.HaloCache, reach 4 longest edges of that triangulation) carry the
  same trim run as the mesh's (trim_runs.trim_tiles, view rules off): the peel, the
  bow-ties, the curtains' noise floor over the peeled triangulation, the curtains;
- each tile's filled triangles are its trimmed ones and those of its re-trimmed ones the
  trim removed (`union_triangles`), with which of them the trim kept.

Triangles of the union belong to the tile of their lowest-numbered corner, as both
parts' do. The halos of the second trim (and of the limiter over the filled
triangulation, bounded_fit) grow with the longest edge there: across the widest hole or
concavity of the hull, so a survey with wide holes reads much of itself per tile
(docs/tiles.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.survey.delaunay_runs import triangulate_tiles
from c1mesh.survey.halos import HaloCache, halo_reach, longest_final_edge
from c1mesh.survey.trim_runs import trim_tiles


@dataclass(frozen=True)
class FilledTiles:
    """The survey's filled triangulation, tile by tile: files, per tile the .npy of its own
    filled triangles (survey numbers); trimmed, per tile the .npy (bool) of which of them
    the trim kept (the rest span the holes); buffers, per tile the whole triangulation's
    buffer (its own triangles' corners lie within it, frame units); longest, the longest
    edge of the filled triangles; spanning, how many span holes."""

    files: list
    trimmed: list
    buffers: np.ndarray
    longest: float
    spanning: int


def fill_tiles(heights, grid, kept_files, temps, runner, rows) -> FilledTiles:
    """The filled triangulation (module docstring) of the survey whose trimmed triangles are
    kept_files (per tile a .npy, survey numbers). heights: the tile_spill.TileSpill of
    height records; grid: the buffered_delaunay.TileGrid; temps: inputs.Temps; runner:
    distributed.TaskRunner; rows: task_rows.TileRows."""
    _, whole, buffers, _ = triangulate_tiles(heights, grid, None, temps, runner, rows, label="whole")
    halos = HaloCache(heights, whole, grid, halo_reach(longest_final_edge(heights, whole, grid, buffers)),
                      temps, label="whole-halo")
    halos.prefetch(runner, rows.name)
    trim_tiles(halos, grid, temps, False, runner, rows.name)
    files, flags, spanning = [], [], 0
    for t in range(len(grid)):
        kept = np.load(kept_files[t]) if kept_files[t] is not None else np.empty((0, 3), np.int64)
        union, trimmed = union_triangles(kept, np.load(whole[t]))
        files.append(temps.new(f"filled-{t}.npy"))
        flags.append(temps.new(f"filled-trimmed-{t}.npy"))
        _save(files[-1], union)
        _save(flags[-1], trimmed)
        spanning += int((~trimmed).sum())
        whole[t].unlink(missing_ok=True)
    longest = longest_final_edge(heights, files, grid, buffers)
    return FilledTiles(files, flags, buffers, longest, spanning)


def union_triangles(kept: np.ndarray, whole: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(union (k + s, 3), trimmed (k + s,) bool): the triangles kept (k, 3) then those of
    whole (w, 3) that are not among them (the same triangle may come in either
    orientation), and which rows are kept's."""
    def keys(triangles):
        return np.sort(triangles, axis=1).view([("a", "<i8"), ("b", "<i8"), ("c", "<i8")]).ravel()
    kept, whole = kept.astype(np.int64), whole.astype(np.int64)
    extra = whole[~np.isin(keys(whole), keys(kept))] if len(whole) else whole
    trimmed = np.concatenate([np.ones(len(kept), bool), np.zeros(len(extra), bool)])
    return np.concatenate([kept, extra]), trimmed


def _save(path, array: np.ndarray) -> None:
    with open(path, "wb") as file:
        np.save(file, array)
