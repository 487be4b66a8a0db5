"""The C1 smoothing fit (c1mesh.stages.smoothing), against independent truth: finite
differences of the interpolator, analytic functions, direct solves of the optimality
conditions, dense traces, and matplotlib's minimum-energy gradients."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.engine.schemes import ShapeTuple, get_scheme
from c1mesh.stages.smoothing import (GradientPrior, SchemeNotPolynomialError, SmoothFit, SmoothingControl,
                                     SmoothingData, SmoothingError, energy_blocks, parse_strength, smooth_fit)
from c1mesh.engine.topology import edge_table
from c1mesh.stages.smoothing_energy import local_dofs, triangle_directions
from c1mesh.stages.smoothing_system import Factor, System, assemble_energy, available_solvers, hat_trace


def grid_mesh(m: int, seed: int = 0, jitter: float = 0.3, size: float = 1.0):
    """A jittered m × m grid over [0, size]², two triangles per cell (no slivers)."""
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    xy = np.stack([i.ravel(), j.ravel()], 1).astype(float)
    xy += rng.uniform(-jitter, jitter, xy.shape)
    v = (i[:-1, :-1] * m + j[:-1, :-1]).ravel()
    tri = np.concatenate([np.stack([v, v + m, v + m + 1], 1), np.stack([v, v + m + 1, v + 1], 1)])
    return xy * (size / (m - 1)), tri, size / (m - 1)


def surface(xy):
    return np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1]) + 0.5 * xy[:, 0] ** 2


def surface_gradient(xy):
    return np.stack([3 * np.cos(3 * xy[:, 0]) * np.cos(2 * xy[:, 1]) + xy[:, 0],
                     -2 * np.sin(3 * xy[:, 0]) * np.sin(2 * xy[:, 1])], 1)


def assembled(points, tri, scheme="sextic", directions=None):
    K = energy_blocks(points, tri, directions, scheme)
    dofs = local_dofs(tri)
    n = 3 * points.shape[0]
    return sp.csr_matrix((K.ravel(), (np.repeat(dofs, 9, 1).ravel(), np.tile(dofs, (1, 9)).ravel())),
                         shape=(n, n)).toarray()


# ------------------------------------------------------------------ 1. energy blocks
def _fd_energies(interp, triangles, n, step=1e-4):
    """∫ F_xx² + 2F_xy² + F_yy² over each triangle: centroid rule on n² sub-triangles,
    Hessian by central differences of interp.gradient (one call per shift)."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = (i + j) < n
    down = (i + j) < n - 1
    b1 = np.concatenate([(i[up] + 1 / 3) / n, (i[down] + 2 / 3) / n])
    b2 = np.concatenate([(j[up] + 1 / 3) / n, (j[down] + 2 / 3) / n])
    lam = np.stack([1 - b1 - b2, b1, b2], 1)
    corners = interp.points[triangles]                                   # (T, 3, 2)
    x = np.einsum("pk,tkd->tpd", lam, corners).reshape(-1, 2)
    hx = (interp.gradient(x + [step, 0]) - interp.gradient(x - [step, 0])) / (2 * step)
    hy = (interp.gradient(x + [0, step]) - interp.gradient(x - [0, step])) / (2 * step)
    density = (hx[:, 0] ** 2 + hy[:, 1] ** 2 + hx[:, 1] ** 2 + hy[:, 0] ** 2).reshape(len(triangles), -1)
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    return density.mean(axis=1) * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / 2


@pytest.mark.parametrize("scheme", ["sextic", "quintic"])
def test_energy_blocks_match_finite_difference_quadrature(scheme):
    rng = np.random.default_rng(7)
    pts = np.array([[0, 0], [1, 0.1], [0.3, 1.2], [1.4, 1.1], [0.9, -0.8]])
    tri = np.array([[0, 1, 2], [1, 3, 2], [0, 4, 1]])
    f, g = rng.normal(size=5), rng.normal(size=(5, 2))
    interp = RSDInterpolator(pts, f, g, tri, scheme=scheme)
    directions = rng.normal(size=interp.edges.shape)            # not the unit normals
    interp = RSDInterpolator(pts, f, g, tri, scheme=scheme, directions=directions)
    K = energy_blocks(pts, tri, directions, scheme)
    u = np.zeros(15)
    u[0::3], u[1::3], u[2::3] = f, g[:, 0], g[:, 1]
    coarse, fine = _fd_energies(interp, tri, 60), _fd_energies(interp, tri, 120)
    reference = (4 * fine - coarse) / 3                           # Richardson: error ∝ n⁻²
    for t, d in enumerate(local_dofs(tri)):
        assert u[d] @ K[t] @ u[d] == pytest.approx(reference[t], rel=1e-6)
        assert np.allclose(K[t], K[t].T)
        assert np.linalg.eigvalsh(K[t]).min() > -1e-9 * np.abs(K[t]).max()


@pytest.mark.parametrize("scheme", ["sextic", "quintic", "ex39b"])
def test_structured_blocks_equal_the_plain_product(scheme):
    """block_energy takes M = diag(ρ) P V apart; block_energy_dense forms M^T E M from the
    9 unit-data calls of rsd.triangle_coefficients."""
    from c1mesh.engine.schemes import get_scheme
    from c1mesh.stages.smoothing_energy import block_energy, block_energy_dense, energy_tensor
    rng = np.random.default_rng(3)
    corners = rng.normal(size=(50, 3, 2))
    directions = rng.normal(size=(50, 3, 2))
    Q = energy_tensor(get_scheme(scheme))
    want = block_energy_dense(corners, directions, Q)
    got = block_energy(corners, directions, Q)
    assert np.abs(got - want).max() < 1e-12 * np.abs(want).max()


def test_non_polynomial_scheme_is_refused():
    import c1mesh.engine.schemes as schemes
    s = schemes.SEXTIC
    custom = ShapeTuple("callables", s.psi0, s.dpsi0, s.psi1, s.dpsi1, s.chi0, s.dchi0, s.chi1, s.dchi1)
    pts, tri, h = grid_mesh(4)
    with pytest.raises(SchemeNotPolynomialError, match="polynomial"):
        smooth_fit(pts, tri, SmoothingData(pts[:, 0], spacing=h),
                   SmoothingControl(strength=1.0, scheme=custom))


# ------------------------------------------------- 2. λ → 0 interpolates, min energy
def test_small_strength_interpolates_with_minimum_energy_gradients():
    pts, tri, h = grid_mesh(12, seed=3)
    z = surface(pts)
    fit = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=1e-9))
    assert np.abs(fit.values - z).max() < 1e-6 * np.abs(z).max()
    # Optimality at fixed f = z: the gradient block solves K_gg g = −K_gf f.
    K = assembled(pts, tri)
    f_idx = np.arange(0, K.shape[0], 3)
    g_idx = np.setdiff1d(np.arange(K.shape[0]), f_idx)
    g = np.linalg.solve(K[np.ix_(g_idx, g_idx)], -K[np.ix_(g_idx, f_idx)] @ z)
    want = np.stack([g[0::2], g[1::2]], 1)
    assert np.abs(fit.gradients - want).max() < 1e-4 * np.abs(want).max()
    # Qualitatively like matplotlib's minimum-energy (reduced HCT) gradients away from the
    # boundary. Theirs are second-order accurate, ours first order (Ψ0'' = 0 at the
    # vertices: the RSD spline has no curvature there; docs/smoothing.md), so the check is
    # closeness to both the truth and theirs, and convergence under refinement.
    from matplotlib.tri import CubicTriInterpolator, Triangulation
    errors = []
    for m in (12, 20):
        pts, tri, h = grid_mesh(m, seed=3)
        z = surface(pts)
        ours = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=1e-9)).gradients
        mpl = CubicTriInterpolator(Triangulation(pts[:, 0], pts[:, 1], tri), z, kind="min_E")
        theirs = np.stack(mpl.gradient(pts[:, 0], pts[:, 1]), 1)
        truth = surface_gradient(pts)
        inner = (pts.min(1) > 2 * h) & (pts.max(1) < 1 - 2 * h)
        scale = np.sqrt(np.mean(truth ** 2))
        rel = lambda a, b: np.sqrt(np.mean((a - b)[inner] ** 2)) / scale  # noqa: E731
        assert rel(ours, truth) < 0.08 and rel(theirs, truth) < 0.01 and rel(ours, theirs) < 0.08
        errors.append(rel(ours, truth))
    assert errors[1] < 0.75 * errors[0]


# ----------------------------------------------------------- 3. affine reproduction
@pytest.mark.parametrize("strength", [1e-6, 1.0, 1e3, "auto"])
def test_affine_data_are_reproduced(strength):
    pts, tri, h = grid_mesh(10, seed=1)
    z = 2.0 + 0.7 * pts[:, 0] - 1.3 * pts[:, 1]
    fit = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=strength))
    assert np.abs(fit.values - z).max() < 1e-8
    assert np.abs(fit.gradients - [0.7, -1.3]).max() < 1e-6
    assert fit.residual_max < 1e-8


def test_affine_data_at_points_off_the_vertices():
    rng = np.random.default_rng(2)
    pts, tri, h = grid_mesh(8, seed=2)
    xy = rng.uniform(0, 1, (400, 2))
    z = -1.0 + 0.3 * xy[:, 0] + 2.0 * xy[:, 1]
    fit = smooth_fit(pts, tri, SmoothingData(z, spacing=h / 2, xy=xy), SmoothingControl(strength=1.0))
    assert np.abs(fit.values - (-1.0 + 0.3 * pts[:, 0] + 2.0 * pts[:, 1])).max() < 1e-8
    assert np.abs(fit.gradients - [0.3, 2.0]).max() < 1e-6


# ------------------------------------------------------ 4. noisy analytic surface
def _held_out_rms(pts, tri, fit, rng):
    xy = rng.uniform(0.05, 0.95, (3000, 2))
    interp = RSDInterpolator(pts, fit.values, fit.gradients, tri)
    return float(np.sqrt(np.nanmean((interp(xy) - surface(xy)) ** 2)))


def test_auto_smoothing_beats_interpolation_and_raw_data():
    pts, tri, h = grid_mesh(30, seed=4)
    rng = np.random.default_rng(5)
    sigma = 0.05
    z = surface(pts) + rng.normal(0, sigma, pts.shape[0])
    auto = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength="auto"))
    exact = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=1e-9))
    auto_rms, exact_rms = _held_out_rms(pts, tri, auto, rng), _held_out_rms(pts, tri, exact, rng)
    assert auto_rms < 0.8 * sigma and auto_rms < 0.8 * exact_rms
    assert len(auto.cv_curve) > 8 and min(r for _, r in auto.cv_curve) == pytest.approx(
        dict(auto.cv_curve)[auto.strength])
    assert interior_or_at_limit(auto) == "interior"       # white noise on a smooth surface: a finite best
    assert 3 < auto.edf < pts.shape[0]


def test_the_search_chooses_a_strength_within_1_percent_of_the_curves_lowest(monkeypatch):
    """The coarse grid and its REFINE_STEPS golden-section steps choose an s whose
    cross-validation score is within 1 % of the lowest of the same score (the same folds
    and system) on a scan of 36 strengths from 1e-3 to 1e4, brute force."""
    import c1mesh.stages.smoothing as sm

    pts, tri, h = grid_mesh(24, seed=7)
    z = surface(pts) + np.random.default_rng(7).normal(0, 0.05, len(pts))
    searched = []
    real = sm._search
    monkeypatch.setattr(sm, "_search", lambda *args: searched.append(args) or real(*args))
    fit = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength="auto"))
    problem, folds, mu, method, seed, keep, lowest = searched[0]
    assert keep is None and problem.points.shape[0] <= sm.SEARCH_VERTICES     # the search ran on the whole problem
    assert lowest == sm.SEARCH_LIMITS[0]                  # no least strength: the vertices are the points
    extent = np.ptp(problem.data_xy, axis=0)
    block = min(sm.CV_BLOCK, max(float(np.sqrt(extent[0] * extent[1] / (4 * folds))), 1.0))
    fold = sm.fold_of(problem.data_xy, folds, block, seed)
    system = problem.system()
    scan = [sm.cv_score(problem, system, 10.0 ** e, fold, folds, mu, method) for e in np.linspace(-3, 4, 36)]
    # the report's curve is in heights: the normalised score times Z, the RMS of the data
    # about their plane (smooth_fit's height unit)
    normalised = sm.cv_score(problem, system, fit.strength, fold, folds, mu, method)
    centred = (pts - pts.mean(axis=0)) / h
    plane = sm.weighted_plane(centred, z, np.ones(z.size))
    Z = np.sqrt(np.mean((z - plane[0] - centred @ plane[1:]) ** 2))
    assert dict(fit.cv_curve)[fit.strength] == pytest.approx(normalised * Z, rel=1e-12)
    assert normalised <= 1.01 * min(scan)


def interior_or_at_limit(fit) -> str:
    """'interior' when fit.strength is an interior minimum of its CV curve (a lower score
    than its neighbours on both sides among the s tried), 'low limit' / 'high limit' when
    it is the smallest / largest s tried and that s is the documented limit, 1e-6 / 1e7
    (docs/smoothing.md) and the fit says the limit was reached; AssertionError otherwise."""
    curve = sorted(fit.cv_curve)
    s = [pair[0] for pair in curve]
    i = s.index(fit.strength)
    if 0 < i < len(s) - 1:
        assert curve[i - 1][1] > curve[i][1] < curve[i + 1][1], curve
        assert fit.search_limit_reached is False
        return "interior"
    assert fit.search_limit_reached is True, curve
    assert fit.strength == pytest.approx(1e-6 if i == 0 else 1e7, rel=1e-12), curve
    return "low limit" if i == 0 else "high limit"


@pytest.mark.parametrize("seed", [0, 1])
def test_exact_data_search_below_the_grid_until_the_curve_turns(seed):
    """Data sampled exactly from an analytic surface want as little smoothing as the
    cross-validation can tell: the best s lies below the grid's lowest, 1e-3, so the
    search must go on down until its curve turns (or say that it reached its limit)."""
    pts, tri, h = grid_mesh(30, seed=seed)
    fit = smooth_fit(pts, tri, SmoothingData(surface(pts), spacing=h), SmoothingControl(strength="auto"))
    assert fit.strength < 1e-3 and min(s for s, _ in fit.cv_curve) < 1e-3
    interior_or_at_limit(fit)
    assert min(s for s, _ in fit.cv_curve) >= 1e-6 * (1 - 1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_pure_noise_on_a_plane_searches_up_to_its_limit_and_says_so(seed):
    """Heavy noise (σ 10 times the plane's rise over the square) on a plane: the truth is
    the plane, which only s → ∞ gives, beyond the grid's highest s, 1e4. The CV curve
    falls all the way, so the search goes on up to its limit, 1e7, and reports it; the
    fit is then the plane, within the error of the least-squares plane of the points."""
    pts, tri, h = grid_mesh(40, seed=seed)
    rng = np.random.default_rng(seed + 10)
    plane = 2.0 + 0.3 * pts[:, 0] - 0.5 * pts[:, 1]
    fit = smooth_fit(pts, tri, SmoothingData(plane + rng.normal(0, 5.0, pts.shape[0]), spacing=h),
                     SmoothingControl(strength="auto"))
    assert interior_or_at_limit(fit) == "high limit"
    assert max(s for s, _ in fit.cv_curve) == pytest.approx(1e7, rel=1e-12)
    # the least-squares plane of n points with noise σ is off by about σ sqrt(3 / n) at its points
    assert np.sqrt(np.mean((fit.values - plane) ** 2)) < 3 * 5.0 * np.sqrt(3 / pts.shape[0])


def test_auto_smoothing_with_thinned_vertices():
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 1, (4000, 2))
    sigma = 0.05
    z = surface(xy) + rng.normal(0, sigma, xy.shape[0])
    cell = np.floor(xy / 0.05).astype(np.int64)
    keep = np.sort(np.unique(cell[:, 0] * 1000 + cell[:, 1], return_index=True)[1])   # a point per 0.05 cell
    from scipy.spatial import Delaunay
    pts = xy[keep]
    tri = Delaunay(pts).simplices
    # drop hull slivers: triangles with an angle above 150°
    c = pts[tri]
    ok = np.ones(tri.shape[0], bool)
    for k in range(3):
        a, b = c[:, (k + 1) % 3] - c[:, k], c[:, (k + 2) % 3] - c[:, k]
        ok &= (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1) > -0.85
    tri = tri[ok]
    fit = smooth_fit(pts, tri, SmoothingData(z, spacing=1 / np.sqrt(4000), xy=xy),
                     SmoothingControl(strength="auto"))
    assert fit.outside > 0                                   # the dropped slivers' points
    truth_rms = _held_out_rms(pts, tri, fit, rng)
    exact = smooth_fit(pts, tri, SmoothingData(z[keep], spacing=0.05), SmoothingControl(strength=1e-9))
    interp = RSDInterpolator(pts, z[keep], exact.gradients, tri)
    q = rng.uniform(0.05, 0.95, (3000, 2))
    interp_rms = float(np.sqrt(np.nanmean((interp(q) - surface(q)) ** 2)))
    assert truth_rms < 0.6 * sigma and truth_rms < 0.6 * interp_rms


# ------------------------------------------------------------- 5. scale invariance
@pytest.mark.parametrize("strength", [0.3, "auto"])
def test_strength_is_scale_invariant(strength):
    pts, tri, h = grid_mesh(16, seed=8)
    rng = np.random.default_rng(9)
    z = surface(pts) + rng.normal(0, 0.05, pts.shape[0])
    w = rng.uniform(0.5, 2.0, pts.shape[0])
    base = smooth_fit(pts, tri, SmoothingData(z, spacing=h, weights=w), SmoothingControl(strength=strength))
    wide = smooth_fit(pts * 1000 + [5e5, 4e6], tri, SmoothingData(z, spacing=h * 1000, weights=w * 7),
                      SmoothingControl(strength=strength))
    tall = smooth_fit(pts, tri, SmoothingData(z * 1000 - 30, spacing=h, weights=w),
                      SmoothingControl(strength=strength))
    for fit, values, gradients in ((wide, base.values, base.gradients / 1000),
                                   (tall, base.values * 1000 - 30, base.gradients * 1000)):
        assert fit.strength == pytest.approx(base.strength, rel=1e-9)
        assert np.abs(fit.values - values).max() < 1e-9 * np.abs(values).max()
        assert np.abs(fit.gradients - gradients).max() < 1e-9 * np.abs(gradients).max()
    assert wide.lam == pytest.approx(base.lam * 1e6 * 7, rel=1e-12)


# ------------------------------------------------------- effective degrees of freedom
def test_edf_matches_the_exact_hat_matrix_trace():
    pts, tri, h = grid_mesh(9, seed=10)
    s = 0.5
    fit = smooth_fit(pts, tri, SmoothingData(pts[:, 0] ** 2, spacing=h), SmoothingControl(strength=s))
    # Exact trace in the normalised units the fit uses (lengths / h, unit weights).
    K = assembled((pts - pts.mean(0)) / h, tri)
    n = pts.shape[0]
    S = s * K
    S[np.arange(0, 3 * n, 3), np.arange(0, 3 * n, 3)] += 1.0
    Sinv = np.linalg.inv(S)
    exact = float(np.trace(Sinv[0::3, 0::3]))
    assert fit.edf == pytest.approx(exact, rel=3 * np.sqrt(2 / (4 * exact)))


@pytest.mark.parametrize("method", available_solvers())
def test_a_factor_solves_several_right_hand_sides_as_numpy_does(method):
    """Factor.solve of k columns at once is numpy's dense solve of each, and hat_trace (its
    probes solved together) is the mean of vᵀ H v over the same Rademacher probes v, with
    H = A S⁻¹ Aᵀ W formed densely."""
    pts, tri, h = grid_mesh(8, seed=21)
    npts = (pts - pts.mean(0)) / h
    n = len(pts)
    table = edge_table(tri, n)
    K = assemble_energy(npts, tri, triangle_directions(npts, tri, table.tri_edge, None, table.edges),
                        get_scheme("sextic"))
    w = np.random.default_rng(22).uniform(0.5, 1.5, n)
    system = System(K, None, np.zeros(n))
    S, _ = system.matrix(0.7, w, 0.0)
    B = np.random.default_rng(23).normal(size=(3 * n, 4))
    factor = Factor(S, method)
    dense = np.linalg.solve(S.toarray(), B)
    X = factor.solve(B)
    assert X.shape == B.shape
    np.testing.assert_allclose(X, dense, rtol=0, atol=1e-8 * np.abs(dense).max())
    for k in range(B.shape[1]):
        np.testing.assert_allclose(factor.solve(B[:, k]), dense[:, k], rtol=0, atol=1e-8 * np.abs(dense).max())
    H = np.linalg.inv(S.toarray())[0::3, 0::3] * w[None, :]
    rng = np.random.default_rng(5)
    V = [rng.choice(np.array([-1.0, 1.0]), size=n) for _ in range(3)]
    exact = np.mean([v @ H @ v for v in V])
    assert hat_trace(system, factor, w, 3, 5) == pytest.approx(exact, rel=1e-8)


def test_gradient_data_pull_the_gradients():
    pts, tri, h = grid_mesh(10, seed=11)
    rng = np.random.default_rng(12)
    z = surface(pts) + rng.normal(0, 0.05, pts.shape[0])
    truth = surface_gradient(pts)
    plain = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=1e-6))
    pulled = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=1e-6),
                        prior=GradientPrior(truth, weight=1e6))
    assert np.abs(pulled.gradients - truth).max() < 1e-3 * np.abs(truth).max()
    assert np.abs(plain.gradients - truth).max() > 10 * np.abs(pulled.gradients - truth).max()


# ------------------------------------------------------------- 6. parse and errors
def test_parse_strength():
    assert parse_strength("off") is None
    assert parse_strength(" AUTO ") == "auto"
    assert parse_strength("0.25") == 0.25
    for bad in ("0", "-1", "nan", "inf", "lots", ""):
        with pytest.raises(SmoothingError, match="positive number"):
            parse_strength(bad)


def test_unusable_input_is_refused():
    pts, tri, h = grid_mesh(4)
    z = pts[:, 0]
    with pytest.raises(SmoothingError):
        smooth_fit(pts, tri, SmoothingData(z[:-1], spacing=h), SmoothingControl(strength=1.0))
    with pytest.raises(SmoothingError):
        smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=-1.0))
    with pytest.raises(SmoothingError):
        smooth_fit(pts, tri, SmoothingData(z, spacing=0.0), SmoothingControl(strength=1.0))
    with pytest.raises(SmoothingError):
        smooth_fit(pts, tri, SmoothingData(z, spacing="wide"), SmoothingControl(strength=1.0))
    with pytest.raises(SmoothingError):
        smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength="lots"))
    with pytest.raises(SmoothingError):
        smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=1.0),
                   directions=np.zeros((3, 2)))
    with pytest.raises(SmoothingError):
        smooth_fit(pts, tri, SmoothingData(z, spacing=h, weights=np.zeros_like(z)),
                   SmoothingControl(strength=1.0))


def test_as_dict_is_json_ready():
    import json
    pts, tri, h = grid_mesh(6)
    fit = smooth_fit(pts, tri, SmoothingData(pts[:, 0] ** 2, spacing=h), SmoothingControl(strength=1.0))
    assert isinstance(fit, SmoothFit)
    d = json.loads(json.dumps(fit.as_dict()))
    assert d["strength"] == 1.0 and d["cv_curve"] == [] and "values" not in d
    assert d["search_limit_reached"] is None                 # no search: s was given


def test_data_rows_are_the_interpolator_with_limiter_directions():
    """With data off the vertices and the limiter's edge directions, the reported
    residuals are those of RSDInterpolator built from the fit (same directions)."""
    from scipy.spatial import Delaunay
    from c1mesh.engine.topology import edge_table
    from c1mesh.stages.limiter import edge_directions
    rng = np.random.default_rng(13)
    pts = rng.uniform(0, 1, (150, 2))
    tri = Delaunay(pts).simplices
    u, _ = edge_directions(pts, tri, edge_table(tri, pts.shape[0]))
    xy = rng.uniform(0.1, 0.9, (600, 2))
    z = surface(xy) + rng.normal(0, 0.05, xy.shape[0])
    fit = smooth_fit(pts, tri, SmoothingData(z, spacing=1 / np.sqrt(600), xy=xy), SmoothingControl(strength=0.5),
                     directions=u)
    interp = RSDInterpolator(pts, fit.values, fit.gradients, tri, directions=u)
    r = z - interp(xy)
    assert fit.outside == 0
    assert fit.residual_rms == pytest.approx(np.sqrt(np.mean(r ** 2)), rel=1e-9)
    assert fit.residual_max == pytest.approx(np.abs(r).max(), rel=1e-9)


@pytest.mark.parametrize("simplicial", [True, False])
def test_simplicial_and_supernodal_factors_solve_the_same_system(monkeypatch, simplicial):
    """Below SIMPLICIAL_BELOW unknowns CHOLMOD factors simplicially, else by its own choice:
    either factor solves an SPD system to rounding (numpy's dense solve of the same
    matrix), and the analysis is asked for that mode."""
    pytest.importorskip("sksparse.cholmod")
    import sksparse.cholmod as cholmod

    import c1mesh.stages.smoothing_system as system

    monkeypatch.setattr(system, "SIMPLICIAL_BELOW", 10 ** 9 if simplicial else 0)
    asked = []
    real = cholmod.analyze
    monkeypatch.setattr(cholmod, "analyze", lambda A, **kw: asked.append(kw.get("mode")) or real(A, **kw))
    S = sp.random(60, 60, density=0.1, random_state=4)
    S = (S @ S.T + 60 * sp.identity(60)).tocsr()
    b = np.random.default_rng(4).normal(size=60)
    x = Factor(S, "cholmod").solve(b)
    np.testing.assert_allclose(x, np.linalg.solve(S.toarray(), b), rtol=1e-12, atol=1e-12)
    assert asked == ["simplicial" if simplicial else "auto"]


def test_large_systems_ordered_by_metis_solve_the_same_fit(monkeypatch):
    """From METIS_FROM unknowns the vertices are renumbered by METIS's order of the vertex
    graph, CHOLMOD factors the system in that order, and the fit is the default ordering's
    to rounding, in the input's vertex order."""
    pytest.importorskip("sksparse.cholmod")
    import sksparse.cholmod as cholmod

    import c1mesh.stages.smoothing_system as system

    pts, tri, h = grid_mesh(40, seed=3)
    z = surface(pts) + np.random.default_rng(3).normal(0, 0.05, len(pts))
    default = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=0.5))
    asked = []
    real = cholmod.analyze
    monkeypatch.setattr(cholmod, "analyze", lambda A, **kw: asked.append((A.shape, kw)) or real(A, **kw))
    monkeypatch.setattr(system, "METIS_FROM", 0)
    metis = smooth_fit(pts, tri, SmoothingData(z, spacing=h), SmoothingControl(strength=0.5))
    n = len(pts)
    mode = "simplicial" if 3 * n < system.SIMPLICIAL_BELOW else "auto"
    assert asked == [((n, n), {"ordering_method": "metis"}),
                     ((3 * n, 3 * n), {"mode": mode, "ordering_method": "natural"})]
    assert "order" in metis.seconds and "order" not in default.seconds
    np.testing.assert_allclose(metis.values, default.values, rtol=0, atol=1e-9)
    np.testing.assert_allclose(metis.gradients, default.gradients, rtol=0, atol=1e-7)
    assert metis.residual_rms == pytest.approx(default.residual_rms, rel=1e-9)
    assert metis.residual_max == pytest.approx(default.residual_max, rel=1e-9)


def test_a_vertex_order_is_a_permutation_that_keeps_the_fill_low():
    """vertex_order is a permutation of the vertices, and the Cholesky factor of the energy
    in that order is no fuller than CHOLMOD's own METIS ordering of the unknowns (10%
    slack) and far sparser than the natural order of a shuffled numbering."""
    pytest.importorskip("sksparse.cholmod")
    from sksparse.cholmod import analyze

    import c1mesh.stages.smoothing_system as system

    pts, tri, _ = grid_mesh(40, seed=4)
    shuffle = np.random.default_rng(4).permutation(len(pts))
    rank = np.argsort(shuffle)
    pts, tri = pts[shuffle], rank[tri]
    S = sp.csc_matrix(assembled(pts, tri)) + sp.identity(3 * len(pts), format="csc")
    assert system.vertex_order(tri, len(pts)) is None        # below METIS_FROM
    system_from, system.METIS_FROM = system.METIS_FROM, 0
    try:
        order = system.vertex_order(tri, len(pts))
    finally:
        system.METIS_FROM = system_from
    assert np.array_equal(np.sort(order), np.arange(len(pts)))
    unknowns = (3 * order[:, None] + np.arange(3)).ravel()
    ordered = S[unknowns][:, unknowns].tocsc()

    def fill(matrix, method):
        return analyze(matrix, ordering_method=method).cholesky(matrix).L().nnz

    ours, cholmods, natural = fill(ordered, "natural"), fill(S, "metis"), fill(S, "natural")
    assert ours <= 1.1 * cholmods
    assert ours < natural / 3


def test_a_held_out_vertex_is_held_out_with_its_gradient_datum():
    """Cross-validation over vertex data leaves a held-out vertex's gradient datum out with
    its height: gradients fitted to the heights carry the held-out heights, and kept in they
    made the CV prefer weaker smoothing. So a fold's solution does not change when the
    gradient data of its held-out vertices do, while the full fit's does."""
    from c1mesh.stages.smoothing_system import System, solve

    pts, tri, _ = grid_mesh(12, seed=5)
    K = sp.csr_matrix(assembled(pts, tri))
    z = surface(pts)
    held_out = (pts[:, 0] > 0.3) & (pts[:, 0] < 0.6) & (pts[:, 1] > 0.3) & (pts[:, 1] < 0.6)
    w = np.where(held_out, 0.0, 1.0)
    gradients = surface_gradient(pts)
    spoiled = gradients.copy()
    spoiled[held_out] += 5.0
    mask = np.ones(len(pts))
    fold = [solve(System(K, None, z, mask, g), 0.1, w, 1.0, "superlu", held_out=held_out)[0]
            for g in (gradients, spoiled)]
    full = [solve(System(K, None, z, mask, g), 0.1, w, 1.0, "superlu")[0] for g in (gradients, spoiled)]
    assert np.array_equal(fold[0], fold[1])
    assert np.abs(full[0] - full[1]).max() > 0.1


def test_the_window_centre_breaks_distance_ties_by_the_lower_x_then_y():
    """On a lattice an anchor is often equally near several nodes: nearest_to_anchors
    takes the lowest x, then the lowest y, among them (checked by brute force), in any
    order of the points."""
    import c1mesh.stages.smoothing as sm

    i, j = np.meshgrid(np.arange(6.0), np.arange(5.0), indexing="ij")
    nodes = np.stack([i.ravel(), j.ravel()], 1)
    anchors = np.array([[2.5, 2.5], [3.0, 1.5], [0.5, 4.0], [10.0, 10.0]])
    for order in (np.arange(len(nodes)), np.random.default_rng(1).permutation(len(nodes))):
        rows = sm.nearest_to_anchors(nodes[order], anchors)
        for anchor, row in zip(anchors, rows):
            d2 = ((nodes - anchor) ** 2).sum(axis=1)
            best = min(range(len(nodes)), key=lambda k: (d2[k], nodes[k, 0], nodes[k, 1]))
            assert tuple(row) == (d2[best], nodes[best, 0], nodes[best, 1])
    assert tuple(sm.nearest_to_anchors(nodes, anchors)[0, 1:]) == (2.0, 2.0)


def test_the_search_windows_depend_only_on_the_survey_points():
    """SearchWindows: the whole mesh up to SEARCH_VERTICES points; beyond, one square on the
    point nearest each anchor of the bounding box (brute force here), of the side that
    holds SEARCH_VERTICES / 9 of evenly spread points, whatever the points' order; and the reduce
    of any split of the points into parts (the tiles of a survey) gives the same centres."""
    import c1mesh.stages.smoothing as sm

    rng = np.random.default_rng(3)
    assert sm.search_windows(rng.uniform(0, 10, (sm.SEARCH_VERTICES, 2))).whole
    xy = rng.uniform([100, -50], [400, 250], (sm.SEARCH_VERTICES + 500, 2))
    windows = sm.search_windows(xy)
    lower, upper = xy.min(axis=0), xy.max(axis=0)
    side = np.sqrt(np.prod(upper - lower) * (sm.SEARCH_VERTICES // len(sm.WINDOW_ANCHORS)) / len(xy))
    assert windows.side == pytest.approx(side, rel=0.05)
    expected = []
    for fx, fy in sm.WINDOW_ANCHORS:
        anchor = lower + np.array([fx, fy]) * (upper - lower)
        best = min(range(len(xy)), key=lambda i: (xy[i, 0] - anchor[0]) ** 2 + (xy[i, 1] - anchor[1]) ** 2)
        expected.append((xy[best, 0], xy[best, 1]))
    assert windows.centres == tuple(expected)
    shuffled = xy[rng.permutation(len(xy))]
    assert sm.search_windows(shuffled) == windows
    anchors = sm.window_anchors(lower, upper)
    parts = np.array_split(shuffled, 7) + [np.empty((0, 2))]
    summaries = [sm.nearest_to_anchors(part, anchors) for part in parts[::-1]]
    assert sm.windows_at(sm.reduce_nearest(summaries), windows.side) == windows
    inside = windows.holding(xy)
    for x, y in windows.centres:
        near = (np.abs(xy[:, 0] - x) <= windows.side / 2) & (np.abs(xy[:, 1] - y) <= windows.side / 2)
        assert inside[near].all()
    assert abs(inside.sum() - sm.SEARCH_VERTICES) < 0.1 * sm.SEARCH_VERTICES      # evenly spread: about that many


def test_a_charts_search_windows_hold_its_share_of_the_vertices():
    """search_windows with a budget: the whole mesh up to the budget, beyond it nine squares
    holding about that many evenly spread points; a perspective chart's budget is
    CHART_SEARCH_SHARE of its vertices, never below a survey's SEARCH_VERTICES nor above
    CHART_SEARCH_MOST."""
    import c1mesh.stages.smoothing as sm

    assert sm.chart_search_vertices(1000) == sm.SEARCH_VERTICES
    assert sm.SEARCH_VERTICES < sm.chart_search_vertices(209_029) == int(sm.CHART_SEARCH_SHARE * 209_029)
    assert sm.chart_search_vertices(209_029) < sm.CHART_SEARCH_MOST
    assert sm.chart_search_vertices(10_000_000) == sm.CHART_SEARCH_MOST
    rng = np.random.default_rng(5)
    xy = rng.uniform([0, 0], [640, 480], (120_000, 2))
    budget = 24_000
    assert sm.search_windows(xy[:budget], budget).whole
    windows = sm.search_windows(xy, budget)
    assert len(windows.centres) == len(sm.WINDOW_ANCHORS)
    assert abs(windows.holding(xy).sum() - budget) < 0.1 * budget
    assert windows.side > sm.search_windows(xy).side
