"""The sparse normal equations of the smoothing fit, and their solvers (issue 24).

Everything here works in *normalised* units (c1mesh.stages.smoothing turns the user's
into them): lengths in mean point spacings h, heights in a scale Z of the data, weights
divided by their mean. Then λ is the dimensionless strength s itself.

Unknowns are interleaved per vertex, u[3v] = f_v and u[3v + 1 : 3v + 3] = ∇f_v, so that
a triangle's 9 local data are the rows `local_dofs` names.

    S = A^T W A + s K + μ P,   rhs = A^T W z + μ P n

K is the assembled thin-plate energy (smoothing_energy), A the data rows (the identity on
f when the data are the vertices, else 9 entries per data point: its triangle's basis at
the point times that triangle's linear map), P the diagonal that picks the gradient
unknowns of vertices with gradient data n.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from c1mesh.core.lazy import LazyModule
from c1mesh.core.threads import blas_threads, parallel_blocks
from c1mesh.engine import rsd
from c1mesh.engine.schemes import ShapeTuple
from c1mesh.stages.smoothing_energy import N_LOCAL, SmoothingError, energy_blocks_of, linear_maps
from c1mesh.stages import _smoothing_system as kernel

sp = LazyModule("scipy.sparse")
spla = LazyModule("scipy.sparse.linalg")

_CHUNK = 1 << 15


ROW_BLOCK = 1 << 14
"""Vertices per block of the pattern's and the indices' rows, and data points per block of
DataRows.fitted (the blocks run in the thread knob's threads)."""
ASSEMBLY_CHUNK = 1 << 17
"""Triangles whose energy blocks are computed and added at a time (assemble_energy): 85 MB
of blocks."""


@dataclass
class VertexPattern:
    """The vertex adjacency of a mesh, each vertex with itself and its neighbours (N, N CSR
    pattern): v's are cols[row_start[v]:row_start[v + 1]], increasing. Also the corners at
    each vertex, corner[start[v]:start[v + 1]] (3 t + k, increasing), from which it is made."""

    start: np.ndarray
    corner: np.ndarray
    row_start: np.ndarray
    cols: np.ndarray


def vertex_pattern(triangles: np.ndarray, n: int) -> VertexPattern:
    """The VertexPattern of n vertices and triangles (T, 3) int64 (kernel: the corners by
    one counting sort, then each block of rows sorts its vertices' neighbours twice, to
    count them and to write them). A vertex no triangle uses (a tile's record outside its
    triangles) has itself as its one neighbour: its 3 × 3 block of K is stored, zero, so
    that S's data and gradient terms have their diagonal entries there (System.matrix)."""
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    start, corner = incidence(tri, n)
    room = 3 * int(np.diff(start).max(initial=0)) + 1
    degree = np.empty(n, dtype=np.int64)
    parallel_blocks(lambda part: kernel.degrees(tri, start, corner, part.start, part.stop,
                                                np.empty(room, dtype=np.int64), degree),
                    n, ROW_BLOCK)
    row_start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(degree, out=row_start[1:])
    cols = np.empty(int(row_start[-1]), dtype=np.int64)
    parallel_blocks(lambda part: kernel.neighbours(tri, start, corner, row_start, part.start,
                                                   part.stop, cols), n, ROW_BLOCK)
    return VertexPattern(start, corner, row_start, cols)


def incidence(triangles: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(start (n + 1,), corner (3T,)) int64: the corners 3 t + k (triangle t, its corner k)
    at vertex v are corner[start[v]:start[v + 1]], increasing, for n vertices and
    triangles (T, 3) (the kernel's counting sort, one thread); ValueError for a vertex
    index outside [0, n)."""
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    if tri.size and (tri.min() < 0 or tri.max() >= n):
        raise ValueError("triangle vertex indices out of range")
    start = np.zeros(n + 1, dtype=np.int64)
    corner = np.empty(tri.size, dtype=np.int64)
    kernel.incidence(tri, start, corner)
    return start, corner


@dataclass(frozen=True)
class TriangleShapes:
    """Triangles that are translates of a few (a lattice's: stages.lattice_solver): key (T,)
    the shape of each triangle, a row of reps (k,), the first triangle of each shape. Their
    energy blocks and data maps are the representatives' (translation changes neither),
    computed k times instead of T times."""

    key: np.ndarray
    reps: np.ndarray

    def subset(self, keep: np.ndarray) -> "TriangleShapes":
        """The shapes of the triangles keep (T,) bool selects, representatives renumbered."""
        key = self.key[keep]
        used, local = np.unique(key, return_inverse=True)
        first = np.full(self.reps.size, -1, dtype=np.int64)
        first[key[::-1]] = np.arange(key.size - 1, -1, -1)
        return TriangleShapes(local.astype(np.int64), first[used])


def assemble_energy(points: np.ndarray, triangles: np.ndarray, dirs: np.ndarray,
                    scheme: ShapeTuple, shapes: TriangleShapes | None = None) -> sp.csr_matrix:
    """K (3N, 3N) CSR, the sum of the triangles' 9 × 9 energy blocks at their unknowns.

    Assembled as 3 × 3 vertex blocks on the pattern of the vertex adjacency
    (`vertex_pattern`), written straight into CSR: row 3v + c lists, for each neighbour w
    of v in increasing order, the columns 3w, 3w + 1, 3w + 2. The blocks are computed
    ASSEMBLY_CHUNK triangles at a time (in the thread knob's threads) and each chunk added
    by the kernel (_smoothing_system.add_blocks) before the next, so only one chunk's
    blocks are held (all of them were 1.3 GB at 2M triangles). Each entry is the sum of
    its triangles' contributions in increasing triangle order from 0, as a bincount over
    the triangles' vertex pairs sums them, so the bits do not depend on the thread count
    or the chunk. shapes: the triangles are translates of shapes.reps' (a lattice's), whose
    blocks serve them all.
    """
    n = points.shape[0]
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    dirs = np.ascontiguousarray(dirs, dtype=np.float64)
    pattern = vertex_pattern(tri, n)
    row_start, cols = pattern.row_start, pattern.cols
    nnz = 9 * cols.size
    index = np.int32 if max(nnz, 3 * n) < 2**31 else np.int64
    data = np.zeros(nnz)
    shared = None if shapes is None else energy_blocks_of(points, tri[shapes.reps], dirs[shapes.reps], scheme)
    for first in range(0, tri.shape[0], ASSEMBLY_CHUNK):
        part = slice(first, first + ASSEMBLY_CHUNK)
        blocks = (energy_blocks_of(points, tri[part], dirs[part], scheme) if shared is None
                  else np.ascontiguousarray(shared[shapes.key[part]]))      # (chunk, 9, 9)
        kernel.add_blocks(tri, first, blocks, row_start, cols, data)
    indices = np.empty(nnz, dtype=index)                              # written as the matrix keeps it
    parallel_blocks(lambda part: kernel.csr_indices(row_start, cols, part.start, part.stop, indices),
                    n, ROW_BLOCK)
    indptr = np.empty(3 * n + 1, dtype=np.int64)
    indptr[:-1].reshape(n, 3)[...] = 9 * row_start[:-1, None] + 3 * np.arange(3) * np.diff(row_start)[:, None]
    indptr[-1] = nnz
    return sp.csr_matrix((data, indices, indptr.astype(index)), shape=(3 * n, 3 * n))


def data_rows(points: np.ndarray, triangles: np.ndarray, dirs: np.ndarray, scheme: ShapeTuple,
              tri: np.ndarray, lam: np.ndarray, shapes: TriangleShapes | None = None) -> "DataRows":
    """The DataRows of data points in triangles tri (M,) at barycentrics lam (M, 3): row i
    of A is F(x_i) as a linear form in the unknowns. shapes: as assemble_energy's (each
    shape's linear map once, its points' rows one product)."""
    m = tri.shape[0]
    if shapes is not None:
        return _shared_rows(points, triangles, dirs, scheme, tri, lam, shapes)
    vals = np.empty((m, N_LOCAL))
    for start in range(0, m, _CHUNK):
        part = slice(start, start + _CHUNK)
        t = tri[part]
        corners = points[triangles[t]]
        G, _ = rsd.barycentric_gradients(corners)
        M = linear_maps(corners, dirs[t], G)                          # (m, 21, 9)
        B = rsd.basis(scheme, lam[part])                             # (21, m)
        vals[part] = np.einsum("bm,mbj->mj", B, M)
    return DataRows(np.ascontiguousarray(triangles, dtype=np.int64),
                    np.ascontiguousarray(tri, dtype=np.int64), vals, 3 * points.shape[0])


def _shared_rows(points, triangles, dirs, scheme, tri, lam, shapes: TriangleShapes) -> "DataRows":
    """data_rows of triangles that are translates of shapes.reps': each shape's points in
    chunks of _CHUNK, the chunks shared among the thread knob's threads with one BLAS
    thread each (every chunk's product is the same call at any count, so the same bits;
    the DTM job's 1M points: the assembly's serial stretch)."""
    corners = points[triangles[shapes.reps]]
    G, _ = rsd.barycentric_gradients(corners)
    maps = linear_maps(corners, dirs[shapes.reps], G)                 # (k, 21, 9)
    key = shapes.key[tri]
    vals = np.empty((tri.shape[0], N_LOCAL))
    chunks = []                                                       # (shape, its points' rows)
    for k in range(shapes.reps.size):
        rows = np.flatnonzero(key == k)
        chunks += [(k, rows[start:start + _CHUNK]) for start in range(0, rows.size, _CHUNK)]

    def fill(block: slice) -> None:
        k, part = chunks[block.start]
        vals[part] = rsd.basis(scheme, lam[part]).T @ maps[k]
    with blas_threads(1):
        parallel_blocks(fill, len(chunks), 1)
    return DataRows(np.ascontiguousarray(triangles, dtype=np.int64),
                    np.ascontiguousarray(tri, dtype=np.int64), vals, 3 * points.shape[0])


@dataclass
class DataRows:
    """The data term's rows A (M, 3N): data point i lies in triangle tri[i] of triangles
    (T, 3) and F(x_i) = values[i] · u[local_dofs(triangles)[tri[i]]] (values (M, 9),
    smoothing_energy's local order); unknowns: the length of u (3N). A is applied by the
    kernels (`fitted`, `adjoint`), never formed as a sparse matrix (0.15 GB at 1M points,
    and 0.2 s to build)."""

    triangles: np.ndarray
    tri: np.ndarray
    values: np.ndarray
    unknowns: int

    def fitted(self, u: np.ndarray) -> np.ndarray:
        """A u: F at the data points (M,) for u (3N,), (M, k) for u (3N, k). Kernel
        rows_product, the points in fixed blocks of ROW_BLOCK in the thread knob's threads;
        each row summed over its unknowns in increasing order (the sums of a CSR product)."""
        columns = np.ascontiguousarray(u, dtype=np.float64).reshape(u.shape[0], -1)
        m = self.tri.shape[0]
        out = np.empty((m, columns.shape[1]))
        values = np.ascontiguousarray(self.values, dtype=np.float64)
        parallel_blocks(lambda part: kernel.rows_product(self.triangles, self.tri, values, columns, out,
                                                         part.start, part.stop), m, ROW_BLOCK)
        return out.reshape((m,) + u.shape[1:])

    def adjoint(self, r: np.ndarray) -> np.ndarray:
        """Aᵀ r (3N,) for r (M,), (3N, k) for r (M, k). Kernel rows_adjoint, one thread over
        the points in increasing order (each entry's sum in that order: a CSR Aᵀ r's)."""
        columns = np.ascontiguousarray(r, dtype=np.float64).reshape(r.shape[0], -1)
        out = np.zeros((self.unknowns, columns.shape[1]))
        kernel.rows_adjoint(self.triangles, self.tri, np.ascontiguousarray(self.values, dtype=np.float64),
                            columns, out)
        return out.reshape((self.unknowns,) + r.shape[1:])

    def points_by_triangle(self) -> tuple[np.ndarray, np.ndarray]:
        """(first (T + 1,), points (M,)) int64: triangle t's data points are
        points[first[t]:first[t + 1]], in increasing order (by_triangle)."""
        count = self.triangles.shape[0]
        first = np.zeros(count + 1, dtype=np.int64)
        np.cumsum(np.bincount(self.tri, minlength=count), out=first[1:])
        return first, self.by_triangle

    def normal_values(self, pattern: "VertexPattern", w: np.ndarray) -> np.ndarray:
        """Aᵀ W A for data weights w (M,) as the CSR values of the energy's pattern
        (assemble_energy's, from `pattern`): each data point's 9 × 9 term added at its
        triangle's unknowns by the kernel (_smoothing_system.data_scatter), in the order
        by_triangle, without forming A or a sparse product."""
        data = np.zeros(9 * pattern.cols.size)
        kernel.data_scatter(self.triangles, self.tri, np.ascontiguousarray(self.values, dtype=np.float64),
                            np.ascontiguousarray(w, dtype=np.float64), self.by_triangle,
                            pattern.row_start, pattern.cols, data)
        return data

    @cached_property
    def by_triangle(self) -> np.ndarray:
        """(M,) the data points by triangle, ties in point order: the order normal_values
        adds them in (each entry then sums its points in this order), so that one
        triangle's points write to the same rows one after another (1M random points
        on a 250k-vertex mesh: 1.08 s in point order, 0.59 s so)."""
        return np.argsort(self.tri, kind="stable")


@dataclass
class System:
    """The pieces of S that do not change with s or the weights (normalised units).

    K: energy (3N, 3N) on assemble_energy's pattern (any CSR with sorted indices and every
    diagonal entry stored, when data is None). data: the data rows (DataRows), or None
    when the data are the vertices (row i is f_i). z (M,) data values. grad_mask (N,)
    vertices with gradient data, grad_values (N, 2) (rows without data are 0).

    S is built on K's pattern: its values are s K's plus the data and gradient terms,
    added in place (the diagonal's positions, and with DataRows their kernel), so no
    sparse sum or product is formed; the indices are K's own arrays. The diagonal's
    positions are found when a matrix first needs them (vertex data, gradients or a
    ridge: 0.6 s at 1M vertices, spent for nothing by a fit of data rows alone).
    """

    K: sp.csr_matrix
    data: DataRows | None
    z: np.ndarray
    grad_mask: np.ndarray | None = None
    grad_values: np.ndarray | None = None
    vertices_ordered: bool = False
    """True when the vertices are numbered in a fill-reducing order already (vertex_order):
    CHOLMOD then factors the matrix as it is, without an ordering of its own."""
    spent: bool = field(default=False, init=False)
    """True once a matrix was made with keep_energy=False: K's values are that matrix's now,
    and the system makes no other. Once `solve` has solved with it by a direct factor, K is
    an empty matrix of its shape, so that the values' memory is free for what follows the
    solve (hat_trace's probes: 0.75 GB at 1M vertices)."""

    @property
    def n_unknowns(self) -> int:
        return self.K.shape[0]

    @cached_property
    def diagonal(self) -> np.ndarray:
        """(3N,) the position of each diagonal entry in K.data."""
        K = self.K
        rows = np.repeat(np.arange(K.shape[0], dtype=K.indices.dtype), np.diff(K.indptr))
        where = np.flatnonzero(K.indices == rows)
        if where.size != K.shape[0]:
            raise ValueError("the energy matrix must store every diagonal entry")
        return where

    @cached_property
    def pattern(self) -> VertexPattern:
        """The vertex pattern K is assembled on (assemble_energy), for the data term."""
        pattern = vertex_pattern(self.data.triangles, self.n_unknowns // 3)
        if 9 * pattern.cols.size != self.K.nnz:
            raise ValueError("the energy matrix is not on the mesh's vertex pattern")
        return pattern

    def fitted(self, u: np.ndarray) -> np.ndarray:
        """F at the data points (M,) for unknowns u (3N,); (M, k) for k columns u (3N, k)."""
        return data_fitted(self.data, u)

    def adjoint(self, r: np.ndarray) -> np.ndarray:
        """A^T r (3N,) for r (M,); (3N, k) for k columns r (M, k)."""
        return data_adjoint(self.data, r, self.n_unknowns)

    def normal_values(self, w: np.ndarray) -> np.ndarray:
        """Aᵀ W A's values on K's pattern (DataRows.normal_values), for data rows only."""
        return self.data.normal_values(self.pattern, w)

    def matrix(self, s: float, w: np.ndarray, mu: float, held_out: np.ndarray | None = None,
               ridge: float = 0.0, normal: np.ndarray | None = None,
               keep_energy: bool = True) -> tuple[sp.csr_matrix, np.ndarray]:
        """(S, rhs) for strength s, data weights w (M,), gradient weight mu. held_out: (N,)
        bool vertices whose gradient data are left out too (a cross-validation fold of
        vertex data: a held-out point is held out with its gradient, which for gradients
        fitted to the heights carries its height). ridge: adds ridge × (mean diagonal of
        S) × I (`solve`). normal: `normal_values(w)` when the caller has them (a
        cross-validation fold reuses its own for every s). keep_energy=False: S's values
        are written over K's (the same bits: each is s times K's, then the same terms
        added), so the system holds one array of values, not two, while S is factored
        (the last matrix of a fit: 0.5 GB at 1M vertices), and is `spent`."""
        if self.spent:
            raise ValueError("the energy's values were overwritten by a matrix made with keep_energy=False")
        n = self.n_unknowns
        rhs = self.adjoint(w * self.z)
        gradients = gradient_terms(self.grad_mask, self.grad_values, mu, held_out)
        if keep_energy:
            values = self.K.data * s
        else:
            values = self.K.data
            values *= s
            self.spent = True
        if self.data is None:
            values[self.diagonal[0::3]] += w
        else:
            values += self.normal_values(w) if normal is None else normal
        if gradients is not None:
            weight, pull = gradients
            values[self.diagonal[1::3]] += weight
            values[self.diagonal[2::3]] += weight
            rhs[1::3] += pull[:, 0]
            rhs[2::3] += pull[:, 1]
        if ridge > 0:
            diag = self.diagonal
            values[diag] += ridge * float(values[diag].mean())
        return sp.csr_matrix((values, self.K.indices, self.K.indptr), shape=(n, n)), rhs


def data_fitted(data: DataRows | None, u: np.ndarray) -> np.ndarray:
    """F at the data points (M,) for unknowns u (3N,), (M, k) for u (3N, k): A u, or the
    vertex values u[0::3] when data is None (the data are the vertices)."""
    return u[0::3].copy() if data is None else data.fitted(u)


def data_adjoint(data: DataRows | None, r: np.ndarray, unknowns: int) -> np.ndarray:
    """Aᵀ r (unknowns,) for r (M,), (unknowns, k) for r (M, k); data None: r on the vertex
    values (the data are the vertices)."""
    if data is None:
        out = np.zeros((unknowns,) + r.shape[1:])
        out[0::3] = r
        return out
    return data.adjoint(r)


def gradient_terms(grad_mask: np.ndarray | None, grad_values: np.ndarray | None, mu: float,
                   held_out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The gradient data's terms of S and rhs for weight mu: (weight (N,), the diagonal
    entries of each vertex's two gradient unknowns; pull (N, 2), their rhs), or None when
    there are no gradient data or mu is 0. grad_mask (N,) 1.0 where a vertex has gradient
    data grad_values (N, 2); held_out (N,) bool: vertices whose gradient data are left out
    (System.matrix)."""
    if grad_mask is None or not mu > 0:
        return None
    mask, grads = grad_mask, grad_values
    if held_out is not None:
        mask = mask * ~held_out
        grads = np.where(mask[:, None] > 0, grads, 0.0)
    return mu * mask, mu * grads


# ------------------------------------------------------------------------------ solvers
def available_solvers() -> list[str]:
    """Solvers this environment can run, best first (docs/smoothing.md: measurements)."""
    names = []
    try:
        import sksparse.cholmod  # noqa: F401
        names.append("cholmod")
    except ImportError:
        pass
    names.append("superlu")
    try:
        import pyamg  # noqa: F401
        names.append("amg-cg")
    except ImportError:
        pass
    return names


DIRECT_BLAS_THREADS = 1
"""BLAS threads of the direct factorisations and solves. CHOLMOD's supernodal kernels give
other bits on two BLAS threads than on one, so the fit's bytes would depend on the
machine's cores and on where a tile ran; one thread costs about 5-10 % of the solve
(200k vertices: 6.8-7.0 s against 6.2-6.7 s on two threads)."""


METIS_FROM = 300_000
"""Unknowns from which the vertices are renumbered in METIS's nested-dissection order of
the vertex graph (vertex_order) before the system is assembled, and CHOLMOD factors it in
that order. Below, CHOLMOD's default chooses (AMD, then METIS as well when AMD's fill is
large, keeping the better; its choice there may be AMD). From 200k vertices up that default
had chosen METIS at every size measured, on the graph of the unknowns, 9× the vertex
graph's entries (RESULTS.md, the smoothing fit in tiles)."""


def vertex_order(triangles: np.ndarray, n: int) -> np.ndarray | None:
    """(n,) METIS's nested-dissection order of the n vertices of a mesh with triangles
    (T, 3); None below METIS_FROM unknowns (3 n) or where this CHOLMOD was built without
    METIS. Numbering the vertices in it (each vertex's 3 unknowns together) gives the
    Cholesky factor the fill of METIS's order of the unknowns' graph, without building
    and ordering that graph."""
    cholmod = _cholmod()
    if 3 * n < METIS_FROM:
        return None
    pattern = vertex_pattern(triangles, n)        # symmetric: its CSR is its CSC
    index = np.int32 if pattern.cols.size < 2**31 else np.int64
    adjacency = sp.csc_matrix((np.ones(pattern.cols.size), pattern.cols.astype(index),
                               pattern.row_start.astype(index)), shape=(n, n))
    try:
        return np.asarray(cholmod.analyze(adjacency, ordering_method="metis").P(), dtype=np.int64)
    except cholmod.CholmodError:
        return None


SIMPLICIAL_BELOW = 40_000
"""Unknowns below which CHOLMOD factors simplicially (left-looking, no BLAS) rather than by
its own choice, which is supernodal for every smoothing system: the search's windows
(15k unknowns: 22-26 ms a factor against 31-38 ms supernodal, 56 factors in a DTM job's
search) and the multigrid's coarsest level are that small; autzen_trim's windows at
--spacing 2 (93k unknowns: 554 ms against 319-349 ms) are not. Measured on this 2-core
machine, one BLAS thread (DIRECT_BLAS_THREADS), scikit-sparse's analyze(mode=...)."""


def _analyze(csc, ordered: bool = False):
    """CHOLMOD's symbolic analysis of csc: in its own order when `ordered` (the vertices
    are numbered by vertex_order), else by CHOLMOD's default ordering; simplicial below
    SIMPLICIAL_BELOW unknowns, else CHOLMOD's choice."""
    cholmod = _cholmod()
    mode = "simplicial" if csc.shape[0] < SIMPLICIAL_BELOW else "auto"
    if ordered:
        return cholmod.analyze(csc, mode=mode, ordering_method="natural")
    return cholmod.analyze(csc, mode=mode)


def _cholmod():
    """scikit-sparse's CHOLMOD module, imported on first use (0.3 s, and only a smoothing
    fit needs it); ImportError where it is not installed (available_solvers says so)."""
    import sksparse.cholmod

    return sksparse.cholmod


class Factor:
    """A solver for one SPD matrix S: ``solve(b)`` for any number of right-hand sides.

    method: "cholmod" (scikit-sparse, AMD/METIS ordering, supernodal Cholesky),
    "superlu" (scipy's splu with the symmetric MMD ordering of A^T + A and diagonal
    pivoting, i.e. a Cholesky-like LU), or "amg-cg" (conjugate gradients preconditioned by
    pyamg's smoothed-aggregation V-cycle, relative residual 1e-10). S: the matrix, for the
    refinement step; None once `solve(keep_energy=False)` released it.
    """

    def __init__(self, S: sp.csr_matrix, method: str, analysis=None, ordered: bool = False):
        self.method = method
        self.ordered = ordered
        self.S = S
        self.analysis = analysis
        with blas_threads(DIRECT_BLAS_THREADS):
            self._factorise(S.T)  # S is symmetric: its CSR transposed is its CSC, without a copy

    def _factorise(self, csc) -> None:
        method = self.method
        try:
            if method == "cholmod":
                if self.analysis is None:          # the fill-reducing ordering, kept for reuse
                    self.analysis = _analyze(csc, self.ordered)
                self._factor = self.analysis.cholesky(csc)
            elif method == "superlu":
                self._factor = spla.splu(csc, permc_spec="MMD_AT_PLUS_A",
                                         diag_pivot_thresh=0.0, options={"SymmetricMode": True})
            elif method == "amg-cg":
                import pyamg
                B = _near_null_space(self.S.shape[0])
                self._ml = pyamg.smoothed_aggregation_solver(self.S, B=B, symmetry="symmetric")
                self._M = self._ml.aspreconditioner(cycle="V")
            else:
                raise SmoothingError(f"unknown solver {method!r}; choose one of "
                                     f"{', '.join(available_solvers())}")
        except Exception as exc:       # scikit-sparse's CholmodError derives from Exception only
            if isinstance(exc, SmoothingError):
                raise
            if not isinstance(exc, (RuntimeError, ValueError, ArithmeticError)) and \
                    type(exc).__module__ != "sksparse.cholmod":
                raise
            raise SmoothingError("the smoothing system is singular: some part of the mesh has "
                                 "fewer than 3 weighted data points") from exc

    def solve(self, b: np.ndarray, refine: bool = True) -> np.ndarray:
        """S⁻¹ b for b (n,), or column by column for b (n, k). Direct solvers take one
        step of iterative refinement: the system's condition grows like N² (a
        fourth-order problem), and at 1M vertices one Cholesky solve left a relative
        residual of 5e-5 (one more solve costs ~3 % of the factorisation). They solve k
        columns in one pass over the factor, which costs less than k passes (hat_trace)."""
        if self.method in ("cholmod", "superlu"):
            if refine and self.S is None:
                raise ValueError("the factor's matrix was released (solve with keep_energy=False): "
                                 "it solves without refinement only")
            direct = self._factor if self.method == "cholmod" else self._factor.solve
            with blas_threads(DIRECT_BLAS_THREADS):
                x = direct(b)
                return x + direct(b - self.S @ x) if refine else x
        if b.ndim == 2:
            return np.stack([self.solve(column, refine) for column in b.T], axis=1)
        x, info = spla.cg(self.S, b, rtol=1e-10, maxiter=2000, M=self._M)
        if info != 0:
            raise SmoothingError(f"conjugate gradients did not converge ({info} iterations)")
        return x


def _near_null_space(n: int) -> np.ndarray:
    """Candidate vectors for smoothed aggregation: the three unknowns of a vertex apart."""
    B = np.zeros((n, 3))
    for c in range(3):
        B[c::3, c] = 1.0
    return B


def solve(system: System, s: float, w: np.ndarray, mu: float, method: str,
          ridge: float = 0.0, held_out: np.ndarray | None = None,
          keep_energy: bool = True) -> tuple[np.ndarray, Factor]:
    """u (3N,) minimising the functional, and the factorisation (to reuse for traces and,
    through its ``analysis``, for matrices of the same pattern).

    ridge: adds ridge × (mean diagonal of S) × I (the pattern is unchanged: every diagonal
    entry is stored). Cross-validation passes a tiny one: a held-out block can cover a
    whole island of the trimmed mesh, whose unknowns then have no data, and the ridge
    gives them the trend plane's height (0 in normalised units) instead of a singular
    matrix; elsewhere it moves the fit by about that relative amount. held_out: vertices
    whose gradient data are left out (System.matrix). keep_energy=False: S is made over
    the system's energy, which then makes no other matrix (System.matrix); a direct
    factor then releases S once u is found (its refinement step was the last use), and
    solves without refinement only (as hat_trace does).
    """
    S, rhs = system.matrix(s, w, mu, held_out, ridge, keep_energy=keep_energy)
    factor = Factor(S, method, None, system.vertices_ordered)
    u = factor.solve(rhs)
    if not keep_energy and method in ("cholmod", "superlu"):
        factor.S = None
        system.K = sp.csr_matrix(system.K.shape)
    return u, factor


def hat_trace(system: System, factor: Factor, w: np.ndarray, probes: int, seed: int) -> float:
    """Hutchinson estimate of tr(H), H = A S⁻¹ A^T W: the effective degrees of freedom.

    Rademacher probes v (M,): E[v^T H v] = tr H; its standard deviation is below
    sqrt(2 tr H / probes) (H's eigenvalues lie in [0, 1]). The probes are solved together,
    as the columns of one right-hand side (Factor.solve: 4 probes at 245k vertices took
    0.30 s so against 0.74 s one by one).
    """
    rng = np.random.default_rng(seed)
    V = np.stack([rng.choice(np.array([-1.0, 1.0]), size=w.shape[0]) for _ in range(probes)], axis=1)
    X = factor.solve(system.adjoint(w[:, None] * V), refine=False)     # an estimate anyway
    F = system.fitted(X)
    # vᵀF by numpy's pairwise sum in one thread: a BLAS dot splits long vectors across its
    # threads, and the edf's last digits then changed with the thread count (1M data)
    return sum(float(np.add.reduce(V[:, k] * F[:, k])) for k in range(probes)) / probes


def timed(seconds: dict, key: str):
    """Context manager adding the wall time of its block to seconds[key]."""
    class _Timer:
        def __enter__(self):
            self.start = time.perf_counter()

        def __exit__(self, *exc):
            seconds[key] = seconds.get(key, 0.0) + time.perf_counter() - self.start
            return False
    return _Timer()


__all__ = ["assemble_energy", "data_rows", "DataRows", "System", "incidence", "data_fitted",
           "data_adjoint", "gradient_terms", "available_solvers", "Factor", "solve",
           "hat_trace", "timed"]
