"""Property-based tests (hypothesis) of the engine on random meshes, thin triangles included."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from c1mesh import RSDInterpolator


@st.composite
def meshes(draw):
    """Random point sets (with optional squashing, which makes thin triangles) and data."""
    seed = draw(st.integers(0, 2**31 - 1))
    n = draw(st.integers(4, 60))
    squash = draw(st.sampled_from([1.0, 0.1, 0.01]))
    rng = np.random.default_rng(seed)
    pts = rng.random((n, 2)) * [1.0, squash]
    try:
        tris = Delaunay(pts).simplices
    except Exception:  # noqa: BLE001 — degenerate draws are skipped by hypothesis.assume below
        tris = np.empty((0, 3), dtype=int)
    return pts, tris, rng


def _with_mesh(draw_result):
    pts, tris, rng = draw_result
    from hypothesis import assume
    assume(len(tris) > 0)
    corners = pts[tris]
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    assume(np.all(np.abs(det) > 1e-9 * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)))
    return pts, tris, rng


@settings(max_examples=40, deadline=None)
@given(meshes())
def test_sextic_reproduces_affine_data_on_any_mesh(drawn):
    pts, tris, rng = _with_mesh(drawn)
    a, b = rng.normal(size=2), rng.normal()
    interp = RSDInterpolator(pts, pts @ a + b, np.tile(a, (len(pts), 1)), triangles=tris)
    lam = rng.dirichlet(np.ones(3), size=len(tris))
    q = np.einsum("tk,tkd->td", lam, pts[tris])
    # tolerance grows with the ratios G_l·u_n / G_n·u_n that thin triangles produce
    scale = 1 + np.abs(a).sum() + abs(b)
    cond = 1 + np.abs(interp.coefficients).max()
    np.testing.assert_allclose(interp(q), q @ a + b, atol=1e-12 * scale * cond)


@settings(max_examples=40, deadline=None)
@given(meshes())
def test_refined_values_match_pointwise_and_vertices_exact(drawn):
    pts, tris, rng = _with_mesh(drawn)
    f = np.sin(3 * pts[:, 0]) + pts[:, 1] ** 2
    A = np.stack([3 * np.cos(3 * pts[:, 0]), 2 * pts[:, 1]], 1)
    interp = RSDInterpolator(pts, f, A, triangles=tris)
    level = int(rng.integers(1, 5))
    r = interp.refine(level)
    assert len(r.triangles) == len(tris) * level**2
    np.testing.assert_array_equal(r.values[:len(pts)], f)
    # evaluate each refined point in its own parent (no point location involved)
    tri_of_point = np.empty(len(r.points), dtype=int)
    tri_of_point[r.triangles.ravel()] = np.repeat(r.parent, 3)
    G = interp.lambda_gradients[tri_of_point]
    anchor = pts[tris[tri_of_point, 1]]
    lam0 = np.einsum("md,md->m", G[:, 0], r.points - anchor)
    lam1 = np.einsum("md,md->m", G[:, 1], r.points - pts[tris[tri_of_point, 2]])
    lam = np.stack([lam0, lam1, 1 - lam0 - lam1], 1)
    from c1mesh.engine import rsd
    expected = np.einsum("mj,jm->m", interp.coefficients[tri_of_point], rsd.basis(interp.scheme, lam))
    tol = 1e-9 * (1 + np.abs(interp.coefficients).max())
    np.testing.assert_allclose(r.values, expected, atol=tol)


@settings(max_examples=30, deadline=None)
@given(meshes())
def test_c1_certificate_small_on_any_mesh(drawn):
    pts, tris, rng = _with_mesh(drawn)
    f = np.exp(pts[:, 0]) * np.cos(pts[:, 1])
    A = np.stack([f, -np.exp(pts[:, 0]) * np.sin(pts[:, 1])], 1)
    interp = RSDInterpolator(pts, f, A, triangles=tris)
    cert = interp.c1_certificate()
    cond = 1 + np.abs(interp.coefficients).max()
    assert cert["value_jump"] <= 1e-13 * cond
    assert cert["gradient_jump"] <= 1e-11 * cond * (1 + np.abs(interp.lambda_gradients).max())
