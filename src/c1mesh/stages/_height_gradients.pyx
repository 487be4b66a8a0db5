# cython: language_level=3
"""The per-point least-squares fit of the height gradients: c1mesh.stages.height_gradients
wraps it (validation, the grid of the neighbour search, the blocks in the thread knob's
threads), and nothing else imports it.

For each point, one small system: the weighted normal equations of a polynomial in the
scaled plane offsets (2 terms for degree 1, 5 for degree 2), with a relative ridge, solved by
Gaussian elimination with partial pivoting. Every point's arithmetic is its own, in a fixed
order, so its bits do not depend on the block or the thread it runs in.
"""
from libc.math cimport fabs, sqrt
from libc.stdint cimport int64_t
from libc.stdlib cimport free, malloc, qsort, realloc
from libc.string cimport memcpy

from c1mesh.core._counting cimport stable_order

cdef enum:
    MAX_TERMS = 5        # the quadratic's terms, the most a system has


cdef int _compare(const void *a, const void *b) noexcept nogil:
    cdef double x = (<const double *> a)[0], y = (<const double *> b)[0]
    return (x > y) - (x < y)


cdef double _median(const double[:, :] dist2, Py_ssize_t row, double *scratch) noexcept nogil:
    """The median of dist2[row] (numpy's: the mean of the two middle values when even)."""
    cdef Py_ssize_t j, k = dist2.shape[1]
    cdef Py_ssize_t i
    cdef double value
    if k > 64:
        for j in range(k):
            scratch[j] = dist2[row, j]
        qsort(scratch, k, sizeof(double), _compare)
    else:                                    # insertion sort: a few dozen values
        for j in range(k):
            value = dist2[row, j]
            i = j - 1
            while i >= 0 and scratch[i] > value:
                scratch[i + 1] = scratch[i]
                i -= 1
            scratch[i + 1] = value
    if k % 2:
        return scratch[k // 2]
    return (scratch[k // 2 - 1] + scratch[k // 2]) / 2.0


cdef void _solve(double *a, double *b, int m) noexcept nogil:
    """b = a⁻¹ b for the m × m row-major a (overwritten): elimination, partial pivoting."""
    cdef int i, j, c, p
    cdef double f, t
    for c in range(m):
        p = c
        for i in range(c + 1, m):
            if fabs(a[i * m + c]) > fabs(a[p * m + c]):
                p = i
        if p != c:
            for j in range(m):
                t = a[c * m + j]
                a[c * m + j] = a[p * m + j]
                a[p * m + j] = t
            t = b[c]
            b[c] = b[p]
            b[p] = t
        for i in range(c + 1, m):
            f = a[i * m + c] / a[c * m + c]
            for j in range(c, m):
                a[i * m + j] -= f * a[c * m + j]
            b[i] -= f * b[c]
    for c in range(m - 1, -1, -1):
        t = b[c]
        for j in range(c + 1, m):
            t -= a[c * m + j] * b[j]
        b[c] = t / a[c * m + c]


def fit_block(const double[::1] z, const int64_t[::1] centre, const int64_t[:, :] neighbours,
              const double[:, :] ux, const double[:, :] uy, const double[:, :] dist2,
              int degree, double ridge, double tiny, double[:, ::1] out):
    """out (b, 2): the gradient at each point centre[i] (b,) of the heights z (n,), from its
    neighbours (b, k) at plane offsets ux, uy and squared distances dist2 (b, k each, plane
    units); gradients in z units per plane unit (height_gradients documents the fit).

    Per point: r² the median of dist2 (1 where 0), offsets scaled by r, weights
    1 / (1 + d²/r²), the terms (u, v[, u²/2, uv, v²/2]); N = Σ w aᵀa and the right side
    Σ w a Δz summed over the neighbours in column order; ridge · trace(N) + tiny added to N's
    diagonal; the solution's first two terms divided by r."""
    cdef Py_ssize_t b = centre.shape[0], k = neighbours.shape[1], i, j
    cdef int m = 2 if degree == 1 else 5, p, q
    cdef double scale2, scale, u, v, w, dz, shift
    cdef double row[MAX_TERMS]
    cdef double normal[MAX_TERMS * MAX_TERMS]
    cdef double rhs[MAX_TERMS]
    cdef double *scratch
    with nogil:
        scratch = <double *> malloc(max(k, 1) * sizeof(double))
        for i in range(b):
            scale2 = _median(dist2, i, scratch)
            if not scale2 > 0:
                scale2 = 1.0
            scale = sqrt(scale2)
            for p in range(m * m):
                normal[p] = 0.0
            for p in range(m):
                rhs[p] = 0.0
            for j in range(k):
                u = ux[i, j] / scale
                v = uy[i, j] / scale
                w = 1.0 / (1.0 + dist2[i, j] / scale2)
                dz = z[neighbours[i, j]] - z[centre[i]]
                row[0] = u
                row[1] = v
                if m == 5:
                    row[2] = 0.5 * u * u
                    row[3] = u * v
                    row[4] = 0.5 * v * v
                for p in range(m):
                    rhs[p] += row[p] * w * dz
                    for q in range(m):
                        normal[p * m + q] += row[p] * w * row[q]
            shift = 0.0
            for p in range(m):
                shift += normal[p * m + p]
            shift = ridge * shift + tiny
            for p in range(m):
                normal[p * m + p] += shift
            _solve(normal, rhs, m)
            out[i, 0] = rhs[0] / scale
            out[i, 1] = rhs[1] / scale
        free(scratch)


cdef struct Candidate:
    double d2             # squared plane distance to the centre
    double dx, dy         # offset from the centre
    int64_t q             # point number


cdef inline bint _before(const Candidate *a, const Candidate *b, const double *z) noexcept nogil:
    """Whether candidate a comes before b: nearer first, ties by the offset dx, then dy, then
    the height, then the point number (equal up to the number: the same datum twice,
    interchangeable in every sum). The heights are read only on an exact tie of the rest."""
    if a.d2 != b.d2:
        return a.d2 < b.d2
    if a.dx != b.dx:
        return a.dx < b.dx
    if a.dy != b.dy:
        return a.dy < b.dy
    if z[a.q] != z[b.q]:
        return z[a.q] < z[b.q]
    return a.q < b.q


cdef Py_ssize_t _lower(const int64_t *cells, Py_ssize_t count, int64_t key) noexcept nogil:
    """The first position of cells[:count] (ascending) holding key or more."""
    cdef Py_ssize_t lo = 0, hi = count, mid
    while lo < hi:
        mid = (lo + hi) >> 1
        if cells[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


cdef inline void _row(const int64_t *cells, const int64_t *starts, Py_ssize_t ncells, int64_t first,
                      int64_t last, int64_t *lo, int64_t *hi) noexcept nogil:
    """The points of the occupied cells numbered first ... last (one row of the grid): the
    rows lo ... hi − 1 of the points, which are sorted by cell."""
    cdef Py_ssize_t pos = _lower(cells, ncells, first), end = pos
    while end < ncells and cells[end] <= last:
        end += 1
    lo[0] = starts[pos]
    hi[0] = starts[end]


cdef struct Candidates:
    Candidate *seen       # every candidate of the square searched so far (seen[:count])
    Candidate *near       # those nearer than a bound
    Py_ssize_t *slot      # near's positions, counting-sorted by distance
    Candidate *top        # the first k in `_before`'s order
    Py_ssize_t *bucket    # each near one's distance bucket
    Py_ssize_t *start     # where each bucket starts in order
    Py_ssize_t count, capacity


cdef bint _grow(Candidates *c, Py_ssize_t need) noexcept nogil:
    """Room for `need` candidates; False when memory ran out."""
    cdef Py_ssize_t capacity = c.capacity
    if need <= capacity:
        return True
    while capacity < need:
        capacity *= 2
    c.seen = <Candidate *> realloc(c.seen, capacity * sizeof(Candidate))
    c.near = <Candidate *> realloc(c.near, capacity * sizeof(Candidate))
    c.slot = <Py_ssize_t *> realloc(c.slot, capacity * sizeof(Py_ssize_t))
    c.bucket = <Py_ssize_t *> realloc(c.bucket, capacity * sizeof(Py_ssize_t))
    c.start = <Py_ssize_t *> realloc(c.start, (capacity + 1) * sizeof(Py_ssize_t))
    c.capacity = capacity
    return (c.seen != NULL and c.near != NULL and c.slot != NULL and c.bucket != NULL
            and c.start != NULL)


cdef bint _add_cells(Candidates *c, const double *xy, const int64_t *cells, const int64_t *starts,
                     Py_ssize_t ncells, int64_t first, int64_t last, int64_t centre,
                     double px, double py) noexcept nogil:
    """Append the points of the occupied cells numbered first ... last (one row of the
    grid) to the candidates, all but the centre itself."""
    cdef int64_t lo, hi, q
    cdef double dx, dy
    cdef Candidate *record
    _row(cells, starts, ncells, first, last, &lo, &hi)
    if not _grow(c, c.count + hi - lo):
        return False
    for q in range(lo, hi):
        if q != centre:
            dx = xy[2 * q] - px
            dy = xy[2 * q + 1] - py
            record = &c.seen[c.count]
            record.d2 = dx * dx + dy * dy
            record.dx = dx
            record.dy = dy
            record.q = q
            c.count += 1
    return True


cdef Py_ssize_t _near(Candidates *c, double bound) noexcept nogil:
    """Copy the candidates nearer than bound (squared) to c.near; how many."""
    cdef Py_ssize_t j, m = 0
    for j in range(c.count):
        c.near[m] = c.seen[j]
        m += c.seen[j].d2 < bound
    return m


cdef void _select(Candidates *c, Py_ssize_t m, double low, double high, Py_ssize_t k,
                  const double *z, int64_t *index, double *ux, double *uy, double *dist2) noexcept nogil:
    """The first k, in `_before`'s order, of c.near[:m] (k ≤ m, squared distances in low ...
    high) into one row of the output. A counting sort into m buckets of equal distance²
    span puts them nearly in order (a bucket holds one on average: the points are spread
    over the plane), and only the buckets up to the one holding the k-th can hold any of
    the first k; a bounded insertion of those then finds the order (O(k) moves when they
    come in order, O(m·k) at worst: a clump of copies at one position)."""
    cdef double scale = m / (high - low)
    cdef Py_ssize_t j, b, slot, end, filled = 0
    cdef Candidate *near = c.near
    cdef Candidate *top = c.top
    cdef Candidate *record
    if not scale <= 1e300:               # all at one distance: one bucket
        scale = 0.0
    for b in range(m + 1):
        c.start[b] = 0
    for j in range(m):
        b = <Py_ssize_t> ((near[j].d2 - low) * scale)
        if b > m - 1:
            b = m - 1
        c.bucket[j] = b
        c.start[b + 1] += 1
    end = -1
    for b in range(m):
        c.start[b + 1] += c.start[b]
        if end < 0 and c.start[b + 1] >= k:
            end = c.start[b + 1]
    for j in range(m):
        b = c.bucket[j]
        c.slot[c.start[b]] = j
        c.start[b] += 1
    for j in range(end):
        record = &near[c.slot[j]]
        if filled == k:
            if not _before(record, &top[k - 1], z):
                continue
            slot = k - 1
        else:
            slot = filled
            filled += 1
        while slot > 0 and _before(record, &top[slot - 1], z):
            top[slot] = top[slot - 1]
            slot -= 1
        top[slot] = record[0]
    for j in range(k):
        index[j] = top[j].q
        ux[j] = top[j].dx
        uy[j] = top[j].dy
        dist2[j] = top[j].d2


def grid_neighbours(const double[:, ::1] xy, const double[::1] z, const int64_t[::1] centre,
                    const int64_t[::1] cell_x, const int64_t[::1] cell_y,
                    const int64_t[::1] cells, const int64_t[::1] starts,
                    int64_t nx, int64_t ny, double x0, double y0, double size,
                    int64_t[:, ::1] out, double[:, ::1] ux, double[:, ::1] uy, double[:, ::1] dist2):
    """out (b, k): the k nearest other points of each point centre (b,) among xy (n, 2),
    in the order of `_before`, and their offsets ux, uy and dist2 = ux·ux + uy·uy (b, k);
    k < n.

    The points are sorted by grid cell: cell (i, j) of side `size` from (x0, y0) has the
    number j·nx + i, `cells` are the occupied numbers ascending and the points of cells[c]
    are rows starts[c] ... starts[c+1] − 1; cell_x, cell_y (n,) are each point's i, j.
    The square of cells within R of the centre's cell (R = 1, 2, ...) is searched until
    at least k of its candidates are nearer than anything outside the square can be (with
    a relative margin, so rounding cannot hide a tie), or the square covers the grid; once
    a ring would have more cells than are occupied (a point far from the rest), every
    point not yet seen is taken instead, so a lone point costs O(cells), not O(R²). The
    first k of the candidates within that bound (all of them when there is none) are then
    put in order (`_select`).

    The common case, R = 1, takes a short way: the 3 × 3 cells are three runs of points
    (one per row of cells, looked up once for all the points of a cell) and only the
    candidates within the bound are kept; when fewer than k are, the general search
    starts over."""
    cdef Py_ssize_t b = centre.shape[0], k = out.shape[1], ncells = cells.shape[0], i, pos, m, r
    cdef Py_ssize_t rows = 0
    cdef int64_t c, ix, iy, R, gy, lo, hi, side, q, total = 0
    cdef int64_t cached_x = -1, cached_y = -1
    cdef int64_t row_lo[3]
    cdef int64_t row_hi[3]
    cdef double px, py, dx, dy, d2, reach, bound, low, high, slack = size * 1e-6
    cdef const double *points = &xy[0, 0]
    cdef const double *heights = &z[0]
    cdef const int64_t *occupied = &cells[0]
    cdef const int64_t *first = &starts[0]
    cdef Candidates found
    cdef Candidate *record
    cdef bint done, bounded, ok = True
    if b == 0 or k == 0:
        return
    found.capacity = 256
    found.count = 0
    found.seen = <Candidate *> malloc(found.capacity * sizeof(Candidate))
    found.near = <Candidate *> malloc(found.capacity * sizeof(Candidate))
    found.slot = <Py_ssize_t *> malloc(found.capacity * sizeof(Py_ssize_t))
    found.top = <Candidate *> malloc(k * sizeof(Candidate))
    found.bucket = <Py_ssize_t *> malloc(found.capacity * sizeof(Py_ssize_t))
    found.start = <Py_ssize_t *> malloc((found.capacity + 1) * sizeof(Py_ssize_t))
    with nogil:
        ok = (found.seen != NULL and found.near != NULL and found.slot != NULL and found.top != NULL
              and found.bucket != NULL and found.start != NULL)
        for i in range(b if ok else 0):
            c = centre[i]
            px = points[2 * c]
            py = points[2 * c + 1]
            ix = cell_x[c]
            iy = cell_y[c]
            R = 1
            reach = min(min(px - (x0 + (ix - R) * size), x0 + (ix + R + 1) * size - px),
                        min(py - (y0 + (iy - R) * size), y0 + (iy + R + 1) * size - py)) - slack
            bound = reach * reach * (1.0 - 1e-12)
            if reach > 0:                                 # the short way
                if ix != cached_x or iy != cached_y:
                    cached_x, cached_y = ix, iy
                    rows = 0
                    total = 0
                    for gy in range(max(iy - 1, 0), min(iy + 1, ny - 1) + 1):
                        _row(occupied, first, ncells, gy * nx + max(ix - 1, 0), gy * nx + min(ix + 1, nx - 1),
                             &row_lo[rows], &row_hi[rows])
                        total += row_hi[rows] - row_lo[rows]
                        rows += 1
                    if not _grow(&found, total):
                        ok = False
                        break
                m = 0
                for r in range(rows):
                    for q in range(row_lo[r], row_hi[r]):
                        dx = points[2 * q] - px
                        dy = points[2 * q + 1] - py
                        d2 = dx * dx + dy * dy
                        record = &found.near[m]
                        record.d2 = d2
                        record.dx = dx
                        record.dy = dy
                        record.q = q
                        m += (d2 < bound) & (q != c)
                if m >= k:
                    _select(&found, m, 0.0, bound, k, heights, &out[i, 0], &ux[i, 0], &uy[i, 0], &dist2[i, 0])
                    continue
            found.count = 0                               # the general search
            for gy in range(max(iy - 1, 0), min(iy + 1, ny - 1) + 1):
                ok = ok and _add_cells(&found, points, occupied, first, ncells,
                                       gy * nx + max(ix - 1, 0), gy * nx + min(ix + 1, nx - 1), c, px, py)
            bounded = False
            while True:
                done = ix - R <= 0 and iy - R <= 0 and ix + R >= nx - 1 and iy + R >= ny - 1
                if not done and found.count >= k:
                    reach = min(min(px - (x0 + (ix - R) * size), x0 + (ix + R + 1) * size - px),
                                min(py - (y0 + (iy - R) * size), y0 + (iy + R + 1) * size - py)) - slack
                    bound = reach * reach * (1.0 - 1e-12)
                    m = _near(&found, bound)
                    done = bounded = reach > 0 and m >= k
                if done or not ok:
                    break
                R += 1
                if 8 * R > ncells:                       # every point not seen yet, cell by cell
                    for pos in range(ncells):
                        lo = occupied[pos] % nx
                        gy = occupied[pos] // nx
                        if lo - ix >= R or ix - lo >= R or gy - iy >= R or iy - gy >= R:
                            ok = ok and _add_cells(&found, points, occupied, first, ncells, occupied[pos],
                                                   occupied[pos], c, px, py)
                    break
                lo, hi = max(ix - R, 0), min(ix + R, nx - 1)
                for side in range(2):                    # the new ring: its bottom and top rows
                    gy = iy - R if side == 0 else iy + R
                    if 0 <= gy < ny:
                        ok = ok and _add_cells(&found, points, occupied, first, ncells, gy * nx + lo,
                                               gy * nx + hi, c, px, py)
                for gy in range(max(iy - R + 1, 0), min(iy + R - 1, ny - 1) + 1):   # its two sides
                    if ix - R >= 0:
                        ok = ok and _add_cells(&found, points, occupied, first, ncells, gy * nx + ix - R,
                                               gy * nx + ix - R, c, px, py)
                    if ix + R < nx:
                        ok = ok and _add_cells(&found, points, occupied, first, ncells, gy * nx + ix + R,
                                               gy * nx + ix + R, c, px, py)
            if not ok:
                break
            if bounded:
                low, high = 0.0, bound
            else:                                        # all of them: every point but the centre
                m = found.count
                low = high = found.seen[0].d2
                for pos in range(m):
                    found.near[pos] = found.seen[pos]
                    low = min(low, found.seen[pos].d2)
                    high = max(high, found.seen[pos].d2)
            _select(&found, m, low, high, k, heights, &out[i, 0], &ux[i, 0], &uy[i, 0], &dist2[i, 0])
    free(found.seen)
    free(found.near)
    free(found.slot)
    free(found.top)
    free(found.bucket)
    free(found.start)
    if not ok:
        raise MemoryError()



def cell_order(const int64_t[::1] number, int64_t[::1] count, int64_t[::1] order):
    """order (n,) = the stable order of the cell numbers number (n,) in [0, len(count) − 1)
    (numpy's argsort(kind="stable"): equal numbers keep their input order), by one
    counting sort (core/_counting.pxd); count (cells + 1,): each cell's first slot on
    return. One thread, O(n + cells)."""
    with nogil:
        stable_order(&number[0] if number.shape[0] else NULL, number.shape[0], &count[0], count.shape[0] - 1,
                     &order[0] if order.shape[0] else NULL)
