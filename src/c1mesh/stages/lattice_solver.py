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
  It depends on the coarse grid's spacings (hx, hy) only. The cycles apply P and Pᵀ from
  the node structure (`Transfer`: each coarse vertex's fine vertices, each fine vertex's
  one or two coarse ones, and the 7 weight blocks), in CSR's summation order; P is never
  stored as a matrix (as CSR it held 0.31 GiB at 1M vertices);
* coarse operators Galerkin, Pᵀ S P (they keep the 7-point block pattern), each coarse
  vertex's blocks summed by the kernel `galerkin` straight into that pattern from the
  Transfer's tables, in the summation order of the CSR products (scipy's two sparse
  products took 2.4 s of the 4 s set-up at 1M vertices; the kernel from CSR P and Pᵀ,
  1.1 s with their assembly);
* the set-up's node passes (`coarsen`: the coarse node list by the rule below, each
  coarse vertex's children and each fine vertex's parents; stencil_neighbours, the
  colour bounds, the check of S's slots, the coarsest level's CSR) are kernels too, over
  each level's grid_vertices table (one int32 per grid node): on the 1M DTM stencil the
  set-up costs about 1.05 s of CPU (2.4 s before; cProfile at one thread: Galerkin
  kernels 0.57 s, the coarsest CHOLMOD factorisation 0.30 s, which holds the GIL, the
  diagonal inverses 0.10 s, before they were formed in the sweeps instead of stored);
* every level's S in stencil form by halves (`Stencil`: each vertex's 7 neighbours and
  its 4 blocks of 3 × 3, itself and its 3 forward neighbours; a backward neighbour's
  block is read as the transpose of that neighbour's forward block, S being symmetric),
  one index per 36 values: every pass over S (sweeps, residuals, CG's product) is bound
  by reading it, and CSR read 45 % more than all 7 blocks; the halves hold 4/7 of those
  (1M DTM job: fine blocks 489 → 279 MiB, coarse levels 184 → 105 MiB); the fine
  level's is assembled in that form (stages.lattice_system), never as CSR nor whole;
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

Several right-hand sides (the edf's probes) are solved side by side as the columns of
(3N, k) arrays: every kernel's pass over S serves all k (a pass is bound by reading S),
while each column keeps its own CG and its bits are those it would have alone.

Determinism: the bits do not depend on the thread count. Every kernel (products with S,
P and Pᵀ, residuals, sweeps, Galerkin rows, inner products) works on fixed blocks of
rows or vertices in the thread knob's threads, each sum in a fixed order; the inner
products' block sums are added in block order; the coarsest solve is Factor's, with
DIRECT_BLAS_THREADS.
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
"""Vertices per block of the Gauss–Seidel, stencil and transfer kernels (one colour's
vertices in blocks in the thread knob's threads)."""
ROW_BLOCK = 3 << 14
"""Rows per block of the inner products and CG's vector updates."""
GALERKIN_BLOCK = 1 << 12
"""Coarse vertices per block of the Galerkin kernel."""
OFFSETS = ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1))
"""The fine nodes a coarse node's data reach: the node itself and the midpoints of its 6
coarse edges, as fine-grid offsets (di, dj) from its fine node. Also a stencil's 7 slots:
slot 0 the vertex itself, the odd slots forward, each even slot the backward offset of
the slot before it."""
HALF = (0, 1, 3, 5)
"""The slots (OFFSETS' indices) whose blocks a Stencil stores: self and the forward
offsets (1, 0), (0, 1), (1, 1)."""


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


def _checked_nodes(lattice: Lattice, n: int) -> tuple[np.ndarray, int, int, np.ndarray]:
    """(nodes, nx, ny, where: grid_vertices), or SmoothingError where the lattice cannot
    describe n vertices."""
    ny, nx = lattice.shape
    nodes = lattice.nodes
    if nodes.shape != (n,):
        raise SmoothingError(f"the lattice's nodes must be ({n},), one per vertex, got {nodes.shape}")
    if n and (nodes.min() < 0 or nodes.max() >= nx * ny):
        raise SmoothingError(f"the lattice's nodes must lie in [0, {nx * ny - 1}]")
    where = grid_vertices(nodes, nx, ny)
    if np.count_nonzero(where >= 0) != n:
        raise SmoothingError("the lattice's nodes must be distinct")
    return nodes, nx, ny, where


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


def child_order(weights: np.ndarray) -> np.ndarray:
    """(k,) int32: the slots (OFFSETS' indices) in the order a CSR row block of Pᵀ first
    reaches them, for weights (7, 3, 3) in OFFSETS' order: rows q in order, each over the
    slots in order and p in order, a slot counted at its first nonzero weights[slot, p, q]
    (slots with no nonzero weight are not listed). The Galerkin kernel sums a coarse
    vertex's children in this order, the one of the CSR Pᵀ it replaced (for the Hermite
    weights: 0, 1, ..., 6)."""
    order = []
    for q in range(3):
        for slot in range(len(OFFSETS)):
            if slot not in order and (weights[slot, :, q] != 0.0).any():
                order.append(slot)
    return np.array(order, dtype=np.int32)


def grid_vertices(nodes: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """(nx ny,) int32: the vertex on each node of an nx × ny grid whose vertex k is node
    nodes[k] (−1: none). Fewer than 2^31 vertices (SmoothingError else)."""
    if nodes.size >= np.iinfo(np.int32).max:
        raise SmoothingError(f"the lattice solver takes fewer than 2^31 vertices, got {nodes.size}")
    where = np.full(nx * ny, -1, dtype=np.int32)
    where[nodes] = np.arange(nodes.size, dtype=np.int32)
    return where


def coarsen(nodes: np.ndarray, where: np.ndarray, nx: int, ny: int, spacing) -> tuple:
    """(transfer, coarse, column, nxc, nyc): the coarse level below the fine level of
    `nodes` (n,) (flat indices j nx + i on an nx × ny grid of spacing (hx, hy); vertex k is
    nodes[k], where (nx ny,) int32 = grid_vertices(nodes, nx, ny)). The coarse grid has
    nxc × nyc = (nx // 2 + 1) × (ny // 2 + 1) nodes, node (I, J) on fine node (2I, 2J);
    coarse (m,) int64 the nodes kept by the module doc's rule, numbered colour by colour
    (colour_order's numbering), column (nxc nyc,) int32 each node's coarse vertex (−1:
    dropped: the coarse level's own grid_vertices); transfer the Transfer of the Hermite
    P (hermite_weights at 2 hx, 2 hy). Kernels: coarse_keep and coarse_number (serial, a
    few lookups a coarse node), parent_tables (fine vertices in blocks of SWEEP_BLOCK in
    the thread knob's threads)."""
    nodes = np.ascontiguousarray(nodes, dtype=np.int64)
    nxc, nyc = nx // 2 + 1, ny // 2 + 1
    offsets = np.array(OFFSETS, dtype=np.int32)
    column = np.empty(nxc * nyc, dtype=np.int32)
    m = kernel.coarse_keep(where, nx, ny, offsets, column)
    coarse = np.empty(m, dtype=np.int64)
    children = np.empty((m, len(OFFSETS)), dtype=np.int32)
    kernel.coarse_number(where, nx, ny, offsets, column, coarse, children)
    parents = np.empty((nodes.size, 2), dtype=np.int32)
    parent_slot = np.empty((nodes.size, 2), dtype=np.int8)
    parallel_blocks(lambda part: kernel.parent_tables(nodes, nx, column, nxc, parents, parent_slot, part.start,
                                                      part.stop), nodes.size, SWEEP_BLOCK)
    W = hermite_weights(2 * float(spacing[0]), 2 * float(spacing[1]))
    weights = np.ascontiguousarray([W[off] for off in OFFSETS], dtype=np.float64)
    return Transfer(children, parents, parent_slot, weights), coarse, column, nxc, nyc


# ------------------------------------------------------------------------ multigrid
def _dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(k,) the column-wise inner products of a, b (n, k): kernel.dots' sums over fixed
    blocks of ROW_BLOCK rows in the thread knob's threads, then the blocks' sums added in
    block order (numpy's pairwise sum): the same bits at any thread count, and for a
    column whatever k is."""
    n, k = a.shape
    partial = np.empty((-(-n // ROW_BLOCK), k))
    parallel_blocks(lambda part: kernel.dots(a, b, partial[part.start // ROW_BLOCK], part.start, part.stop),
                    n, ROW_BLOCK)
    return np.array([np.add.reduce(partial[:, c]) for c in range(k)])


def _blockwise(work, n: int) -> None:
    """work(slice) over fixed blocks of ROW_BLOCK of range(n) in the thread knob's threads
    (numpy's element-wise kernels release the GIL; the bits do not depend on the threads)."""
    parallel_blocks(work, n, ROW_BLOCK)


def colours(nodes: np.ndarray, nx: int) -> np.ndarray:
    """(N,) int8: the colour (i + j) mod 3 of each node j nx + i."""
    j, i = np.divmod(np.asarray(nodes, dtype=np.int64), nx)
    return ((i + j) % 3).astype(np.int8)


def _colour_bounds(nodes: np.ndarray, nx: int) -> np.ndarray | None:
    """(4,) int64: each colour's first vertex and the count (vertices bounds[c] to
    bounds[c + 1] have colour c), for nodes (N,) of a grid nx wide numbered colour by
    colour; None when they are not (the kernel colour_bounds: one pass)."""
    bounds = np.empty(4, dtype=np.int64)
    return bounds if kernel.colour_bounds(np.ascontiguousarray(nodes, dtype=np.int64), nx, bounds) else None


def colour_order(lattice: Lattice) -> np.ndarray:
    """(N,) the vertices in the order the solver's levels number them: colour by colour
    ((i + j) mod 3), by node within a colour. LatticeSolver takes a system assembled with
    its vertices numbered so (smooth_fit renumbers them)."""
    return np.lexsort((lattice.nodes, colours(lattice.nodes, lattice.shape[1])))


class Transfer:
    """P and Pᵀ between a level and the next coarser one, applied from the lattice's node
    structure instead of stored as CSR (at 1M vertices P and Pᵀ as CSR held 0.31 GiB; these
    tables hold 22 MB; `coarsen` makes them). children (m, 7) int32: the fine vertex at
    each of OFFSETS' offsets from each coarse vertex (−1: none); parents (n, 2) int32: the
    coarse vertices whose stencil reaches each fine vertex, ascending (−1: none),
    parent_slot (n, 2) int8 the offset of the fine vertex from each; weights (7, 3, 3)
    hermite_weights in OFFSETS' order. P's row 3f + p is Σ weights[slot, p, q] over f's
    parents and q, Pᵀ's row 3c + q Σ weights[slot, p, q] over c's children and p (zero
    weights left out). Each product row is summed in the order of the CSR row (P's
    columns sorted; Pᵀ's entries slot by slot, p by p), so the bits are those of the CSR
    products; rows in fixed blocks of SWEEP_BLOCK in the thread knob's threads."""

    def __init__(self, children: np.ndarray, parents: np.ndarray, parent_slot: np.ndarray, weights: np.ndarray):
        self.children, self.parents, self.parent_slot, self.weights = children, parents, parent_slot, weights
        self.shape = (3 * parents.shape[0], 3 * children.shape[0])      # P's

    def prolong(self, x: np.ndarray, out: np.ndarray | None = None, add: bool = False) -> np.ndarray:
        """P x (3n, k) for the coarse x (3m, k), into out (None: a new array), or out += P x
        when add (one pass, no temporary); returns out."""
        out = np.empty((self.shape[0], x.shape[1])) if out is None else out
        parallel_blocks(lambda part: kernel.prolong(self.parents, self.parent_slot, self.weights, x, out, add,
                                                    part.start, part.stop), self.parents.shape[0], SWEEP_BLOCK)
        return out

    def restrict(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Pᵀ x (3m, k) for the fine x (3n, k), into out (None: a new array); returns out."""
        out = np.empty((self.shape[1], x.shape[1])) if out is None else out
        parallel_blocks(lambda part: kernel.restrict(self.children, self.weights, x, out, part.start, part.stop),
                        self.children.shape[0], SWEEP_BLOCK)
        return out


def stencil_neighbours(nodes: np.ndarray, nx: int, ny: int, where: np.ndarray | None = None) -> np.ndarray:
    """(N, 7) int32: for each vertex of a level (vertex k on node nodes[k] of an nx × ny
    grid), the vertex at each of OFFSETS' offsets from it (slot 0 itself), −1 where
    there is none: the slots of its blocks in stencil form (Stencil). where: the level's
    grid_vertices (None: made here). The kernel `neighbours`, the vertices in blocks of
    SWEEP_BLOCK in the thread knob's threads."""
    nodes = np.ascontiguousarray(nodes, dtype=np.int64)
    where = grid_vertices(nodes, nx, ny) if where is None else where
    offsets = np.array(OFFSETS, dtype=np.int32)
    out = np.empty((nodes.size, len(OFFSETS)), dtype=np.int32)
    parallel_blocks(lambda part: kernel.neighbours(nodes, where, nx, ny, offsets, out, part.start, part.stop),
                    nodes.size, SWEEP_BLOCK)
    return out


def _slots_match(nbr: np.ndarray, nodes: np.ndarray, nx: int, ny: int, where: np.ndarray) -> bool:
    """Whether nbr (N, 7) is stencil_neighbours(nodes, nx, ny) (where: grid_vertices),
    checked by the kernel neighbour_mismatches without making that table (vertices in
    blocks of SWEEP_BLOCK in the thread knob's threads)."""
    if nbr.shape != (nodes.size, len(OFFSETS)) or nbr.dtype != np.int32 or not nbr.flags.c_contiguous:
        return False
    nodes = np.ascontiguousarray(nodes, dtype=np.int64)
    offsets = np.array(OFFSETS, dtype=np.int32)
    wrong = []
    parallel_blocks(lambda part: wrong.append(kernel.neighbour_mismatches(nodes, where, nx, ny, offsets, nbr,
                                                                          part.start, part.stop)),
                    nodes.size, SWEEP_BLOCK)
    return sum(wrong) == 0


class Stencil:
    """A level's S in stencil form by halves: nbr (N, 7) int32 (stencil_neighbours) and
    blocks (4, N, 3, 3), blocks[h, v] the 3 × 3 block of S coupling vertex v to vertex
    nbr[v, HALF[h]] (itself, then its forward neighbours at slots 1, 3, 5; zeros where
    it is −1). S is symmetric: v's block at a backward slot 2, 4, 6 (the vertex u there)
    is the transpose of u's block at the forward slot 1, 3, 5 (where v is), and every
    kernel reads it so. A pass over S reads 0.32 kB a vertex where all 7 blocks were
    0.53 and CSR 0.77, and every pass of the solver is bound by that read. One array of
    blocks per half slot (h first): the backward reads then stream through consecutive
    vertices' whole blocks (vertex-major, they took a pass 3.2 times as long). Products
    and residuals with (3N, k) blocks of vectors, the vertices in fixed blocks of
    SWEEP_BLOCK in the thread knob's threads (each row's sum in a fixed order: the bits
    do not depend on the threads)."""

    def __init__(self, nbr: np.ndarray, blocks: np.ndarray):
        if blocks.shape != (len(HALF), nbr.shape[0], 3, 3):
            raise ValueError(f"a stencil's blocks must be ({len(HALF)}, {nbr.shape[0]}, 3, 3), got {blocks.shape}")
        self.nbr, self.blocks = nbr, blocks
        self.shape = (3 * nbr.shape[0],) * 2

    def csr(self):
        """S (3N, 3N) CSR with sorted indices, both halves (every slot present stored whole,
        zeros too, a backward one as the transpose of the neighbour's forward block),
        by the kernel stencil_csr (one serial pass: the coarsest level's factorisation
        and the tests ask for it)."""
        n = self.nbr.shape[0]
        nnz = 9 * int(np.count_nonzero(self.nbr >= 0))
        indptr, indices, data = np.empty(3 * n + 1, dtype=np.int64), np.empty(nnz, dtype=np.int64), np.empty(nnz)
        kernel.stencil_csr(self.nbr, self.blocks, indptr, indices, data)
        return sp.csr_matrix((data, indices, indptr), shape=self.shape)

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        """S x (3N, k) for x (3N, k)."""
        return self.product(x, np.empty((self.shape[0], x.shape[1])))

    def product(self, x: np.ndarray, out: np.ndarray) -> np.ndarray:
        """out = S x (3N, k) for x (3N, k), in place (out is not x); returns out."""
        parallel_blocks(lambda part: kernel.stencil_product(self.nbr, self.blocks, x, out, part.start, part.stop),
                        self.nbr.shape[0], SWEEP_BLOCK)
        return out

    def residual(self, b: np.ndarray, x: np.ndarray, out: np.ndarray | None = None,
                 vertices: int | None = None) -> np.ndarray:
        """b − S x (3N, k) in one pass, into out (None: a new array); with `vertices`, only
        the rows of the first `vertices` vertices are computed and the others set to 0
        (the caller knows them)."""
        r = np.empty_like(b) if out is None else out
        vertices = self.nbr.shape[0] if vertices is None else vertices
        parallel_blocks(lambda part: kernel.stencil_residual(self.nbr, self.blocks, b, x, r, part.start, part.stop),
                        vertices, SWEEP_BLOCK)
        r[3 * vertices:] = 0.0
        return r


def galerkin(fine: "_Level", transfer: Transfer, neighbours: np.ndarray) -> Stencil:
    """Pᵀ S P in stencil form (by halves: only its HALF slots summed) for the level below
    `fine` (its S), P the `transfer`'s,
    neighbours (m, 7) the coarse level's stencil_neighbours, by the kernel `galerkin`
    straight from the Transfer's node structure (no P as CSR), the coarse vertices in
    fixed blocks of GALERKIN_BLOCK in the thread knob's threads. SmoothingError when an
    entry falls outside the coarse stencil (not a lattice prolongation)."""
    offsets = np.array(OFFSETS, dtype=np.int32)
    order = child_order(transfer.weights)
    blocks = np.empty((len(HALF), neighbours.shape[0], 3, 3))
    S, t = fine.op, transfer
    missing = []
    parallel_blocks(lambda part: missing.append(kernel.galerkin(
        S.nbr, S.blocks, offsets, t.children, order, t.parents, t.parent_slot, t.weights, neighbours, blocks,
        part.start, part.stop)), neighbours.shape[0], GALERKIN_BLOCK)
    if sum(missing):
        raise SmoothingError(f"{sum(missing)} entries of the Galerkin product fall outside the lattice's stencil")
    return Stencil(neighbours, blocks)


class _Level:
    """One grid: S in stencil form (op) with its vertices numbered colour by colour
    (colour_order), their nodes, each colour's first vertex (bounds (4,)), its grid
    spacing (hx, hy), and the Transfer to the next coarser grid (None on the coarsest).
    The inverses of S's diagonal blocks are formed by the sweeps where they use them (not
    stored: 72 MB at the 1M fine level); made here only to check that none is singular. where: its grid_vertices while the level below is made
    (then None). S: op as CSR, made when asked."""

    def __init__(self, op: Stencil, nodes: np.ndarray, nx: int, ny: int, spacing: tuple, where: np.ndarray):
        self.op, self.nodes, self.nx, self.ny, self.spacing, self.where = op, nodes, nx, ny, spacing, where
        self.bounds = _colour_bounds(nodes, nx)
        if self.bounds is None:
            raise ValueError("a level's vertices must be numbered colour by colour")
        counts = []
        parallel_blocks(lambda part: counts.append(kernel.singular_blocks(op.blocks, part.start, part.stop)),
                        nodes.size, SWEEP_BLOCK)
        if sum(counts):
            raise SmoothingError(f"{sum(counts)} diagonal 3 × 3 blocks of the lattice system are not positive "
                                 "definite: a vertex lacks data and energy")
        self.transfer = None
        self._scratch = {}

    @property
    def S(self):
        return self.op.csr()

    def scratch(self, name: str, shape: tuple) -> np.ndarray:
        """A work array of this level kept between cycles (fresh arrays of 3N × k doubles
        cost their page faults again every time): its contents are the caller's to set."""
        array = self._scratch.get(name)
        if array is None or array.shape != shape:
            array = self._scratch[name] = np.empty(shape)
        return array

    def sweep(self, x: np.ndarray, b: np.ndarray, order, from_zero: bool = False) -> None:
        """Block Gauss–Seidel over the colours in `order`, in place, on x, b (3N, k);
        from_zero: x is zero on entry (the first colour reads no S: kernel.first_sweep)."""
        op = self.op
        for n, c in enumerate(order):
            first = int(self.bounds[c])
            if from_zero and n == 0:
                work = lambda part: kernel.first_sweep(op.blocks, b, x, first + part.start, first + part.stop)
            else:
                work = lambda part: kernel.sweep(op.nbr, op.blocks, b, x, first + part.start, first + part.stop)
            parallel_blocks(work, int(self.bounds[c + 1]) - first, SWEEP_BLOCK)


class LatticeSolver:
    """The multigrid hierarchy of S on `lattice` (module doc), built once for any number of
    right-hand sides: `start` (the full-multigrid guess), `pcg` (CG from it), `cycle` (one
    V-cycle, the preconditioner). S: the fine level's Stencil (lattice_system.LatticeSystem
    assembles it), symmetric positive definite, vertex k's unknowns 3k..3k+2 on node
    lattice.nodes[k], the vertices numbered colour by colour (colour_order; SmoothingError
    else), its slots stencil_neighbours(lattice.nodes, ...); lattice in the lengths S was
    built in. coarsest: coarsen while a level has more vertices (None: COARSEST, read when
    called). seconds: the set-up's wall time."""

    def __init__(self, S: Stencil, lattice: Lattice, coarsest: int | None = None):
        t0 = time.perf_counter()
        nodes, nx, ny, where = _checked_nodes(lattice, S.nbr.shape[0])
        coarsest = COARSEST if coarsest is None else int(coarsest)
        if _colour_bounds(nodes, nx) is None:
            raise SmoothingError("the lattice solver takes its vertices numbered colour by colour (colour_order)")
        if not _slots_match(S.nbr, nodes, nx, ny, where):
            raise SmoothingError("the stencil's slots are not the lattice's neighbours (stencil_neighbours)")
        self.levels = [_Level(S, nodes, nx, ny, lattice.spacing, where)]
        while self.levels[-1].nodes.size > coarsest:
            below = self._coarsen(self.levels[-1])
            if below is None:
                break
            self.levels.append(below)
        method = available_solvers()[0]
        self.coarse = Factor(self.levels[-1].S, "superlu" if method == "amg-cg" else method)
        self.seconds = time.perf_counter() - t0

    @staticmethod
    def _coarsen(level: _Level) -> "_Level | None":
        """The level below `level` (None when coarsening keeps every vertex), with
        level.transfer set (`coarsen`) and its operator by the Galerkin kernel from it."""
        transfer, coarse, column, nxc, nyc = coarsen(level.nodes, level.where, level.nx, level.ny, level.spacing)
        level.where = None
        if coarse.size >= level.nodes.size:
            return None
        level.transfer = transfer
        op = galerkin(level, transfer, stencil_neighbours(coarse, nxc, nyc, column))
        hx, hy = level.spacing
        return _Level(op, coarse, nxc, nyc, (2 * hx, 2 * hy), column)

    def _coarsest(self, b: np.ndarray) -> np.ndarray:
        """The coarsest level's direct solve of b (n, k), as (n, k) C-contiguous."""
        x = self.coarse.solve(b[:, 0] if b.shape[1] == 1 else b, refine=False)
        return np.ascontiguousarray(x, dtype=np.float64).reshape(b.shape)

    def cycle(self, b: np.ndarray, k: int = 0, out: np.ndarray | None = None) -> np.ndarray:
        """One symmetric V(1,1) cycle from zero on level k for right-hand sides b (3N, c)
        (in the levels' numbering: colour by colour), into out (C-contiguous, b's shape,
        not b; None: a new array) on a level above the coarsest; returns it."""
        if k == len(self.levels) - 1:
            return self._coarsest(b)
        level = self.levels[k]
        if out is None:
            x = np.zeros(b.shape)
        else:
            x = out
            x.fill(0.0)
        level.sweep(x, b, (0, 1, 2), from_zero=True)
        # the last colour swept has no residual left (its block equations were just solved
        # with its neighbours as they are): only colours 0 and 1 are computed
        r = level.op.residual(b, x, level.scratch("residual", b.shape), vertices=int(level.bounds[2]))
        below = self.levels[k + 1]
        coarse = level.transfer.restrict(r, below.scratch("restricted", (3 * below.nodes.size, b.shape[1])))
        level.transfer.prolong(self.cycle(coarse, k + 1), x, add=True)
        level.sweep(x, b, (2, 1, 0))
        return x

    def start(self, rhs: np.ndarray) -> np.ndarray:
        """The full-multigrid guess for rhs (3N, c): rhs restricted by Pᵀ to every level,
        the coarsest solved, then on each finer level P and one V-cycle on its residual
        (in the levels' numbering)."""
        bs = [rhs]
        for level in self.levels[:-1]:
            bs.append(level.transfer.restrict(bs[-1]))
        x = self._coarsest(bs[-1])
        for k in range(len(self.levels) - 2, -1, -1):
            level = self.levels[k]
            x = level.transfer.prolong(x)
            x += self.cycle(level.op.residual(bs[k], x), k)
        return x

    def pcg(self, rhs: np.ndarray, step_tol: float, x0: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """(x, iterations): CG on S x = rhs preconditioned by `cycle`, from x0 (None: `start`),
        stopped when a step moves no value unknown (x[0::3]) by more than step_tol;
        SmoothingError after MAX_ITERATIONS steps. rhs (3N,), or (3N, k): k systems solved
        side by side, each column's CG its own (the column's bits as if solved alone), the
        kernels' passes over S shared; iterations then the most any column took."""
        S = self.levels[0].op
        rhs = np.asarray(rhs, dtype=np.float64)
        if rhs.shape[:1] != (S.shape[0],) or rhs.ndim not in (1, 2):
            raise SmoothingError(f"the right-hand side must have shape ({S.shape[0]},) or ({S.shape[0]}, k), "
                                 f"got {rhs.shape}")
        columns = np.ascontiguousarray(rhs.reshape(S.shape[0], -1))
        x0 = None if x0 is None else np.array(x0, dtype=np.float64).reshape(columns.shape)
        x, iterations = self._pcg(columns, step_tol, x0)
        return x.reshape(rhs.shape), iterations

    def _pcg(self, rhs: np.ndarray, step_tol: float, x0: np.ndarray | None) -> tuple[np.ndarray, int]:
        """pcg on rhs (3N, k) C-contiguous: the columns still moving (`live`) iterate
        together, a column leaves the block when its CG stops. Each (3N, k) array is held
        once: p starts as the first z, S p and the next z share one buffer (S p is spent
        once r has it, z once p has it), and the answer is x itself when the columns stop
        together (the edf's 4 probes: 98 MB an array at 1M vertices)."""
        A = self.levels[0].op
        n, columns = rhs.shape
        x = self.start(rhs) if x0 is None else x0
        out = None                                    # the columns stopped while others go on
        live = np.arange(columns)
        r = A.residual(rhs, x)
        p = self.cycle(r)
        rz = _dots(r, p)
        Ap = np.empty_like(p)                         # S p, then the next z
        for k in range(1, MAX_ITERATIONS + 1):
            done = rz == 0.0                          # r = 0: x solves it
            if done.all():
                return _stopped(out, live, x, columns), k - 1
            A.product(p, Ap)
            pAp = _dots(p, Ap)
            if not (pAp[~done] > 0.0).all() or not np.isfinite(pAp).all():
                raise SmoothingError("the smoothing system is not positive definite on the lattice")
            alpha = np.where(done, 0.0, rz / np.where(done, 1.0, pAp))     # a column with r = 0 stays
            _blockwise(lambda part: (np.add(x[part], alpha * p[part], out=x[part]),
                                     np.subtract(r[part], alpha * Ap[part], out=r[part])), n)
            done |= np.abs(alpha) * np.abs(p[0::3]).max(axis=0) <= step_tol
            if done.all():
                return _stopped(out, live, x, columns), k
            if done.any():
                out = _stopped(out, live[done], x[:, done], columns)
                live, x, r, p, rz = live[~done], *(np.ascontiguousarray(v[:, ~done]) for v in (x, r, p)), rz[~done]
                Ap = np.empty_like(p)
            z = self.cycle(r, out=Ap)
            rz_next = _dots(r, z)
            beta = rz_next / rz
            _blockwise(lambda part: np.add(z[part], beta * p[part], out=p[part]), n)
            rz = rz_next
        raise SmoothingError(f"the lattice solver did not converge in {MAX_ITERATIONS} iterations "
                             f"(steps still above {step_tol:g})")


def _stopped(out: np.ndarray | None, live: np.ndarray, x: np.ndarray, columns: int) -> np.ndarray:
    """The answer (3N, columns) with the stopped columns x (3N, c) put at their places live
    (c,) in out (None: none stopped before; made here). When x is every column in order,
    x itself (no copy)."""
    if out is None and live.size == columns:       # no column left before: live is range(columns)
        return x
    if out is None:
        out = np.empty((x.shape[0], columns))
    out[:, live] = x
    return out


class LatticeFactor:
    """A LatticeSolver in smoothing_system.Factor's place where only its `solve` is used
    (hat_trace's probes): the columns solved side by side by `pcg` to step_tol, each its
    own CG (refine is ignored)."""

    def __init__(self, solver: LatticeSolver, step_tol: float):
        self.solver, self.step_tol = solver, step_tol

    def solve(self, b: np.ndarray, refine: bool = False) -> np.ndarray:
        return self.solver.pcg(b, self.step_tol)[0]


def lattice_solve(S: Stencil, rhs: np.ndarray, lattice: Lattice, step_tol: float, x0: np.ndarray | None = None,
                  coarsest: int | None = None) -> tuple[np.ndarray, int]:
    """(x, iterations): S x = rhs by CG preconditioned by the multigrid V(1,1) cycle of S on
    `lattice` (module doc; LatticeSolver), from the full-multigrid guess (x0 None) or x0,
    stopped when a step moves no value unknown (every third) by more than step_tol, in
    S's height units. S: the fine level's Stencil, vertex k's unknowns 3k..3k+2 on node
    lattice.nodes[k], numbered colour by colour; the lattice in the lengths S was built in.
    SmoothingError when S is not the lattice's, or after MAX_ITERATIONS."""
    return LatticeSolver(S, lattice, coarsest).pcg(rhs, step_tol, x0)


__all__ = ["Lattice", "LatticeSolver", "LatticeFactor", "lattice_solve",
           "coarsen", "grid_vertices", "child_order", "Transfer", "hermite_weights", "galerkin", "stencil_neighbours",
           "Stencil", "OFFSETS", "HALF",
           "colour_order",
           "COARSEST", "MAX_ITERATIONS"]
