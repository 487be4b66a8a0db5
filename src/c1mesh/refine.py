"""Uniform refinement of an RSD spline: every triangle split into level² sub-triangles.

Output point numbering (so that input vertex i is output point i, and every point on a
shared edge or vertex exists once — a conforming, crack-free mesh):

  [0, N)                      the N input points (values and gradients exactly the data)
  [N, N + E(L−1))             L−1 points inside each unique edge, ordered from
                              edges[e, 0] to edges[e, 1]; edges grouped by how their
                              owner triangle sees them (so each group is one block)
  [N + E(L−1), M)             (L−1)(L−2)/2 interior points of each triangle, triangle-major

Values and gradients are matrix products: coefficients (T × 21) @ basis (21 × P), with
basis matrices built once per level and tuple (rsd.basis). Interior points of a block of
triangles are written straight into their contiguous slice of the output; edge points are
evaluated from one owner triangle per edge, grouped by the owner's local edge slot.

Memory: the outputs (M values, 2M gradients, 2M coordinates, 3·L²·T indices) plus
temporaries of a few CHUNK_ENTRIES-sized buffers (≈ 1 MiB, independent of T) and
O(E + T) bookkeeping arrays (edge order, coefficients), which are smaller than the output.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from c1mesh import rsd
from c1mesh.schemes import ShapeTuple
from c1mesh.topology import EdgeTable

CHUNK_ENTRIES = 1 << 14  # triangles per chunk × points per triangle: temporaries stay in cache


@dataclass
class RefinedMesh:
    """A refined triangle mesh with spline values and gradients at its points.

    points (M, 2), triangles (K, 3) counter-clockwise when the input triangles are,
    values (M,), gradients (M, 2), parent (K,) the input triangle of each sub-triangle
    (sub-triangles are stored parent by parent, level² each; computed on first use).
    Index arrays are int32 when M < 2**31 (halves memory), else int64.
    """

    points: np.ndarray
    triangles: np.ndarray
    values: np.ndarray
    gradients: np.ndarray
    level: int
    source_triangles: np.ndarray = field(repr=False, default=None)
    source_edges: np.ndarray = field(repr=False, default=None)

    @property
    def parent(self) -> np.ndarray:
        if getattr(self, "_parent", None) is None:
            self._parent = np.repeat(np.arange(self.source_triangles.shape[0], dtype=self.triangles.dtype),
                                     self.level * self.level)
        return self._parent

    def linear(self, field_values: np.ndarray) -> np.ndarray:
        """Piecewise-linear interpolation of per-input-vertex data onto the refined points.

        field_values: (N,) or (N, d) array over the input points (e.g. colours). Returns
        (M,) or (M, d) float64: input points keep their data exactly, edge and interior
        points get the barycentric blend of their parent's corners.
        """
        data = np.asarray(field_values, dtype=float)
        flat = data.reshape(data.shape[0], -1)
        pattern = lattice_pattern(self.level)
        count = (flat.shape[0] + self.source_edges.shape[0] * (self.level - 1)
                 + self.source_triangles.shape[0] * pattern.interior.size)
        out = _linear_field(flat, self.source_triangles, self.source_edges, pattern, count)
        return out.reshape((out.shape[0],) + data.shape[1:])


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
    """Values and gradients at a fixed set of barycentric points for blocks of triangles.

    Temporaries are preallocated for one chunk and reused, so they stay in cache; outputs
    are written in place into slices of the refined arrays.
    """

    def __init__(self, scheme: ShapeTuple, lam: np.ndarray, chunk: int):
        self.B = np.ascontiguousarray(rsd.basis(scheme, lam))
        d0, d1 = rsd.gradient_basis(scheme, lam)
        self.D0, self.D1 = np.ascontiguousarray(d0), np.ascontiguousarray(d1)
        self.chunk = chunk
        self._d0 = np.empty((chunk, lam.shape[0]))
        self._d1 = np.empty((chunk, lam.shape[0]))
        self._tmp = np.empty((chunk, lam.shape[0]))

    def into(self, C: np.ndarray, G: np.ndarray, values_out: np.ndarray, grads_out: np.ndarray):
        """values_out (c, P) and grads_out (c, P, 2) for coefficient rows C (c, 21), G (c, 3, 2)."""
        n = C.shape[0]
        d0, d1, tmp = self._d0[:n], self._d1[:n], self._tmp[:n]
        np.matmul(C, self.B, out=values_out)
        np.matmul(C, self.D0, out=d0)
        np.matmul(C, self.D1, out=d1)
        for axis in range(2):    # ∇F = (C @ D0) G_0 + (C @ D1) G_1
            np.multiply(d0, G[:, 0, axis, None], out=grads_out[..., axis])
            np.multiply(d1, G[:, 1, axis, None], out=tmp)
            grads_out[..., axis] += tmp


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
    lam = pat.lattice / level
    # Output order of edges: grouped by (owner slot k, direction), so each group's points
    # form one contiguous block written by one product per chunk.
    group = (2 * table.owner_slot + (~table.forward[table.owner, table.owner_slot])).astype(np.int8)
    edge_order = np.argsort(group, kind="stable")     # radix sort on int8: linear time
    edge_rank = np.empty(E, dtype=np.int64)
    edge_rank[edge_order] = np.arange(E)

    out_values = np.empty(M)
    out_grads = np.empty((M, 2))
    out_values[:N] = values
    out_grads[:N] = gradients
    _evaluate_interior(pat, lam, coefficients, G, scheme, out_values[N + E * n_edge:],
                       out_grads[N + E * n_edge:], T)
    _evaluate_edges(pat, lam, coefficients, G, scheme, table, edge_order, group,
                    out_values[N:N + E * n_edge], out_grads[N:N + E * n_edge])
    ordered_edges = table.edges[edge_order]
    out_points = _linear_field(points, triangles, ordered_edges, pat, M)
    out_tris = np.empty((T * level * level, 3), dtype=index_dtype)
    local = np.empty((_chunk_rows(pat.lattice.shape[0]), pat.lattice.shape[0]), dtype=index_dtype)
    for part in _chunks(T, pat.lattice.shape[0]):
        n = part.stop - part.start
        _global_indices(triangles, table, edge_rank, pat, part, N, E, local[:n])
        np.take(local[:n], pat.template.ravel(), axis=1,
                out=out_tris[part.start * level**2:part.stop * level**2].reshape(n, -1))
    return RefinedMesh(out_points, out_tris, out_values, out_grads, level,
                       source_triangles=triangles, source_edges=ordered_edges)


def _evaluate_interior(pat, lam, coefficients, G, scheme, out_values, out_grads, T):
    n_int = pat.interior.size
    if n_int == 0:
        return
    evaluator = _Evaluator(scheme, lam[pat.interior], _chunk_rows(n_int))
    values = out_values.reshape(T, n_int)
    grads = out_grads.reshape(T, n_int, 2)
    for part in _chunks(T, n_int):
        evaluator.into(coefficients[part], G[part], values[part], grads[part])


def _evaluate_edges(pat, lam, coefficients, G, scheme, table, edge_order, group,
                    out_values, out_grads):
    """Edge points from one owner triangle per edge, one contiguous block per edge group."""
    n_edge = pat.level - 1
    if n_edge == 0:
        return
    E = edge_order.size
    values = out_values.reshape(E, n_edge)
    grads = out_grads.reshape(E, n_edge, 2)
    bounds = np.searchsorted(group[edge_order], np.arange(7))
    rows = _chunk_rows(n_edge)
    C_buf = np.empty((rows, coefficients.shape[1]))
    G_buf = np.empty((rows, 3, 2))
    for g in range(6):
        k, reverse = divmod(g, 2)
        edge_lam = lam[pat.edge_rows[k]]
        evaluator = _Evaluator(scheme, edge_lam[::-1] if reverse else edge_lam, rows)
        for part in _chunks(bounds[g + 1] - bounds[g], n_edge):
            block = slice(bounds[g] + part.start, bounds[g] + part.stop)
            tri = table.owner[edge_order[block]]
            n = tri.size
            np.take(coefficients, tri, axis=0, out=C_buf[:n])
            np.take(G, tri, axis=0, out=G_buf[:n])
            evaluator.into(C_buf[:n], G_buf[:n], values[block], grads[block])


def _chunk_rows(width: int) -> int:
    return max(1, CHUNK_ENTRIES // max(width, 1))


def _chunks(n: int, width: int):
    step = _chunk_rows(width)
    for start in range(0, n, step):
        yield slice(start, min(start + step, n))


def _linear_field(data, triangles, ordered_edges, pat: LatticePattern, M: int) -> np.ndarray:
    """Per-vertex data (N, d) blended linearly onto all M output points, in output order.

    Used for the point coordinates themselves and for colours. Each block is a product of
    gathered corner data with a fixed weight matrix, written straight into the output:
    ends (c, 2d) @ W_edge for edge points, corners (c, 3d) @ W_int for interior points.
    """
    L, N, d = pat.level, data.shape[0], data.shape[1]
    out = np.empty((M, d))
    out[:N] = data
    E = ordered_edges.shape[0]
    s = np.arange(1, L) / L
    edge_weights = np.stack([1 - s, s], axis=1)               # (L−1, 2) on (a, b)
    _blend_by_product(data, ordered_edges, edge_weights, out[N:N + E * (L - 1)])
    interior_weights = pat.lattice[pat.interior] / L          # (n_int, 3)
    _blend_by_product(data, triangles, interior_weights, out[N + E * (L - 1):])
    return out


def _blend_by_product(data, cells, weights, out) -> None:
    """out[(c, p)] = Σ_k weights[p, k] data[cells[c, k]] for data (N, d), chunked products."""
    n_pts, n_corners = weights.shape
    d = data.shape[1]
    if n_pts == 0:
        return
    W = np.zeros((d * n_corners, d * n_pts))
    for k in range(n_corners):
        for j in range(d):
            W[d * k + j, j::d] = weights[:, k]
    flat = out.reshape(cells.shape[0], d * n_pts)
    for part in _chunks(cells.shape[0], d * n_pts):
        corners = data[cells[part]].reshape(-1, d * n_corners)
        np.matmul(corners, W, out=flat[part])


def _global_indices(triangles, table: EdgeTable, edge_rank, pat: LatticePattern, part: slice,
                    N: int, E: int, out: np.ndarray) -> None:
    """Fill out (c, P) with the global output index of every lattice point of ``part``."""
    L = pat.level
    tris = triangles[part]
    for k, (a1, a2) in enumerate(((0, 0), (L, 0), (0, L))):   # lattice (a1, a2) of vertex k
        out[:, pat.index_of[a1, a2]] = tris[:, k]
    s = np.arange(1, L)
    for k in range(3):
        e = edge_rank[table.tri_edge[part, k]]
        fwd = table.forward[part, k]
        pos = np.where(fwd[:, None], s[None, :], L - s[None, :])   # position along the edge
        out[:, pat.edge_rows[k]] = N + e[:, None] * (L - 1) + pos - 1
    n_int = pat.interior.size
    base = N + E * (L - 1)
    out[:, pat.interior] = base + (np.arange(part.start, part.stop)[:, None] * n_int
                                   + np.arange(n_int)[None, :])
