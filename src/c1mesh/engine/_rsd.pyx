# cython: language_level=3
"""The RSD coefficients of whole meshes, triangle by triangle: c1mesh.engine.rsd wraps these
kernels (shapes, the blocks in the thread knob's threads), and nothing else imports them.

Each triangle's arithmetic is its own and in a fixed order, the order of the formulas in
rsd.py's module docstring, so its bits depend neither on the block nor on the thread that
computes it. Points and per-vertex data are read as rows (one cache line per corner: the
triangles of a Delaunay triangulation reach their corners in no order); each triangle
writes its own rows of the outputs.
"""
from libc.math cimport fabs, hypot
from libc.stdint cimport int64_t, uint8_t

from c1mesh.core._prefetch cimport AHEAD, prefetch, prefetch_corners
from c1mesh.engine._rsd_orders cimport rsd_orders

# (k, i), i != k: the columns 3..8 of the coefficients, g_ki = A_k · (p_i − p_k);
# (l, m, n): the columns 9..14 (r_ln f_l) and 15..20 (r_ln g_lm) (_pair(l, m): the
# column 3 + j of g_lm)
cdef int PAIR_K[6], PAIR_I[6], PERM_L[6], PERM_M[6], PERM_N[6]
rsd_orders(PAIR_K, PAIR_I, PERM_L, PERM_M, PERM_N)


cdef inline int _pair(int k, int i) noexcept nogil:
    """j of (k, i) in rsd.PAIRS ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))."""
    return 2 * k + (i if i < k else i - 1)


cdef inline double _gradients(const double[:, ::1] rows, const int64_t[:, ::1] tri, Py_ssize_t t,
                              double *x, double *y, double *gx, double *gy) noexcept nogil:
    """Corner coordinates x, y (3,) of triangle t and G_k = (gx[k], gy[k]) = perp(p_{k+1} −
    p_{k+2}) / det; returns det = (x1 − x0)(y2 − y0) − (y1 − y0)(x2 − x0). det = 0 gives
    G = 0 (its inverse taken as 1/inf), a NaN det NaN."""
    cdef int k, a, b
    cdef double det, inv
    for k in range(3):
        x[k] = rows[tri[t, k], 0]
        y[k] = rows[tri[t, k], 1]
    det = (x[1] - x[0]) * (y[2] - y[0]) - (y[1] - y[0]) * (x[2] - x[0])
    inv = 0.0 if det == 0 else 1.0 / det
    for k in range(3):
        a = (k + 1) % 3
        b = (k + 2) % 3
        gx[k] = (y[a] - y[b]) * inv
        gy[k] = (x[b] - x[a]) * inv
    return det


def triangle_gradients(const double[:, ::1] rows, const int64_t[:, ::1] tri, double[:, :, ::1] G,
                       double[::1] det, Py_ssize_t start, Py_ssize_t stop):
    """G[t] (3, 2), the gradients of triangle t's barycentric coordinates, and det[t], twice
    its signed area, for start <= t < stop: corners tri (T, 3) into rows (n, >= 2) whose
    first two columns are x, y."""
    cdef Py_ssize_t t
    cdef int k
    cdef double x[3]
    cdef double y[3]
    cdef double gx[3]
    cdef double gy[3]
    with nogil:
        for t in range(start, stop):
            prefetch_corners(rows, tri, t + AHEAD, stop)
            det[t] = _gradients(rows, tri, t, x, y, gx, gy)
            for k in range(3):
                G[t, k, 0] = gx[k]
                G[t, k, 1] = gy[k]


def vertex_coefficients(const double[:, ::1] rows, const int64_t[:, ::1] tri, double min_sine,
                        double[:, ::1] C, double[:, :, ::1] G, double[::1] det,
                        uint8_t[::1] degenerate, Py_ssize_t start, Py_ssize_t stop):
    """For triangles start <= t < stop of tri (T, 3) into rows (n, 5) (x, y, f, fx, fy of each
    vertex): columns 0..8 of C[t] (f_k, then g_ki for (k, i) in rsd.PAIRS), G[t] (3, 2),
    det[t]; and when degenerate has T entries, degenerate[t] = not |det| > min_sine ·
    |p1 − p0| · |p2 − p0| (lengths by libm's hypot; NaN counts as degenerate)."""
    cdef Py_ssize_t t
    cdef int k, i, j
    cdef double x[3]
    cdef double y[3]
    cdef double gx[3]
    cdef double gy[3]
    cdef double d, e1, e2
    cdef bint check = degenerate.shape[0] == C.shape[0]
    with nogil:
        for t in range(start, stop):
            prefetch_corners(rows, tri, t + AHEAD, stop)
            d = _gradients(rows, tri, t, x, y, gx, gy)
            det[t] = d
            for k in range(3):
                G[t, k, 0] = gx[k]
                G[t, k, 1] = gy[k]
                C[t, k] = rows[tri[t, k], 2]
            for j in range(6):
                k = PAIR_K[j]
                i = PAIR_I[j]
                C[t, 3 + j] = rows[tri[t, k], 3] * (x[i] - x[k]) + rows[tri[t, k], 4] * (y[i] - y[k])
            if check:
                e1 = hypot(x[1] - x[0], y[1] - y[0])
                e2 = hypot(x[2] - x[0], y[2] - y[0])
                degenerate[t] = not (fabs(d) > min_sine * e1 * e2)


def ratio_coefficients(double[:, ::1] C, const double[:, :, ::1] G, const double[:, ::1] directions,
                       const int64_t[:, ::1] tri_edge, Py_ssize_t start, Py_ssize_t stop):
    """Columns 9..20 of C[t] (T, 21) from its columns 0..8, G[t] (3, 2) and the directions
    (E, 2) of its edges tri_edge[t] (the edge opposite each corner), for start <= t < stop:
    r_ln = G_l·u_n / G_n·u_n, then r_ln f_l and r_ln g_lm for (l, m, n) in rsd.PERMS."""
    cdef Py_ssize_t t
    cdef int j, l, m, n
    cdef double ratio, ux, uy
    with nogil:
        for t in range(start, stop):
            if t + AHEAD < stop:
                for j in range(3):
                    prefetch(&directions[tri_edge[t + AHEAD, j], 0])
            for j in range(6):
                l = PERM_L[j]
                m = PERM_M[j]
                n = PERM_N[j]
                ux = directions[tri_edge[t, n], 0]
                uy = directions[tri_edge[t, n], 1]
                ratio = (G[t, l, 0] * ux + G[t, l, 1] * uy) / (G[t, n, 0] * ux + G[t, n, 1] * uy)
                C[t, 9 + j] = ratio * C[t, l]
                C[t, 15 + j] = ratio * C[t, 3 + _pair(l, m)]
