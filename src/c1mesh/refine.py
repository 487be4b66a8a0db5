"""Uniform refinement of an RSD spline: every triangle split into level² sub-triangles.

Output point numbering (so that input vertex i is output point i, and every point on a
shared edge or vertex exists once — a conforming, crack-free mesh):

  [0, N)                      the N input points (values and gradients exactly the data)
  [N, N + E(L−1))             L−1 points inside each unique edge e, ordered from
                              edges[e, 0] to edges[e, 1]
  [N + E(L−1), M)             (L−1)(L−2)/2 interior points of each triangle, triangle-major

Values and gradients are matrix products: coefficients (T × 21) @ basis (21 × P), with
basis matrices built once per level and tuple (rsd.basis). Interior points of a block of
triangles are written straight into their contiguous slice of the output; edge points are
evaluated from one owner triangle per edge, grouped by the owner's local edge slot.

Memory: the outputs (M values, 2M gradients, 3·L²·T indices, L²·T parents) plus
temporaries bounded by about 4 × CHUNK_ENTRIES × 8 bytes ≈ 64 MiB, independent of T.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh import rsd
from c1mesh.schemes import ShapeTuple
from c1mesh.topology import EdgeTable

CHUNK_ENTRIES = 1 << 21  # triangles per chunk × points per triangle, for temporaries


@dataclass
class RefinedMesh:
    """A refined triangle mesh with spline values and gradients at its points.

    points (M, 2), triangles (K, 3) counter-clockwise when the input triangles are,
    values (M,), gradients (M, 2), parent (K,) the input triangle of each sub-triangle.
    Index arrays are int32 when M < 2**31 (halves memory), else int64.
    """

    points: np.ndarray
    triangles: np.ndarray
    values: np.ndarray
    gradients: np.ndarray
    parent: np.ndarray
    level: int


@dataclass(frozen=True)
class LatticePattern:
    """Barycentric lattice of one triangle at a level L: points a/L with a0 + a1 + a2 = L.

    lattice (P, 3) integer coordinates; index_of (L+1, L+1) maps (a1, a2) to a lattice row;
    interior rows; edge_rows[k] rows of the points strictly inside the edge opposite vertex
    k, ordered from vertex k+1 towards vertex k+2; template (L², 3) sub-triangles as lattice
    rows, same orientation as the parent.
    """

    level: int
    lattice: np.ndarray
    index_of: np.ndarray
    interior: np.ndarray
    edge_rows: tuple
    template: np.ndarray


def lattice_pattern(level: int) -> LatticePattern:
    L = level
    a1, a2 = np.meshgrid(np.arange(L + 1), np.arange(L + 1), indexing="ij")
    mask = a1 + a2 <= L
    a1, a2 = a1[mask], a2[mask]
    lattice = np.stack([L - a1 - a2, a1, a2], axis=1)
    index_of = np.full((L + 1, L + 1), -1, dtype=np.int64)
    index_of[a1, a2] = np.arange(a1.size)
    interior = np.flatnonzero((lattice > 0).all(axis=1))
    s = np.arange(1, L)
    edge_rows = []
    for k in range(3):
        coords = np.zeros((L - 1, 3), dtype=np.int64)
        coords[:, (k + 1) % 3] = L - s
        coords[:, (k + 2) % 3] = s
        edge_rows.append(index_of[coords[:, 1], coords[:, 2]])
    up = [(i, j) for i in range(L) for j in range(L - i)]
    down = [(i, j) for i in range(L - 1) for j in range(L - 1 - i)]
    template = [(index_of[i, j], index_of[i + 1, j], index_of[i, j + 1]) for i, j in up]
    template += [(index_of[i + 1, j], index_of[i + 1, j + 1], index_of[i, j + 1]) for i, j in down]
    return LatticePattern(L, lattice, index_of, interior, tuple(edge_rows), np.array(template))


class _Evaluator:
    """Values and gradients at a fixed lattice subset for blocks of triangles."""

    def __init__(self, scheme: ShapeTuple, lam: np.ndarray):
        self.B = np.ascontiguousarray(rsd.basis(scheme, lam))
        d0, d1 = rsd.gradient_basis(scheme, lam)
        self.D0, self.D1 = np.ascontiguousarray(d0), np.ascontiguousarray(d1)

    def into(self, C: np.ndarray, G: np.ndarray, values_out: np.ndarray, grads_out: np.ndarray):
        """values_out (c, P) and grads_out (c, P, 2) for coefficient rows C (c, 21), G (c, 3, 2)."""
        np.matmul(C, self.B, out=values_out)
        d0 = C @ self.D0
        d1 = C @ self.D1
        for axis in range(2):
            np.multiply(d0, G[:, 0, axis, None], out=grads_out[..., axis])
            grads_out[..., axis] += d1 * G[:, 1, axis, None]


def refine_spline(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                  triangles: np.ndarray, coefficients: np.ndarray, G: np.ndarray,
                  table: EdgeTable, scheme: ShapeTuple, level: int) -> RefinedMesh:
    """Evaluate the spline on a uniform level-``level`` subdivision of every triangle."""
    if int(level) != level or level < 1:
        raise ValueError(f"level must be a positive integer, got {level!r}")
    level = int(level)
    pat = lattice_pattern(level)
    N, T, E = points.shape[0], triangles.shape[0], table.edges.shape[0]
    n_edge, n_int = level - 1, pat.interior.size
    M = N + E * n_edge + T * n_int
    index_dtype = np.int32 if M < 2**31 - 1 else np.int64
    out_values = np.empty(M)
    out_grads = np.empty((M, 2))
    out_values[:N] = values
    out_grads[:N] = gradients
    lam = pat.lattice / level

    interior_eval = _Evaluator(scheme, lam[pat.interior])
    int_values = out_values[N + E * n_edge:].reshape(T, n_int)
    int_grads = out_grads[N + E * n_edge:].reshape(T, n_int, 2)
    for part in _chunks(T, max(n_int, 1)):
        interior_eval.into(coefficients[part], G[part], int_values[part], int_grads[part])

    edge_values = out_values[N:N + E * n_edge].reshape(E, n_edge)
    edge_grads = out_grads[N:N + E * n_edge].reshape(E, n_edge, 2)
    for k in range(3):
        evaluator = _Evaluator(scheme, lam[pat.edge_rows[k]])
        edges_k = np.flatnonzero(table.owner_slot == k)
        for part in _chunks(edges_k.size, max(n_edge, 1)):
            e = edges_k[part]
            tri = table.owner[e]
            vals = np.empty((e.size, n_edge))
            grads = np.empty((e.size, n_edge, 2))
            evaluator.into(coefficients[tri], G[tri], vals, grads)
            reverse = ~table.forward[tri, k]
            vals[reverse] = vals[reverse, ::-1]
            grads[reverse] = grads[reverse, ::-1]
            edge_values[e] = vals
            edge_grads[e] = grads

    out_points = _refined_points(points, triangles, table, pat, M)
    out_tris = np.empty((T * level * level, 3), dtype=index_dtype)
    for part in _chunks(T, pat.lattice.shape[0]):
        local_to_global = _global_indices(triangles, table, pat, part, N, E)
        out_tris[part.start * level**2:part.stop * level**2] = \
            local_to_global[:, pat.template].reshape(-1, 3)
    parent = np.repeat(np.arange(T, dtype=index_dtype), level * level)
    return RefinedMesh(out_points, out_tris, out_values, out_grads, parent, level)


def _chunks(n: int, width: int):
    step = max(1, CHUNK_ENTRIES // max(width, 1))
    for start in range(0, n, step):
        yield slice(start, min(start + step, n))


def _refined_points(points, triangles, table: EdgeTable, pat: LatticePattern, M: int) -> np.ndarray:
    """Coordinates of all output points (M, 2) in the module's numbering."""
    L, N = pat.level, points.shape[0]
    out = np.empty((M, 2))
    out[:N] = points
    s = np.arange(1, L) / L
    a, b = points[table.edges[:, 0]], points[table.edges[:, 1]]
    E = table.edges.shape[0]
    edge_pts = out[N:N + E * (L - 1)].reshape(E, L - 1, 2)
    for d in range(2):
        edge_pts[..., d] = a[:, None, d] + s[None, :] * (b[:, None, d] - a[:, None, d])
    lam = pat.lattice[pat.interior] / L                       # (n_int, 3)
    T = triangles.shape[0]
    int_pts = out[N + E * (L - 1):].reshape(T, lam.shape[0], 2)
    for part in _chunks(T, max(lam.shape[0], 1)):
        corners = points[triangles[part]]                     # (c, 3, 2)
        np.einsum("pk,ckd->cpd", lam, corners, out=int_pts[part])
    return out


def _global_indices(triangles, table: EdgeTable, pat: LatticePattern, part: slice,
                    N: int, E: int) -> np.ndarray:
    """(c, P) global output index of every lattice point of the triangles in ``part``."""
    L = pat.level
    tris = triangles[part]
    c = tris.shape[0]
    out = np.empty((c, pat.lattice.shape[0]), dtype=np.int64)
    for k, (a1, a2) in enumerate(((0, 0), (L, 0), (0, L))):   # lattice (a1, a2) of vertex k
        out[:, pat.index_of[a1, a2]] = tris[:, k]
    s = np.arange(1, L)
    for k in range(3):
        e = table.tri_edge[part, k]
        fwd = table.forward[part, k]
        pos = np.where(fwd[:, None], s[None, :], L - s[None, :])   # position along the edge
        out[:, pat.edge_rows[k]] = N + e[:, None] * (L - 1) + pos - 1
    n_int = pat.interior.size
    base = N + E * (L - 1)
    out[:, pat.interior] = base + (np.arange(part.start, part.stop)[:, None] * n_int
                                   + np.arange(n_int)[None, :])
    return out
