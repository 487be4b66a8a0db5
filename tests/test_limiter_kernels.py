"""The limiter's kernels (stages/_limiter.pyx, through stages/limiter.py) against plain
Python loops over the edges, triangles and vertices of small noisy meshes.

The loops use Python floats, which are IEEE doubles as the kernels' are: where a loop does
the same operations in the same order the results must agree to the bit, and the checks
say so; a least-squares solve is compared to a tolerance.
"""
import math

import numpy as np
import pytest

from c1mesh.engine.topology import edge_table
from c1mesh.engine.triangulation import delaunay
from c1mesh.stages import limiter
from c1mesh.stages.limiter import (CONSISTENCY, CREASE_LEVEL, HEIGHT_CLIP, NOISE_FACTOR, NORMAL_WEIGHT,
                                   SECANT_FACTOR, EdgeGeometry, edge_directions, inconsistent_edges,
                                   limit_gradients, reconcile_gradients, reconcile_heights,
                                   trapezoid_residuals)


@pytest.fixture(params=[0, 1])
def noisy(request):
    """(xy, z, gradients, triangles, table): a Delaunay mesh of 300 random points with
    noisy heights and gradients (many inconsistent edges), plus a near-coincident pair
    (a creasing edge) and a thin sliver (an edge whose unit normal the screen flags)."""
    rng = np.random.default_rng(40 + request.param)
    xy = rng.random((300, 2))
    xy = np.vstack([xy, xy[0] + [1e-3, 0.0], [[0.5, -0.02], [0.52, -0.02], [0.51, -0.0199]]])
    z = np.sin(3 * xy[:, 0]) * xy[:, 1] + 0.02 * rng.standard_normal(len(xy))
    g = np.column_stack([3 * np.cos(3 * xy[:, 0]) * xy[:, 1], np.sin(3 * xy[:, 0])])
    g += 0.3 * rng.standard_normal(g.shape)
    tri = delaunay(xy)
    return xy, z, g, tri, edge_table(tri, len(xy))


def _edge_loop(xy, z, g, edges):
    """Per edge a→b: (dx, dy, delta, size, pred_a, pred_b, residual) as Python floats."""
    rows = []
    for a, b in edges.tolist():
        dx, dy = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]
        pa = g[a, 0] * dx + g[a, 1] * dy
        pb = g[b, 0] * dx + g[b, 1] * dy
        delta = z[b] - z[a]
        rows.append((dx, dy, delta, abs(z[a]) + abs(z[b]), pa, pb, delta - 0.5 * (pa + pb)))
    return np.array(rows)


def test_edge_geometry_predictions_and_residuals_are_the_loops(noisy):
    xy, z, g, tri, table = noisy
    expected = _edge_loop(xy, z, g, table.edges)
    geometry = EdgeGeometry.of(xy, z, table.edges)
    got = np.column_stack([geometry.dx, geometry.dy, geometry.delta, geometry.size,
                           *geometry.predictions(g), trapezoid_residuals(xy, z, g, table.edges)])
    np.testing.assert_array_equal(got, expected)
    near = np.arange(len(table.edges)) % 3 == 0                  # some rows, into kept arrays
    kept = (np.full(near.size, 7.0), np.full(near.size, 8.0))
    pred_a, pred_b = geometry.predictions(2 * g, near, into=kept)
    np.testing.assert_array_equal(pred_a, np.where(near, 2 * expected[:, 4], 7.0))
    np.testing.assert_array_equal(pred_b, np.where(near, 2 * expected[:, 5], 8.0))


def test_edge_indices_outside_the_points_are_refused(noisy):
    xy, z, g, tri, table = noisy
    with pytest.raises(Exception, match="edge indices"):
        EdgeGeometry.of(xy[:-1], z[:-1], table.edges)


def test_inconsistent_edges_is_the_loop(noisy):
    xy, z, g, tri, table = noisy
    rows = _edge_loop(xy, z, g, table.edges)
    floor = float(np.median(np.abs(rows[:, 6])))
    expected = []
    for dx, dy, delta, size, pa, pb, e in rows.tolist():
        scale = max(abs(delta), 0.5 * max(abs(pa), abs(pb)))
        rounding = 64 * np.finfo(float).eps * (size + abs(pa) + abs(pb))
        expected.append(abs(e) > CONSISTENCY * scale + NOISE_FACTOR * floor + rounding)
    bad, parts = inconsistent_edges(xy, z, g, table.edges)
    assert 0.1 < np.mean(expected) < 0.9                          # both kinds are tested
    np.testing.assert_array_equal(bad, expected)
    assert parts["noise"] == NOISE_FACTOR * floor


def test_reconcile_heights_is_the_mean_of_each_vertexs_clipped_moves(noisy):
    xy, z, g, tri, table = noisy
    rows = _edge_loop(xy, z, g, table.edges)
    floor = float(np.median(np.abs(rows[:, 6])))
    length2 = rows[:, 0] ** 2 + rows[:, 1] ** 2
    reach2 = np.zeros(len(rows))                                  # longest edge of the edge's triangles
    for t in range(len(tri)):
        longest = max(length2[e] for e in table.tri_edge[t])
        for e in table.tri_edge[t]:
            reach2[e] = max(reach2[e], longest)
    a_moves, b_moves = {}, {}
    for (a, b), row, l2, r2 in zip(table.edges.tolist(), rows.tolist(), length2, reach2):
        e = row[6]
        if 6.0 * abs(e) * math.sqrt(r2) > CREASE_LEVEL * l2:
            m = min(max(0.5 * e, -HEIGHT_CLIP * floor), HEIGHT_CLIP * floor)
            a_moves.setdefault(a, []).append(m)
            b_moves.setdefault(b, []).append(-m)
    moved = set(a_moves) | set(b_moves)
    expected = z.copy()
    for v in moved:
        ms = a_moves.get(v, []) + b_moves.get(v, [])     # numpy's bincount order, kept by the kernel
        total = 0.0
        for m in ms:
            total += m
        expected[v] = z[v] + total / len(ms)
    out, changed = reconcile_heights(xy, z, g, tri, table)
    assert 0 < len(moved) < len(z)
    np.testing.assert_array_equal(changed, np.isin(np.arange(len(z)), list(moved)))
    np.testing.assert_array_equal(out, expected)


def test_reconcile_gradients_solves_each_touched_vertexs_least_squares(noisy):
    xy, z, g, tri, table = noisy
    rows = _edge_loop(xy, z, g, table.edges)
    bad, _ = inconsistent_edges(xy, z, g, table.edges)
    touched = set(table.edges[bad].ravel().tolist())
    expected = g.copy()
    for v in touched:
        M = np.zeros((2, 2))
        r = np.zeros(2)
        degree = 0
        for (a, b), row in zip(table.edges.tolist(), rows.tolist()):
            if v not in (a, b):
                continue
            length = math.sqrt(row[0] ** 2 + row[1] ** 2)
            u = np.array([row[0], row[1]]) / length
            M += np.outer(u, u)
            r += u * row[2] / length
            degree += 1
        weight = NORMAL_WEIGHT * degree
        expected[v] = np.linalg.solve(M + weight * np.eye(2), r + weight * g[v])
    out, changed = reconcile_gradients(xy, z, g, table.edges)
    np.testing.assert_array_equal(changed, np.isin(np.arange(len(z)), list(touched)))
    assert 0 < changed.sum() < len(z)
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(out[~changed], g[~changed])


def test_limit_gradients_scales_by_the_smallest_allowed_fraction(noisy):
    xy, z, g, tri, table = noisy
    rows = _edge_loop(xy, z, g, table.edges)
    bad, parts = inconsistent_edges(xy, z, g, table.edges)
    slack = parts["noise"]
    factor = np.ones(len(z))
    for (a, b), row, is_bad in zip(table.edges.tolist(), rows.tolist(), bad):
        if not is_bad:
            continue
        delta = row[2]
        for vertex, pred in ((a, row[4]), (b, row[5])):
            high = max(SECANT_FACTOR * delta, 0.0) + slack
            low = min(SECANT_FACTOR * delta, 0.0) - slack
            t = high / pred if pred > 0 else low / pred if pred < 0 else 1.0
            factor[vertex] = min(factor[vertex], min(max(t, 0.0), 1.0))
    limited, changed = limit_gradients(xy, z, g, table.edges)
    assert 0 < changed.sum() < len(z)
    np.testing.assert_array_equal(changed, factor < 1)
    np.testing.assert_array_equal(limited, g * factor[:, None])


def test_limit_gradients_sign_zeros_as_numpys_minimum_at():
    """With a zero noise floor, Δ = 0 and a negative prediction give t = −0.0 (low/pred with
    low = 0.0): numpy's minimum.at keeps the later of equal values, and so must the kernel,
    since the sign of a zero gradient reaches the output's bytes. Vertex 1 meets t = 0.0
    as an a-end (edge 1→2), then t = −0.0 as a b-end (edge 0→1): −0.0 wins."""
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    z = np.zeros(3)
    g = np.array([[-1.0, 0.0], [-1.0, 0.0], [0.0, 0.0]])
    edges = np.array([[0, 1], [0, 2], [1, 2]])
    limited, changed = limit_gradients(xy, z, g, edges, noise_floor=0.0)
    bad, parts = inconsistent_edges(xy, z, g, edges, noise_floor=0.0)
    assert bad.tolist() == [True, False, True] and parts["noise"] == 0.0
    factor = np.ones(3)
    with np.errstate(all="ignore"):
        for vertex, pred in ((edges[bad, 0], parts["pred_a"][bad]), (edges[bad, 1], parts["pred_b"][bad])):
            bound = SECANT_FACTOR * parts["delta"][bad]
            t = np.where(pred > 0, np.maximum(bound, 0.0) / pred, np.where(pred < 0, np.minimum(bound, 0.0) / pred, 1.0))
            np.minimum.at(factor, vertex, np.clip(t, 0.0, 1.0))
    assert changed.tolist() == [True, True, False]
    np.testing.assert_array_equal(limited, g * factor[:, None])
    np.testing.assert_array_equal(np.signbit(limited), np.signbit(g * factor[:, None]))
    assert np.signbit(factor).tolist() == [True, True, False]
    assert np.signbit(limited).tolist() == [[False, True], [False, True], [False, False]]


def test_edge_directions_screen_and_opposite_vertices_are_the_loops(noisy):
    xy, z, g, tri, table = noisy
    worst = np.full(len(table.edges), -1.0)
    opposite = {}
    for t in range(len(tri)):
        for k in range(3):
            c, i, j = tri[t, k], tri[t, (k + 1) % 3], tri[t, (k + 2) % 3]
            ex, ey = xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1]
            s = ((xy[c, 0] - xy[i, 0]) * ex + (xy[c, 1] - xy[i, 1]) * ey) / (ex * ex + ey * ey)
            e = table.tri_edge[t, k]
            worst[e] = max(worst[e], abs(s), abs(1 - s))
            opposite.setdefault(int(e), []).append(int(c))
    tri64 = tri.astype(np.int64)
    np.testing.assert_array_equal(limiter._normal_ratio_screen(xy, tri64, table), worst)
    idx = np.flatnonzero((worst > 1.5) | (table.count == 1))        # and the boundary
    first, second = limiter._opposite_vertices(tri64, table, idx)
    assert idx.size > 0 and (second == -1).any() and (second >= 0).any()
    for e, f, s in zip(idx, first, second):
        assert f == tri[table.owner[e], table.owner_slot[e]]
        assert sorted([f] + ([s] if s >= 0 else [])) == sorted(opposite[int(e)])
    directions, changed = edge_directions(xy, tri, table)
    d = xy[table.edges[:, 1]] - xy[table.edges[:, 0]]
    normal = np.column_stack([-d[:, 1], d[:, 0]]) / np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])[:, None]
    np.testing.assert_array_equal(directions[~changed], normal[~changed])
    assert changed.any() and not (changed & (worst <= limiter.RATIO_LIMIT * (1 - 1e-9))).any()


def _worst(u, l, e, pa, pb):
    """The loop's worst max(|s|, |1 − s|) of direction u over the opposite vertices pa, pb
    (pb None on the boundary), inf when u is not finite or nearly parallel to the edge."""
    cross = e[0] * u[1] - e[1] * u[0]
    worst = 0.0
    for pn in (pa, pb):
        if pn is None:
            continue
        with np.errstate(all="ignore"):
            s = np.float64((pn[0] - l[0]) * u[1] - (pn[1] - l[1]) * u[0]) / cross
        ratio = max(abs(s), abs(1 - s))
        worst = max(worst, ratio if math.isfinite(ratio) else math.inf)
    if not all(map(math.isfinite, u)) or abs(cross) <= 1e-9 * math.sqrt(e[0] ** 2 + e[1] ** 2) * math.sqrt(u[0] ** 2 + u[1] ** 2):
        return math.inf
    return worst


@pytest.mark.parametrize("ratio_limit", [limiter.RATIO_LIMIT, 0.6])    # 0.6: boundary edges too
def test_edge_directions_pick_the_candidate_of_smallest_worst_ratio_by_a_loop(noisy, ratio_limit):
    """Every edge the screen flags, against a loop over its four candidates (the unit
    normal, the line between the opposite vertices, and from each to the edge's midpoint)."""
    xy, z, g, tri, table = noisy
    screen = limiter._normal_ratio_screen(xy, tri.astype(np.int64), table)
    flagged = np.flatnonzero(screen > ratio_limit * (1 - 1e-9))
    first, second = limiter._opposite_vertices(tri.astype(np.int64), table, flagged)
    directions, changed = edge_directions(xy, tri, table, ratio_limit)
    turned = 0
    for e, f, s in zip(flagged, first, second):
        l, m = xy[table.edges[e, 0]].tolist(), xy[table.edges[e, 1]].tolist()
        d = (m[0] - l[0], m[1] - l[1])
        length = math.sqrt(d[0] * d[0] + d[1] * d[1])
        pa, pb = xy[f].tolist(), (xy[s].tolist() if s >= 0 else None)
        mid = (0.5 * (l[0] + m[0]), 0.5 * (l[1] + m[1]))
        nan = (math.nan, math.nan)
        candidates = [(-d[1] / length, d[0] / length),
                      (pb[0] - pa[0], pb[1] - pa[1]) if pb else nan,
                      (mid[0] - pa[0], mid[1] - pa[1]),
                      (mid[0] - pb[0], mid[1] - pb[1]) if pb else nan]
        costs = [_worst(u, l, d, pa, pb) for u in candidates]
        best = costs.index(min(costs))
        if costs[0] > ratio_limit and best > 0:
            u = candidates[best]
            norm = math.sqrt(u[0] * u[0] + u[1] * u[1])
            assert changed[e] and directions[e].tolist() == [u[0] / norm, u[1] / norm]
            turned += 1
        else:
            assert not changed[e] and directions[e].tolist() == list(candidates[0])
    assert turned > 0 and (ratio_limit > 1.5 or (second < 0).any())
