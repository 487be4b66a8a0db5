# cython: language_level=3
"""The trim's kernel: c1mesh.stages.trim wraps it (validation, threads), and nothing else
imports it."""
from cython.parallel cimport prange
from libc.math cimport hypot
from libc.stdint cimport int64_t

cdef Py_ssize_t BLOCK = 1 << 14
"""Triangles per parallel block: fixed, so every element is computed the same way at any
thread count (each row of the output is written by exactly one block)."""


def edge_lengths(const double[::1] x, const double[::1] y, const int64_t[:, ::1] tri,
                 double[:, ::1] out, int threads):
    """out[t, k] = the length of the edge opposite corner k of triangle t (from corner k + 2
    to corner k + 1, by libm's hypot, as numpy's), for tri (T, 3) into x, y (n,) in one
    unit; out (T, 3) in that unit. `threads` OpenMP threads over blocks of BLOCK triangles."""
    cdef Py_ssize_t T = tri.shape[0], blocks = (T + BLOCK - 1) // BLOCK, b, t, end
    cdef int k
    cdef int64_t i, j
    for b in prange(blocks, nogil=True, num_threads=threads, schedule="static"):
        end = (b + 1) * BLOCK
        if end > T:
            end = T
        for t in range(b * BLOCK, end):
            for k in range(3):
                i = tri[t, (k + 2) % 3]
                j = tri[t, (k + 1) % 3]
                out[t, k] = hypot(x[i] - x[j], y[i] - y[j])
