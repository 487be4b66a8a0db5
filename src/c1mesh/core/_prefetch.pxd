# The CPU's prefetch hint (GCC's and Clang's __builtin_prefetch), cimported by the kernels
# whose loops read rows in no order: a triangle's corners, an edge's far end. The row that
# a few iterations later will need is asked for now, so that its cache miss overlaps this
# iteration's work. A hint only: no result depends on it (nothing is compiled from this
# file on its own).
from libc.stdint cimport int64_t


cdef extern from *:
    """
    #define C1MESH_PREFETCH(address) __builtin_prefetch((address), 0, 0)
    """
    void prefetch "C1MESH_PREFETCH"(const void *address) noexcept nogil


# AHEAD: how many iterations ahead a loop asks for rows: far enough for a cache miss to
# arrive (measured on 1M random points: 6 to 12 did alike), near enough to stay cached.
cdef enum:
    AHEAD = 8


cdef inline void prefetch_corners(const double[:, ::1] rows, const int64_t[:, ::1] triangles,
                                  Py_ssize_t t, Py_ssize_t stop) noexcept nogil:
    """Ask for the rows (n, >= 1) of triangle t's three corners, when t < stop: a loop over
    triangles calls it for the triangle some iterations ahead of the one it works on."""
    if t < stop:
        prefetch(&rows[triangles[t, 0], 0])
        prefetch(&rows[triangles[t, 1], 0])
        prefetch(&rows[triangles[t, 2], 0])
