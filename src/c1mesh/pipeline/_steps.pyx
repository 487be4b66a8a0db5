# cython: language_level=3
"""The report's mesh kernels: c1mesh.pipeline.steps wraps them (mesh_pieces), and nothing
else imports them."""
from libc.math cimport fabs
from libc.stdint cimport int64_t

from c1mesh.core._prefetch cimport AHEAD, prefetch
from c1mesh.core._union_find cimport root


def pieces(const int64_t[:, ::1] tri_edge, const int64_t[::1] owner, int64_t[::1] parent,
           int64_t[::1] size):
    """(count, largest): the pieces of the triangles (T,) joined through shared edges, and
    the triangles in the largest. tri_edge (T, 3): each triangle's edges; owner (E,): one
    triangle holding each edge, so a triangle that is not its edge's owner is joined to the
    owner (union-find). parent, size (T,) scratch. One thread."""
    cdef Py_ssize_t T = tri_edge.shape[0], t
    cdef int k
    cdef int64_t a, b, count = 0, largest = 0
    with nogil:
        for t in range(T):
            parent[t] = t
            size[t] = 0
        for t in range(T):
            if t + 2 * AHEAD < T:               # a later triangle's edges' owners, then
                for k in range(3):              # the owners' parents, asked for ahead
                    prefetch(&owner[tri_edge[t + 2 * AHEAD, k]])
            if t + AHEAD < T:
                for k in range(3):
                    prefetch(&parent[owner[tri_edge[t + AHEAD, k]]])
            a = root(&parent[0], t)
            for k in range(3):
                b = owner[tri_edge[t, k]]
                if b != t:
                    b = root(&parent[0], b)
                    if a != b:                  # join at the lower root
                        if b < a:
                            a, b = b, a
                        parent[b] = a
        for t in range(T):
            a = root(&parent[0], t)
            if size[a] == 0:
                count += 1
            size[a] += 1
            if size[a] > largest:
                largest = size[a]
    return count, largest


def doubled_areas(const double[::1] x, const double[::1] y, const int64_t[:, ::1] tri,
                  double[::1] out, Py_ssize_t start, Py_ssize_t stop):
    """out[t] = |(x1 − x0)(y2 − y0) − (y1 − y0)(x2 − x0)|, twice the area of triangle t of
    tri (T, 3) over x, y (n,) (corners 0, 1, 2), for start <= t < stop; in the square of
    xy's unit."""
    cdef Py_ssize_t t
    cdef double x0, y0, ux, uy, vx, vy
    with nogil:
        for t in range(start, stop):
            x0 = x[tri[t, 0]]
            y0 = y[tri[t, 0]]
            ux = x[tri[t, 1]] - x0
            uy = y[tri[t, 1]] - y0
            vx = x[tri[t, 2]] - x0
            vy = y[tri[t, 2]] - y0
            out[t] = fabs(ux * vy - uy * vx)


def number_used(const int64_t[:, ::1] tri, int64_t[::1] remap):
    """Number the points (n,) that the triangles tri (T, 3) use in ascending order: remap
    (n,), which must start at -1, gets each used point's new number (unused: -1). Returns
    how many points are used. One thread: a mark pass over the triangles (their corners'
    entries asked for ahead) and a numbering pass over the points."""
    cdef Py_ssize_t T = tri.shape[0], n = remap.shape[0], t, v
    cdef int k
    cdef int64_t count = 0
    with nogil:
        for t in range(T):
            if t + AHEAD < T:
                for k in range(3):
                    prefetch(&remap[tri[t + AHEAD, k]])
            for k in range(3):
                remap[tri[t, k]] = 0
        for v in range(n):
            if remap[v] == 0:
                remap[v] = count
                count += 1
            else:
                remap[v] = -1
    return count


def renumber_rows(const int64_t[:, ::1] tri, const int64_t[::1] remap, int64_t[:, ::1] out,
                  Py_ssize_t start, Py_ssize_t stop):
    """out[t] = remap[tri[t]] (T, 3) for the triangles start <= t < stop (number_used's
    numbers): each block writes its own rows, in any thread."""
    cdef Py_ssize_t t
    cdef int k
    with nogil:
        for t in range(start, stop):
            if t + AHEAD < stop:
                for k in range(3):
                    prefetch(&remap[tri[t + AHEAD, k]])
            for k in range(3):
                out[t, k] = remap[tri[t, k]]


cdef inline double _cross(const double[::1] x, const double[::1] y, int64_t o, int64_t a,
                          int64_t b) noexcept nogil:
    return (x[a] - x[o]) * (y[b] - y[o]) - (y[a] - y[o]) * (x[b] - x[o])


def hull_area(const double[::1] x, const double[::1] y, int64_t[::1] chain) -> float:
    """The area of the convex hull of the points (x, y) (n,), sorted by x then y (Andrew's
    monotone chain: the lower hull left to right, then the upper right to left, dropping
    every turn that is not strictly to the left; the area as a fan of triangles from its
    first corner, so large coordinates (state plane) lose no digits). chain (2n + 1,)
    scratch. 0 for fewer than 3 points or points on one line."""
    cdef Py_ssize_t n = x.shape[0], i, k = 0, lower
    cdef double twice = 0.0
    if n < 3:
        return 0.0
    with nogil:
        for i in range(n):
            while k >= 2 and _cross(x, y, chain[k - 2], chain[k - 1], i) <= 0:
                k -= 1
            chain[k] = i
            k += 1
        lower = k + 1
        for i in range(n - 2, -1, -1):
            while k >= lower and _cross(x, y, chain[k - 2], chain[k - 1], i) <= 0:
                k -= 1
            chain[k] = i
            k += 1
        for i in range(1, k - 2):               # the fan from chain[0] (chain[k - 1] is it again):
            twice += _cross(x, y, chain[0], chain[i], chain[i + 1])     # no far-off coordinates
    return 0.5 * twice
