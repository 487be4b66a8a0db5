# cython: language_level=3
"""The smoothing fit's input checks over the whole mesh, and its data points located on a
lattice mesh: c1mesh.stages.smoothing wraps them (the blocks in the thread knob's
threads), and nothing else imports them.

Each check is a yes/no per edge or triangle, reduced over a block: the comparisons are
those of the numpy expressions they replace, operation for operation, so the same meshes
pass. The barycentrics are rsd.barycentric_gradients' arithmetic, operation for operation
(the build's -ffp-contract=off keeps it unfused), so a point's bits are those of the
generic locator's formula.
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


def lattice_slots(const int64_t[::1] nodes, const int64_t[:, ::1] triangles, int64_t nx,
                  int64_t[::1] where) -> None:
    """where[2 c + upper] = t for each lattice triangle t (T, 3) of node numbers nodes[...]
    (j nx + i): c = j (nx − 1) + i the cell of its least corner (i, j), upper = 1 when it
    holds node (i, j + 1), the half above the cell's (i, j)-(i+1, j+1) diagonal."""
    cdef Py_ssize_t t
    cdef int k
    cdef int64_t lowest, node, ci, cj, above
    cdef bint upper
    with nogil:
        for t in range(triangles.shape[0]):
            lowest = nodes[triangles[t, 0]]
            for k in range(1, 3):
                node = nodes[triangles[t, k]]
                if node < lowest:
                    lowest = node
            cj = lowest // nx
            ci = lowest - cj * nx
            above = lowest + nx
            upper = False
            for k in range(3):
                if nodes[triangles[t, k]] == above:
                    upper = True
            where[2 * (cj * (nx - 1) + ci) + upper] = t


def lattice_barycentrics(const double[:, ::1] npts, const int64_t[:, ::1] triangles,
                         const int64_t[::1] tri, const double[:, ::1] xy, double[:, ::1] lam,
                         Py_ssize_t start, Py_ssize_t stop) -> None:
    """lam[p] (3,) the barycentrics of point xy[p] in triangle tri[p] (corners npts[triangles
    [t]]) for start <= p < stop with tri[p] >= 0, in rsd.barycentric_gradients' arithmetic:
    G_k = perp(p_{k+1} − p_{k+2}) / det, λ_k = G_k · (x − p_0) for k = 1, 2 and λ_0 =
    1 − (λ_1 + λ_2); rows with tri[p] < 0 are left as they are."""
    cdef Py_ssize_t p
    cdef int64_t t
    cdef int k, a, b
    cdef double x[3]
    cdef double y[3]
    cdef double det, inv, dx, dy, r1, r2
    with nogil:
        for p in range(start, stop):
            t = tri[p]
            if t < 0:
                continue
            for k in range(3):
                x[k] = npts[triangles[t, k], 0]
                y[k] = npts[triangles[t, k], 1]
            det = (x[1] - x[0]) * (y[2] - y[0]) - (y[1] - y[0]) * (x[2] - x[0])
            inv = 0.0 if det == 0 else 1.0 / det
            dx = xy[p, 0] - x[0]
            dy = xy[p, 1] - y[0]
            r1 = ((y[2] - y[0]) * inv) * dx + ((x[0] - x[2]) * inv) * dy
            r2 = ((y[0] - y[1]) * inv) * dx + ((x[1] - x[0]) * inv) * dy
            lam[p, 0] = 1.0 - (r1 + r2)
            lam[p, 1] = r1
            lam[p, 2] = r2
