# cython: language_level=3
"""The assembly of a lattice mesh's smoothing system in stencil form: c1mesh.stages.lattice_system
wraps it (validation, the vertices in fixed blocks in the thread knob's threads), and
nothing else imports it.

S = s K + Aᵀ W A + diag is written vertex by vertex, by halves (the solver's stencil
form, stages/_lattice_solver.pyx): vertex v's 3 rows against itself and its forward
neighbours nbr[v, 1], nbr[v, 3], nbr[v, 5] (slot 0 itself, −1 absent), blocks[:, v]
(4, 3, 3) of blocks (4, N, 3, 3);
its blocks at the backward slots 2, 4, 6 are the transposes of those neighbours' forward
blocks at v, so they are neither summed nor stored. Only v's own rows are written, from
the triangles at v, so a block of vertices needs no
other block's work and the bits do not depend on the threads. Each entry sums in a fixed
order: K's over the triangles at v in increasing triangle order from 0, the data term's
over those triangles' points (each triangle's in the order given) from 0, each product
w_i a_ij a_ik formed as (w_i a_i,min(j,k)) a_i,max(j,k); then (K s + data) + diag. Those
are the sums and products the CSR assembly of the energy (_smoothing_system.add_blocks)
and of the data term (_smoothing_system.data_scatter) formed, added as System.matrix
added them: the stored rows have its bits. Its other half (the backward blocks, which
System.matrix summed at the other vertex, in that vertex's triangle order and with its
products (w a_v) a_u against (w a_u) a_v) differs from the transposes read here in the
last bits only. -ffp-contract=off: no fused multiply-add.

Two passes write it, so that the data term, which needs no s and holds nearly all the
work (9 × 9 products per point), can be summed while the strength is being searched:
`assemble_data` stores each vertex's data blocks, and `assemble_energy` then sums K and
writes K s + data + diag over them, the same expressions in the same order as one pass.
"""
from libc.stdint cimport int32_t, int64_t
from libc.string cimport memset

cdef enum:
    SLOTS = 7       # a vertex and its 6 stencil neighbours


cdef inline int _local(int vertex, int component) noexcept nogil:
    """Local datum of (local vertex, component 0 = f, 1 = ∂x, 2 = ∂y): smoothing_energy's
    order f0, f1, f2, ∂x f0, ∂y f0, ..."""
    return vertex if component == 0 else 3 + 2 * vertex + component - 1


cdef inline bint _slots(const int64_t[:, ::1] triangles, const int32_t[:, ::1] nbr, Py_ssize_t v,
                        Py_ssize_t t, int *slots) noexcept nogil:
    """Each corner b of triangle t: its slot in nbr[v] (SLOTS: none); True when all three
    have one (else the corners outside the stencil are counted by the caller)."""
    cdef int b, slot
    for b in range(3):
        slot = 0
        while slot < SLOTS and nbr[v, slot] != triangles[t, b]:
            slot += 1
        slots[b] = slot
    return slots[0] != SLOTS and slots[1] != SLOTS and slots[2] != SLOTS


cdef inline int _missing(int *slots) noexcept nogil:
    """How many of a triangle's three corners have no stencil slot."""
    return (slots[0] == SLOTS) + (slots[1] == SLOTS) + (slots[2] == SLOTS)


cdef inline bint _corner_at(const int64_t[:, ::1] triangles, const int32_t[:, ::1] nbr,
                            const int64_t[::1] corner, Py_ssize_t v, Py_ssize_t e, Py_ssize_t *t, int *a,
                            int *slots, int64_t *outside) noexcept nogil:
    """The incidence entry e at vertex v: its triangle t and corner a, its corners' slots
    (_slots); False (and the corners outside the stencil counted) when one has none."""
    t[0] = corner[e] // 3
    a[0] = corner[e] % 3
    if _slots(triangles, nbr, v, t[0], slots):
        return True
    outside[0] += _missing(slots)
    return False


def assemble_data(const int64_t[:, ::1] triangles, const int64_t[::1] start, const int64_t[::1] corner,
                  const int64_t[::1] first_point, const int64_t[::1] points, const double[:, ::1] rows,
                  const double[::1] w, const int32_t[:, ::1] nbr, double[:, :, :, ::1] blocks,
                  Py_ssize_t first, Py_ssize_t stop):
    """blocks[:, v] (4, 3, 3) of the data term Aᵀ W A for first <= v < stop: its blocks at
    slots 0, 1, 3, 5 of nbr[v] (self and the forward neighbours; zeros where absent);
    returns the triangle corners at those vertices that are none of nbr[v]'s (0 when the
    mesh is the lattice's).

    triangles (T, 3); the corners 3 t + k at vertex v are corner[start[v]:start[v + 1]],
    increasing (_smoothing_system.incidence). The data points of triangle t are
    points[first_point[t]:first_point[t + 1]], point i's row of A rows[i] (9,) in that
    order, its weight w[i] (weight 0: skipped); with no data rows (the data are the
    vertices) first_point is all zeros."""
    cdef Py_ssize_t v, e, p, i, t
    cdef int a, b, c, d, j, k, slot, h
    cdef int slots[3]
    cdef int64_t outside = 0
    cdef double D[SLOTS][3][3]
    cdef double row[9]
    cdef double weighted[9]
    with nogil:
        for v in range(first, stop):
            memset(&D[0][0][0], 0, sizeof(D))
            for e in range(start[v], start[v + 1]):
                if not _corner_at(triangles, nbr, corner, v, e, &t, &a, slots, &outside):
                    continue
                for p in range(first_point[t], first_point[t + 1]):
                    i = points[p]
                    if w[i] == 0.0:
                        continue
                    for j in range(9):
                        row[j] = rows[i, j]
                        weighted[j] = w[i] * row[j]
                    for c in range(3):
                        j = _local(a, c)
                        for b in range(3):
                            if slots[b] != 0 and not slots[b] & 1:
                                continue                  # a backward block: not stored
                            for d in range(3):
                                k = _local(b, d)
                                D[slots[b]][c][d] += (weighted[j] * row[k] if j <= k else weighted[k] * row[j])
            for h in range(4):
                slot = 0 if h == 0 else 2 * h - 1
                for c in range(3):
                    for d in range(3):
                        blocks[h, v, c, d] = D[slot][c][d]
    return outside


def assemble_energy(const int64_t[:, ::1] triangles, const int64_t[::1] start, const int64_t[::1] corner,
                    const int64_t[::1] shape_of, const double[:, :, ::1] elements,
                    const int32_t[:, ::1] nbr, double s, const double[:, ::1] diag,
                    double[:, :, :, ::1] blocks, Py_ssize_t first, Py_ssize_t stop):
    """blocks[:, v] = K s + blocks[:, v] for first <= v < stop, blocks holding the data
    term (assemble_data), then diag (N, 3) added to the diagonal of v's own block: S's
    stored half. Triangle t's 9 × 9 energy block is elements[shape_of[t]]
    (smoothing_energy's local order), K summed over the triangles at v in increasing
    order; returns the corners outside the stencil, as assemble_data."""
    cdef Py_ssize_t v, e, t
    cdef int a, b, c, d, j, slot, h
    cdef int slots[3]
    cdef int64_t outside = 0
    cdef double K[SLOTS][3][3]
    cdef const double *element
    with nogil:
        for v in range(first, stop):
            memset(&K[0][0][0], 0, sizeof(K))
            for e in range(start[v], start[v + 1]):
                if not _corner_at(triangles, nbr, corner, v, e, &t, &a, slots, &outside):
                    continue
                element = &elements[shape_of[t], 0, 0]
                for c in range(3):
                    j = _local(a, c)
                    for b in range(3):
                        if slots[b] != 0 and not slots[b] & 1:
                            continue                  # a backward block: not stored
                        for d in range(3):
                            K[slots[b]][c][d] += element[9 * j + _local(b, d)]
            for h in range(4):
                slot = 0 if h == 0 else 2 * h - 1
                for c in range(3):
                    for d in range(3):
                        blocks[h, v, c, d] = K[slot][c][d] * s + blocks[h, v, c, d]
            for c in range(3):
                blocks[0, v, c, c] = blocks[0, v, c, c] + diag[v, c]
    return outside
