"""The RSD spline on one triangle as 21 basis functions of λ times 21 coefficients.

rsd-math.md, "One triangle": with barycentric weights λ = (λ1, λ2, λ3), G_q = ∇λ_q,
g_ki = A_k·(p_i − p_k) and r_ln = G_l·u_n / G_n·u_n,

    F(λ) = Σ_k Ψ0(λ_k) f_k + Σ_k Σ_{i≠k} Ψ1(λ_k) λ_i g_ki
           − Σ_(l,m,n) r_ln [ f_l χ0(λ_l,λ_m,λ_n) + g_lm χ1(λ_l,λ_m,λ_n) ],     (1.3)

and ∇F(x) = Σ_q (∂F/∂λ_q) G_q. The 21 basis functions depend on λ only, so at a fixed
pattern of barycentric points they are the same matrix for every triangle: the values of a
whole refined mesh are one product coefficients (T × 21) @ basis (21 × P).

Layout of the 21 columns (indices local to a triangle, vertices 0, 1, 2):
  0..2    Ψ0(λ_k)                  coefficient f_k
  3..8    Ψ1(λ_k) λ_i, (k,i) in PAIRS   coefficient g_ki
  9..14   −χ0(λ_l, λ_m, λ_n), PERMS     coefficient r_ln f_l
  15..20  −χ1(λ_l, λ_m, λ_n), PERMS     coefficient r_ln g_lm
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.engine.schemes import ShapeTuple
from c1mesh.core.threads import parallel_blocks
from c1mesh.engine import _rsd as kernel

PAIRS = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))                    # (k, i), i ≠ k
PERMS = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))  # (l, m, n)
N_BASIS = 21


def barycentric_gradients(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """G_q = ∇λ_q for each triangle, and twice the signed areas.

    corners: (T, 3, 2) vertex coordinates. Returns G (T, 3, 2) and det (T,), where
    det = cross(p1 − p0, p2 − p0) (> 0 for counter-clockwise triangles) and
    G_k = perp(p_{k+1} − p_{k+2}) / det, so that G_k·(p_k − p_j) = 1 for j ≠ k.
    Degenerate triangles (det = 0) get G = 0; callers reject them. (The kernel's
    triangle_gradients, its corners numbered 3t, 3t + 1, 3t + 2.)
    """
    T = corners.shape[0]
    G, det = np.empty((T, 3, 2)), np.empty(T)
    kernel.triangle_gradients(np.ascontiguousarray(corners, dtype=np.float64).reshape(3 * T, 2),
                              _own_corners(T), G, det, 0, T)
    return G, det


def triangle_coefficients(corners: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                          directions: np.ndarray, G: np.ndarray) -> np.ndarray:
    """The (T, 21) coefficient matrix of every triangle (column layout in the module doc).

    corners (T, 3, 2), values f (T, 3), gradients A (T, 3, 2), directions u (T, 3, 2) where
    u_k belongs to the edge opposite vertex k, G (T, 3, 2) from barycentric_gradients.
    `mesh_coefficients` with each triangle's corners and edges its own.
    """
    T = corners.shape[0]
    rows = np.empty((3 * T, 5))                                   # x, y, f, fx, fy
    rows[:, :2] = np.reshape(corners, (3 * T, 2))
    rows[:, 2] = np.reshape(values, 3 * T)
    rows[:, 3:] = np.reshape(gradients, (3 * T, 2))
    own = _own_corners(T)
    C = np.empty((T, N_BASIS))
    kernel.vertex_coefficients(rows, own, 0.0, C, np.empty((T, 3, 2)), np.empty(T), np.empty(0, np.uint8), 0, T)
    kernel.ratio_coefficients(C, np.ascontiguousarray(G, dtype=np.float64),
                              np.ascontiguousarray(directions, dtype=np.float64).reshape(3 * T, 2), own, 0, T)
    return C


def _own_corners(T: int) -> np.ndarray:
    """(T, 3) int64: triangle t's corners (and edges) are rows 3t, 3t + 1, 3t + 2."""
    return np.arange(3 * T, dtype=np.int64).reshape(T, 3)


@dataclass(frozen=True)
class VertexData:
    """The first-order data a spline is built from, one row per vertex: points (N, 2)
    the vertices' coordinates, values (N,) f at them, gradients (N, 2) ∇f at them (in
    units of values per unit of the coordinates). The arrays are held, not copied."""

    points: np.ndarray
    values: np.ndarray
    gradients: np.ndarray


def mesh_coefficients(vertices: VertexData, triangles: np.ndarray, edge_directions: np.ndarray,
                      tri_edge: np.ndarray, chunk: int = 1 << 13, min_sine: float | None = None,
                      threads: int | None = None) -> tuple:
    """Coefficients (T, 21), G (T, 3, 2) and det (T,) of a whole mesh, from per-vertex data.

    vertices: the VertexData (N vertices), triangles (T, 3), edge_directions (E, 2)
    and tri_edge (T, 3) (the edge opposite each local vertex). With ``min_sine`` also
    returns degenerate (T,) bool: ~(|det| > min_sine·|p1 − p0|·|p2 − p0|), i.e. the
    |sin| of the angle at vertex 0 is not above min_sine (NaN counts as degenerate).
    Two passes, `vertex_coefficients` (all that needs no edge directions) then
    `ratio_coefficients`; RSDInterpolator runs the first while it builds the edge table.
    """
    out = vertex_coefficients(vertices, triangles, chunk, min_sine, threads)
    ratio_coefficients(out[0], out[1], edge_directions, tri_edge, chunk, threads)
    return out


def vertex_coefficients(vertices: VertexData, triangles: np.ndarray, chunk: int = 1 << 13,
                        min_sine: float | None = None, threads: int | None = None) -> tuple:
    """First pass of `mesh_coefficients`: C (T, 21) with columns 0..8 filled (9..20 are
    left for `ratio_coefficients`), G, det and, with min_sine, degenerate.

    The kernel (engine/_rsd.pyx) over blocks of `chunk` triangles in the thread knob's
    threads (or ``threads``), the per-vertex data packed in rows (one cache line per
    corner); each triangle's arithmetic is its own, so the bits do not depend on the count.
    """
    T = triangles.shape[0]
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    C, G, det = np.empty((T, N_BASIS)), np.empty((T, 3, 2)), np.empty(T)
    degenerate = np.empty(T if min_sine is not None else 0, dtype=bool)
    vertex = np.empty((vertices.points.shape[0], 5))              # x, y, f, fx, fy
    vertex[:, :2], vertex[:, 2], vertex[:, 3:] = vertices.points, vertices.values, vertices.gradients
    flags = degenerate.view(np.uint8)
    sine = 0.0 if min_sine is None else float(min_sine)
    parallel_blocks(lambda part: kernel.vertex_coefficients(vertex, tri, sine, C, G, det, flags,
                                                            part.start, part.stop),
                    T, chunk, threads)
    return (C, G, det) if min_sine is None else (C, G, det, degenerate)


def ratio_coefficients(C: np.ndarray, G: np.ndarray, edge_directions: np.ndarray,
                       tri_edge: np.ndarray, chunk: int = 1 << 13,
                       threads: int | None = None) -> None:
    """Second pass of `mesh_coefficients`: columns 9..20 of C (T, 21), in place, from its
    columns 0..8, G (T, 3, 2), edge_directions (E, 2) and tri_edge (T, 3); the kernel over
    blocks of `chunk` triangles, as `vertex_coefficients`."""
    directions = np.ascontiguousarray(edge_directions, dtype=np.float64)
    edges = np.ascontiguousarray(tri_edge, dtype=np.int64)
    parallel_blocks(lambda part: kernel.ratio_coefficients(C, G, directions, edges, part.start, part.stop),
                    C.shape[0], chunk, threads)


def basis(scheme: ShapeTuple, lam: np.ndarray) -> np.ndarray:
    """The 21 basis functions at barycentric points lam (P, 3): returns (21, P)."""
    B = np.empty((N_BASIS, lam.shape[0]))
    L = [lam[:, 0], lam[:, 1], lam[:, 2]]
    for k in range(3):
        B[k] = scheme.psi0(L[k])
    for j, (k, i) in enumerate(PAIRS):
        B[3 + j] = scheme.psi1(L[k]) * L[i]
    for j, (l, m, n) in enumerate(PERMS):
        B[9 + j] = -scheme.chi0(L[l], L[m], L[n])
        B[15 + j] = -scheme.chi1(L[l], L[m], L[n])
    return B


def basis_derivatives(scheme: ShapeTuple, lam: np.ndarray) -> np.ndarray:
    """∂B/∂λ_q at barycentric points lam (P, 3): returns (3, 21, P), λ's taken as independent."""
    P = lam.shape[0]
    D = np.zeros((3, N_BASIS, P))
    L = [lam[:, 0], lam[:, 1], lam[:, 2]]
    for k in range(3):
        D[k, k] = scheme.dpsi0(L[k])
    for j, (k, i) in enumerate(PAIRS):
        D[k, 3 + j] = scheme.dpsi1(L[k]) * L[i]
        D[i, 3 + j] += scheme.psi1(L[k])
    for j, (l, m, n) in enumerate(PERMS):
        for offset, dchi in ((9, scheme.dchi0), (15, scheme.dchi1)):
            partials = dchi(L[l], L[m], L[n])
            for slot, q in enumerate((l, m, n)):
                D[q, offset + j] -= partials[slot]
    return D


def gradient_basis(scheme: ShapeTuple, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(∂B/∂λ_0 − ∂B/∂λ_2, ∂B/∂λ_1 − ∂B/∂λ_2), each (21, P).

    Since G_0 + G_1 + G_2 = 0, ∇F = (C @ D0) G_0 + (C @ D1) G_1 with these two matrices:
    two products per gradient instead of three.
    """
    D = basis_derivatives(scheme, lam)
    return D[0] - D[2], D[1] - D[2]


def values_at(scheme: ShapeTuple, C: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """F at m points, each in its own triangle: coefficient rows C (m, 21), lam (m, 3)."""
    return np.einsum("mj,jm->m", C, basis(scheme, lam))


def gradients_at(scheme: ShapeTuple, C: np.ndarray, G: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """∇F (m, 2) at m points: coefficient rows C (m, 21), G (m, 3, 2), lam (m, 3)."""
    D0, D1 = gradient_basis(scheme, lam)
    d0, d1 = np.einsum("mj,jm->m", C, D0), np.einsum("mj,jm->m", C, D1)
    return d0[:, None] * G[:, 0] + d1[:, None] * G[:, 1]
