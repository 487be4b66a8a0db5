# cython: language_level=3
"""The lattice solver's kernels: c1mesh.stages.lattice_solver wraps them (validation, rows
or vertices in fixed blocks in the thread knob's threads), and nothing else imports them.

S is the smoothing system on lattice nodes, 3 unknowns per vertex, coupled only along the
7-point stencil of the split cells. A level holds it in stencil form by halves: nbr
(N, 7) int32 the vertex at each of OFFSETS' 7 offsets from vertex v (slot 0 v itself; −1
absent) and blocks (4, N, 3, 3), blocks[h, v] the 3 × 3 block of S coupling v to itself
(h = 0) and to its 3 forward neighbours, slots 1, 3, 5 (offsets (1, 0), (0, 1), (1, 1)),
at h = 1, 2, 3 (zero where absent): one array of blocks per half slot, so that the
backward reads (below) stream through whole blocks of consecutive vertices (with each
vertex's 4 blocks together, (N, 4, 3, 3), they read 72 B of every 288 and a pass over
S took 3.2 times as long at 420k vertices). S is symmetric, so the block of v at a backward slot 2, 4 or 6 (the
neighbour u at the opposite offset) is the transpose of u's block at forward slot 1, 3
or 5: every kernel reads it so (`_slot_block`), and S takes 4/7 of the memory of all 7
blocks (0.32 kB a vertex with nbr, against 0.53 and 0.77 as CSR; every pass is bound
by reading S).
Vertices of one colour (i + j) mod 3 never touch each other: a block of them reads only
other colours' unknowns and writes only its own (S is only read), and the bits do not
depend on the blocks' threads. A row's sum runs over the slots in order, the 3
unknowns of each in order (-ffp-contract=off: no fused multiply-add).

Vectors are (n, k) C-contiguous arrays: k right-hand sides solved together (the edf's
probes), each column summed exactly as it would be alone (LANES columns side by side, as
independent chains for the CPU), so a column's bits do not depend on k either. Every
kernel works on a range of rows or vertices and writes only those: the wrapper hands out
fixed blocks in the thread knob's threads.
"""
from libc.math cimport isfinite
from libc.stdint cimport int8_t, int32_t, int64_t

cdef enum:
    LANES = 4       # columns summed side by side: independent chains for the CPU, one pass over a row
    SLOTS = 7       # a vertex and its 6 stencil neighbours


cdef inline bint _inverse(const double *d, double *inv) noexcept nogil:
    """inv (9,) row-major: the inverse of the 3 × 3 block d (9,) row-major (the adjugate
    over the determinant, each entry divided); False (inv zero) when the determinant is
    not positive and finite. The one formula of `sweep`, `first_sweep` and
    `singular_blocks`: the diagonal inverses are formed where they are used, not stored
    ((N, 3, 3) at every level: 72 MB at 1M vertices)."""
    cdef int t
    cdef double det
    inv[0] = d[4] * d[8] - d[5] * d[7]
    inv[1] = d[2] * d[7] - d[1] * d[8]
    inv[2] = d[1] * d[5] - d[2] * d[4]
    inv[3] = d[5] * d[6] - d[3] * d[8]
    inv[4] = d[0] * d[8] - d[2] * d[6]
    inv[5] = d[2] * d[3] - d[0] * d[5]
    inv[6] = d[3] * d[7] - d[4] * d[6]
    inv[7] = d[1] * d[6] - d[0] * d[7]
    inv[8] = d[0] * d[4] - d[1] * d[3]
    det = d[0] * inv[0] + d[1] * inv[3] + d[2] * inv[6]
    if det > 0.0 and isfinite(det):
        for t in range(9):
            inv[t] = inv[t] / det
        return True
    for t in range(9):
        inv[t] = 0.0
    return False


def singular_blocks(const double[:, :, :, ::1] blocks, Py_ssize_t start, Py_ssize_t stop):
    """How many of S's diagonal blocks blocks[0, v] (blocks the half stencil
    (4, N, 3, 3)), start <= v < stop, have a determinant that is not positive and finite
    (`_inverse`: the sweeps leave those vertices alone)."""
    cdef Py_ssize_t v
    cdef double inv[9]
    cdef int64_t singular = 0
    with nogil:
        for v in range(start, stop):
            if not _inverse(&blocks[0, v, 0, 0], inv):
                singular += 1
    return singular


cdef inline const double *_slot_block(const int32_t *nbr, const double *blocks, Py_ssize_t n, Py_ssize_t v, Py_ssize_t slot,
                                      int *sp, int *sq) noexcept nogil:
    """The block of S coupling vertex v to nbr[slot] (nbr v's row (7,), the slot present),
    blocks the (4, n, 3, 3) half stencil's first entry: its entry (p, q) is
    blk[p sp + q sq]. Slot 0 and the forward slots 1, 3, 5 are v's own half slots 0, 1,
    2, 3 (sp, sq = 3, 1); a backward slot 2, 4, 6 is the transpose of the neighbour's
    block at the forward slot before it (sp, sq = 1, 3)."""
    if slot == 0 or slot & 1:
        sp[0] = 3
        sq[0] = 1
        return blocks + 9 * ((slot + 1) // 2 * n + v)
    sp[0] = 1
    sq[0] = 3
    return blocks + 9 * (slot // 2 * n + <Py_ssize_t> nbr[slot])


cdef inline void _load_block(const int32_t *nbr, const double *blocks, Py_ssize_t n, Py_ssize_t v, Py_ssize_t slot,
                             double *m) noexcept nogil:
    """m (9,) row-major: the block of S coupling vertex v to nbr[slot] (`_slot_block`),
    copied with constant offsets (a backward block transposed as it is copied): the sums
    then index it by constants."""
    cdef int sp, sq
    cdef const double *blk = _slot_block(nbr, blocks, n, v, slot, &sp, &sq)
    if sp == 3:
        m[0] = blk[0]
        m[1] = blk[1]
        m[2] = blk[2]
        m[3] = blk[3]
        m[4] = blk[4]
        m[5] = blk[5]
        m[6] = blk[6]
        m[7] = blk[7]
        m[8] = blk[8]
    else:
        m[0] = blk[0]
        m[1] = blk[3]
        m[2] = blk[6]
        m[3] = blk[1]
        m[4] = blk[4]
        m[5] = blk[7]
        m[6] = blk[2]
        m[7] = blk[5]
        m[8] = blk[8]


cdef inline void _vertex_sums(const int32_t *nbr, const double *blocks, Py_ssize_t n, Py_ssize_t v, const double *x,
                              Py_ssize_t k, Py_ssize_t c0, Py_ssize_t w, double *out) noexcept nogil:
    """out[p LANES + c] = (S x)[3v + p, c0 + c] for p < 3, c < w <= LANES, from vertex v's
    nbr row (7,) and the half stencil blocks (4, n, 3, 3) (its first entry; backward
    blocks read transposed: `_load_block`), x (n, k) row-major: each sum over the slots in
    order, the 3 unknowns of each in order, from 0, in local variables."""
    cdef Py_ssize_t slot, c
    cdef int q
    cdef double a
    cdef const double *xg
    cdef double blk[9]
    cdef double s00 = 0.0, s01 = 0.0, s02 = 0.0, s03 = 0.0
    cdef double s10 = 0.0, s11 = 0.0, s12 = 0.0, s13 = 0.0
    cdef double s20 = 0.0, s21 = 0.0, s22 = 0.0, s23 = 0.0
    if w == LANES:
        for slot in range(SLOTS):
            if nbr[slot] < 0:
                continue
            _load_block(nbr, blocks, n, v, slot, blk)
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
                _load_block(nbr, blocks, n, v, slot, blk)
                for q in range(3):
                    a = x[(3 * <Py_ssize_t> nbr[slot] + q) * k + c0 + c]
                    s00 = s00 + blk[q] * a
                    s10 = s10 + blk[3 + q] * a
                    s20 = s20 + blk[6 + q] * a
            out[c] = s00
            out[LANES + c] = s10
            out[2 * LANES + c] = s20


def sweep(const int32_t[:, ::1] nbr, const double[:, :, :, ::1] blocks, const double[:, ::1] b,
          double[:, ::1] x, Py_ssize_t start, Py_ssize_t stop):
    """One block Gauss–Seidel step on the vertices start <= v < stop (all of one colour):
    for each, r = b[3v:3v+3] − (S x)[3v:3v+3], then x[3v:3v+3] += D⁻¹ r, D⁻¹ the
    inverse of its diagonal block (`_inverse`, formed here: zero where singular), column
    by column of x (n, k). In place. The level numbers its vertices colour by colour, so a
    colour's blocks are read in one stream (every third vertex of the grid's order took
    6 times as long per vertex)."""
    cdef Py_ssize_t v, c, c0, w, chunk, k = x.shape[1], lanes = LANES
    cdef int p
    cdef double r[3 * LANES]
    cdef double dinv[9]
    if stop <= start:
        return
    with nogil:
        for v in range(start, stop):
            _inverse(&blocks[0, v, 0, 0], dinv)
            for chunk in range((k + lanes - 1) // lanes):
                c0 = chunk * lanes
                w = min(lanes, k - c0)
                _vertex_sums(&nbr[v, 0], &blocks[0, 0, 0, 0], blocks.shape[1], v, &x[0, 0], k, c0, w, r)
                for p in range(3):
                    for c in range(w):
                        r[p * LANES + c] = b[3 * v + p, c0 + c] - r[p * LANES + c]
                for p in range(3):
                    for c in range(w):
                        x[3 * v + p, c0 + c] = x[3 * v + p, c0 + c] + (
                            dinv[3 * p] * r[c] + dinv[3 * p + 1] * r[LANES + c] + dinv[3 * p + 2] * r[2 * LANES + c])


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
            _vertex_sums(&nbr[v, 0], &blocks[0, 0, 0, 0], blocks.shape[1], v, &x[0, 0], k, c0, w, acc)
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
    the order of a CSR row of P with its columns sorted, so the bits are those of that
    CSR product (tests/test_lattice_solver.py builds P explicitly)."""
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
    weights skipped, from 0: the order of a CSR row of Pᵀ stored slot by slot, p by p."""
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


def first_sweep(const double[:, :, :, ::1] blocks, const double[:, ::1] b, double[:, ::1] x,
                Py_ssize_t start, Py_ssize_t stop):
    """`sweep` where x is zero on every vertex its rows reach (a V-cycle's first colour,
    from x = 0): x[3v:3v+3] = D⁻¹ b[3v:3v+3] for start <= v < stop (D⁻¹ as `sweep`
    forms it), the bits `sweep` gives there (b − 0 is b), reading only the diagonal
    blocks of S (blocks the half stencil (4, N, 3, 3))."""
    cdef Py_ssize_t v, c, k = x.shape[1]
    cdef int p
    cdef double dinv[9]
    with nogil:
        for v in range(start, stop):
            _inverse(&blocks[0, v, 0, 0], dinv)
            for p in range(3):
                for c in range(k):
                    x[3 * v + p, c] = 0.0 + (dinv[3 * p] * b[3 * v, c] + dinv[3 * p + 1] * b[3 * v + 1, c]
                                             + dinv[3 * p + 2] * b[3 * v + 2, c])


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


def galerkin(const int32_t[:, ::1] nbr, const double[:, :, :, ::1] blocks, const int32_t[:, ::1] offsets,
             const int32_t[:, ::1] children, const int32_t[::1] order, const int32_t[:, ::1] parents,
             const int8_t[:, ::1] parent_slot, const double[:, :, ::1] weights, const int32_t[:, ::1] coarse_nbr,
             double[:, :, :, ::1] coarse_blocks, Py_ssize_t start, Py_ssize_t stop):
    """coarse_blocks[:, I] (4, 3, 3): the coarse operator Pᵀ S P's half stencil for the coarse
    vertices start <= I < stop: its blocks at slots 0, 1, 3, 5 of coarse_nbr[I] (its own
    vertex and its 6 stencil neighbours, OFFSETS' order, −1 absent: zeros there), the
    backward slots 2, 4, 6 neither summed nor stored (they are the transposes of the
    neighbours' forward blocks).

    S in stencil form by halves (nbr (n, 7), blocks (4, n, 3, 3): a backward block read as
    the transpose of the neighbour's forward one) on the fine vertices; offsets (7, 2) OFFSETS; P from
    the Transfer's node structure (`prolong`, `restrict`): children (m, 7) the fine vertex
    at each offset from a coarse vertex (−1: none), parents (n, 2) / parent_slot (n, 2)
    each fine vertex's coarse vertices ascending and its offset from each, weights
    (7, 3, 3) the fine datum per unit coarse datum at each offset; order (k,) the slots in
    the order of their first entry in a CSR row block of Pᵀ (rows q, then slots, then p:
    lattice_solver.child_order), the order its children are summed in.

    For each coarse vertex: R_f = weights[slot]ᵀ at each child f (at most 7), then
    U = Σ_f R_f S_f,g over the children's stencils, g on the 5 × 5 fine nodes around the
    coarse node (children in `order`, their slots in order, R's zero weights skipped: most
    Hermite weights are 0), then the coarse row Σ_g U_g P_g over those nodes in grid
    order, each P row 3g + q over g's parents ascending and q' in order, zero weights
    skipped: the summation order of the CSR products it replaces (Pᵀ's rows, P's rows
    with sorted columns), so the bits are theirs. A 7-point block stencil stays one under
    the Hermite P (a coarse entry needs fine offsets a + b − c = 2 (J − I) from three
    stencil offsets, which no J beyond the 7 allows), so the slots have room for every
    entry; an entry of P for a vertex not in the slots is counted and skipped (returned:
    0 when the pattern holds)."""
    cdef Py_ssize_t I, e, g, f, J, slot, fslot, last_j, last_slot, n, u, base, pslot, t, k = order.shape[0]
    cdef int p, q, r, qq
    cdef int64_t missing = 0
    cdef double back[9]
    cdef Py_ssize_t uvert[25]
    cdef double U[25][9]
    cdef double acc[SLOTS][9]
    cdef double rw, uw, u0, u1, u2
    cdef const double *blk
    cdef double *Ug
    # each slot's nonzero weights, in the order the sums take them: for Pᵀ (R = Wᵀ) by
    # p then r, for P by q then q'
    cdef int rn[SLOTS][3]
    cdef int rr[SLOTS][3][3]
    cdef double rv[SLOTS][3][3]
    cdef int pn[SLOTS][3]
    cdef int pq[SLOTS][3][3]
    cdef double pv[SLOTS][3][3]
    cdef int ushift[SLOTS]
    for slot in range(SLOTS):
        ushift[slot] = offsets[slot, 1] * 5 + offsets[slot, 0]
        for p in range(3):
            rn[slot][p] = 0
            pn[slot][p] = 0
            for r in range(3):
                if weights[slot, r, p] != 0.0:
                    rr[slot][p][rn[slot][p]] = r
                    rv[slot][p][rn[slot][p]] = weights[slot, r, p]
                    rn[slot][p] += 1
                if weights[slot, p, r] != 0.0:
                    pq[slot][p][pn[slot][p]] = r
                    pv[slot][p][pn[slot][p]] = weights[slot, p, r]
                    pn[slot][p] += 1
    with nogil:
        for I in range(start, stop):
            for u in range(25):
                uvert[u] = -1
                for t in range(9):
                    U[u][t] = 0.0
            for n in range(k):
                slot = order[n]
                f = children[I, slot]
                if f < 0:
                    continue
                base = 12 + ushift[slot]                  # (2, 2) is the coarse node's own fine node
                for fslot in range(SLOTS):
                    g = nbr[f, fslot]
                    if g < 0:
                        continue
                    u = base + ushift[fslot]
                    uvert[u] = g
                    _load_block(&nbr[f, 0], &blocks[0, 0, 0, 0], blocks.shape[1], f, fslot, back)
                    blk = &back[0]                        # row-major (a backward block transposed)
                    Ug = &U[u][0]
                    for p in range(3):
                        for t in range(rn[slot][p]):
                            rw = rv[slot][p][t]
                            r = rr[slot][p][t]
                            Ug[3 * p] = Ug[3 * p] + rw * blk[3 * r]
                            Ug[3 * p + 1] = Ug[3 * p + 1] + rw * blk[3 * r + 1]
                            Ug[3 * p + 2] = Ug[3 * p + 2] + rw * blk[3 * r + 2]
            for slot in range(SLOTS):
                for t in range(9):
                    acc[slot][t] = 0.0
            last_j = -1
            last_slot = SLOTS
            for u in range(25):
                g = uvert[u]
                if g < 0:
                    continue
                for q in range(3):
                    u0 = U[u][q]
                    u1 = U[u][3 + q]
                    u2 = U[u][6 + q]
                    for e in range(2):
                        J = parents[g, e]
                        if J < 0:
                            continue
                        if J != last_j:
                            slot = 0
                            while slot < SLOTS and coarse_nbr[I, slot] != J:
                                slot += 1
                            last_j = J
                            last_slot = slot
                        pslot = parent_slot[g, e]
                        if last_slot == SLOTS:
                            missing += pn[pslot][q]
                            continue
                        if last_slot != 0 and not last_slot & 1:
                            continue                      # a backward block: not stored
                        for t in range(pn[pslot][q]):
                            uw = pv[pslot][q][t]
                            qq = pq[pslot][q][t]
                            acc[last_slot][qq] = acc[last_slot][qq] + u0 * uw
                            acc[last_slot][3 + qq] = acc[last_slot][3 + qq] + u1 * uw
                            acc[last_slot][6 + qq] = acc[last_slot][6 + qq] + u2 * uw
            for slot in range(4):
                for t in range(9):
                    coarse_blocks[slot, I, t // 3, t % 3] = acc[0 if slot == 0 else 2 * slot - 1][t]
    return missing


cdef inline int32_t _vertex_at(const int32_t[::1] where, Py_ssize_t nx, Py_ssize_t ny, Py_ssize_t i,
                               Py_ssize_t j) noexcept nogil:
    """The vertex on grid node (i, j) of an nx × ny grid (where (nx ny,)), −1 when the node
    is absent or beyond the grid."""
    if i < 0 or i >= nx or j < 0 or j >= ny:
        return -1
    return where[j * nx + i]


def neighbours(const int64_t[::1] nodes, const int32_t[::1] where, Py_ssize_t nx, Py_ssize_t ny,
               const int32_t[:, ::1] offsets, int32_t[:, ::1] out, Py_ssize_t start, Py_ssize_t stop):
    """out[v, k] (7,): the vertex at offsets[k] from vertex v's node nodes[v] = j nx + i
    (where (nx ny,) each node's vertex, −1 none), −1 where there is none, for
    start <= v < stop."""
    cdef Py_ssize_t v, i, j, k
    with nogil:
        for v in range(start, stop):
            i = nodes[v] % nx
            j = nodes[v] // nx
            for k in range(SLOTS):
                out[v, k] = _vertex_at(where, nx, ny, i + offsets[k, 0], j + offsets[k, 1])


cdef inline bint _kept(const int32_t[::1] where, Py_ssize_t nx, Py_ssize_t ny, const int32_t[:, ::1] offsets,
                       Py_ssize_t I, Py_ssize_t J) noexcept nogil:
    """Whether coarse node (I, J) is kept: its own fine node (2I, 2J) is a vertex, or at
    least two fine nodes at offsets from it are."""
    cdef Py_ssize_t k
    cdef int reach = 0
    if _vertex_at(where, nx, ny, 2 * I, 2 * J) >= 0:
        return True
    for k in range(1, SLOTS):
        if _vertex_at(where, nx, ny, 2 * I + offsets[k, 0], 2 * J + offsets[k, 1]) >= 0:
            reach += 1
    return reach >= 2


def coarse_keep(const int32_t[::1] where, Py_ssize_t nx, Py_ssize_t ny, const int32_t[:, ::1] offsets,
                int32_t[::1] column):
    """The first pass over the coarse grid below the fine grid nx × ny whose node
    j nx + i holds vertex where[j nx + i] (−1: none): the coarse grid has
    (nx // 2 + 1) × (ny // 2 + 1) nodes, node (I, J) on fine node (2I, 2J); column
    (nxc nyc,) gets −2 − (I + J) mod 3 on the nodes kept (`_kept`, the module doc's rule)
    and −1 on the others. Returns how many are kept. Serial: a few lookups a node."""
    cdef Py_ssize_t nxc = nx // 2 + 1, nyc = ny // 2 + 1, I, J, m = 0
    with nogil:
        for J in range(nyc):
            for I in range(nxc):
                if _kept(where, nx, ny, offsets, I, J):
                    column[J * nxc + I] = -2 - <int32_t> ((I + J) % 3)
                    m += 1
                else:
                    column[J * nxc + I] = -1
    return m


def coarse_number(const int32_t[::1] where, Py_ssize_t nx, Py_ssize_t ny, const int32_t[:, ::1] offsets,
                  int32_t[::1] column, int64_t[::1] coarse, int32_t[:, ::1] children):
    """The second pass (after `coarse_keep` marked column): the kept coarse nodes numbered
    colour by colour ((I + J) mod 3), by node within a colour (lattice_solver.colour_order's
    numbering): column[node] becomes its coarse vertex (−1: dropped), coarse[c] (m,) the
    node of coarse vertex c, children[c, k] (m, 7) the fine vertex at offsets[k] from it
    (−1: none). Serial: a few lookups a node."""
    cdef Py_ssize_t nxc = nx // 2 + 1, nyc = ny // 2 + 1, node, I, J, k, m = 0
    cdef int colour
    with nogil:
        for colour in range(3):
            for J in range(nyc):
                for I in range(nxc):
                    node = J * nxc + I
                    if column[node] != -2 - colour:
                        continue
                    column[node] = <int32_t> m
                    coarse[m] = node
                    for k in range(SLOTS):
                        children[m, k] = _vertex_at(where, nx, ny, 2 * I + offsets[k, 0], 2 * J + offsets[k, 1])
                    m += 1


def parent_tables(const int64_t[::1] nodes, Py_ssize_t nx, const int32_t[::1] column, Py_ssize_t nxc,
                  int32_t[:, ::1] parents, int8_t[:, ::1] parent_slot, Py_ssize_t start, Py_ssize_t stop):
    """parents[f] (2,): the coarse vertices whose Hermite stencil reaches fine vertex f
    (on node nodes[f] = j nx + i), ascending, −1 where fewer, and parent_slot[f] the
    offset (OFFSETS' index) of f from each, for start <= f < stop; column (nxc nyc,) each
    coarse node's vertex (−1: dropped). Node (i, j) with i, j even is coarse node
    (i/2, j/2) itself (slot 0); otherwise it is the midpoint of the coarse edge from
    ((i − di)/2, (j − dj)/2) (offset (di, dj), di = i mod 2, dj = j mod 2: slot 1, 3 or 5)
    to ((i + di)/2, (j + dj)/2) (offset (−di, −dj): slot 2, 4 or 6), both on the coarse
    grid."""
    cdef Py_ssize_t f, i, j, di, dj
    cdef int32_t a, b, t
    cdef int8_t sa, sb, st
    with nogil:
        for f in range(start, stop):
            i = nodes[f] % nx
            j = nodes[f] // nx
            di = i & 1
            dj = j & 1
            if di == 0 and dj == 0:
                parents[f, 0] = column[(j // 2) * nxc + i // 2]
                parents[f, 1] = -1
                parent_slot[f, 0] = 0
                parent_slot[f, 1] = 0
                continue
            sa = 1 if dj == 0 else (3 if di == 0 else 5)
            sb = sa + 1
            a = column[((j - dj) // 2) * nxc + (i - di) // 2]
            b = column[((j + dj) // 2) * nxc + (i + di) // 2]
            if a < 0 or (b >= 0 and b < a):
                t = a
                a = b
                b = t
                st = sa
                sa = sb
                sb = st
            parents[f, 0] = a
            parent_slot[f, 0] = sa if a >= 0 else 0
            parents[f, 1] = b
            parent_slot[f, 1] = sb if b >= 0 else 0


def colour_bounds(const int64_t[::1] nodes, Py_ssize_t nx, int64_t[::1] bounds):
    """bounds (4,): each colour's first vertex and the count, bounds[c] <= v < bounds[c + 1]
    the vertices of colour c = (i + j) mod 3 of node nodes[v] = j nx + i, when the vertices
    are numbered colour by colour (returns True); False (bounds unset) when a vertex's
    colour is below the one before it. One pass."""
    cdef Py_ssize_t v, n = nodes.shape[0]
    cdef int colour, last = 0, c
    cdef bint ordered = True
    with nogil:
        bounds[0] = 0
        for v in range(n):
            colour = <int> ((nodes[v] % nx + nodes[v] // nx) % 3)
            if colour < last:
                ordered = False
                break
            for c in range(last + 1, colour + 1):
                bounds[c] = v
            last = colour
        if ordered:
            for c in range(last + 1, 4):
                bounds[c] = n
    return ordered


def neighbour_mismatches(const int64_t[::1] nodes, const int32_t[::1] where, Py_ssize_t nx, Py_ssize_t ny,
                         const int32_t[:, ::1] offsets, const int32_t[:, ::1] nbr, Py_ssize_t start,
                         Py_ssize_t stop):
    """How many of nbr[v, k] for start <= v < stop differ from what `neighbours` writes
    there (the vertex at offsets[k] from node nodes[v], −1 none): a stencil's slots
    checked against the lattice without a second (N, 7) table."""
    cdef Py_ssize_t v, i, j, k
    cdef int64_t wrong = 0
    with nogil:
        for v in range(start, stop):
            i = nodes[v] % nx
            j = nodes[v] // nx
            for k in range(SLOTS):
                if nbr[v, k] != _vertex_at(where, nx, ny, i + offsets[k, 0], j + offsets[k, 1]):
                    wrong += 1
    return wrong


def stencil_csr(const int32_t[:, ::1] nbr, const double[:, :, :, ::1] blocks, int64_t[::1] indptr,
                int64_t[::1] indices, double[::1] data):
    """S (3N, 3N) as CSR from its stencil form by halves (blocks (4, N, 3, 3)), both
    halves written out: rows 3v + p in order, each row's columns ascending: vertex v's
    present slots sorted by their vertex (at most 7: an insertion sort), each slot's 3
    unknowns in order, the block's entry (p, q) (`_slot_block`: a backward slot's the
    neighbour's forward block's (q, p)) stored whether zero or not. indptr (3N + 1,), indices and data (9 × present slots,). Serial (the coarsest
    level's few thousand vertices, for its direct factorisation)."""
    cdef Py_ssize_t v, n = nbr.shape[0], e = 0, a, b
    cdef int p, q, count, sp, sq
    cdef const double *blk
    cdef int32_t order[SLOTS]
    cdef int32_t t
    with nogil:
        indptr[0] = 0
        for v in range(n):
            count = 0
            for a in range(SLOTS):
                if nbr[v, a] < 0:
                    continue
                b = count
                while b > 0 and nbr[v, order[b - 1]] > nbr[v, a]:
                    order[b] = order[b - 1]
                    b -= 1
                order[b] = <int32_t> a
                count += 1
            for p in range(3):
                for a in range(count):
                    t = order[a]
                    blk = _slot_block(&nbr[v, 0], &blocks[0, 0, 0, 0], blocks.shape[1], v, t, &sp, &sq)
                    for q in range(3):
                        indices[e] = 3 * <int64_t> nbr[v, t] + q
                        data[e] = blk[p * sp + q * sq]
                        e += 1
                indptr[3 * v + p + 1] = e
