"""The RSD engine against the paper: interpolation, C1, RSD formula, reproduction, refinement."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Delaunay

import reference_rsd as ref
from c1mesh import RSDInterpolator
from c1mesh.engine import rsd
from c1mesh.core.errors import InputError
from c1mesh.engine.properties import scheme_properties
from c1mesh.engine.schemes import NAMED_TUPLES, get_scheme
from c1mesh.engine.topology import mesh_edges


def franke(x):
    X, Y = 9 * x[..., 0], 9 * x[..., 1]
    return (0.75 * np.exp(-((X - 2) ** 2 + (Y - 2) ** 2) / 4) + 0.75 * np.exp(-(X + 1) ** 2 / 49 - (Y + 1) / 10)
            + 0.5 * np.exp(-((X - 7) ** 2 + (Y - 3) ** 2) / 4) - 0.2 * np.exp(-(X - 4) ** 2 - (Y - 7) ** 2))


def smooth(x):
    return np.exp(x[..., 0]) * np.sin(2 * x[..., 1])


def smooth_grad(x):
    e = np.exp(x[..., 0])
    return np.stack([e * np.sin(2 * x[..., 1]), 2 * e * np.cos(2 * x[..., 1])], axis=-1)


def random_mesh(n=80, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.random((n, 2))
    return pts, Delaunay(pts).simplices


@pytest.fixture(scope="module")
def mesh():
    return random_mesh()


@pytest.mark.parametrize("name", ["sextic", "quintic", "ex39b"])
def test_matches_independent_implementation(mesh, name):
    pts, tris = mesh
    rng = np.random.default_rng(1)
    f, A = smooth(pts), smooth_grad(pts)
    interp = RSDInterpolator(pts, f, A, triangles=tris, scheme=name)
    q = rng.random((300, 2))
    simplex = Delaunay(pts).find_simplex(q)
    q, simplex = q[simplex >= 0], simplex[simplex >= 0]
    ours_v, ours_g = interp(q), interp.gradient(q)
    # default directions: the unit normal of each edge
    for x, s, v, g in zip(q, simplex, ours_v, ours_g):
        t = tris[s]
        p = pts[t]
        u = np.array([[-(p[(k + 2) % 3] - p[(k + 1) % 3])[1], (p[(k + 2) % 3] - p[(k + 1) % 3])[0]]
                      for k in range(3)])
        rv, rg = ref.value_and_gradient(name, p, f[t], A[t], u, x)
        assert abs(v - rv) <= 1e-10 * max(1.0, abs(rv))
        assert np.abs(g - rg).max() <= 1e-10 * max(1.0, np.abs(rg).max())


@pytest.mark.parametrize("name", list(NAMED_TUPLES))
def test_interpolates_vertex_values_and_gradients(mesh, name):
    pts, tris = mesh
    f, A = franke(pts), smooth_grad(pts)
    interp = RSDInterpolator(pts, f, A, triangles=tris, scheme=name)
    used = np.unique(tris)
    np.testing.assert_allclose(interp(pts[used]), f[used], rtol=0, atol=1e-12)
    np.testing.assert_allclose(interp.gradient(pts[used]), A[used], rtol=0, atol=1e-9)


def _edge_samples(interp, tris):
    """For each interior edge, its two triangles and exact barycentrics of edge points in each."""
    table = interp.edge_table
    s = np.linspace(0.05, 0.95, 7)
    for e in np.flatnonzero(table.count == 2):
        owners = np.flatnonzero((table.tri_edge == e).any(axis=1))
        a, b = table.edges[e]
        lams = []
        for t in owners:
            lam = np.zeros((s.size, 3))
            lam[:, list(tris[t]).index(a)] = 1 - s
            lam[:, list(tris[t]).index(b)] = s
            lams.append(lam)
        yield e, owners, lams, s


def _local_eval(interp, t, lam):
    C = interp.coefficients[t]
    value = C @ rsd.basis(interp.scheme, lam)
    D0, D1 = rsd.gradient_basis(interp.scheme, lam)
    G = interp.lambda_gradients[t]
    grad = np.outer(C @ D0, G[0]) + np.outer(C @ D1, G[1])
    return value, grad


@pytest.mark.parametrize("name", list(NAMED_TUPLES))
def test_c1_across_every_interior_edge(mesh, name):
    pts, tris = mesh
    f, A = franke(pts), smooth_grad(pts) * 3
    interp = RSDInterpolator(pts, f, A, triangles=tris, scheme=name)
    worst_v = worst_g = 0.0
    checked = 0
    for _, (t1, t2), (l1, l2), _ in _edge_samples(interp, tris):
        v1, g1 = _local_eval(interp, t1, l1)
        v2, g2 = _local_eval(interp, t2, l2)
        scale_v = 1.0 + np.abs(v1).max()
        scale_g = 1.0 + np.abs(g1).max()
        worst_v = max(worst_v, np.abs(v1 - v2).max() / scale_v)
        worst_g = max(worst_g, np.abs(g1 - g2).max() / scale_g)
        checked += 1
    assert checked > 100
    assert worst_v <= 1e-11 and worst_g <= 1e-11


def test_without_shared_directions_the_spline_is_not_c1(mesh):
    """The C1 test can fail: per-triangle random directions break the gradient continuity."""
    pts, tris = mesh
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    rng = np.random.default_rng(3)
    interp.coefficients = rsd.triangle_coefficients(
        pts[tris], interp.values[tris], interp.gradients[tris], rng.normal(size=(len(tris), 3, 2)), interp.lambda_gradients)
    jumps = [np.abs(_local_eval(interp, t1, l1)[1] - _local_eval(interp, t2, l2)[1]).max()
             for _, (t1, t2), (l1, l2), _ in _edge_samples(interp, tris)]
    assert max(jumps) > 1e-3


@pytest.mark.parametrize("name", list(NAMED_TUPLES))
def test_reduced_side_derivative_formula(mesh, name):
    """Along edge [p_i, p_j]: ∇F·u = Ψ1(λ_i) A_i·u + Ψ1(λ_j) A_j·u (Definition 3.2)."""
    pts, tris = mesh
    f, A = franke(pts), smooth_grad(pts)
    interp = RSDInterpolator(pts, f, A, triangles=tris, scheme=name)
    psi1 = get_scheme(name).psi1
    rng = np.random.default_rng(5)
    for t in rng.choice(len(tris), 20, replace=False):
        for k in range(3):
            i, j = (k + 1) % 3, (k + 2) % 3
            s = np.linspace(0, 1, 9)
            lam = np.zeros((9, 3))
            lam[:, i], lam[:, j] = s, 1 - s
            _, grad = _local_eval(interp, t, lam)
            u = interp.directions[interp.edge_table.tri_edge[t, k]]
            Ai, Aj = A[tris[t, i]], A[tris[t, j]]
            expected = psi1(s) * (Ai @ u) + psi1(1 - s) * (Aj @ u)
            np.testing.assert_allclose(grad @ u, expected, atol=1e-10 * (1 + np.abs(expected).max()))


def test_gradient_matches_finite_differences(mesh):
    pts, tris = mesh
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    rng = np.random.default_rng(7)
    q = rng.random((200, 2)) * 0.6 + 0.2
    h = 1e-6
    fd = np.stack([(interp(q + [h, 0]) - interp(q - [h, 0])) / (2 * h),
                   (interp(q + [0, h]) - interp(q - [0, h])) / (2 * h)], axis=1)
    ok = np.isfinite(fd).all(axis=1)
    np.testing.assert_allclose(interp.gradient(q)[ok], fd[ok], atol=1e-5 * (1 + np.abs(fd).max()))


@pytest.mark.parametrize("name", list(NAMED_TUPLES))
def test_constants_reproduced(mesh, name):
    pts, tris = mesh
    interp = RSDInterpolator(pts, np.full(len(pts), 2.5), np.zeros((len(pts), 2)), triangles=tris, scheme=name)
    q = np.random.default_rng(2).random((500, 2))
    v, g = interp(q), interp.gradient(q)
    ok = np.isfinite(v)
    assert ok.sum() > 300
    assert np.abs(v[ok] - 2.5).max() < 1e-12
    assert np.abs(g[ok]).max() < 1e-9


def test_affine_reproduced_by_sextic_only(mesh):
    pts, tris = mesh
    a, b = np.array([1.5, -0.7]), 0.3
    q = np.random.default_rng(4).random((500, 2))
    defects = {}
    for name in NAMED_TUPLES:
        interp = RSDInterpolator(pts, pts @ a + b, np.tile(a, (len(pts), 1)), triangles=tris, scheme=name)
        v, g = interp(q), interp.gradient(q)
        ok = np.isfinite(v)
        defects[name] = (np.abs(v[ok] - (q[ok] @ a + b)).max(), np.abs(g[ok] - a).max())
    assert defects["sextic"][0] < 1e-12 and defects["sextic"][1] < 1e-9
    # The paper: the 2022 quintic and Ex. 3.9b are not affine invariant; the defect is O(1) in gradients.
    for name in ("quintic", "ex39b"):
        assert defects[name][0] > 1e-4 and defects[name][1] > 0.1


def test_computed_properties_match_the_paper():
    props = {name: scheme_properties(name) for name in NAMED_TUPLES}
    assert all(p.reproduces_constants for p in props.values())
    assert props["sextic"].reproduces_affine
    assert not props["quintic"].reproduces_affine and not props["ex39b"].reproduces_affine


def test_direction_sign_does_not_matter(mesh):
    pts, tris = mesh
    base = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    rng = np.random.default_rng(8)
    u = base.directions * np.where(rng.random(len(base.directions)) < 0.5, -1.0, 1.0)[:, None]
    flipped = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris, directions=u)
    q = rng.random((300, 2))
    np.testing.assert_allclose(flipped(q), base(q), atol=1e-13, equal_nan=True)
    np.testing.assert_allclose(flipped.gradient(q), base.gradient(q), atol=1e-11, equal_nan=True)


def test_other_directions_change_the_spline_but_keep_c1(mesh):
    pts, tris = mesh
    rng = np.random.default_rng(9)
    edges = mesh_edges(tris, len(pts))
    vec = pts[edges[:, 1]] - pts[edges[:, 0]]
    u = np.stack([-vec[:, 1], vec[:, 0]], 1) + 0.5 * vec * rng.uniform(-1, 1, (len(vec), 1))
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris, directions=u)
    base = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    q = rng.random((300, 2))
    assert np.nanmax(np.abs(interp(q) - base(q))) > 1e-6
    for _, (t1, t2), (l1, l2), _ in _edge_samples(interp, tris):
        g1, g2 = _local_eval(interp, t1, l1)[1], _local_eval(interp, t2, l2)[1]
        assert np.abs(g1 - g2).max() <= 1e-11 * (1 + np.abs(g1).max())


def test_fill_value_outside_and_shape_of_queries(mesh):
    pts, tris = mesh
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris, fill_value=-7.0)
    q = np.array([[[5.0, 5.0], [0.5, 0.5]], [[-1.0, 0.2], [0.4, 0.6]]])
    v = interp(q)
    assert v.shape == (2, 2) and v[0, 0] == -7.0 and v[1, 0] == -7.0 and v[0, 1] != -7.0
    assert interp.gradient(q).shape == (2, 2, 2)
    assert np.isnan(RSDInterpolator(pts, franke(pts), smooth_grad(pts))([[9.0, 9.0]])[0])


def test_point_location_in_a_non_delaunay_triangulation():
    """Long skinny fan triangles (far from Delaunay): location must still be exact."""
    n = 40
    ang = np.linspace(0, np.pi, n)
    rim = np.stack([np.cos(ang), 0.05 * np.sin(ang)], 1)
    pts = np.vstack([[0.0, 0.0], rim])
    tris = np.array([[0, i, i + 1] for i in range(1, n)])
    interp = RSDInterpolator(pts, smooth(pts), smooth_grad(pts), triangles=tris)
    rng = np.random.default_rng(10)
    q = rng.uniform([-1, 0], [1, 0.05], (2000, 2))
    found = interp.find_simplex(q)
    for x, t in zip(q, found):
        lam, _ = ref.barycentric(pts[tris[t]], x) if t >= 0 else (None, None)
        if t >= 0:
            assert lam.min() >= -1e-9
        else:  # outside: no triangle contains it
            assert all(ref.barycentric(pts[tri], x)[0].min() < 1e-9 for tri in tris)


def test_the_locator_is_the_best_barycentric_of_a_loop_over_every_triangle(monkeypatch):
    """TriangleLocator.find (a kernel over the bucket grid, queries in blocks and threads)
    against a plain loop over all triangles: the triangle whose smallest barycentric
    coordinate is largest (at least -tolerance; ties to the lowest index), with those
    barycentrics, -1 and NaN elsewhere: outside the mesh, non-finite, at vertices and on
    edges (ties), in blocks of any size and any number of threads."""
    from c1mesh.core.threads import limit
    from c1mesh.engine import locate, rsd

    rng = np.random.default_rng(12)
    pts, tris = random_mesh(60)
    tris = np.asarray(tris, dtype=np.int64)
    G, _ = rsd.barycentric_gradients(pts[tris])
    q = np.concatenate([rng.uniform(-0.2, 1.2, (1500, 2)), pts, (pts[tris[:, 0]] + pts[tris[:, 1]]) / 2,
                        [[np.nan, 0.5], [0.5, np.inf]]])
    want_tri = np.full(len(q), -1)
    want_lam = np.full((len(q), 3), np.nan)
    for i, x in enumerate(q):
        best = -np.inf
        for t, (a, b, c) in enumerate(tris):       # λ_k = G_k · (x − p_{k+1}), unfused (BLAS's dot fuses)
            lam0 = G[t, 0, 0] * (x[0] - pts[b, 0]) + G[t, 0, 1] * (x[1] - pts[b, 1])
            lam1 = G[t, 1, 0] * (x[0] - pts[c, 0]) + G[t, 1, 1] * (x[1] - pts[c, 1])
            lam = np.array([lam0, lam1, 1.0 - lam0 - lam1])
            if lam.min() >= -1e-10 and lam.min() > best:
                best, want_tri[i], want_lam[i] = lam.min(), t, lam
    monkeypatch.setattr(locate, "_QUERY_BLOCK", 37)
    for threads in (1, 2):
        with limit(threads):
            tri, lam = locate.TriangleLocator(pts, tris, G).find(q)
        assert np.array_equal(tri, want_tri)
        assert np.allclose(lam, want_lam, rtol=0, atol=1e-12, equal_nan=True)


def test_errors_are_clear():
    pts, tris = random_mesh(20)
    f, A = smooth(pts), smooth_grad(pts)
    with pytest.raises(InputError, match="points must have shape"):
        RSDInterpolator(pts[:, :1], f, A)
    with pytest.raises(InputError, match="gradients must have shape"):
        RSDInterpolator(pts, f, A[:5])
    with pytest.raises(InputError, match="NaN or Inf"):
        RSDInterpolator(pts, np.where(np.arange(20) == 3, np.nan, f), A)
    bad = np.vstack([pts, pts[0] + 0.5 * (pts[1] - pts[0])])
    with pytest.raises(InputError, match="degenerate"):
        RSDInterpolator(bad, np.append(f, 0), np.vstack([A, [0, 0]]), triangles=[[0, 1, 20]])
    edges = mesh_edges(tris, 20)
    u = np.ones((len(edges), 2))
    u[3] = pts[edges[3, 1]] - pts[edges[3, 0]]
    with pytest.raises(InputError, match="parallel"):
        RSDInterpolator(pts, f, A, triangles=tris, directions=u)
    with pytest.raises(ValueError):   # InputError is a ValueError, as in scipy
        RSDInterpolator(pts, f, A, triangles=[[0, 1, 99]])


def test_refine_agrees_with_pointwise_evaluation(mesh):
    pts, tris = mesh
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    for level in (1, 2, 5):
        r = interp.refine(level)
        assert r.triangles.shape == (len(tris) * level**2, 3)
        np.testing.assert_array_equal(r.values[:len(pts)], franke(pts))       # exact input values
        np.testing.assert_allclose(r.values, interp(r.points), atol=1e-12)
        np.testing.assert_allclose(r.gradients, interp.gradient(r.points), atol=1e-9)
        # every sub-triangle lies inside its parent and keeps its orientation
        centroids = r.points[r.triangles].mean(axis=1)
        assert np.array_equal(interp.find_simplex(centroids), r.parent)
        def area(P):
            a, b = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
            return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]

        assert np.all(np.sign(area(r.points[r.triangles])) == np.sign(area(pts[tris]))[r.parent])


def _euler(triangles):
    e = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    return len(np.unique(triangles)) - len(edges) + len(triangles), counts


def test_refined_mesh_is_conforming(mesh):
    pts, tris = mesh
    r = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris).refine(4)
    chi_in, counts_in = _euler(tris)
    chi_out, counts_out = _euler(r.triangles.astype(np.int64))
    assert chi_out == chi_in == 1
    assert counts_out.max() == 2
    # boundary edges: each input boundary edge becomes exactly `level` boundary edges
    assert (counts_out == 1).sum() == 4 * (counts_in == 1).sum()
    # no duplicated points (a crack would show up as two points at one position)
    assert len(np.unique(np.round(r.points, 12), axis=0)) == len(r.points)


def test_refine_level_checks(mesh):
    pts, tris = mesh
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    with pytest.raises(ValueError, match="level"):
        interp.refine(0)
    with pytest.raises(ValueError, match="level"):
        interp.refine(2.5)


def test_c1_certificate_measures_jumps(mesh):
    pts, tris = mesh
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    cert = interp.c1_certificate()
    assert cert["edges_checked"] == int((interp.edge_table.count == 2).sum())
    assert cert["value_jump"] < 1e-12 and cert["gradient_jump"] < 1e-11
    # breaking the shared directions must show up in the certificate
    interp.coefficients = rsd.triangle_coefficients(
        pts[tris], interp.values[tris], interp.gradients[tris],
        np.random.default_rng(0).normal(size=(len(tris), 3, 2)), interp.lambda_gradients)
    assert interp.c1_certificate()["gradient_jump"] > 1e-3


def test_refined_linear_field_is_barycentric_blend(mesh):
    pts, tris = mesh
    r = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris).refine(3)
    colours = np.stack([pts[:, 0] * 200, pts[:, 1] * 100 + 5], axis=1)
    blended = r.linear(colours)
    # a linear function of position must come out as that function of the refined points
    np.testing.assert_allclose(blended, np.stack([r.points[:, 0] * 200, r.points[:, 1] * 100 + 5], 1),
                               atol=1e-9)
    np.testing.assert_array_equal(blended[:len(pts)], colours)


@pytest.mark.parametrize("level", [1, 2, 3, 5])
def test_refinement_in_many_small_blocks(monkeypatch, level):
    """Blocks of a few triangles (so edges are owned across block boundaries) must give
    the same conforming, correct mesh as one block: pointwise values, shared edge points."""
    import c1mesh.engine.refine as refine_module
    pts, tris = random_mesh(200, seed=4)
    interp = RSDInterpolator(pts, smooth(pts), smooth_grad(pts), triangles=tris)
    whole = interp.refine(level)
    monkeypatch.setattr(refine_module, "CHUNK_ENTRIES", 40)
    small = interp.refinement(level)
    assert small.rows < len(tris) // 10
    r = small.mesh()
    np.testing.assert_allclose(r.values, interp(r.points), atol=1e-12)
    np.testing.assert_allclose(r.gradients, interp.gradient(r.points), atol=1e-9)
    np.testing.assert_array_equal(r.points[:len(pts)], pts)
    chi, counts = _euler(r.triangles.astype(np.int64))
    assert chi == 1 and counts.max() == 2
    assert len(np.unique(np.round(r.points, 12), axis=0)) == len(r.points)
    # the same sub-triangles (as point triples) as with one block, parent by parent
    key = lambda m: np.sort(np.round(m.points[m.triangles], 12).reshape(len(m.triangles), -1), axis=1)  # noqa: E731
    np.testing.assert_array_equal(np.sort(key(r), axis=0), np.sort(key(whole), axis=0))
    np.testing.assert_array_equal(r.parent, whole.parent)


def test_vertex_blocks_cover_the_output_once(mesh):
    pts, tris = mesh
    refinement = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris).refinement(4)
    starts, stops = zip(*[(b.start, b.stop) for b in refinement.vertex_blocks()])
    assert starts[0] == 0 and stops[-1] == refinement.vertex_count
    assert list(starts[1:]) == list(stops[:-1])
    faces = [f.copy() for _, f in refinement.face_blocks()]
    assert sum(len(f) for f in faces) == refinement.face_count


def test_mesh_coefficients_threads_and_passes_give_the_same_bits(mesh):
    from c1mesh.engine.topology import edge_table
    points, triangles = mesh
    interp = RSDInterpolator(points, smooth(points), smooth_grad(points), triangles=triangles)
    table = edge_table(interp.triangles, len(points))
    args = (rsd.VertexData(interp.points, interp.values, interp.gradients), interp.triangles,
            interp.directions, table.tri_edge)
    one = rsd.mesh_coefficients(*args, chunk=7, threads=1)
    two = rsd.mesh_coefficients(*args, chunk=7, threads=2)
    for a, b in zip(one, two):
        assert np.array_equal(a, b)
    assert np.array_equal(one[0], interp.coefficients) and np.array_equal(one[1], interp.lambda_gradients)
    t = interp.triangles
    corners = interp.points[t]
    G, det = rsd.barycentric_gradients(corners)
    C = rsd.triangle_coefficients(corners, interp.values[t], interp.gradients[t],
                                  interp.directions[table.tri_edge], G)
    assert np.array_equal(C, one[0]) and np.array_equal(G, one[1]) and np.array_equal(det, one[2])


def test_mesh_coefficients_are_the_formulas_of_a_loop_over_triangles(mesh):
    """The coefficient kernel (engine/_rsd.pyx) against the module docstring's formulas in
    a plain Python loop over the triangles, float by float in the same order (so equal to
    the bit); a degenerate triangle (a corner repeated) flagged and its G zero."""
    from c1mesh.engine.topology import edge_table
    points, triangles = mesh
    triangles = np.vstack([triangles, [[0, 1, 1]]])           # zero area: det 0
    f, A = smooth(points), smooth_grad(points)
    u = np.random.default_rng(4).normal(size=(3 * len(triangles), 2))
    tri_edge = np.arange(3 * len(triangles)).reshape(-1, 3)   # each triangle's own edges
    C, G, det, bad = rsd.mesh_coefficients(rsd.VertexData(points, f, A), triangles, u, tri_edge,
                                           chunk=5, min_sine=1e-3, threads=2)
    for t, corners in enumerate(triangles.tolist()):
        x = [float(points[v, 0]) for v in corners]
        y = [float(points[v, 1]) for v in corners]
        d = (x[1] - x[0]) * (y[2] - y[0]) - (y[1] - y[0]) * (x[2] - x[0])
        inv = 0.0 if d == 0 else 1.0 / d
        g = [((y[(k + 1) % 3] - y[(k + 2) % 3]) * inv, (x[(k + 2) % 3] - x[(k + 1) % 3]) * inv) for k in range(3)]
        want = [float(f[v]) for v in corners]
        for k, i in rsd.PAIRS:
            want.append(float(A[corners[k], 0]) * (x[i] - x[k]) + float(A[corners[k], 1]) * (y[i] - y[k]))
        ratios = []
        with np.errstate(all="ignore"):                       # 0 / 0 of the degenerate one: NaN
            for l, m, n in rsd.PERMS:
                ux, uy = (float(c) for c in u[tri_edge[t, n]])
                ratios.append(np.float64(g[l][0] * ux + g[l][1] * uy) / np.float64(g[n][0] * ux + g[n][1] * uy))
            want += [r * want[l] for r, (l, m, n) in zip(ratios, rsd.PERMS)]
            want += [r * want[3 + rsd.PAIRS.index((l, m))] for r, (l, m, n) in zip(ratios, rsd.PERMS)]
        assert det[t] == d and G[t].tolist() == [list(gk) for gk in g]
        np.testing.assert_array_equal(C[t], want)
        e1, e2 = np.hypot(x[1] - x[0], y[1] - y[0]), np.hypot(x[2] - x[0], y[2] - y[0])
        assert bad[t] == (not abs(d) > 1e-3 * e1 * e2)
    assert bad[-1] and not bad[:-1].any() and not G[-1].any()


@pytest.mark.parametrize("workers", [2, 3])
def test_workers_and_prefaulting_change_no_byte(mesh, monkeypatch, workers):
    """Worker threads (each a range of blocks) and page pre-faulting must never alter
    outputs: one worker without pre-faulting and several with it give identical arrays."""
    import c1mesh.engine.refine as refine_module
    pts, tris = mesh
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    monkeypatch.setattr(refine_module, "CHUNK_ENTRIES", 200)            # many blocks per worker
    refinement = interp.refinement(6)
    assert -(-len(tris) // refinement.rows) >= 3 * workers
    parallel = refinement.mesh(workers=workers)
    monkeypatch.setattr(refine_module, "_madvise", None)
    serial = refinement.mesh(workers=1)
    for name in ("points", "values", "gradients", "triangles", "parent"):
        np.testing.assert_array_equal(getattr(parallel, name), getattr(serial, name))
    np.testing.assert_array_equal(parallel.parent, np.repeat(np.arange(len(tris)), 36))
    streamed = np.concatenate([b.values.copy() for b in refinement.vertex_blocks()])
    np.testing.assert_array_equal(streamed, serial.values)


def test_worker_errors_reach_the_caller(mesh, monkeypatch):
    import c1mesh.engine.refine as refine_module
    pts, tris = mesh
    calls = []

    def failing(self, first, last, out):
        calls.append(first)
        if first > 0:
            raise MemoryError("worker failed")
        yield from ()
    monkeypatch.setattr(refine_module, "CHUNK_ENTRIES", 30)
    refinement = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris).refinement(2)
    monkeypatch.setattr(refine_module.Refinement, "_face_range", failing)
    with pytest.raises(MemoryError, match="worker failed"):
        refinement.mesh(workers=2)
    assert sorted(calls)[0] == 0 and len(calls) == 2


def _interior_bits(refinement, mesh, triangle):
    """The bytes of the points, values and gradients inside one triangle of a refinement
    (interior points come last among the triangle's points, and every triangle owns them)."""
    stop = int(refinement.tri_start[triangle + 1])
    part = slice(stop - refinement.n_int, stop)
    return mesh.points[part].tobytes() + mesh.values[part].tobytes() + mesh.gradients[part].tobytes()


def _sub_refinement(interp, first, last, level):
    """The refinement of triangles [first, last) alone (same coefficient rows), as a
    --seamless tile refines a subset of the survey's triangles."""
    from c1mesh.engine.refine import Refinement
    from c1mesh.engine.topology import edge_table
    part = slice(first, last)
    triangles = interp.triangles[part]
    vertices = rsd.VertexData(interp.points, interp.values, interp.gradients)
    return Refinement(vertices, triangles, interp.coefficients[part], interp.lambda_gradients[part],
                      edge_table(triangles, len(interp.points)), interp.scheme, level)


@pytest.mark.parametrize("level", [4, 8])
def test_a_point_has_the_same_bits_in_a_block_of_any_size(level):
    """A refined point's bits must not depend on the block its triangle is evaluated in:
    a full block, a short last block of a few triangles, at any offset, with one BLAS
    thread or two. (--seamless -O tiles evaluate a border triangle in different blocks;
    issue 21: OpenBLAS's small-matrix kernel, taken by short blocks only, rounded
    differently and the tiles wrote one border vertex with two different bits.)"""
    from c1mesh.core.threads import blas_threads
    pts, tris = random_mesh({4: 5000, 8: 2000}[level], seed=11)
    interp = RSDInterpolator(pts, franke(pts), smooth_grad(pts), triangles=tris)
    whole = interp.refinement(level)
    assert whole.rows < len(interp.triangles), "the whole refinement must have a full block"
    with blas_threads(1):
        reference = whole.mesh(workers=1)
    assert whole.n_int > 0
    probes = [0, 1, 7, whole.rows // 2, whole.rows - 1]
    for first, count in [(0, 1), (1, 5), (0, 40), (3, 300), (whole.rows // 2 - 2, 64)]:
        part = _sub_refinement(interp, first, first + count, level)
        with blas_threads(1):
            got = part.mesh(workers=1)
        for t in [p for p in probes if first <= p < first + count]:
            assert _interior_bits(part, got, t - first) == _interior_bits(whole, reference, t), (first, count, t)
    with blas_threads(2):                  # the streamed pass keeps the caller's BLAS threads
        two_threads = _streamed(whole)
    assert all(_interior_bits(whole, two_threads, t) == _interior_bits(whole, reference, t) for t in probes)


def _streamed(refinement):
    """The refined points, values and gradients of a streamed pass (vertex_blocks)."""
    from types import SimpleNamespace
    M = refinement.vertex_count
    out = SimpleNamespace(points=np.empty((M, 2)), values=np.empty(M), gradients=np.empty((M, 2)))
    for _ in refinement.vertex_blocks(out=[out.points, out.values, out.gradients]):
        pass
    return out
