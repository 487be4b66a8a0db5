# cython: language_level=3
"""The lattice solver's kernels: c1mesh.stages.lattice_solver wraps them (validation, rows
or vertices in fixed blocks in the thread knob's threads), and nothing else imports them.

S is the smoothing system on lattice nodes, 3 unknowns per vertex, coupled only along the
7-point stencil of the split cells. A level holds it in stencil form: nbr (N, 7) int32 the
vertex at each of OFFSETS' 7 offsets from vertex v (slot 0 v itself; −1 absent) and
blocks (N, 7, 3, 3) the 3 × 3 block of S coupling v to it (zero where absent): one index
per 9 values, so a pass over S reads 0.53 kB a vertex where CSR read 0.77 (every pass is
bound by that read). Vertices of one colour (i + j) mod 3 never touch each other: a
block of them reads only other colours' unknowns and writes only its own, and the bits
do not depend on the blocks' threads. A row's sum runs over the slots in order, the 3
unknowns of each in order (-ffp-contract=off: no fused multiply-add).

Vectors are (n, k) C-contiguous arrays: k right-hand sides solved together (the edf's
probes), each column summed exactly as it would be alone (LANES columns side by side, as
independent chains for the CPU), so a column's bits do not depend on k either. Every
kernel works on a range of rows or vertices and writes only those: the wrapper hands out
fixed blocks in the thread knob's threads.
"""
from libc.math cimport isfinite
from libc.stdint cimport int8_t, int32_t, int64_t

ctypedef fused index_t:
    int32_t
    int64_t


cdef enum:
    LANES = 4       # columns summed side by side: independent chains for the CPU, one pass over a row
    SLOTS = 7       # a vertex and its 6 stencil neighbours


def block_inverses(const double[:, :, :, ::1] blocks, double[:, :, ::1] dinv, Py_ssize_t start, Py_ssize_t stop):
    """dinv[v] (3, 3): the inverse of S's diagonal block blocks[v, 0] for start <= v < stop
    (the adjugate over the determinant). Returns the blocks whose determinant is not
    positive and finite (their dinv is zero: the sweep leaves those vertices alone)."""
    cdef Py_ssize_t v
    cdef int p, q
    cdef double d[3][3]
    cdef double det
    cdef int64_t singular = 0
    with nogil:
        for v in range(start, stop):
            for p in range(3):
                for q in range(3):
                    d[p][q] = blocks[v, 0, p, q]
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
    return singular


cdef inline void _vertex_sums(const int32_t *nbr, const double *blocks, const double *x, Py_ssize_t k,
                              Py_ssize_t c0, Py_ssize_t w, double *out) noexcept nogil:
    """out[p LANES + c] = (S x)[3v + p, c0 + c] for p < 3, c < w <= LANES, from vertex v's
    nbr row (7,) and blocks (7, 3, 3), x (n, k) row-major: each sum over the slots in
    order, the 3 unknowns of each in order, from 0, in local variables."""
    cdef Py_ssize_t slot, c
    cdef int p, q
    cdef double a
    cdef const double *xg
    cdef const double *blk
    cdef double s00 = 0.0, s01 = 0.0, s02 = 0.0, s03 = 0.0
    cdef double s10 = 0.0, s11 = 0.0, s12 = 0.0, s13 = 0.0
    cdef double s20 = 0.0, s21 = 0.0, s22 = 0.0, s23 = 0.0
    if w == LANES:
        for slot in range(SLOTS):
            if nbr[slot] < 0:
                continue
            blk = blocks + 9 * slot
            for q in range(3):
                xg = x + (3 * <Py_ssize_t> nbr[slot] + q) * k + c0
                a = blk[q]
                s00 = s00 + a * xg[0]
                s01 = s01 + a * xg[1]
                s02 = s02 + a * xg[2]
                s03 = s03 + a * xg[3]
                a = blk[3 + q]
                s10 = s10 + a * xg[0]
                s11 = s11 + a * xg[1]
                s12 = s12 + a * xg[2]
                s13 = s13 + a * xg[3]
                a = blk[6 + q]
                s20 = s20 + a * xg[0]
                s21 = s21 + a * xg[1]
                s22 = s22 + a * xg[2]
                s23 = s23 + a * xg[3]
        out[0] = s00
        out[1] = s01
        out[2] = s02
        out[3] = s03
        out[LANES] = s10
        out[LANES + 1] = s11
        out[LANES + 2] = s12
        out[LANES + 3] = s13
        out[2 * LANES] = s20
        out[2 * LANES + 1] = s21
        out[2 * LANES + 2] = s22
        out[2 * LANES + 3] = s23
    else:
        for c in range(w):
            s00 = 0.0
            s10 = 0.0
            s20 = 0.0
            for slot in range(SLOTS):
                if nbr[slot] < 0:
                    continue
                blk = blocks + 9 * slot
                for q in range(3):
                    a = x[(3 * <Py_ssize_t> nbr[slot] + q) * k + c0 + c]
                    s00 = s00 + blk[q] * a
                    s10 = s10 + blk[3 + q] * a
                    s20 = s20 + blk[6 + q] * a
            out[c] = s00
            out[LANES + c] = s10
            out[2 * LANES + c] = s20


def sweep(const int32_t[:, ::1] nbr, const double[:, :, :, ::1] blocks, const double[:, ::1] b,
          double[:, ::1] x, const double[:, :, ::1] dinv, Py_ssize_t start, Py_ssize_t stop):
    """One block Gauss–Seidel step on the vertices start <= v < stop (all of one colour):
    for each, r = b[3v:3v+3] − (S x)[3v:3v+3], then x[3v:3v+3] += dinv[v] r, column by
    column of x (n, k). In place. The level numbers its vertices colour by colour, so a
    colour's blocks are read in one stream (every third vertex of the grid's order took
    6 times as long per vertex)."""
    cdef Py_ssize_t v, c, c0, w, chunk, k = x.shape[1], lanes = LANES
    cdef int p
    cdef double r[3 * LANES]
    if stop <= start:
        return
    with nogil:
        for v in range(start, stop):
            for chunk in range((k + lanes - 1) // lanes):
                c0 = chunk * lanes
                w = min(lanes, k - c0)
                _vertex_sums(&nbr[v, 0], &blocks[v, 0, 0, 0], &x[0, 0], k, c0, w, r)
                for p in range(3):
                    for c in range(w):
                        r[p * LANES + c] = b[3 * v + p, c0 + c] - r[p * LANES + c]
                for p in range(3):
                    for c in range(w):
                        x[3 * v + p, c0 + c] = x[3 * v + p, c0 + c] + (
                            dinv[v, p, 0] * r[c] + dinv[v, p, 1] * r[LANES + c] + dinv[v, p, 2] * r[2 * LANES + c])


cdef void _stencil_rows(const int32_t[:, ::1] nbr, const double[:, :, :, ::1] blocks, const double* b,
                        const double[:, ::1] x, double[:, ::1] out, Py_ssize_t start, Py_ssize_t stop) noexcept nogil:
    """out[3v:3v+3] = (S x)[3v:3v+3] for start <= v < stop, column by column of x (n, k);
    where b is not NULL (the first entry of an (n, k) C-contiguous array), b[3v:3v+3] minus
    that instead. The one loop of stencil_product and stencil_residual."""
    cdef Py_ssize_t v, c, c0, w, chunk, k = x.shape[1], lanes = LANES
    cdef int p
    cdef double acc[3 * LANES]
    for v in range(start, stop):
        for chunk in range((k + lanes - 1) // lanes):
            c0 = chunk * lanes
            w = min(lanes, k - c0)
            _vertex_sums(&nbr[v, 0], &blocks[v, 0, 0, 0], &x[0, 0], k, c0, w, acc)
            for p in range(3):
                for c in range(w):
                    if b == NULL:
                        out[3 * v + p, c0 + c] = acc[p * LANES + c]
                    else:
                        out[3 * v + p, c0 + c] = b[(3 * v + p) * k + c0 + c] - acc[p * LANES + c]


def stencil_product(const int32_t[:, ::1] nbr, const double[:, :, :, ::1] blocks, const double[:, ::1] x,
                    double[:, ::1] y, Py_ssize_t start, Py_ssize_t stop):
    """y[3v:3v+3] = (S x)[3v:3v+3] for start <= v < stop, column by column of x (n, k)."""
    if stop <= start:
        return
    with nogil:
        _stencil_rows(nbr, blocks, NULL, x, y, start, stop)


def stencil_residual(const int32_t[:, ::1] nbr, const double[:, :, :, ::1] blocks, const double[:, ::1] b,
                     const double[:, ::1] x, double[:, ::1] r, Py_ssize_t start, Py_ssize_t stop):
    """r[3v:3v+3] = b[3v:3v+3] − (S x)[3v:3v+3] for start <= v < stop (S x summed as
    `stencil_product` does), column by column of x (n, k); b has x's shape."""
    if stop <= start or x.shape[1] == 0:
        return
    if b.shape[0] != x.shape[0] or b.shape[1] != x.shape[1]:
        raise ValueError(f"b must have x's shape {(x.shape[0], x.shape[1])}, got {(b.shape[0], b.shape[1])}")
    with nogil:
        _stencil_rows(nbr, blocks, &b[0, 0], x, r, start, stop)


def prolong(const int32_t[:, ::1] parents, const int8_t[:, ::1] parent_slot, const double[:, :, ::1] weights,
            const double[:, ::1] x, double[:, ::1] y, bint add, Py_ssize_t start, Py_ssize_t stop):
    """y[3f:3f+3] = (P x)[3f:3f+3], or y[3f:3f+3] + (P x)[3f:3f+3] when add, for the fine
    vertices start <= f < stop, column by column of the coarse x (3m, k).

    P is applied from the lattice's structure: parents (n, 2) the coarse vertices whose
    Hermite stencil reaches fine vertex f, ascending (−1: none), parent_slot (n, 2) the
    offset (OFFSETS' index) of f from each, weights (7, 3, 3) the fine datum per unit
    coarse datum at each offset (hermite_weights). Row 3f + p sums weights[slot, p, q]
    x[3c + q] over the parents in order and q in order, zero weights skipped, from 0:
    the order of a CSR row of P with its columns sorted (what lattice_solver.prolongation
    stores), so the bits are those of that CSR product."""
    cdef Py_ssize_t f, c, e, col, k = x.shape[1]
    cdef int p, q, slot
    cdef double s, w
    with nogil:
        for f in range(start, stop):
            for p in range(3):
                for col in range(k):
                    s = 0.0
                    for e in range(2):
                        c = parents[f, e]
                        if c < 0:
                            continue
                        slot = parent_slot[f, e]
                        for q in range(3):
                            w = weights[slot, p, q]
                            if w != 0.0:
                                s = s + w * x[3 * c + q, col]
                    if add:
                        y[3 * f + p, col] = y[3 * f + p, col] + s
                    else:
                        y[3 * f + p, col] = s


def restrict(const int32_t[:, ::1] children, const double[:, :, ::1] weights, const double[:, ::1] x,
             double[:, ::1] y, Py_ssize_t start, Py_ssize_t stop):
    """y[3c:3c+3] = (Pᵀ x)[3c:3c+3] for the coarse vertices start <= c < stop, column by
    column of the fine x (3n, k): children (m, 7) the fine vertex at each of OFFSETS'
    offsets from coarse vertex c (−1: none), weights (7, 3, 3) as `prolong`'s. Row 3c + q
    sums weights[slot, p, q] x[3 f + p] over the slots in order and p in order, zero
    weights skipped, from 0: the order of lattice_solver.stencil_rows' CSR row."""
    cdef Py_ssize_t c, f, col, k = x.shape[1]
    cdef int p, q, slot
    cdef double s, w
    with nogil:
        for c in range(start, stop):
            for q in range(3):
                for col in range(k):
                    s = 0.0
                    for slot in range(SLOTS):
                        f = children[c, slot]
                        if f < 0:
                            continue
                        for p in range(3):
                            w = weights[slot, p, q]
                            if w != 0.0:
                                s = s + w * x[3 * f + p, col]
                    y[3 * c + q, col] = s


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


def galerkin(const int32_t[:, ::1] nbr, const double[:, :, :, ::1] blocks, const int64_t[::1] nodes,
             Py_ssize_t nx, const int32_t[:, ::1] offsets,
             const index_t[::1] p_indptr, const index_t[::1] p_indices, const double[::1] p_data,
             const index_t[::1] t_indptr, const index_t[::1] t_indices, const double[::1] t_data,
             const int64_t[::1] coarse_nodes, Py_ssize_t nxc, const int32_t[:, ::1] coarse_nbr,
             double[:, :, :, ::1] coarse_blocks, Py_ssize_t start, Py_ssize_t stop):
    """coarse_blocks[I] (7, 3, 3): the coarse operator Pᵀ S P's blocks for the coarse
    vertices start <= I < stop, in the slots of coarse_nbr[I] (its own vertex and its 6
    stencil neighbours, OFFSETS' order, −1 absent: zeros there).

    S in stencil form (nbr, blocks) on the fine vertices, on nodes (n,) of a grid nx wide;
    offsets (7, 2) OFFSETS; P (3n, 3m) and T = Pᵀ (3m, 3n) CSR; coarse_nodes (m,) on the
    coarse grid nxc wide, coarse node (I, J) on fine node (2I, 2J).

    For each coarse vertex: R_f = T's 3 × 3 block at each child f (the fine vertices its
    rows reach, at most 7), then U = Σ_f R_f S_f,g over the children's stencils, g on the
    5 × 5 fine nodes around the coarse node (children in T's order, their slots in order,
    R's zero weights skipped: most Hermite weights are 0), then the coarse row
    Σ_g U_g P_g over those nodes in grid order, P's rows in order. A 7-point block stencil
    stays one under the Hermite P (a coarse entry needs fine offsets a + b − c = 2 (J − I)
    from three stencil offsets, which no J beyond the 7 allows), so the slots have room
    for every entry; anything beyond them (a child off the 3 × 3 fine nodes around the
    coarse node, an entry of P for a vertex not in the slots) is counted and skipped
    (returned: 0 when the pattern holds)."""
    cdef Py_ssize_t I, e, g, f, b, c, J, slot, fslot, last_j, last_slot, nchild, ch, u, ci, cj, gx, gy
    cdef int p, q, r
    cdef int64_t missing = 0
    cdef Py_ssize_t child[SLOTS]
    cdef double R[SLOTS][3][3]
    cdef Py_ssize_t uvert[25]
    cdef double U[25][3][3]
    cdef double acc[3][SLOTS][3]
    cdef double rw, uw
    with nogil:
        for I in range(start, stop):
            ci = coarse_nodes[I] % nxc
            cj = coarse_nodes[I] // nxc
            nchild = 0
            for p in range(3):
                for e in range(t_indptr[3 * I + p], t_indptr[3 * I + p + 1]):
                    f = t_indices[e] // 3
                    ch = 0
                    while ch < nchild and child[ch] != f:
                        ch += 1
                    if ch == nchild:
                        if nchild == SLOTS:
                            missing += 1
                            continue
                        child[ch] = f
                        for q in range(3):
                            for r in range(3):
                                R[ch][q][r] = 0.0
                        nchild += 1
                    R[ch][p][t_indices[e] - 3 * f] = t_data[e]
            for u in range(25):
                uvert[u] = -1
                for p in range(3):
                    for q in range(3):
                        U[u][p][q] = 0.0
            for ch in range(nchild):
                f = child[ch]
                gx = nodes[f] % nx - 2 * ci
                gy = nodes[f] // nx - 2 * cj
                if gx < -1 or gx > 1 or gy < -1 or gy > 1:
                    missing += 1
                    continue
                for fslot in range(SLOTS):
                    g = nbr[f, fslot]
                    if g < 0:
                        continue
                    u = (gy + offsets[fslot, 1] + 2) * 5 + gx + offsets[fslot, 0] + 2
                    uvert[u] = g
                    for p in range(3):
                        for r in range(3):
                            rw = R[ch][p][r]
                            if rw == 0.0:
                                continue
                            for q in range(3):
                                U[u][p][q] = U[u][p][q] + rw * blocks[f, fslot, r, q]
            for p in range(3):
                for slot in range(SLOTS):
                    for q in range(3):
                        acc[p][slot][q] = 0.0
            last_j = -1
            last_slot = SLOTS
            for u in range(25):
                g = uvert[u]
                if g < 0:
                    continue
                for q in range(3):
                    b = 3 * g + q
                    for e in range(p_indptr[b], p_indptr[b + 1]):
                        c = p_indices[e]
                        J = c // 3
                        if J != last_j:
                            slot = 0
                            while slot < SLOTS and coarse_nbr[I, slot] != J:
                                slot += 1
                            last_j = J
                            last_slot = slot
                        if last_slot == SLOTS:
                            missing += 1
                            continue
                        uw = p_data[e]
                        for p in range(3):
                            acc[p][last_slot][c - 3 * J] = acc[p][last_slot][c - 3 * J] + U[u][p][q] * uw
            for slot in range(SLOTS):
                for p in range(3):
                    for q in range(3):
                        coarse_blocks[I, slot, p, q] = acc[p][slot][q]
    return missing
