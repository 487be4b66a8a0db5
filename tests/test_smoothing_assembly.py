"""The smoothing system's kernels (stages/_smoothing_energy.pyx, stages/_smoothing_system.pyx)
against references written here: a plain Python loop over the triangles for the assembled
matrix and the vertex adjacency, CHOLMOD on an adjacency built here for the vertex order,
and documented properties of the energy (planes have none; blocks symmetric, PSD)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from c1mesh.core.threads import limit
from c1mesh.engine.schemes import get_scheme
from c1mesh.engine.topology import edge_table
from c1mesh.stages import smoothing_energy, smoothing_system
from c1mesh.stages.smoothing_energy import energy_blocks_of, local_dofs, triangle_directions
from c1mesh.stages.smoothing_system import assemble_energy, vertex_order, vertex_pattern


def shuffled_mesh(m: int, seed: int = 0):
    """A jittered m × m grid, two triangles per cell, with its vertices and triangles in
    random order (so a vertex's triangles are far apart in the list) and random edge
    directions: points (N, 2), triangles (T, 3), per-triangle directions (T, 3, 2)."""
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    xy = np.stack([i.ravel(), j.ravel()], 1) + rng.uniform(-0.3, 0.3, (m * m, 2))
    v = (i[:-1, :-1] * m + j[:-1, :-1]).ravel()
    tri = np.concatenate([np.stack([v, v + m, v + m + 1], 1), np.stack([v, v + m + 1, v + 1], 1)])
    tri = tri[rng.permutation(tri.shape[0])]
    perm = rng.permutation(m * m)
    rank = np.empty_like(perm)
    rank[perm] = np.arange(m * m)
    pts, tri = xy[perm], rank[tri]
    table = edge_table(tri, pts.shape[0])
    dirs = triangle_directions(pts, tri, table.tri_edge, rng.normal(size=table.edges.shape),
                               table.edges)
    return pts, tri, dirs


# ------------------------------------------------------------------ energy blocks
def test_planes_have_no_energy():
    rng = np.random.default_rng(5)
    pts, tri, dirs = shuffled_mesh(9, seed=5)
    K = energy_blocks_of(pts, tri, dirs, get_scheme("sextic"))
    a, b, c = rng.normal(size=3)
    u = np.zeros(3 * pts.shape[0])
    u[0::3], u[1::3], u[2::3] = a + b * pts[:, 0] + c * pts[:, 1], b, c
    for t, d in enumerate(local_dofs(tri)):
        scale = np.abs(K[t]).max() * (u[d] @ u[d])
        assert abs(u[d] @ K[t] @ u[d]) <= 1e-12 * scale
        assert np.abs(K[t] - K[t].T).max() <= 1e-13 * np.abs(K[t]).max()
        assert np.linalg.eigvalsh(K[t]).min() > -1e-10 * np.abs(K[t]).max()


def test_a_triangles_block_is_its_own(monkeypatch):
    """A block depends on its triangle only: the same bits alone, in a mesh, in blocks of
    any size and in any number of threads (the kernel's triangles are taken 8 at a time)."""
    pts, tri, dirs = shuffled_mesh(8, seed=2)
    scheme = get_scheme("quintic")
    whole = energy_blocks_of(pts, tri, dirs, scheme)
    for t in (0, 7, 8, tri.shape[0] - 1):
        alone = energy_blocks_of(pts, tri[t:t + 1], dirs[t:t + 1], scheme)
        assert np.array_equal(alone[0], whole[t])
    monkeypatch.setattr(smoothing_energy, "_CHUNK", 5)
    for threads in (1, 2):
        with limit(threads):
            assert energy_blocks_of(pts, tri, dirs, scheme).tobytes() == whole.tobytes()


# ------------------------------------------------------------------ vertex pattern
def test_vertex_pattern_is_the_adjacency_with_the_corners_in_triangle_order():
    pts, tri, _ = shuffled_mesh(7, seed=1)
    n = pts.shape[0]
    pattern = vertex_pattern(tri, n)
    for v in range(n):
        corners = [3 * t + k for t in range(tri.shape[0]) for k in range(3) if tri[t, k] == v]
        assert list(pattern.corner[pattern.start[v]:pattern.start[v + 1]]) == corners
        near = sorted({int(w) for t in range(tri.shape[0]) if v in tri[t] for w in tri[t]})
        assert list(pattern.cols[pattern.row_start[v]:pattern.row_start[v + 1]]) == near


def test_vertex_pattern_keeps_a_vertex_without_triangles():
    """A vertex no triangle uses is its own one neighbour: K stores its (zero) diagonal
    block, where S's data and gradient terms go."""
    pattern = vertex_pattern(np.array([[0, 1, 3]]), 5)
    assert list(pattern.row_start) == [0, 3, 6, 7, 10, 11]
    assert list(pattern.cols) == [0, 1, 3, 0, 1, 3, 2, 0, 1, 3, 4]
    assert list(pattern.start) == [0, 1, 2, 2, 3, 3]            # its corners: none


# ------------------------------------------------------------------ assembly
def dense_loop(blocks: np.ndarray, tri: np.ndarray, n: int) -> np.ndarray:
    """The plain assembly: each triangle's 9 × 9 block added at its unknowns, triangle
    after triangle, into a dense (3n, 3n) matrix."""
    K = np.zeros((3 * n, 3 * n))
    for t, dofs in enumerate(local_dofs(tri)):
        for i in range(9):
            for j in range(9):
                K[dofs[i], dofs[j]] += blocks[t, i, j]
    return K


@pytest.mark.parametrize("scheme", ["sextic", "ex39b"])
def test_assembly_equals_the_loop_over_triangles(scheme):
    """Every entry is the sum of its triangles' contributions in triangle order, so the
    loop gives the same bits; the stored entries are the 3 × 3 blocks of adjacent vertices."""
    pts, tri, dirs = shuffled_mesh(8, seed=3)
    n = pts.shape[0]
    shape = get_scheme(scheme)
    K = assemble_energy(pts, tri, dirs, shape)
    want = dense_loop(energy_blocks_of(pts, tri, dirs, shape), tri, n)
    assert K.has_sorted_indices and K.shape == (3 * n, 3 * n)
    assert np.array_equal(K.toarray(), want)
    adjacent = np.zeros((n, n), dtype=bool)
    for a in range(3):
        for b in range(3):
            adjacent[tri[:, a], tri[:, b]] = True
    stored = sp.csr_matrix((np.ones(K.nnz), K.indices, K.indptr), shape=K.shape).toarray() > 0
    assert np.array_equal(stored, np.kron(adjacent, np.ones((3, 3), dtype=bool)))


def test_assembly_bytes_do_not_depend_on_threads_row_blocks_or_chunks(monkeypatch):
    pts, tri, dirs = shuffled_mesh(12, seed=4)
    scheme = get_scheme("sextic")
    with limit(1):
        want = assemble_energy(pts, tri, dirs, scheme)
    monkeypatch.setattr(smoothing_system, "ROW_BLOCK", 7)
    monkeypatch.setattr(smoothing_system, "ASSEMBLY_CHUNK", 5)
    for threads in (1, 2):
        with limit(threads):
            got = assemble_energy(pts, tri, dirs, scheme)
        for name in ("data", "indices", "indptr"):
            assert getattr(got, name).tobytes() == getattr(want, name).tobytes()


def test_the_data_term_equals_the_loop_over_data_points():
    """System.matrix adds Aᵀ W A by the kernel (_smoothing_system.data_scatter) into the
    energy's pattern: the same matrix as a dense loop over the data points adding
    w_i a_i a_iᵀ at their triangles' unknowns (to rounding: the kernel forms each product
    once), exactly symmetric, with weight-0 points leaving no trace, and the values of A
    (which scipy sorts in place when it builds the CSR) still in local order afterwards."""
    from c1mesh.engine import rsd
    from c1mesh.stages.smoothing_system import System, data_rows

    rng = np.random.default_rng(8)
    pts, tri, dirs = shuffled_mesh(7, seed=8)
    n, scheme = pts.shape[0], get_scheme("sextic")
    t = rng.integers(0, tri.shape[0], 300)
    lam = rng.dirichlet(np.ones(3), 300)
    rows = data_rows(pts, tri, dirs, scheme, t, lam)
    # each row is F at its point: the interpolant's basis times the triangle's linear map
    corners = pts[tri[t]]
    G, _ = rsd.barycentric_gradients(corners)
    maps = smoothing_energy.linear_maps(corners, dirs[t], G)
    basis = rsd.basis(scheme, lam)
    assert np.allclose(rows.values, np.einsum("bm,mbj->mj", basis, maps), rtol=0, atol=1e-12)
    before = rows.values.copy()
    K = assemble_energy(pts, tri, dirs, scheme)
    system = System(K, rows, rng.normal(size=300))
    w = rng.uniform(0.5, 2.0, 300)
    w[::7] = 0.0
    system.fitted(rng.normal(size=3 * n))           # applied first: it must not reorder values
    S, _ = system.matrix(0.0, w, 0.0)
    want = np.zeros((3 * n, 3 * n))
    dofs = local_dofs(tri)
    for i in range(300):
        d = dofs[t[i]]
        want[np.ix_(d, d)] += w[i] * np.outer(before[i], before[i])
    got = S.toarray()
    assert np.abs(got - want).max() <= 1e-13 * np.abs(want).max()
    assert np.array_equal(got, got.T)
    assert np.array_equal(rows.values, before)
    A = np.zeros((300, 3 * n))
    for i in range(300):
        A[i, dofs[t[i]]] += before[i]
    assert np.allclose(got, A.T @ (w[:, None] * A), rtol=0, atol=1e-13 * np.abs(want).max())
    # s K is added on the same pattern, and the diagonal's positions are K's
    S2, _ = system.matrix(2.5, w, 0.0)
    assert np.array_equal(S2.indices, K.indices) and np.allclose(S2.toarray(), got + 2.5 * K.toarray(),
                                                                rtol=0, atol=1e-12 * np.abs(S2.data).max())


def test_the_data_rows_products_are_scipys_csr_products(monkeypatch):
    """DataRows.fitted (A u) and adjoint (Aᵀ r), by the kernels without forming A, against
    scipy's products with A as CSR (its columns sorted, as scipy's COO assembly leaves
    them): the same bits, for one column and for k columns, at 1 and 2 threads over many
    blocks of points and vertices; A itself is the dense loop over the points."""
    from c1mesh.stages.smoothing_system import data_rows

    rng = np.random.default_rng(10)
    pts, tri, dirs = shuffled_mesh(9, seed=10)
    n, m = pts.shape[0], 700
    t = rng.integers(0, tri.shape[0], m)
    rows = data_rows(pts, tri, dirs, get_scheme("sextic"), t, rng.dirichlet(np.ones(3), m))
    dofs = local_dofs(tri)[t]
    A = sp.coo_matrix((rows.values.ravel(), (np.repeat(np.arange(m), 9), dofs.ravel())), shape=(m, 3 * n)).tocsr()
    dense = np.zeros((m, 3 * n))
    for i in range(m):
        dense[i, dofs[i]] += rows.values[i]
    assert np.array_equal(A.toarray(), dense)
    u, r = rng.normal(size=(3 * n, 5)), rng.normal(size=(m, 5))
    monkeypatch.setattr(smoothing_system, "ROW_BLOCK", 13)
    for threads in (1, 2):
        with limit(threads):
            assert rows.fitted(u).tobytes() == (A @ u).tobytes()
            assert rows.adjoint(r).tobytes() == (A.T @ r).tobytes()
            assert rows.fitted(u[:, 0]).tobytes() == (A @ u[:, 0]).tobytes()
            assert rows.adjoint(r[:, 2]).tobytes() == (A.T @ r[:, 2]).tobytes()


def test_vertex_data_terms_go_on_the_diagonal_also_of_a_vertex_without_triangles():
    """System.matrix for vertex data: s K plus the weights on the f diagonal and μ × mask
    on the gradient diagonal, written on K's pattern: the dense sum, also at a vertex no
    triangle uses (a tile's record outside its triangles), whose block K stores as zero."""
    from c1mesh.stages.smoothing_system import System

    rng = np.random.default_rng(9)
    pts, tri, dirs = shuffled_mesh(5, seed=9)
    pts = np.vstack([pts, [[9.0, 9.0]]])                  # vertex n - 1: in no triangle
    n = pts.shape[0]
    K = assemble_energy(pts, tri, dirs, get_scheme("sextic"))
    w, mask, grads = rng.uniform(0.5, 2, n), (rng.uniform(size=n) > 0.3).astype(float), rng.normal(size=(n, 2))
    z = rng.normal(size=n)
    S, rhs = System(K, None, z, mask, grads * mask[:, None]).matrix(3.0, w, 0.7)
    want = 3.0 * K.toarray()
    want[np.arange(0, 3 * n, 3), np.arange(0, 3 * n, 3)] += w
    for c in (1, 2):
        want[np.arange(c, 3 * n, 3), np.arange(c, 3 * n, 3)] += 0.7 * mask
    assert np.array_equal(S.toarray(), want)
    assert S.toarray()[3 * n - 3, 3 * n - 3] == w[-1] and np.array_equal(S.indices, K.indices)
    assert np.allclose(rhs[1::3], 0.7 * grads[:, 0] * mask) and np.allclose(rhs[2::3], 0.7 * grads[:, 1] * mask)
    # written over K's values (the last matrix of a fit): the same matrix, then no other
    spent = System(K.copy(), None, z, mask, grads * mask[:, None])
    S_over, rhs_over = spent.matrix(3.0, w, 0.7, keep_energy=False)
    assert np.array_equal(S_over.toarray(), want) and np.array_equal(rhs_over, rhs)
    assert np.shares_memory(S_over.data, spent.K.data)
    with pytest.raises(ValueError):
        spent.matrix(3.0, w, 0.7)
    # solve's last matrix: u is numpy's dense solve, and then the factor and the system let go
    # of S (gradient data at every vertex: the one in no triangle has no energy to fix them)
    every = want + 0.7 * np.diag(np.tile([0.0, 1.0, 1.0], n) * np.repeat(1 - mask, 3))
    b = np.zeros(3 * n)
    b[0::3], b[1::3], b[2::3] = w * z, 0.7 * grads[:, 0], 0.7 * grads[:, 1]
    dense = np.linalg.solve(every, b)
    for method in smoothing_system.available_solvers():
        last = System(K.copy(), None, z, np.ones(n), grads)
        u, factor = smoothing_system.solve(last, 3.0, w, 0.7, method, keep_energy=False)
        assert np.abs(u - dense).max() <= 1e-9 * np.abs(dense).max()
        if method in ("cholmod", "superlu"):
            assert factor.S is None and last.K.shape == K.shape and last.K.nnz == 0
            assert np.abs(factor.solve(b, refine=False) - dense).max() <= 1e-6 * np.abs(dense).max()
            with pytest.raises(ValueError):
                factor.solve(b)


# ------------------------------------------------------------------ vertex order
def test_vertex_order_is_cholmods_metis_order_of_the_adjacency(monkeypatch):
    cholmod = pytest.importorskip("sksparse.cholmod")
    pts, tri, _ = shuffled_mesh(20, seed=6)
    n = pts.shape[0]
    monkeypatch.setattr(smoothing_system, "METIS_FROM", 3)
    rows, cols = [], []
    for t in tri:
        for a in t:
            for b in t:
                rows.append(a)
                cols.append(b)
    adjacency = sp.csc_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    try:
        want = cholmod.analyze(adjacency, ordering_method="metis").P()
    except cholmod.CholmodError:
        pytest.skip("this CHOLMOD has no METIS")
    got = vertex_order(tri, n)
    assert np.array_equal(got, want)
    assert np.array_equal(np.sort(got), np.arange(n))


# ------------------------------------------------------------------ input checks
def _python_checks(points, triangles, edges, u, degeneracy=1e-12):
    """The checks as plain Python loops: every direction crosses its edge, every
    triangle's |sin| at vertex 0 exceeds degeneracy."""
    import math
    crosses = True
    for (a, b), (ux, uy) in zip(edges, u):
        vx, vy = points[b] - points[a]
        cross = ux * vy - uy * vx
        crosses &= bool(cross * cross > degeneracy**2 * (ux * ux + uy * uy) * (vx * vx + vy * vy))
    fine = True
    for t in triangles:
        ax, ay = points[t[1]] - points[t[0]]
        bx, by = points[t[2]] - points[t[0]]
        fine &= bool(abs(ax * by - ay * bx) > degeneracy * math.hypot(ax, ay) * math.hypot(bx, by))
    return crosses, fine


@pytest.mark.parametrize("case", ["good", "parallel", "zero", "sliver", "nan"])
def test_input_checks_agree_with_python_loops(case, monkeypatch):
    from c1mesh.stages import smoothing
    pts, tri, _ = shuffled_mesh(6, seed=7)
    table = edge_table(tri, pts.shape[0])
    u = np.random.default_rng(7).normal(size=table.edges.shape)
    if case == "parallel":
        u[5] = pts[table.edges[5, 1]] - pts[table.edges[5, 0]]
    elif case == "zero":
        u[-1] = 0.0
    elif case == "sliver":
        a, b, c = tri[3]
        pts = pts.copy()
        pts[c] = pts[a] + 0.5 * (pts[b] - pts[a])             # collinear: zero area
    elif case == "nan":
        pts = pts.copy()
        pts[tri[-1, 0], 0] = np.nan
    monkeypatch.setattr(smoothing, "CHECK_BLOCK", 4)          # many blocks, the bad one among them
    crosses, fine = _python_checks(pts, tri, table.edges, u)
    assert smoothing._nondegenerate(pts, tri) == fine
    assert smoothing._all_blocks(smoothing.kernel.directions_cross, pts, table.edges, u) == crosses
    assert (crosses and fine) == (case == "good")
