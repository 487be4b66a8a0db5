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

Vectors are (n, k) C-contiguous arrays: k right-hand sides solved together (the edf's
probes), each column summed exactly as it would be alone, so a column's bits do not
depend on k either. Every kernel works on a range of rows (or vertices) and writes only
those: the wrapper hands out fixed blocks in the thread knob's threads.
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


cdef enum:
    LANES = 4       # columns summed side by side: independent chains for the CPU, one pass over a row


cdef inline void _row_sums(const index_t *indices, const double *data, Py_ssize_t lo, Py_ssize_t hi,
                           const double *x, Py_ssize_t k, Py_ssize_t c0, Py_ssize_t w,
                           double *acc) noexcept nogil:
    """acc[c] = Σ data[e] x[indices[e], c0 + c] over lo <= e < hi, for c < w <= LANES, x (n, k)
    row-major: each column's sum from 0 in the entries' order (what it would be alone).
    The sums run in local variables (a store per entry to acc cost 4 times the time)."""
    cdef Py_ssize_t e, c
    cdef double a, s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0
    cdef const double *xe
    if w == LANES:
        for e in range(lo, hi):
            a = data[e]
            xe = x + indices[e] * k + c0
            s0 = s0 + a * xe[0]
            s1 = s1 + a * xe[1]
            s2 = s2 + a * xe[2]
            s3 = s3 + a * xe[3]
        acc[0] = s0
        acc[1] = s1
        acc[2] = s2
        acc[3] = s3
    else:
        for c in range(w):
            s0 = 0.0
            for e in range(lo, hi):
                s0 = s0 + data[e] * x[indices[e] * k + c0 + c]
            acc[c] = s0


def sweep(const index_t[::1] indptr, const index_t[::1] indices, const double[::1] data,
          const double[:, ::1] b, double[:, ::1] x, const double[:, :, ::1] dinv,
          Py_ssize_t start, Py_ssize_t stop):
    """One block Gauss–Seidel step on the vertices start <= v < stop (all of one colour):
    for each, r = b[3v:3v+3] − (S x)[3v:3v+3] over its three CSR rows, then
    x[3v:3v+3] += dinv[v] r, column by column of x (n, k). In place. The level numbers its
    vertices colour by colour, so a colour's rows are read in one stream (every third
    vertex of the grid's order took 6 times as long per vertex)."""
    cdef Py_ssize_t v, row, c, c0, w, chunk, k = x.shape[1], lanes = LANES
    cdef int p
    cdef double r[3][LANES]
    cdef double *xp
    if stop <= start:
        return
    xp = &x[0, 0]
    with nogil:
        for v in range(start, stop):
            for chunk in range((k + lanes - 1) // lanes):
                c0 = chunk * lanes
                w = min(LANES, k - c0)
                for p in range(3):
                    row = 3 * v + p
                    _row_sums(&indices[0], &data[0], indptr[row], indptr[row + 1], xp, k, c0, w, r[p])
                    for c in range(w):
                        r[p][c] = b[row, c0 + c] - r[p][c]
                for p in range(3):
                    for c in range(w):
                        x[3 * v + p, c0 + c] = x[3 * v + p, c0 + c] + (
                            dinv[v, p, 0] * r[0][c] + dinv[v, p, 1] * r[1][c] + dinv[v, p, 2] * r[2][c])


def first_sweep(const double[:, ::1] b, double[:, ::1] x, const double[:, :, ::1] dinv,
                Py_ssize_t start, Py_ssize_t stop):
    """`sweep` where x is zero on every vertex its rows reach (a V-cycle's first colour,
    from x = 0): x[3v:3v+3] = dinv[v] b[3v:3v+3] for start <= v < stop, the bits `sweep`
    gives there (b − 0 is b), without reading S."""
    cdef Py_ssize_t v, c, k = x.shape[1]
    cdef int p
    with nogil:
        for v in range(start, stop):
            for p in range(3):
                for c in range(k):
                    x[3 * v + p, c] = 0.0 + (dinv[v, p, 0] * b[3 * v, c] + dinv[v, p, 1] * b[3 * v + 1, c]
                                             + dinv[v, p, 2] * b[3 * v + 2, c])


def product(const index_t[::1] indptr, const index_t[::1] indices, const double[::1] data,
            const double[:, ::1] x, double[:, ::1] y, bint add, Py_ssize_t start, Py_ssize_t stop):
    """y[row] = (A x)[row], or y[row] + (A x)[row] when add, for the CSR rows
    start <= row < stop of A, column by column of x (n, k): each sum over the row's stored
    entries in their order, from 0."""
    cdef Py_ssize_t row, c, c0, w, chunk, k = x.shape[1], lanes = LANES
    cdef double acc[LANES]
    if stop <= start:
        return
    with nogil:
        for row in range(start, stop):
            for chunk in range((k + lanes - 1) // lanes):
                c0 = chunk * lanes
                w = min(LANES, k - c0)
                _row_sums(&indices[0], &data[0], indptr[row], indptr[row + 1], &x[0, 0], k, c0, w, acc)
                for c in range(w):
                    if add:
                        y[row, c0 + c] = y[row, c0 + c] + acc[c]
                    else:
                        y[row, c0 + c] = acc[c]


def residual(const index_t[::1] indptr, const index_t[::1] indices, const double[::1] data,
             const double[:, ::1] b, const double[:, ::1] x, double[:, ::1] r, Py_ssize_t start, Py_ssize_t stop):
    """r[row] = b[row] − (A x)[row] for the CSR rows start <= row < stop (A x summed as
    `product` does), column by column of x (n, k)."""
    cdef Py_ssize_t row, c, c0, w, chunk, k = x.shape[1], lanes = LANES
    cdef double acc[LANES]
    if stop <= start:
        return
    with nogil:
        for row in range(start, stop):
            for chunk in range((k + lanes - 1) // lanes):
                c0 = chunk * lanes
                w = min(LANES, k - c0)
                _row_sums(&indices[0], &data[0], indptr[row], indptr[row + 1], &x[0, 0], k, c0, w, acc)
                for c in range(w):
                    r[row, c0 + c] = b[row, c0 + c] - acc[c]


def dots(const double[:, ::1] a, const double[:, ::1] b, double[::1] out, Py_ssize_t start, Py_ssize_t stop):
    """out[c] = Σ a[i, c] b[i, c] over start <= i < stop, each column's sum in the rows' order."""
    cdef Py_ssize_t i, c, c0, w, chunk, k = a.shape[1], lanes = LANES
    cdef double acc[LANES]
    with nogil:
        for chunk in range((k + lanes - 1) // lanes):
            c0 = chunk * lanes
            w = min(LANES, k - c0)
            for c in range(w):
                acc[c] = 0.0
            for i in range(start, stop):
                for c in range(w):
                    acc[c] = acc[c] + a[i, c0 + c] * b[i, c0 + c]
            for c in range(w):
                out[c0 + c] = acc[c]


cdef enum:
    MAX_CHILD_ROWS = 64     # distinct fine rows restricting to one coarse vertex (Hermite P: 21)


def galerkin(const index_t[::1] s_indptr, const index_t[::1] s_indices, const double[::1] s_data,
             const index_t[::1] p_indptr, const index_t[::1] p_indices, const double[::1] p_data,
             const index_t[::1] t_indptr, const index_t[::1] t_indices, const double[::1] t_data,
             const int64_t[:, ::1] neighbours, const int64_t[::1] out_indptr, index_t[::1] out_indices,
             double[::1] out_data, Py_ssize_t start, Py_ssize_t stop):
    """The rows 3I..3I+2 of the coarse operator Pᵀ S P for the coarse vertices
    start <= I < stop, written into the CSR arrays out_* at out_indptr's places (the
    wrapper sizes them: 3 entries per row for each neighbour).

    S (3n, 3n), P (3n, 3m) and T = Pᵀ (3m, 3n) CSR; neighbours (m, 7): the coarse
    vertices I's row may couple to (its own node and its 6 stencil neighbours), ascending,
    −1 after the last. A 7-point block stencil stays one under the Hermite P (a coarse
    entry needs fine offsets a + b − c = 2 (J − I) from three stencil offsets, which no J
    beyond the 7 allows), so the coarse rows have room for every entry; an entry of
    P's rows whose vertex is not among them is counted and skipped (returned: 0 when
    the pattern holds).

    For each fine row a in I's rows of T (its children, with weights w[p] = T[3I+p, a]),
    the row (S P)[a] over I's neighbours is summed (S's row in order, P's rows in order),
    then added w[p] times to row 3I+p, children in the order T lists them. A row of S P
    is so computed once for each coarse vertex it restricts to (at most two), and none
    is stored."""
    cdef Py_ssize_t I, e, f, g, a, b, c, J, slot, last_j, last_slot, nn, nchild, ch, pos
    cdef int p, q
    cdef int64_t missing = 0
    cdef index_t child_row[MAX_CHILD_ROWS]
    cdef double child_w[MAX_CHILD_ROWS][3]
    cdef double acc[3][7][3]
    cdef double row_sp[7][3]
    cdef double s
    with nogil:
        for I in range(start, stop):
            nn = 0
            while nn < 7 and neighbours[I, nn] >= 0:
                nn += 1
            nchild = 0
            for p in range(3):
                for e in range(t_indptr[3 * I + p], t_indptr[3 * I + p + 1]):
                    a = t_indices[e]
                    ch = 0
                    while ch < nchild and child_row[ch] != a:
                        ch += 1
                    if ch == nchild:
                        if nchild == MAX_CHILD_ROWS:
                            missing += 1
                            continue
                        child_row[ch] = <index_t> a
                        child_w[ch][0] = 0.0
                        child_w[ch][1] = 0.0
                        child_w[ch][2] = 0.0
                        nchild += 1
                    child_w[ch][p] = t_data[e]
            for p in range(3):
                for slot in range(7):
                    for q in range(3):
                        acc[p][slot][q] = 0.0
            for ch in range(nchild):
                a = child_row[ch]
                for slot in range(7):
                    for q in range(3):
                        row_sp[slot][q] = 0.0
                last_j = -1
                last_slot = -1
                for f in range(s_indptr[a], s_indptr[a + 1]):
                    b = s_indices[f]
                    s = s_data[f]
                    for g in range(p_indptr[b], p_indptr[b + 1]):
                        c = p_indices[g]
                        J = c // 3
                        if J != last_j:
                            slot = 0
                            while slot < nn and neighbours[I, slot] != J:
                                slot += 1
                            last_j = J
                            last_slot = slot
                        if last_slot == nn:
                            missing += 1
                            continue
                        row_sp[last_slot][c - 3 * J] = row_sp[last_slot][c - 3 * J] + s * p_data[g]
                for p in range(3):
                    if child_w[ch][p] == 0.0:       # adds nothing (most Hermite weights are 0)
                        continue
                    for slot in range(nn):
                        for q in range(3):
                            acc[p][slot][q] = acc[p][slot][q] + child_w[ch][p] * row_sp[slot][q]
            for p in range(3):
                pos = out_indptr[3 * I + p]
                for slot in range(nn):
                    J = neighbours[I, slot]
                    for q in range(3):
                        out_indices[pos] = <index_t> (3 * J + q)
                        out_data[pos] = acc[p][slot][q]
                        pos += 1
    return missing
