# cython: language_level=3
"""The lattice solver's block Gauss–Seidel kernels: c1mesh.stages.lattice_solver wraps them
(validation, the vertices of one colour in fixed blocks in the thread knob's threads), and
nothing else imports them.

S is the smoothing system on lattice nodes, 3 unknowns per vertex (rows 3v, 3v + 1,
3v + 2 of a CSR matrix), coupled only along the 7-point stencil of the split cells, so
vertices of one colour (i + j) mod 3 never touch each other: a block of them reads
only other colours' unknowns and writes only its own, and the bits do not depend on
the blocks' threads. The sums run over each row's stored entries in their order
(-ffp-contract=off: no fused multiply-add).
"""
from libc.math cimport isfinite
from libc.stdint cimport int8_t, int32_t, int64_t

ctypedef fused index_t:
    int32_t
    int64_t


def block_inverses(const index_t[::1] indptr, const index_t[::1] indices, const double[::1] data,
                   const int8_t[::1] colour, double[:, :, ::1] dinv, Py_ssize_t start, Py_ssize_t stop):
    """dinv[v] (3, 3): the inverse of S's diagonal 3 × 3 block at vertex v, for
    start <= v < stop (the adjugate over the determinant). Returns (couplings, singular):
    the nonzero entries of those rows that couple v to another vertex of its colour
    (none in a lattice system), and the blocks whose determinant is not positive and
    finite (their dinv is zero: the sweep leaves those vertices alone)."""
    cdef Py_ssize_t v, row, k, w
    cdef int p, q
    cdef double d[3][3]
    cdef double det
    cdef int64_t couplings = 0, singular = 0
    with nogil:
        for v in range(start, stop):
            for p in range(3):
                for q in range(3):
                    d[p][q] = 0.0
            for p in range(3):
                row = 3 * v + p
                for k in range(indptr[row], indptr[row + 1]):
                    w = indices[k] // 3
                    if w == v:
                        d[p][indices[k] - 3 * v] = data[k]
                    elif colour[w] == colour[v] and data[k] != 0.0:
                        couplings += 1
            dinv[v, 0, 0] = d[1][1] * d[2][2] - d[1][2] * d[2][1]
            dinv[v, 0, 1] = d[0][2] * d[2][1] - d[0][1] * d[2][2]
            dinv[v, 0, 2] = d[0][1] * d[1][2] - d[0][2] * d[1][1]
            dinv[v, 1, 0] = d[1][2] * d[2][0] - d[1][0] * d[2][2]
            dinv[v, 1, 1] = d[0][0] * d[2][2] - d[0][2] * d[2][0]
            dinv[v, 1, 2] = d[0][2] * d[1][0] - d[0][0] * d[1][2]
            dinv[v, 2, 0] = d[1][0] * d[2][1] - d[1][1] * d[2][0]
            dinv[v, 2, 1] = d[0][1] * d[2][0] - d[0][0] * d[2][1]
            dinv[v, 2, 2] = d[0][0] * d[1][1] - d[0][1] * d[1][0]
            det = d[0][0] * dinv[v, 0, 0] + d[0][1] * dinv[v, 1, 0] + d[0][2] * dinv[v, 2, 0]
            if det > 0.0 and isfinite(det):
                for p in range(3):
                    for q in range(3):
                        dinv[v, p, q] = dinv[v, p, q] / det
            else:
                singular += 1
                for p in range(3):
                    for q in range(3):
                        dinv[v, p, q] = 0.0
    return couplings, singular


def sweep(const index_t[::1] indptr, const index_t[::1] indices, const double[::1] data,
          const double[::1] b, double[::1] x, const double[:, :, ::1] dinv, Py_ssize_t start, Py_ssize_t stop):
    """One block Gauss–Seidel step on the vertices start <= v < stop (all of one colour):
    for each, r = b[3v:3v+3] − (S x)[3v:3v+3] over its three CSR rows, then
    x[3v:3v+3] += dinv[v] r. In place. The level numbers its vertices colour by colour,
    so a colour's rows are read in one stream (every third vertex of the grid's order
    took 6 times as long per vertex)."""
    cdef Py_ssize_t v, row, k
    cdef int p
    cdef double r[3]
    cdef double acc
    with nogil:
        for v in range(start, stop):
            for p in range(3):
                row = 3 * v + p
                acc = b[row]
                for k in range(indptr[row], indptr[row + 1]):
                    acc = acc - data[k] * x[indices[k]]
                r[p] = acc
            for p in range(3):
                x[3 * v + p] = x[3 * v + p] + (dinv[v, p, 0] * r[0] + dinv[v, p, 1] * r[1]
                                               + dinv[v, p, 2] * r[2])
