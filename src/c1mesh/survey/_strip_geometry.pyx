# cython: language_level=3
"""The buffered Delaunay's certification kernels: c1mesh.survey.strip_geometry wraps them
(validation, the polygon test of the few disks that reach a strip's rectangle), and nothing
else imports them.

Each function is one pass over triangles or edges doing, per element, the arithmetic that
numpy did over whole arrays, in the same order and with the same operations (no fused
multiply-add: the build sets -ffp-contract=off), so every centre, radius and decision is
the same to the bit. `_nan_max` is np.maximum's rule (a NaN wins), which decides the
degenerate triangles' NaN centres as numpy did: they reach nothing.
"""
from libc.math cimport hypot, INFINITY, isfinite
from libc.stdint cimport int64_t, uint8_t

from c1mesh.core._prefetch cimport AHEAD, prefetch, prefetch_corners
from c1mesh.core._triangles cimport corner_offsets


cdef inline double _nan_max(double a, double b) noexcept nogil:
    """np.maximum(a, b): the NaN of either, else the larger."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


cdef inline bint _reaches(double cx, double cy, double reach, const double[:, ::1] strips,
                          Py_ssize_t s) noexcept nogil:
    """Whether the disk (cx, cy, reach) reaches the rectangle strips[s] (x0, y0, x1, y1)."""
    cdef double dx = _nan_max(_nan_max(strips[s, 0] - cx, cx - strips[s, 2]), 0.0)
    cdef double dy = _nan_max(_nan_max(strips[s, 1] - cy, cy - strips[s, 3]), 0.0)
    return hypot(dx, dy) <= reach


def circumcircles(const double[:, ::1] xy, const int64_t[:, ::1] tri, double[:, ::1] centre,
                  double[::1] radius):
    """centre (k, 2), radius (k,) of the triangles tri (k, 3) into xy (n, 2): the corner a
    plus (ux, uy), the solution of the two chord equations, as strip_geometry.circumcircles
    documents; a degenerate triangle's radius is infinite."""
    cdef Py_ssize_t t, k = tri.shape[0]
    cdef double ax, ay, bx, by, cx, cy, d, bb, cc, ux, uy, r
    cdef double c[6]           # corner a, then b - a and c - a
    with nogil:
        for t in range(k):
            prefetch_corners(xy, tri, t + AHEAD, k)
            corner_offsets(xy, tri, t, c)
            ax, ay, bx, by, cx, cy = c[0], c[1], c[2], c[3], c[4], c[5]
            d = 2.0 * (bx * cy - by * cx)
            bb = bx * bx + by * by
            cc = cx * cx + cy * cy
            ux = (cy * bb - by * cc) / d
            uy = (bx * cc - cx * bb) / d
            r = hypot(ux, uy)
            radius[t] = r if isfinite(r) else INFINITY
            centre[t, 0] = ax + ux
            centre[t, 1] = ay + uy


def strip_hits(const double[:, ::1] centre, const double[::1] radius, double scale,
               const double[:, ::1] strips, uint8_t[:, ::1] hits):
    """hits (k, s): whether disk k, its radius grown by the relative margin 1e-9 plus
    1e-12 · scale, reaches strip rectangle s (strip_geometry.disks_clear's first test)."""
    cdef Py_ssize_t i, s, k = centre.shape[0], m = strips.shape[0]
    cdef double reach, margin = 1e-12 * scale
    with nogil:
        for i in range(k):
            reach = radius[i] * (1 + 1e-9) + margin
            for s in range(m):
                hits[i, s] = _reaches(centre[i, 0], centre[i, 1], reach, strips, s)


def smallest_empty_circles(const double[:, ::1] xy, const int64_t[:, ::1] simplices,
                           const int64_t[:, ::1] neighbors, const int64_t[::1] t, const int64_t[::1] k,
                           const int64_t[::1] a, const int64_t[::1] b, const double[:, ::1] centres,
                           double[:, ::1] best, double[::1] radius):
    """best (e, 2) and radius (e,): strip_geometry.smallest_empty_circle's centre for each
    edge (a, b) opposite corner k of triangle t, and its distance to corner a."""
    cdef Py_ssize_t i, e = t.shape[0]
    cdef int64_t other
    cdef double mx, my, c1x, c1y, sx, sy, length2, s, ex, ey, ox, oy, px, py
    with nogil:
        for i in range(e):
            mx = (xy[a[i], 0] + xy[b[i], 0]) / 2
            my = (xy[a[i], 1] + xy[b[i], 1]) / 2
            c1x = centres[t[i], 0]
            c1y = centres[t[i], 1]
            other = neighbors[t[i], k[i]]
            if other < 0:                           # a hull edge: from c1 away from the apex
                ex = xy[b[i], 0] - xy[a[i], 0]
                ey = xy[b[i], 1] - xy[a[i], 1]
                ox = ey
                oy = -ex
                px = xy[simplices[t[i], k[i]], 0] - xy[a[i], 0]
                py = xy[simplices[t[i], k[i]], 1] - xy[a[i], 1]
                if px * ox + py * oy > 0:
                    ox = -ox
                    oy = -oy
                if (mx - c1x) * ox + (my - c1y) * oy > 0:
                    best[i, 0] = mx
                    best[i, 1] = my
                else:
                    best[i, 0] = c1x
                    best[i, 1] = c1y
            else:
                sx = centres[other, 0] - c1x
                sy = centres[other, 1] - c1y
                length2 = sx * sx + sy * sy
                if length2 == 0:
                    s = 0.0
                else:
                    s = ((mx - c1x) * sx + (my - c1y) * sy) / length2
                    if s < 0.0:
                        s = 0.0
                    elif s > 1.0:
                        s = 1.0
                best[i, 0] = c1x + s * sx
                best[i, 1] = c1y + s * sy
            radius[i] = hypot(xy[a[i], 0] - best[i, 0], xy[a[i], 1] - best[i, 1])


def triangle_flags(const double[:, ::1] xy, const int64_t[:, ::1] simplices, const int64_t[:, ::1] neighbors,
                   const uint8_t[::1] own, const int64_t[::1] index, double bound, double[::1] longest,
                   uint8_t[::1] at_own, uint8_t[::1] mine, int64_t[:, ::1] edges, double[::1] lengths):
    """Per triangle of simplices (T, 3) into the tile's points xy (n, 2), own (n,) and
    survey numbers index (n,): longest (T,) its longest edge (libm's hypot, as
    stages.trim.edge_lengths measures it); at_own (T,) a corner is own and longest <= bound
    (its circumdisk must be certified); mine (T,) its lowest-numbered corner is own and
    longest <= bound (the tile writes it).

    With room for them (edges (3T, 4), lengths (3T,); neighbors (T, 3)), in the same pass
    each edge of the triangulation once (on the hull, or towards a higher-numbered
    triangle), in row order of (triangle t, corner k), that is at most `bound` long and
    whose lower-numbered end is own: rows (t, k, a, b) with a, b the ends (corners k + 1,
    k + 2) and its length. Returns their count (0 without room)."""
    cdef Py_ssize_t t, T = simplices.shape[0], count = 0
    cdef int k
    cdef bint with_edges = edges.shape[0] > 0
    cdef int64_t p, q, r, low, a, b, other
    cdef double m
    cdef double e[3]
    with nogil:
        for t in range(T):
            if t + AHEAD < T:                      # a later triangle's corners' rows
                prefetch_corners(xy, simplices, t + AHEAD, T)
                for k in range(3):
                    prefetch(&index[simplices[t + AHEAD, k]])
            p = simplices[t, 0]
            q = simplices[t, 1]
            r = simplices[t, 2]
            e[0] = hypot(xy[r, 0] - xy[q, 0], xy[r, 1] - xy[q, 1])      # the edge opposite corner k
            e[1] = hypot(xy[p, 0] - xy[r, 0], xy[p, 1] - xy[r, 1])
            e[2] = hypot(xy[q, 0] - xy[p, 0], xy[q, 1] - xy[p, 1])
            m = e[0] if e[0] >= e[1] else e[1]
            m = m if m >= e[2] else e[2]
            if e[0] != e[0] or e[1] != e[1] or e[2] != e[2]:       # numpy's max: a NaN wins
                m = e[0] + e[1] + e[2]
            longest[t] = m
            low = index[p]
            if index[q] < low:
                low = index[q]
            if index[r] < low:
                low = index[r]
            at_own[t] = (own[p] or own[q] or own[r]) and m <= bound
            mine[t] = ((own[p] and index[p] == low) or (own[q] and index[q] == low)
                       or (own[r] and index[r] == low)) and m <= bound
            if not with_edges:
                continue
            for k in range(3):
                other = neighbors[t, k]
                if other >= 0 and other <= t:
                    continue
                a = simplices[t, (k + 1) % 3]
                b = simplices[t, (k + 2) % 3]
                if not (e[k] <= bound and own[a if index[a] < index[b] else b]):
                    continue
                edges[count, 0] = t
                edges[count, 1] = k
                edges[count, 2] = a
                edges[count, 3] = b
                lengths[count] = e[k]
                count += 1
    return count
