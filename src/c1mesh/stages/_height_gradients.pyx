# cython: language_level=3
"""The per-point least-squares fit of the height gradients: c1mesh.stages.height_gradients
wraps it (validation, the neighbour search, the blocks in the thread knob's threads), and
nothing else imports it.

For each point, one small system: the weighted normal equations of a polynomial in the
scaled plane offsets (2 terms for degree 1, 5 for degree 2), with a relative ridge, solved by
Gaussian elimination with partial pivoting. Every point's arithmetic is its own, in a fixed
order, so its bits do not depend on the block or the thread it runs in.
"""
from libc.math cimport fabs, sqrt
from libc.stdint cimport int64_t
from libc.stdlib cimport free, malloc, qsort

cdef enum:
    MAX_TERMS = 5        # the quadratic's terms, the most a system has


cdef int _compare(const void *a, const void *b) noexcept nogil:
    cdef double x = (<const double *> a)[0], y = (<const double *> b)[0]
    return (x > y) - (x < y)


cdef double _median(const double[:, :] dist2, Py_ssize_t row, double *scratch) noexcept nogil:
    """The median of dist2[row] (numpy's: the mean of the two middle values when even)."""
    cdef Py_ssize_t j, k = dist2.shape[1]
    cdef Py_ssize_t i
    cdef double value
    if k > 64:
        for j in range(k):
            scratch[j] = dist2[row, j]
        qsort(scratch, k, sizeof(double), _compare)
    else:                                    # insertion sort: a few dozen values
        for j in range(k):
            value = dist2[row, j]
            i = j - 1
            while i >= 0 and scratch[i] > value:
                scratch[i + 1] = scratch[i]
                i -= 1
            scratch[i + 1] = value
    if k % 2:
        return scratch[k // 2]
    return (scratch[k // 2 - 1] + scratch[k // 2]) / 2.0


cdef void _solve(double *a, double *b, int m) noexcept nogil:
    """b = a⁻¹ b for the m × m row-major a (overwritten): elimination, partial pivoting."""
    cdef int i, j, c, p
    cdef double f, t
    for c in range(m):
        p = c
        for i in range(c + 1, m):
            if fabs(a[i * m + c]) > fabs(a[p * m + c]):
                p = i
        if p != c:
            for j in range(m):
                t = a[c * m + j]
                a[c * m + j] = a[p * m + j]
                a[p * m + j] = t
            t = b[c]
            b[c] = b[p]
            b[p] = t
        for i in range(c + 1, m):
            f = a[i * m + c] / a[c * m + c]
            for j in range(c, m):
                a[i * m + j] -= f * a[c * m + j]
            b[i] -= f * b[c]
    for c in range(m - 1, -1, -1):
        t = b[c]
        for j in range(c + 1, m):
            t -= a[c * m + j] * b[j]
        b[c] = t / a[c * m + c]


def fit_block(const double[::1] z, const int64_t[::1] centre, const int64_t[:, :] neighbours,
              const double[:, :] ux, const double[:, :] uy, const double[:, :] dist2,
              int degree, double ridge, double tiny, double[:, ::1] out):
    """out (b, 2): the gradient at each point centre[i] (b,) of the heights z (n,), from its
    neighbours (b, k) at plane offsets ux, uy and squared distances dist2 (b, k each, plane
    units); gradients in z units per plane unit (height_gradients documents the fit).

    Per point: r² the median of dist2 (1 where 0), offsets scaled by r, weights
    1 / (1 + d²/r²), the terms (u, v[, u²/2, uv, v²/2]); N = Σ w aᵀa and the right side
    Σ w a Δz summed over the neighbours in column order; ridge · trace(N) + tiny added to N's
    diagonal; the solution's first two terms divided by r."""
    cdef Py_ssize_t b = centre.shape[0], k = neighbours.shape[1], i, j
    cdef int m = 2 if degree == 1 else 5, p, q
    cdef double scale2, scale, u, v, w, dz, shift
    cdef double row[MAX_TERMS]
    cdef double normal[MAX_TERMS * MAX_TERMS]
    cdef double rhs[MAX_TERMS]
    cdef double *scratch
    with nogil:
        scratch = <double *> malloc(max(k, 1) * sizeof(double))
        for i in range(b):
            scale2 = _median(dist2, i, scratch)
            if not scale2 > 0:
                scale2 = 1.0
            scale = sqrt(scale2)
            for p in range(m * m):
                normal[p] = 0.0
            for p in range(m):
                rhs[p] = 0.0
            for j in range(k):
                u = ux[i, j] / scale
                v = uy[i, j] / scale
                w = 1.0 / (1.0 + dist2[i, j] / scale2)
                dz = z[neighbours[i, j]] - z[centre[i]]
                row[0] = u
                row[1] = v
                if m == 5:
                    row[2] = 0.5 * u * u
                    row[3] = u * v
                    row[4] = 0.5 * v * v
                for p in range(m):
                    rhs[p] += row[p] * w * dz
                    for q in range(m):
                        normal[p * m + q] += row[p] * w * row[q]
            shift = 0.0
            for p in range(m):
                shift += normal[p * m + p]
            shift = ridge * shift + tiny
            for p in range(m):
                normal[p * m + p] += shift
            _solve(normal, rhs, m)
            out[i, 0] = rhs[0] / scale
            out[i, 1] = rhs[1] / scale
        free(scratch)


def offsets(const double[:, ::1] xy, const int64_t[::1] centre, const int64_t[:, ::1] index,
            double[:, ::1] ux, double[:, ::1] uy, double[:, ::1] dist2):
    """ux, uy, dist2 (b, k): the plane offsets xy[index] - xy[centre] of each point's
    candidates index (b, k) from the point centre (b,), and their squares' sum
    dx·dx + dy·dy, in xy's unit (squared)."""
    cdef Py_ssize_t b = index.shape[0], k = index.shape[1], i, j
    cdef double cx, cy, dx, dy
    with nogil:
        for i in range(b):
            cx = xy[centre[i], 0]
            cy = xy[centre[i], 1]
            for j in range(k):
                dx = xy[index[i, j], 0] - cx
                dy = xy[index[i, j], 1] - cy
                ux[i, j] = dx
                uy[i, j] = dy
                dist2[i, j] = dx * dx + dy * dy
