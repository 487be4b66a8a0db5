# cython: language_level=3
"""Point location in the bucket grid of c1mesh.engine.locate.TriangleLocator, one query
after another: the locator's rule (the candidate of the query's cell with the largest
smallest barycentric coordinate, at least -tolerance; ties to the first in the cell's
list) and its arithmetic (λ_k = G_k · (x − p_{k+1}) for k = 0, 1, λ_2 = 1 − λ_0 − λ_1),
so the same triangles and the same bits as the numpy pairs it replaces. Each query writes
only its own rows: any block of queries in any thread.
"""
from libc.math cimport floor, isfinite
from libc.stdint cimport int64_t


def find(const double[:, ::1] points, const int64_t[:, ::1] triangles, const double[:, :, ::1] G,
         const int64_t[::1] bucket_start, const int64_t[::1] bucket_tris, double ox, double oy,
         double cell, int64_t ni, int64_t nj, double tolerance, const double[:, ::1] xy,
         Py_ssize_t first, Py_ssize_t stop, int64_t[::1] tri, double[:, ::1] lam):
    """tri[q] and lam[q] (set by the caller to -1 and NaN) for queries q in [first, stop):
    the containing triangle and its barycentrics, left as they are when none holds q."""
    cdef Py_ssize_t q, c
    cdef int64_t i, j, t, best
    cdef double x, y, l0, l1, l2, score, best_score, b0, b1, b2
    cdef double lo_x = ox - 0.5 * cell, lo_y = oy - 0.5 * cell
    cdef double hi_x = ox + ni * cell + 0.5 * cell, hi_y = oy + nj * cell + 0.5 * cell
    with nogil:
        for q in range(first, stop):
            x = xy[q, 0]
            y = xy[q, 1]
            if not (isfinite(x) and isfinite(y)) or x < lo_x or y < lo_y or x > hi_x or y > hi_y:
                continue
            i = <int64_t> floor((x - ox) / cell)
            j = <int64_t> floor((y - oy) / cell)
            i = 0 if i < 0 else (ni - 1 if i > ni - 1 else i)
            j = 0 if j < 0 else (nj - 1 if j > nj - 1 else j)
            best = -1
            best_score = 0.0
            for c in range(bucket_start[i * nj + j], bucket_start[i * nj + j + 1]):
                t = bucket_tris[c]
                l0 = G[t, 0, 0] * (x - points[triangles[t, 1], 0]) + G[t, 0, 1] * (y - points[triangles[t, 1], 1])
                l1 = G[t, 1, 0] * (x - points[triangles[t, 2], 0]) + G[t, 1, 1] * (y - points[triangles[t, 2], 1])
                l2 = 1.0 - l0 - l1
                score = l0 if l0 < l1 else l1
                score = score if score < l2 else l2
                if score >= -tolerance and (best < 0 or score > best_score):
                    best, best_score, b0, b1, b2 = t, score, l0, l1, l2
            if best >= 0:
                tri[q] = best
                lam[q, 0] = b0
                lam[q, 1] = b1
                lam[q, 2] = b2
