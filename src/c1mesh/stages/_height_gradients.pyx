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


cdef inline bint _before(double d2, double dx, double dy, double h, int64_t q,
                         double d2b, double dxb, double dyb, double hb, int64_t qb) noexcept nogil:
    """Whether candidate (d2, dx, dy, h, q) comes before (d2b, ...): nearer first, ties by the
    offset dx, then dy, then the height, then the point number (equal up to the number: the
    same datum twice, interchangeable in every sum)."""
    if d2 != d2b:
        return d2 < d2b
    if dx != dxb:
        return dx < dxb
    if dy != dyb:
        return dy < dyb
    if h != hb:
        return h < hb
    return q < qb


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


cdef struct Candidates:
    int64_t *index        # candidate point numbers
    double *dist2         # their squared distances
    double *work          # scratch for the selection
    Py_ssize_t count, capacity


cdef bint _grow(Candidates *c, Py_ssize_t need) noexcept nogil:
    """Room for `need` candidates; False when memory ran out."""
    cdef Py_ssize_t capacity = c.capacity
    if need <= capacity:
        return True
    while capacity < need:
        capacity *= 2
    c.index = <int64_t *> realloc(c.index, capacity * sizeof(int64_t))
    c.dist2 = <double *> realloc(c.dist2, capacity * sizeof(double))
    c.work = <double *> realloc(c.work, capacity * sizeof(double))
    c.capacity = capacity
    return c.index != NULL and c.dist2 != NULL and c.work != NULL


cdef bint _add_cells(Candidates *c, const double *xy, const int64_t *cells, const int64_t *starts,
                     Py_ssize_t ncells, int64_t first, int64_t last, int64_t centre,
                     double px, double py) noexcept nogil:
    """Append the points of the occupied cells numbered first ... last (one row of the
    grid) to the candidates, all but the centre itself."""
    cdef Py_ssize_t pos = _lower(cells, ncells, first)
    cdef int64_t q
    cdef double dx, dy
    while pos < ncells and cells[pos] <= last:
        if not _grow(c, c.count + starts[pos + 1] - starts[pos]):
            return False
        for q in range(starts[pos], starts[pos + 1]):
            if q != centre:
                dx = xy[2 * q] - px
                dy = xy[2 * q + 1] - py
                c.index[c.count] = q
                c.dist2[c.count] = dx * dx + dy * dy
                c.count += 1
        pos += 1
    return True


cdef double _kth(double *values, Py_ssize_t count, Py_ssize_t k) noexcept nogil:
    """The k-th smallest (1-based) of values[:count], which it reorders (quickselect)."""
    cdef Py_ssize_t lo = 0, hi = count - 1, i, j, want = k - 1
    cdef double pivot, t
    while lo < hi:
        pivot = values[(lo + hi) >> 1]
        i = lo
        j = hi
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                t = values[i]
                values[i] = values[j]
                values[j] = t
                i += 1
                j -= 1
        if want <= j:
            hi = j
        elif want >= i:
            lo = i
        else:
            break
    return values[want]


cdef void _take_nearest(Candidates *c, const double *xy, const double *z, double px, double py,
                        double threshold, Py_ssize_t k, int64_t *index, double *ux, double *uy,
                        double *dist2) noexcept nogil:
    """The first k, in `_before`'s order, of the candidates no farther than threshold (the
    k-th smallest squared distance: at least k of them) into one row of the output."""
    cdef Py_ssize_t j, slot, count = 0
    cdef int64_t q
    cdef double dx, dy, d2
    for j in range(c.count):
        d2 = c.dist2[j]
        if d2 > threshold:
            continue
        q = c.index[j]
        dx = xy[2 * q] - px
        dy = xy[2 * q + 1] - py
        if count == k and not _before(d2, dx, dy, z[q], q, dist2[k - 1], ux[k - 1], uy[k - 1],
                                      z[index[k - 1]], index[k - 1]):
            continue
        slot = count if count < k else k - 1
        while slot > 0 and _before(d2, dx, dy, z[q], q, dist2[slot - 1], ux[slot - 1], uy[slot - 1],
                                   z[index[slot - 1]], index[slot - 1]):
            index[slot] = index[slot - 1]
            ux[slot] = ux[slot - 1]
            uy[slot] = uy[slot - 1]
            dist2[slot] = dist2[slot - 1]
            slot -= 1
        index[slot] = q
        ux[slot] = dx
        uy[slot] = dy
        dist2[slot] = d2
        if count < k:
            count += 1


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
    its k-th nearest candidate is nearer than anything outside the square can be (with a
    relative margin, so rounding cannot hide a tie), or the square covers the grid; once a
    ring would have more cells than are occupied (a point far from the rest), every point
    not yet seen is taken instead, so a lone point costs O(cells), not O(R²). The k nearest
    (a quickselect of the squared distances) are then put in order."""
    cdef Py_ssize_t b = centre.shape[0], k = out.shape[1], ncells = cells.shape[0], i, pos
    cdef int64_t c, ix, iy, R, gy, lo, hi, side
    cdef double px, py, reach, threshold, slack = size * 1e-6
    cdef const double *points = &xy[0, 0]
    cdef const double *heights = &z[0]
    cdef const int64_t *occupied = &cells[0]
    cdef const int64_t *first = &starts[0]
    cdef Candidates found
    cdef bint done, ok = True
    if b == 0 or k == 0:
        return
    found.capacity = 256
    found.count = 0
    found.index = <int64_t *> malloc(found.capacity * sizeof(int64_t))
    found.dist2 = <double *> malloc(found.capacity * sizeof(double))
    found.work = <double *> malloc(found.capacity * sizeof(double))
    if found.index == NULL or found.dist2 == NULL or found.work == NULL:
        free(found.index)
        free(found.dist2)
        free(found.work)
        raise MemoryError()
    with nogil:
        for i in range(b):
            c = centre[i]
            px = points[2 * c]
            py = points[2 * c + 1]
            ix = cell_x[c]
            iy = cell_y[c]
            found.count = 0
            R = 1
            for gy in range(max(iy - 1, 0), min(iy + 1, ny - 1) + 1):
                ok = ok and _add_cells(&found, points, occupied, first, ncells,
                                       gy * nx + max(ix - 1, 0), gy * nx + min(ix + 1, nx - 1), c, px, py)
            while True:
                done = ix - R <= 0 and iy - R <= 0 and ix + R >= nx - 1 and iy + R >= ny - 1
                if not done and found.count >= k:
                    memcpy(found.work, found.dist2, found.count * sizeof(double))
                    threshold = _kth(found.work, found.count, k)
                    reach = min(min(px - (x0 + (ix - R) * size), x0 + (ix + R + 1) * size - px),
                                min(py - (y0 + (iy - R) * size), y0 + (iy + R + 1) * size - py)) - slack
                    done = reach > 0 and threshold < reach * reach * (1.0 - 1e-12)
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
            memcpy(found.work, found.dist2, found.count * sizeof(double))
            threshold = _kth(found.work, found.count, k)
            _take_nearest(&found, points, heights, px, py, threshold, k, &out[i, 0], &ux[i, 0], &uy[i, 0],
                          &dist2[i, 0])
    free(found.index)
    free(found.dist2)
    free(found.work)
    if not ok:
        raise MemoryError()
