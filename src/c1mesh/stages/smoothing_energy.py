"""The thin-plate energy of the RSD spline as one 9 × 9 block per triangle (issue 24).

On a triangle the spline is F = basis(λ) · C with 21 coefficients C that are linear in the
9 vertex data d = (f0, f1, f2, ∂x f0, ∂y f0, ∂x f1, ∂y f1, ∂x f2, ∂y f2) once the edge
directions are fixed: C = M d, M (21, 9). `linear_maps` builds M by calling
c1mesh.engine.rsd.triangle_coefficients with the 9 unit data vectors, so it is exactly the
code the interpolator evaluates.

The energy ∫_T F_xx² + 2 F_xy² + F_yy² dx = ||H||_F² integrated, H the Hessian in x, is
d^T K_T d with K_T = M^T E_T M. Since G_0 + G_1 + G_2 = 0 (G_q = ∇λ_q),

    H = Σ_{a,b ∈ {0,1}} R_ab(λ) G_a G_b^T,   R_ab = (∂_a − ∂_2)(∂_b − ∂_2) basis,

and <G_a G_b^T, G_c G_d^T>_F = S_ac S_bd with S = G G^T (2 × 2), so

    E_T = |det| Σ_{abcd} S_ac S_bd Q_abcd,   Q_abcd = Σ_p w_p R_ab(λ_p) R_cd(λ_p)^T  (21 × 21)

with a quadrature rule (λ_p, w_p) of the reference triangle (weights summing to 1/2,
|det| = twice the area). Q is the same for every triangle: 16 fixed 21 × 21 matrices,
computed once per scheme.

Second λ-derivatives: the basis of a polynomial scheme of degree d is a polynomial of
degree d in the three λ's taken as independent, so its first derivatives
(rsd.basis_derivatives, the interpolator's own code) are polynomials of degree d − 1.
`_SecondDerivatives` recovers their monomial coefficients by least squares on random points
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
from c1mesh.engine import rsd
from c1mesh.engine.schemes import ShapeTuple, get_scheme
from c1mesh.engine.topology import edge_table

N_LOCAL = 9
"""Local unknowns of a triangle: f0, f1, f2, then (∂x f_k, ∂y f_k) for k = 0, 1, 2."""

_CHUNK = 1 << 15


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


@lru_cache(maxsize=8)
def _energy_tensor_cached(name: str) -> np.ndarray:
    return _energy_tensor(get_scheme(name))


def energy_tensor(scheme: ShapeTuple) -> np.ndarray:
    """Q (16, 21, 21): Σ_p w_p R_ab(λ_p) R_cd(λ_p)^T, index 8a + 4b + 2c + d (module doc)."""
    try:
        if get_scheme(scheme.name) is scheme:
            return _energy_tensor_cached(scheme.name)
    except C1MeshError:
        pass
    return _energy_tensor(scheme)


def _energy_tensor(scheme: ShapeTuple) -> np.ndarray:
    degree = scheme.degree if scheme.degree is not None else 0
    lam, w = quadrature(max(0, 2 * (degree - 2)))
    D2 = second_derivatives(scheme, lam)
    R = np.empty((2, 2, rsd.N_BASIS, lam.shape[0]))
    for a in range(2):
        for b in range(2):
            R[a, b] = D2[a, b] - D2[a, 2] - D2[2, b] + D2[2, 2]
    Rw = R * w
    Q = np.einsum("abip,cdjp->abcdij", Rw, R).reshape(16, rsd.N_BASIS, rsd.N_BASIS)
    return Q


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


def block_energy(corners: np.ndarray, directions: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(T, 9, 9) energy blocks for triangles corners (T, 3, 2), directions (T, 3, 2)."""
    G, det = rsd.barycentric_gradients(corners)
    M = linear_maps(corners, directions, G)
    G2 = G[:, :2]                                                  # (T, 2, 2): G_0, G_1
    S = np.einsum("tai,tbi->tab", G2, G2)                          # (T, 2, 2)
    weights = np.einsum("tac,tbd->tabcd", S, S).reshape(-1, 16) * np.abs(det)[:, None]
    E = (weights @ Q.reshape(16, -1)).reshape(-1, rsd.N_BASIS, rsd.N_BASIS)
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
    """`energy_blocks` from per-triangle directions dirs (T, 3, 2), in chunks."""
    Q = energy_tensor(scheme)
    T = triangles.shape[0]
    out = np.empty((T, N_LOCAL, N_LOCAL))
    for start in range(0, T, _CHUNK):
        part = slice(start, start + _CHUNK)
        out[part] = block_energy(points[triangles[part]], dirs[part], Q)
    return out


def local_dofs(triangles: np.ndarray) -> np.ndarray:
    """(T, 9) global unknown of each local datum, unknowns interleaved per vertex:
    3v is f_v, 3v + 1 and 3v + 2 its gradient's x and y."""
    t3 = 3 * np.asarray(triangles, dtype=np.int64)
    return np.concatenate([t3, (t3[:, :, None] + np.array([1, 2])).reshape(-1, 6)], axis=1)


__all__ = ["SmoothingError", "SchemeNotPolynomialError", "N_LOCAL", "quadrature",
           "second_derivatives", "energy_tensor", "triangle_directions", "linear_maps",
           "block_energy", "energy_blocks", "energy_blocks_of", "local_dofs"]
