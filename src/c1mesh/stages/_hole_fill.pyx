# cython: language_level=3
"""The hole fill's kernel: c1mesh.stages.hole_fill wraps it (validation), and nothing else
imports it."""
from libc.stdint cimport int64_t, uint8_t


def octagon_corners(const double[:, :] xy, int64_t[::1] corners):
    """corners[0..7] = the rows of xy (n, 2), n >= 1, that are extreme along the directions
    −y, x − y, x, x + y, y, −x + y, −x, −x − y (the first row of a tie): the corners of the
    octagon they span, counter-clockwise. One pass, without the GIL."""
    cdef Py_ssize_t k, n = xy.shape[0]
    cdef int d
    cdef double x, y, value
    cdef double best[8]
    cdef double ax[8]
    cdef double ay[8]
    ax[:] = [0.0, 1.0, 1.0, 1.0, 0.0, -1.0, -1.0, -1.0]
    ay[:] = [-1.0, -1.0, 0.0, 1.0, 1.0, 1.0, 0.0, -1.0]
    with nogil:
        for d in range(8):
            corners[d] = 0
            best[d] = ax[d] * xy[0, 0] + ay[d] * xy[0, 1]
        for k in range(1, n):
            x = xy[k, 0]
            y = xy[k, 1]
            for d in range(8):
                value = ax[d] * x + ay[d] * y
                if value > best[d]:
                    best[d] = value
                    corners[d] = k


def outside_octagon(const double[:, :] xy, const double[:, ::1] octagon, uint8_t[::1] out):
    """out[k] = 1 when row k of xy (n, 2) lies on or outside an edge of the convex polygon
    octagon (8, 2), counter-clockwise, whose corners may repeat (an edge of length zero is
    skipped), else 0: a point strictly inside every edge is no corner of the points' convex
    hull. Without the GIL."""
    cdef Py_ssize_t k, n = xy.shape[0]
    cdef int e, f
    cdef double x, y
    with nogil:
        for k in range(n):
            x = xy[k, 0]
            y = xy[k, 1]
            out[k] = 0
            for e in range(8):
                f = (e + 1) % 8
                if octagon[f, 0] == octagon[e, 0] and octagon[f, 1] == octagon[e, 1]:
                    continue
                if (octagon[f, 0] - octagon[e, 0]) * (y - octagon[e, 1]) - \
                        (octagon[f, 1] - octagon[e, 1]) * (x - octagon[e, 0]) <= 0.0:
                    out[k] = 1
                    break


def ascending_cells(const int64_t[::1] corners, int64_t nx, int64_t[::1] out):
    """The distinct cells of lattice triangles given by their first corners (T,) (node
    numbers j nx + i; the cell is j (nx − 1) + i), written to out[:k] when the corners never
    decrease (a fit's triangles, cell by cell); returns k, or −1 as soon as a corner is
    less than the one before (the caller sorts). Without the GIL."""
    cdef Py_ssize_t t, k = 0, n = corners.shape[0]
    cdef int64_t node, last = -1
    with nogil:
        for t in range(n):
            node = corners[t]
            if node < last:
                k = -1
                break
            if node != last:
                out[k] = node - node // nx
                k += 1
                last = node
    return k
