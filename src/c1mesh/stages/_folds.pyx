# cython: language_level=3
"""The fold net's kernel: c1mesh.stages.folds wraps it (validation, threads), and nothing
else imports it."""
from libc.stdint cimport int64_t, uint8_t


def spread_candidates(const double[:, ::1] xy, const double[::1] values, const double[:, ::1] gradients,
                      const int64_t[:, ::1] tri, double spread, uint8_t[::1] out,
                      Py_ssize_t start, Py_ssize_t stop):
    """out[t] = 1 when a corner's gradient of triangle t lies more than `spread` from the
    gradient of the linear interpolant of its corners' values, else 0, for start <= t < stop
    of tri (T, 3) into xy (n, 2), values (n,), gradients (n, 2). A degenerate triangle
    (zero area) is marked. Without the GIL: the wrapper runs blocks in its threads."""
    cdef Py_ssize_t t
    cdef int k
    cdef int64_t a, b, c, v
    cdef double e1x, e1y, e2x, e2y, dz1, dz2, det, sx, sy, dx, dy, limit = spread * spread
    with nogil:
        for t in range(start, stop):
            a = tri[t, 0]
            b = tri[t, 1]
            c = tri[t, 2]
            e1x = xy[b, 0] - xy[a, 0]
            e1y = xy[b, 1] - xy[a, 1]
            e2x = xy[c, 0] - xy[a, 0]
            e2y = xy[c, 1] - xy[a, 1]
            dz1 = values[b] - values[a]
            dz2 = values[c] - values[a]
            det = e1x * e2y - e1y * e2x
            out[t] = 0
            if det == 0.0:
                out[t] = 1
                continue
            sx = (e2y * dz1 - e1y * dz2) / det
            sy = (e1x * dz2 - e2x * dz1) / det
            for k in range(3):
                v = tri[t, k]
                dx = gradients[v, 0] - sx
                dy = gradients[v, 1] - sy
                if dx * dx + dy * dy > limit:
                    out[t] = 1
                    break
