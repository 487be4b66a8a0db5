# cython: language_level=3
"""The curtain stage's kernels: c1mesh.stages.curtains wraps them (validation, threads), and
nothing else imports them. Element by element, in the order of operations the wrapper's
docstrings give (no contraction into fused multiply-adds: the build's -ffp-contract=off),
over a range [start, stop) without the GIL: the wrapper runs fixed blocks in its threads,
each output element is written by one block, so the bytes do not depend on the thread count.
The points come as rows p (n, 5) = (x, y, z, gx, gy): the triangles of a Delaunay
triangulation reach their points in no order, and a row is one cache line where five
columns are five."""
from libc.math cimport isnan, NAN
from libc.stdint cimport int64_t, uint8_t

from c1mesh.core._prefetch cimport AHEAD, prefetch_corners


cdef inline double _maximum(double a, double b) noexcept nogil:
    """numpy's maximum: NaN when either is NaN."""
    if isnan(a) or isnan(b):
        return NAN
    return a if a >= b else b


def curtain_masks(const double[:, ::1] p, const int64_t[:, ::1] tri, const uint8_t[::1] alive,
                  double cos2_shadow, double cos2_grazing, double floor, bint view_rules,
                  uint8_t[::1] shadow, uint8_t[::1] grazing, uint8_t[::1] away,
                  uint8_t[::1] thin, Py_ssize_t start, Py_ssize_t stop):
    """The four (T,) 0/1 masks of curtains.curtain_triangles for the triangles start <= t <
    stop of tri (T, 3) over the point rows p (n, 5); all 0 for a triangle not alive (T,)."""
    cdef Py_ssize_t t
    cdef int k
    cdef int64_t c0, c1, c2, c, nxt
    cdef double ex, ey, ez, flat2, longest2, ux, uy, uz, vx, vy, vz, nx, ny, nz
    cdef bint is_shadow, is_grazing, is_away
    with nogil:
        for t in range(start, stop):
            prefetch_corners(p, tri, t + AHEAD, stop)
            if not alive[t]:
                shadow[t] = grazing[t] = away[t] = thin[t] = 0
                continue
            c0 = tri[t, 0]
            c1 = tri[t, 1]
            c2 = tri[t, 2]
            is_shadow = False
            longest2 = 0.0
            for k in range(3):              # edge k: corner k + 1 minus corner k
                c = c0 if k == 0 else (c1 if k == 1 else c2)
                nxt = c1 if k == 0 else (c2 if k == 1 else c0)
                ex = p[nxt, 0] - p[c, 0]
                ey = p[nxt, 1] - p[c, 1]
                ez = p[nxt, 2] - p[c, 2]
                flat2 = ex * ex + ey * ey
                longest2 = flat2 if k == 0 else _maximum(longest2, flat2)
                if ez * ez > cos2_shadow * (flat2 + ez * ez):
                    is_shadow = True
            ux = p[c1, 0] - p[c0, 0]
            uy = p[c1, 1] - p[c0, 1]
            uz = p[c1, 2] - p[c0, 2]
            vx = -(p[c0, 0] - p[c2, 0])
            vy = -(p[c0, 1] - p[c2, 1])
            vz = -(p[c0, 2] - p[c2, 2])
            nx = uy * vz - uz * vy
            ny = uz * vx - ux * vz
            nz = ux * vy - uy * vx
            if nz < 0:                       # the normal on the axis side
                nx = -nx
                ny = -ny
                nz = -nz
            is_grazing = not (nz * nz >= cos2_grazing * (nx * nx + ny * ny + nz * nz)) and not is_shadow
            is_away = False
            for k in range(3):               # a data normal (-g, 1) the plane faces away from
                c = c0 if k == 0 else (c1 if k == 1 else c2)
                if nz - nx * p[c, 3] - ny * p[c, 4] < 0:
                    is_away = True
            is_away = is_away and not is_shadow and not is_grazing
            if not view_rules:
                is_shadow = is_grazing = is_away = False
            shadow[t] = is_shadow
            grazing[t] = is_grazing
            away[t] = is_away
            thin[t] = (nz * nz < floor * floor * longest2) and not is_shadow and not is_grazing \
                and not is_away
