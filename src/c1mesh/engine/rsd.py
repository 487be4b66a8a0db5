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

PAIRS = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))                    # (k, i), i ≠ k
PERMS = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))  # (l, m, n)
N_BASIS = 21


def barycentric_gradients(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """G_q = ∇λ_q for each triangle, and twice the signed areas.

    corners: (T, 3, 2) vertex coordinates. Returns G (T, 3, 2) and det (T,), where
    det = cross(p1 − p0, p2 − p0) (> 0 for counter-clockwise triangles) and
    G_k = perp(p_{k+1} − p_{k+2}) / det, so that G_k·(p_k − p_j) = 1 for j ≠ k.
    Degenerate triangles (det = 0) get G = 0; callers reject them.
    """
    gx, gy, det = _gradients_soa(*_components(corners))
    return _interleave(gx, gy), det


def triangle_coefficients(corners: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                          directions: np.ndarray, G: np.ndarray) -> np.ndarray:
    """The (T, 21) coefficient matrix of every triangle (column layout in the module doc).

    corners (T, 3, 2), values f (T, 3), gradients A (T, 3, 2), directions u (T, 3, 2) where
    u_k belongs to the edge opposite vertex k, G (T, 3, 2) from barycentric_gradients.
    """
    px, py = _components(corners)
    C = np.empty((N_BASIS, px.shape[1]))
    _vertex_soa(px, py, np.ascontiguousarray(values.T), *_components(gradients), C[:9])
    _ratio_soa(C[:9], *_components(directions), *_components(G), C[9:])
    return np.ascontiguousarray(C.T)


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

    Works on blocks of triangles: per-vertex data packed in rows, so a block is one row
    gather per corner (not five scattered ones), then turned into contiguous component
    arrays; every temporary stays in cache and no full-size (T, 3, 2) gathers are made.
    """
    T = triangles.shape[0]
    C, G, det = np.empty((T, N_BASIS)), np.empty((T, 3, 2)), np.empty(T)
    degenerate = None if min_sine is None else np.empty(T, dtype=bool)
    vertex = np.empty((vertices.points.shape[0], 5))              # x, y, f, fx, fy
    vertex[:, :2], vertex[:, 2], vertex[:, 3:] = vertices.points, vertices.values, vertices.gradients

    def block(part: slice) -> None:
        px, py, f, ax, ay = _gather(vertex, triangles[part])
        gx, gy, det[part] = _gradients_soa(px, py)
        G[part, :, 0], G[part, :, 1] = gx.T, gy.T
        rows = np.empty((9, px.shape[1]))
        _vertex_soa(px, py, f, ax, ay, rows)
        C[part, :9] = rows.T
        if degenerate is not None:
            e1 = np.hypot(px[1] - px[0], py[1] - py[0])
            e2 = np.hypot(px[2] - px[0], py[2] - py[0])
            np.logical_not(np.abs(det[part]) > min_sine * e1 * e2, out=degenerate[part])

    _blocks(block, T, chunk, threads)
    return (C, G, det) if degenerate is None else (C, G, det, degenerate)


def ratio_coefficients(C: np.ndarray, G: np.ndarray, edge_directions: np.ndarray,
                       tri_edge: np.ndarray, chunk: int = 1 << 13,
                       threads: int | None = None) -> None:
    """Second pass of `mesh_coefficients`: columns 9..20 of C (T, 21), in place, from its
    columns 0..8, G (T, 3, 2), edge_directions (E, 2) and tri_edge (T, 3)."""
    directions = np.ascontiguousarray(edge_directions, dtype=np.float64)

    def block(part: slice) -> None:
        ux, uy = _gather(directions, tri_edge[part])
        gx, gy = np.ascontiguousarray(G[part].transpose(2, 1, 0))
        rows = np.empty((12, ux.shape[1]))
        _ratio_soa(np.ascontiguousarray(C[part, :9].T), ux, uy, gx, gy, rows)
        C[part, 9:] = rows.T

    _blocks(block, C.shape[0], chunk, threads)


def _blocks(work, T: int, chunk: int, threads: int | None) -> None:
    """work(slice) for consecutive blocks of `chunk` triangles, in ``threads`` threads
    (default: c1mesh.core.threads.workers()) by c1mesh.core.threads.parallel_blocks: blocks
    are independent and numpy releases the GIL in their gathers and ufuncs (results do not
    depend on the count)."""
    parallel_blocks(work, T, chunk, threads)


def _gather(rows: np.ndarray, index: np.ndarray) -> np.ndarray:
    """rows (N, m) gathered at index (c, 3) -> (m, 3, c) contiguous: component, corner, triangle."""
    return np.ascontiguousarray(np.take(rows, index.T, axis=0).transpose(2, 0, 1))


def _components(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3, 2) -> x (3, T), y (3, T): one transposing copy, then contiguous arithmetic."""
    soa = np.ascontiguousarray(vectors.transpose(2, 1, 0))
    return soa[0], soa[1]


def _interleave(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x, y (3, T) -> (T, 3, 2) contiguous."""
    return np.ascontiguousarray(np.stack([x, y]).transpose(2, 1, 0))


def _gradients_soa(x: np.ndarray, y: np.ndarray):
    """gx, gy (3, c) and det (c,) from corner components x, y (3, c)."""
    det = (x[1] - x[0]) * (y[2] - y[0]) - (y[1] - y[0]) * (x[2] - x[0])
    inv = 1.0 / np.where(det == 0, np.inf, det)
    gx, gy = np.empty_like(x), np.empty_like(y)
    for k in range(3):
        a, b = (k + 1) % 3, (k + 2) % 3
        np.multiply(y[a] - y[b], inv, out=gx[k])
        np.multiply(x[b] - x[a], inv, out=gy[k])
    return gx, gy, det


def _vertex_soa(px, py, f, ax, ay, out) -> None:
    """Rows 0..8 of the coefficients into out (9, c): f_k, then g_ki for (k, i) in PAIRS."""
    out[0:3] = f
    for j, (k, i) in enumerate(PAIRS):
        out[3 + j] = ax[k] * (px[i] - px[k]) + ay[k] * (py[i] - py[k])


def _ratio_soa(vertex, ux, uy, gx, gy, out) -> None:
    """Rows 9..20 into out (12, c) from rows 0..8 (vertex), directions and G components:
    r_ln f_l and r_ln g_lm for (l, m, n) in PERMS."""
    g = {pair: vertex[3 + j] for j, pair in enumerate(PAIRS)}
    for j, (l, m, n) in enumerate(PERMS):
        with np.errstate(divide="ignore", invalid="ignore"):   # degenerate: rejected by callers
            ratio = (gx[l] * ux[n] + gy[l] * uy[n]) / (gx[n] * ux[n] + gy[n] * uy[n])
        np.multiply(ratio, vertex[l], out=out[j])
        np.multiply(ratio, g[l, m], out=out[6 + j])


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
