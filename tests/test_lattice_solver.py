"""The lattice solver (stages/lattice_solver.py, its kernel stages/_lattice_solver.pyx) against
independent truth: CHOLMOD's solution of the same system, quadratics the Hermite
prolongation must reproduce (computed here from their formulas), the same bytes at one
and two threads, and smooth_fit with a lattice against smooth_fit without one."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from c1mesh.core.threads import limit
from c1mesh.engine import rsd
from c1mesh.engine.schemes import DEFAULT_SCHEME, get_scheme
from c1mesh.engine.topology import edge_table
from c1mesh.stages import lattice_solver, smoothing
from c1mesh.stages.lattice_solver import (HALF, OFFSETS, Lattice, LatticeSolver, colour_order, coarsen, grid_vertices,
                                          hermite_weights, lattice_solve, stencil_neighbours)
from c1mesh.stages.lattice_system import LatticeSystem
from c1mesh.stages.smoothing import SmoothingControl, SmoothingData, smooth_fit
from c1mesh.stages.smoothing_energy import SmoothingError, energy_blocks_of, triangle_directions
from c1mesh.stages.smoothing_system import assemble_energy, data_rows

NOISE = 0.02
NX, NY, HX, HY = 60, 50, 1.0, 0.7


def full_blocks(op) -> np.ndarray:
    """(N, 7, 3, 3): a Stencil's blocks at all 7 slots, written out here by numpy from its
    halves: slots 0, 1, 3, 5 as stored, each backward slot 2, 4, 6 (the vertex u there)
    u's block at the slot before it, transposed (zeros where absent)."""
    n = op.nbr.shape[0]
    out = np.zeros((n, 7, 3, 3))
    out[:, 0] = op.blocks[0]
    for h, slot in enumerate((1, 3, 5), start=1):
        out[:, slot] = op.blocks[h]
        v = np.nonzero(op.nbr[:, slot + 1] >= 0)[0]
        out[v, slot + 1] = op.blocks[h, op.nbr[v, slot + 1]].transpose(0, 2, 1)
    return out


def full_csr(op):
    """A Stencil's S (3N, 3N) as CSR built here from full_blocks by scipy (BSR of its
    present slots), independent of the kernel stencil_csr."""
    full, present = full_blocks(op), op.nbr >= 0
    indptr = np.concatenate([[0], np.cumsum(present.sum(axis=1))])
    return sp.bsr_matrix((full[present], op.nbr[present], indptr), shape=op.shape).tocsr()


def lattice_mesh(nx=NX, ny=NY, hx=HX, hy=HY, hole=True, seed=0, other_diagonal=False):
    """A lattice mesh with missing cells (a 15 × 15 hole and a cut corner, so some nodes are
    absent) and its vertices in random order: points (N, 2), triangles (T, 3), the
    Lattice, and a function locating points in the present cells (xy, triangle, barycentrics)."""
    rng = np.random.default_rng(seed)
    idx = np.arange(nx * ny).reshape(ny, nx)
    cells = np.ones((ny - 1, nx - 1), bool)
    if hole:
        cells[15:30, 20:35] = False
        cells[:5, :7] = False
    a, b, c, d = (idx[:-1, :-1][cells], idx[:-1, 1:][cells], idx[1:, :-1][cells], idx[1:, 1:][cells])
    if other_diagonal:
        T = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    else:
        T = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    nodes = rng.permutation(np.unique(T))
    rank = np.full(nx * ny, -1)
    rank[nodes] = np.arange(nodes.size)
    T = rank[T]
    lattice = Lattice((ny, nx), (hx, hy), (10.0, -5.0), nodes.astype(np.int64))
    points = lattice.positions()
    present = np.cumsum(cells.ravel()) - 1

    def data(m):
        ci, cj = rng.integers(0, nx - 1, 4 * m), rng.integers(0, ny - 1, 4 * m)
        ok = cells[cj, ci]
        ci, cj = ci[ok][:m], cj[ok][:m]
        fx, fy = rng.uniform(0, 1, ci.size), rng.uniform(0, 1, ci.size)
        cell = present[cj * (nx - 1) + ci]
        upper = fy > fx
        tri = np.where(upper, cell + cells.sum(), cell)
        lam = np.where(upper[:, None], np.stack([1 - fy, fx, fy - fx], 1), np.stack([1 - fx, fx - fy, fy], 1))
        xy = np.stack([10.0 + (ci + fx) * hx, -5.0 + (cj + fy) * hy], 1)
        z = np.sin(xy[:, 0] / 9) * np.cos(xy[:, 1] / 7) + rng.normal(0, NOISE, xy.shape[0])
        return xy, z, tri, lam
    return points, T, lattice, data


def brute_coarsening(nodes, nx, ny, spacing):
    """(P CSR with sorted columns, coarse nodes, nxc, nyc) by Python loops over the grid,
    from the module doc's rule: coarse node (I, J) on fine node (2I, 2J) kept when that
    node is a vertex or at least two fine nodes at OFFSETS from it are; the kept ones
    numbered by (colour (I + J) mod 3, node); P's entry (3f + p, 3c + q) the Hermite
    weight W[offset][p, q] (nonzero ones) for fine vertex f at offset from coarse vertex c."""
    vertex = {int(node): k for k, node in enumerate(nodes)}
    nxc, nyc = nx // 2 + 1, ny // 2 + 1

    def fine(I, J, di, dj):
        i, j = 2 * I + di, 2 * J + dj
        return vertex.get(j * nx + i, -1) if 0 <= i < nx and 0 <= j < ny else -1
    kept = [J * nxc + I for J in range(nyc) for I in range(nxc)
            if fine(I, J, 0, 0) >= 0 or sum(fine(I, J, di, dj) >= 0 for di, dj in OFFSETS[1:]) >= 2]
    coarse = sorted(kept, key=lambda node: ((node % nxc + node // nxc) % 3, node))
    W = hermite_weights(2 * spacing[0], 2 * spacing[1])
    rows, cols, vals = [], [], []
    for c, node in enumerate(coarse):
        J, I = divmod(node, nxc)
        for off in OFFSETS:
            f = fine(I, J, *off)
            for p in range(3):
                for q in range(3):
                    if f >= 0 and W[off][p, q] != 0.0:
                        rows.append(3 * f + p)
                        cols.append(3 * c + q)
                        vals.append(W[off][p, q])
    P = sp.csr_matrix((vals, (rows, cols)), shape=(3 * len(nodes), 3 * len(coarse)))
    P.sort_indices()
    return P, np.array(coarse, dtype=np.int64), nxc, nyc


def lattice_system(s, **kw):
    """(S, rhs, lattice): the smoothing system of 3 points per vertex off the vertices in
    the solver's stencil form (the package's LatticeSystem, one energy block per triangle,
    unit normals, lengths as given), its vertices renumbered colour by colour as the
    solver takes them."""
    points, T, lattice, data = lattice_mesh(**kw)
    xy, z, tri, lam = data(3 * points.shape[0])
    order = colour_order(lattice)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    points, T, lattice = points[order], rank[T], Lattice(lattice.shape, lattice.spacing, lattice.origin,
                                                          lattice.nodes[order])
    table = edge_table(T, points.shape[0])
    dirs = triangle_directions(points, T, table.tri_edge, None, table.edges)
    scheme = get_scheme(DEFAULT_SCHEME)
    ny, nx = lattice.shape
    system = LatticeSystem(T, np.arange(T.shape[0]), energy_blocks_of(points, T, dirs, scheme),
                           stencil_neighbours(lattice.nodes, nx, ny), data_rows(points, T, dirs, scheme, tri, lam), z)
    S, rhs = system.stencil(s, np.ones(z.size), 0.0)
    return S, rhs, lattice


@pytest.mark.parametrize("s", [0.003, 1.0, 30.0])
def test_lattice_solve_reaches_cholmods_heights(s):
    cholmod = pytest.importorskip("sksparse.cholmod")
    S, rhs, lattice = lattice_system(s)
    csr = S.csr()
    factor = cholmod.cholesky(csr.tocsc())
    truth = factor(rhs)
    truth = truth + factor(rhs - csr @ truth)
    x, iterations = lattice_solve(S, rhs, lattice, 1e-3 * NOISE, coarsest=150)
    assert 1 <= iterations <= 30
    assert np.abs(x[0::3] - truth[0::3]).max() < 5e-3 * NOISE
    assert np.abs(x - truth).max() < 2e-2 * NOISE           # gradients too (per unit length)


def test_the_hierarchy_drops_absent_nodes_level_by_level():
    S, rhs, lattice = lattice_system(1.0)
    solver = LatticeSolver(S, lattice, coarsest=150)
    sizes = [level.nodes.size for level in solver.levels]
    assert len(sizes) >= 3 and sizes[-1] <= 150 < sizes[-2]
    assert all(n < NX * NY for n in sizes)                 # the hole's inner nodes are on no level
    for level in solver.levels:
        assert level.S.shape == (3 * level.nodes.size,) * 2


def test_the_same_bytes_at_one_and_two_threads(monkeypatch):
    monkeypatch.setattr(lattice_solver, "SWEEP_BLOCK", 97)           # many blocks per colour,
    monkeypatch.setattr(lattice_solver, "ROW_BLOCK", 301)            # per product of P, Pᵀ and dot,
    monkeypatch.setattr(lattice_solver, "GALERKIN_BLOCK", 23)        # and per coarse operator
    S, rhs, lattice = lattice_system(0.1)
    runs = []
    probes = np.random.default_rng(1).choice([-1.0, 1.0], (rhs.size, 5))
    for threads in (1, 2, 1):
        with limit(threads):
            solver = LatticeSolver(S, lattice, coarsest=150)
            runs.append((solver.pcg(rhs, 1e-6), solver.pcg(probes, 1e-3), solver.levels[1].op.blocks))
    for run in runs[1:]:
        assert run[0][1] == runs[0][0][1] and run[1][1] == runs[0][1][1]
        assert run[0][0].tobytes() == runs[0][0][0].tobytes()
        assert run[1][0].tobytes() == runs[0][1][0].tobytes()
        assert run[2].tobytes() == runs[0][2].tobytes()


def _quadratic(x, y):
    return (0.3 + 0.7 * x - 1.1 * y + 0.45 * x * x - 0.8 * x * y + 0.35 * y * y,
            0.7 + 0.9 * x - 0.8 * y, -1.1 - 0.8 * x + 0.7 * y)


@pytest.mark.parametrize("hole", [False, True])
def test_the_hermite_prolongation_reproduces_quadratics(hole):
    """Coarse data (value, gradient) of a quadratic → P (Transfer.prolong) → the quadratic's data at every fine
    node whose coarse ends (a node on a coarse node: that one; an edge midpoint: the edge's
    two ends) are all kept; with no node absent, at every fine node."""
    nx, ny, hx, hy = 21, 17, 0.8, 1.3
    _, _, lattice, _ = lattice_mesh(nx, ny, hx, hy, hole=hole)
    nodes = lattice.nodes
    transfer, coarse, _, nxc, nyc = coarsen(nodes, grid_vertices(nodes, nx, ny), nx, ny, (hx, hy))
    J, I = np.divmod(coarse, nxc)
    f, fx, fy = _quadratic(I * 2 * hx, J * 2 * hy)
    u = np.stack([f, fx, fy], 1).reshape(-1, 1)
    fine = transfer.prolong(u).reshape(-1, 3)
    j, i = np.divmod(nodes, nx)
    want = np.stack(_quadratic(i * hx, j * hy), 1)
    kept = np.zeros(nxc * nyc, bool)
    kept[coarse] = True
    ends = [(i // 2, j // 2), ((i + 1) // 2, (j + 1) // 2)]             # the same node twice on a coarse node
    exact = kept[ends[0][1] * nxc + ends[0][0]] & kept[ends[1][1] * nxc + ends[1][0]]
    assert exact.mean() > (0.9 if hole else 0.999)
    assert np.abs(fine[exact] - want[exact]).max() < 1e-12


def test_smooth_fit_with_the_lattice_is_smooth_fit_without(monkeypatch):
    monkeypatch.setattr(lattice_solver, "COARSEST", 150)
    monkeypatch.setattr(smoothing, "EDF_PROBES", smoothing.LATTICE_EDF_PROBES)    # the same probes both ways
    points, T, lattice, data = lattice_mesh()
    xy, z, _, _ = data(3 * points.shape[0])
    h = float(np.sqrt(HX * HY / 3))
    fits = {}
    for s in (0.01, 10.0):
        given = SmoothingData(z, spacing=h, xy=xy)
        direct = smooth_fit(points, T, given, SmoothingControl(strength=s))
        fit = smooth_fit(points, T, given, SmoothingControl(strength=s), lattice=lattice)
        fits[s] = fit
        assert fit.solver == "lattice-pcg" and "lattice_setup" in fit.seconds
        assert np.abs(fit.values - direct.values).max() < 1e-4 * NOISE
        assert np.abs(fit.gradients - direct.gradients).max() < 1e-4 * NOISE
        assert abs(fit.edf - direct.edf) < 1e-3 * direct.edf
        assert fit.residual_rms == pytest.approx(direct.residual_rms, rel=1e-6)


def test_a_mesh_that_is_not_the_lattice_is_refused():
    points, T, lattice, data = lattice_mesh(hole=False)
    xy, z, _, _ = data(points.shape[0])
    given = SmoothingData(z, spacing=0.5, xy=xy)
    moved = Lattice(lattice.shape, lattice.spacing, (10.5, -5.0), lattice.nodes)
    with pytest.raises(SmoothingError, match="not the lattice's nodes"):
        smooth_fit(points, T, given, SmoothingControl(strength=1.0), lattice=moved)
    with pytest.raises(SmoothingError, match="stencil"):
        lattice_system(1.0, hole=False, other_diagonal=True)
    S, rhs, lattice = lattice_system(1.0, hole=False)
    with pytest.raises(SmoothingError, match="colour by colour"):
        lattice_solve(S, rhs, Lattice(lattice.shape, lattice.spacing, lattice.origin, lattice.nodes[::-1]), 1e-6)
    with pytest.raises(SmoothingError, match="distinct"):
        lattice_solve(S, rhs, Lattice(lattice.shape, lattice.spacing, lattice.origin,
                                      np.zeros_like(lattice.nodes)), 1e-6)
    with pytest.raises(SmoothingError, match="spacing"):
        Lattice((NY, NX), (1.0, 0.0), (0.0, 0.0), lattice.nodes)


def test_a_lattice_mesh_is_built_from_its_few_triangle_shapes():
    """On a lattice mesh (holes, vertices in random order, each triangle's corners rotated
    at random) the system built from each triangle shape's energy block and data map equals
    the one built triangle by triangle, and lattice_locate finds every data point's
    triangle and barycentrics (as the lattice_mesh fixture placed it) by arithmetic."""
    from c1mesh.stages.smoothing import _directions, lattice_locate, lattice_shapes
    from c1mesh.stages.smoothing_system import TriangleShapes

    points, T, lattice, data = lattice_mesh(seed=3)
    rng = np.random.default_rng(4)
    turn = rng.integers(0, 3, T.shape[0])
    T = np.stack([np.roll(row, k) for row, k in zip(T, turn)])       # the same triangles, corners rotated
    xy, z, tri, lam = data(3000)
    lam = np.stack([np.roll(row, k) for row, k in zip(lam, turn[tri])])
    shapes = lattice_shapes(lattice, T)
    assert isinstance(shapes, TriangleShapes) and shapes.reps.size == 6     # 2 triangles × 3 rotations
    j, i = np.divmod(lattice.nodes[T], NX)
    offsets = np.concatenate([i[:, 1:] - i[:, :1], j[:, 1:] - j[:, :1]], axis=1)
    _, reps, key = np.unique(offsets, axis=0, return_index=True, return_inverse=True)
    assert np.array_equal(shapes.reps, reps) and np.array_equal(shapes.key, key.ravel())
    far = np.array([[np.argmin(lattice.nodes), np.argmax(lattice.nodes), np.argmax(lattice.nodes) - 1]])
    with pytest.raises(SmoothingError, match="one cell's nodes"):                # corners across the grid
        lattice_shapes(lattice, far)
    found, barycentric = lattice_locate(lattice, points, T, xy)
    assert np.array_equal(found, tri)
    assert np.abs(barycentric - lam).max() < 1e-12
    inside = found >= 0                 # the kernel's bits: rsd.barycentric_gradients' formula in numpy
    corners = points[T[found[inside]]]
    G, _ = rsd.barycentric_gradients(corners)
    rest = np.einsum("mkd,md->mk", G[:, 1:], xy[inside] - corners[:, 0])
    assert np.column_stack([1.0 - rest.sum(axis=1), rest]).tobytes() == barycentric[inside].tobytes()
    assert np.isnan(barycentric[~inside]).all()
    scheme = get_scheme(DEFAULT_SCHEME)
    dirs = _directions(points, T, None)
    one_by_one = assemble_energy(points, T, dirs, scheme)
    shared = assemble_energy(points, T, dirs, scheme, shapes)
    assert np.array_equal(one_by_one.indices, shared.indices)
    assert np.abs(shared.data - one_by_one.data).max() < 1e-9 * np.abs(one_by_one.data).max()
    rows = data_rows(points, T, dirs, scheme, tri, lam)
    shared_rows = data_rows(points, T, dirs, scheme, tri, lam, shapes)
    assert np.abs(shared_rows.values - rows.values).max() < 1e-11
    outside = lattice_locate(lattice, points, T, np.array([[10.0 + 25 * HX, -5.0 + 20 * HY], [0.0, 0.0]]))[0]
    assert list(outside) == [-1, -1]                                  # in the hole; beyond the lattice


@pytest.mark.parametrize("nx, ny", [(41, 33), (40, 34), (41, 34)])
def test_the_galerkin_kernel_is_scipys_triple_product(nx, ny):
    """Every coarse operator equals Pᵀ S P as scipy multiplies it here (P built explicitly,
    brute_coarsening), entry by entry to rounding, on lattices with holes and odd and even
    sizes (coarse nodes standing in for missing ones beyond ragged borders)."""
    S, _, lattice = lattice_system(0.3, nx=nx, ny=ny)
    solver = LatticeSolver(S, lattice, coarsest=40)
    assert len(solver.levels) >= 3
    for fine, coarse in zip(solver.levels, solver.levels[1:]):
        P, nodes, _, _ = brute_coarsening(fine.nodes, fine.nx, fine.ny, fine.spacing)
        assert np.array_equal(coarse.nodes, nodes)
        want = (P.T @ fine.S @ P).tocsr()
        got = coarse.S
        assert got.shape == want.shape
        scale = np.abs(want.data).max()
        assert abs(got - want).max() <= 1e-12 * scale
        assert (abs(want) > 1e-9 * scale).nnz > 0.5 * got.nnz          # the pattern is no padding


def test_the_product_kernels_are_scipys_products_column_by_column():
    """The half stencil's product and residual against scipy's product with the full
    symmetric matrix built here from the halves (full_csr: each backward block the
    neighbour's forward one transposed), with k = 1, 3 and 6 columns (LANES and what is
    left), each column's bits the same whatever k."""
    S, rhs, lattice = lattice_system(1.0)
    solver = LatticeSolver(S, lattice, coarsest=150)
    fine = solver.levels[0]
    S = full_csr(S)
    off = S - sp.block_diag([full_blocks(solver.levels[0].op)[v, 0] for v in range(S.shape[0] // 3)], "csr")
    assert abs(off - off.T).max() == 0.0 and (S.diagonal() > 0).all()      # mirrored off the diagonal blocks
    X = np.random.default_rng(5).normal(size=(S.shape[0], 6))
    for k in (1, 3, 6):
        x = np.ascontiguousarray(X[:, :k])
        want = S @ x
        got = fine.op @ x
        assert np.allclose(got, want, rtol=1e-13, atol=1e-13 * np.abs(want).max())
        assert got[:, 0].tobytes() == (fine.op @ np.ascontiguousarray(X[:, :1]))[:, 0].tobytes()
        B = np.ascontiguousarray(np.repeat(rhs[:, None], k, axis=1))
        assert np.allclose(fine.op.residual(B, x), B - want, rtol=1e-13, atol=1e-12 * np.abs(want).max())


def _slot_ordered_transpose(P, children: np.ndarray):
    """Pᵀ CSR with each coarse row block's entries by offset slot (the fine vertex at
    children[c, slot]), then fine unknown p: the order restrict and the Galerkin kernel
    sum Pᵀ's rows in (the fine vertices of a row are not ascending by slot)."""
    PT = P.T.tocsr()
    indptr, indices, data = [0], [], []
    for row in range(PT.shape[0]):
        entries = dict(zip(PT.indices[PT.indptr[row]:PT.indptr[row + 1]], PT.data[PT.indptr[row]:PT.indptr[row + 1]]))
        for f in children[row // 3]:
            for p in range(3):
                if f >= 0 and 3 * f + p in entries:
                    indices.append(3 * f + p)
                    data.append(entries.pop(3 * f + p))
        assert not entries                                  # every entry is a child's
        indptr.append(len(indices))
    return sp.csr_matrix((data, indices, indptr), shape=PT.shape)


def _csr_rows(M, x: np.ndarray) -> np.ndarray:
    """M x (m, k) by brute-force loops over M's stored entries, each row summed in the
    stored order from 0 (the order the transfer kernels must keep)."""
    out = np.zeros((M.shape[0], x.shape[1]))
    for row in range(M.shape[0]):
        for c in range(x.shape[1]):
            s = 0.0
            for e in range(M.indptr[row], M.indptr[row + 1]):
                s = s + M.data[e] * x[M.indices[e], c]
            out[row, c] = s
    return out


@pytest.mark.parametrize("nx, ny", [(41, 33), (40, 34), (41, 34)])
def test_the_transfer_kernels_are_the_csr_products_bit_for_bit(nx, ny):
    """Transfer's P x, P x added and Pᵀ x have the bits of a loop over the explicit P
    (brute_coarsening, columns sorted) and its transpose as CSR (each row in its stored
    order: Pᵀ's row by fine vertex, i.e. by offset slot for the Hermite stencil), on
    lattices with holes, odd and even sizes (every level down to a few dozen vertices),
    with 1, 3 and 6 columns, at one and two threads."""
    S, _, lattice = lattice_system(0.5, nx=nx, ny=ny)
    for level in LatticeSolver(S, lattice, coarsest=20).levels[:-1]:
        P = brute_coarsening(level.nodes, level.nx, level.ny, level.spacing)[0]
        PT = _slot_ordered_transpose(P, level.transfer.children)
        rng = np.random.default_rng(level.nodes.size)
        for k in (1, 3, 6):
            xc = rng.normal(size=(P.shape[1], k))
            xf = rng.normal(size=(P.shape[0], k))
            start = rng.normal(size=(P.shape[0], k))
            prolonged, restricted = _csr_rows(P, xc), _csr_rows(PT, xf)
            for threads in (1, 2):
                with limit(threads):
                    assert level.transfer.prolong(xc).tobytes() == prolonged.tobytes()
                    added = level.transfer.prolong(xc, start.copy(), add=True)
                    assert added.tobytes() == (start + prolonged).tobytes()
                    assert level.transfer.restrict(xf).tobytes() == restricted.tobytes()


def test_right_hand_sides_solved_together_are_each_solved_alone():
    """pcg on (3N, k): each column's CG is its own, so its bits are those of the column
    solved alone (and the columns stop at their own iterations)."""
    S, rhs, lattice = lattice_system(0.1)
    solver = LatticeSolver(S, lattice, coarsest=150)
    B = np.stack([rhs, 1e-3 * rhs[::-1], np.random.default_rng(2).choice([-1.0, 1.0], rhs.size)], axis=1)
    together, _ = solver.pcg(B, 1e-5)
    for c in range(B.shape[1]):
        alone, _ = solver.pcg(np.ascontiguousarray(B[:, c]), 1e-5)
        assert together[:, c].tobytes() == alone.tobytes()


def test_smooth_fit_on_the_lattice_gives_the_same_bytes_at_one_and_two_threads(monkeypatch):
    """Values, gradients and the edf (Hutchinson's vᵀF over 40k data: long enough for a
    BLAS dot to split across threads) are the same bytes at 1 and 2 threads."""
    monkeypatch.setattr(lattice_solver, "COARSEST", 150)
    monkeypatch.setattr(lattice_solver, "SWEEP_BLOCK", 97)
    points, T, lattice, data = lattice_mesh()
    xy, z, _, _ = data(40_000)
    given = SmoothingData(z, spacing=float(np.sqrt(HX * HY / 3)), xy=xy)
    fits = []
    for threads in (1, 2):
        with limit(threads):
            fits.append(smooth_fit(points, T, given, SmoothingControl(strength=1.0), lattice=lattice))
    assert fits[0].values.tobytes() == fits[1].values.tobytes()
    assert fits[0].gradients.tobytes() == fits[1].gradients.tobytes()
    assert np.float64(fits[0].edf).tobytes() == np.float64(fits[1].edf).tobytes()


@pytest.mark.parametrize("nx, ny", [(41, 33), (40, 34), (41, 34)])
def test_coarsen_is_the_rule_by_brute_force(nx, ny, monkeypatch):
    """coarsen's coarse nodes (numbered colour by colour), their grid_vertices (column),
    children and the parents with their slots are those of Python loops over the grid
    (brute_coarsening's P: a coarse vertex's children are its P columns' fine vertices,
    a fine vertex's parents its P row's coarse vertices, ascending), on every level of
    lattices with holes and odd and even sizes, at one and two threads."""
    monkeypatch.setattr(lattice_solver, "SWEEP_BLOCK", 37)
    S, _, lattice = lattice_system(0.5, nx=nx, ny=ny)
    for level in LatticeSolver(S, lattice, coarsest=20).levels[:-1]:
        P, coarse, nxc, nyc = brute_coarsening(level.nodes, level.nx, level.ny, level.spacing)
        for threads in (1, 2):
            with limit(threads):
                where = grid_vertices(level.nodes, level.nx, level.ny)
                transfer, got, column, gxc, gyc = coarsen(level.nodes, where, level.nx, level.ny, level.spacing)
            assert (gxc, gyc) == (nxc, nyc) and np.array_equal(got, coarse)
            want_column = np.full(nxc * nyc, -1)
            want_column[coarse] = np.arange(coarse.size)
            assert np.array_equal(column, want_column)
            j, i = np.divmod(level.nodes, level.nx)
            for c, node in enumerate(coarse):
                J, I = divmod(int(node), nxc)
                for slot, (di, dj) in enumerate(OFFSETS):
                    f = transfer.children[c, slot]
                    if f < 0:
                        assert not ((i == 2 * I + di) & (j == 2 * J + dj)).any()
                    else:
                        assert (i[f], j[f]) == (2 * I + di, 2 * J + dj)
            P = P.tocsr()
            for f in range(level.nodes.size):
                parents = sorted({int(col) // 3 for col in P.indices[P.indptr[3 * f]:P.indptr[3 * f + 3]]})
                got_parents = [int(c) for c in transfer.parents[f] if c >= 0]
                assert got_parents == parents and np.all(transfer.parents[f, len(parents):] == -1)
                for c, slot in zip(transfer.parents[f, :len(parents)], transfer.parent_slot[f]):
                    assert transfer.children[c, slot] == f


def test_stencil_neighbours_by_brute_force():
    """Each vertex's 7 stencil neighbours are the vertices at OFFSETS from its node (Python
    loops over a lattice with holes whose vertices are in random order), −1 where none."""
    _, _, lattice, _ = lattice_mesh(23, 19, seed=2)
    ny, nx = lattice.shape
    vertex = {int(node): k for k, node in enumerate(lattice.nodes)}
    got = stencil_neighbours(lattice.nodes, nx, ny)
    for k, node in enumerate(lattice.nodes):
        j, i = divmod(int(node), nx)
        want = [vertex.get((j + dj) * nx + i + di, -1) if 0 <= i + di < nx and 0 <= j + dj < ny else -1
                for di, dj in OFFSETS]
        assert list(got[k]) == want


def _galerkin_by_loops(S, P, PT, fine_nodes, nx, coarse_nodes, nxc, coarse_nbr):
    """Pᵀ S P's coarse blocks (m, 7, 3, 3) by Python loops over the CSR P (columns sorted)
    and PT (rows by slot: _slot_ordered_transpose), in the summation order the Galerkin
    kernel keeps: U_g = Σ_f R_f S_f,g over the children f in the order PT's rows first
    reach them, each child's stencil slots in order, R's unknowns in order (zeros
    skipped); then each coarse block Σ_g U_g P_g over the fine nodes g in grid order
    around the coarse node, P's rows in order."""
    m = coarse_nodes.size
    blocks = full_blocks(S)
    out = np.zeros((m, 7, 3, 3))
    for I in range(m):
        ci, cj = coarse_nodes[I] % nxc, coarse_nodes[I] // nxc
        children, R = [], {}
        for p in range(3):
            for e in range(PT.indptr[3 * I + p], PT.indptr[3 * I + p + 1]):
                f = PT.indices[e] // 3
                if f not in R:
                    children.append(f)
                    R[f] = np.zeros((3, 3))
                R[f][p, PT.indices[e] - 3 * f] = PT.data[e]
        U = {}
        for f in children:
            for fslot in range(7):
                g = S.nbr[f, fslot]
                if g < 0:
                    continue
                u = ((fine_nodes[g] // nx - 2 * cj + 2) * 5 + fine_nodes[g] % nx - 2 * ci + 2, g)
                Ug = U.setdefault(u, [[0.0] * 3 for _ in range(3)])
                for p in range(3):
                    for r in range(3):
                        if R[f][p, r] != 0.0:
                            for q in range(3):
                                Ug[p][q] = Ug[p][q] + R[f][p, r] * blocks[f, fslot, r, q]
        for (_, g), Ug in sorted(U.items()):
            for q in range(3):
                for e in range(P.indptr[3 * g + q], P.indptr[3 * g + q + 1]):
                    J, qq = divmod(int(P.indices[e]), 3)
                    slot = list(coarse_nbr[I]).index(J)
                    for p in range(3):
                        out[I, slot, p, qq] = out[I, slot, p, qq] + Ug[p][q] * P.data[e]
    return out


@pytest.mark.parametrize("nx, ny", [(25, 21), (26, 20)])
def test_the_galerkin_kernel_has_the_bits_of_the_csr_loops(nx, ny):
    """Every coarse operator's stored half (slots 0, 1, 3, 5) has the bits of
    _galerkin_by_loops over the explicit P (brute_coarsening) and the fine level's
    blocks written out whole (full_blocks), on lattices with holes, odd and even sizes;
    the slots not stored are, to rounding, the transposes the kernels read there."""
    S, _, lattice = lattice_system(0.3, nx=nx, ny=ny)
    solver = LatticeSolver(S, lattice, coarsest=20)
    assert len(solver.levels) >= 3
    for fine, coarse in zip(solver.levels, solver.levels[1:]):
        P, nodes, nxc, _ = brute_coarsening(fine.nodes, fine.nx, fine.ny, fine.spacing)
        PT = _slot_ordered_transpose(P, fine.transfer.children)
        want = _galerkin_by_loops(fine.op, P, PT, fine.nodes, fine.nx, nodes, nxc, coarse.op.nbr)
        assert coarse.op.blocks.tobytes() == np.ascontiguousarray(want[:, list(HALF)].transpose(1, 0, 2, 3)).tobytes()
        full = full_blocks(coarse.op)
        assert np.abs(full - want).max() <= 1e-13 * np.abs(want).max()


def test_a_stencil_whose_slots_are_not_the_lattices_is_refused():
    """LatticeSolver checks every slot of the fine stencil against the lattice (one slot
    moved, or a neighbour dropped, is refused) and the numbering colour by colour."""
    S, _, lattice = lattice_system(1.0, nx=23, ny=19)
    LatticeSolver(S, lattice, coarsest=40)
    for v, k, value in ((5, 3, -1), (S.nbr.shape[0] - 1, 0, 0)):
        nbr = S.nbr.copy()
        nbr[v, k] = value if nbr[v, k] != value else 1
        with pytest.raises(SmoothingError, match="slots"):
            LatticeSolver(lattice_solver.Stencil(nbr, S.blocks), lattice, coarsest=40)


def test_the_colour_bounds_are_numpys():
    """_colour_bounds (one pass) is searchsorted over the colours for nodes numbered colour
    by colour (some colours empty, none at all), and None when they are not so numbered."""
    rng = np.random.default_rng(0)
    for nx in (5, 7, 40):
        for n in (0, 1, 2, 3, 50):
            nodes = rng.choice(nx * nx, size=min(n, nx * nx), replace=False)
            colour = lattice_solver.colours(nodes, nx)
            nodes = nodes[np.lexsort((nodes, colour))]
            want = np.searchsorted(lattice_solver.colours(nodes, nx), np.arange(4))
            assert np.array_equal(lattice_solver._colour_bounds(nodes, nx), want)
            mixed = len(set(colour.tolist())) > 1
            assert (lattice_solver._colour_bounds(nodes[::-1].copy(), nx) is None) == mixed


def test_the_stencil_as_csr_is_its_blocks_by_loops():
    """Stencil.csr (kernel stencil_csr) stores, row 3v + p, every present slot's 3 entries
    (zeros too) with the columns ascending, a backward slot's as its neighbour's forward
    block transposed: the same arrays as Python loops over the slots sorted by vertex on
    full_blocks, on a lattice with holes and on its coarsest Galerkin level."""
    S, _, lattice = lattice_system(0.7, nx=23, ny=19)
    for op in (S, LatticeSolver(S, lattice, coarsest=40).levels[-1].op):
        blocks = full_blocks(op)
        indptr, indices, data = [0], [], []
        for v in range(op.nbr.shape[0]):
            slots = sorted((int(g), k) for k, g in enumerate(op.nbr[v]) if g >= 0)
            for p in range(3):
                for g, k in slots:
                    for q in range(3):
                        indices.append(3 * g + q)
                        data.append(blocks[v, k, p, q])
                indptr.append(len(indices))
        got = op.csr()
        assert got.shape == op.shape and got.has_sorted_indices
        assert np.array_equal(got.indptr, indptr) and np.array_equal(got.indices, indices)
        assert got.data.tobytes() == np.array(data).tobytes()
