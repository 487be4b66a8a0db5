"""Overshoot control for noisy scans that keeps the spline C1 (docs/overshoot.md).

Two remedies, plain functions over arrays, applied by the fit pipeline between the height
field and the RSDInterpolator:

* `reconcile_gradients` blends a vertex gradient that disagrees with the heights of its
  neighbours with their secant slopes (least squares), one gradient per vertex.
* `limit_gradients` then scales a vertex gradient down where it disagrees with the heights of
  its neighbours (a Fritsch–Carlson-like limiter on the secants of the vertex's edges).
  A vertex has one gradient, shared by all its triangles, so the spline stays C1.
* `edge_directions` picks, for every edge, the direction u the RSD spline uses across it
  (Thm 3.4: any vector not parallel to the edge, one per edge, shared by both triangles).
  The unit normal makes the ratios r_ln = G_l·u_n / G_n·u_n blow up on obtuse thin
  triangles; a direction through the opposite vertices keeps them within [-1, 0].

Both change nothing on well-behaved data: the limiter only acts on edges whose data fail
the trapezoid test (below), which exact data of any quadratic passes and smooth data
passes up to O(h³); the directions change only edges whose unit-normal ratio exceeds
`RATIO_LIMIT`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.topology import EdgeTable, edge_table

OVERSHOOT_MODES = ("limit", "off")

SECANT_FACTOR = 2.0
"""A gradient may predict at most this multiple of an inconsistent edge's height change
(Fritsch–Carlson allow 3 for cubic Hermite; the RSD edge curve uses Φ(t) = t³(10 − 15t +
6t²) for the derivative term too, whose bump is about twice the cubic one)."""
CONSISTENCY = 0.25
"""An edge is inconsistent when its trapezoid residual exceeds this fraction of its scale."""
NOISE_FACTOR = 1.0
"""Residuals within this multiple of the median |trapezoid residual| (the noise floor of
the data; O(h³) for exact smooth data) are tolerated, and so is a prediction that far
outside the secant band."""
NORMAL_WEIGHT = 1.0
"""Weight of a vertex's normal against its edges' secant slopes in `reconcile_gradients`."""
RATIO_LIMIT = 2.0
"""Edges whose unit-normal RSD ratio max(|s|, |1 − s|) exceeds this get another direction."""


@dataclass
class LimiterReport:
    """What the remedies changed: vertices whose gradient was scaled down, and edges whose
    direction is not the unit normal."""

    gradients_limited: int = 0
    directions_changed: int = 0

    def as_dict(self) -> dict:
        return {"gradients_limited": self.gradients_limited,
                "directions_changed": self.directions_changed}


def control_overshoot(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                      triangles: np.ndarray, mode: str = "limit"
                      ) -> tuple[np.ndarray, np.ndarray | None, LimiterReport]:
    """Gradients and edge directions for an RSDInterpolator on a (noisy) height field.

    points (n, 2), values (n,), gradients (n, 2), triangles (T, 3). mode "limit" applies
    `reconcile_gradients`, then `limit_gradients`, and `edge_directions`; "off" returns the gradients unchanged and
    None (the interpolator's unit normals). Returns (gradients, directions in the order
    of c1mesh.topology.edge_table(triangles, n).edges or None, report).
    """
    if mode == "off":
        return gradients, None, LimiterReport()
    table = edge_table(triangles, points.shape[0])
    reconciled, moved = reconcile_gradients(points, values, gradients, table.edges)
    limited, changed = limit_gradients(points, values, reconciled, table.edges)
    directions, turned = edge_directions(points, triangles, table)
    return limited, directions, LimiterReport(int((changed | moved).sum()), int(turned.sum()))


def inconsistent_edges(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                       edges: np.ndarray, consistency: float = CONSISTENCY,
                       noise_factor: float = NOISE_FACTOR) -> tuple[np.ndarray, dict]:
    """Edges (E,) bool whose end gradients say something their heights do not.

    For an edge k→j with d = p_j − p_k, Δ = f_j − f_k, δ_k = A_k·d, δ_j = A_j·d, the
    trapezoid residual e = Δ − (δ_k + δ_j)/2 vanishes for every quadratic and is O(|d|³)
    for smooth data. An edge is inconsistent when |e| > consistency · max(|Δ|, |δ_k|/2,
    |δ_j|/2) + noise_factor · median |e| (the noise floor of the data set) + rounding.
    Also returns the per-edge quantities {"delta", "pred_a", "pred_b", "noise"}.
    """
    p = np.asarray(points, dtype=float)
    f = np.asarray(values, dtype=float)
    A = np.asarray(gradients, dtype=float)
    a, b = edges[:, 0], edges[:, 1]
    d = p[b] - p[a]
    delta = f[b] - f[a]
    pred_a = np.einsum("ij,ij->i", A[a], d)
    pred_b = np.einsum("ij,ij->i", A[b], d)
    residual = delta - 0.5 * (pred_a + pred_b)
    scale = np.maximum(np.abs(delta), 0.5 * np.maximum(np.abs(pred_a), np.abs(pred_b)))
    noise = noise_factor * float(np.median(np.abs(residual))) if residual.size else 0.0
    rounding = 64 * np.finfo(float).eps * (np.abs(f[a]) + np.abs(f[b]) + np.abs(pred_a) + np.abs(pred_b))
    bad = np.abs(residual) > consistency * scale + noise + rounding
    return bad, {"delta": delta, "pred_a": pred_a, "pred_b": pred_b, "noise": noise}


def reconcile_gradients(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                        edges: np.ndarray, normal_weight: float = NORMAL_WEIGHT
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Gradients (n, 2) blended with the 1-ring heights where they disagree with them.

    At every vertex k touching an inconsistent edge (`inconsistent_edges`), the gradient
    becomes the least-squares solution of the secant slopes of all its edges and the
    normal's own gradient A_k:

        min_G  Σ_e (G·û_e − Δ_e/|d_e|)² + normal_weight · deg_k · |G − A_k|²,

    û_e the unit edge direction, deg_k the vertex's edge count: the heights and the normal
    weigh the same at normal_weight = 1. Other vertices keep A_k, so exact smooth data
    (no inconsistent edge) are unchanged. One gradient per vertex: the spline stays C1.
    Returns (gradients, changed (n,) bool).
    """
    p = np.asarray(points, dtype=float)
    f = np.asarray(values, dtype=float)
    A = np.asarray(gradients, dtype=float)
    n = p.shape[0]
    bad, _ = inconsistent_edges(p, f, A, edges)
    touched = np.zeros(n, dtype=bool)
    touched[edges[bad].ravel()] = True
    near = touched[edges[:, 0]] | touched[edges[:, 1]]      # only these edges reach a touched vertex
    a, b = edges[near, 0], edges[near, 1]
    d = p[b] - p[a]
    length = np.linalg.norm(d, axis=1)
    keep = length > 0
    a, b, d, length = a[keep], b[keep], d[keep], length[keep]
    u = d / length[:, None]
    slope = (f[b] - f[a]) / length
    terms = (u[:, 0] * u[:, 0], u[:, 0] * u[:, 1], u[:, 1] * u[:, 1],
             u[:, 0] * slope, u[:, 1] * slope, np.ones(a.size))
    both = np.concatenate([a, b])
    xx, xy, yy, rx, ry, deg = (np.bincount(both, np.concatenate([t, t]), minlength=n)[touched]
                               for t in terms)
    weight = normal_weight * deg
    M_t = np.stack([np.stack([xx + weight, xy], axis=1), np.stack([xy, yy + weight], axis=1)], axis=1)
    r_t = np.stack([rx, ry], axis=1) + weight[:, None] * A[touched]
    out = A.copy()
    out[touched] = np.linalg.solve(M_t, r_t[:, :, None])[:, :, 0]
    return out, touched


def limit_gradients(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                    edges: np.ndarray, secant_factor: float = SECANT_FACTOR,
                    consistency: float = CONSISTENCY,
                    noise_factor: float = NOISE_FACTOR) -> tuple[np.ndarray, np.ndarray]:
    """Gradients (n, 2) scaled down where they disagree with the neighbouring heights.

    points (n, 2), values (n,), gradients (n, 2) in the height-field frame; edges (E, 2)
    vertex pairs of the triangulation. Returns (new gradients, changed (n,) bool).

    For an edge k→j with d = p_j − p_k, the height change Δ = f_j − f_k and the changes
    the end gradients predict, δ_k = A_k·d and δ_j = A_j·d, the trapezoid residual
    e = Δ − (δ_k + δ_j)/2 vanishes for every quadratic and is O(|d|³) for smooth data.
    An edge is inconsistent when |e| > consistency · max(|Δ|, |δ_k|/2, |δ_j|/2) +
    noise_factor · median |e| (the noise floor of the whole data set) + rounding: the
    gradients then say something the heights do not. On inconsistent edges each end's
    prediction must lie between 0 and secant_factor · Δ (so it has the secant's sign and
    at most that multiple of its size, as in Fritsch–Carlson); a vertex gradient is
    multiplied by the largest t in [0, 1] that meets this on all its inconsistent edges.
    Scaling keeps the direction, and 0 always qualifies (a flat vertex cannot overshoot
    along an edge by itself).
    """
    A = np.asarray(gradients, dtype=float)
    bad, parts = inconsistent_edges(points, values, A, edges, consistency, noise_factor)
    a, b = edges[:, 0], edges[:, 1]
    delta, pred_a, pred_b, noise = parts["delta"], parts["pred_a"], parts["pred_b"], parts["noise"]
    factor = np.ones(A.shape[0])
    for vertex, pred in ((a, pred_a), (b, pred_b)):
        t = _allowed_fraction(pred[bad], delta[bad], secant_factor, noise)
        np.minimum.at(factor, vertex[bad], t)
    changed = factor < 1.0
    limited = A.copy()
    limited[changed] *= factor[changed, None]
    return limited, changed


def _allowed_fraction(pred: np.ndarray, delta: np.ndarray, secant_factor: float,
                      slack: float) -> np.ndarray:
    """Largest t in [0, 1] with t·pred in [min(0, c·delta) − slack, max(0, c·delta) + slack]."""
    bound = secant_factor * delta
    high = np.maximum(bound, 0.0) + slack
    low = np.minimum(bound, 0.0) - slack
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(pred > 0, high / pred, np.where(pred < 0, low / pred, 1.0))
    return np.clip(t, 0.0, 1.0)


def edge_directions(points: np.ndarray, triangles: np.ndarray, table: EdgeTable,
                    ratio_limit: float = RATIO_LIMIT) -> tuple[np.ndarray, np.ndarray]:
    """One direction per edge of ``table`` (E, 2) that keeps the RSD ratios small.

    In a triangle with the edge [p_l, p_m] opposite p_n, a direction u through p_n meets
    the edge's line at q = p_l + s (p_m − p_l), and then G_l·u / G_n·u = −(1 − s) and
    G_m·u / G_n·u = −s: the ratios are bounded by 1 when q lies on the edge, and grow
    without bound for the unit normal on obtuse thin triangles (its foot q falls far
    outside the edge). Candidates: the unit normal, the line joining the two opposite
    vertices (interior edges; q on the edge when the quadrilateral is convex), and the
    lines from each opposite vertex to the edge's midpoint. The unit normal is kept
    unless its worst ratio over the edge's triangles exceeds ``ratio_limit``; otherwise
    the candidate with the smallest worst ratio wins. Returns (directions (E, 2),
    changed (E,) bool). Every direction is used by both triangles of its edge, so the
    spline stays C1 (Thm 3.4).
    """
    p = np.asarray(points, dtype=float)
    l, m = p[table.edges[:, 0]], p[table.edges[:, 1]]
    edge = m - l
    first, second = _opposite_vertices(triangles, table)
    pa = p[first]
    pb = np.where((second >= 0)[:, None], p[np.maximum(second, 0)], np.nan)
    normal = np.stack([-edge[:, 1], edge[:, 0]], axis=1) / np.linalg.norm(edge, axis=1)[:, None]
    # The unit normal's foot is the projection of the opposite vertex onto the edge's line:
    # s = (p_n − l)·e / |e|², so its worst ratio needs no cross products. Only the edges
    # where it exceeds the limit (a few percent on real scans) weigh the other candidates.
    change = _normal_ratio(l, edge, pa, pb) > ratio_limit
    out = normal
    if change.any():
        idx = np.flatnonzero(change)
        l_c, edge_c, pa_c, pb_c = l[idx], edge[idx], pa[idx], pb[idx]
        mid = 0.5 * (l_c + m[idx])
        candidates = [normal[idx], pb_c - pa_c, mid - pa_c, mid - pb_c]
        costs = np.stack([_worst_ratio(u, l_c, edge_c, pa_c, pb_c) for u in candidates])
        best = np.argmin(np.where(np.isfinite(costs), costs, np.inf), axis=0)
        turn = (costs[0] > ratio_limit) & (best > 0)
        change[idx[~turn]] = False
        for c in range(1, len(candidates)):
            pick = turn & (best == c)
            out[idx[pick]] = candidates[c][pick] / np.linalg.norm(candidates[c][pick], axis=1)[:, None]
    return out, change


def _normal_ratio(l: np.ndarray, edge: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Worst max(|s|, |1 − s|) of the unit normal over each edge's one or two triangles
    (pb rows of nan: a boundary edge, one triangle). A quick screen: `_worst_ratio`
    decides on the edges it flags."""
    length2 = np.einsum("ij,ij->i", edge, edge)
    worst = np.zeros(edge.shape[0])
    for pn in (pa, pb):
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.einsum("ij,ij->i", pn - l, edge) / length2
        ratio = np.maximum(np.abs(s), np.abs(1.0 - s))
        np.fmax(worst, ratio, out=worst)                  # nan (boundary) leaves worst as is
    return worst


def _opposite_vertices(triangles: np.ndarray, table: EdgeTable) -> tuple[np.ndarray, np.ndarray]:
    """For every edge the vertex opposite it in its owner triangle, and in the other
    triangle (-1 on the boundary)."""
    E = table.edges.shape[0]
    first = triangles[table.owner, table.owner_slot]
    second = np.full(E, -1, dtype=np.int64)
    opposite = triangles.ravel()
    slots = table.tri_edge.ravel()
    other = opposite != first[slots]
    second[slots[other]] = opposite[other]
    return first, second


def _worst_ratio(u: np.ndarray, l: np.ndarray, edge: np.ndarray, pa: np.ndarray,
                 pb: np.ndarray) -> np.ndarray:
    """max over the edge's triangles of max(|s|, |1 − s|) for direction u (nan rows: inf)."""
    cross_eu = edge[:, 0] * u[:, 1] - edge[:, 1] * u[:, 0]
    worst = np.zeros(u.shape[0])
    for pn in (pa, pb):
        rel = pn - l
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (rel[:, 0] * u[:, 1] - rel[:, 1] * u[:, 0]) / cross_eu
        ratio = np.maximum(np.abs(s), np.abs(1.0 - s))
        present = np.isfinite(pn).all(axis=1)
        ratio = np.where(present, ratio, 0.0)
        worst = np.maximum(worst, np.where(np.isfinite(ratio), ratio, np.inf))
    bad = ~np.isfinite(u).all(axis=1) | (np.abs(cross_eu) <= 1e-9 * np.linalg.norm(edge, axis=1)
                                          * np.linalg.norm(np.nan_to_num(u), axis=1))
    return np.where(bad, np.inf, worst)
