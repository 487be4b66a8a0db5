"""The fit's trim stage on a survey fitted in tiles: c1mesh.stages.trim.trim (long edges,
sliver peel, bow-ties) then c1mesh.stages.curtains.remove_curtains, as
pipeline.build_surface runs them, with the same result (tests/test_tiled_fit.py).

Each rule runs the stage's own function, per tile on its halo (tiled_halo.Halo: the cell
grown by 4 longest final edges, which holds the whole star of every vertex within 3 of
the cell); what has to see the whole survey is orchestrated here, and only that:

- long edges, trim.trim's max_edge: per tile in buffered_delaunay.tile_pass (triangles
  whose trim.edge_lengths are all <= max_edge); "auto" (trim.AUTO_EDGE_FACTOR x the
  median edge) is survey-wide: buffered_delaunay.trimmed_delaunay, run by
  c1mesh.survey.tiled_triangulation before this module;
- which triangles are thin, trim.trim's sliver test: per tile, `thin_triangles`:
  trim.circle_ratio(trim.edge_lengths) < trim.MIN_CIRCLE_RATIO, on the boundary by
  trim.triangle_neighbours;
- the peel of trim.trim (its `_peel`): survey-wide, `peeled`, over the survey's list
  of thin triangles (below);
- bow-ties, trim.remove_bowties: per tile, `bowtie_cuts`, remove_bowties(at= the
  vertices in the tile's cell);
- trim.trim's loop (peel, bow-ties, peel again from the cut fans' neighbours, until no
  bow-tie is left): survey-wide, `_TrimState.settle`;
- curtains, curtains.curtain_triangles: per tile, `curtain_cuts`, with floor= the
  survey's curtains.noise_floor, found survey-wide by tiled_halo.edge_floor (the
  limiter's floor_summary per tile and reduce_floor, as curtains.noise_floor in memory);
- remove_curtains' second trim.trim(max_edge=None) of the holes: survey-wide,
  `_TrimState.settle` again from the curtains' neighbours.

`trim_tiles` chains these; the per-tile steps run in the thread knob's threads (the
parent's tile loops, results in tile order). Why the peel is survey-wide: `trim` peels
thin triangles (circle ratio below min_circle_ratio) off the boundary, and then,
repeatedly, the thin triangles each removal exposes. What it removes is therefore every
connected set of thin triangles (joined through shared edges) with at least one triangle
on the boundary of what the long-edge rule kept, and such a set may cross any number of
tiles. Thin triangles are rare in a Delaunay triangulation (219 of 1M on synthetic
terrain, 28 of 50k on Autzen ground), so the survey's list of them fits in memory:

- one pass over the tiles: each tile reads its halo (tiled_halo.HaloCache, cell + 3
  longest edges for the limiter; the peel needs 2, which hold both triangles of every
  edge of its own triangles) and lists its own thin triangles, with whether each has an
  edge no other final triangle shares;
- in memory: the components of that list through shared edges; those with a boundary
  triangle are peeled;
- each tile's triangle file loses its peeled triangles.

Bow-tie removal (all but the largest fan at a vertex where fans meet; ties by the fans'
smallest sorted corner triple, a rule of point numbers) is decided by the tile whose cell
holds the vertex, as its halo holds the vertex's whole star; a curtain is a property of
one triangle and its data, given the noise floor.
"""
from __future__ import annotations

import numpy as np

from c1mesh.core.threads import map_in_threads
from c1mesh.stages.curtains import REASONS, curtain_triangles
from c1mesh.stages.trim import MIN_CIRCLE_RATIO as min_ratio
from c1mesh.stages.trim import circle_ratio, edge_lengths, peel, remove_bowties, triangle_neighbours
from c1mesh.survey.tiled_halo import drop_triangles, edge_floor


def thin_triangles(halo, min_ratio: float, grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tile's own thin triangles: (k, 3) survey numbers, (k,) bool whether each lies
    on the boundary, (k, 3) the tile of each corner (grid: the buffered_delaunay.TileGrid).
    halo: a tiled_halo.Halo (own triangles: lowest corner in the cell)."""
    triangles = halo.triangles
    if not len(triangles):
        return np.empty((0, 3), np.int64), np.empty(0, bool), np.empty((0, 3), np.int64)
    own = halo.own[triangles.min(axis=1)]
    thin = np.zeros(len(triangles), dtype=bool)
    thin[own] = circle_ratio(edge_lengths(halo.points, triangles[own])) < min_ratio
    boundary = (triangle_neighbours(triangles, len(halo.records))[thin] < 0).any(axis=1)
    return halo.records["index"][triangles[thin]], boundary, corner_tiles(halo, triangles[thin], grid)


def peeled(triangles: np.ndarray, boundary: np.ndarray) -> np.ndarray:
    """(k,) bool: which of the thin triangles (k, 3) (survey numbers) the peel removes,
    boundary (k,): which lie on the boundary of the mesh. trim.peel over these triangles
    alone, all thin, starting from the boundary ones: it removes the components, through
    shared edges, that hold a boundary triangle, as it does in the whole triangulation (a
    thin triangle's non-thin neighbours are never peeled, so leaving them out changes
    nothing but the start, which `boundary` gives)."""
    k = len(triangles)
    if not k or not boundary.any():
        return np.zeros(k, dtype=bool)
    corners, local = np.unique(triangles, return_inverse=True)
    alive = np.ones(k, dtype=bool)
    peel(alive, triangle_neighbours(local.reshape(-1, 3), len(corners)), np.ones(k, dtype=bool),
         np.flatnonzero(boundary))
    return ~alive


def bowtie_cuts(halo, grid) -> tuple[np.ndarray, np.ndarray]:
    """What trim's bow-tie removal cuts around the tile's own vertices: (k, 3) survey
    numbers of the triangles of every fan but the kept one, and (k, 3) the tile of each
    corner. halo: a tiled_halo.Halo, which holds the whole star of every own vertex
    (its reach is at least one longest edge); the fan tie-break
    (trim.remove_bowties) uses point numbers alone, and the halo's rows follow
    the survey numbers, so the tile decides as the whole survey does."""
    triangles = halo.triangles
    if not len(triangles):
        return np.empty((0, 3), np.int64), np.empty((0, 3), np.int64)
    alive = np.ones(len(triangles), dtype=bool)
    cut = remove_bowties(triangles, alive, triangle_neighbours(triangles, len(halo.records)), at=halo.own)
    return halo.records["index"][triangles[cut]], corner_tiles(halo, triangles[cut], grid)


def curtain_cuts(halo, floor: float, grid, view_rules: bool = True
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The tile's own triangles that curtains.curtain_triangles drops with the survey's
    noise floor `floor` (and view_rules, curtains.view_rules_apply): (k, 3) survey
    numbers, (k, 3) the tile of each corner, and the count by reason."""
    triangles = halo.triangles
    if not len(triangles):
        return np.empty((0, 3), np.int64), np.empty((0, 3), np.int64), {reason: 0 for reason in REASONS}
    own = triangles[halo.own[triangles.min(axis=1)]]
    masks = curtain_triangles(halo.points, halo.records["z"], halo.gradients, own, floor=floor,
                              view_rules=view_rules)
    cut = np.logical_or.reduce([masks[reason] for reason in REASONS])
    return (halo.records["index"][own[cut]], corner_tiles(halo, own[cut], grid),
            {reason: int(masks[reason].sum()) for reason in REASONS})


def touching(triangles: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(k,) bool: which of triangles (k, 3) share an edge with one of others (m, 3)
    (survey numbers)."""
    if not len(triangles) or not len(others):
        return np.zeros(len(triangles), dtype=bool)
    n = int(max(triangles.max(), others.max())) + 1

    def keys(t):
        return [np.minimum(t[:, a], t[:, b]) * n + np.maximum(t[:, a], t[:, b]) for a, b in ((0, 1), (1, 2), (2, 0))]
    theirs = np.concatenate(keys(others))
    return np.logical_or.reduce([np.isin(k, theirs) for k in keys(triangles)])


def corner_tiles(halo, rows: np.ndarray, grid) -> np.ndarray:
    """(k, 3) the tile whose cell holds each corner of the halo's triangles rows (k, 3)."""
    if not len(rows):
        return np.empty((0, 3), np.int64)
    xy = np.column_stack([halo.records["x"][rows.ravel()], halo.records["y"][rows.ravel()]])
    return grid.tile_of(xy).reshape(-1, 3)


def owner_tiles(triangles: np.ndarray, tiles: np.ndarray) -> np.ndarray:
    """(k,) the tile owning each triangle (k, 3) (survey numbers), the tile of its
    lowest-numbered corner, given the tile of each corner (k, 3)."""
    return tiles[np.arange(len(triangles)), np.argmin(triangles, axis=1)]


def trim_tiles(halos, grid, temps, view_rules: bool = True) -> dict[str, int]:
    """The in-memory default trim after the long-edge rule, over the tiles
    (c1mesh.survey.tiled_trim): trim's sliver peel and bow-tie removal, then curtains
    (c1mesh.stages.curtains) with the survey's noise floor, then the peel and bow-tie removal
    of the holes they left, as pipeline.build_surface runs them. halos: the
    tiled_halo.HaloCache, whose `removed` grows as triangles go (each halo drops them
    as it loads); the removed triangles also leave their tiles' files. Returns the
    removed counts by reason (as TrimReport.removed). view_rules: curtains.view_rules_apply."""
    thin, boundary, tiles = [np.empty((0, 3), np.int64)], [np.empty(0, bool)], [np.empty((0, 3), np.int64)]
    for triangles, on_boundary, corners in map_in_threads(
            lambda t: thin_triangles(halos.halo(t), min_ratio, grid), list(halos.tiles())):
        thin.append(triangles)
        boundary.append(on_boundary)
        tiles.append(corners)
    state = _TrimState(halos, grid, np.concatenate(thin), np.concatenate(tiles))
    state.settle(np.concatenate(boundary), set(halos.tiles()))
    floor = edge_floor(halos, temps, "residuals-curtains")
    cut, corners, counts = [np.empty((0, 3), np.int64)], [np.empty((0, 3), np.int64)], {r: 0 for r in REASONS}
    for triangles, where, reasons in map_in_threads(
            lambda t: curtain_cuts(halos.halo(t), floor, grid, view_rules), list(halos.tiles())):
        cut.append(triangles)
        corners.append(where)
        for reason, count in reasons.items():
            counts[reason] += count
    cut, corners = np.concatenate(cut), np.concatenate(corners)
    state.remove(cut, corners)
    state.settle(state.next_to(cut), set(np.unique(corners).tolist()))
    state.write_files()
    return {"sliver": state.sliver, "bowtie": state.bowtie, **counts}


class _TrimState:
    """What the tiled trim has removed so far. thin (k, 3): every thin triangle of the
    survey after the long-edge rule (survey numbers; peeling only ever removes those),
    tiles (k, 3) the tile of each corner; `alive` marks those still in the mesh."""

    def __init__(self, halos, grid, thin: np.ndarray, tiles: np.ndarray):
        self.halos, self.grid, self.thin, self.tiles = halos, grid, thin, tiles
        self.alive = np.ones(len(thin), dtype=bool)
        self.sliver = self.bowtie = 0

    def remove(self, triangles: np.ndarray, tiles: np.ndarray) -> None:
        """Remove triangles (k, 3) whose corners lie in tiles (k, 3); a thin one (a
        bow-tie fan's or a curtain) can then no longer be peeled. The halo cache keeps
        them by owner tile (HaloCache.removed)."""
        if len(triangles):                  # compares only rows sharing a lowest corner with a thin one
            kept = drop_triangles(np.column_stack([self.thin, np.arange(len(self.thin))]), triangles)
            still = np.zeros(len(self.thin), dtype=bool)
            still[kept[:, 3]] = True
            self.alive &= still
        owners = owner_tiles(triangles, tiles)
        order = np.argsort(owners, kind="stable")
        tile_numbers, starts = np.unique(owners[order], return_index=True)
        for t, group in zip(tile_numbers.tolist(), np.split(triangles[order], starts[1:])):
            earlier = self.halos.removed.get(t)
            self.halos.removed[t] = group if earlier is None else np.concatenate([earlier, group])

    def next_to(self, triangles: np.ndarray) -> np.ndarray:
        """(k,) bool: the thin triangles sharing an edge with one of triangles."""
        return touching(self.thin, triangles)

    def settle(self, front: np.ndarray, pending: set) -> None:
        """trim's loop: peel the live thin components that hold a live `front` triangle
        (k,) bool, then cut bow-ties, peel from the cuts' neighbours, until no bow-tie is
        left (trim.trim). A bow-tie can only appear at a corner of a removed
        triangle, so a round looks only at the tiles holding such corners: `pending`
        (tile numbers) for the first, those of the triangles removed since, later."""
        while True:
            live = np.flatnonzero(self.alive)
            gone = live[peeled(self.thin[live], front[live])]
            self.alive[gone] = False
            self.sliver += len(gone)
            self.remove(self.thin[gone], self.tiles[gone])
            pending |= set(np.unique(self.tiles[gone]).tolist())
            cut, corners = [np.empty((0, 3), np.int64)], [np.empty((0, 3), np.int64)]
            for triangles, where in map_in_threads(lambda t: bowtie_cuts(self.halos.halo(t), self.grid),
                                                   sorted(pending & set(self.halos.tiles()))):
                cut.append(triangles)
                corners.append(where)
            cut, corners = np.concatenate(cut), np.concatenate(corners)
            if not len(cut):
                return
            self.bowtie += len(cut)
            self.remove(cut, corners)
            front, pending = self.next_to(cut), set(np.unique(corners).tolist())

    def write_files(self) -> None:
        """Drop the removed triangles from their owners' triangle files and the cached halos."""
        for t, removed in self.halos.removed.items():
            triangles = np.load(self.halos.files[t])
            with open(self.halos.files[t], "wb") as file:
                np.save(file, drop_triangles(triangles, removed))
        self.halos.prune()
