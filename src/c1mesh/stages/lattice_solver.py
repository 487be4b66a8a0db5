"""The smoothing system solved by multigrid-preconditioned CG when the vertices are lattice nodes (issue 38).

When a mesh's vertices are nodes of a regular grid and every cell (i, j)-(i+1, j+1) is
split by the diagonal from (i, j) to (i+1, j+1) (cells may be missing), the smoothing
system S u = rhs (smoothing_system.System.matrix: 3 unknowns f, ∂x f, ∂y f per vertex) is
a 7-point stencil of 3 × 3 blocks whose coefficients vary only through the data term. So
geometric multigrid solves it, where CHOLMOD needs 41-48 s and 6.7 GB at 1M vertices
(benchmarks/RESULTS.md, "Grid-vertex smoothing solvers (issue 38, study)"). `lattice_solve`
is what that study recommends:

* CG on S, preconditioned by one symmetric V(1,1) cycle, started from the full-multigrid
  guess (the rhs restricted to every level, the coarsest solved, then on each finer level
  P and one V-cycle);
* coarse grids of twice the spacing (coarse node (I, J) on fine node (2I, 2J), the same
  diagonal), down to about COARSEST vertices, solved there by the package's direct solver
  (smoothing_system.Factor: CHOLMOD with DIRECT_BLAS_THREADS BLAS threads);
* P the cubic Hermite on the coarse edges: a fine node is a coarse node (its data copied)
  or the midpoint of a coarse edge p0 → p1 (e = p1 − p0, unit tangent t, normal m), where
  f = (f0 + f1)/2 + (g0 − g1)·e/8, ∂t f = (3/2)(f1 − f0)/|e| − (g0 + g1)·e/(4|e|),
  ∂m f = (g0 + g1)·m/2: exact for quadratics (what a fourth-order operator needs; the
  coarse RSD spline's own values reproduce only linears and took twice the iterations).
  It depends on the coarse grid's spacings (hx, hy) only;
* coarse operators Galerkin, Pᵀ S P (they keep the 7-point block pattern);
* the smoother block (3 × 3 per vertex) Gauss–Seidel in the 3 colours (i + j) mod 3, which
  no stencil offset keeps: 0, 1, 2 before the coarse correction and 2, 1, 0 after it, so
  the cycle is symmetric (stages/_lattice_solver.pyx; the vertices of a colour in fixed
  blocks in the thread knob's threads).

Nodes absent from the grid (outside the data's support, missing cells) are simply not
vertices: P's rows for them are dropped, and a coarse node is kept when its own fine node
exists, or when at least two fine nodes of its support do (it then stands in for the
missing node beyond a ragged border, so that P stays exact for quadratics on the fine
nodes next to it). A coarse node reaching no fine node, or only one, is dropped: its P
columns would be empty or would share their only rows with a neighbour's, and Pᵀ S P
would be singular. Each level keeps its own node list.

Stopping (`pcg`): when the last CG step moved no value unknown by more than `step_tol`.
The relative residual is no guide here: inside data holes S is s K, ~1e-9 of the data's
eigenvalues, and a residual of 6e-7 left 113 mm at s = 0.003 (the study); under this
preconditioner each step contracts the error by 0.3-0.6, so the last step bounds it (0.05
mm stopped every run of the study within 0.007-0.074 mm of CHOLMOD). MAX_ITERATIONS is a
hard cap: reaching it raises SmoothingError.

Determinism: the bits do not depend on the thread count. CG's inner products are numpy's
pairwise sums (np.add.reduce), not BLAS dot products (OpenBLAS may split those across
threads); scipy's sparse products run in one thread; the coarsest solve is Factor's,
with DIRECT_BLAS_THREADS; the sweeps write disjoint vertices in fixed blocks.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from c1mesh.core.lazy import LazyModule
from c1mesh.core.threads import parallel_blocks
from c1mesh.stages import _lattice_solver as kernel
from c1mesh.stages.smoothing_energy import SmoothingError
from c1mesh.stages.smoothing_system import Factor, available_solvers

sp = LazyModule("scipy.sparse")

COARSEST = 20_000
"""Coarsen while a level has more vertices than this; the last level is factored
(1M vertices: 1001² → 501² → 251² → 126², the study's hierarchy)."""
MAX_ITERATIONS = 200
"""CG iterations after which `pcg` gives up (SmoothingError). The study needed at most 34
(V-cycles without the full-multigrid start, s = 0.003, 1M vertices with holes)."""
SWEEP_BLOCK = 1 << 14
"""Vertices per block of the Gauss–Seidel kernels (one colour's vertices in blocks in the
thread knob's threads)."""
OFFSETS = ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1))
"""The fine nodes a coarse node's data reach: the node itself and the midpoints of its 6
coarse edges, as fine-grid offsets (di, dj) from its fine node."""


@dataclass(frozen=True, eq=False)
class Lattice:
    """Where a system's vertices sit on a regular grid.

    shape (ny, nx): the full grid's nodes; spacing (hx, hy) and origin (x0, y0) in the
    units of the points (smooth_fit: the points given to it; lattice_solve: the lengths S
    was built in, since its gradient unknowns are per those units); nodes (N,) int64:
    vertex k of the system is grid node nodes[k] = j nx + i, at origin + (i hx, j hy).
    Nodes absent from the mesh are not listed. The mesh's triangles split each cell
    (i, j)-(i+1, j+1) by the diagonal from (i, j) to (i+1, j+1); cells may be missing.
    Made with anything else (not two whole positive sizes, spacings > 0, a finite
    origin, 1-D integer nodes): SmoothingError."""

    shape: tuple
    spacing: tuple
    origin: tuple
    nodes: np.ndarray

    def __post_init__(self):
        try:
            ny, nx = (int(v) for v in self.shape)
            hx, hy = (float(v) for v in self.spacing)
            x0, y0 = (float(v) for v in self.origin)
        except (TypeError, ValueError):
            raise SmoothingError("a lattice's shape must be (ny, nx), its spacing (hx, hy) and its origin "
                                 "(x0, y0)") from None
        if ny < 1 or nx < 1 or not all(np.isfinite(v) for v in (hx, hy, x0, y0)) or hx <= 0 or hy <= 0:
            raise SmoothingError(f"a lattice needs a positive shape and spacing and a finite origin, got "
                                 f"{self.shape}, {self.spacing}, {self.origin}")
        nodes = np.asarray(self.nodes)
        if nodes.ndim != 1 or not np.issubdtype(nodes.dtype, np.integer):
            raise SmoothingError(f"a lattice's nodes must be a 1-D integer array, got {nodes.dtype} {nodes.shape}")
        object.__setattr__(self, "shape", (ny, nx))
        object.__setattr__(self, "spacing", (hx, hy))
        object.__setattr__(self, "origin", (x0, y0))
        object.__setattr__(self, "nodes", nodes.astype(np.int64, copy=False))

    def positions(self) -> np.ndarray:
        """(N, 2) the vertices' positions, origin + (i hx, j hy)."""
        j, i = np.divmod(self.nodes, self.shape[1])
        return np.stack([self.origin[0] + i * self.spacing[0], self.origin[1] + j * self.spacing[1]], axis=1)

    def scaled(self, centre, length: float) -> "Lattice":
        """The same lattice in the units (x − centre) / length (smooth_fit's normalised units)."""
        return replace(self, spacing=(self.spacing[0] / length, self.spacing[1] / length),
                       origin=((self.origin[0] - centre[0]) / length, (self.origin[1] - centre[1]) / length))


def _checked_nodes(lattice: Lattice, n: int) -> tuple[np.ndarray, int, int]:
    """(nodes, nx, ny), or SmoothingError where the lattice cannot describe n vertices."""
    ny, nx = lattice.shape
    nodes = lattice.nodes
    if nodes.shape != (n,):
        raise SmoothingError(f"the lattice's nodes must be ({n},), one per vertex, got {nodes.shape}")
    if n and (nodes.min() < 0 or nodes.max() >= nx * ny):
        raise SmoothingError(f"the lattice's nodes must lie in [0, {nx * ny - 1}]")
    if np.unique(nodes).size != n:
        raise SmoothingError("the lattice's nodes must be distinct")
    return nodes, nx, ny


# ------------------------------------------------------------------------ prolongation
def hermite_weights(Hx: float, Hy: float) -> dict:
    """{(di, dj): W (3, 3)}: the fine datum (f, ∂x f, ∂y f) at fine offset (di, dj) from a
    coarse node, per unit coarse datum there, for coarse spacings (Hx, Hy): the identity at
    (0, 0), and at an edge midpoint the p0 part of the module doc's Hermite formula with
    e = (di Hx, dj Hy)."""
    W = {(0, 0): np.eye(3)}
    for di, dj in OFFSETS[1:]:
        e = np.array([di * Hx, dj * Hy], dtype=float)
        le = float(np.hypot(e[0], e[1]))
        t = e / le
        m = np.array([-t[1], t[0]])
        w = np.zeros((3, 3))
        w[0, 0] = 0.5
        w[0, 1:] = e / 8
        w[1:, 0] = t * (-1.5 / le)
        w[1:, 1:] = np.outer(t, -e / (4 * le)) + np.outer(m, m / 2)
        W[(di, dj)] = w
    return W


def prolongation(nodes: np.ndarray, nx: int, ny: int, spacing) -> tuple:
    """(P, coarse nodes, nxc, nyc) from the fine level of `nodes` (flat indices j nx + i,
    ascending or not; vertex k is nodes[k]) on an nx × ny grid of spacing (hx, hy) to the
    coarse grid of (nx // 2 + 1) × (ny // 2 + 1) nodes, coarse node (I, J) on fine node
    (2I, 2J). P (3 len(nodes), 3 len(coarse nodes)) CSR: Hermite weights (hermite_weights
    at 2 hx, 2 hy); coarse nodes (ascending flat indices) those kept by the module doc's
    rule: own fine node present, or at least two fine nodes of its support."""
    nodes = np.asarray(nodes, dtype=np.int64)
    nxc, nyc = nx // 2 + 1, ny // 2 + 1
    where = np.full(nx * ny, -1, dtype=np.int64)
    where[nodes] = np.arange(nodes.size)
    W = hermite_weights(2 * float(spacing[0]), 2 * float(spacing[1]))
    J, I = np.divmod(np.arange(nxc * nyc, dtype=np.int64), nxc)
    hits = []
    reach = np.zeros(nxc * nyc, dtype=np.int64)
    for di, dj in OFFSETS:
        fi, fj = 2 * I + di, 2 * J + dj
        inside = (fi >= 0) & (fi < nx) & (fj >= 0) & (fj < ny)
        fine = np.full(I.size, -1, dtype=np.int64)
        fine[inside] = where[fj[inside] * nx + fi[inside]]
        hits.append(fine)
        reach += fine >= 0
    keep = (hits[0] >= 0) | (reach >= 2)
    coarse = np.flatnonzero(keep)
    column = np.full(nxc * nyc, -1, dtype=np.int64)
    column[coarse] = np.arange(coarse.size)
    return stencil_matrix(hits, column, W, nodes.size, coarse.size), coarse, nxc, nyc


def stencil_matrix(hits: list, column: np.ndarray, weights: dict, fine: int, coarse: int):
    """P (3 fine, 3 coarse) CSR of a prolongation stencil: hits[k] (C,) the fine vertex at
    OFFSETS[k] from each of C coarse grid nodes (−1: none), column (C,) each node's coarse
    vertex (−1: dropped), weights {(di, dj): W (3, 3)} the fine datum per unit coarse datum
    at each offset (hermite_weights; benchmarks.grid_solver measures others)."""
    rows, cols, vals = [], [], []
    for (di, dj), hit in zip(OFFSETS, hits):
        ok = (hit >= 0) & (column >= 0)
        fv, cv = hit[ok], column[ok]
        w = weights[(di, dj)]
        for p in range(3):
            for q in range(3):
                if w[p, q] != 0.0:
                    rows.append(3 * fv + p)
                    cols.append(3 * cv + q)
                    vals.append(np.full(fv.size, w[p, q]))
    P = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(3 * fine, 3 * coarse))
    P.sum_duplicates()
    return P


# ------------------------------------------------------------------------ multigrid
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a · b by numpy's pairwise sum in one thread (the same bits at any thread count)."""
    return float(np.add.reduce(a * b))


def colours(nodes: np.ndarray, nx: int) -> np.ndarray:
    """(N,) int8: the colour (i + j) mod 3 of each node j nx + i."""
    j, i = np.divmod(np.asarray(nodes, dtype=np.int64), nx)
    return ((i + j) % 3).astype(np.int8)


def colour_order(lattice: Lattice) -> np.ndarray:
    """(N,) the vertices in the order the solver's levels number them: colour by colour
    ((i + j) mod 3), by node within a colour. A system assembled with its vertices
    numbered so (smooth_fit does) is solved in place; any other order costs the solver
    a permuted copy of S."""
    return np.lexsort((lattice.nodes, colours(lattice.nodes, lattice.shape[1])))


def _permuted(S, order: np.ndarray):
    """S with vertex order[k] as vertex k (rows and columns, 3 unknowns a vertex): a copy."""
    unknowns = (3 * order[:, None] + np.arange(3)).ravel()
    rank = np.empty_like(unknowns)
    rank[unknowns] = np.arange(unknowns.size)
    rows = S[unknowns]
    rows.indices = rank[rows.indices].astype(rows.indices.dtype)
    rows.has_sorted_indices = False
    return rows


class _Level:
    """One grid: S (CSR) with its vertices numbered colour by colour (colour_order), their
    nodes, each colour's first vertex (bounds (4,)), the inverses of S's diagonal blocks,
    and P, Pᵀ to the next coarser grid (None on the coarsest)."""

    def __init__(self, S, nodes: np.ndarray, nx: int, ny: int):
        S = S.tocsr()
        if S.indptr.dtype != S.indices.dtype:
            S.indptr = S.indptr.astype(S.indices.dtype)
        self.S, self.nodes, self.nx, self.ny = S, nodes, nx, ny
        colour = colours(nodes, nx)
        if (np.diff(colour) < 0).any():
            raise ValueError("a level's vertices must be numbered colour by colour")
        self.bounds = np.searchsorted(colour, np.arange(4, dtype=np.int8))
        self.dinv = np.empty((nodes.size, 3, 3))
        counts = []
        parallel_blocks(lambda part: counts.append(kernel.block_inverses(
            S.indptr, S.indices, S.data, colour, self.dinv, part.start, part.stop)), nodes.size, SWEEP_BLOCK)
        self.couplings = sum(c for c, _ in counts)
        singular = sum(s for _, s in counts)
        if singular and not self.couplings:
            raise SmoothingError(f"{singular} diagonal 3 × 3 blocks of the lattice system are not positive "
                                 "definite: a vertex lacks data and energy")
        self.P = self.PT = None

    def sweep(self, x: np.ndarray, b: np.ndarray, order) -> None:
        """Block Gauss–Seidel over the colours in `order`, in place."""
        S = self.S
        for c in order:
            first = int(self.bounds[c])
            parallel_blocks(lambda part: kernel.sweep(S.indptr, S.indices, S.data, b, x, self.dinv,
                                                      first + part.start, first + part.stop),
                            int(self.bounds[c + 1]) - first, SWEEP_BLOCK)


class LatticeSolver:
    """The multigrid hierarchy of S on `lattice` (module doc), built once for any number of
    right-hand sides: `start` (the full-multigrid guess), `pcg` (CG from it), `cycle` (one
    V-cycle, the preconditioner). S (3N, 3N) CSR, symmetric positive definite, vertex k's
    unknowns 3k..3k+2 on node lattice.nodes[k], lattice in the lengths S was built in.
    Vertices numbered colour by colour (colour_order) are solved in S itself, others in
    a permuted copy. coarsest: coarsen while a level has more vertices (None: COARSEST,
    read when called). seconds: the set-up's wall time."""

    def __init__(self, S, lattice: Lattice, coarsest: int | None = None):
        t0 = time.perf_counter()
        if S.shape[0] != S.shape[1] or S.shape[0] % 3:
            raise SmoothingError(f"the system must be square with 3 unknowns per vertex, got {S.shape}")
        nodes, nx, ny = _checked_nodes(lattice, S.shape[0] // 3)
        coarsest = COARSEST if coarsest is None else int(coarsest)
        order = colour_order(lattice)
        self.order = None if (order == np.arange(order.size)).all() else order
        if self.order is not None:
            S, nodes = _permuted(S.tocsr(), order), nodes[order]
        fine = _Level(S, nodes, nx, ny)
        if fine.couplings:
            raise SmoothingError(f"the system is not on the lattice's stencil: {fine.couplings} entries couple "
                                 "vertices of one colour (i + j) mod 3 (cells split by the other diagonal, or "
                                 "nodes that are not the vertices' own?)")
        hx, hy = lattice.spacing
        self.levels = [fine]
        while self.levels[-1].nodes.size > coarsest:
            level = self.levels[-1]
            P, coarse, nxc, nyc = prolongation(level.nodes, level.nx, level.ny, (hx, hy))
            if coarse.size >= level.nodes.size:
                break
            corder = np.lexsort((coarse, colours(coarse, nxc)))
            P = P[:, (3 * corder[:, None] + np.arange(3)).ravel()].tocsr()
            PT = P.T.tocsr()
            level.P, level.PT = P, PT
            self.levels.append(_Level(PT @ (level.S @ P), coarse[corder], nxc, nyc))
            hx, hy = 2 * hx, 2 * hy
        method = available_solvers()[0]
        self.coarse = Factor(self.levels[-1].S, "superlu" if method == "amg-cg" else method)
        self.seconds = time.perf_counter() - t0

    def cycle(self, b: np.ndarray, k: int = 0) -> np.ndarray:
        """One symmetric V(1,1) cycle from zero on level k for right-hand side b (in the
        levels' numbering: colour by colour)."""
        if k == len(self.levels) - 1:
            return self.coarse.solve(b, refine=False)
        level = self.levels[k]
        x = np.zeros_like(b)
        level.sweep(x, b, (0, 1, 2))
        r = b - level.S @ x
        x += level.P @ self.cycle(level.PT @ r, k + 1)
        level.sweep(x, b, (2, 1, 0))
        return x

    def start(self, rhs: np.ndarray) -> np.ndarray:
        """The full-multigrid guess: rhs restricted by Pᵀ to every level, the coarsest
        solved, then on each finer level P and one V-cycle on its residual (in the levels'
        numbering)."""
        bs = [rhs]
        for level in self.levels[:-1]:
            bs.append(level.PT @ bs[-1])
        x = self.coarse.solve(bs[-1], refine=False)
        for k in range(len(self.levels) - 2, -1, -1):
            level = self.levels[k]
            x = level.P @ x
            x += self.cycle(bs[k] - level.S @ x, k)
        return x

    def pcg(self, rhs: np.ndarray, step_tol: float, x0: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """(x, iterations): CG on S x = rhs preconditioned by `cycle`, from x0 (None: `start`),
        stopped when a step moves no value unknown (x[0::3]) by more than step_tol;
        SmoothingError after MAX_ITERATIONS steps."""
        S = self.levels[0].S
        rhs = np.asarray(rhs, dtype=np.float64)
        if rhs.shape != (S.shape[0],):
            raise SmoothingError(f"the right-hand side must have shape ({S.shape[0]},), got {rhs.shape}")
        if self.order is not None:
            x, iterations = self._pcg(rhs.reshape(-1, 3)[self.order].ravel(), step_tol,
                                      None if x0 is None else np.asarray(x0, float).reshape(-1, 3)[self.order].ravel())
            out = np.empty_like(x)
            out.reshape(-1, 3)[self.order] = x.reshape(-1, 3)
            return out, iterations
        return self._pcg(rhs, step_tol, None if x0 is None else np.array(x0, dtype=np.float64))

    def _pcg(self, rhs: np.ndarray, step_tol: float, x0: np.ndarray | None) -> tuple[np.ndarray, int]:
        """pcg in the levels' numbering."""
        S = self.levels[0].S
        x = self.start(rhs) if x0 is None else x0
        r = rhs - S @ x
        z = self.cycle(r)
        p = z.copy()
        rz = _dot(r, z)
        for k in range(1, MAX_ITERATIONS + 1):
            if rz == 0.0:                             # r = 0: x solves it
                return x, k - 1
            Ap = S @ p
            pAp = _dot(p, Ap)
            if not (pAp > 0.0 and np.isfinite(pAp)):
                raise SmoothingError("the smoothing system is not positive definite on the lattice")
            alpha = rz / pAp
            x += alpha * p
            r -= alpha * Ap
            if abs(alpha) * float(np.abs(p[0::3]).max()) <= step_tol:
                return x, k
            z = self.cycle(r)
            rz_next = _dot(r, z)
            p *= rz_next / rz
            p += z
            rz = rz_next
        raise SmoothingError(f"the lattice solver did not converge in {MAX_ITERATIONS} iterations "
                             f"(steps still above {step_tol:g})")


class LatticeFactor:
    """A LatticeSolver in smoothing_system.Factor's place where only its `solve` is used
    (hat_trace's probes): each column solved by `pcg` to step_tol (refine is ignored)."""

    def __init__(self, solver: LatticeSolver, step_tol: float):
        self.solver, self.step_tol = solver, step_tol

    def solve(self, b: np.ndarray, refine: bool = False) -> np.ndarray:
        if b.ndim == 2:
            return np.stack([self.solver.pcg(np.ascontiguousarray(c), self.step_tol)[0] for c in b.T], axis=1)
        return self.solver.pcg(b, self.step_tol)[0]


def lattice_solve(S, rhs: np.ndarray, lattice: Lattice, step_tol: float, x0: np.ndarray | None = None,
                  coarsest: int | None = None) -> tuple[np.ndarray, int]:
    """(x, iterations): S x = rhs by CG preconditioned by the multigrid V(1,1) cycle of S on
    `lattice` (module doc; LatticeSolver), from the full-multigrid guess (x0 None) or x0,
    stopped when a step moves no value unknown (every third) by more than step_tol, in
    S's height units. S (3N, 3N) CSR, vertex k's unknowns 3k..3k+2 on node lattice.nodes[k];
    the lattice in the lengths S was built in. SmoothingError when the system is not on the
    lattice's stencil, or after MAX_ITERATIONS."""
    return LatticeSolver(S, lattice, coarsest).pcg(rhs, step_tol, x0)


__all__ = ["Lattice", "LatticeSolver", "LatticeFactor", "lattice_solve", "prolongation", "hermite_weights",
           "stencil_matrix", "OFFSETS",
           "colour_order",
           "COARSEST", "MAX_ITERATIONS"]
