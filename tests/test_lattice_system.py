"""The lattice system's stencil assembly (stages/lattice_system.py, its kernel
stages/_lattice_system.pyx) against a brute-force sum written here: every triangle's 9 × 9
energy block and every data point's 9 × 9 outer product added into a dense S at their
unknowns, one by one, on small lattices with holes, odd and even sizes and corners in
any order; the same bytes at one and two threads; and the bits of the CSR system the
search for s builds on the same vertices in the stored half (the other half: to
rounding)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from c1mesh.core.threads import limit
from c1mesh.engine.schemes import DEFAULT_SCHEME, get_scheme
from c1mesh.stages import lattice_system
from c1mesh.stages.lattice_solver import HALF, Lattice, colour_order, stencil_neighbours
from c1mesh.stages.smoothing import _directions, _Problem, lattice_locate, lattice_shapes
from c1mesh.stages.smoothing_energy import SmoothingError

SCHEME = get_scheme(DEFAULT_SCHEME)


def lattice_problem(nx, ny, seed=0, holes=True, vertex_data=False, gradients=False, other_diagonal=False):
    """(_Problem, Lattice) on an nx × ny lattice in normalised units: cells missing at
    random and in a block (holes, ragged borders), each cell split by the (i, j)-(i+1, j+1)
    diagonal (or the other one), each triangle's corners rotated at random, the vertices
    numbered colour by colour (colour_order) as the solver takes them; 4 data points a
    cell at random positions, a tenth of them weight 0 (or the data at the vertices), and
    gradient data at half the vertices when asked."""
    rng = np.random.default_rng(seed)
    cells = np.ones((ny - 1, nx - 1), bool)
    if holes:
        cells[rng.random(cells.shape) < 0.12] = False
        cells[1:3, 2:5] = False
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = (idx[:-1, :-1][cells], idx[:-1, 1:][cells], idx[1:, :-1][cells], idx[1:, 1:][cells])
    halves = ([np.stack([a, b, c], 1), np.stack([b, d, c], 1)] if other_diagonal
              else [np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    node_triangles = np.concatenate(halves)
    turn = rng.integers(0, 3, node_triangles.shape[0])
    node_triangles = np.stack([np.roll(row, k) for row, k in zip(node_triangles, turn)])
    nodes = np.unique(node_triangles)
    lattice = Lattice((ny, nx), (0.9, 1.2), (-4.0, 3.0), nodes)
    nodes = nodes[colour_order(lattice)]
    lattice = Lattice((ny, nx), (0.9, 1.2), (-4.0, 3.0), nodes)
    rank = np.full(nx * ny, -1)
    rank[nodes] = np.arange(nodes.size)
    triangles = rank[node_triangles]
    points = lattice.positions()
    n = points.shape[0]
    shapes = None if other_diagonal else lattice_shapes(lattice, triangles)
    dirs = _directions(points, triangles, None)
    if vertex_data:
        xy, tri, lam = points, None, None
    else:
        cj, ci = np.nonzero(cells)
        pick = rng.integers(0, ci.size, 4 * ci.size)
        xy = np.stack([-4.0 + (ci[pick] + rng.random(pick.size)) * 0.9,
                       3.0 + (cj[pick] + rng.random(pick.size)) * 1.2], 1)
        tri, lam = ((None, None) if other_diagonal
                    else lattice_locate(lattice, points, triangles, xy))
    m = xy.shape[0]
    w = rng.uniform(0.5, 2.0, m) * (rng.random(m) > 0.1)
    z = rng.normal(size=m)
    grad = None
    if gradients:
        grad = rng.normal(size=(n, 2))
        grad[rng.random(n) < 0.5] = np.nan
    problem = _Problem(points, triangles, dirs, SCHEME, z, w, xy, tri, lam, grad, shapes)
    return problem, lattice


def built(problem, lattice):
    """The problem's LatticeSystem (the package's construction, as smooth_fit makes it)."""
    ny, nx = lattice.shape
    return problem.lattice_system(stencil_neighbours(lattice.nodes, nx, ny))


def brute_force(system, s, w, mu):
    """S (3N, 3N) dense: s × each triangle's energy block (system.elements[shape]) added
    at its unknowns, plus each data point's w a aᵀ (a its row of A) at its triangle's,
    plus the vertex data's w on f and mu on the gradient unknowns of vertices with
    gradient data: one term at a time, in a Python loop."""
    n = system.nbr.shape[0]
    S = np.zeros((3 * n, 3 * n))
    T = system.triangles

    def unknowns(t):
        v = T[t]
        return [3 * v[0], 3 * v[1], 3 * v[2], 3 * v[0] + 1, 3 * v[0] + 2, 3 * v[1] + 1, 3 * v[1] + 2,
                3 * v[2] + 1, 3 * v[2] + 2]

    for t in range(T.shape[0]):
        u = unknowns(t)
        element = system.elements[system.shape_of[t]]
        for j in range(9):
            for k in range(9):
                S[u[j], u[k]] += s * element[j, k]
    if system.data is None:
        for v in range(n):
            S[3 * v, 3 * v] += w[v]
    else:
        for i in range(w.size):
            u, a = unknowns(system.data.tri[i]), system.data.values[i]
            for j in range(9):
                for k in range(9):
                    S[u[j], u[k]] += w[i] * a[j] * a[k]
    if system.grad_mask is not None:
        for v in range(n):
            S[3 * v + 1, 3 * v + 1] += mu * system.grad_mask[v]
            S[3 * v + 2, 3 * v + 2] += mu * system.grad_mask[v]
    return S


@pytest.mark.parametrize("nx, ny, seed", [(9, 7, 0), (10, 8, 1), (11, 12, 2), (12, 11, 3)])
@pytest.mark.parametrize("kind", ["points", "vertices", "gradients"])
def test_the_stencil_is_the_brute_force_sum(nx, ny, seed, kind):
    problem, lattice = lattice_problem(nx, ny, seed, vertex_data=kind == "vertices", gradients=kind == "gradients")
    system = built(problem, lattice)
    s, mu = 0.37, 0.8
    S, rhs = system.stencil(s, problem.w, mu)
    want = brute_force(system, s, problem.w, mu)
    got = S.csr().toarray()
    assert np.abs(got - want).max() <= 1e-13 * np.abs(want).max()
    np.testing.assert_array_equal(S.blocks[S.nbr[:, list(HALF)].T < 0], 0.0)   # absent neighbours: zero blocks
    assert S.blocks.shape == (4, S.nbr.shape[0], 3, 3)                          # the halves only
    A = np.zeros((problem.w.size, 3 * lattice.nodes.size))
    if system.data is None:
        A[np.arange(problem.w.size), 3 * np.arange(problem.w.size)] = 1.0
    else:
        for i in range(problem.w.size):
            t = system.triangles[system.data.tri[i]]
            cols = [3 * t[0], 3 * t[1], 3 * t[2], 3 * t[0] + 1, 3 * t[0] + 2, 3 * t[1] + 1, 3 * t[1] + 2,
                    3 * t[2] + 1, 3 * t[2] + 2]
            A[i, cols] += system.data.values[i]
    want_rhs = A.T @ (problem.w * problem.z)
    if problem.grad is not None:
        has = np.isfinite(problem.grad).all(axis=1)
        want_rhs.reshape(-1, 3)[has, 1:] += mu * problem.grad[has]
    assert np.abs(rhs - want_rhs).max() <= 1e-13 * np.abs(want_rhs).max()


@pytest.mark.parametrize("kind", ["points", "vertices", "gradients"])
def test_the_stencil_has_the_bits_of_the_searchs_csr_system_in_its_half(kind):
    """The stencil's stored half (each vertex's rows against itself and its forward
    neighbours) holds, entry by entry, the bits of System.matrix's CSR on the same
    vertices (the sums in the same order). The other half cannot: System.matrix sums a
    backward block at its own vertex (its triangles in that vertex's order, products
    (w a_v) a_u against (w a_u) a_v), so it is not bitwise the transpose the stencil
    reads there. So S off its diagonal blocks is exactly symmetric (the self blocks are
    System.matrix's), and S is System.matrix's to rounding; System.matrix is not exactly
    symmetric (else the half would have changed no bit)."""
    problem, lattice = lattice_problem(14, 13, 5, vertex_data=kind == "vertices", gradients=kind == "gradients")
    S, rhs = built(problem, lattice).stencil(2.5, problem.w, 0.3)
    want, want_rhs = problem.system().matrix(2.5, problem.w, 0.3)
    got, want = S.csr().toarray(), want.toarray()
    n = S.nbr.shape[0]
    stored = np.zeros((n, n), bool)                          # (v, u): u at slot 0, 1, 3 or 5 of v
    for slot in HALF:
        v = np.nonzero(S.nbr[:, slot] >= 0)[0]
        stored[v, S.nbr[v, slot]] = True
    stored = np.kron(stored, np.ones((3, 3), bool))
    assert np.array_equal(got[stored], want[stored])
    off = got * ~np.kron(np.eye(n, dtype=bool), np.ones((3, 3), bool))   # the self blocks as assembled
    assert np.array_equal(off, off.T)
    assert np.abs(got - want).max() <= 1e-14 * np.abs(want).max()
    assert not np.array_equal(want, want.T)
    assert rhs.tobytes() == want_rhs.tobytes()


def test_the_same_bytes_at_one_and_two_threads(monkeypatch):
    monkeypatch.setattr(lattice_system, "ASSEMBLY_BLOCK", 7)          # many blocks of vertices
    monkeypatch.setattr(lattice_system, "DATA_BLOCK", 5)
    problem, lattice = lattice_problem(23, 21, 6, gradients=True)
    runs = []
    for threads in (1, 2, 1):
        with limit(threads):
            S, rhs = built(problem, lattice).stencil(0.05, problem.w, 1.0)
        runs.append(S.blocks.tobytes() + rhs.tobytes())
    assert runs[1] == runs[0] and runs[2] == runs[0]
    with limit(2):                    # the data term summed ahead, in the background, while the caller waits
        system = built(problem, lattice)
        with system.data_term_ahead(problem.w, 1.0) as data:
            time.sleep(0.05)
            S, rhs = system.with_strength(0.05, data())
    assert S.blocks.tobytes() + rhs.tobytes() == runs[0]


def test_cells_split_by_the_other_diagonal_are_refused():
    problem, lattice = lattice_problem(9, 8, 7, vertex_data=True, other_diagonal=True)
    with pytest.raises(SmoothingError, match="not on the lattice's stencil"):
        built(problem, lattice).stencil(1.0, problem.w, 0.0)
