"""An independent, deliberately plain implementation of the paper's formulas, for tests.

Nothing here is imported from c1mesh: the shape functions are written out by hand with
hand-derived partial derivatives, λ and G come from a 3×3 linear solve, and F follows
(1.3) literally with A_k·(x − p_k) (not the λ-expansion the package uses), its gradient
following (2.4) and the proof of Theorem 3.4.
"""
from __future__ import annotations

import itertools

import numpy as np

PHI = (lambda t: t**3 * (10 - 15 * t + 6 * t**2), lambda t: 30 * t**2 * (1 - t) ** 2)
THETA = (lambda t: t**3 * (4 - 3 * t), lambda t: 12 * t**2 * (1 - t))
CHI0 = (lambda a, b, c: 30 * a**2 * b**2 * c,
        lambda a, b, c: (60 * a * b**2 * c, 60 * a**2 * b * c, 30 * a**2 * b**2))
CHI1_QUINTIC = (lambda a, b, c: 12 * a**2 * b**2 * c,
                lambda a, b, c: (24 * a * b**2 * c, 24 * a**2 * b * c, 12 * a**2 * b**2))
CHI1_SEXTIC = (lambda a, b, c: 30 * a**2 * b**3 * c + 15 * a**2 * b**2 * c**2,
               lambda a, b, c: (60 * a * b**3 * c + 30 * a * b**2 * c**2,
                                90 * a**2 * b**2 * c + 30 * a**2 * b * c**2,
                                30 * a**2 * b**3 + 30 * a**2 * b**2 * c))
CHI1_EX39B = (lambda a, b, c: 30 * a**2 * b**3 * c,
              lambda a, b, c: (60 * a * b**3 * c, 90 * a**2 * b**2 * c, 30 * a**2 * b**3))

TUPLES = {
    "sextic": (PHI, PHI, CHI0, CHI1_SEXTIC),
    "quintic": (PHI, THETA, CHI0, CHI1_QUINTIC),
    "ex39b": (PHI, PHI, CHI0, CHI1_EX39B),
}


def barycentric(p: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """λ (3,) of x in the triangle p (3, 2), and G (3, 2) = ∇λ, by a linear solve."""
    M = np.vstack([p.T, np.ones(3)])              # M @ λ = (x, y, 1)
    Minv = np.linalg.inv(M)
    lam = Minv @ np.array([x[0], x[1], 1.0])
    G = Minv[:, :2]                               # ∂λ/∂(x, y)
    return lam, G


def value_and_gradient(name: str, p, f, A, u, x) -> tuple[float, np.ndarray]:
    """F(x) and ∇F(x) on one triangle: p (3,2), f (3,), A (3,2), u (3,2) (u_k opposite k)."""
    (psi0, dpsi0), (psi1, dpsi1), (chi0, dchi0), (chi1, dchi1) = TUPLES[name]
    lam, G = barycentric(p, x)
    F = 0.0
    dF = np.zeros(2)
    for k in range(3):
        lin = A[k] @ (x - p[k])
        F += psi0(lam[k]) * f[k] + psi1(lam[k]) * lin
        dF += (dpsi0(lam[k]) * f[k] + dpsi1(lam[k]) * lin) * G[k] + psi1(lam[k]) * A[k]
    for l, m, n in itertools.permutations(range(3)):
        r = (G[l] @ u[n]) / (G[n] @ u[n])
        g = A[l] @ (p[m] - p[l])
        t = (lam[l], lam[m], lam[n])
        F -= r * (f[l] * chi0(*t) + g * chi1(*t))
        d0, d1 = dchi0(*t), dchi1(*t)
        for slot, q in enumerate((l, m, n)):
            dF -= r * (f[l] * d0[slot] + g * d1[slot]) * G[q]
    return F, dF
