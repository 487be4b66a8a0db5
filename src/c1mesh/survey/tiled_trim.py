"""The trim's sliver peel (trim.trim) on a survey fitted in tiles.

After the long-edge rule, `trim` peels thin triangles (circle ratio below
min_circle_ratio) off the boundary, and then, repeatedly, the thin triangles each removal
exposes. What it removes is therefore every connected set of thin triangles (joined
through shared edges) with at least one triangle on the boundary of what the long-edge
rule kept. Thin triangles are rare in a Delaunay triangulation (219 of 1M on synthetic
terrain, 28 of 50k on Autzen ground), so the survey's list of them fits in memory:

- one pass over the tiles: each tile reads its halo (tiled_limiter.HaloCache, cell + 3
  longest edges for the limiter; the peel needs 2, which hold both triangles of every
  edge of its own triangles) and lists its own thin triangles, with whether each has an
  edge no other final triangle shares;
- in memory: the components of that list through shared edges; those with a boundary
  triangle are peeled;
- each tile's triangle file loses its peeled triangles.

Bow-tie removal (all but the largest fan at a vertex where fans meet; ties by the fans'
smallest sorted corner triple, a rule of point numbers) is decided by the tile whose cell
holds the vertex, as its halo holds the vertex's whole star (`bowtie_cuts`); curtains
(c1mesh.stages.curtains) are per triangle given the survey's noise floor (`curtain_cuts`).
tiled_fit._trim chains these into trim's loop and remove_curtains' clean-up.
"""
from __future__ import annotations

import numpy as np

def thin_triangles(halo, min_ratio: float, grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tile's own thin triangles: (k, 3) survey numbers, (k,) bool whether each lies
    on the boundary, (k, 3) the tile of each corner (grid: the buffered_delaunay.TileGrid).
    halo: a tiled_limiter.Halo (own triangles: lowest corner in the cell)."""
    from c1mesh.stages.trim import edge_lengths, triangle_neighbours, circle_ratio

    triangles = halo.triangles
    if not len(triangles):
        return np.empty((0, 3), np.int64), np.empty(0, bool), np.empty((0, 3), np.int64)
    own = halo.own[triangles.min(axis=1)]
    thin = np.zeros(len(triangles), dtype=bool)
    thin[own] = circle_ratio(edge_lengths(halo.points, triangles[own])) < min_ratio
    boundary = (triangle_neighbours(triangles, len(halo.records))[thin] < 0).any(axis=1)
    return halo.records["index"][triangles[thin]], boundary, corner_tiles(halo, triangles[thin], grid)


def peeled(triangles: np.ndarray, boundary: np.ndarray) -> np.ndarray:
    """(k,) bool: which of the thin triangles (k, 3) (survey numbers) the peel removes:
    those in a component, through shared edges, with a boundary triangle (boundary (k,))."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    k = len(triangles)
    if not k or not boundary.any():
        return np.zeros(k, dtype=bool)
    ends = np.concatenate([np.sort(triangles[:, [a, b]], axis=1) for a, b in ((1, 2), (2, 0), (0, 1))])
    owner = np.tile(np.arange(k), 3)
    order = np.lexsort((ends[:, 1], ends[:, 0]))
    ends, owner = ends[order], owner[order]
    same = np.flatnonzero((ends[1:] == ends[:-1]).all(axis=1))
    graph = coo_matrix((np.ones(same.size, np.int8), (owner[same], owner[same + 1])), shape=(k, k))
    _, label = connected_components(graph, directed=False)
    return np.isin(label, label[boundary])


def drop_triangles(triangles: np.ndarray, removed: np.ndarray, columns: int = 3) -> np.ndarray:
    """The rows of triangles (T, >= 3) whose first three entries are not, as a set of
    corners, a row of removed (R, 3, few): only rows sharing a removed triangle's lowest
    corner are compared."""
    if not len(removed) or not len(triangles):
        return triangles
    corners = triangles[:, :columns]
    lowest = corners.min(axis=1)
    removed_lowest = removed.min(axis=1)
    candidates = np.flatnonzero(np.isin(lowest, removed_lowest))
    if not len(candidates):
        return triangles
    # Only removed triangles that share a lowest corner with a candidate can match: a
    # survey's removed list grows with the survey, a halo's share of it does not.
    near = removed[np.isin(removed_lowest, lowest[candidates])]
    gone = {tuple(row) for row in np.sort(near, axis=1).tolist()}
    rows = np.sort(corners[candidates], axis=1).tolist()
    keep = np.ones(len(triangles), dtype=bool)
    keep[[c for c, row in zip(candidates.tolist(), rows) if tuple(row) in gone]] = False
    return triangles[keep]


def bowtie_cuts(halo, grid) -> tuple[np.ndarray, np.ndarray]:
    """What trim's bow-tie removal cuts around the tile's own vertices: (k, 3) survey
    numbers of the triangles of every fan but the kept one, and (k, 3) the tile of each
    corner. halo: a tiled_limiter.Halo, which holds the whole star of every own vertex
    (its reach is at least one longest edge); the fan tie-break
    (trim.remove_bowties) uses point numbers alone, and the halo's rows follow
    the survey numbers, so the tile decides as the whole survey does."""
    from c1mesh.stages.trim import triangle_neighbours, remove_bowties

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
    from c1mesh.stages.curtains import REASONS, curtain_triangles

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
