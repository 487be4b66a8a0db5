# cython: language_level=3
"""The in-circle screen of c1mesh.engine.triangulation.canonical_ties: for every interior
edge of a Delaunay triangulation, whether the four points of its two triangles may lie on
one circle. Each triangle writes only its own row: any block of triangles in any thread.
"""
from libc.math cimport fabs
from libc.stdint cimport int8_t, int64_t

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
