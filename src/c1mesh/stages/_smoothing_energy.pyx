# cython: language_level=3
"""The per-triangle 9 × 9 thin-plate energy blocks: c1mesh.stages.smoothing_energy wraps it
(the collected tensor Z, the blocks of triangles in threads), and nothing else imports it.

Per triangle, the arithmetic of smoothing_energy's module doc in a fixed order, each
operation the one numpy's former pass made (so the bits are those of that pass):
barycentric gradients G and det as rsd.barycentric_gradients; the six ratios
ρ_j = G_l·u_n / G_n·u_n and the edge vectors g_ki = p_i − p_k as rsd.triangle_coefficients
gives them for unit data; the mode weights |det| <N_m, N_n>_F; the 168 features
(mode weight × monomial of the ratios); the upper triangle of E' as Z @ features summed
over each row's nonzeros in CSR order from 0 (scipy's csr_matvecs); then K = V^T E' V by
the row operations of V (the identity on f, the g's on the gradients).
"""
from libc.stdint cimport int64_t

from c1mesh.engine._rsd_orders cimport rsd_orders

cdef enum:
    N_LOCAL = 9
    N_UPPER = 45         # entries of a 9 × 9 upper triangle
    N_MONOMIALS = 28     # 1, ρ_j, ρ_j ρ_j' (j <= j')
    N_FEATURES = 168     # 6 mode pairs × 28 monomials
    LANES = 8            # triangles taken together through Z's terms

# rsd.PAIRS (k, i) and rsd.PERMS (l, m, n), the rsd module's orders.
cdef int PAIR_K[6], PAIR_I[6], PERM_L[6], PERM_M[6], PERM_N[6]
rsd_orders(PAIR_K, PAIR_I, PERM_L, PERM_M, PERM_N)


cdef void _geometry(const double *px, const double *py, const double *ux, const double *uy,
                    double *weights, double *ratios, double *gx_pairs, double *gy_pairs) noexcept nogil:
    """weights (6): the mode weights; ratios (6): ρ_j for PERMS; gx_pairs, gy_pairs (6): the
    components of p_i − p_k for PAIRS. Corners px, py (3), directions ux, uy (3)."""
    cdef double det, inv, s00, s01, s11, adet
    cdef double gx[3]
    cdef double gy[3]
    cdef int k, a, b, j, l, n
    det = (px[1] - px[0]) * (py[2] - py[0]) - (py[1] - py[0]) * (px[2] - px[0])
    inv = 1.0 / det if det != 0 else 0.0          # numpy's 1 / inf for degenerate ones
    for k in range(3):
        a = (k + 1) % 3
        b = (k + 2) % 3
        gx[k] = (py[a] - py[b]) * inv
        gy[k] = (px[b] - px[a]) * inv
    for j in range(6):
        l = PERM_L[j]
        n = PERM_N[j]
        ratios[j] = (gx[l] * ux[n] + gy[l] * uy[n]) / (gx[n] * ux[n] + gy[n] * uy[n])
        gx_pairs[j] = px[PAIR_I[j]] - px[PAIR_K[j]]
        gy_pairs[j] = py[PAIR_I[j]] - py[PAIR_K[j]]
    s00 = gx[0] * gx[0] + gy[0] * gy[0]
    s01 = gx[0] * gx[1] + gy[0] * gy[1]
    s11 = gx[1] * gx[1] + gy[1] * gy[1]
    adet = det if det >= 0 else -det
    weights[0] = (s00 * s00) * adet
    weights[1] = ((2 * s00) * s01) * adet
    weights[2] = (s01 * s01) * adet
    weights[3] = (2 * (s00 * s11 + s01 * s01)) * adet
    weights[4] = ((2 * s01) * s11) * adet
    weights[5] = (s11 * s11) * adet


cdef void _upper(const double (*weights)[LANES], const double (*ratios)[LANES],
                 const int64_t[::1] z_rows, const int64_t[::1] z_cols, const double[::1] z_values,
                 double (*upper)[LANES]) noexcept nogil:
    """upper (45 × LANES): Z @ features for each lane's triangle, features[28 k + μ] =
    weights[k] · μ(ρ) for the monomials μ = r_a r_b (a <= b, r_0 = 1, r_1.. = ρ) in
    smoothing_energy._MONOMIALS' order. Z's terms (z_rows, z_cols, z_values) come in
    smoothing_energy._z_terms' order, each row's in CSR order, so each sum is rounded as
    scipy's csr_matvecs rounds it; a term is applied to all the lanes at once."""
    cdef double r[7][LANES]
    cdef double mono[N_MONOMIALS][LANES]
    cdef double features[N_FEATURES][LANES]
    cdef int a, b, i, k, lane
    cdef Py_ssize_t p
    cdef int64_t row, col
    cdef double z
    for lane in range(LANES):
        r[0][lane] = 1.0
    for a in range(6):
        for lane in range(LANES):
            r[1 + a][lane] = ratios[a][lane]
    i = 0
    for a in range(7):
        for b in range(a, 7):
            for lane in range(LANES):
                mono[i][lane] = r[a][lane] * r[b][lane]
            i += 1
    for k in range(6):
        for i in range(N_MONOMIALS):
            for lane in range(LANES):
                features[k * N_MONOMIALS + i][lane] = mono[i][lane] * weights[k][lane]
    for i in range(N_UPPER):
        for lane in range(LANES):
            upper[i][lane] = 0.0
    for p in range(z_rows.shape[0]):
        row = z_rows[p]
        col = z_cols[p]
        z = z_values[p]
        for lane in range(LANES):
            upper[row][lane] += z * features[col][lane]


cdef void _apply_v(const double (*upper)[LANES], int lane, const double *gx_pairs,
                   const double *gy_pairs, double *out) noexcept nogil:
    """out (9 × 9, row-major) = V^T E' V for the symmetric E' given by its upper triangle
    (row-major order) in column `lane` of upper: V is the identity on f_k and maps ∇f_k to the vertex coefficients
    g_ki = ∇f_k · (p_i − p_k), so a column 3 + j of E' (j the PAIRS index of (k, i)) adds
    into the columns 3 + 2k (x) and 4 + 2k (y), then the same for the rows."""
    cdef double E[N_LOCAL * N_LOCAL]
    cdef double right[N_LOCAL * N_LOCAL]
    cdef double g[2]
    cdef int i, j, c, col, p = 0
    for i in range(N_LOCAL):
        for j in range(i, N_LOCAL):
            E[i * N_LOCAL + j] = upper[p][lane]
            E[j * N_LOCAL + i] = upper[p][lane]
            p += 1
    for i in range(N_LOCAL):
        for j in range(3):
            right[i * N_LOCAL + j] = E[i * N_LOCAL + j]
        for j in range(3, N_LOCAL):
            right[i * N_LOCAL + j] = 0.0
    for j in range(6):
        g[0] = gx_pairs[j]
        g[1] = gy_pairs[j]
        for c in range(2):
            col = 3 + 2 * PAIR_K[j] + c
            for i in range(N_LOCAL):
                right[i * N_LOCAL + col] += E[i * N_LOCAL + 3 + j] * g[c]
    for i in range(3 * N_LOCAL):
        out[i] = right[i]
    for i in range(3 * N_LOCAL, N_LOCAL * N_LOCAL):
        out[i] = 0.0
    for j in range(6):
        g[0] = gx_pairs[j]
        g[1] = gy_pairs[j]
        for c in range(2):
            col = 3 + 2 * PAIR_K[j] + c          # the row of out
            for i in range(N_LOCAL):
                out[col * N_LOCAL + i] += right[(3 + j) * N_LOCAL + i] * g[c]


def energy_blocks(const double[:, ::1] points, const int64_t[:, ::1] triangles,
                  const double[:, :, ::1] directions, const int64_t[::1] z_rows,
                  const int64_t[::1] z_cols, const double[::1] z_values,
                  Py_ssize_t start, Py_ssize_t stop, double[:, :, ::1] out):
    """out[t] (9, 9) for the triangles t in [start, stop): the energy block of triangle
    triangles[t] (vertex indices into points (N, 2)) with edge directions directions[t]
    (3, 2), u_k opposite vertex k. Z's nonzeros (z_rows, z_cols, z_values: rows in
    [0, 45), columns in [0, 168)) are smoothing_energy._collected's in _z_terms' order.
    Each triangle's arithmetic is its own."""
    cdef Py_ssize_t first, t, count
    cdef int k, lane
    cdef double px[3]
    cdef double py[3]
    cdef double ux[3]
    cdef double uy[3]
    cdef double geometry[6]
    cdef double ratio[6]
    cdef double weights[6][LANES]
    cdef double ratios[6][LANES]
    cdef double gx_pairs[LANES][6]
    cdef double gy_pairs[LANES][6]
    cdef double upper[N_UPPER][LANES]
    with nogil:
        first = start
        while first < stop:
            count = min(<Py_ssize_t> LANES, stop - first)
            for lane in range(LANES):
                t = first + (lane if lane < count else 0)      # spare lanes redo the first
                for k in range(3):
                    px[k] = points[triangles[t, k], 0]
                    py[k] = points[triangles[t, k], 1]
                    ux[k] = directions[t, k, 0]
                    uy[k] = directions[t, k, 1]
                _geometry(px, py, ux, uy, geometry, ratio, gx_pairs[lane], gy_pairs[lane])
                for k in range(6):
                    weights[k][lane] = geometry[k]
                    ratios[k][lane] = ratio[k]
            _upper(weights, ratios, z_rows, z_cols, z_values, upper)
            for lane in range(count):
                _apply_v(upper, lane, gx_pairs[lane], gy_pairs[lane], &out[first + lane, 0, 0])
            first += LANES
