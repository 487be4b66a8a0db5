"""Vertex gradients fitted to the heights (c1mesh.stages.height_gradients) against analytic ones.

Ground truth is the analytic gradient of the height function; the PCA route
(c1mesh.stages.normals.estimate_normals, then -n_xy / n_z) is the peer on the same points.
"""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.core.cloud import PointCloud
from c1mesh.core.errors import InputError
from c1mesh.stages.height_gradients import height_gradients, height_neighbours, use_height_gradients
from c1mesh.stages.normals import estimate_normals
from c1mesh.pipeline.driver import FitOptions, build_surface


def _quadratic(xy):
    x, y = xy[:, 0], xy[:, 1]
    return 0.7 * x * x - 1.3 * x * y + 0.4 * y * y + 2 * x - y + 5, np.c_[1.4 * x - 1.3 * y + 2, -1.3 * x + 0.8 * y - 1]


def _smooth(xy):
    x, y = xy[:, 0], xy[:, 1]
    return np.exp(x) * np.sin(2 * y), np.c_[np.exp(x) * np.sin(2 * y), 2 * np.exp(x) * np.cos(2 * y)]


def test_quadratic_heights_give_exact_gradients():
    xy = np.random.default_rng(0).random((2000, 2)) * 10
    z, truth = _quadratic(xy)
    np.testing.assert_allclose(height_gradients(xy, z), truth, atol=1e-6)


def test_degree_one_is_exact_for_planes_and_not_for_quadratics():
    xy = np.random.default_rng(1).random((1000, 2))
    plane = 3 * xy[:, 0] - 2 * xy[:, 1] + 1
    np.testing.assert_allclose(height_gradients(xy, plane, degree=1), np.tile([3.0, -2.0], (1000, 1)),
                               atol=1e-7)
    z, truth = _quadratic(xy)
    assert np.abs(height_gradients(xy, z, degree=1) - truth).max() > 1e-3


def test_smooth_heights_converge_at_second_order():
    """Interior points (away from the one-sided rim): error / h² stays bounded as h halves."""
    errors = []
    for n in (2000, 8000, 32000):
        xy = np.random.default_rng(2).random((n, 2))
        z, truth = _smooth(xy)
        inner = np.all((xy > 0.2) & (xy < 0.8), axis=1)
        errors.append(np.sqrt(np.mean(np.sum((height_gradients(xy, z) - truth)[inner] ** 2, axis=1))))
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:])) * 2     # n x4 -> h / 2
    assert np.all(rates > 1.7), (errors, rates)


def test_heights_beat_pca_normals_on_curved_ground():
    """On a curved surface the PCA plane's slope is O(h) off; the quadratic fit is exact."""
    xy = np.random.default_rng(3).random((5000, 2)) * 20
    z, truth = _quadratic(xy / 10)
    truth = truth / 10
    inner = np.all((xy > 2) & (xy < 18), axis=1)
    normals = estimate_normals(np.c_[xy, z], k=16)
    pca = -normals[:, :2] / normals[:, 2:]
    ours = height_gradients(xy, z)
    pca_error = np.abs(pca - truth)[inner].max()
    assert pca_error > 1e-3
    assert np.abs(ours - truth)[inner].max() < 1e-3 * pca_error


def test_collinear_neighbourhoods_stay_finite():
    """Points on a few scan lines: every neighbourhood of a point lies on one line."""
    x = np.linspace(0, 1, 400)
    xy = np.concatenate([np.c_[x, np.full_like(x, y)] for y in (0.0, 10.0, 20.0)])
    z = 2 * xy[:, 0]
    g = height_gradients(xy, z)
    assert np.isfinite(g).all()
    np.testing.assert_allclose(g[:, 0], 2.0, atol=1e-6)


def _grid_with_ties(seed):
    """A 9 x 9 unit grid around the origin (every ring of neighbours equally far), three
    extra points on grid positions with other heights, random heights: (xy, z)."""
    g = np.arange(-4.0, 5.0)
    xy = np.c_[np.repeat(g, 9), np.tile(g, 9)]
    xy = np.concatenate([xy, [[2.0, 1.0], [-3.0, 0.0], [1.0, -1.0]]])
    return xy, np.random.default_rng(seed).normal(size=len(xy))


def _search(xy, z, centres, k):
    """nearest_neighbours of the points centres (indices into xy) as height_gradients runs
    it (points in the grid's order), as indices into xy."""
    from c1mesh.stages.height_gradients import nearest_neighbours, plane_grid

    grid, order = plane_grid(xy)
    rank = np.empty(len(xy), dtype=np.int64)
    rank[order] = np.arange(len(xy))
    index, _ = nearest_neighbours(grid, np.ascontiguousarray(xy[order]), np.ascontiguousarray(z[order]),
                                  rank[np.asarray(centres)], k)
    return order[index]


def test_a_distance_tie_is_broken_by_the_offsets():
    """From the origin the 4 nearest points are 1 away, the next 4 (plus a duplicate of
    (1, -1)) sqrt 2 away: with k = 6, the two nearest of those by the stated rule (dx,
    then dy, then the height) are (-1, -1) and (-1, 1); then k = 10 takes all five at
    sqrt 2, the duplicate after (1, -1) by height, and (-2, 0) as the first of the
    ring at 2."""
    xy, z = _grid_with_ties(0)
    centre = np.flatnonzero((xy == 0).all(axis=1))
    got = xy[_search(xy, z, centre, 6)[0]]
    np.testing.assert_array_equal(got, [[-1, 0], [0, -1], [0, 1], [1, 0], [-1, -1], [-1, 1]])
    index = _search(xy, z, centre, 10)[0]
    want = [[-1, 0], [0, -1], [0, 1], [1, 0], [-1, -1], [-1, 1], [1, -1], [1, -1], [1, 1], [-2, 0]]
    np.testing.assert_array_equal(xy[index], want)
    duplicate = index[6:8]
    assert z[duplicate[0]] < z[duplicate[1]]


@pytest.mark.parametrize("k", [6, 10, 24])
def test_gradients_do_not_depend_on_point_numbering_or_far_points(k):
    """Ties everywhere (a unit grid): every gradient is the same to the bit when the
    points are renumbered, and the origin's is the same when all points beyond its
    neighbourhood (more than 3 away) are dropped. This is what lets a tile, which holds
    its points in another order and misses the far ones, give the survey's gradients."""
    xy, z = _grid_with_ties(1)
    reference = height_gradients(xy, z, k=k)
    for seed in range(4):
        shuffle = np.random.default_rng(seed).permutation(len(xy))
        np.testing.assert_array_equal(height_gradients(xy[shuffle], z[shuffle], k=k), reference[shuffle])
    origin = np.flatnonzero((xy == 0).all(axis=1))[0]
    near = np.flatnonzero(np.hypot(*xy.T) <= 3)            # k = 24: the 24th and 25th are at sqrt 8
    for seed in range(4):
        keep = np.random.default_rng(seed).permutation(near)
        got = height_gradients(xy[keep], z[keep], k=k)[np.flatnonzero(keep == origin)[0]]
        np.testing.assert_array_equal(got, reference[origin])


def test_a_stack_larger_than_the_first_query_is_still_order_free():
    """40 points at one plane position (a vertical stack; more than three grid cells hold
    on average, all in one cell): each stacked point's
    neighbours are the other 39, by height, and its gradient does not depend on the
    numbering; the grid points' gradients neither."""
    from c1mesh.stages.height_gradients import PER_CELL

    xy, z = _grid_with_ties(2)
    stack = 40
    assert stack > 3 * PER_CELL
    xy = np.concatenate([xy, np.tile([[0.5, 0.5]], (stack, 1))])
    z = np.concatenate([z, np.random.default_rng(3).normal(size=stack)])
    first = len(xy) - stack
    index = _search(xy, z, np.array([first]), 6)
    others = np.arange(first + 1, len(xy))
    np.testing.assert_array_equal(index[0], others[np.argsort(z[others])][:6])
    reference = height_gradients(xy, z, k=6)
    assert np.isfinite(reference).all()
    for seed in range(3):
        shuffle = np.random.default_rng(seed).permutation(len(xy))
        np.testing.assert_array_equal(height_gradients(xy[shuffle], z[shuffle], k=6), reference[shuffle])


def test_bad_input_is_refused():
    with pytest.raises(InputError):
        height_gradients(np.zeros((5, 3)), np.zeros(5))
    with pytest.raises(InputError):
        height_gradients(np.zeros((2, 2)), np.zeros(2))
    with pytest.raises(InputError):
        height_gradients(np.random.default_rng(0).random((10, 2)), np.zeros(10), degree=3)
    with pytest.raises(InputError):
        use_height_gradients("smooth", "estimated")


def test_the_pipeline_fits_gradients_to_heights_only_where_normals_are_estimated():
    """auto: heights for estimated normals, the file's normals otherwise; the options
    "normals" and "heights" force either."""
    xy = np.random.default_rng(4).random((3000, 2)) * 10
    z, truth = _quadratic(xy / 5)
    truth = truth / 5
    file_normals = np.c_[-truth, np.ones(len(z))] * 0.5 + np.c_[0.3, 0.0, 0.0]   # wrong on purpose
    cloud = PointCloud(points=np.c_[xy, z], normals=file_normals)
    bare = PointCloud(points=np.c_[xy, z])

    def gradients(c, **options):
        model = build_surface(c, FitOptions(smooth="off", axis="z", overshoot="off", **options))
        return model.hf.gradients, truth[model.hf.source_index]

    ours, want = gradients(bare)                         # estimated normals: heights
    np.testing.assert_allclose(ours, want, atol=1e-6)
    ours, want = gradients(bare, gradients="normals")    # the PCA normals: O(h) off
    assert np.abs(ours - want).max() > 1e-3
    ours, want = gradients(cloud)                        # file normals are kept
    assert np.abs(ours - want).max() > 0.1
    ours, want = gradients(cloud, gradients="heights")
    np.testing.assert_allclose(ours, want, atol=1e-6)
    assert use_height_gradients("auto", "estimated") and not use_height_gradients("auto", "file")
    assert height_neighbours(16) == 24


def test_the_cli_option_chooses_the_gradients_and_the_report_says_which(tmp_path):
    import json

    from click.testing import CliRunner

    from c1mesh.cli import main

    xy = np.random.default_rng(5).random((500, 2)) * 10
    z, _ = _quadratic(xy / 5)
    source = tmp_path / "bare.xyz"
    np.savetxt(source, np.c_[xy, z])
    for option, want in (("auto", "heights"), ("normals", "normals")):
        report = tmp_path / f"{option}.json"
        result = CliRunner().invoke(main, ["fit", "--smooth", "off", str(source), "-o", str(tmp_path / f"{option}.ply"),
                                           "--axis", "z", "--level", "1", "--gradients", option,
                                           "--report", str(report), "-q"])
        assert result.exit_code == 0, result.output
        assert json.loads(report.read_text())["gradients"] == want


def test_exact_terrain_without_normals_trips_the_limiter_no_more_than_exact_gradients():
    """Exact heights of a smooth terrain: gradients fitted to the heights trip the
    overshoot limiter (whose trapezoid test flags what heights and gradients disagree on)
    at no more vertices than the analytic gradients do, give or take 1 in 1000; the PCA
    normals' gradients, O(h) off, trip it at far more (so the test can fail)."""
    xy = np.random.default_rng(6).random((20000, 2)) * 100
    x, y = xy[:, 0], xy[:, 1]
    points = np.c_[xy, 3 * np.sin(x / 10) * np.cos(y / 15) + 0.02 * x]
    exact = np.c_[-(0.3 * np.cos(x / 10) * np.cos(y / 15) + 0.02), 0.2 * np.sin(x / 10) * np.sin(y / 15),
                  np.ones(len(x))]
    limited = {}
    for name, normals, gradients in (("exact", exact, "auto"), ("heights", None, "auto"),
                                     ("pca", None, "normals")):
        model = build_surface(PointCloud(points=points, normals=normals),
                              FitOptions(smooth="off", axis="z", gradients=gradients))
        limited[name] = model.overshoot.gradients_limited
    assert limited["heights"] <= limited["exact"] + len(points) // 1000, limited
    assert limited["pca"] > 20 * (limited["heights"] + 1), limited


def test_fewer_than_three_distinct_plane_positions_are_refused():
    """Many points at two (x, y) positions span no plane: no slope can be fitted there."""
    xy = np.repeat([[0.0, 0.0], [1.0, 0.5]], 5, axis=0)
    with pytest.raises(InputError, match="3 distinct .* positions, got 10 points at 2"):
        height_gradients(xy, np.arange(10.0))
    with pytest.raises(InputError, match="got 4 points at 1"):
        height_gradients(np.ones((4, 2)), np.arange(4.0))
    height_gradients(np.r_[xy, [[3.0, -1.0]]], np.arange(11.0))     # a third position suffices


def _hill_m_over_km(xy):
    """Heights in metres over x, y in kilometres, and their gradients in metres per km."""
    x, y = xy[:, 0], xy[:, 1]
    return (150 * np.sin(x) * np.cos(y) + 40 * x,
            np.c_[150 * np.cos(x) * np.cos(y) + 40, -150 * np.sin(x) * np.sin(y)])


def _km_csv(path, n):
    """A CSV 'x,y,z' of n random points of `_hill_m_over_km` on [0, 3] x [0, 2] km."""
    xy = np.random.default_rng(n).random((n, 2)) * [3.0, 2.0]
    np.savetxt(path, np.c_[xy, _hill_m_over_km(xy)[0]], delimiter=",", header="x,y,z", comments="")
    return xy


def test_csv_heights_in_metres_over_kilometres_give_the_analytic_gradients(tmp_path):
    """Issue 21: the slopes, ~200 m per km, read as numbers of one metric are ~89.7° steep;
    the header names z, so the gradients are fitted to the heights over the plan: every
    point is kept and the error of the local quadratic fit falls as h² (to a quarter
    with 4x the points), and the spline's gradient is as good as the spline's with the
    exact gradients (its own discretisation error, O(h))."""
    from c1mesh.formats import read_cloud
    from c1mesh.engine.interpolator import RSDInterpolator

    errors = []
    for n in (1000, 4000):
        xy = _km_csv(tmp_path / f"hill{n}.csv", n)
        model = build_surface(read_cloud(tmp_path / f"hill{n}.csv"), FitOptions())
        assert model.hf.z.size == n
        origin = model.frame.origin
        truth = _hill_m_over_km(model.hf.xy + origin[:2])[1]
        errors.append(np.sqrt(np.mean((model.hf.gradients - truth) ** 2)))
    assert errors[1] < errors[0] / 3, errors
    assert errors[1] < 1e-2 * np.sqrt(np.mean(truth ** 2)), errors
    queries = np.random.default_rng(7).random((2000, 2)) * [2.4, 1.4] + 0.3
    ours = model.interp.gradient(queries - origin[:2]) - _hill_m_over_km(queries)[1]
    exact = RSDInterpolator(xy, *_hill_m_over_km(xy)).gradient(queries) - _hill_m_over_km(queries)[1]
    assert np.sqrt(np.mean(ours ** 2)) < 1.25 * np.sqrt(np.mean(exact ** 2))


def test_csv_heights_fit_the_same_in_any_unit(tmp_path):
    """Heights in metres and in kilometres over the same km plan give the same gradients,
    scaled by 1000: nothing in the fit compares heights with plan distances."""
    from c1mesh.formats import read_cloud

    _km_csv(tmp_path / "m.csv", 2000)
    metres = read_cloud(tmp_path / "m.csv")
    km = PointCloud(points=metres.points * [1, 1, 1e-3], height_column="z")
    in_m, in_km = (build_surface(c, FitOptions()).hf for c in (metres, km))
    np.testing.assert_array_equal(in_m.source_index, in_km.source_index)
    np.testing.assert_allclose(in_m.gradients, 1e3 * in_km.gradients, rtol=1e-9, atol=0)


def test_blocks_run_in_the_thread_knobs_threads_and_give_the_same_gradients(monkeypatch):
    """Under `limit(n)` the blocks (each a neighbour search and a fit) run in at most n
    threads; the gradients do not depend on n or on the blocking."""
    import threading

    import c1mesh.stages.height_gradients as hg
    from c1mesh.core.threads import limit

    searched, ran_in = [], set()
    search = hg.nearest_neighbours

    def recording(*args, **kwargs):
        searched.append(len(args[3]))
        ran_in.add(threading.get_ident())
        return search(*args, **kwargs)
    xy = np.random.default_rng(4).random((3000, 2))
    z = np.sin(3 * xy[:, 0]) + xy[:, 1] ** 2
    plain = height_gradients(xy, z, k=24)                   # one block of 3000
    monkeypatch.setattr(hg, "nearest_neighbours", recording)
    monkeypatch.setattr(hg, "BLOCK", 256)                   # 12 blocks
    for threads in (1, 2):
        searched.clear()
        ran_in.clear()
        with limit(threads):
            np.testing.assert_array_equal(height_gradients(xy, z, k=24), plain)
        assert sorted(searched) == sorted([256] * 11 + [3000 - 11 * 256])
        assert 1 <= len(ran_in) <= threads


def test_gradients_at_some_points_are_those_rows_and_reach_the_kth_neighbour():
    """gradients_at(at) gives the bits of height_gradients' rows `at`, in at's order, and
    each point's reach is the plane distance to its k-th nearest other point (a plain
    cKDTree query, which counts the point itself first)."""
    from scipy.spatial import cKDTree

    from c1mesh.stages.height_gradients import gradients_at

    rng = np.random.default_rng(8)
    xy = rng.random((4000, 2))
    z = np.cos(2 * xy[:, 0]) * xy[:, 1]
    at = rng.choice(4000, 700, replace=False)
    gradients, reach = gradients_at(xy, z, at, k=24)
    np.testing.assert_array_equal(gradients, height_gradients(xy, z, k=24)[at])
    kth = cKDTree(xy).query(xy[at], k=25)[0][:, -1]        # an independent search
    np.testing.assert_allclose(reach, kth, rtol=1e-12, atol=0)
    twice = np.concatenate([at[:50], at[:50]])               # a point asked for twice: both rows
    again, _ = gradients_at(xy, z, twice, k=24)
    np.testing.assert_array_equal(again, np.concatenate([gradients[:50], gradients[:50]]))


@pytest.mark.parametrize("degree", [1, 2])
def test_the_kernel_solves_each_points_weighted_system_as_a_plain_loop_does(degree):
    """height_gradients against the fit written out point by point: the k nearest other
    points by brute force, the median scale, the weights, the ridged normal equations solved
    by numpy (LAPACK). Random points: no distance ties, so the neighbours are unambiguous."""
    from c1mesh.stages.height_gradients import RIDGE

    rng = np.random.default_rng(11)
    xy = rng.random((600, 2)) * 50.0
    z = np.sin(xy[:, 0] / 7) * xy[:, 1] / 9 + rng.normal(scale=0.05, size=600)
    k = 24
    fitted = height_gradients(xy, z, k=k, degree=degree)
    for i in range(0, 600, 7):
        d = xy - xy[i]
        dist2 = (d ** 2).sum(axis=1)
        near = [j for j in np.argsort(dist2) if j != i][:k]
        r2 = float(np.median(dist2[near]))
        u, v = d[near, 0] / np.sqrt(r2), d[near, 1] / np.sqrt(r2)
        a = np.c_[u, v] if degree == 1 else np.c_[u, v, u * u / 2, u * v, v * v / 2]
        w = 1.0 / (1.0 + dist2[near] / r2)
        normal = a.T @ (w[:, None] * a)
        normal += np.eye(len(normal)) * (RIDGE * np.trace(normal) + np.finfo(float).tiny)
        coef = np.linalg.solve(normal, a.T @ (w * (z[near] - z[i])))
        np.testing.assert_allclose(fitted[i], coef[:2] / np.sqrt(r2), rtol=1e-9, atol=1e-12)


def test_a_clump_of_duplicates_takes_its_neighbours_without_a_quadratic_query():
    """20,000 copies of three data at one plane position (heights 0, 1 and 2) beside a
    grid: each copy's 6 neighbours are the other copies with the lowest heights, as the
    rule (distance, offset, height) orders them, checked against a brute-force sort of
    every point; and finding them holds no clump-by-clump table (tracemalloc's peak stays
    far below the 20,000 × 20,000 query's 3.2 GB per array, which once exhausted memory)."""
    import tracemalloc

    xy, z = _grid_with_ties(2)
    copies = 20_000
    xy = np.concatenate([xy, np.tile([[0.5, 0.5]], (copies, 1))])
    z = np.concatenate([z, np.arange(copies) % 3.0])
    first = len(xy) - copies
    centres = np.array([first, first + 1, first + 2, len(xy) - 1, 0])
    tracemalloc.start()
    index = _search(xy, z, centres, 6)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50e6
    for row, c in enumerate(centres):
        others = np.delete(np.arange(len(xy)), c)
        d = xy[others] - xy[c]
        brute = others[np.lexsort((z[others], d[:, 1], d[:, 0], (d * d).sum(axis=1)))][:6]
        # equal data are interchangeable: compare what the fit sees, offsets and heights
        np.testing.assert_array_equal(np.column_stack([xy[index[row]], z[index[row]]]),
                                      np.column_stack([xy[brute], z[brute]]))
    gradients = height_gradients(xy, z, k=6)
    assert np.isfinite(gradients).all()


@pytest.mark.parametrize("case", ["uniform", "integer grid with duplicates", "decimal lattice far from 0",
                                  "strip and far outlier", "clumps"])
def test_the_grid_search_finds_what_a_brute_force_sort_finds(case):
    """Every point's k nearest other points, in order, against a brute-force sort of all
    points by (squared distance, dx, dy, height, number): on uniform points, on an integer
    grid full of distance ties and exact duplicates, on a 0.1 lattice at 1000 (offsets
    rounded, so some distances that tie on paper differ in the last bit and some do not),
    on a thin diagonal strip with one point 10^4 away (the grid must size its cells to
    the strip, not to the box), and on clumps of 30 points at one position. Heights take
    3 values: exact data ties down to the point number."""
    rng = np.random.default_rng(11)
    if case == "uniform":
        xy = rng.random((700, 2)) * 50
    elif case == "integer grid with duplicates":
        xy = rng.integers(0, 12, (700, 2)).astype(float)
    elif case == "decimal lattice far from 0":
        xy = 1000.3 + rng.integers(0, 26, (700, 2)) * 0.1
    elif case == "strip and far outlier":
        t = rng.random(699) * 100
        xy = np.concatenate([np.column_stack([t, t + rng.random(699) * 0.5]), [[1e4, -1e4]]])
    else:
        xy = np.repeat(rng.random((20, 2)) * 10, 30, axis=0) + np.repeat(rng.integers(0, 2, (20, 1)), 30, axis=0)
    z = rng.integers(0, 3, len(xy)).astype(float)
    for k in (1, 6, 24):
        index = _search(xy, z, np.arange(len(xy)), k)
        for c in range(len(xy)):
            others = np.delete(np.arange(len(xy)), c)
            d = xy[others] - xy[c]
            brute = others[np.lexsort((others, z[others], d[:, 1], d[:, 0], d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]))][:k]
            np.testing.assert_array_equal(index[c], brute, err_msg=f"{case}, k {k}, point {c}")


@pytest.mark.parametrize("points, cells", [(20_000, 900), (5, 2), (1, 1), (300, 100_000)])
def test_the_points_sorted_by_cell_keep_their_order_within_a_cell(points, cells):
    """plane_grid's order of the points by cell number is numpy's stable argsort, by the
    counting sort or (far more cells than points) by numpy itself: many ties here."""
    from c1mesh.stages.height_gradients import _stable_order
    number = np.random.default_rng(points).integers(0, cells, points)
    np.testing.assert_array_equal(_stable_order(number, cells), np.argsort(number, kind="stable"))


@pytest.mark.parametrize("late", [5, (1 << 14) - 1, 1 << 14, 40_000])
def test_the_first_distinct_rows_are_found_wherever_they_lie(late):
    """distinct_rows against a loop over the rows: the first `enough` distinct rows in row
    order, also when the second and third first appear at or past a chunk's end, and
    after rows already seen (as a stream of chunks passes them on)."""
    from c1mesh.stages.height_gradients import distinct_rows

    def brute(rows, enough, seen=()):
        found = [tuple(r) for r in seen]
        for row in map(tuple, rows):
            if len(found) >= enough:
                break
            if row not in found:
                found.append(row)
        return found[len(seen):] if seen else found
    xy = np.zeros((50_000, 2))
    xy[late:] = [1.0, 0.0]
    xy[late + 3:] = [1.0, 2.0]
    xy[-1] = [7.0, 7.0]
    for enough in (1, 3, 4):
        assert [tuple(r) for r in distinct_rows(xy, enough)] == brute(xy, enough)
    seen = [np.array([1.0, 0.0])]
    assert [tuple(r) for r in distinct_rows(xy, 3, seen)][1:] == brute(xy, 3, [(1.0, 0.0)])
    assert len(distinct_rows(np.zeros((30_000, 2)), 3)) == 1
