# cython: language_level=3
"""The edge table's kernel: c1mesh.engine.topology wraps it (validation, the EdgeTable), and
nothing else imports it.

Every triangle slot s = 3t + k (the edge opposite local vertex k of triangle t) goes, with one
counting sort, into the bucket of its edge's lower vertex, as the packed value
high << 32 | s; each bucket is then sorted (a few values: insertion sort; a fan's many:
qsort), so the buckets read in order list the unique edges sorted lexicographically, each
edge's occurrences side by side. Linear in T + n plus the buckets' sorts. The counting
sort runs in one thread; the buckets' sorts and the table's fill over ranges of vertices
(their buckets are disjoint), in the wrapper's threads, each range numbering its edges
from the count of the ranges before it: the same table at any thread count.
Vertex numbers and slots must be below 2**31 (the wrapper checks).

The sub-table of kept triangles (topology.sub_table, live_edges) is linear passes over
the whole table: the kept triangles per edge, then the kept triangles, the live edges and
the kept triangles' rows renumbered in order, each pass over ranges of rows numbered from
the rows kept before the range (the wrapper counts them).

The edges alone (topology.unique_edges: bucket_highs, fill_edges) bucket the higher ends
(32 bits) by lower vertex the same way, without the slots, and sort and deduplicate each
bucket in place.
"""
import numpy as np

from libc.stdint cimport int8_t, int32_t, int64_t, uint8_t, uint32_t, uint64_t
from libc.stdlib cimport qsort

cdef int INSERTION_MAX = 24
"""Buckets up to this size are insertion-sorted; larger ones (a vertex with many edges to
higher vertices, such as a fan's centre) go to qsort."""


ctypedef fused bucket_key:
    uint32_t
    uint64_t


cdef int _compare(const void *a, const void *b) noexcept nogil:
    cdef uint64_t x = (<const uint64_t *> a)[0], y = (<const uint64_t *> b)[0]
    return (x > y) - (x < y)


cdef int _compare32(const void *a, const void *b) noexcept nogil:
    cdef uint32_t x = (<const uint32_t *> a)[0], y = (<const uint32_t *> b)[0]
    return (x > y) - (x < y)


cdef void _sort_bucket(bucket_key *values, Py_ssize_t size) noexcept nogil:
    """Sort values[:size] ascending: insertion sort, qsort past INSERTION_MAX. The slots'
    packed keys (uint64) and the edges-only buckets' higher ends (uint32) share it."""
    cdef Py_ssize_t i, j
    cdef bucket_key v
    if size > INSERTION_MAX:
        if bucket_key is uint64_t:
            qsort(values, size, sizeof(uint64_t), _compare)
        else:
            qsort(values, size, sizeof(uint32_t), _compare32)
        return
    for i in range(1, size):
        v = values[i]
        j = i - 1
        while j >= 0 and values[j] > v:
            values[j + 1] = values[j]
            j -= 1
        values[j + 1] = v


cdef void _bucket_starts(int64_t[::1] first, int64_t n_points) noexcept nogil:
    """first[v] (n + 1) bucket sizes -> their starts (an exclusive sum) in place."""
    cdef int64_t v, c, total = 0
    for v in range(n_points + 1):
        c = first[v]
        first[v] = total
        total += c


cdef void _starts_back(int64_t[::1] first, int64_t n_points) noexcept nogil:
    """After a scatter that moved each first[v] to its bucket's end: the starts again."""
    cdef int64_t v
    for v in range(n_points, 0, -1):
        first[v] = first[v - 1]
    first[0] = 0


def bucket_slots(const int64_t[:, ::1] tri, int64_t n_points):
    """(packed (3T,) uint64, start (n + 1,) int64): packed[start[v]:start[v + 1]] are the
    slots whose edge has lower vertex v, as high << 32 | slot, in slot order (sort_buckets
    sorts them). One counting sort: two passes over the triangles, one thread."""
    cdef Py_ssize_t T = tri.shape[0], t
    cdef int k
    cdef int64_t a, b, v
    packed = np.empty(3 * T, dtype=np.uint64)
    start = np.zeros(n_points + 1, dtype=np.int64)
    cdef uint64_t[::1] out = packed
    cdef int64_t[::1] first = start
    with nogil:
        for t in range(T):                                   # bucket sizes
            for k in range(3):
                a, b = tri[t, (k + 1) % 3], tri[t, (k + 2) % 3]
                first[a if a < b else b] += 1
        _bucket_starts(first, n_points)
        for t in range(T):                                   # scatter; first[v] moves to its end
            for k in range(3):
                a, b = tri[t, (k + 1) % 3], tri[t, (k + 2) % 3]
                v = a if a < b else b
                out[first[v]] = (<uint64_t> (a if a > b else b) << 32) | <uint64_t> (3 * t + k)
                first[v] += 1
        _starts_back(first, n_points)
    return packed, start


def sort_buckets(uint64_t[::1] packed, const int64_t[::1] start, Py_ssize_t v0, Py_ssize_t v1,
                 int64_t[::1] facts):
    """Sort the buckets of the vertices v0 <= v < v1 of bucket_slots' packed (each bucket's
    slots of one edge then side by side, the edges ascending) and write facts (4,): the
    number of unique edges among them, the largest number of slots one edge has, and the
    first edge (in sorted order) that has it, low and high. Buckets are disjoint: ranges
    of vertices run in any thread."""
    cdef Py_ssize_t v, i, j
    cdef int64_t E = 0, most = 0, worst_low = -1, worst_high = -1
    cdef uint64_t high_mask = 0xFFFFFFFF00000000
    with nogil:
        for v in range(v0, v1):
            _sort_bucket(&packed[start[v]], start[v + 1] - start[v])
            i = start[v]
            while i < start[v + 1]:                          # runs of one edge
                j = i + 1
                while j < start[v + 1] and (packed[j] & high_mask) == (packed[i] & high_mask):
                    j += 1
                if j - i > most:
                    most, worst_low, worst_high = j - i, v, <int64_t> (packed[i] >> 32)
                E += 1
                i = j
    facts[0], facts[1], facts[2], facts[3] = E, most, worst_low, worst_high


def clear_sides(const int64_t[:, ::1] tri, uint8_t[:, ::1] forward, int64_t[:, ::1] across,
                Py_ssize_t t0, Py_ssize_t t1):
    """forward[t, k] (whether the edge opposite corner k runs from its lower end) and
    across[t, k] = -1, for the triangles t0 <= t < t1: what fill_table expects before it
    fills across. An empty across (0 rows) is left alone: table_from_slots' tables have
    no neighbours."""
    cdef Py_ssize_t t
    cdef int k
    cdef bint clear = across.shape[0] > 0
    with nogil:
        for t in range(t0, t1):
            for k in range(3):
                forward[t, k] = tri[t, (k + 1) % 3] < tri[t, (k + 2) % 3]
                if clear:
                    across[t, k] = -1


def fill_table(const uint64_t[::1] packed, const int64_t[::1] start, int64_t[:, ::1] edges,
               int64_t[:, ::1] tri_edge, int64_t[::1] owner, int64_t[::1] owner_slot, int64_t[::1] count,
               int64_t[::1] other, int64_t[:, ::1] across, Py_ssize_t v0, Py_ssize_t v1, int64_t e):
    """Fill the table's rows of the edges whose lower end is v0 <= v < v1, numbered from e
    (the edges of the lower vertices before them), from the sorted buckets (every edge in
    at most 2 triangles): edges (E, 2), owner, owner_slot, count, other (E,), and tri_edge
    and across (T, 3) at their slots, as topology.edge_table_sides documents them. An
    edge's owner is its occurrence of lowest (k, t). Each slot is in one bucket, so ranges
    of vertices write disjoint entries and run in any thread."""
    cdef Py_ssize_t v, i
    cdef int64_t s1, s2, t1, t2, k1, k2
    cdef uint64_t low_mask = 0xFFFFFFFF
    with nogil:
        for v in range(v0, v1):
            i = start[v]
            while i < start[v + 1]:
                s1 = <int64_t> (packed[i] & low_mask)
                t1, k1 = s1 // 3, s1 % 3
                edges[e, 0], edges[e, 1] = v, <int64_t> (packed[i] >> 32)
                tri_edge[t1, k1] = e
                if i + 1 < start[v + 1] and (packed[i + 1] >> 32) == (packed[i] >> 32):
                    s2 = <int64_t> (packed[i + 1] & low_mask)
                    t2, k2 = s2 // 3, s2 % 3
                    tri_edge[t2, k2] = e
                    across[t1, k1], across[t2, k2] = t2, t1
                    if k2 < k1:                              # slot-major: (k, t) decides
                        t1, k1, t2, k2 = t2, k2, t1, k1
                    owner[e], owner_slot[e], count[e], other[e] = t1, k1, 2, 3 * t2 + k2
                    i += 2
                else:
                    owner[e], owner_slot[e], count[e], other[e] = t1, k1, 1, -1
                    i += 1
                e += 1


def fill_neighbours(const uint64_t[::1] packed, const int64_t[::1] start, int64_t[:, ::1] across,
                    Py_ssize_t v0, Py_ssize_t v1):
    """across (T, 3): the triangle across each slot's edge, or -1, for the slots in the
    buckets of the vertices v0 <= v < v1 of the sorted buckets (every edge in at most 2
    triangles). Every slot is in one bucket: ranges of vertices run in any thread."""
    cdef Py_ssize_t v, i
    cdef int64_t s1, s2
    cdef uint64_t low_mask = 0xFFFFFFFF
    with nogil:
        for v in range(v0, v1):
            i = start[v]
            while i < start[v + 1]:
                s1 = <int64_t> (packed[i] & low_mask)
                if i + 1 < start[v + 1] and (packed[i + 1] >> 32) == (packed[i] >> 32):
                    s2 = <int64_t> (packed[i + 1] & low_mask)
                    across[s1 // 3, s1 % 3], across[s2 // 3, s2 % 3] = s2 // 3, s1 // 3
                    i += 2
                else:
                    across[s1 // 3, s1 % 3] = -1
                    i += 1


def edge_counts(const uint8_t[::1] keep, const int64_t[::1] owner, const int64_t[::1] other,
                uint8_t[::1] owner_kept, int8_t[::1] count, Py_ssize_t e0, Py_ssize_t e1):
    """For the triangles keep (T,) 0/1 and the edges e0 <= e < e1: owner_kept (E,) 0/1
    whether each edge's owner (E,) is kept, and count (E,) how many of its one or two
    triangles are (the owner, and the slot other (E,) = 3t + k of its second triangle,
    -1 on a boundary edge). Each edge writes its own entries: ranges in any thread."""
    cdef Py_ssize_t e
    with nogil:
        for e in range(e0, e1):
            owner_kept[e] = keep[owner[e]]
            count[e] = owner_kept[e]
            if other[e] >= 0:
                count[e] += keep[other[e] // 3]


def number_kept(const uint8_t[::1] keep, int64_t[::1] number, Py_ssize_t t0, Py_ssize_t t1,
                int64_t first):
    """number[t] = first + how many of keep[t0:t] (0/1) are set, for t0 <= t < t1: the new
    numbers of kept rows, a block's numbering starting from the rows kept before it."""
    cdef Py_ssize_t t
    with nogil:
        for t in range(t0, t1):
            number[t] = first
            first += keep[t]


def fill_sub_edges(const int64_t[:, ::1] edges, const int64_t[::1] owner, const int64_t[::1] owner_slot,
                   const int64_t[::1] other, const uint8_t[::1] owner_kept, const int8_t[::1] count,
                   const int64_t[::1] remap, const int64_t[::1] new_triangle, int64_t[::1] rank,
                   int64_t[:, ::1] sub_edges, int64_t[::1] sub_owner, int64_t[::1] sub_owner_slot,
                   int64_t[::1] sub_count, Py_ssize_t e0, Py_ssize_t e1, int64_t live):
    """The sub-table's rows of the live edges (count > 0) among e0 <= e < e1, numbered from
    live (the live edges before e0), in their order: rank (E,) each edge's new number (a
    dead edge the next live one's), sub_edges (renumbered by remap (n,) when it is not
    empty; increasing, so the order holds), sub_owner (new_triangle (T,): the kept
    triangles' new numbers), sub_owner_slot, sub_count. An edge whose owner is dropped is
    owned by its other slot (topology.sub_table says why that is edge_table's owner)."""
    cdef Py_ssize_t e
    cdef int64_t slot
    cdef bint renumber = remap.shape[0] > 0
    with nogil:
        for e in range(e0, e1):
            rank[e] = live
            if count[e] == 0:
                continue
            slot = owner[e] * 3 + owner_slot[e] if owner_kept[e] else other[e]
            sub_owner[live] = new_triangle[slot // 3]
            sub_owner_slot[live] = slot % 3
            sub_count[live] = count[e]
            if renumber:
                sub_edges[live, 0], sub_edges[live, 1] = remap[edges[e, 0]], remap[edges[e, 1]]
            else:
                sub_edges[live, 0], sub_edges[live, 1] = edges[e, 0], edges[e, 1]
            live += 1


def fill_sub_triangles(const uint8_t[::1] keep, const int64_t[:, ::1] tri_edge, const uint8_t[:, ::1] forward,
                       const int64_t[::1] rank, const int64_t[::1] new_triangle,
                       int64_t[:, ::1] sub_tri_edge, uint8_t[:, ::1] sub_forward, Py_ssize_t t0, Py_ssize_t t1):
    """The sub-table's rows of the kept triangles among t0 <= t < t1: their edges' new
    numbers (rank, from fill_sub_edges) and orientations, at their new numbers."""
    cdef Py_ssize_t t
    cdef int k
    with nogil:
        for t in range(t0, t1):
            if keep[t]:
                for k in range(3):
                    sub_tri_edge[new_triangle[t], k] = rank[tri_edge[t, k]]
                    sub_forward[new_triangle[t], k] = forward[t, k]


cdef Py_ssize_t _sorted_distinct(uint32_t *values, Py_ssize_t size) noexcept nogil:
    """Sort values[:size] (_sort_bucket) and move the distinct ones to the front,
    ascending; returns how many."""
    cdef Py_ssize_t i, kept
    _sort_bucket(values, size)
    if size == 0:
        return 0
    kept = 1
    for i in range(1, size):
        if values[i] != values[kept - 1]:
            values[kept] = values[i]
            kept += 1
    return kept


def bucket_highs(const int64_t[:, ::1] tri, const uint8_t[::1] counted, int64_t n_points):
    """(highs (3T,) uint32, start (n + 1,) int64, size (n,) int64, E): the unique edges of
    the triangles tri (T, 3) whose lower vertex v has counted[v] (counted empty: every
    edge), as highs[start[v]:start[v] + size[v]], the higher ends of v's edges, ascending
    and distinct; E their total. One counting sort of the slots by lower vertex, then each
    bucket sorted and deduplicated (edge_table's buckets, without the slots)."""
    cdef Py_ssize_t T = tri.shape[0], t, v
    cdef int k
    cdef int64_t a, b, low, E = 0
    cdef bint every = counted.shape[0] == 0
    highs = np.empty(3 * T, dtype=np.uint32)
    start = np.zeros(n_points + 1, dtype=np.int64)
    size = np.empty(n_points, dtype=np.int64)
    cdef uint32_t[::1] out = highs
    cdef int64_t[::1] first = start
    cdef int64_t[::1] kept = size
    with nogil:
        for t in range(T):                                   # bucket sizes
            for k in range(3):
                a, b = tri[t, k], tri[t, (k + 1) % 3]
                low = a if a < b else b
                if every or counted[low]:
                    first[low] += 1
        _bucket_starts(first, n_points)
        for t in range(T):                                   # scatter; first[v] moves to its end
            for k in range(3):
                a, b = tri[t, k], tri[t, (k + 1) % 3]
                low = a if a < b else b
                if every or counted[low]:
                    out[first[low]] = <uint32_t> (a if a > b else b)
                    first[low] += 1
        _starts_back(first, n_points)
        for v in range(n_points):
            kept[v] = _sorted_distinct(&out[first[v]], first[v + 1] - first[v])
            E += kept[v]
    return highs, start, size, E


def fill_edges(const uint32_t[::1] highs, const int64_t[::1] start, const int64_t[::1] size,
               int64_t[:, ::1] edges):
    """edges (E, 2): bucket_highs' edges, lower vertex ascending, then higher."""
    cdef Py_ssize_t n = size.shape[0], v, i, e = 0
    with nogil:
        for v in range(n):
            for i in range(start[v], start[v] + size[v]):
                edges[e, 0] = v
                edges[e, 1] = highs[i]
                e += 1


def table_from_slots(const int64_t[:, ::1] tri, const int32_t[:, ::1] slots, int64_t[:, ::1] edges,
                     int64_t[:, ::1] tri_edge, int64_t[::1] owner, int64_t[::1] owner_slot, int64_t[::1] count,
                     int64_t[::1] other, Py_ssize_t e0, Py_ssize_t e1):
    """The table's rows of the edges e0 <= e < e1 from slots (E, 2), each edge's owner
    slot 3t + k and its second slot (-1: none), as fill_table wrote them: its ends (the
    owner's corners other than k, lower first), owner, owner_slot, count, other, and
    tri_edge at both its slots. Each edge writes its own entries and slots: ranges in any
    thread."""
    cdef Py_ssize_t e
    cdef int64_t s, t, k, a, b
    with nogil:
        for e in range(e0, e1):
            s = slots[e, 0]
            t, k = s // 3, s % 3
            a, b = tri[t, (k + 1) % 3], tri[t, (k + 2) % 3]
            edges[e, 0], edges[e, 1] = (a, b) if a < b else (b, a)
            owner[e], owner_slot[e] = t, k
            tri_edge[t, k] = e
            s = slots[e, 1]
            other[e] = s
            count[e] = 1
            if s >= 0:
                tri_edge[s // 3, s % 3] = e
                count[e] = 2

