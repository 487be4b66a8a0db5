"""The thin-plate energy of the RSD spline as one 9 × 9 block per triangle (issue 24).

On a triangle the spline is F = basis(λ) · C with 21 coefficients C that are linear in the
9 vertex data d = (f0, f1, f2, ∂x f0, ∂y f0, ∂x f1, ∂y f1, ∂x f2, ∂y f2) once the edge
directions are fixed: C = M d, M (21, 9). `linear_maps` builds M by calling
c1mesh.engine.rsd.triangle_coefficients with the 9 unit data vectors, so it is exactly the
code the interpolator evaluates; `block_energy` (the one used) computes the same numbers
(the ratios r_ln and the edge vectors p_i − p_k) in the kernel _smoothing_energy.pyx, a
triangle at a time, and uses M's structure (see there); `block_energy_dense` is the plain
M^T E_T M.

The energy ∫_T F_xx² + 2 F_xy² + F_yy² dx = ||H||_F² integrated, H the Hessian in x, is
d^T K_T d with K_T = M^T E_T M. Since G_0 + G_1 + G_2 = 0 (G_q = ∇λ_q),

    H = Σ_{a,b ∈ {0,1}} R_ab(λ) G_a G_b^T,   R_ab = (∂_a − ∂_2)(∂_b − ∂_2) basis,

and <G_a G_b^T, G_c G_d^T>_F = S_ac S_bd with S = G G^T (2 × 2), so

    E_T = |det| Σ_{abcd} S_ac S_bd Q_abcd,   Q_abcd = Σ_p w_p R_ab(λ_p) R_cd(λ_p)^T  (21 × 21)

with a quadrature rule (λ_p, w_p) of the reference triangle (weights summing to 1/2,
|det| = twice the area). Q is the same for every triangle: computed once per scheme, and
since R_01 = R_10 it reduces to 6 fixed 21 × 21 matrices (three Hessian modes, their
pairs; `energy_tensor`, `mode_weights`).

Second λ-derivatives: the basis of a polynomial scheme of degree d is a polynomial of
degree d in the three λ's taken as independent, so its first derivatives
(rsd.basis_derivatives, the interpolator's own code) are polynomials of degree d − 1.
`second_derivatives` recovers their monomial coefficients by least squares on random points
of [-1, 1]³, checks the fit is exact to round-off (else the scheme is not a polynomial of
its declared degree and is refused), and differentiates the monomials once more. The
quadrature is the collapsed (Duffy) Gauss–Legendre product rule with n = d − 1
points per direction, exact for the integrand's degree 2(d − 2) plus the Jacobian's 1
(sextic: 5 × 5 = 25 points, exact to degree 9 in the collapsed coordinate).
"""
from __future__ import annotations

from functools import lru_cache
from itertools import product

import numpy as np

from c1mesh.core.errors import C1MeshError
from c1mesh.core.lazy import LazyModule
from c1mesh.core.threads import parallel_blocks
from c1mesh.engine import rsd
from c1mesh.engine.schemes import ShapeTuple, get_scheme
from c1mesh.engine.topology import edge_table
from c1mesh.stages import _smoothing_energy as kernel

sp = LazyModule("scipy.sparse")

N_LOCAL = 9
"""Local unknowns of a triangle: f0, f1, f2, then (∂x f_k, ∂y f_k) for k = 0, 1, 2."""

_CHUNK = 1 << 13


class SmoothingError(C1MeshError, ValueError):
    """Input a smoothing fit cannot use (a one-line message says what to change)."""


class SchemeNotPolynomialError(SmoothingError):
    """The scheme has no (verifiable) polynomial degree, so its energy cannot be integrated
    exactly; the named schemes (sextic, quintic, ex39b) are all polynomial."""


def quadrature(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """A rule exact for polynomials of total ``degree`` on the reference triangle.

    Returns barycentrics lam (P, 3) and weights (P,) summing to 1/2 (the reference area).
    Collapsed Gauss–Legendre: λ1 = s, λ2 = (1 − s) t, Jacobian (1 − s), n points in s and t
    with 2n − 1 >= degree + 1.
    """
    n = max(1, (degree + 2 + 1) // 2)
    x, w = np.polynomial.legendre.leggauss(n)
    s, ws = (x + 1) / 2, w / 2
    S, T = np.meshgrid(s, s, indexing="ij")
    W = np.outer(ws * (1 - s), ws)
    l1, l2 = S.ravel(), ((1 - S) * T).ravel()
    lam = np.stack([1 - l1 - l2, l1, l2], axis=1)
    return lam, W.ravel()


def _monomials(degree: int) -> list[tuple[int, int, int]]:
    return [e for e in product(range(degree + 1), repeat=3) if sum(e) <= degree]


def _evaluate(exps, pts: np.ndarray) -> np.ndarray:
    """(P, n_mono) values of the monomials at pts (P, 3)."""
    return np.stack([pts[:, 0] ** a * pts[:, 1] ** b * pts[:, 2] ** c for a, b, c in exps], axis=1)


def _partial(exps, pts: np.ndarray, r: int) -> np.ndarray:
    """(P, n_mono) values of ∂/∂λ_r of the monomials at pts (P, 3)."""
    cols = []
    for e in exps:
        if e[r] == 0:
            cols.append(np.zeros(pts.shape[0]))
            continue
        lowered = list(e)
        lowered[r] -= 1
        a, b, c = lowered
        cols.append(e[r] * pts[:, 0] ** a * pts[:, 1] ** b * pts[:, 2] ** c)
    return np.stack(cols, axis=1)


def second_derivatives(scheme: ShapeTuple, lam: np.ndarray) -> np.ndarray:
    """∂²basis/∂λ_q∂λ_r at barycentric points lam (P, 3): returns (3, 3, 21, P).

    Exact to round-off for polynomial schemes (module doc); SchemeNotPolynomialError else.
    """
    degree = scheme.degree
    if degree is None or degree < 1:
        raise SchemeNotPolynomialError(
            f"scheme {scheme.name!r} has no polynomial degree; smoothing needs a polynomial "
            "scheme (sextic, quintic or ex39b)")
    exps = _monomials(degree - 1)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1.0, 1.0, size=(4 * len(exps), 3))
    V = _evaluate(exps, pts)
    D = rsd.basis_derivatives(scheme, pts)                        # (3, 21, P)
    rhs = D.reshape(3 * rsd.N_BASIS, -1).T                       # (P, 63)
    coef, *_ = np.linalg.lstsq(V, rhs, rcond=None)
    check = rng.uniform(-1.0, 1.0, size=(64, 3))
    want = rsd.basis_derivatives(scheme, check).reshape(3 * rsd.N_BASIS, -1).T
    miss = float(np.abs(_evaluate(exps, check) @ coef - want).max())
    if not miss <= 1e-8 * (1.0 + float(np.abs(want).max())):
        raise SchemeNotPolynomialError(
            f"scheme {scheme.name!r} is not a polynomial of its declared degree {degree} "
            f"(off by {miss:.3g}); smoothing needs a polynomial scheme")
    coef = coef.reshape(-1, 3, rsd.N_BASIS)                        # (n_mono, q, 21)
    out = np.empty((3, 3, rsd.N_BASIS, lam.shape[0]))
    for r in range(3):
        dr = _partial(exps, lam, r)                                # (P, n_mono)
        out[:, r] = np.einsum("pm,mqb->qbp", dr, coef)
    return 0.5 * (out + out.transpose(1, 0, 2, 3))                # exact ones are symmetric


_MODES = ((0, 0), (0, 1), (1, 1))
"""Hessian modes: H = R_00 G0 G0^T + R_01 (G0 G1^T + G1 G0^T) + R_11 G1 G1^T."""
_PAIRS_OF_MODES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@lru_cache(maxsize=8)
def _energy_tensor_cached(name: str) -> np.ndarray:
    return _energy_tensor(get_scheme(name))


def energy_tensor(scheme: ShapeTuple) -> np.ndarray:
    """Q (6, 21, 21): for the mode pairs (m, n) in _PAIRS_OF_MODES, Σ_p w_p R_m R_n^T
    (+ its transpose when m ≠ n), so that E_T = |det| Σ_k c_k(S) Q_k (`mode_weights`)."""
    if scheme.name in ("sextic", "quintic", "ex39b") and get_scheme(scheme.name) is scheme:
        return _energy_tensor_cached(scheme.name)
    return _energy_tensor(scheme)


def _energy_tensor(scheme: ShapeTuple) -> np.ndarray:
    degree = scheme.degree if scheme.degree is not None else 0
    lam, w = quadrature(max(0, 2 * (degree - 2)))
    D2 = second_derivatives(scheme, lam)
    R = np.stack([D2[a, b] - D2[a, 2] - D2[2, b] + D2[2, 2] for a, b in _MODES])  # (3, 21, P)
    Q = np.einsum("mip,njp->mnij", R * w, R)
    out = np.empty((6, rsd.N_BASIS, rsd.N_BASIS))
    for k, (m, n) in enumerate(_PAIRS_OF_MODES):
        out[k] = Q[m, n] if m == n else Q[m, n] + Q[n, m]
    return out


def mode_weights(G: np.ndarray, det: np.ndarray) -> np.ndarray:
    """(T, 6) |det| <N_m, N_n>_F for the mode pairs, N_0 = G0 G0^T, N_1 = G0 G1^T + G1 G0^T,
    N_2 = G1 G1^T; <G_a G_b^T, G_c G_d^T>_F = S_ac S_bd with S = G G^T."""
    s00 = np.einsum("ti,ti->t", G[:, 0], G[:, 0])
    s01 = np.einsum("ti,ti->t", G[:, 0], G[:, 1])
    s11 = np.einsum("ti,ti->t", G[:, 1], G[:, 1])
    c = np.stack([s00 * s00, 2 * s00 * s01, s01 * s01, 2 * (s00 * s11 + s01 * s01),
                  2 * s01 * s11, s11 * s11], axis=1)
    return c * np.abs(det)[:, None]


def triangle_directions(points: np.ndarray, triangles: np.ndarray, tri_edge: np.ndarray,
                        directions: np.ndarray | None, edges: np.ndarray) -> np.ndarray:
    """Per-triangle edge directions u (T, 3, 2): u_k of the edge opposite local vertex k.

    directions (E, 2) in the order of ``edges`` (the RSDInterpolator's), or None for the
    unit edge normals the interpolator uses by default.
    """
    if directions is None:
        vec = points[edges[:, 1]] - points[edges[:, 0]]
        length = np.sqrt(vec[:, 0] * vec[:, 0] + vec[:, 1] * vec[:, 1])
        directions = np.stack([-vec[:, 1] / length, vec[:, 0] / length], axis=1)
    return directions[tri_edge]


def linear_maps(corners: np.ndarray, directions: np.ndarray, G: np.ndarray) -> np.ndarray:
    """M (T, 21, 9): the coefficients of each triangle as a linear map of its 9 local data.

    corners (T, 3, 2), directions u (T, 3, 2) (u_k opposite vertex k), G (T, 3, 2) from
    rsd.barycentric_gradients. Column j is rsd.triangle_coefficients of the j-th unit datum.
    """
    T = corners.shape[0]
    M = np.empty((T, rsd.N_BASIS, N_LOCAL))
    for j in range(N_LOCAL):
        values, gradients = np.zeros((T, 3)), np.zeros((T, 3, 2))
        if j < 3:
            values[:, j] = 1.0
        else:
            gradients[:, (j - 3) // 2, (j - 3) % 2] = 1.0
        M[:, :, j] = rsd.triangle_coefficients(corners, values, gradients, directions, G)
    return M


# Column layout of rsd's 21 coefficients in terms of the 9 "vertex coefficients"
# c = (f0, f1, f2, g_ki for (k, i) in PAIRS): column r of C is ρ_r c[_GROUP[r]], with
# ρ_r = 1 for r < 9 and ρ_r = r_ln for the ratio columns 9 + j and 15 + j, (l, m, n) =
# PERMS[j] (rsd module doc). _RATIO[r] is 0 for ρ_r = 1, else 1 + j.
_GROUP = np.array(list(range(9)) + [l for l, m, n in rsd.PERMS]
                  + [3 + rsd.PAIRS.index((l, m)) for l, m, n in rsd.PERMS])
_RATIO = np.array([0] * 9 + list(range(1, 7)) * 2)
_MONOMIALS = [(a, b) for a in range(7) for b in range(a, 7)]     # 1, ρ_j, ρ_j ρ_j' (28)
_UPPER = np.triu_indices(9)
_UPPER_FLAT = np.ravel_multi_index(_UPPER, (9, 9))


@lru_cache(maxsize=8)
def _collected_cached(name: str) -> np.ndarray:
    return _collected(energy_tensor(get_scheme(name)))


def _collected(Q: np.ndarray) -> sp.csr_matrix:
    """Z (45, 6 · 28) sparse: the upper triangle of E'_T = P^T diag(ρ) E_T diag(ρ) P (9 × 9, in the vertex coefficients)
    is Σ_k Σ_μ mode_weights_k · μ(ρ) · Z[k, μ] over the 28 monomials μ of degree <= 2 in
    the six ratios, since ρ_r ρ_s is one of them for every pair of columns (r, s)."""
    index = {mono: i for i, mono in enumerate(_MONOMIALS)}
    Z = np.zeros((6, len(_MONOMIALS), 9, 9))
    for r in range(rsd.N_BASIS):
        for s in range(rsd.N_BASIS):
            mono = index[tuple(sorted((_RATIO[r], _RATIO[s])))]
            Z[:, mono, _GROUP[r], _GROUP[s]] += Q[:, r, s]
    Z = Z.reshape(6 * len(_MONOMIALS), 81)
    # E' is symmetric: keep its upper triangle, and only Z's nonzeros (about 6 %).
    Z = Z[:, _UPPER_FLAT].T
    Z[np.abs(Z) <= 1e-14 * np.abs(Z).max()] = 0.0
    return sp.csr_matrix(Z)


def _z_terms(Z: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z's nonzeros as the kernel takes them: rows and columns (int64) and values, ordered
    by their place within their row, then by row (every row's first, every row's second,
    ...). Each row's terms stay in CSR order, so its sum is rounded as scipy's Z @ x
    rounds it, while consecutive terms belong to different rows and their sums can run
    side by side rather than one long chain of dependent additions."""
    counts = np.diff(Z.indptr)
    rows = np.repeat(np.arange(Z.shape[0]), counts)
    place = np.arange(Z.nnz) - np.repeat(Z.indptr[:-1], counts)
    order = np.argsort(place, kind="stable")
    return (rows[order].astype(np.int64), Z.indices[order].astype(np.int64),
            np.ascontiguousarray(Z.data[order], dtype=np.float64))


def _kernel_blocks(points: np.ndarray, triangles: np.ndarray, dirs: np.ndarray,
                   Z: sp.csr_matrix) -> np.ndarray:
    """(T, 9, 9) energy blocks by the kernel (_smoothing_energy.energy_blocks) over blocks
    of _CHUNK triangles in the thread knob's threads; each triangle's arithmetic is its
    own, so the bits do not depend on the thread count."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    dirs = np.ascontiguousarray(dirs, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2 or triangles.ndim != 2 or triangles.shape[1] != 3 \
            or dirs.shape != (triangles.shape[0], 3, 2):
        raise ValueError("points (N, 2), triangles (T, 3) and dirs (T, 3, 2) expected")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= points.shape[0]):
        raise ValueError("triangle vertex indices out of range")
    if Z.shape != (45, 6 * len(_MONOMIALS)) or not Z.has_canonical_format:
        raise ValueError("Z must be _collected's canonical (45, 168) CSR matrix")
    rows, cols, values = _z_terms(Z)
    out = np.empty((triangles.shape[0], N_LOCAL, N_LOCAL))

    def work(part: slice) -> None:
        kernel.energy_blocks(points, triangles, dirs, rows, cols, values,
                             part.start, part.stop, out)
    parallel_blocks(work, triangles.shape[0], _CHUNK)
    return out


def block_energy(corners: np.ndarray, directions: np.ndarray, Q: np.ndarray,
                 Z: sp.csr_matrix | None = None) -> np.ndarray:
    """(T, 9, 9) energy blocks for triangles corners (T, 3, 2), directions (T, 3, 2).

    K_T = M^T E_T M with M = diag(ρ) P V taken apart: E'_T = P^T diag(ρ) E_T diag(ρ) P is
    one sparse product Z (45, 168) @ features (168,) per triangle (`_collected`), then V
    (the identity on f and the components of p_i − p_k on each vertex's gradient) is
    applied by row operations; the kernel _smoothing_energy does it triangle by triangle.
    Same result as `block_energy_dense` to round-off.
    """
    corners = np.asarray(corners, dtype=np.float64)
    T = corners.shape[0]
    triangles = np.arange(3 * T, dtype=np.int64).reshape(T, 3)
    return _kernel_blocks(corners.reshape(-1, 2), triangles, directions,
                          _collected(Q) if Z is None else Z)


def block_energy_dense(corners: np.ndarray, directions: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """`block_energy` the plain way, M^T E_T M with M from `linear_maps` (for tests)."""
    G, det = rsd.barycentric_gradients(corners)
    M = linear_maps(corners, directions, G)
    E = (mode_weights(G, det) @ Q.reshape(6, -1)).reshape(-1, rsd.N_BASIS, rsd.N_BASIS)
    return np.matmul(np.matmul(M.transpose(0, 2, 1), E), M)


def energy_blocks(points, triangles, directions=None, scheme="sextic") -> np.ndarray:
    """The (T, 9, 9) thin-plate energy blocks K_T of the RSD spline on a mesh.

    points (N, 2), triangles (T, 3), directions (E, 2) in RSDInterpolator's edge order or
    None (unit edge normals), scheme a name or ShapeTuple. With the local data d (9,) of a
    triangle (f0, f1, f2, ∂x f0, ∂y f0, ∂x f1, ∂y f1, ∂x f2, ∂y f2),
    d^T K_T d = ∫_T F_xx² + 2 F_xy² + F_yy² dx (units: value² / length²).
    """
    points = np.asarray(points, dtype=float)
    triangles = np.asarray(triangles, dtype=np.int64)
    table = edge_table(triangles, points.shape[0])
    dirs = triangle_directions(points, triangles, table.tri_edge,
                               None if directions is None else np.asarray(directions, float),
                               table.edges)
    return energy_blocks_of(points, triangles, dirs, get_scheme(scheme))


def energy_blocks_of(points: np.ndarray, triangles: np.ndarray, dirs: np.ndarray,
                     scheme: ShapeTuple) -> np.ndarray:
    """`energy_blocks` from per-triangle directions dirs (T, 3, 2): (T, 9, 9)."""
    named = scheme.name in ("sextic", "quintic", "ex39b") and get_scheme(scheme.name) is scheme
    Z = _collected_cached(scheme.name) if named else _collected(energy_tensor(scheme))
    return _kernel_blocks(points, triangles, dirs, Z)


def local_dofs(triangles: np.ndarray) -> np.ndarray:
    """(T, 9) global unknown of each local datum, unknowns interleaved per vertex:
    3v is f_v, 3v + 1 and 3v + 2 its gradient's x and y."""
    t3 = 3 * np.asarray(triangles, dtype=np.int64)
    return np.concatenate([t3, (t3[:, :, None] + np.array([1, 2])).reshape(-1, 6)], axis=1)


__all__ = ["SmoothingError", "SchemeNotPolynomialError", "N_LOCAL", "quadrature",
           "second_derivatives", "energy_tensor", "triangle_directions", "linear_maps",
           "block_energy", "block_energy_dense", "mode_weights", "energy_blocks", "energy_blocks_of", "local_dofs"]
