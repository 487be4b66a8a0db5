"""Edge numbering of a triangle mesh: one record per unique edge, shared by its triangles.

The RSD spline needs one direction vector per edge, used by both triangles that contain it
(that is what makes the union C1), so edges are numbered once and every triangle refers to
its three edges by number.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.threads import parallel_blocks
from c1mesh.engine import _topology


@dataclass(frozen=True)
class EdgeTable:
    """Unique edges of a mesh and how triangles refer to them.

    edges:      (E, 2) int64 vertex indices with edges[:, 0] < edges[:, 1], sorted
                lexicographically — the documented order of ``directions``.
    tri_edge:   (T, 3) int64: the edge opposite local vertex k of each triangle.
    forward:    (T, 3) bool: local edge k, run from vertex k+1 to vertex k+2, goes from
                edges[e, 0] to edges[e, 1] (the edge's own direction).
    owner:      (E,) int64: one triangle containing each edge (the one whose values the
                refinement uses for points on that edge).
    owner_slot: (E,) int64: the local vertex k that edge is opposite to in ``owner``.
    count:      (E,) int64: triangles containing each edge (1 = boundary, 2 = interior).
    """

    edges: np.ndarray
    tri_edge: np.ndarray
    forward: np.ndarray
    owner: np.ndarray
    owner_slot: np.ndarray
    count: np.ndarray


def edge_table(triangles: np.ndarray, n_points: int) -> EdgeTable:
    """Number the unique edges of ``triangles`` (T, 3); raise InputError for a non-manifold edge."""
    return _edge_table(triangles, n_points, False)[0]


def edge_table_sides(triangles: np.ndarray, n_points: int) -> tuple[EdgeTable, np.ndarray, np.ndarray]:
    """`edge_table`, with what the same sort gives of each edge's second triangle:
    (table, other, neighbours).

    other:      (E,) int64 the slot 3t + k where the edge's second triangle t holds it
                opposite local vertex k (the first is owner, owner_slot), -1 on a boundary edge;
    neighbours: (T, 3) int64 the triangle across the edge opposite local vertex k, or -1
                (what `triangle_neighbours` gives alone).
    """
    return _edge_table(triangles, n_points, True)


def edge_slots(table: EdgeTable, other: np.ndarray) -> np.ndarray:
    """(E, 2) int32: each edge's owner slot 3t + k and its second slot (-1: none), from
    `edge_table_sides`' table and other. With the triangles, that is everything the two
    hold, in 8 bytes an edge against their 72 (`table_from_slots` gives them back): a
    survey's tile keeps its table this way between two passes over it."""
    slots = np.empty((len(other), 2), dtype=np.int32)
    np.add(3 * table.owner, table.owner_slot, out=slots[:, 0], casting="unsafe")     # < LIMIT: _checked
    slots[:, 1] = other
    return slots


def table_from_slots(triangles: np.ndarray, n_points: int, slots: np.ndarray) -> tuple[EdgeTable, np.ndarray]:
    """(table, other) of edge_table_sides(triangles, n_points) from `edge_slots` of them:
    the same arrays, by one pass over the edges and one over the triangles in the thread
    knob's threads (no sort: about half the time of building them, 24 against 51 ms at
    283k points). InputError unless every slot lies in the triangles (the slots must be
    those of these triangles)."""
    tri = _checked(triangles, n_points)
    slots = np.ascontiguousarray(slots, dtype=np.int32)
    T, E = tri.shape[0], slots.shape[0]
    if slots.ndim != 2 or slots.shape[1] != 2 or (E and (slots[:, 0].min() < 0 or slots.max() >= 3 * T
                                                           or slots[:, 1].min() < -1)):
        raise InputError(f"edge slots must be (E, 2) slots of the {T} triangles")
    edges = np.empty((E, 2), dtype=np.int64)
    tri_edge = np.empty((T, 3), dtype=np.int64)
    forward = np.empty((T, 3), dtype=bool)
    owner, owner_slot, count, other = (np.empty(E, dtype=np.int64) for _ in range(4))
    parallel_blocks(lambda part: _topology.table_from_slots(tri, slots, edges, tri_edge, owner, owner_slot, count,
                                                            other, part.start, part.stop), E, BLOCK)
    flags = forward.view(np.uint8)
    no_neighbours = np.empty((0, 3), dtype=np.int64)
    parallel_blocks(lambda part: _topology.clear_sides(tri, flags, no_neighbours, part.start, part.stop), T, BLOCK)
    return EdgeTable(edges=edges, tri_edge=tri_edge, forward=forward, owner=owner, owner_slot=owner_slot,
                     count=count), other


LIMIT = 2 ** 31
"""The kernel packs a vertex number and a slot 3t + k into 32 bits each: meshes up to 2**31
vertices and 715 million triangles (far above what fits in memory)."""


def _checked(triangles: np.ndarray, n_points: int) -> np.ndarray:
    """triangles as the kernel takes them, (T, 3) C-ordered int64, after checking what it
    does not: the shape, every index in [0, n_points) and the 32-bit packing's LIMIT."""
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise InputError(f"triangles must have shape (T, 3), got {tri.shape}")
    if tri.size and (tri.min() < 0 or tri.max() >= n_points):
        raise InputError(f"triangle indices must lie in [0, {n_points}), got {tri.min()}..{tri.max()}")
    if n_points >= LIMIT or 3 * tri.shape[0] >= LIMIT:
        raise InputError(f"the edge table takes meshes below {LIMIT} vertices and {LIMIT // 3} "
                         f"triangles, got {n_points} and {tri.shape[0]}: fit the survey in tiles (--memory)")
    return tri


def _edge_table(triangles: np.ndarray, n_points: int, sides: bool):
    """The EdgeTable of triangles (T, 3) over n_points vertices, with other and neighbours
    (edge_table_sides) or None, None. The kernel (engine/_topology.pyx) buckets the 3T slots
    by their edge's lower vertex (one thread, linear in T + n_points), then sorts the
    buckets and fills the table over fixed blocks of vertices in the thread knob's
    threads (`_sorted_buckets`)."""
    tri = _checked(triangles, n_points)
    T = tri.shape[0]
    packed, start, blocks = _sorted_buckets(tri, int(n_points))
    most, low, high = _most_shared(blocks)
    if most > 2:
        raise InputError(f"edge ({low}, {high}) belongs to {most} triangles: the triangles overlap "
                         f"or are not a valid mesh")
    E = int(blocks[:, 0].sum())
    edges = np.empty((E, 2), dtype=np.int64)
    tri_edge = np.empty((T, 3), dtype=np.int64)
    forward = np.empty((T, 3), dtype=bool)
    owner, owner_slot, count, other = (np.empty(E, dtype=np.int64) for _ in range(4))
    across = np.empty((T, 3), dtype=np.int64)
    flags = forward.view(np.uint8)
    parallel_blocks(lambda part: _topology.clear_sides(tri, flags, across, part.start, part.stop), T, BLOCK)
    first = np.concatenate([[0], np.cumsum(blocks[:, 0])])        # each block's first edge number
    parallel_blocks(lambda part: _topology.fill_table(
        packed, start, edges, tri_edge, owner, owner_slot, count, other, across,
        part.start, part.stop, int(first[part.start // BLOCK])), n_points, BLOCK)
    table = EdgeTable(edges=edges, tri_edge=tri_edge, forward=forward, owner=owner,
                      owner_slot=owner_slot, count=count)
    return (table, other, across) if sides else (table, None, None)


BLOCK = 1 << 15
"""Vertices (and triangles) per block of the edge table's parallel passes."""


def _sorted_buckets(tri: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(packed, start, blocks (b, 4)): the kernel's slot buckets of tri (T, 3), sorted, and
    each block of BLOCK vertices' facts (its unique edges, the most slots one of its edges
    has, the first such edge's low and high end)."""
    packed, start = _topology.bucket_slots(tri, n_points)
    blocks = np.zeros((-(-n_points // BLOCK), 4), dtype=np.int64)
    parallel_blocks(lambda part: _topology.sort_buckets(packed, start, part.start, part.stop,
                                                        blocks[part.start // BLOCK]), n_points, BLOCK)
    return packed, start, blocks


def _most_shared(blocks: np.ndarray) -> tuple[int, int, int]:
    """(the most triangles one edge has, that edge's low and high end: the first in sorted
    order) from _sorted_buckets' blocks; (0, -1, -1) without edges."""
    if not blocks.size or blocks[:, 1].max() == 0:
        return 0, -1, -1
    first = int(np.argmax(blocks[:, 1] == blocks[:, 1].max()))
    return int(blocks[first, 1]), int(blocks[first, 2]), int(blocks[first, 3])


def unique_edges(triangles: np.ndarray, n_points: int, counted: np.ndarray | None = None) -> np.ndarray:
    """(E, 2) int64 the unique edges of triangles (T, 3) over n_points vertices, lower end
    first, sorted lexicographically: edge_table's edges (without its check that an edge
    has at most two triangles); counted (n,) bool: only the edges whose lower end it
    marks. The kernel (engine/_topology.pyx) buckets the higher ends by lower vertex as
    edge_table does, without the slots, so it writes a quarter of the table's bytes."""
    tri = _checked(triangles, n_points)
    if counted is None:
        mask = np.empty(0, dtype=np.uint8)
    else:
        mask = np.ascontiguousarray(counted, dtype=bool).view(np.uint8)
        if mask.shape != (n_points,):
            raise InputError(f"counted must have shape ({n_points},), got {mask.shape}")
    highs, start, size, E = _topology.bucket_highs(tri, mask, int(n_points))
    edges = np.empty((E, 2), dtype=np.int64)
    _topology.fill_edges(highs, start, size, edges)
    return edges


def triangle_neighbours(triangles: np.ndarray, n_points: int) -> np.ndarray:
    """(T, 3) int64 the triangle across the edge opposite local vertex k of each triangle of
    triangles (T, 3) over n_points vertices, or -1; InputError if an edge is in 3 or more
    triangles. The edge table's slot buckets, without filling the table (blocks of
    vertices in the thread knob's threads, as `_edge_table`)."""
    tri = _checked(triangles, n_points)
    packed, start, blocks = _sorted_buckets(tri, int(n_points))
    if _most_shared(blocks)[0] > 2:
        raise InputError("the triangles are not edge-manifold (an edge is shared by three or "
                         "more triangles); pass a triangulation such as delaunay(xy)")
    across = np.empty(tri.shape, dtype=np.int64)
    parallel_blocks(lambda part: _topology.fill_neighbours(packed, start, across, part.start, part.stop),
                    int(n_points), BLOCK)
    return across


def live_edges(table: EdgeTable, keep: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the triangles ``keep`` (T,) bool: (owner kept (E,) bool, triangles kept per edge
    (E,) int8); the kept triangles' edges are those with a count above 0. other: the
    second slots of `edge_table_sides`. The kernel (engine/_topology.pyx), one pass over
    blocks of edges in the thread knob's threads."""
    keep = _checked_keep(keep, table)
    owner_kept = np.empty(table.owner.shape[0], dtype=bool)
    count = np.empty(table.owner.shape[0], dtype=np.int8)
    flags, other = keep.view(np.uint8), np.ascontiguousarray(other, dtype=np.int64)
    parallel_blocks(lambda part: _topology.edge_counts(flags, table.owner, other, owner_kept.view(np.uint8),
                                                       count, part.start, part.stop), count.shape[0], BLOCK)
    return owner_kept, count


def _checked_keep(keep: np.ndarray, table: EdgeTable) -> np.ndarray:
    """keep as a C-ordered (T,) bool array, InputError unless it has one entry per triangle."""
    keep = np.ascontiguousarray(keep, dtype=bool)
    if keep.shape != (table.tri_edge.shape[0],):
        raise InputError(f"keep must have shape ({table.tri_edge.shape[0]},), got {keep.shape}")
    return keep


def sub_table(table: EdgeTable, keep: np.ndarray, other: np.ndarray,
              used: np.ndarray | None = None) -> EdgeTable:
    """The EdgeTable of the triangles ``keep`` (T,) bool of ``table``'s mesh, in their order:
    equal, array for array, to edge_table(triangles[keep], n), without its sort.

    Why it is the same: the kept triangles' edges are a subset of the sorted edges (still
    sorted), their slots and orientations do not change, and an edge's owner, its lowest
    (slot, triangle) occurrence, stays the owner when kept (dropping triangles keeps the
    order of the others) or else is its other side. used: (n',) ascending vertex numbers
    to renumber the edges to 0..n'-1 (pipeline.steps.compact_vertices' `used`; an
    increasing renumbering keeps the edges' order and orientation). other: the second
    slots of `edge_table_sides`. The kernel (engine/_topology.pyx) fills the table in
    linear passes over fixed blocks of rows in the thread knob's threads, each block
    numbering its rows from the counts of the blocks before it (`_kept_before`): the same
    table at any count.
    """
    keep = _checked_keep(keep, table)
    other = np.ascontiguousarray(other, dtype=np.int64)
    owner_kept, count = live_edges(table, keep, other)
    flags, T = keep.view(np.uint8), keep.shape[0]
    live = count.view(np.uint8).astype(bool)
    E, kept = _kept_before(live), _kept_before(flags)
    remap = np.empty(0, dtype=np.int64)
    if used is not None:
        remap = np.full(int(used[-1]) + 1 if used.size else 0, -1, dtype=np.int64)
        remap[used] = np.arange(used.size, dtype=np.int64)
    sub = EdgeTable(edges=np.empty((E[-1], 2), dtype=np.int64), tri_edge=np.empty((kept[-1], 3), dtype=np.int64),
                    forward=np.empty((kept[-1], 3), dtype=bool), owner=np.empty(E[-1], dtype=np.int64),
                    owner_slot=np.empty(E[-1], dtype=np.int64), count=np.empty(E[-1], dtype=np.int64))
    new_triangle, rank = np.empty(T, dtype=np.int64), np.empty(count.shape[0], dtype=np.int64)
    parallel_blocks(lambda part: _topology.number_kept(flags, new_triangle, part.start, part.stop,
                                                       int(kept[part.start // BLOCK])), T, BLOCK)
    parallel_blocks(lambda part: _topology.fill_sub_edges(
        table.edges, table.owner, table.owner_slot, other, owner_kept.view(np.uint8), count, remap,
        new_triangle, rank, sub.edges, sub.owner, sub.owner_slot, sub.count, part.start, part.stop,
        int(E[part.start // BLOCK])), count.shape[0], BLOCK)
    parallel_blocks(lambda part: _topology.fill_sub_triangles(
        flags, table.tri_edge, table.forward.view(np.uint8), rank, new_triangle, sub.tri_edge,
        sub.forward.view(np.uint8), part.start, part.stop), T, BLOCK)
    return sub


def _kept_before(flags: np.ndarray) -> np.ndarray:
    """(b + 1,) int64: how many of flags (m,) 0/1 lie before each of its b blocks of BLOCK
    rows, then the total."""
    counts = np.add.reduceat(flags, np.arange(0, flags.shape[0], BLOCK), dtype=np.int64) if flags.size \
        else np.zeros(0, dtype=np.int64)
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def mesh_edges(triangles: np.ndarray, n_points: int | None = None) -> np.ndarray:
    """The (E, 2) unique edges of a mesh in the order ``RSDInterpolator(directions=...)`` expects."""
    triangles = np.asarray(triangles)
    n = int(triangles.max()) + 1 if n_points is None else n_points
    return edge_table(triangles, n).edges
