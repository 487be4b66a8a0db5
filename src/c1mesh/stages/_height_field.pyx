# cython: language_level=3
"""The height field's kernels: c1mesh.stages.height_field wraps them (validation, scratch
arrays, the float keys), and nothing else imports them. One thread: sorts and union-find
do not split into independent blocks, and each pass is a few milliseconds per million
points. Only comparisons and the arithmetic the wrapper's docstrings give, in that order
(the build's -ffp-contract=off keeps it unfused), so the results are numpy's and cKDTree's
bits."""
from libc.math cimport fabs, isnan, sqrt, INFINITY, NAN
from libc.stdint cimport int64_t, uint8_t, uint64_t
from libc.string cimport memcpy

from c1mesh.core._union_find cimport root


cdef inline uint64_t _float_key(double value) noexcept nogil:
    """An unsigned key that orders as the double does (-0.0 and 0.0 equal; no NaN)."""
    cdef double v = value + 0.0                 # -0.0 + 0.0 is 0.0
    cdef uint64_t bits
    memcpy(&bits, &v, sizeof(double))
    if bits >> 63:
        return ~bits
    return bits | (<uint64_t> 1 << 63)


cdef void _radix_sort(uint64_t *key, int64_t *order, uint64_t *key_tmp, int64_t *order_tmp,
                      Py_ssize_t n) noexcept nogil:
    """Sort the pairs (key[i], order[i]) stably by key: least significant byte first, the
    bytes all keys share skipped. The result ends in key, order; *_tmp are scratch (n,)."""
    cdef Py_ssize_t count[8][256]
    cdef Py_ssize_t i, total, c
    cdef int byte, digit, shift
    cdef uint64_t *src_key = key
    cdef int64_t *src_order = order
    cdef uint64_t *dst_key = key_tmp
    cdef int64_t *dst_order = order_tmp
    cdef uint64_t *swap_key
    cdef int64_t *swap_order
    for byte in range(8):
        for digit in range(256):
            count[byte][digit] = 0
    for i in range(n):
        for byte in range(8):
            count[byte][(key[i] >> (8 * byte)) & 255] += 1
    for byte in range(8):
        shift = 8 * byte
        if n == 0 or count[byte][(key[0] >> shift) & 255] == n:
            continue                            # every key has this byte: order unchanged
        total = 0
        for digit in range(256):
            c = count[byte][digit]
            count[byte][digit] = total
            total += c
        for i in range(n):
            digit = (src_key[i] >> shift) & 255
            dst_key[count[byte][digit]] = src_key[i]
            dst_order[count[byte][digit]] = src_order[i]
            count[byte][digit] += 1
        swap_key, swap_order = src_key, src_order
        src_key, src_order = dst_key, dst_order
        dst_key, dst_order = swap_key, swap_order
    if src_key != key:
        memcpy(key, src_key, n * sizeof(uint64_t))
        memcpy(order, src_order, n * sizeof(int64_t))


cdef void _insertion_sort(uint64_t *key, int64_t *order, Py_ssize_t n) noexcept nogil:
    """Sort the pairs (key[i], order[i]) stably by key: for the few points of a run."""
    cdef Py_ssize_t i, j
    cdef uint64_t k
    cdef int64_t o
    for i in range(1, n):
        k = key[i]
        o = order[i]
        j = i
        while j > 0 and key[j - 1] > k:
            key[j] = key[j - 1]
            order[j] = order[j - 1]
            j -= 1
        key[j] = k
        order[j] = o


cdef enum:
    SMALL_RUN = 32       # runs of tied x up to this long are insertion-sorted by y


cdef inline void _sort_run(uint64_t *key, int64_t *order, uint64_t *key_tmp, int64_t *order_tmp,
                           Py_ssize_t n) noexcept nogil:
    """Sort one run's pairs (key[i], order[i]) stably by key: insertion for up to SMALL_RUN,
    else the radix sort (*_tmp scratch of the run's length)."""
    if n <= SMALL_RUN:
        _insertion_sort(key, order, n)
    else:
        _radix_sort(key, order, key_tmp, order_tmp, n)


def sort_xy(const double[::1] x, const double[::1] y, int64_t[::1] order, uint64_t[::1] key,
            uint64_t[::1] key_tmp, int64_t[::1] order_tmp):
    """order (n,): the permutation sorting the points (x, y) (n,) by x, then y, then index
    (np.lexsort((y, x)), -0.0 equal to 0.0). A stable radix sort by x, then each run of tied
    x sorted stably by y (LiDAR's quantised x ties in runs of tens). key, key_tmp (n,),
    order_tmp (n,) scratch."""
    cdef Py_ssize_t n = order.shape[0], i, start, stop
    cdef uint64_t run_key
    if n == 0:
        return
    with nogil:
        for i in range(n):
            order[i] = i
            key[i] = _float_key(x[i])
        _radix_sort(&key[0], &order[0], &key_tmp[0], &order_tmp[0], n)
        start = 0
        while start < n:
            run_key = key[start]
            stop = start + 1
            while stop < n and key[stop] == run_key:
                stop += 1
            if stop - start > 1:
                for i in range(start, stop):
                    key[i] = _float_key(y[order[i]])
                _sort_run(&key[start], &order[start], &key_tmp[start], &order_tmp[start], stop - start)
            start = stop


def sort_by_float(const double[::1] values, int64_t[::1] order, uint64_t[::1] key,
                  uint64_t[::1] key_tmp, int64_t[::1] order_tmp):
    """Reorder the permutation order (n,) stably by values[order] (values (N,) finite):
    ties keep their order. key, key_tmp (n,), order_tmp (n,) scratch."""
    cdef Py_ssize_t n = order.shape[0], i
    with nogil:
        for i in range(n):
            key[i] = _float_key(values[order[i]])
        _radix_sort(&key[0], &order[0], &key_tmp[0], &order_tmp[0], n)


def sort_runs_by_float(const double[::1] values, const int64_t[::1] starts, int64_t[::1] order,
                       uint64_t[::1] key, uint64_t[::1] key_tmp, int64_t[::1] order_tmp):
    """order (n,) = each run [starts[r], starts[r + 1]) of range(n) sorted stably by values
    (n,) (finite; -0.0 equal to 0.0): insertion sort for short runs, else the radix sort,
    each run in cache. The result of sort_by_float from arange followed by a stable sort
    by run number, in one pass over small runs. key, key_tmp (n,), order_tmp (n,) scratch."""
    cdef Py_ssize_t runs = starts.shape[0] - 1, r, i, start, stop
    with nogil:
        for r in range(runs):
            start, stop = starts[r], starts[r + 1]
            for i in range(start, stop):
                order[i] = i
                key[i] = _float_key(values[i])
            _sort_run(&key[start], &order[start], &key_tmp[start], &order_tmp[start], stop - start)


def sort_by_int(const int64_t[::1] values, int64_t[::1] order, uint64_t[::1] key,
                uint64_t[::1] key_tmp, int64_t[::1] order_tmp):
    """Reorder the permutation order (n,) stably by values[order] (values (N,) >= 0)."""
    cdef Py_ssize_t n = order.shape[0], i
    with nogil:
        for i in range(n):
            key[i] = <uint64_t> values[order[i]]
        _radix_sort(&key[0], &order[0], &key_tmp[0], &order_tmp[0], n)


def position_groups(const double[:, ::1] local, const double[:, ::1] gradients,
                    const int64_t[::1] order, int64_t[::1] group, int64_t[::1] first,
                    double[:, ::1] columns, double[::1] z_range):
    """Group the points of local (n, 3) that share an exact position (x, y), given order
    (n,) sorting them by (x, y, index). group (n,): each point's group, numbered in that
    order; of the first m rows (m: the number of groups, returned): first (n,) each
    group's first (lowest-index) point, columns (5, n) its x, y, z and gradient (from
    gradients (n, 2)) as rows, z_range (n,) the group's largest minus smallest z."""
    cdef Py_ssize_t n = order.shape[0], i
    cdef int64_t p, g = -1
    cdef double z, low = 0.0, high = 0.0
    with nogil:
        for i in range(n):
            p = order[i]
            z = local[p, 2]
            if g < 0 or local[p, 0] != columns[0, g] or local[p, 1] != columns[1, g]:
                if g >= 0:
                    z_range[g] = high - low
                g += 1
                first[g] = p
                columns[0, g] = local[p, 0]
                columns[1, g] = local[p, 1]
                columns[2, g] = z
                columns[3, g] = gradients[p, 0]
                columns[4, g] = gradients[p, 1]
                low = high = z
            else:
                low = z if z < low else low
                high = z if z > high else high
            group[p] = g
        if g >= 0:
            z_range[g] = high - low
    return g + 1


cdef double _search_run(const double *x, const double *y, const double *z, const int64_t *order,
                        Py_ssize_t start, Py_ssize_t stop, int64_t p, double best) noexcept nogil:
    """The least of best and the squared 3D distances (dx·dx + dy·dy + dz·dz) from point p to
    the points order[start:stop] (one strip, sorted by y) other than p: binary search for
    y[p], then walk up and down while dy·dy alone does not exceed the best (every point
    farther along is farther)."""
    cdef Py_ssize_t lo = start, hi = stop, mid
    while lo < hi:
        mid = (lo + hi) // 2
        if y[order[mid]] < y[p]:
            lo = mid + 1
        else:
            hi = mid
    best = _walk(x, y, z, order, lo, stop, 1, p, best)
    return _walk(x, y, z, order, lo - 1, start - 1, -1, p, best)


cdef double _walk(const double *x, const double *y, const double *z, const int64_t *order,
                  Py_ssize_t j, Py_ssize_t end, Py_ssize_t step, int64_t p, double best) noexcept nogil:
    """_search_run's walk from order[j] by step until end (excluded), or until dy·dy alone
    exceeds best: the least of best and the squared distances met."""
    cdef int64_t q
    cdef double dx, dy, dz, d2
    while j != end:
        q = order[j]
        dy = y[q] - y[p]
        if dy * dy > best:
            break
        if q != p:
            dx = x[q] - x[p]
            dz = z[q] - z[p]
            d2 = dx * dx + dy * dy + dz * dz
            best = d2 if d2 < best else best
        j += step
    return best


def nearest_distances(const double[::1] x, const double[::1] y, const double[::1] z,
                      const int64_t[::1] order, const int64_t[::1] starts, const double[::1] low,
                      const double[::1] high, const int64_t[::1] query, const int64_t[::1] query_run,
                      double[::1] out):
    """out (q,): the 3D distance from each point query[k] (q,) to its nearest other point of
    x, y, z (m,): sqrt of the least dx·dx + dy·dy + dz·dz, summed in that order as cKDTree
    does (sqrt is monotone: the least root is the root of the least sum); inf when there is
    no other point. The points come in strips of x: order (m,) sorts them by (strip, y),
    starts (R + 1,) bounds each strip's run of order, low and high (R,) its least and
    largest x; query_run (q,) is the run of each query point. The search visits the runs
    outwards from the query's own and stops on a side where the next run's x bound alone
    is farther than the best (`_search_run` within a run)."""
    cdef Py_ssize_t q = query.shape[0], R = low.shape[0], k, r
    cdef int64_t p
    cdef double best, dx
    if x.shape[0] == 0:
        return
    with nogil:
        for k in range(q):
            p = query[k]
            best = _search_run(&x[0], &y[0], &z[0], &order[0], starts[query_run[k]],
                               starts[query_run[k] + 1], p, INFINITY)
            r = query_run[k] - 1
            while r >= 0:
                dx = x[p] - high[r]
                if dx * dx > best:
                    break
                best = _search_run(&x[0], &y[0], &z[0], &order[0], starts[r], starts[r + 1], p, best)
                r -= 1
            r = query_run[k] + 1
            while r < R:
                dx = low[r] - x[p]
                if dx * dx > best:
                    break
                best = _search_run(&x[0], &y[0], &z[0], &order[0], starts[r], starts[r + 1], p, best)
                r += 1
            out[k] = sqrt(best)


cdef inline double _maximum(double a, double b) noexcept nogil:
    """numpy's maximum: NaN when either is NaN."""
    if isnan(a) or isnan(b):
        return NAN
    return a if a >= b else b


cdef struct _Pairs:
    # what close_pairs tests each pair with (one struct, not a dozen arguments)
    const double *x
    const double *y
    const double *z
    const double *slope
    const int64_t *rank
    uint8_t *bad
    int64_t *parent
    double radius2
    double margin
    double merge_radius
    bint jumps


cdef void _test_pair(_Pairs *s, int64_t i, int64_t j) noexcept nogil:
    """The pair (i, j) if within the radius: flag a height jump, join a merge."""
    cdef double dx = s.x[i] - s.x[j], dy = s.y[i] - s.y[j]
    cdef double d2 = dx * dx + dy * dy, dist
    cdef int64_t a, b
    if not d2 <= s.radius2:
        return
    dist = sqrt(d2)
    if s.jumps and fabs(s.z[i] - s.z[j]) > s.margin + _maximum(s.slope[i], s.slope[j]) * dist:
        s.bad[i] = 1
        s.bad[j] = 1
    if dist <= s.merge_radius:
        a = root(s.parent, i)
        b = root(s.parent, j)
        if s.rank[b] < s.rank[a]:
            a, b = b, a
        s.parent[b] = a


def close_pairs(const double[::1] x, const double[::1] y, const double[::1] z,
                const double[::1] slope, const int64_t[::1] strip, const int64_t[::1] order,
                double radius2, double window, double margin, double merge_radius, bint jumps,
                const int64_t[::1] rank, uint8_t[::1] bad, int64_t[::1] parent):
    """Every pair of points (m,) with dx·dx + dy·dy <= radius2 (cKDTree.query_pairs' test),
    found in strips: strip (m,) numbers strips of x at least `window` wide (window above
    the radius by a margin for rounding), order (m,) sorts the points by (strip, y); a
    point meets the points of its own and the next strip within `window` in y. For each
    pair at distance d = sqrt(dx·dx + dy·dy): jumps: |z_i − z_j| > margin + max(slope_i,
    slope_j)·d sets bad (m,) of both; d <= merge_radius joins their sets in parent (m,),
    a union-find forest rooted at the member of least rank (m,). parent ends flattened:
    each point's root."""
    cdef Py_ssize_t m = order.shape[0], a, b, lo = 0, strip_end = 0, next_end = 0
    cdef int64_t i
    cdef _Pairs s
    if m == 0:
        return
    s.x, s.y, s.z, s.slope, s.rank = &x[0], &y[0], &z[0], &slope[0], &rank[0]
    s.bad, s.parent = &bad[0], &parent[0]
    s.radius2, s.margin, s.merge_radius, s.jumps = radius2, margin, merge_radius, jumps
    with nogil:
        for a in range(m):
            parent[a] = a
        for a in range(m):
            i = order[a]
            if a >= strip_end:                   # a new strip: where it and the next one end
                while strip_end < m and strip[order[strip_end]] == strip[i]:
                    strip_end += 1
                next_end = strip_end
                while next_end < m and strip[order[next_end]] == strip[i] + 1:
                    next_end += 1
                lo = strip_end
            b = a + 1
            while b < strip_end and y[order[b]] - y[i] <= window:
                _test_pair(&s, i, order[b])
                b += 1
            while lo < next_end and y[i] - y[order[lo]] > window:
                lo += 1
            b = lo
            while b < next_end and y[order[b]] - y[i] <= window:
                _test_pair(&s, i, order[b])
                b += 1
        for a in range(m):
            parent[a] = root(&parent[0], a)
