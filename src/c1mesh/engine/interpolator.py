"""`RSDInterpolator`: Stachó's RSD C1 spline through values and gradients, scipy-style.

    interp = RSDInterpolator(points, values, gradients)      # Delaunay when no triangles
    z = interp(xi)                                            # values at (M, 2) points
    g = interp.gradient(xi)                                   # gradients (M, 2)
    mesh = interp.refine(8)                                   # uniform refinement, see refine.py

Coordinates are used as given: centre large coordinates (LiDAR at 1e5–1e7) before building
an interpolator, as the fit pipeline does, so that barycentric arithmetic keeps its digits.
"""
from __future__ import annotations

import numpy as np

from c1mesh.engine import rsd
from c1mesh.core.errors import InputError
from c1mesh.engine.locate import TriangleLocator
from c1mesh.engine.refine import RefinedMesh, Refinement
from c1mesh.engine.schemes import DEFAULT_SCHEME, ShapeTuple, get_scheme
from c1mesh.core.threads import overlap, parallel_blocks
from c1mesh.core.threads import workers as thread_count
from c1mesh.engine.topology import EdgeTable
from c1mesh.engine.topology import edge_table as build_edge_table
from c1mesh.engine.triangulation import delaunay

# |sin| of the angle below which a triangle is degenerate or a direction parallel to its edge.
_DEGENERACY = 1e-12


class RSDInterpolator:
    """C1 piecewise interpolant of first-order data (values and gradients) on a triangle mesh.

    Parameters
    ----------
    points : (N, 2) float array of vertex coordinates.
    values : (N,) float array, the function values f at the points.
    gradients : (N, 2) float array, the gradients ∇f at the points.
    triangles : (T, 3) int array of vertex indices, or None for the Delaunay
        triangulation of ``points`` (c1mesh.engine.triangulation.delaunay: scipy's triangles,
        computed tile by tile for large inputs). Any valid (non-overlapping, non-degenerate)
        triangulation is accepted; orientation is free.
    scheme : name of a shape-function tuple ('sextic' default, 'quintic', 'ex39b') or a
        ShapeTuple (c1mesh.engine.schemes).
    directions : None for the unit normal of each edge, or an (E, 2) array with one vector
        per unique edge, in the order of ``self.edges`` (``c1mesh.engine.topology.mesh_edges``:
        edges (i, j) with i < j, sorted lexicographically). Each vector is shared by both
        triangles containing the edge, which makes the spline C1; its sign is irrelevant.
    fill_value : value returned at points outside the triangulation (default nan), as in
        scipy.interpolate.
    edge_table : c1mesh.engine.topology.edge_table(triangles, N) when the caller has built it
        already (the fit pipeline's overshoot control does), so the edges are numbered once.

    Threads: building uses the process-wide setting of c1mesh.core.threads (by default the
    CPUs this process may use; ``with c1mesh.core.threads.limit(n):`` around the call for
    fewer), ``refine`` takes its own ``workers``. Results are the same for every count.

    Attributes: points, values, gradients, triangles, edges (E, 2), directions (E, 2),
    scheme (ShapeTuple), coefficients (T, 21), edge_table (the
    c1mesh.engine.topology.EdgeTable of the triangles: edges, each triangle's edges and
    their neighbours), lambda_gradients (T, 3, 2): the gradient of each triangle's three
    barycentric coordinates (rsd.gradients_at turns spline derivatives into ∇F with it).
    """

    def __init__(self, points, values, gradients, triangles=None,
                 scheme: "str | ShapeTuple" = DEFAULT_SCHEME, directions=None,
                 fill_value: float = np.nan, edge_table: EdgeTable | None = None):
        self.points = _float_array(points, "points", (None, 2))
        n = self.points.shape[0]
        self.values = _float_array(values, "values", (n,))
        self.gradients = _float_array(gradients, "gradients", (n, 2))
        self.scheme = get_scheme(scheme)
        self.fill_value = fill_value
        self.triangles = self._triangles(triangles)
        self.edge_table, (C, self.lambda_gradients, _, degenerate) = self._coefficients_and_edges(edge_table)
        self.edges = self.edge_table.edges
        self.directions = self._directions(directions)
        rsd.ratio_coefficients(C, self.lambda_gradients, self.directions, self.edge_table.tri_edge)
        self.coefficients = C
        self._check_degenerate(degenerate)
        self._locator: TriangleLocator | None = None

    # ----------------------------------------------------------------- construction
    def _coefficients_and_edges(self, table: EdgeTable | None) -> tuple:
        """(edge table, rsd.vertex_coefficients(...)): rsd.mesh_coefficients in two passes,
        what needs no edge directions runs while another thread numbers the edges (numpy
        releases the GIL in both), unless the caller brought the table."""
        n = self.points.shape[0]

        def coefficients(threads: int):
            return rsd.vertex_coefficients(self._vertex_data(), self.triangles, min_sine=_DEGENERACY,
                                           threads=threads)
        if table is None:
            return overlap(lambda: build_edge_table(self.triangles, n),
                           lambda: coefficients(max(1, thread_count() - 1)))
        if table.tri_edge.shape != self.triangles.shape:
            raise InputError(f"edge_table has {table.tri_edge.shape[0]} triangles, "
                             f"the mesh {self.triangles.shape[0]}")
        return table, coefficients(thread_count())

    def _triangles(self, triangles) -> np.ndarray:
        n = self.points.shape[0]
        if triangles is None:
            return delaunay(self.points)   # CDT's Delaunay triangles (engine.triangulation)
        tri = np.asarray(triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0:
            raise InputError(f"triangles must have shape (T, 3) with T >= 1, got {tri.shape}")
        if not np.issubdtype(tri.dtype, np.integer):
            raise InputError(f"triangles must be integer vertex indices, got dtype {tri.dtype}")
        if tri.min() < 0 or tri.max() >= n:
            raise InputError(f"triangle vertex indices must lie in [0, {n - 1}]")
        return tri.astype(np.int64)

    def _check_degenerate(self, bad: np.ndarray) -> None:
        """Reject triangles whose |sin(angle)| at vertex 0 is not above _DEGENERACY.

        bad (T,) bool comes from rsd.mesh_coefficients(..., min_sine=_DEGENERACY).
        """
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise InputError(f"{int(bad.sum())} degenerate (zero-area) triangle(s), first: "
                             f"triangle {first} with vertices {self.triangles[first].tolist()}")

    def _directions(self, directions) -> np.ndarray:
        if directions is None:
            return _unit_normals(self.points, self.edges)
        u = _float_array(directions, "directions", (self.edges.shape[0], 2))
        bad = _crosses_badly(self.points, self.edges, u)
        if bad.any():
            e = int(np.flatnonzero(bad)[0])
            raise InputError(f"direction {e} is zero or parallel to its edge "
                             f"{self.edges[e].tolist()}; it must cross the edge")
        return u

    # ----------------------------------------------------------------- evaluation
    def _locate(self, xi) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple]:
        xy = np.asarray(xi, dtype=float)
        if xy.shape[-1:] != (2,):
            raise InputError(f"query points must have shape (..., 2), got {xy.shape}")
        shape = xy.shape[:-1]
        xy = xy.reshape(-1, 2)
        if self._locator is None:
            self._locator = TriangleLocator(self.points, self.triangles, self.lambda_gradients)
        tri, lam = self._locator.find(xy)
        return xy, tri, lam, shape

    def __call__(self, xi) -> np.ndarray:
        """Spline values at query points xi (..., 2); ``fill_value`` outside the mesh."""
        _, tri, lam, shape = self._locate(xi)
        out = np.full(tri.shape, self.fill_value, dtype=float)
        inside = tri >= 0
        if inside.any():
            out[inside] = rsd.values_at(self.scheme, self.coefficients[tri[inside]], lam[inside])
        return out.reshape(shape)

    def gradient(self, xi) -> np.ndarray:
        """Spline gradients (..., 2) at query points xi (..., 2); ``fill_value`` outside."""
        _, tri, lam, shape = self._locate(xi)
        out = np.full(tri.shape + (2,), self.fill_value, dtype=float)
        inside = tri >= 0
        if inside.any():
            t = tri[inside]
            out[inside] = rsd.gradients_at(self.scheme, self.coefficients[t], self.lambda_gradients[t], lam[inside])
        return out.reshape(shape + (2,))

    def find_simplex(self, xi) -> np.ndarray:
        """Index of the triangle containing each query point (−1 outside), like scipy's."""
        _, tri, _, shape = self._locate(xi)
        return tri.reshape(shape)

    def c1_certificate(self, max_edges: int = 2000, samples: int = 5, seed: int = 0) -> dict:
        """Largest value and gradient jumps across interior edges, measured, not assumed.

        Up to ``max_edges`` interior edges (random, reproducible by ``seed``) are sampled at
        ``samples`` points each; at each point both adjacent triangles are evaluated with
        exact edge barycentrics. Jumps are relative to the largest |value| and |gradient| of
        the data. Returns {"edges_checked", "value_jump", "gradient_jump"}.
        """
        table = self.edge_table
        interior = np.flatnonzero(table.count == 2)
        rng = np.random.default_rng(seed)
        if interior.size > max_edges:
            interior = np.sort(rng.choice(interior, max_edges, replace=False))
        if interior.size == 0:
            return {"edges_checked": 0, "value_jump": 0.0, "gradient_jump": 0.0}
        sides = _triangles_of_edges(table.tri_edge, interior)          # (n, 2)
        s = (np.arange(samples) + 0.5) / samples
        results = []
        for side in range(2):
            t = np.repeat(sides[:, side], samples)
            a = np.repeat(table.edges[interior, 0], samples)
            b = np.repeat(table.edges[interior, 1], samples)
            lam = np.zeros((t.size, 3))
            local = self.triangles[t]
            lam[local == a[:, None]] = np.tile(1 - s, interior.size)
            lam[local == b[:, None]] = np.tile(s, interior.size)
            C = self.coefficients[t]
            results.append((rsd.values_at(self.scheme, C, lam),
                            rsd.gradients_at(self.scheme, C, self.lambda_gradients[t], lam)))
        (v1, g1), (v2, g2) = results
        value_scale = max(float(np.abs(self.values).max()), np.finfo(float).tiny)
        grad_scale = max(float(np.abs(self.gradients).max()), np.finfo(float).tiny)
        return {"edges_checked": int(interior.size),
                "value_jump": float(np.abs(v1 - v2).max() / value_scale),
                "gradient_jump": float(np.abs(g1 - g2).max() / grad_scale)}

    def refine(self, level: int, workers: int | None = None) -> RefinedMesh:
        """Uniform refinement: each triangle split into level² sub-triangles (refine.py),
        computed by `workers` threads (default: the process-wide setting; Refinement.mesh)."""
        return self.refinement(level).mesh(workers)

    def refinement(self, level: int) -> Refinement:
        """The level-``level`` refinement, to evaluate block by block (streaming) or whole."""
        return Refinement(self._vertex_data(), self.triangles, self.coefficients, self.lambda_gradients,
                          self.edge_table, self.scheme, level)

    def _vertex_data(self) -> rsd.VertexData:
        return rsd.VertexData(self.points, self.values, self.gradients)


def _crosses_badly(points: np.ndarray, edges: np.ndarray, u: np.ndarray,
                   block: int = 1 << 16) -> np.ndarray:
    """(E,) bool: direction u is zero, not finite, or within |sin| _DEGENERACY of parallel
    to its edge v = points[j] − points[i], i.e. not (u × v)² > _DEGENERACY² |u|² |v|².
    In blocks of edges in worker threads (c1mesh.core.threads.parallel_blocks), gathering
    from contiguous coordinate columns, so the temporaries stay in cache."""
    x, y = np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1])
    bad = np.empty(edges.shape[0], dtype=bool)

    def crosses(part: slice) -> None:
        i, j = np.ascontiguousarray(edges[part, 0]), np.ascontiguousarray(edges[part, 1])
        vx, vy, ux, uy = x[j] - x[i], y[j] - y[i], u[part, 0], u[part, 1]
        cross = ux * vy - uy * vx
        bound = (ux * ux + uy * uy) * (vx * vx + vy * vy) * (_DEGENERACY * _DEGENERACY)
        np.logical_not(cross * cross > bound, out=bad[part])
    parallel_blocks(crosses, edges.shape[0], block)
    return bad


def _unit_normals(points: np.ndarray, edges: np.ndarray, block: int = 1 << 16) -> np.ndarray:
    """(-vy, vx) / |v| for the edge vectors v = points[j] - points[i] of edges (E, 2).

    In fixed blocks in the thread knob's threads, so no full-size temporaries and the same
    bits at any count; |v| is computed as np.linalg.norm does (sqrt(vx² + vy²)), so the
    bits are those of the plain expression.
    """
    out = np.empty((edges.shape[0], 2))

    def normals(part: slice) -> None:
        vec = points[edges[part, 1]] - points[edges[part, 0]]
        vx, vy = vec[:, 0], vec[:, 1]
        length = np.sqrt(vx * vx + vy * vy)
        np.divide(-vy, length, out=out[part, 0])
        np.divide(vx, length, out=out[part, 1])
    parallel_blocks(normals, edges.shape[0], block)
    return out


def _triangles_of_edges(tri_edge: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(n, 2) the two triangles containing each of the interior ``edges`` (distinct ids).

    One pass marks where the wanted edges occur (no sort of all 3T slots: the C1
    certificate samples a few thousand edges of millions).
    """
    flat = tri_edge.ravel()
    wanted = np.zeros(int(flat.max()) + 1, dtype=bool)
    wanted[edges] = True
    slots = np.flatnonzero(wanted[flat])                  # (t * 3 + k) holding a wanted edge
    order = np.argsort(flat[slots], kind="stable")
    slots = slots[order]
    start = np.searchsorted(flat[slots], edges)
    return np.stack([slots[start] // 3, slots[start + 1] // 3], axis=1)


def _float_array(a, name: str, shape: tuple) -> np.ndarray:
    """A float64 copy of ``a`` checked for shape (None = any size) and finiteness; copied
    and checked over blocks of rows in the thread knob's threads (a 1M-vertex fit copies
    40 MB here)."""
    try:
        source = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array") from None
    if source.ndim != len(shape) or any(want is not None and got != want
                                        for got, want in zip(source.shape, shape)):
        want = "(" + ", ".join("N" if w is None else str(w) for w in shape) + ")"
        raise InputError(f"{name} must have shape {want}, got {source.shape}")
    arr = np.empty(source.shape)
    finite = np.ones(max(1, -(-source.shape[0] // COPY_BLOCK)), dtype=bool)

    def copy(part: slice) -> None:
        arr[part] = source[part]
        finite[part.start // COPY_BLOCK] = np.isfinite(arr[part]).all()
    parallel_blocks(copy, source.shape[0], COPY_BLOCK)
    if not finite.all():
        raise InputError(f"{name} contains NaN or Inf")
    return arr


COPY_BLOCK = 1 << 16
"""Rows per block of `_float_array`'s copy."""
