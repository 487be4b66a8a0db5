# cython: language_level=3
"""The kernels of c1mesh.engine.triangulation (which wraps them; nothing else imports them).

* `screen`, the in-circle screen of canonical_ties: for every interior edge of a Delaunay
  triangulation, whether the four points of its two triangles may lie on one circle. Each
  triangle writes only its own row: any block of triangles in any thread.
* `drop_super_triangle`: CDT's triangles and neighbours as its erase_super_triangle leaves
  them, from the rows before it, in two linear passes (CDT's own erase looks every
  triangle up in hash sets: 0.35 s at 1M points).
* `cell_order`: the points by cells of a grid, row by row: the order CDT is given them in.
"""
import numpy as np

from libc.math cimport fabs, floor, sqrt
from libc.stdint cimport int8_t, int64_t, uint32_t

from c1mesh.core._counting cimport stable_order
from c1mesh.core._prefetch cimport AHEAD, prefetch, prefetch_corners

cdef enum:
    _RECTANGLE = 1
    _NEAR = 2
    _ILLEGAL = 3

RECTANGLE = _RECTANGLE
"""Two x values and two y values, each held by two of the four points: exactly cocircular."""
NEAR = _NEAR
"""In-circle determinant within the screen's bound: the caller decides it exactly."""
ILLEGAL = _ILLEGAL
"""The far corner clearly inside the triangle's circumcircle (beyond the bound): not Delaunay."""


cdef inline bint _rectangle(double ax, double ay, double bx, double by, double cx, double cy,
                            double dx, double dy) noexcept nogil:
    """The four distinct points are the corners of an axis-parallel rectangle (exact tests)."""
    cdef int same_x = (ax == bx) + (ax == cx) + (ax == dx) + (bx == cx) + (bx == dx) + (cx == dx)
    cdef int same_y = (ay == by) + (ay == cy) + (ay == dy) + (by == cy) + (by == dy) + (cy == dy)
    # exactly 2 equal pairs among four values: two values, each held twice; as the points
    # are distinct, the x pairs and the y pairs cross, so they are the four corners
    return same_x == 2 and same_y == 2


def screen(const double[:, ::1] xy, const int64_t[:, ::1] tri, const int64_t[:, ::1] across,
           double bound, Py_ssize_t first, Py_ssize_t stop, int8_t[:, ::1] flag):
    """flag[t, k] (zeroed by the caller: 0, not cocircular) for triangles t in [first, stop) and the edge
    opposite their corner k, when the triangle across it has a larger number: RECTANGLE,
    NEAR (|in-circle determinant| <= bound × its permanent, from the points' differences
    to the far corner) or ILLEGAL (the determinant above it: the far corner inside)."""
    cdef Py_ssize_t t, k
    cdef int64_t u, a, b, c, d
    cdef double adx, ady, bdx, bdy, cdx, cdy, alift, blift, clift, det, permanent
    with nogil:
        for t in range(first, stop):
            prefetch_corners(xy, tri, t + 2 * AHEAD, stop)    # a later triangle's corners,
            if t + 2 * AHEAD < stop:                         # the triangles across it,
                for k in range(3):
                    if across[t + 2 * AHEAD, k] > t + 2 * AHEAD:
                        prefetch(&tri[across[t + 2 * AHEAD, k], 0])
            if t + AHEAD < stop:                             # then their far corners
                for k in range(3):
                    u = across[t + AHEAD, k]
                    if u > t + AHEAD:
                        prefetch(&xy[tri[u, 0] + tri[u, 1] + tri[u, 2] - tri[t + AHEAD, (k + 1) % 3]
                                     - tri[t + AHEAD, (k + 2) % 3], 0])
            for k in range(3):
                u = across[t, k]
                if u <= t:
                    continue
                a = tri[t, k]
                b = tri[t, (k + 1) % 3]
                c = tri[t, (k + 2) % 3]
                d = tri[u, 0] + tri[u, 1] + tri[u, 2] - b - c     # u's corner off the edge
                adx = xy[a, 0] - xy[d, 0]
                ady = xy[a, 1] - xy[d, 1]
                bdx = xy[b, 0] - xy[d, 0]
                bdy = xy[b, 1] - xy[d, 1]
                cdx = xy[c, 0] - xy[d, 0]
                cdy = xy[c, 1] - xy[d, 1]
                alift = adx * adx + ady * ady
                blift = bdx * bdx + bdy * bdy
                clift = cdx * cdx + cdy * cdy
                det = (alift * (bdx * cdy - cdx * bdy) + blift * (cdx * ady - adx * cdy)
                       + clift * (adx * bdy - bdx * ady))
                permanent = (alift * (fabs(bdx * cdy) + fabs(cdx * bdy))
                             + blift * (fabs(cdx * ady) + fabs(adx * cdy))
                             + clift * (fabs(adx * bdy) + fabs(bdx * ady)))
                if fabs(det) <= bound * permanent:
                    # a rectangle is cocircular exactly, whatever its float determinant
                    if _rectangle(xy[a, 0], xy[a, 1], xy[b, 0], xy[b, 1], xy[c, 0], xy[c, 1],
                                  xy[d, 0], xy[d, 1]):
                        flag[t, k] = _RECTANGLE
                    else:
                        flag[t, k] = _NEAR
                elif det > 0:
                    flag[t, k] = _ILLEGAL


def drop_super_triangle(const uint32_t[:, ::1] vertices, const uint32_t[:, ::1] neighbours,
                        int64_t n_points, const int64_t[::1] label):
    """CDT's triangulation of n_points points as its erase_super_triangle leaves it, from
    its rows before it: vertices (T, 3) (0, 1, 2 the super triangle's corners, the points
    3 ... n_points + 2) and neighbours (T, 3) (the triangle across the edge from corner k
    to corner k + 1, none as 2**32 - 1). Returns (tri, across) (m, 3) int64: as CDT
    leaves them, the rows with no super-triangle corner in their order, the point CDT
    numbers i (from 0) numbered label[i], a dropped neighbour none; and, as
    canonical_ties wants them, slot k
    the triangle across the edge opposite corner k, none as -1. None when a row holds a
    number out of range (the caller then lets CDT erase)."""
    cdef Py_ssize_t T = vertices.shape[0], t, k, m = 0
    cdef uint32_t none = 0xFFFFFFFF, v, n
    cdef uint32_t top = <uint32_t> (n_points + 3)
    cdef int64_t[::1] number = np.empty(T, dtype=np.int64)
    cdef bint bad = False
    with nogil:
        for t in range(T):
            number[t] = -1
            if vertices[t, 0] >= 3 and vertices[t, 1] >= 3 and vertices[t, 2] >= 3:
                number[t] = m
                m += 1
    tri_ = np.empty((m, 3), dtype=np.int64)
    across_ = np.empty((m, 3), dtype=np.int64)
    cdef int64_t[:, ::1] tri = tri_, across = across_
    with nogil:
        for t in range(T):
            if number[t] < 0:
                continue
            for k in range(3):
                v = vertices[t, k]
                n = neighbours[t, (k + 1) % 3]
                if v >= top or (n != none and n >= T):
                    bad = True
                    break
                tri[number[t], k] = label[v - 3]
                across[number[t], k] = -1 if n == none else number[n]
            if bad:
                break
    return None if bad else (tri_, across_)


def cell_order(const double[:, ::1] xy, double per_cell):
    """(n,) int64 the points xy (n, 2) ordered by the cells of a square grid over their box
    holding about per_cell points each, the cells row by row (every other row backwards),
    each cell's points in index order: core/_counting.pxd's counting sort. The cell side
    is at least the box's longer side × per_cell / n, so that a box thin along one axis
    gets at most about 3 n / per_cell cells."""
    cdef Py_ssize_t n = xy.shape[0], i
    order_ = np.arange(n, dtype=np.int64)
    if n < 2:
        return order_
    cdef double x0 = xy[0, 0], x1 = xy[0, 0], y0 = xy[0, 1], y1 = xy[0, 1]
    with nogil:
        for i in range(n):
            x0 = min(x0, xy[i, 0])
            x1 = max(x1, xy[i, 0])
            y0 = min(y0, xy[i, 1])
            y1 = max(y1, xy[i, 1])
    cdef double side = max(sqrt((x1 - x0) * (y1 - y0) * per_cell / n), max(x1 - x0, y1 - y0) * per_cell / n)
    if not side > 0:                       # one position: any order
        return order_
    cdef int64_t nx = <int64_t> floor((x1 - x0) / side) + 1, ny = <int64_t> floor((y1 - y0) / side) + 1
    cdef int64_t[::1] cell = np.empty(n, dtype=np.int64)
    cdef int64_t[::1] start = np.empty(nx * ny + 1, dtype=np.int64)
    cdef int64_t[::1] order = order_
    cdef int64_t ix, iy
    with nogil:
        for i in range(n):
            ix = min(<int64_t> ((xy[i, 0] - x0) / side), nx - 1)
            iy = min(<int64_t> ((xy[i, 1] - y0) / side), ny - 1)
            if iy % 2:
                ix = nx - 1 - ix
            cell[i] = iy * nx + ix
        stable_order(&cell[0], n, &start[0], nx * ny, &order[0])
    return order_
