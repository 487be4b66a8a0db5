# cython: language_level=3
"""The limiter's kernels: c1mesh.stages.limiter wraps them (validation), and nothing else
imports them."""
from libc.math cimport isnan, NAN
from libc.stdint cimport int64_t


cdef inline double _maximum(double a, double b) noexcept nogil:
    """numpy's maximum: NaN when either is NaN, else the larger."""
    if isnan(a) or isnan(b):
        return NAN
    return a if a >= b else b


def longest_adjacent(const double[::1] length2, const int64_t[:, ::1] tri_edge,
                     const int64_t[::1] owner, double[::1] per_triangle, double[::1] out):
    """out (E,): the largest length2 (E,) over the edges of the one or two triangles holding
    each edge (tri_edge (T, 3) the triangles' edges, owner (E,) one triangle of each edge);
    per_triangle (T,) scratch: each triangle's largest. NaN wherever a NaN takes part, as
    numpy's maximum gives it. Only picks among the values: no rounding. One thread."""
    cdef Py_ssize_t T = tri_edge.shape[0], E = out.shape[0], t, e
    cdef int k
    with nogil:
        for t in range(T):
            per_triangle[t] = _maximum(_maximum(length2[tri_edge[t, 0]], length2[tri_edge[t, 1]]),
                                       length2[tri_edge[t, 2]])
        for e in range(E):
            out[e] = per_triangle[owner[e]]
        for t in range(T):
            for k in range(3):
                e = tri_edge[t, k]
                out[e] = _maximum(out[e], per_triangle[t])
