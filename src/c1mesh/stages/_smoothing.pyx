# cython: language_level=3
"""The smoothing fit's input checks over the whole mesh: c1mesh.stages.smoothing wraps them
(the blocks in the thread knob's threads), and nothing else imports them.

Each is a yes/no per edge or triangle, reduced over a block: the comparisons are those of
the numpy expressions they replace, operation for operation, so the same meshes pass.
"""
from libc.math cimport fabs, hypot
from libc.stdint cimport int64_t

from c1mesh.core._triangles cimport corner_offsets


def directions_cross(const double[:, ::1] points, const int64_t[:, ::1] edges,
                     const double[:, ::1] u, double threshold, Py_ssize_t first,
                     Py_ssize_t stop) -> bool:
    """Whether every edge e in [first, stop) has its direction u[e] (2,) cross the edge
    vector v = points[edges[e, 1]] − points[edges[e, 0]]: cross² > threshold² |u|² |v|²,
    cross = u_x v_y − u_y v_x (NaN fails)."""
    cdef Py_ssize_t e
    cdef double vx, vy, cross, square = threshold * threshold
    cdef bint ok = True
    with nogil:
        for e in range(first, stop):
            vx = points[edges[e, 1], 0] - points[edges[e, 0], 0]
            vy = points[edges[e, 1], 1] - points[edges[e, 0], 1]
            cross = u[e, 0] * vy - u[e, 1] * vx
            if not (cross * cross > square * (u[e, 0] * u[e, 0] + u[e, 1] * u[e, 1])
                    * (vx * vx + vy * vy)):
                ok = False
                break
    return ok


def nondegenerate(const double[:, ::1] points, const int64_t[:, ::1] triangles, double threshold,
                  Py_ssize_t first, Py_ssize_t stop) -> bool:
    """Whether every triangle t in [first, stop) has |det| > threshold · |p1 − p0| · |p2 − p0|,
    det = cross(p1 − p0, p2 − p0) (twice the signed area; NaN fails)."""
    cdef Py_ssize_t t
    cdef double det
    cdef double c[6]           # x0, y0, ax, ay, bx, by
    cdef bint ok = True
    with nogil:
        for t in range(first, stop):
            corner_offsets(points, triangles, t, c)
            det = c[2] * c[5] - c[3] * c[4]
            if not (fabs(det) > threshold * hypot(c[2], c[3]) * hypot(c[4], c[5])):
                ok = False
                break
    return ok
