# cython: language_level=3
"""The trim's kernels: c1mesh.stages.trim wraps them (validation, threads), and nothing else
imports them. The triangles of a Delaunay triangulation come in no particular order of
their points, so every kernel reads its points as rows (x, y together: one cache line)."""
import numpy as np

from libc.math cimport hypot, sqrt
from libc.stdint cimport int64_t, uint8_t, uint64_t

from c1mesh.core._prefetch cimport AHEAD, prefetch, prefetch_corners
from c1mesh.core._union_find cimport root


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
            prefetch_corners(xy, tri, t + AHEAD, stop)
            a = tri[t, 0]
            b = tri[t, 1]
            c = tri[t, 2]
            out[t, 0] = hypot(xy[c, 0] - xy[b, 0], xy[c, 1] - xy[b, 1])
            out[t, 1] = hypot(xy[a, 0] - xy[c, 0], xy[a, 1] - xy[c, 1])
            out[t, 2] = hypot(xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1])


cdef inline bint _counts_edge(const int64_t[:, ::1] neighbours, Py_ssize_t t, int k) noexcept nogil:
    """Whether triangle t holds its edge opposite corner k once for the whole triangulation:
    the triangle across it is none (-1) or comes later."""
    return neighbours[t, k] < 0 or neighbours[t, k] > t


def once_count(const int64_t[:, ::1] neighbours, Py_ssize_t start, Py_ssize_t stop):
    """How many lengths once_lengths writes for the triangles start <= t < stop."""
    cdef Py_ssize_t t, count = 0
    cdef int k
    with nogil:
        for t in range(start, stop):
            for k in range(3):
                count += _counts_edge(neighbours, t, k)
    return count


def once_lengths(const double[:, ::1] lengths, const int64_t[:, ::1] neighbours, double[::1] out,
                 Py_ssize_t start, Py_ssize_t stop):
    """Each edge's length once: lengths[t, k] (T, 3) where the triangle across, neighbours
    [t, k] (T, 3), is none (-1) or comes later (> t), for the triangles start <= t < stop
    in row order into out (from its start: once_count of them). Returns how many."""
    cdef Py_ssize_t t, count = 0
    cdef int k
    with nogil:
        for t in range(start, stop):
            for k in range(3):
                if _counts_edge(neighbours, t, k):
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


cdef inline double _side(const double[:, ::1] xy, int64_t a, int64_t b) noexcept nogil:
    """The distance from point a to point b by sqrt, within a few ulps of libm's hypot."""
    cdef double dx = xy[b, 0] - xy[a, 0], dy = xy[b, 1] - xy[a, 1]
    return sqrt(dx * dx + dy * dy)


def thin_rows_at(const double[:, ::1] xy, const int64_t[:, ::1] tri, const uint8_t[::1] alive,
                 double min_ratio, double screen, int64_t[::1] out):
    """`thin_rows` from the corners' coordinates xy (n, 2) instead of stored lengths: the
    live triangles of tri (T, 3) whose circle ratio of edge lengths (hypot, as
    edge_lengths measures them) is below min_ratio, ascending into out (T,). Returns how
    many. Each triangle's ratio is first screened with sqrt lengths (a few times faster
    than hypot); those below `screen`, or with a side under a millionth of another, get
    hypot's lengths and the exact test. With its sides within a factor 1e6, a ratio's
    rounding is below 1e-8 either way, so a screen well above min_ratio (the caller's
    2 x, c1mesh.stages.trim._thin_rows_at) skips no thin triangle. One thread."""
    cdef Py_ssize_t T = tri.shape[0], t, count = 0
    cdef int64_t a, b, c
    cdef double la, lb, lc, shortest, longest
    with nogil:
        for t in range(T):
            if not alive[t]:
                continue
            a = tri[t, 0]
            b = tri[t, 1]
            c = tri[t, 2]
            la = _side(xy, b, c)
            lb = _side(xy, c, a)
            lc = _side(xy, a, b)
            shortest = min(la, min(lb, lc))
            longest = max(la, max(lb, lc))
            # a side a millionth of another: rounding could move the ratio; the exact test
            if _circle_ratio(la, lb, lc) >= screen and shortest >= 1e-6 * longest:
                continue
            if _circle_ratio(hypot(xy[c, 0] - xy[b, 0], xy[c, 1] - xy[b, 1]),
                             hypot(xy[a, 0] - xy[c, 0], xy[a, 1] - xy[c, 1]),
                             hypot(xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1])) < min_ratio:
                out[count] = t
                count += 1
    return count


# ---- survey-number lookups of a survey's halos (c1mesh.survey.halos, .trim_runs) --------
# Open-addressing hash tables (linear probing, a power-of-two size at least twice the
# keys): one pass over the triangles, no sort of them, memory of the keys' size.

cdef inline uint64_t _spread(uint64_t h) noexcept nogil:
    """A 64-bit finaliser (splitmix64's): every input bit moves every output bit."""
    h ^= h >> 30
    h *= 0xBF58476D1CE4E5B9ULL
    h ^= h >> 27
    h *= 0x94D049BB133111EBULL
    h ^= h >> 31
    return h


cdef inline uint64_t _triple_hash(int64_t a, int64_t b, int64_t c) noexcept nogil:
    return _spread(_spread(_spread(<uint64_t>a) ^ <uint64_t>b) ^ <uint64_t>c)


cdef inline void _sort3(int64_t *a, int64_t *b, int64_t *c) noexcept nogil:
    cdef int64_t s
    if a[0] > b[0]:
        s = a[0]; a[0] = b[0]; b[0] = s
    if b[0] > c[0]:
        s = b[0]; b[0] = c[0]; c[0] = s
    if a[0] > b[0]:
        s = a[0]; a[0] = b[0]; b[0] = s


def kept_triangles(const int64_t[:, ::1] corners, const int64_t[::1] numbers, bint mapped,
                   const int64_t[:, ::1] removed, int64_t[::1] table, uint8_t[::1] keep,
                   const uint8_t[::1] candidate):
    """keep[t] = 0 where triangle t of corners (T, 3) is, as a set of corners, a row of
    removed (R, 3), else 1; mapped: corners are rows into numbers (m,), and compared as
    numbers[corner]. table: (S,) filled with -1, S a power of two >= 2R (the removed
    rows' slots). candidate: (m,) nonzero at the rows that are a corner of a removed
    triangle (mapped only; empty: not known), so a triangle whose first corner is not one
    is kept without its numbers looked up. Returns how many are kept. Without the GIL:
    one thread each."""
    cdef Py_ssize_t T = corners.shape[0], R = removed.shape[0], t, r, count = 0
    cdef bint screened = mapped and candidate.shape[0] > 0
    cdef uint64_t mask = <uint64_t>table.shape[0] - 1, slot
    cdef int64_t a, b, c, x, y, z, found
    with nogil:
        for r in range(R):
            a = removed[r, 0]
            b = removed[r, 1]
            c = removed[r, 2]
            _sort3(&a, &b, &c)
            slot = _triple_hash(a, b, c) & mask
            while table[slot] >= 0:
                slot = (slot + 1) & mask
            table[slot] = r
        for t in range(T):
            if screened and not candidate[corners[t, 0]]:
                keep[t] = 1
                count += 1
                continue
            if mapped and not screened and t + AHEAD < T:        # a later triangle's corners' numbers
                for r in range(3):
                    prefetch(&numbers[corners[t + AHEAD, r]])
            a = corners[t, 0]
            b = corners[t, 1]
            c = corners[t, 2]
            if mapped:
                a = numbers[a]
                b = numbers[b]
                c = numbers[c]
            _sort3(&a, &b, &c)
            slot = _triple_hash(a, b, c) & mask
            keep[t] = 1
            while True:
                found = table[slot]
                if found < 0:
                    break
                x = removed[found, 0]
                y = removed[found, 1]
                z = removed[found, 2]
                _sort3(&x, &y, &z)
                if x == a and y == b and z == c:
                    keep[t] = 0
                    break
                slot = (slot + 1) & mask
            count += keep[t]
    return count


cdef enum:
    FILTER_SHIFT = 32    # a number's filter bit comes from the top half of its hash, its slot from the bottom


def number_table(const int64_t[::1] index, int64_t[:, ::1] table, uint64_t[::1] bits):
    """Fill table (S, 2) (every row -1, -1 on entry; S a power of two >= 2m) with each of
    index (m,) (distinct numbers) and its row, by linear probing, and set its bit in bits
    (B,) (zero on entry; 64 B a power of two): the hash `triangles_among` looks numbers
    up in. One thread."""
    cdef Py_ssize_t m = index.shape[0], i
    cdef uint64_t mask = <uint64_t>table.shape[0] - 1, fmask = <uint64_t>bits.shape[0] * 64 - 1, h, slot, f
    with nogil:
        for i in range(m):
            h = _spread(<uint64_t>index[i])
            f = (h >> FILTER_SHIFT) & fmask
            bits[f >> 6] |= (<uint64_t>1) << (f & 63)
            slot = h & mask
            while table[slot, 1] >= 0:
                slot = (slot + 1) & mask
            table[slot, 0] = index[i]
            table[slot, 1] = i


cdef inline int64_t _row_of(const int64_t *table, uint64_t mask, const uint64_t *bits, uint64_t fmask,
                            int64_t number) noexcept nogil:
    """The row of number through number_table's table and bits, or -1. A number whose bit
    is clear is not there (most numbers a halo looks up: a neighbour's triangles far from
    its cell), found with one read of the bits, which fit in the cache where the table
    does not; the table holds each number beside its row, so a probe reads one line."""
    cdef uint64_t h = _spread(<uint64_t>number), f = (h >> FILTER_SHIFT) & fmask, slot
    if not (bits[f >> 6] >> (f & 63)) & 1:
        return -1
    slot = h & mask
    while True:
        if table[2 * slot + 1] < 0 or table[2 * slot] == number:
            return table[2 * slot + 1]
        slot = (slot + 1) & mask


def triangles_among(const int64_t[:, ::1] table, const uint64_t[::1] bits, const int64_t[:, ::1] triangles,
                    int64_t[:, ::1] out):
    """The triangles (T, 3) of survey numbers whose three corners number_table's table
    (S, 2) and bits hold, as their rows, in their order into out (T, 3). Returns how many.
    One thread."""
    cdef Py_ssize_t T = triangles.shape[0], t, count = 0
    cdef uint64_t mask = <uint64_t>table.shape[0] - 1, fmask = <uint64_t>bits.shape[0] * 64 - 1
    cdef const int64_t *slots = &table[0, 0]
    cdef const uint64_t *filter_bits = &bits[0]
    cdef int64_t a, b, c
    with nogil:
        for t in range(T):
            a = _row_of(slots, mask, filter_bits, fmask, triangles[t, 0])
            if a < 0:
                continue
            b = _row_of(slots, mask, filter_bits, fmask, triangles[t, 1])
            if b < 0:
                continue
            c = _row_of(slots, mask, filter_bits, fmask, triangles[t, 2])
            if c < 0:
                continue
            out[count, 0] = a
            out[count, 1] = b
            out[count, 2] = c
            count += 1
    return count


def component_labels(const int64_t[::1] a, const int64_t[::1] b, int64_t[::1] labels):
    """labels (n,): the connected set of each of n items that the pairs (a[i], b[i]) (m,)
    join, the sets numbered 0, 1, ... in the order of their lowest item (as scipy's
    connected_components numbers an undirected graph's components). Returns how many
    sets. Union-find, one thread."""
    cdef Py_ssize_t n = labels.shape[0], m = a.shape[0], i
    cdef int64_t x, y, count = 0
    parent_ = np.arange(n, dtype=np.int64)
    cdef int64_t[::1] parent = parent_
    with nogil:
        for i in range(m):
            x = root(&parent[0], a[i])
            y = root(&parent[0], b[i])
            if x != y:                              # join at the lower root
                if y < x:
                    x, y = y, x
                parent[y] = x
        for i in range(n):                          # a set's lowest item is its root
            x = root(&parent[0], i)
            if x == i:
                labels[i] = count
                count += 1
            else:
                labels[i] = labels[x]
    return count
