"""Edge numbering of a triangle mesh: one record per unique edge, shared by its triangles.

The RSD spline needs one direction vector per edge, used by both triangles that contain it
(that is what makes the union C1), so edges are numbered once and every triangle refers to
its three edges by number.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.errors import InputError


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
    tri = triangles.astype(np.int64, copy=False)
    T = triangles.shape[0]
    keys, forward = _edge_keys(tri, n_points)
    # One sort gives everything np.unique would (unique keys, first occurrence, inverse, counts).
    order = np.argsort(keys)
    sorted_keys = keys[order]
    new = np.empty(sorted_keys.size, dtype=bool)
    new[:1] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=new[1:])
    starts = np.flatnonzero(new)
    unique_keys = sorted_keys[starts]
    count = np.diff(starts, append=order.size)
    if count.size and count.max() > 2:
        bad = int(np.argmax(count))
        raise InputError(f"edge ({unique_keys[bad] // n_points}, {unique_keys[bad] % n_points}) "
                         f"belongs to {count[bad]} triangles: the triangles overlap or are not a valid mesh")
    # Concatenation order is slot-major: position = slot * T + triangle.
    owner_slot, owner = np.divmod(order[starts], T) if T else (starts, starts)
    # Fresh memory is slow to touch, so the dead key buffers are reused for the inverse.
    rank = np.cumsum(new, dtype=np.int64, out=sorted_keys)
    rank -= 1
    inverse = keys.reshape(3, T)
    inverse.ravel()[order] = rank
    del rank, order, sorted_keys, keys
    edges = np.empty((unique_keys.size, 2), dtype=np.int64)
    np.floor_divide(unique_keys, n_points, out=edges[:, 0])
    np.remainder(unique_keys, n_points, out=edges[:, 1])
    return EdgeTable(edges=edges, tri_edge=inverse.T.copy(), forward=forward, owner=owner,
                     owner_slot=owner_slot, count=count)


def _edge_keys(tri: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Keys min·n + max of the edges opposite each local vertex, slot-major (3T,), and
    forward (T, 3): whether local edge k runs from the smaller vertex to the larger."""
    T = tri.shape[0]
    keys = np.empty(3 * T, dtype=np.int64)
    forward = np.empty((T, 3), dtype=bool)
    for k in range(3):
        a, b = tri[:, (k + 1) % 3], tri[:, (k + 2) % 3]
        part = keys[k * T:(k + 1) * T]
        np.minimum(a, b, out=part)
        part *= np.int64(n_points)
        part += np.maximum(a, b)
        np.less(a, b, out=forward[:, k])
    return keys, forward


def mesh_edges(triangles: np.ndarray, n_points: int | None = None) -> np.ndarray:
    """The (E, 2) unique edges of a mesh in the order ``RSDInterpolator(directions=...)`` expects."""
    triangles = np.asarray(triangles)
    n = int(triangles.max()) + 1 if n_points is None else n_points
    return edge_table(triangles, n).edges
