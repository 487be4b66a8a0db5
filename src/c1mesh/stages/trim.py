"""Trimming of what should not be meshed: the fit's trim stage after the Delaunay triangulation.

`trim` removes triangles that bridge gaps (any edge longer than `max_edge`) and then peels
thin triangles ("slivers") off the boundary, because the spline divides by quantities that
vanish as triangles flatten; fans that touch the rest at one vertex ("bowties") go too.
The memory-bounded survey fit runs the same rules per tile (c1mesh.survey.tiled_trim).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from c1mesh.core.errors import InputError
from c1mesh.core.threads import overlap, parallel_blocks
from c1mesh.engine.topology import EdgeTable, edge_table_sides, live_edges, sub_table
from c1mesh.engine.topology import triangle_neighbours as topology_neighbours
from c1mesh.engine.triangulation import as_xy
from c1mesh.stages import _trim as kernel

AUTO_EDGE_FACTOR = 4.0
"""max_edge="auto" is this times the median edge length. In the Delaunay triangulation of
uniform random points (the most irregular gap-free sampling) the longest edge of a triangle
stays below ~4x the median edge: 0-2 of 650,000 interior triangles exceed it. Real LiDAR
ground (4_6_crop.las, class 2) loses 4% of its area at 4x, mostly under trees and buildings
(81% of that area holds non-ground returns); at 2.5x it would also cut the many holes left
by one or two missing points."""


@dataclass
class TrimReport:
    """What `trim` did.

    triangles_before / triangles_after: counts in and out.
    removed: triangles removed by reason: "long_edge" (an edge longer than max_edge),
             "sliver" (thin boundary triangles), "bowtie" (fans that touched the rest of
             the mesh at a single vertex).
    max_edge: the edge-length limit used (local units), or None when disabled.
    unreferenced_points: points of xy that no remaining triangle uses.
    """

    triangles_before: int
    triangles_after: int
    removed: dict[str, int] = field(default_factory=dict)
    max_edge: float | None = None
    unreferenced_points: int = 0


KERNEL_BLOCK = 1 << 14
"""Triangles per block of the edge-length kernel, run in the thread knob's threads
(core.threads.parallel_blocks; Python threads, not OpenMP, whose thread pool does not
survive a fork: a forked --jobs worker would hang in it)."""

MIN_CIRCLE_RATIO = 0.01
"""trim's default: a boundary triangle whose inscribed/circumscribed radius ratio is below
this is a sliver (the in-memory and the tiled trim use the same value)."""


def check_triangles_left(count: int) -> None:
    """InputError when the trim left no triangle (`count` 0): nothing to fit or refine. Every
    path says it right after its trim, before the smoothing fit or the refinement."""
    if count == 0:
        raise InputError("no triangles are left after trimming; try --max-edge none")


def trim(xy: ArrayLike, triangles: ArrayLike, max_edge: str | float | None = "auto",
         min_circle_ratio: float = MIN_CIRCLE_RATIO) -> tuple[np.ndarray, TrimReport]:
    """Remove gap-bridging and thin boundary triangles; return (triangles (T', 3), report).

    xy:        (n, 2) plane points; triangles: (T, 3) indices into xy, e.g. from `delaunay`.
    max_edge:  triangles with an edge longer than this are removed (bridges over gaps,
               long hull triangles; holes stay holes). "auto" = AUTO_EDGE_FACTOR x the
               median edge length of the input triangulation; None (or "none") disables.
    min_circle_ratio: boundary triangles whose inradius/circumradius ratio, scaled so an
               equilateral triangle has 1 (matplotlib's TriAnalyzer ratio x 2), is below
               this are removed, repeatedly while newly exposed boundary triangles
               qualify. Interior triangles are never removed by this rule. 0 disables.
    Guarantees: the result is a subset of the input in input order and orientation; if
    the input is edge-manifold (every edge in at most 2 triangles, as any triangulation
    is) so is the result, and no vertex is a bowtie: the triangles around every vertex
    form one fan (where two fans met at a vertex, the smaller ones are removed).
    Raises InputError for bad shapes, indices, options, or a non-edge-manifold input.
    `trim_mesh` is the same trim for a fit that goes on with the kept triangles' edges.
    """
    pts = as_xy(xy)
    tri = _as_triangles(triangles, pts.shape[0])
    lengths, neighbours = overlap(lambda: edge_lengths(pts, tri),     # independent
                                  lambda: triangle_neighbours(tri, pts.shape[0]))
    alive, report = _trim(pts.shape[0], tri, lengths, neighbours, max_edge, min_circle_ratio)
    return tri[alive], report


class TrimmedMesh:
    """The triangles a trim kept, with the topology of the triangulation they were cut from,
    so the stages after the trim reuse its one edge sort: curtains.remove_curtains (the
    noise floor's edges, the re-trim around its holes) and the interpolator (`edge_table`).

    source (T, 3) int64: the triangulation trimmed; alive (T,) bool: the kept triangles;
    triangles (T', 3): source[alive], in input order and orientation; table, other,
    neighbours: topology.edge_table_sides(source, n_points); lengths (T, 3): edge_lengths
    of source. `without(drop)` removes more triangles (sharing the rest).
    """

    def __init__(self, source: np.ndarray, alive: np.ndarray, table: EdgeTable, other: np.ndarray,
                 neighbours: np.ndarray, lengths: np.ndarray, n_points: int):
        self.source, self.alive, self.table, self.other = source, alive, table, other
        self.neighbours, self.lengths, self.n_points = neighbours, lengths, n_points

    @cached_property
    def triangles(self) -> np.ndarray:
        """source[alive] (T', 3), made when first asked: a trim, its curtains and their
        re-trim each make a TrimmedMesh, and only the last one's triangles are needed."""
        return np.compress(self.alive, self.source, axis=0)     # 3x faster than a 2-d mask

    @classmethod
    def of(cls, xy: np.ndarray, triangles: ArrayLike) -> "TrimmedMesh":
        """All of ``triangles`` (T, 3) over the points xy (n, 2), nothing removed."""
        pts = as_xy(xy)
        tri = _as_triangles(triangles, pts.shape[0])
        lengths, (table, other, neighbours) = overlap(lambda: edge_lengths(pts, tri),
                                                      lambda: edge_table_sides(tri, pts.shape[0]))
        return cls(tri, np.ones(tri.shape[0], dtype=bool), table, other, neighbours, lengths, pts.shape[0])

    def with_alive(self, alive: np.ndarray) -> "TrimmedMesh":
        """The same source with the triangles ``alive`` (T,) bool kept."""
        return TrimmedMesh(self.source, alive, self.table, self.other, self.neighbours,
                           self.lengths, self.n_points)

    def live_edge_mask(self) -> np.ndarray:
        """(E,) bool over table.edges: the edges of the kept triangles."""
        return live_edges(self.table, self.alive, self.other)[1] > 0

    def edges(self) -> np.ndarray:
        """(E', 2) the kept triangles' unique edges, lower vertex first, sorted."""
        return np.compress(self.live_edge_mask(), self.table.edges, axis=0)

    def edge_table(self, used: np.ndarray | None = None) -> EdgeTable:
        """topology.edge_table of the kept triangles (self.triangles), with the vertices
        renumbered by ``used`` as pipeline.steps.compact_vertices does (None: not)."""
        return sub_table(self.table, self.alive, self.other, used)


def trim_mesh(xy: ArrayLike, triangles: ArrayLike, max_edge: str | float | None = "auto",
              min_circle_ratio: float = MIN_CIRCLE_RATIO) -> tuple[TrimmedMesh, TrimReport]:
    """`trim`, with the kept triangles as a TrimmedMesh (mesh.triangles: `trim`'s result).

    Its edge table comes from the same sort as its neighbours, so a fit numbers the edges
    once (a non-manifold input raises InputError from topology.edge_table instead)."""
    mesh = TrimmedMesh.of(xy, triangles)
    alive, report = _trim(mesh.n_points, mesh.source, mesh.lengths, mesh.neighbours, max_edge,
                          min_circle_ratio)
    return mesh.with_alive(alive), report


def trim_again(mesh: TrimmedMesh, max_edge: str | float | None,
               min_circle_ratio: float = MIN_CIRCLE_RATIO) -> tuple[TrimmedMesh, TrimReport]:
    """trim_mesh of the triangulation `mesh` was cut from (mesh.source) with another
    max_edge, reusing its edge lengths and neighbours (no second edge sort): a DEM's fill
    (c1mesh.pipeline.driver.filled_mesh) trims it again without max_edge."""
    alive, report = _trim(mesh.n_points, mesh.source, mesh.lengths, mesh.neighbours, max_edge,
                          min_circle_ratio)
    return mesh.with_alive(alive), report


def retrim(mesh: TrimmedMesh, drop: np.ndarray, min_circle_ratio: float = MIN_CIRCLE_RATIO
           ) -> tuple[TrimmedMesh, dict[str, int]]:
    """The mesh without the live triangles ``drop`` (indices into mesh.source), and without
    the slivers and bowties their holes expose; and {"long_edge": 0, "sliver", "bowtie"}.

    The same as trim(xy, mesh.triangles minus drop, max_edge=None) for a mesh that trim
    left (no thin triangle on its boundary, no bowtie vertex): only the triangles beside
    the holes can be newly on the boundary, and only vertices of removed triangles can
    become bowties, so peeling starts beside the holes and bowties are looked for there.
    """
    alive = mesh.alive.copy()
    alive[drop] = False
    at = np.zeros(mesh.n_points, dtype=bool)
    at[mesh.source[drop].ravel()] = True
    thin = _Thin(mesh.lengths, min_circle_ratio)
    sliver, bowtie = _peel_and_cut(mesh.source, alive, mesh.neighbours, thin,
                                   mesh.neighbours[drop].ravel(), at)
    return mesh.with_alive(alive), {"long_edge": 0, "sliver": sliver, "bowtie": bowtie}


def _trim(n_points: int, tri: np.ndarray, lengths: np.ndarray, neighbours: np.ndarray, max_edge,
          min_circle_ratio: float) -> tuple[np.ndarray, TrimReport]:
    """`trim` given the edge lengths and neighbours: (alive (T,) bool, report)."""
    limit = _edge_limit(lengths, neighbours, max_edge)
    if not 0.0 <= min_circle_ratio <= 1.0:
        raise InputError(f"min_circle_ratio must be between 0 and 1, got {min_circle_ratio}")

    alive = np.ones(tri.shape[0], dtype=bool)
    if limit is not None:
        for k in range(3):
            alive &= ~(lengths[:, k] > limit)
    long_edge = int((~alive).sum())
    thin = _Thin(lengths, min_circle_ratio)
    front = np.flatnonzero(alive & _on_boundary(alive, neighbours))
    front = front[thin[front]]
    sliver, bowtie = _peel_and_cut(tri, alive, neighbours, thin, front)
    report = TrimReport(triangles_before=int(tri.shape[0]), triangles_after=int(np.count_nonzero(alive)),
                        removed={"long_edge": long_edge, "sliver": sliver, "bowtie": bowtie},
                        max_edge=limit, unreferenced_points=n_points - used_points(tri, alive, n_points))
    return alive, report


def _peel_and_cut(tri: np.ndarray, alive: np.ndarray, neighbours: np.ndarray, thin: "_Thin",
                  front: np.ndarray, at: np.ndarray | None = None) -> tuple[int, int]:
    """Peel thin boundary triangles from `front` and cut bowtie fans until neither is left;
    returns (slivers, bowtie triangles) removed. at: (n,) bool vertices whose stars may
    have changed (None: all), grown by the corners of every triangle removed here."""
    sliver = bowtie = 0
    while True:
        peeled = peel(alive, neighbours, thin, front)
        sliver += peeled.size
        if at is not None:
            at[tri[peeled].ravel()] = True
        cut = remove_bowties(tri, alive, neighbours, at)
        if cut.size == 0:
            return sliver, bowtie
        bowtie += cut.size
        if at is not None:
            at[tri[cut].ravel()] = True
        front = neighbours[cut].ravel()


def circle_ratio(lengths: np.ndarray) -> np.ndarray:
    """2 r_in / R_circ of triangles with edge lengths (T, 3): 1 for equilateral, 0 if flat.

    From Heron: 16 A^2 = P (P-2a)(P-2b)(P-2c) with r = 2A/P, R = abc/4A, so
    2r/R = (P-2a)(P-2b)(P-2c) / (abc).
    """
    a, b, c = lengths[:, 0], lengths[:, 1], lengths[:, 2]
    p = a + b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (p - 2 * a) * (p - 2 * b) * (p - 2 * c) / (a * b * c)
    return np.nan_to_num(np.clip(ratio, 0.0, 1.0), nan=0.0)


class _Thin:
    """thin[idx]: circle_ratio < min_ratio for triangles idx, computed only where asked
    (peeling looks at boundary triangles only) and remembered."""

    def __init__(self, lengths: np.ndarray, min_ratio: float):
        self.lengths, self.min_ratio = lengths, min_ratio
        self.known = np.zeros(lengths.shape[0], dtype=bool)
        self.value = np.zeros(lengths.shape[0], dtype=bool)

    def __getitem__(self, idx: np.ndarray) -> np.ndarray:
        new = idx[~self.known[idx]]
        self.value[new] = circle_ratio(self.lengths[new]) < self.min_ratio
        self.known[new] = True
        return self.value[idx]


def _as_triangles(triangles: ArrayLike, n: int) -> np.ndarray:
    tri = np.asarray(triangles)
    if tri.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer):
        raise InputError(f"triangles must be an integer array of shape (T, 3), got {tri.dtype} "
                         f"with shape {tri.shape}")
    if tri.min() < 0 or tri.max() >= n:
        raise InputError(f"triangle indices must lie in [0, {n}), got {tri.min()}..{tri.max()}")
    return tri.astype(np.int64, copy=False)


def edge_lengths(xy: np.ndarray, tri: np.ndarray, workers: int | None = None) -> np.ndarray:
    """(T, 3) length of the edge opposite vertex k of the triangles tri (T, 3), indices into
    xy (n, 2); lengths in xy's unit. The kernel (stages/_trim.pyx) runs over fixed blocks of
    KERNEL_BLOCK triangles in the thread knob's threads (workers: that many instead); each
    length is one hypot, the same at any count."""
    tri = np.ascontiguousarray(tri, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise InputError(f"triangles must have shape (T, 3), got {tri.shape}")
    if tri.size and (tri.min() < 0 or tri.max() >= len(xy)):
        raise InputError(f"triangle indices must lie in [0, {len(xy)}), got {tri.min()}..{tri.max()}")
    rows = np.ascontiguousarray(xy, dtype=np.float64)
    lengths = np.empty(tri.shape)
    parallel_blocks(lambda part: kernel.edge_lengths(rows, tri, lengths, part.start, part.stop),
                    tri.shape[0], KERNEL_BLOCK, threads=workers)
    return lengths


def triangle_neighbours(tri: np.ndarray, n: int) -> np.ndarray:
    """(T, 3) triangle across the edge opposite vertex k, or -1; InputError if an edge has 3+
    (topology.triangle_neighbours, the edge table's kernel without the table)."""
    return topology_neighbours(tri, n)


def _edge_limit(lengths: np.ndarray, neighbours: np.ndarray, max_edge) -> float | None:
    """The max_edge option resolved to a length, or None."""
    if max_edge is None or (isinstance(max_edge, str) and max_edge.strip().lower() == "none"):
        return None
    if isinstance(max_edge, str) and max_edge.strip().lower() == "auto":
        once = _each_edge_once(lengths, neighbours)
        return float(AUTO_EDGE_FACTOR * np.median(once, overwrite_input=True)) if once.size else None  # a temporary
    try:
        limit = float(max_edge)
    except (TypeError, ValueError):
        limit = float("nan")
    if not np.isfinite(limit) or limit <= 0:
        raise InputError(f"max_edge must be 'auto', None or a positive length, got {max_edge!r}")
    return limit


def _each_edge_once(lengths: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """The lengths (T, 3) of every edge once, from the triangle whose neighbour across it
    (neighbours (T, 3)) is none or later, in row order: the edges of the triangulation,
    each once (kernel: stages/_trim.pyx; one pass, no (T, 3) masks)."""
    once = np.empty(lengths.size)
    count = kernel.once_lengths(np.ascontiguousarray(lengths, dtype=np.float64),
                                np.ascontiguousarray(neighbours, dtype=np.int64), once)
    return once[:count]


def used_points(tri: np.ndarray, alive: np.ndarray, n_points: int) -> int:
    """How many of n_points points the triangles tri (T, 3) that are alive (T,) bool use
    (kernel: stages/_trim.pyx; no copy of the live triangles)."""
    used = np.zeros(n_points, dtype=np.uint8)
    kernel.mark_used(np.ascontiguousarray(tri, dtype=np.int64), np.ascontiguousarray(alive).view(np.uint8),
                     used)
    return int(np.count_nonzero(used))


def _live_rows(tri: np.ndarray, alive: np.ndarray, at: np.ndarray | None) -> np.ndarray:
    """Ascending indices of the live triangles of tri (T, 3) (alive (T,) bool) with a
    corner in at (n,) bool (None: every live one); kernel: stages/_trim.pyx."""
    rows = np.empty(tri.shape[0], dtype=np.int64)
    everywhere = at is None
    marks = np.zeros(1, dtype=np.uint8) if everywhere else np.ascontiguousarray(at).view(np.uint8)
    return rows[:kernel.live_rows(tri, alive.view(np.uint8), marks, everywhere, rows)]


def _corner_slots(tri: np.ndarray, rows: np.ndarray, marked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t, slot): the corners at marked (n,) bool vertices of the triangles rows (R,) of
    tri (T, 3), by row then slot: np.nonzero(marked[tri[rows]]) with t = rows[r], without
    the (R, 3) gathers (kernel: stages/_trim.pyx)."""
    t, slot = np.empty(3 * rows.size, dtype=np.int64), np.empty(3 * rows.size, dtype=np.int64)
    count = kernel.corner_slots(tri, rows, np.ascontiguousarray(marked).view(np.uint8), t, slot)
    return t[:count], slot[:count]


def _on_boundary(alive: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """(T,) True for triangles with an edge that has no live triangle across it."""
    return np.any((neighbours < 0) | ~alive[neighbours], axis=1)


def peel(alive: np.ndarray, neighbours: np.ndarray, thin, front: np.ndarray) -> np.ndarray:
    """Remove live thin triangles starting from `front`, then their thin live neighbours,
    repeatedly (a removed triangle exposes its neighbours). Returns the removed triangles.

    alive (T,) bool, changed in place; neighbours (T, 3) as triangle_neighbours gives
    them; thin: thin[idx] (T,) bool for triangle indices idx; front: the triangles to
    start from (those not live, thin and on the boundary are skipped). The survey fitted
    in tiles peels the survey's thin triangles with it (c1mesh.survey.tiled_trim.peeled)."""
    removed = []
    front = np.unique(front[front >= 0])
    front = front[alive[front] & thin[front] & _on_boundary(alive, neighbours[front])] \
        if front.size else front
    while front.size:
        alive[front] = False
        removed.append(front)
        nxt = np.unique(neighbours[front].ravel())
        nxt = nxt[nxt >= 0]
        front = nxt[alive[nxt] & thin[nxt]]
    return np.concatenate(removed) if removed else np.zeros(0, dtype=np.int64)


def remove_bowties(tri: np.ndarray, alive: np.ndarray, neighbours: np.ndarray,
                    at: np.ndarray | None = None) -> np.ndarray:
    """Remove all but the largest fan at every bowtie vertex; return the removed triangles.

    A vertex is a bowtie when more than 2 boundary edges meet there (each fan brings 2).
    A fan is a set of live triangles around the vertex joined through edges at it. Among
    fans of equal size the one whose smallest triangle (corners sorted, then compared
    lexicographically) comes first is kept: a rule of point numbers alone, so a tile that
    holds the vertex's star decides as the whole triangulation does (c1mesh.survey.tiled_trim).
    at: (n,) bool, the vertices to look at (None: all); a tile passes the vertices whose
    whole star it holds.
    """
    tri = np.ascontiguousarray(tri, dtype=np.int64)
    neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
    n = tri.max(initial=0) + 1
    live = _live_rows(tri, alive, None if at is None else at[:n])
    ends = np.zeros(n, dtype=np.int64)
    kernel.open_ends(tri, alive.view(np.uint8), neighbours, live, ends)
    bow = ends > 2
    if at is not None:
        bow &= at[:n]
    if not bow.any():
        return np.zeros(0, dtype=np.int64)
    t, j = _corner_slots(tri, live, bow)                      # incidences (triangle, slot)
    v = tri[t, j]
    key = v * len(tri) + t
    order = np.argsort(key)
    # neighbours through the two edges at v (opposite the other two slots)
    links = []
    for step in (1, 2):
        other = neighbours[t, (j + step) % 3]
        ok = (other >= 0) & alive[np.maximum(other, 0)]
        pos = order[np.searchsorted(key[order], v[ok] * len(tri) + other[ok])]
        links.append(np.stack([np.flatnonzero(ok), pos]))
    links = np.concatenate(links, axis=1)
    graph = coo_matrix((np.ones(links.shape[1], dtype=np.int8), tuple(links)), shape=(t.size,) * 2)
    fan = connected_components(graph, directed=False)[1]
    size = np.bincount(fan)
    # per vertex keep the fan with most triangles; ties: the fan holding the smallest
    # triangle as a sorted corner triple (order-free: the same in any triangle order)
    corners = np.sort(tri[t], axis=1)
    rank = np.empty(t.size, dtype=np.int64)
    rank[np.lexsort(corners.T[::-1])] = np.arange(t.size)
    smallest = np.full(size.size, t.size, dtype=np.int64)
    np.minimum.at(smallest, fan, rank)
    best = np.lexsort((smallest[fan], -size[fan], v))          # sorted by v, then best fan first
    first = np.ones(best.size, dtype=bool)
    first[1:] = v[best[1:]] != v[best[:-1]]
    keep_fan = np.zeros(size.size, dtype=bool)
    keep_fan[fan[best[first]]] = True
    cut = np.unique(t[~keep_fan[fan]])
    alive[cut] = False
    return cut
