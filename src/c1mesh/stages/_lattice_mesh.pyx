# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
"""The lattice mesh's kernels: c1mesh.stages.lattice_mesh wraps them (validation, the
bucket grid's size, the blocks in the thread knob's threads), and nothing else imports
them. Squared distances dx*dx + dy*dy, unfused (the build's -ffp-contract=off), so a
position's answer does not depend on the block or thread that computes it."""
from libc.math cimport floor
from libc.stdint cimport int64_t
from libc.stdlib cimport free, malloc

from c1mesh.core._counting cimport stable_order


def bucket_points(const double[:, ::1] xy, const int64_t[::1] index, const int64_t[::1] bucket,
                  int64_t buckets, int64_t[::1] start, double[:, ::1] held, int64_t[::1] ids) -> None:
    """Counting sort of the points xy (m, 2) by bucket (m,), stable (core/_counting.pxd):
    start (buckets + 1,) the first slot of each bucket; held (m, 2) and ids (m,) the points'
    coordinates and index, bucket by bucket, in row order within one."""
    cdef Py_ssize_t m = xy.shape[0], slot
    cdef int64_t p
    cdef int64_t *order = <int64_t *> malloc(max(m, 1) * sizeof(int64_t))
    if order == NULL:
        raise MemoryError()
    with nogil:
        stable_order(&bucket[0] if m else NULL, m, &start[0], buckets, order)
        for slot in range(m):
            p = order[slot]
            held[slot, 0] = xy[p, 0]
            held[slot, 1] = xy[p, 1]
            ids[slot] = index[p]
    free(order)


cdef inline int64_t _max(int64_t a, int64_t b) noexcept nogil:
    return a if a > b else b


cdef inline int64_t _min(int64_t a, int64_t b) noexcept nogil:
    return a if a < b else b


cdef struct Best:
    double d2
    int64_t id


cdef inline void _visit(Best *best, double px, double py, int64_t a, int64_t b,
                        const double[:, ::1] held, const int64_t[::1] ids) noexcept nogil:
    """best updated with the slots [a, b) of one bucket: the lower squared distance, or the
    lower id at an equal one."""
    cdef Py_ssize_t s
    cdef double dx, dy, d2
    for s in range(a, b):
        dx = px - held[s, 0]
        dy = py - held[s, 1]
        d2 = dx * dx + dy * dy
        if best.id < 0 or d2 < best.d2 or (d2 == best.d2 and ids[s] < best.id):
            best.d2 = d2
            best.id = ids[s]


def nearest_in_buckets(const double[:, ::1] positions, Py_ssize_t first, Py_ssize_t stop,
                       const int64_t[::1] start, const double[:, ::1] held, const int64_t[::1] ids,
                       double x0, double y0, double size, int64_t cols, int64_t bucket_rows,
                       int64_t[::1] out) -> None:
    """out[q] = the id of the point nearest position q, for q in [first, stop): the lowest
    id among the equally near. The buckets (cols × bucket_rows squares of side `size` from
    (x0, y0), bucket_points' start/held/ids) are searched in square rings around the
    position's bucket (which may lie off the grid), from the first ring that meets the
    grid, until the best squared distance is below (r·size)², the least of any point beyond
    ring r: no farther point can then be as near."""
    cdef Py_ssize_t q
    cdef int64_t ci, cj, r, i, j, i_lo, i_hi, j_lo, j_hi, b, side
    cdef double px, py, bound
    cdef Best best
    with nogil:
        for q in range(first, stop):
            px = positions[q, 0]
            py = positions[q, 1]
            ci = <int64_t> floor((px - x0) / size)
            cj = <int64_t> floor((py - y0) / size)
            r = _max(_max(_max(-ci, ci - (cols - 1)), _max(-cj, cj - (bucket_rows - 1))), 0)
            best.d2 = 0.0
            best.id = -1
            while True:
                i_lo, i_hi = _max(ci - r, 0), _min(ci + r, cols - 1)
                j_lo, j_hi = _max(cj - r + 1, 0), _min(cj + r - 1, bucket_rows - 1)
                for side in range(2 if r > 0 else 1):                 # the ring's rows ...
                    j = cj - r + 2 * r * side
                    if 0 <= j < bucket_rows:
                        for i in range(i_lo, i_hi + 1):
                            b = j * cols + i
                            _visit(&best, px, py, start[b], start[b + 1], held, ids)
                if r > 0:                                              # ... and columns
                    for side in range(2):
                        i = ci - r + 2 * r * side
                        if 0 <= i < cols:
                            for j in range(j_lo, j_hi + 1):
                                b = j * cols + i
                                _visit(&best, px, py, start[b], start[b + 1], held, ids)
                bound = r * size
                if best.id >= 0 and best.d2 < bound * bound:
                    break
                r += 1
            out[q] = best.id
