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
    a = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]])
    b = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]])
    keys = np.minimum(a, b) * np.int64(n_points) + np.maximum(a, b)
    # One sort gives everything np.unique would (unique keys, first occurrence, inverse, counts).
    order = np.argsort(keys)
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.concatenate([[True], sorted_keys[1:] != sorted_keys[:-1]]))
    unique_keys = sorted_keys[starts]
    first = order[starts]
    count = np.diff(np.append(starts, keys.size))
    inverse = np.empty(keys.size, dtype=np.int64)
    inverse[order] = np.repeat(np.arange(starts.size), count)
    if count.size and count.max() > 2:
        bad = int(np.argmax(count))
        raise InputError(f"edge ({unique_keys[bad] // n_points}, {unique_keys[bad] % n_points}) "
                         f"belongs to {count[bad]} triangles: the triangles overlap or are not a valid mesh")
    T = triangles.shape[0]
    edges = np.stack([unique_keys // n_points, unique_keys % n_points], axis=1)
    # Concatenation order is slot-major: position = slot * T + triangle.
    tri_edge = inverse.reshape(3, T).T.copy()
    forward = (a < b).reshape(3, T).T.copy()
    return EdgeTable(edges=edges, tri_edge=tri_edge, forward=forward, owner=first % T,
                     owner_slot=first // T, count=count)


def mesh_edges(triangles: np.ndarray, n_points: int | None = None) -> np.ndarray:
    """The (E, 2) unique edges of a mesh in the order ``RSDInterpolator(directions=...)`` expects."""
    triangles = np.asarray(triangles)
    n = int(triangles.max()) + 1 if n_points is None else n_points
    return edge_table(triangles, n).edges
