# cython: language_level=3
"""The trim's kernels: c1mesh.stages.trim wraps them (validation, threads), and nothing else
imports them. The triangles of a Delaunay triangulation come in no particular order of
their points, so every kernel reads its points as rows (x, y together: one cache line)."""
from libc.math cimport hypot
from libc.stdint cimport int64_t, uint8_t


def edge_lengths(const double[:, ::1] xy, const int64_t[:, ::1] tri, double[:, ::1] out,
                 Py_ssize_t start, Py_ssize_t stop):
    """out[t, k] = the length of the edge opposite corner k of triangle t (from corner k + 2
    to corner k + 1, by libm's hypot, as numpy's), for the triangles start <= t < stop of
    tri (T, 3) into xy (n, 2) in one unit; out (T, 3) in that unit. Without the GIL: the
    wrapper runs blocks of triangles in its threads."""
    cdef Py_ssize_t t
    cdef int64_t a, b, c
    with nogil:
        for t in range(start, stop):
            a = tri[t, 0]
            b = tri[t, 1]
            c = tri[t, 2]
            out[t, 0] = hypot(xy[c, 0] - xy[b, 0], xy[c, 1] - xy[b, 1])
            out[t, 1] = hypot(xy[a, 0] - xy[c, 0], xy[a, 1] - xy[c, 1])
            out[t, 2] = hypot(xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1])


def once_lengths(const double[:, ::1] lengths, const int64_t[:, ::1] neighbours, double[::1] out):
    """Each edge's length once: lengths[t, k] (T, 3) where the triangle across, neighbours
    [t, k] (T, 3), is none (-1) or comes later (> t), in row order into out (3T,). Returns
    how many."""
    cdef Py_ssize_t T = lengths.shape[0], t, count = 0
    cdef int k
    with nogil:
        for t in range(T):
            for k in range(3):
                if neighbours[t, k] < 0 or neighbours[t, k] > t:
                    out[count] = lengths[t, k]
                    count += 1
    return count


def mark_used(const int64_t[:, ::1] tri, const uint8_t[::1] alive, uint8_t[::1] used):
    """used[v] = 1 for every corner v of the triangles of tri (T, 3) that are alive (T,);
    used (n,) starts at 0. One thread."""
    cdef Py_ssize_t T = tri.shape[0], t
    with nogil:
        for t in range(T):
            if alive[t]:
                used[tri[t, 0]] = 1
                used[tri[t, 1]] = 1
                used[tri[t, 2]] = 1


def live_rows(const int64_t[:, ::1] tri, const uint8_t[::1] alive, const uint8_t[::1] at,
              bint everywhere, int64_t[::1] out):
    """The live triangles (alive (T,)) of tri (T, 3) with a corner in at (n,) (everywhere:
    all live ones), ascending into out (T,). Returns how many. One thread."""
    cdef Py_ssize_t T = tri.shape[0], t, count = 0
    with nogil:
        for t in range(T):
            if alive[t] and (everywhere or at[tri[t, 0]] or at[tri[t, 1]] or at[tri[t, 2]]):
                out[count] = t
                count += 1
    return count


def open_ends(const int64_t[:, ::1] tri, const uint8_t[::1] alive, const int64_t[:, ::1] neighbours,
              const int64_t[::1] rows, int64_t[::1] ends):
    """ends[v] += 1 for both ends v of every open edge (no live triangle across it,
    neighbours (T, 3)) of the triangles rows (R,) of tri (T, 3). One thread."""
    cdef Py_ssize_t R = rows.shape[0], r
    cdef int64_t t, across
    cdef int k
    with nogil:
        for r in range(R):
            t = rows[r]
            for k in range(3):
                across = neighbours[t, k]
                if across < 0 or not alive[across]:
                    ends[tri[t, (k + 1) % 3]] += 1
                    ends[tri[t, (k + 2) % 3]] += 1


def corner_slots(const int64_t[:, ::1] tri, const int64_t[::1] rows, const uint8_t[::1] marked,
                 int64_t[::1] t_out, int64_t[::1] slot_out):
    """The corners of the triangles rows (R,) of tri (T, 3) at marked (n,) vertices: their
    triangle into t_out and slot (0-2) into slot_out, by row then slot (np.nonzero's order
    of marked[tri[rows]]). Returns how many; t_out, slot_out hold 3R. One thread."""
    cdef Py_ssize_t R = rows.shape[0], r, count = 0
    cdef int64_t t
    cdef int k
    with nogil:
        for r in range(R):
            t = rows[r]
            for k in range(3):
                if marked[tri[t, k]]:
                    t_out[count] = t
                    slot_out[count] = k
                    count += 1
    return count


cdef inline double _circle_ratio(double a, double b, double c) noexcept nogil:
    """2 r_in / R_circ of a triangle with edge lengths a, b, c: (p-2a)(p-2b)(p-2c) / (abc),
    p = a + b + c, evaluated left to right; clipped to [0, 1], NaN (0/0, a point-like
    triangle) as 0."""
    cdef double p = a + b + c
    cdef double ratio = (p - 2 * a) * (p - 2 * b) * (p - 2 * c) / (a * b * c)
    if ratio != ratio or ratio < 0:
        return 0.0
    if ratio > 1:
        return 1.0
    return ratio


def circle_ratios(const double[:, ::1] lengths, double[::1] out, Py_ssize_t start, Py_ssize_t stop):
    """out[t] = the circle ratio of triangle t's edge lengths (T, 3), for start <= t < stop.
    Without the GIL: the wrapper runs blocks of triangles in its threads."""
    cdef Py_ssize_t t
    with nogil:
        for t in range(start, stop):
            out[t] = _circle_ratio(lengths[t, 0], lengths[t, 1], lengths[t, 2])


def thin_rows(const double[:, ::1] lengths, const uint8_t[::1] alive, double min_ratio, int64_t[::1] out):
    """The live triangles (alive (T,)) whose circle ratio of edge lengths (T, 3) is below
    min_ratio, ascending into out (T,). Returns how many. One thread."""
    cdef Py_ssize_t T = lengths.shape[0], t, count = 0
    with nogil:
        for t in range(T):
            if alive[t] and _circle_ratio(lengths[t, 0], lengths[t, 1], lengths[t, 2]) < min_ratio:
                out[count] = t
                count += 1
    return count
