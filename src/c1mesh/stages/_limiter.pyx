# cython: language_level=3
"""The limiter's kernels: c1mesh.stages.limiter wraps them (validation, the blocks in the
thread knob's threads), and nothing else imports them.

Two kinds. Per-edge or per-triangle passes take a range start <= i < stop and write only
their own rows, so the wrapper runs fixed blocks in threads and the bits do not depend on
the count. Scatters into vertices (a vertex's sums, its smallest factor) take the edges
in the order numpy's bincount and ufunc.at took them: every a-end in edge order, then
every b-end, so each vertex adds its terms in the same order as before. They run in one
thread, except normal_equations, which takes a range of vertices and scans every edge
for them (a vertex's order is the same in any range).

The arithmetic is numpy's, operation for operation (the build sets -ffp-contract=off);
`_np_maximum`, `_np_minimum` and `_np_clip` pick as numpy's maximum, minimum and clip do,
NaN and signed zeros included.
"""
from libc.math cimport fabs, isfinite, isnan, sqrt, INFINITY, NAN
from libc.stdint cimport int64_t, uint8_t

from c1mesh.core._prefetch cimport AHEAD, prefetch_corners


cdef inline double _maximum(double a, double b) noexcept nogil:
    """NaN when either is NaN, else the larger (the first when equal)."""
    if isnan(a) or isnan(b):
        return NAN
    return a if a >= b else b


cdef inline double _np_maximum(double a, double b) noexcept nogil:
    """numpy's maximum(a, b): a NaN operand wins, else the larger, b when equal."""
    if isnan(a):
        return a
    return a if a > b else b


cdef inline double _np_minimum(double a, double b) noexcept nogil:
    """numpy's minimum(a, b): a NaN operand wins, else the smaller, b when equal."""
    if isnan(a):
        return a
    return a if a < b else b


cdef inline double _np_clip(double x, double low, double high) noexcept nogil:
    """numpy's clip(x, low, high) for low <= high: NaN stays NaN, -0.0 stays -0.0."""
    if x < low:
        return low
    if x > high:
        return high
    return x


def longest_adjacent(const double[::1] length2, const int64_t[:, ::1] tri_edge, double[::1] out):
    """out (E,): the largest length2 (E,) over the edges of the one or two triangles holding
    each edge (tri_edge (T, 3) the triangles' edges; every edge in at least one). NaN
    wherever a NaN takes part, as numpy's maximum gives it; the largest does not depend
    on the order the triangles come in. Only picks among the values: no rounding. One
    pass over the triangles, one thread."""
    cdef Py_ssize_t T = tri_edge.shape[0], E = out.shape[0], t, e
    cdef int k
    cdef double longest
    with nogil:
        for e in range(E):
            out[e] = -INFINITY
        for t in range(T):
            longest = _maximum(_maximum(length2[tri_edge[t, 0]], length2[tri_edge[t, 1]]),
                               length2[tri_edge[t, 2]])
            for k in range(3):
                e = tri_edge[t, k]
                out[e] = _maximum(out[e], longest)


# ------------------------------------------------------------------ per-edge passes

def edge_vectors(const double[:, ::1] xy, const int64_t[::1] a, const int64_t[::1] b,
                 double[::1] dx, double[::1] dy, Py_ssize_t start, Py_ssize_t stop):
    """dx, dy (E,): p_b − p_a of the edges a→b (E,), points xy (n, 2) in plane units (a
    point's x and y in one row: one cache line per end)."""
    cdef Py_ssize_t e
    with nogil:
        for e in range(start, stop):
            dx[e] = xy[b[e], 0] - xy[a[e], 0]
            dy[e] = xy[b[e], 1] - xy[a[e], 1]


def edge_values(const double[::1] f, const int64_t[::1] a, const int64_t[::1] b,
                double[::1] delta, double[::1] size, Py_ssize_t start, Py_ssize_t stop):
    """delta (E,) = f_b − f_a and size (E,) = |f_a| + |f_b| of the edges a→b, heights f (n,)."""
    cdef Py_ssize_t e
    cdef double fa, fb
    with nogil:
        for e in range(start, stop):
            fa = f[a[e]]
            fb = f[b[e]]
            delta[e] = fb - fa
            size[e] = fabs(fa) + fabs(fb)


def predict(const double[:, ::1] g, const int64_t[::1] a, const int64_t[::1] b,
            const double[::1] dx, const double[::1] dy, const uint8_t[::1] rows,
            double[::1] pred_a, double[::1] pred_b, Py_ssize_t start, Py_ssize_t stop):
    """pred_a, pred_b (E,): the height changes A_a·d and A_b·d that the end gradients g
    (n, 2) predict along each edge a→b with d = (dx, dy); only the edges with rows[e]
    set when rows (E,) is given, every edge when it is empty."""
    cdef Py_ssize_t e
    cdef bint every = rows.shape[0] == 0
    with nogil:
        for e in range(start, stop):
            if every or rows[e]:
                pred_a[e] = g[a[e], 0] * dx[e] + g[a[e], 1] * dy[e]
                pred_b[e] = g[b[e], 0] * dx[e] + g[b[e], 1] * dy[e]


def residuals(const double[::1] delta, const double[::1] pred_a, const double[::1] pred_b,
              double[::1] out, Py_ssize_t start, Py_ssize_t stop):
    """out (E,): the trapezoid residual Δ − (δ_a + δ_b)/2 of each edge, in height units."""
    cdef Py_ssize_t e
    with nogil:
        for e in range(start, stop):
            out[e] = delta[e] - 0.5 * (pred_a[e] + pred_b[e])


def inconsistent(const double[::1] delta, const double[::1] pred_a, const double[::1] pred_b,
                 const double[::1] size, double consistency, double noise, double rounding,
                 uint8_t[::1] bad, Py_ssize_t start, Py_ssize_t stop):
    """bad (E,) 0/1: |e| > consistency · max(|Δ|, max(|δ_a|, |δ_b|)/2) + noise +
    rounding · (size + |δ_a| + |δ_b|), e the trapezoid residual (limiter.inconsistent_edges);
    a NaN anywhere makes an edge consistent, as numpy's comparison does."""
    cdef Py_ssize_t e
    cdef double residual, abs_a, abs_b, scale
    with nogil:
        for e in range(start, stop):
            residual = delta[e] - 0.5 * (pred_a[e] + pred_b[e])
            abs_a = fabs(pred_a[e])
            abs_b = fabs(pred_b[e])
            scale = _np_maximum(fabs(delta[e]), 0.5 * _np_maximum(abs_a, abs_b))
            bad[e] = fabs(residual) > consistency * scale + noise + rounding * (size[e] + abs_a + abs_b)


def unit_normals(const double[::1] dx, const double[::1] dy, double[:, ::1] out,
                 Py_ssize_t start, Py_ssize_t stop):
    """out (E, 2): the unit normal (−dy, dx) / |d| of each edge vector (dx, dy) (E,)."""
    cdef Py_ssize_t e
    cdef double length
    with nogil:
        for e in range(start, stop):
            length = sqrt(dx[e] * dx[e] + dy[e] * dy[e])
            out[e, 0] = -dy[e] / length
            out[e, 1] = dx[e] / length


cdef inline double _corner_ratio(double ux, double uy, double lx, double ly, double pnx, double pny,
                                 double cross) noexcept nogil:
    """max(|s|, |1 − s|) for the opposite vertex p_n (0 when absent: not finite, inf when
    the ratio is not finite); cross = e × u."""
    cdef double s = ((pnx - lx) * uy - (pny - ly) * ux) / cross
    cdef double ratio = _np_maximum(fabs(s), fabs(1.0 - s))
    if not (isfinite(pnx) and isfinite(pny)):
        return 0.0
    return ratio if isfinite(ratio) else INFINITY


cdef double _worst_ratio(double ux, double uy, double lx, double ly, double ex, double ey,
                         double pax, double pay, double pbx, double pby) noexcept nogil:
    """The worst max(|s|, |1 − s|) of direction u over the edge's triangles (opposite
    vertices pa, pb; pb NaN on the boundary), s where the line through p_n along u meets
    the edge l + s·e; inf when u is not finite or (nearly) parallel to the edge."""
    cdef double cross = ex * uy - ey * ux, worst
    worst = _np_maximum(0.0, _corner_ratio(ux, uy, lx, ly, pax, pay, cross))
    worst = _np_maximum(worst, _corner_ratio(ux, uy, lx, ly, pbx, pby, cross))
    if not (isfinite(ux) and isfinite(uy)):
        return INFINITY
    if fabs(cross) <= 1e-9 * sqrt(ex * ex + ey * ey) * sqrt(ux * ux + uy * uy):
        return INFINITY
    return worst


def choose_directions(const double[:, ::1] xy, const int64_t[::1] a,
                      const int64_t[::1] b, const double[::1] dx, const double[::1] dy,
                      const int64_t[::1] idx, const int64_t[::1] first, const int64_t[::1] second,
                      double ratio_limit, double[:, ::1] out, uint8_t[::1] change,
                      Py_ssize_t start, Py_ssize_t stop):
    """For the flagged edges idx[i], start <= i < stop (opposite vertices first[i] and
    second[i], -1 on the boundary): the candidate of smallest worst ratio (`_worst_ratio`)
    among out's unit normal, pb − pa, mid − pa and mid − pb (the first of equal ones); when
    the normal's exceeds ratio_limit and another wins, out[e] becomes that candidate over
    its length, else change[e] is cleared (limiter.edge_directions)."""
    cdef Py_ssize_t i
    cdef int64_t e
    cdef int c, best
    cdef double lx, ly, midx, midy, pax, pay, pbx, pby, length
    cdef double ux[4]
    cdef double uy[4]
    cdef double cost[4]
    with nogil:
        for i in range(start, stop):
            e = idx[i]
            lx, ly = xy[a[e], 0], xy[a[e], 1]
            midx, midy = 0.5 * (lx + xy[b[e], 0]), 0.5 * (ly + xy[b[e], 1])
            pax, pay = xy[first[i], 0], xy[first[i], 1]
            pbx, pby = NAN, NAN
            if second[i] >= 0:
                pbx, pby = xy[second[i], 0], xy[second[i], 1]
            ux[0], uy[0] = out[e, 0], out[e, 1]
            ux[1], uy[1] = pbx - pax, pby - pay
            ux[2], uy[2] = midx - pax, midy - pay
            ux[3], uy[3] = midx - pbx, midy - pby
            best = 0
            for c in range(4):
                cost[c] = _worst_ratio(ux[c], uy[c], lx, ly, dx[e], dy[e], pax, pay, pbx, pby)
                if cost[c] < cost[best]:
                    best = c
            if cost[0] > ratio_limit and best > 0:
                length = sqrt(ux[best] * ux[best] + uy[best] * uy[best])
                out[e, 0], out[e, 1] = ux[best] / length, uy[best] / length
            else:
                change[e] = 0


# ------------------------------------------------------------------ per-triangle passes

def corner_ratios(const double[:, ::1] xy, const int64_t[:, ::1] tri,
                  double[:, ::1] out, Py_ssize_t start, Py_ssize_t stop):
    """out (T, 3): max(|s|, |1 − s|) at each corner k of the triangles tri (T, 3), s the
    foot of p_k on the line of the opposite edge p_i → p_j (i, j = k + 1, k + 2):
    s = (p_k − p_i)·e / |e|², e = p_j − p_i (NaN for a zero-length edge)."""
    cdef Py_ssize_t t
    cdef int k, i, j
    cdef double ex, ey, foot
    cdef double px[3]
    cdef double py[3]
    with nogil:
        for t in range(start, stop):
            prefetch_corners(xy, tri, t + AHEAD, stop)
            for k in range(3):                   # each corner's coordinates read once
                px[k] = xy[tri[t, k], 0]
                py[k] = xy[tri[t, k], 1]
            for k in range(3):
                i, j = (k + 1) % 3, (k + 2) % 3
                ex = px[j] - px[i]
                ey = py[j] - py[i]
                foot = (px[k] - px[i]) * ex + (py[k] - py[i]) * ey
                foot = foot / (ex * ex + ey * ey)
                out[t, k] = _np_maximum(fabs(foot), fabs(1.0 - foot))


def edge_screen(const int64_t[:, ::1] tri_edge, const int64_t[::1] owner, const int64_t[::1] owner_slot,
                const int64_t[::1] count, const double[:, ::1] ratio, double[::1] out,
                Py_ssize_t start, Py_ssize_t stop):
    """out (E,): each edge's worst corner ratio (T, 3) over its one or two triangles, written
    from the triangles start <= t < stop: an edge of one triangle by its owner, an edge of
    two by its other slot, as first if first > last else last (first the owner's ratio;
    NaN-aware as the scatter it replaces: a NaN last wins, a NaN first loses)."""
    cdef Py_ssize_t t
    cdef int k
    cdef int64_t e
    cdef double first, last
    with nogil:
        for t in range(start, stop):
            for k in range(3):
                e = tri_edge[t, k]
                last = ratio[t, k]
                if owner[e] == t and owner_slot[e] == k:
                    if count[e] == 1:
                        out[e] = last
                    continue
                first = ratio[owner[e], owner_slot[e]]
                out[e] = first if first > last else last


# ------------------------------------------------------------------ scatters, one thread

def opposite_vertices(const int64_t[:, ::1] tri, const int64_t[:, ::1] tri_edge,
                      const int64_t[::1] position, const int64_t[::1] first, int64_t[::1] second):
    """second (m,): for the m edges with position[e] >= 0 (E,), the vertex opposite the edge
    in a triangle that holds it other than first[position[e]] (the owner's), left as it is
    (-1) on a boundary edge; the last such slot in triangle order."""
    cdef Py_ssize_t T = tri.shape[0], t
    cdef int k
    cdef int64_t p
    with nogil:
        for t in range(T):
            for k in range(3):
                p = position[tri_edge[t, k]]
                if p >= 0 and tri[t, k] != first[p]:
                    second[p] = tri[t, k]


def crease_moves(const double[::1] f, const int64_t[::1] a, const int64_t[::1] b,
                 const double[::1] residual, const double[::1] length2, const double[::1] reach2,
                 double crease_level, double clip, double[::1] total, int64_t[::1] count,
                 int64_t[::1] creasing, double[::1] out):
    """limiter.reconcile_heights' moves: every edge a→b with 6|e|·√reach2 > crease_level ·
    length2 (e the residual, length2 its squared length, reach2 the squared longest edge
    of its triangles) moves a by m = clip(e/2, ±clip) and b by −m; out (n,) = f plus
    each moved vertex's mean move (total (n,) zeroed and count (n,) zeroed: its sum and
    number of moves; creasing (E,) scratch: the creasing edges, listed by the one test).
    Returns the number of such edges."""
    cdef Py_ssize_t E = a.shape[0], n = f.shape[0], e, i, m = 0, v
    cdef double move
    with nogil:
        for e in range(E):
            if 6.0 * fabs(residual[e]) * sqrt(reach2[e]) > crease_level * length2[e]:
                creasing[m] = e
                m += 1
        for i in range(m):                   # a-ends, then b-ends: numpy's bincount order
            e = creasing[i]
            total[a[e]] += _np_clip(0.5 * residual[e], -clip, clip)
            count[a[e]] += 1
        for i in range(m):
            e = creasing[i]
            move = _np_clip(0.5 * residual[e], -clip, clip)
            total[b[e]] += -move
            count[b[e]] += 1
        for v in range(n):
            out[v] = f[v] + total[v] / count[v] if count[v] > 0 else f[v]
    return m


def touch(const int64_t[::1] a, const int64_t[::1] b, const uint8_t[::1] bad,
          uint8_t[::1] touched, uint8_t[::1] near):
    """touched (n,) zeroed: set at both ends of every bad (E,) edge; near (E,): the edges
    with a touched end."""
    cdef Py_ssize_t E = a.shape[0], e
    with nogil:
        for e in range(E):
            if bad[e]:
                touched[a[e]] = 1
                touched[b[e]] = 1
        for e in range(E):
            near[e] = touched[a[e]] | touched[b[e]]


def normal_equations(const int64_t[::1] a, const int64_t[::1] b, const double[::1] dx,
                     const double[::1] dy, const double[::1] delta, const uint8_t[::1] near,
                     const int64_t[::1] position, const int64_t[::1] vertices,
                     const double[:, ::1] g, double normal_weight, double[::1] degree,
                     double[:, :, ::1] M, double[:, ::1] r, Py_ssize_t start, Py_ssize_t stop):
    """limiter.reconcile_gradients' least-squares systems M (m, 2, 2), r (m, 2) of the
    vertices[p] (m,), start <= p < stop (position (n,): each vertex's p, else -1), M, r and
    degree (m,) zeroed: over the near (E,) edges of nonzero length at each, with û = d/|d|
    and the secant slope Δ/|d|, M = [[Σûx², Σûxûy], [Σûxûy, Σûy²]] + w·I and
    r = Σû·slope + w·A, w = normal_weight · degree (the number of such edges) and A = g[v]
    (n, 2) the vertex's gradient; each sum is complete before w is added.

    Each vertex adds its a-ends in edge order, then its b-ends (numpy's bincount order), so
    its sums do not depend on how the vertices are split into ranges: the wrapper runs one
    range per thread, each scanning every edge for its own vertices."""
    cdef Py_ssize_t E = a.shape[0], e, p
    cdef int end
    cdef int64_t v
    cdef double length, ux, uy, slope, weight
    with nogil:
        for end in range(2):
            for e in range(E):
                if not near[e]:
                    continue
                p = position[a[e] if end == 0 else b[e]]
                if p < start or p >= stop:
                    continue
                length = sqrt(dx[e] * dx[e] + dy[e] * dy[e])
                if not length > 0:
                    continue
                ux, uy, slope = dx[e] / length, dy[e] / length, delta[e] / length
                M[p, 0, 0] += ux * ux
                M[p, 0, 1] += ux * uy
                M[p, 1, 1] += uy * uy
                r[p, 0] += ux * slope
                r[p, 1] += uy * slope
                degree[p] += 1.0
        for p in range(start, stop):
            v = vertices[p]
            weight = normal_weight * degree[p]
            M[p, 1, 0] = M[p, 0, 1]
            M[p, 0, 0] += weight
            M[p, 1, 1] += weight
            r[p, 0] += weight * g[v, 0]
            r[p, 1] += weight * g[v, 1]


def limit_factors(const int64_t[::1] a, const int64_t[::1] b, const double[::1] delta,
                  const double[::1] pred_a, const double[::1] pred_b, const uint8_t[::1] bad,
                  double secant_factor, double slack, double[::1] factor):
    """factor (n,), from ones: at each end of every bad (E,) edge, the smaller of itself and
    the largest t in [0, 1] with t·pred in [min(0, c·Δ) − slack, max(0, c·Δ) + slack]
    (limiter.limit_gradients; c = secant_factor), as numpy's minimum.at took them."""
    cdef Py_ssize_t E = a.shape[0], e
    with nogil:
        for e in range(E):
            if bad[e]:
                factor[a[e]] = _np_minimum(factor[a[e]], _allowed(pred_a[e], delta[e], secant_factor, slack))
        for e in range(E):
            if bad[e]:
                factor[b[e]] = _np_minimum(factor[b[e]], _allowed(pred_b[e], delta[e], secant_factor, slack))


cdef inline double _allowed(double pred, double delta, double secant_factor, double slack) noexcept nogil:
    """The largest t in [0, 1] with t·pred within the secant band (limit_factors)."""
    cdef double bound = secant_factor * delta, t
    if pred > 0:
        t = (_np_maximum(bound, 0.0) + slack) / pred
    elif pred < 0:
        t = (_np_minimum(bound, 0.0) - slack) / pred
    else:
        t = 1.0
    return _np_clip(t, 0.0, 1.0)
