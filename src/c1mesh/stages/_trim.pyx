# cython: language_level=3
"""The trim's kernel: c1mesh.stages.trim wraps it (validation, threads), and nothing else
imports it."""
from libc.math cimport hypot
from libc.stdint cimport int64_t


def edge_lengths(const double[::1] x, const double[::1] y, const int64_t[:, ::1] tri,
                 double[:, ::1] out, Py_ssize_t start, Py_ssize_t stop):
    """out[t, k] = the length of the edge opposite corner k of triangle t (from corner k + 2
    to corner k + 1, by libm's hypot, as numpy's), for the triangles start <= t < stop of
    tri (T, 3) into x, y (n,) in one unit; out (T, 3) in that unit. Without the GIL: the
    wrapper runs blocks of triangles in its threads."""
    cdef Py_ssize_t t
    cdef int k
    cdef int64_t i, j
    with nogil:
        for t in range(start, stop):
            for k in range(3):
                i = tri[t, (k + 2) % 3]
                j = tri[t, (k + 1) % 3]
                out[t, k] = hypot(x[i] - x[j], y[i] - y[j])
