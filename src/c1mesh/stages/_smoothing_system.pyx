# cython: language_level=3
"""The assembly of the smoothing system's energy matrix: c1mesh.stages.smoothing_system wraps
it (validation, the rows in blocks in the thread knob's threads), and nothing else imports it.

The matrix is 3 × 3 vertex blocks on the pattern of the vertex adjacency (each vertex and
its neighbours in the triangles, in increasing order). The triangles' blocks are added one
triangle after another in increasing order (`add_blocks`, on consecutive chunks), so an
entry is the sum of its triangles' contributions in triangle order, from 0: the order in
which numpy's bincount over the triangles' vertex pairs summed them before, whatever the
chunks and the threads that computed the blocks.
"""
from libc.stdint cimport int32_t, int64_t

ctypedef fused index_t:
    int32_t
    int64_t


def incidence(const int64_t[:, ::1] triangles, int64_t[::1] start, int64_t[::1] corner):
    """start (N + 1,) and corner (3T,): the corners 3 t + k (triangle t, local vertex k) at
    vertex v are corner[start[v]:start[v + 1]], in increasing order (a counting sort of the
    triangles' vertices; start zeroed by the caller). One thread: O(T)."""
    cdef Py_ssize_t T = triangles.shape[0], n = start.shape[0] - 1, t, v
    cdef int k
    cdef int64_t total = 0, count
    with nogil:
        for t in range(T):
            for k in range(3):
                start[triangles[t, k] + 1] += 1
        for v in range(n):
            total += start[v + 1]
            start[v + 1] = total
        for t in range(T):                      # start[v] is v's next free slot meanwhile
            for k in range(3):
                v = triangles[t, k]
                corner[start[v]] = 3 * t + k
                start[v] += 1
        for v in range(n, 0, -1):               # and back to each vertex's first slot
            start[v] = start[v - 1]
        start[0] = 0


cdef Py_ssize_t _neighbours(const int64_t[:, ::1] triangles, const int64_t[::1] start,
                            const int64_t[::1] corner, Py_ssize_t v, int64_t *out) noexcept nogil:
    """v and the distinct vertices of the triangles at v, increasing, into out (room for
    3 × the corners at v, and 1); returns their count, 1 for a vertex without triangles
    (its diagonal block is stored: the data and gradient terms add to it). Insertion
    sort: a few dozen."""
    cdef Py_ssize_t count = 1, i, j, i2
    cdef int64_t t, w
    cdef int k
    out[0] = v
    for i in range(start[v], start[v + 1]):
        t = corner[i] // 3
        for k in range(3):
            w = triangles[t, k]
            j = count - 1
            while j >= 0 and out[j] > w:
                j -= 1
            if j >= 0 and out[j] == w:
                continue
            j += 1
            for i2 in range(count, j, -1):
                out[i2] = out[i2 - 1]
            out[j] = w
            count += 1
    return count


def degrees(const int64_t[:, ::1] triangles, const int64_t[::1] start, const int64_t[::1] corner,
            Py_ssize_t first, Py_ssize_t stop, int64_t[::1] scratch, int64_t[::1] out):
    """out[v] for v in [first, stop): the number of v's neighbours, itself included.
    scratch: room for 3 × the most corners at a vertex."""
    cdef Py_ssize_t v
    with nogil:
        for v in range(first, stop):
            out[v] = _neighbours(triangles, start, corner, v, &scratch[0])


def neighbours(const int64_t[:, ::1] triangles, const int64_t[::1] start, const int64_t[::1] corner,
               const int64_t[::1] row_start, Py_ssize_t first, Py_ssize_t stop, int64_t[::1] out):
    """out[row_start[v]:row_start[v + 1]] for v in [first, stop): v's neighbours (itself
    included), increasing; row_start (N + 1,) from `degrees`' counts."""
    cdef Py_ssize_t v
    with nogil:
        for v in range(first, stop):
            _neighbours(triangles, start, corner, v, &out[row_start[v]])


def csr_indices(const int64_t[::1] row_start, const int64_t[::1] cols, Py_ssize_t first,
                Py_ssize_t stop, index_t[::1] out):
    """The CSR column indices of rows 3v, 3v + 1, 3v + 2 for v in [first, stop) into out
    (int32 or int64, the matrix's index type):
    each row lists 3w, 3w + 1, 3w + 2 for v's neighbours w (cols[row_start[v]:row_start[v + 1]])."""
    cdef Py_ssize_t v, i, p
    cdef int c, d
    with nogil:
        for v in range(first, stop):
            p = 9 * row_start[v]
            for c in range(3):
                for i in range(row_start[v], row_start[v + 1]):
                    for d in range(3):
                        out[p] = <index_t> (3 * cols[i] + d)
                        p += 1


cdef inline int _local(int vertex, int component) noexcept nogil:
    """Local datum of (local vertex, component 0 = f, 1 = ∂x, 2 = ∂y): smoothing_energy's
    order f0, f1, f2, ∂x f0, ∂y f0, ..."""
    return vertex if component == 0 else 3 + 2 * vertex + component - 1


cdef inline Py_ssize_t _slot(const int64_t[::1] cols, Py_ssize_t lo, Py_ssize_t hi,
                             int64_t w) noexcept nogil:
    """The position of w in the increasing cols[lo:hi] (w is there): bisection."""
    cdef Py_ssize_t mid
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if cols[mid] <= w:
            lo = mid
        else:
            hi = mid
    return lo


cdef inline void _triangle_places(const int64_t[:, ::1] triangles, int64_t t, const int64_t[::1] row_start,
                                   const int64_t[::1] cols, Py_ssize_t *base, Py_ssize_t *width,
                                   Py_ssize_t slot[3][3]) noexcept nogil:
    """Where triangle t's 9 x 9 block goes in the CSR values of the vertex pattern
    (`add_blocks`): for each corner a, base[a] = 9 · its row's first pattern entry,
    width[a] = 3 · its row's length (the stride between its 3 component rows), and
    slot[a][b] = 3 · the position of corner b among that row's columns (9 bisections)."""
    cdef int a, b
    cdef Py_ssize_t lo, deg
    for a in range(3):
        lo = row_start[triangles[t, a]]
        deg = row_start[triangles[t, a] + 1] - lo
        base[a] = 9 * lo
        width[a] = 3 * deg
        for b in range(3):
            slot[a][b] = 3 * (_slot(cols, lo, lo + deg, triangles[t, b]) - lo)


def add_blocks(const int64_t[:, ::1] triangles, Py_ssize_t first, const double[:, :, ::1] blocks,
               const int64_t[::1] row_start, const int64_t[::1] cols, double[::1] data):
    """Adds the 9 × 9 blocks (B, 9, 9) of triangles first, ..., first + B − 1 into the CSR
    values data of the vertex pattern (each vertex's rows list 3 values per neighbour w,
    components 0, 1, 2 of w, in increasing w; `neighbours`), one triangle after another.
    Called on consecutive chunks of the triangles from 0, every entry is the sum of its
    triangles' contributions in increasing triangle order from 0 (data zeroed first). One
    thread: 9 bisections and 81 additions a triangle."""
    cdef Py_ssize_t B = blocks.shape[0], i, row
    cdef Py_ssize_t base[3]
    cdef Py_ssize_t width[3]
    cdef Py_ssize_t slot[3][3]
    cdef int64_t t
    cdef int a, b, c, d
    with nogil:
        for i in range(B):
            t = first + i
            _triangle_places(triangles, t, row_start, cols, base, width, slot)
            for a in range(3):
                for c in range(3):
                    row = base[a] + c * width[a]
                    for b in range(3):
                        for d in range(3):
                            data[row + slot[a][b] + d] += blocks[i, _local(a, c), _local(b, d)]


def data_scatter(const int64_t[:, ::1] triangles, const int64_t[::1] tri, const double[:, ::1] rows,
                 const double[::1] w, const int64_t[::1] order, const int64_t[::1] row_start,
                 const int64_t[::1] cols, double[::1] data):
    """Adds Aᵀ W A into the CSR values data of the vertex pattern (`add_blocks`): data point i lies in triangle tri[i], its row of A is rows[i]
    (9,) over that triangle's local data (smoothing_energy's order), its weight w[i]. The
    points are taken in increasing order, points of weight 0 skipped; each product
    w_i a_j a_k is formed once for j <= k and added to both (j, k) and (k, j), so the
    matrix stays exactly symmetric. One thread: O(81 M) additions, 9 bisections a point."""
    cdef Py_ssize_t m = order.shape[0], p, i
    cdef Py_ssize_t base[3]
    cdef Py_ssize_t width[3]
    cdef Py_ssize_t slot[3][3]
    cdef int64_t t
    cdef int j, k, a, b, c, d
    cdef double wa, term
    with nogil:
        for p in range(m):
            i = order[p]
            if w[i] == 0.0:
                continue
            t = tri[i]
            _triangle_places(triangles, t, row_start, cols, base, width, slot)
            for j in range(9):
                a, c = _vertex_of(j), _component_of(j)
                wa = w[i] * rows[i, j]
                for k in range(j, 9):
                    b, d = _vertex_of(k), _component_of(k)
                    term = wa * rows[i, k]
                    data[base[a] + c * width[a] + slot[a][b] + d] += term
                    if k != j:
                        data[base[b] + d * width[b] + slot[b][a] + c] += term


cdef inline int _vertex_of(int local) noexcept nogil:
    """The local vertex of local datum `local` (the inverse of _local)."""
    return local if local < 3 else (local - 3) // 2


cdef inline int _component_of(int local) noexcept nogil:
    """The component (0 = f, 1 = ∂x, 2 = ∂y) of local datum `local` (the inverse of _local)."""
    return 0 if local < 3 else 1 + (local - 3) % 2


def rows_product(const int64_t[:, ::1] triangles, const int64_t[::1] tri, const double[:, ::1] values,
                 const double[:, ::1] u, double[:, ::1] out, Py_ssize_t first, Py_ssize_t stop):
    """out[i] = A[i] u for the data points first <= i < stop, column by column of u (3N, k):
    point i lies in triangle tri[i], its row of A is values[i] (9,) over that triangle's
    local data (smoothing_energy's order). Each sum runs from 0 over the row's unknowns in
    increasing order (the triangle's vertices by number, components 0, 1, 2): the order
    in which scipy's product summed the CSR row of A, whose columns are sorted."""
    cdef Py_ssize_t i, col, k = u.shape[1]
    cdef int64_t t, v
    cdef int m, a, c
    cdef int order[3]
    cdef double s
    with nogil:
        for i in range(first, stop):
            t = tri[i]
            _by_vertex(triangles, t, order)
            for col in range(k):
                s = 0.0
                for m in range(3):
                    a = order[m]
                    v = triangles[t, a]
                    for c in range(3):
                        s = s + values[i, _local(a, c)] * u[3 * v + c, col]
                out[i, col] = s


cdef inline void _by_vertex(const int64_t[:, ::1] triangles, int64_t t, int order[3]) noexcept nogil:
    """order: triangle t's corners 0, 1, 2 by increasing vertex number."""
    cdef int m, swap
    order[0], order[1], order[2] = 0, 1, 2
    for m in range(2):
        if triangles[t, order[1]] < triangles[t, order[0]]:
            swap = order[0]
            order[0] = order[1]
            order[1] = swap
        if triangles[t, order[2]] < triangles[t, order[1]]:
            swap = order[1]
            order[1] = order[2]
            order[2] = swap


def rows_adjoint(const int64_t[:, ::1] triangles, const int64_t[::1] tri, const double[:, ::1] values,
                 const double[:, ::1] r, double[:, ::1] out):
    """out = Aᵀ r (3N, k) for r (M, k), out zeroed by the caller: each data point's row
    values[i] (9,) times r[i] added at its triangle's unknowns, the points in increasing
    order, so that each entry is its sum over the points in that order from 0 (the order
    of scipy's Aᵀ r over A's rows). One thread: a point's entries go to its triangle's
    vertices, which other points share (0.15 s for 1M points and 4 columns)."""
    cdef Py_ssize_t i, col, row, m = r.shape[0], k = r.shape[1]
    cdef int64_t t
    cdef int a, c
    cdef double value
    with nogil:
        for i in range(m):
            t = tri[i]
            for a in range(3):
                for c in range(3):
                    value = values[i, _local(a, c)]
                    row = 3 * triangles[t, a] + c
                    for col in range(k):
                        out[row, col] = out[row, col] + value * r[i, col]
