"""Delaunay triangulation (tiled, checked against plain qhull and exact arithmetic) and trimming."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import Delaunay

from c1mesh.stages import trim as trim_stage
from c1mesh.core.errors import InputError
from c1mesh.engine.triangulation import delaunay
from c1mesh.stages.trim import TrimReport, circle_ratio, trim

REAL = Path(__file__).resolve().parent.parent / "data_samples"  # copies of ../shared/data/real


@pytest.fixture
def mtri():
    """matplotlib.tri, the peer for circle ratios and flat-triangle masks (only the tests
    that compare with it are skipped without matplotlib)."""
    return pytest.importorskip("matplotlib.tri")


def as_set(tri):
    return set(map(tuple, np.sort(np.asarray(tri), axis=1).tolist()))


def doubled_areas(xy, tri):
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def exact_violations(q, tri):
    """Interior edges whose opposite vertex lies strictly inside the other triangle's
    circumcircle, and exact ties, with Python integers (q: (n, 2) integer coordinates)."""
    tri = np.asarray(tri)
    u, v, w = tri.ravel(), tri[:, [1, 2, 0]].ravel(), tri[:, [2, 0, 1]].ravel()
    n = len(q)
    key, twin = u * n + v, v * n + u
    order = np.argsort(key)
    pos = np.minimum(np.searchsorted(key[order], twin), len(order) - 1)
    has = key[order][pos] == twin
    qo = q.astype(object)
    a, b, c, d = qo[u[has]], qo[v[has]], qo[w[has]], qo[w[order[pos[has]]]]
    ad, bd, cd = a - d, b - d, c - d
    det = ((ad[:, 0] ** 2 + ad[:, 1] ** 2) * (bd[:, 0] * cd[:, 1] - bd[:, 1] * cd[:, 0])
           - (bd[:, 0] ** 2 + bd[:, 1] ** 2) * (ad[:, 0] * cd[:, 1] - ad[:, 1] * cd[:, 0])
           + (cd[:, 0] ** 2 + cd[:, 1] ** 2) * (ad[:, 0] * bd[:, 1] - ad[:, 1] * bd[:, 0]))
    return int(sum(x > 0 for x in det)), int(sum(x == 0 for x in det))


def assert_valid_triangulation(xy, tri):
    """ccw, edge-manifold, Euler count and area equal to the convex hull's."""
    from scipy.spatial import ConvexHull
    area = doubled_areas(xy, tri)
    assert np.all(area > 0)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert count.max() <= 2
    boundary = int((count == 1).sum())
    used = np.unique(tri).size
    assert len(tri) == 2 * used - boundary - 2
    assert area.sum() / 2 == pytest.approx(ConvexHull(xy).volume, rel=1e-9)


def centred(xy):
    return xy - (xy.min(axis=0) + xy.max(axis=0)) / 2


# --- delaunay -----------------------------------------------------------------------------

def test_small_random_input_equals_plain_qhull_and_is_ccw():
    xy = np.random.default_rng(0).random((3000, 2))
    tri = delaunay(xy)
    assert tri.dtype == np.int64 and tri.shape[1] == 3
    assert as_set(tri) == as_set(Delaunay(xy).simplices)
    assert np.all(doubled_areas(xy, tri) > 0)


def test_large_random_input_equals_plain_qhull():
    xy = np.random.default_rng(1).random((60_000, 2))
    tri = delaunay(xy)
    assert as_set(tri) == as_set(Delaunay(xy).simplices)
    assert np.all(doubled_areas(xy, tri) > 0)


@pytest.mark.parametrize("kind", ["uniform", "clusters", "annulus", "anisotropic", "strip"])
def test_triangulation_equals_plain_qhull_on_the_same_coordinates(kind):
    rng = np.random.default_rng(2)
    n = 30_000
    xy = {
        "uniform": lambda: rng.random((n, 2)),
        "clusters": lambda: rng.random((20, 2))[rng.integers(0, 20, n)] * 100 + rng.normal(size=(n, 2)),
        "annulus": lambda: (lambda p: p[np.hypot(*(p - 0.5).T) > 0.3])(rng.random((n, 2))),
        "anisotropic": lambda: rng.normal(size=(n, 2)) * [1.0, 0.01],
        "strip": lambda: rng.random((n, 2)) * [1000.0, 1.0],
    }[kind]()
    c = centred(xy)
    tri = delaunay(c)
    assert as_set(tri) == as_set(Delaunay(c).simplices)
    assert np.all(doubled_areas(c, tri) > 0)


def test_grid_ties_give_a_valid_delaunay_triangulation():
    g = np.stack(np.meshgrid(np.arange(150), np.arange(120)), axis=-1).reshape(-1, 2)
    tri = delaunay(g.astype(float))
    assert_valid_triangulation(g.astype(float), tri)
    inside, ties = exact_violations(g, tri)
    assert inside == 0 and ties > 0                     # every grid square is a tie


def _square_diagonals(g: np.ndarray, order: np.ndarray, tri: np.ndarray, width: int, height: int) -> tuple:
    """Brute force over the grid squares: (squares whose diagonal in tri passes through
    their lowest-numbered corner, squares). g: the grid points in row-major position,
    order: each position's point number."""
    edges = {tuple(sorted(e)) for t in tri.tolist() for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    good = 0
    for j in range(height - 1):
        for i in range(width - 1):
            p, q, r, s = (order[j * width + i], order[j * width + i + 1],
                          order[(j + 1) * width + i + 1], order[(j + 1) * width + i])
            diagonal = (p, r) if min(p, r) < min(q, s) else (q, s)
            good += tuple(sorted(diagonal)) in edges
    return good, (width - 1) * (height - 1)


def test_grid_ties_are_cut_through_each_squares_lowest_numbered_corner():
    """Whatever the points' order, every grid square is cut by the diagonal through its
    lowest-numbered corner (the fan rule), and the result is still Delaunay (exact)."""
    width, height = 40, 30
    g = np.stack(np.meshgrid(np.arange(width), np.arange(height)), axis=-1).reshape(-1, 2)
    for seed in range(3):
        order = np.random.default_rng(seed).permutation(len(g))     # position -> point number
        xy = np.empty((len(g), 2))
        xy[order] = g * 0.5 + [6.4e5, 8.5e5]                        # state-plane-like, exact
        tri = delaunay(xy)
        assert_valid_triangulation(xy - xy.mean(axis=0), tri)
        q = np.empty_like(g)
        q[order] = g
        assert exact_violations(q, tri)[0] == 0
        good, squares = _square_diagonals(g, order, tri, width, height)
        assert good == squares


def test_points_on_one_circle_are_the_fan_from_the_lowest_numbered_one():
    """The 12 lattice points on the circle of radius 5 (no rectangle among the 4 corners of
    most quads, so the exact in-circle test decides), inside a ring of far points: their
    polygon is one Delaunay face, 10 triangles, each through the lowest-numbered of them."""
    circle = np.array([(5, 0), (4, 3), (3, 4), (0, 5), (-3, 4), (-4, 3), (-5, 0), (-4, -3), (-3, -4),
                       (0, -5), (3, -4), (4, -3)], dtype=float)
    ring = 40 * np.array([(np.cos(a), np.sin(a)) for a in np.linspace(0, 2 * np.pi, 9)[:-1]])
    for seed in range(5):
        rng = np.random.default_rng(seed)
        xy = np.concatenate([circle, ring])[rng.permutation(len(circle) + len(ring))]
        on_circle = np.flatnonzero(np.isclose(np.hypot(*xy.T), 5))
        tri = delaunay(xy + 0.25)                                 # off the origin: not symmetric
        assert_valid_triangulation(xy, tri)
        inner = tri[np.isin(tri, on_circle).all(axis=1)]
        assert len(inner) == 10
        assert (inner == on_circle.min()).any(axis=1).all()


def _inside_counts(xy: np.ndarray, tri: np.ndarray) -> tuple[int, int]:
    """(interior edges whose far corner is strictly inside the other triangle's circle,
    exactly on it), with fractions.Fraction on the float coordinates as they are."""
    from fractions import Fraction
    nb = trim_stage.triangle_neighbours(tri, len(xy))
    inside = on = 0
    for t, k in zip(*np.nonzero(nb > np.arange(len(tri))[:, None])):
        u = nb[t, k]
        far = [v for v in tri[u] if v not in (tri[t, (k + 1) % 3], tri[t, (k + 2) % 3])][0]
        a, b, c, d = ([Fraction(v) for v in xy[i]] for i in (tri[t, k], tri[t, (k + 1) % 3], tri[t, (k + 2) % 3], far))
        rows = [(p[0] - d[0], p[1] - d[1]) for p in (a, b, c)]
        lift = [x * x + y * y for x, y in rows]
        det = (lift[0] * (rows[1][0] * rows[2][1] - rows[2][0] * rows[1][1])
               - lift[1] * (rows[0][0] * rows[2][1] - rows[2][0] * rows[0][1])
               + lift[2] * (rows[0][0] * rows[1][1] - rows[1][0] * rows[0][1]))
        inside, on = inside + (det > 0), on + (det == 0)
    return inside, on


def _exact_orientations(xy: np.ndarray, tri: np.ndarray) -> list:
    from fractions import Fraction
    out = []
    for t in tri.tolist():
        (ax, ay), (bx, by), (cx, cy) = ([Fraction(v) for v in xy[i]] for i in t)
        out.append((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))
    return out


def test_near_ties_and_straight_borders_are_exact_in_the_given_coordinates():
    """A millimetre-quantised 0.5 m grid rotated by 30 degrees near the origin: its squares
    are nearly (not exactly) cocircular and its borders nearly straight. The triangulation
    holds in exact arithmetic on the coordinates as given: every triangle counter-clockwise,
    no point inside another triangle's circle. (Triangulating the points centred on their
    box, which rounds coordinates this small, fails this test.)"""
    g = np.stack(np.meshgrid(np.arange(40), np.arange(30)), axis=-1).reshape(-1, 2) * 0.5
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    xy = np.round(g @ np.array([[c, s], [-s, c]]) * 1000) / 1000 + [3.0, 1.0]   # near the origin
    xy = xy[np.random.default_rng(4).permutation(len(xy))]
    tri = delaunay(xy)
    assert min(_exact_orientations(xy, tri)) > 0
    assert _inside_counts(xy, tri)[0] == 0


@pytest.mark.parametrize("name", [
    "4_6_crop.las",
    pytest.param("autzen_trim.laz", marks=pytest.mark.slow),
])
def test_lidar_coordinates_are_triangulated_exactly_delaunay(name):
    # plain qhull on the raw state-plane coordinates (~6.4e5, 8.5e5) is not: 3858 interior
    # edges of 4_6_crop.las fail the exact empty-circle test; centring fixes that
    laspy = pytest.importorskip("laspy")
    las = laspy.read(str(REAL / name))
    xy = np.unique(np.column_stack([las.x, las.y]), axis=0)       # state-plane feet, 0.01 steps
    q = np.round((xy - xy.min(axis=0)) * 100).astype(np.int64)    # the exact integer lattice
    assert np.allclose(q / 100 + xy.min(axis=0), xy, rtol=0, atol=1e-6)
    tri = delaunay(xy)
    assert exact_violations(q, tri)[0] == 0
    assert_valid_triangulation(xy - xy.mean(axis=0), tri)


def test_exact_duplicates_are_triangulated_once_by_their_first_copy():
    """The library refuses duplicate points; delaunay triangulates the first (lowest
    index) of each and leaves the copies in no triangle, so the public interpolator takes
    scans with repeated points (its own check: the set of triangles of the distinct points)."""
    from c1mesh.engine.interpolator import RSDInterpolator

    rng = np.random.default_rng(4)
    distinct = rng.random((500, 2))
    copies = rng.integers(0, 500, 200)
    xy = np.concatenate([distinct, distinct[copies]])
    tri = delaunay(xy)
    assert tri.max() < 500                                  # no copy is used
    assert as_set(tri) == as_set(Delaunay(distinct).simplices)
    z = np.sin(3 * xy[:, 0]) + xy[:, 1]
    interp = RSDInterpolator(xy, z, np.column_stack([3 * np.cos(3 * xy[:, 0]), np.ones(len(xy))]))
    assert np.allclose(interp(distinct[:20]), z[:20])


@pytest.mark.parametrize("xy, msg", [
    (np.zeros((2, 2)), "at least 3"),
    (np.column_stack([np.arange(10.0), 3 * np.arange(10.0) + 1]), "one line"),
    (np.ones((5, 2)), "one line"),
    (np.array([[0, 0], [1, 0], [0, np.nan]]), "finite"),
    (np.zeros((5, 3)), "shape"),
])
def test_unusable_points_are_input_errors(xy, msg):
    with pytest.raises(InputError, match=msg):
        delaunay(xy)


# --- trim ---------------------------------------------------------------------------------

def test_circle_ratio_is_one_for_equilateral_and_twice_matplotlibs(mtri):
    xy = np.random.default_rng(4).random((200, 2))
    tri = Delaunay(xy).simplices
    ours = circle_ratio(trim_stage.edge_lengths(xy, tri))
    theirs = mtri.TriAnalyzer(mtri.Triangulation(xy[:, 0], xy[:, 1], tri)).circle_ratios(rescale=False)
    assert np.allclose(ours, 2 * theirs)
    assert circle_ratio(np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 2.0], [0.0, 1.0, 1.0]])) == \
        pytest.approx([1.0, 0.0, 0.0])


def grid_with_hole():
    """A 31 x 25 unit grid without the points strictly inside [10, 19] x [7, 15]."""
    g = np.stack(np.meshgrid(np.arange(31.0), np.arange(25.0)), axis=-1).reshape(-1, 2)
    in_hole = (g[:, 0] > 10) & (g[:, 0] < 19) & (g[:, 1] > 7) & (g[:, 1] < 15)
    return g[~in_hole]


def cross2(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def points_in(xy, tri, samples):
    """(S,) True where a sample lies inside some triangle (barycentric test)."""
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    hit = np.zeros(len(samples), dtype=bool)
    for i, s in enumerate(samples):
        d = [cross2(b - a, s - a), cross2(c - b, s - b), cross2(a - c, s - c)]
        hit[i] = np.any((d[0] >= 0) & (d[1] >= 0) & (d[2] >= 0))
    return hit


def test_trim_removes_the_triangles_over_a_hole_and_nothing_else():
    xy = grid_with_hole()
    tri = delaunay(xy)
    out, rep = trim(xy, tri)
    assert rep.max_edge == pytest.approx(4.0, rel=1e-2)        # 4 x the grid spacing
    centroid_in_hole = lambda t: np.all(  # noqa: E731
        (np.abs(xy[t].mean(axis=1) - [14.5, 11.0]) < [4.5, 4.0]), axis=1)
    # everything outside the hole is kept; what is removed lies over the hole
    assert as_set(tri[~centroid_in_hole(tri)]) <= as_set(out)
    removed = as_set(tri) - as_set(out)
    assert removed and all(centroid_in_hole(np.array([t]))[0] for t in removed)
    # and the hole stays a hole: its core (one spacing in from the edge) is not covered
    core = np.stack(np.meshgrid(np.linspace(11.5, 17.5, 13), np.linspace(8.5, 13.5, 11)),
                    axis=-1).reshape(-1, 2)
    assert not points_in(xy, out, core).any()
    assert points_in(xy, tri, core).all()                      # it was, before trimming
    assert rep.triangles_before == len(tri) and rep.triangles_after == len(out)
    assert rep.triangles_before - rep.triangles_after == sum(rep.removed.values())
    assert rep.unreferenced_points == 0


def bulged_arc(seed=6):
    """Random points under a top edge that sags slightly inwards: the convex hull's top is
    the chord, and between chord and arc qhull must fill nested layers of slivers."""
    rng = np.random.default_rng(seed)
    x = np.linspace(-1, 1, 60)
    arc = np.column_stack([x, 1 - 0.002 * (1 - x**2)])
    inner = rng.uniform([-1, 0], [1, 0.95], size=(600, 2))
    return np.vstack([arc, inner])


def test_hull_slivers_are_peeled_like_matplotlibs_flat_triangle_mask(mtri):
    xy = bulged_arc()
    tri = delaunay(xy)
    out, rep = trim(xy, tri, max_edge=None)
    flat = mtri.TriAnalyzer(mtri.Triangulation(xy[:, 0], xy[:, 1], tri)).get_flat_tri_mask(
        min_circle_ratio=0.01 / 2, rescale=False)
    assert rep.removed["sliver"] == int(flat.sum()) > 20
    assert as_set(out) == as_set(tri[~flat])
    assert min(circle_ratio(trim_stage.edge_lengths(xy, out))[_boundary(out)]) >= 0.01


def test_sliver_peeling_after_long_edge_removal_matches_matplotlib_with_a_mask(mtri):
    """matplotlib masks the same long-edge and sliver triangles; it does not resolve
    bowties, so ours is its result minus the smaller fans at its bowtie vertices."""
    xy = np.vstack([bulged_arc(7), grid_with_hole() / 30 - [0.5, 1.0]])
    tri = delaunay(xy)
    out, rep = trim(xy, tri, max_edge=0.08)
    long = trim_stage.edge_lengths(xy, tri).max(axis=1) > 0.08
    peer = mtri.Triangulation(xy[:, 0], xy[:, 1], tri, mask=long)
    flat = mtri.TriAnalyzer(peer).get_flat_tri_mask(min_circle_ratio=0.005, rescale=False)
    theirs = tri[~flat]
    assert rep.removed["long_edge"] == int(long.sum())
    assert rep.removed["sliver"] == int(flat.sum() - long.sum())
    ours, extra = as_set(out), as_set(theirs) - as_set(out)
    assert ours <= as_set(theirs)
    assert len(extra) == rep.removed["bowtie"] > 0
    pinched = set(bowtie_vertices(theirs))
    assert pinched and all(pinched & set(t) for t in extra)
    assert bowtie_vertices(out) == []


def _boundary(tri):
    """(T,) True for triangles with an edge used once."""
    edges = np.sort(np.concatenate([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]]), axis=1)
    _, inv, count = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    return (count[inv.ravel()] == 1).reshape(3, -1).any(axis=0)


def test_interior_slivers_are_never_removed():
    rng = np.random.default_rng(8)
    xy = np.vstack([rng.random((400, 2)), [[0.5, 0.5], [0.5, 0.50001]]])   # needles around a pair
    tri = delaunay(xy)
    thin = circle_ratio(trim_stage.edge_lengths(xy, tri)) < 0.01
    interior_thin = thin & np.all(np.abs(xy[tri].mean(axis=1) - 0.5) < 0.3, axis=1)
    assert interior_thin.sum() >= 2
    out, _ = trim(xy, tri, max_edge=None)
    assert as_set(tri[interior_thin]) <= as_set(out)


def test_bowtie_fans_are_reduced_to_the_largest():
    xy = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [-1, 0], [-1, -1], [0, -1], [2, 1]], float)
    tri = np.array([[0, 1, 2], [0, 2, 3], [2, 1, 7], [0, 4, 5]])   # vertex 0: fans of 2 and 1
    out, rep = trim(xy, tri, max_edge=None, min_circle_ratio=0.0)
    assert as_set(out) == as_set(tri[:3])
    assert rep.removed == {"long_edge": 0, "sliver": 0, "bowtie": 1}
    assert rep.unreferenced_points == 3                            # 4, 5 and 6


def test_non_manifold_and_bad_options_are_input_errors():
    xy = np.random.default_rng(9).random((10, 2))
    with pytest.raises(InputError, match="edge-manifold"):
        trim(xy, np.array([[0, 1, 2], [0, 1, 3], [1, 0, 4]]))
    with pytest.raises(InputError, match="max_edge"):
        trim(xy, np.array([[0, 1, 2]]), max_edge=-1.0)
    with pytest.raises(InputError, match="max_edge"):
        trim(xy, np.array([[0, 1, 2]]), max_edge="long")
    with pytest.raises(InputError, match="indices"):
        trim(xy, np.array([[0, 1, 10]]))
    with pytest.raises(InputError, match="min_circle_ratio"):
        trim(xy, np.array([[0, 1, 2]]), min_circle_ratio=2.0)
    out, rep = trim(xy, np.zeros((0, 3), dtype=np.int64))
    assert out.shape == (0, 3) and rep == TrimReport(0, 0, {"long_edge": 0, "sliver": 0,
                                                            "bowtie": 0}, None, 10)


def test_gap_free_random_points_lose_no_interior_triangle_to_auto_max_edge():
    xy = np.random.default_rng(10).random((40_000, 2))
    tri = delaunay(xy)
    out, rep = trim(xy, tri)
    lost = as_set(tri) - as_set(out)
    centroids = np.array([xy[list(t)].mean(axis=0) for t in lost]).reshape(-1, 2)
    assert np.all(np.abs(centroids - 0.5).max(axis=1) > 0.45)     # only near the border


def bowtie_vertices(tri):
    """Vertices whose triangles form more than one edge-connected fan (plain Python)."""
    around: dict[int, list[int]] = {}
    for t, row in enumerate(tri.tolist()):
        for v in row:
            around.setdefault(v, []).append(t)
    bad = []
    for v, ts in around.items():
        seen, stack = {ts[0]}, [ts[0]]
        while stack:
            t = stack.pop()
            for u in ts:
                if u not in seen and len(set(tri[t]) & set(tri[u])) == 2:
                    seen.add(u)
                    stack.append(u)
        if len(seen) != len(ts):
            bad.append(v)
    return bad


def test_lidar_ground_gives_a_sane_trimmed_mesh():
    laspy = pytest.importorskip("laspy")
    las = laspy.read(str(REAL / "4_6_crop.las"))
    ground = np.asarray(las.classification) == 2
    xy_all = np.column_stack([np.asarray(las.x), np.asarray(las.y)])
    xy_all -= xy_all.mean(axis=0)
    xy, other = xy_all[ground], xy_all[~ground]
    tri = delaunay(xy)
    out, rep = trim(xy, tri)
    plain = Delaunay(xy).simplices
    plain_edges = np.unique(np.sort(np.concatenate([plain[:, [0, 1]], plain[:, [1, 2]],
                                                    plain[:, [2, 0]]]), axis=1), axis=0)
    median = np.median(np.linalg.norm(xy[plain_edges[:, 0]] - xy[plain_edges[:, 1]], axis=1))
    assert rep.max_edge == pytest.approx(4 * median)
    assert trim_stage.edge_lengths(xy, out).max() <= rep.max_edge
    assert rep.triangles_before == len(tri) == len(plain)
    assert rep.triangles_before - rep.triangles_after == sum(rep.removed.values())
    assert rep.unreferenced_points == len(xy) - np.unique(out).size
    assert 0 < rep.removed["long_edge"] < 0.05 * len(tri)
    assert bowtie_vertices(out) == []
    # what was cut bridges gaps in the ground: most of its area covers non-ground returns
    removed = np.array(sorted(as_set(tri) - as_set(out)))
    finder = Delaunay(xy)
    hits = np.zeros(len(plain), dtype=int)
    np.add.at(hits, finder.find_simplex(other)[finder.find_simplex(other) >= 0], 1)
    index = {t: i for i, t in enumerate(map(tuple, np.sort(plain, axis=1).tolist()))}
    covered = np.array([hits[index[tuple(t)]] > 0 for t in removed])
    area = np.abs(doubled_areas(xy, removed))
    assert area[covered].sum() > 0.7 * area.sum()


def test_bowties_left_by_trimming_real_lidar_gaps_are_resolved():
    laspy = pytest.importorskip("laspy")
    las = laspy.read(str(REAL / "autzen_trim.laz"))
    ground = np.asarray(las.classification) == 2
    xy = np.unique(np.column_stack([np.asarray(las.x), np.asarray(las.y)])[ground], axis=0)
    xy -= xy.mean(axis=0)
    out, rep = trim(xy, delaunay(xy))
    assert rep.removed["bowtie"] > 0                 # the gaps do pinch the mesh at vertices
    assert bowtie_vertices(out) == []
    assert rep.unreferenced_points == len(xy) - np.unique(out).size


def test_edge_lengths_of_3_4_5_triangles_and_against_a_loop_at_any_thread_count():
    """The trim kernel's lengths: exact on a 3-4-5 triangle (each corner rotation), and for
    a Delaunay mesh equal to the bit to a loop of hypot over every edge, at 1 and 3 threads."""
    xy = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0]])
    for tri in ([0, 1, 2], [1, 2, 0], [2, 0, 1], [0, 2, 1]):
        expected = [np.hypot(*(xy[tri[(k + 2) % 3]] - xy[tri[(k + 1) % 3]])) for k in range(3)]
        assert trim_stage.edge_lengths(xy, np.array([tri])).tolist() == [expected]
    assert sorted(trim_stage.edge_lengths(xy, np.array([[0, 1, 2]]))[0]) == [3.0, 4.0, 5.0]
    rng = np.random.default_rng(4)
    xy = rng.random((40000, 2)) * 1e3
    tri = delaunay(xy)                                        # > 4 of the kernel's blocks
    loop = np.array([[np.hypot(xy[t[(k + 2) % 3], 0] - xy[t[(k + 1) % 3], 0],
                               xy[t[(k + 2) % 3], 1] - xy[t[(k + 1) % 3], 1]) for k in range(3)]
                     for t in tri.tolist()])
    for threads in (1, 3):
        assert np.array_equal(trim_stage.edge_lengths(xy, tri, workers=threads), loop)


def test_neighbours_are_symmetric_and_share_the_edge():
    rng = np.random.default_rng(9)
    xy = rng.random((3000, 2))
    tri = delaunay(xy)
    nb = trim_stage.triangle_neighbours(tri, len(xy))
    t, k = np.nonzero(nb >= 0)
    edge = np.sort(np.stack([tri[t, (k + 1) % 3], tri[t, (k + 2) % 3]], axis=1), axis=1)
    other = tri[nb[t, k]]
    assert np.all((other == edge[:, :1]).any(axis=1) & (other == edge[:, 1:]).any(axis=1))
    assert np.all((nb[nb[t, k]] == t[:, None]).sum(axis=1) == 1)
    from scipy.spatial import ConvexHull
    t, k = np.nonzero(nb < 0)                # the edges without a neighbour: the hull's
    open_edges = np.sort(np.stack([tri[t, (k + 1) % 3], tri[t, (k + 2) % 3]], axis=1), axis=1)
    hull = ConvexHull(xy).simplices
    assert as_set(open_edges) == set(map(tuple, np.sort(hull, axis=1).tolist()))
    assert len(open_edges) == len(hull)


def test_bowtie_tie_break_does_not_depend_on_triangle_order():
    """Two fans of one triangle each meet at point 0: trim keeps the fan whose smallest
    sorted corner triple comes first, (0, 1, 2), in either input order (a tile, which has
    no qhull order, must decide the same way)."""
    xy = np.array([[0, 0], [1, -0.6], [1, 0.6], [-1, 0.6], [-1, -0.6]], dtype=float)
    right, left = [0, 1, 2], [0, 3, 4]
    for triangles in ([right, left], [left, right]):
        kept, report = trim(xy, np.array(triangles), max_edge=None)
        assert report.removed["bowtie"] == 1
        assert kept.tolist() == [right]


def test_trim_of_lidar_ground_does_not_depend_on_triangle_order():
    """Autzen ground has 57 bow-tie triangles; any permutation of qhull's triangles gives
    the same trimmed set."""
    laspy = pytest.importorskip("laspy")
    las = laspy.read(str(Path(__file__).resolve().parent.parent / "data_samples" / "autzen_trim.laz"))
    xy = np.column_stack([las.x, las.y])[np.asarray(las.classification) == 2]
    xy = np.unique(xy, axis=0)
    triangles = delaunay(xy)
    kept, report = trim(xy, triangles)
    assert report.removed["bowtie"] > 0
    shuffled, _ = trim(xy, triangles[np.random.default_rng(0).permutation(len(triangles))])
    as_set = lambda t: set(map(tuple, np.sort(t, axis=1).tolist()))      # noqa: E731
    assert as_set(shuffled) == as_set(kept)


def test_trim_mesh_keeps_what_trim_keeps_with_the_kept_triangles_edge_table():
    """trim_mesh (the fit's trim, sharing its edge sort) against trim on Autzen ground (57
    bowtie triangles, slivers): the same triangles and report, and an edge table equal to
    edge_table of the kept triangles."""
    from c1mesh.engine.topology import edge_table
    from c1mesh.stages.trim import trim_mesh

    laspy = pytest.importorskip("laspy")
    las = laspy.read(str(Path(__file__).resolve().parent.parent / "data_samples" / "autzen_trim.laz"))
    xy = np.unique(np.column_stack([las.x, las.y])[np.asarray(las.classification) == 2], axis=0)
    triangles = delaunay(xy)
    kept, report = trim(xy, triangles)
    mesh, mesh_report = trim_mesh(xy, triangles)
    assert report.removed["bowtie"] > 0 and report.removed["sliver"] > 0
    assert np.array_equal(mesh.triangles, kept) and mesh_report == report
    table, expected = mesh.edge_table(), edge_table(kept, len(xy))
    for field in ("edges", "tri_edge", "forward", "owner", "owner_slot", "count"):
        assert np.array_equal(getattr(table, field), getattr(expected, field)), field


def test_bowtie_search_at_given_vertices_finds_what_the_whole_search_finds():
    """remove_bowties(at=...) looks only at the triangles around those vertices; where it
    is given every vertex of a real trim's bowties, it removes what the whole search does."""
    from c1mesh.stages.trim import remove_bowties, triangle_neighbours

    laspy = pytest.importorskip("laspy")
    las = laspy.read(str(Path(__file__).resolve().parent.parent / "data_samples" / "autzen_trim.laz"))
    xy = np.unique(np.column_stack([las.x, las.y])[np.asarray(las.classification) == 2], axis=0)
    triangles = delaunay(xy)
    kept, _ = trim(xy, triangles, min_circle_ratio=0.0)
    rng = np.random.default_rng(2)
    alive = rng.random(len(kept)) > 0.2                    # holes everywhere: many bowties
    nb = triangle_neighbours(kept, len(xy))
    whole = remove_bowties(kept, alive.copy(), nb)
    at = np.zeros(len(xy), dtype=bool)
    at[kept[~alive].ravel()] = True                        # every vertex whose star changed
    local = remove_bowties(kept, alive.copy(), nb, at=at)
    assert whole.size > 100 and np.array_equal(local, whole)
    at[kept[whole[0]]] = False                             # not looked at: not cut there
    assert not np.isin(whole[0], remove_bowties(kept, alive.copy(), nb, at=at))


# ---- the trim's kernels against the numpy expressions they replace -------------------------
def _random_mesh(seed, keep=0.8):
    """A Delaunay triangulation of 300 random points, its neighbours and a random alive mask."""
    rng = np.random.default_rng(seed)
    xy = rng.random((300, 2))
    tri = delaunay(xy)
    return rng, xy, tri, trim_stage.triangle_neighbours(tri, len(xy)), rng.random(len(tri)) < keep


@pytest.mark.parametrize("seed, block", [(0, 1 << 14), (1, 1 << 14), (0, 7), (1, 64)])
def test_each_edge_once_is_the_lengths_where_the_neighbour_is_none_or_later(seed, block, monkeypatch):
    """In row order, also when the triangles are split into blocks of 7 or 64 (each block
    into its own part, joined)."""
    monkeypatch.setattr(trim_stage, "KERNEL_BLOCK", block)
    _, xy, tri, nb, _ = _random_mesh(seed)
    lengths = trim_stage.edge_lengths(xy, tri)
    once = trim_stage._each_edge_once(lengths, nb)
    want = lengths[(nb < 0) | (nb > np.arange(len(nb))[:, None])]
    assert np.array_equal(once, want)
    assert once.size == len({tuple(sorted(e)) for t in tri.tolist() for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))})


@pytest.mark.parametrize("seed", [0, 1])
def test_used_points_counts_the_corners_of_live_triangles(seed):
    _, xy, tri, _, alive = _random_mesh(seed, keep=0.3)
    want = len(set(tri[alive].ravel().tolist()))
    assert trim_stage.used_points(tri, alive, len(xy)) == want < len(xy)


@pytest.mark.parametrize("seed", [0, 1])
def test_live_rows_and_corner_slots_are_numpys_masks_and_nonzero(seed):
    rng, xy, tri, _, alive = _random_mesh(seed)
    at = rng.random(len(xy)) < 0.2
    assert np.array_equal(trim_stage._live_rows(tri, alive, None), np.flatnonzero(alive))
    rows = trim_stage._live_rows(tri, alive, at)
    assert np.array_equal(rows, np.flatnonzero(alive & at[tri].any(axis=1)))
    t, slot = trim_stage._corner_slots(tri, rows, at)
    r, want_slot = np.nonzero(at[tri[rows]])
    assert np.array_equal(t, rows[r]) and np.array_equal(slot, want_slot) and t.size > 10


@pytest.mark.parametrize("kind", ["random", "grid", "duplicates"])
def test_cdts_neighbours_are_a_plain_loop_over_the_triangles_edges(kind):
    """delaunay_with_neighbours' (T, 3) neighbours (CDT's, reordered) against a dictionary of
    every triangle's edges: slot k holds the other triangle with the edge opposite corner
    k, -1 where none has it, on random points, a grid (cocircular ties) and with exact
    duplicates (the triangles of the first copies)."""
    from c1mesh.engine.triangulation import delaunay_with_neighbours
    rng = np.random.default_rng(5)
    if kind == "grid":
        xy = np.stack(np.meshgrid(np.arange(12.0), np.arange(9.0)), -1).reshape(-1, 2)
    else:
        xy = rng.random((300, 2))
    if kind == "duplicates":
        xy = np.vstack([xy, xy[:40]])
    triangles, neighbours = delaunay_with_neighbours(xy)
    assert np.array_equal(triangles, delaunay(xy))
    having: dict = {}
    for t, corners in enumerate(triangles.tolist()):
        for k in range(3):
            having.setdefault(frozenset((corners[(k + 1) % 3], corners[(k + 2) % 3])), []).append(t)
    for t, corners in enumerate(triangles.tolist()):
        for k in range(3):
            others = [u for u in having[frozenset((corners[(k + 1) % 3], corners[(k + 2) % 3]))] if u != t]
            assert neighbours[t, k] == (others[0] if others else -1)
    assert (neighbours == -1).sum() > 0


@pytest.mark.parametrize("kind", ["random", "grid", "circle", "collinear"])
def test_dropping_cdts_super_triangle_leaves_what_cdts_own_erase_leaves(kind):
    """_ties.drop_super_triangle on CDT's rows before erase_super_triangle gives the rows
    CDT's own erase gives (the same triangles in the same order, the same neighbours, none
    as -1), on random points, a shuffled grid (ties), points on a circle and points on a
    line (no triangle); a row with a number out of range is refused (None)."""
    import pythoncdt

    from c1mesh.engine import _ties
    rng = np.random.default_rng(3)
    xy = {"random": rng.random((2000, 2)),
          "grid": np.stack(np.meshgrid(np.arange(30.0), np.arange(20.0)), -1).reshape(-1, 2)[rng.permutation(600)],
          "circle": np.c_[np.cos(np.arange(50.0)), np.sin(np.arange(50.0))],
          "collinear": np.c_[np.arange(8.0), 3 * np.arange(8.0)]}[kind]

    def inserted():
        cdt = pythoncdt.Triangulation(pythoncdt.VertexInsertionOrder.AUTO,
                                      pythoncdt.IntersectingConstraintEdges.NOT_ALLOWED, 0.0)
        cdt.insert_vertices(np.ascontiguousarray(xy))
        return cdt

    rows = inserted().triangles_array(copy=True)
    vertices, neighbours = np.ascontiguousarray(rows["vertices"]), np.ascontiguousarray(rows["neighbors"])
    tri, across = _ties.drop_super_triangle(vertices, neighbours, len(xy), np.arange(len(xy)))
    label = rng.permutation(len(xy))                 # the points renumbered on the way
    assert np.array_equal(_ties.drop_super_triangle(vertices, neighbours, len(xy), label)[0], label[tri])
    erased = inserted()
    erased.erase_super_triangle()
    want = erased.triangles_array(copy=True)
    want_across = want["neighbors"].astype(np.int64)[:, [1, 2, 0]]
    want_across[want_across == np.iinfo(np.uint32).max] = -1
    assert np.array_equal(tri, want["vertices"].astype(np.int64))
    assert np.array_equal(across, want_across)
    if kind == "collinear":
        assert len(tri) == 0
        return
    assert np.array_equal(np.unique(tri), np.arange(len(xy)))    # every point a corner
    bad = vertices.copy()
    bad[np.flatnonzero((bad >= 3).all(axis=1))[0], 1] = len(xy) + 3
    assert _ties.drop_super_triangle(bad, neighbours, len(xy), np.arange(len(xy))) is None


@pytest.mark.parametrize("kind", ["random", "thin", "one_x", "same"])
def test_cdts_insertion_order_is_the_points_by_cells_row_by_row(kind):
    """_ties.cell_order against a brute-force sort: each point's cell (side s from the box,
    at least the longer side's share), cells row by row, every other row backwards, ties in
    index order; on random points, a box thin in y, points on one x and one position."""
    from c1mesh.engine import _ties
    rng = np.random.default_rng(5)
    n, per = 5000, 16.0
    xy = {"random": rng.random((n, 2)) * [300, 70] - 40,
          "thin": np.c_[rng.random(n) * 1000, rng.random(n) * 1e-9],
          "one_x": np.c_[np.full(n, 2.0), rng.random(n)],
          "same": np.full((n, 2), 7.0)}[kind]
    order = _ties.cell_order(np.ascontiguousarray(xy), per)
    low, span = xy.min(axis=0), np.ptp(xy, axis=0)
    side = max(np.sqrt(span[0] * span[1] * per / n), span.max() * per / n)
    if side == 0:
        assert np.array_equal(order, np.arange(n))
        return
    nx, ny = (np.floor(span / side) + 1).astype(int)
    ix = np.minimum(((xy[:, 0] - low[0]) / side).astype(int), nx - 1)
    iy = np.minimum(((xy[:, 1] - low[1]) / side).astype(int), ny - 1)
    ix = np.where(iy % 2 == 1, nx - 1 - ix, ix)
    assert np.array_equal(order, np.lexsort((np.arange(n), iy * nx + ix)))
    assert nx * ny <= 3 * n / per + 1


def test_the_triangulation_does_not_depend_on_the_order_cdt_is_given_the_points():
    """delaunay (CDT given the points by cells) is the same set of triangles as CDT given
    them in the caller's order, both with their ties cut by canonical_ties, on a
    quantised shuffled grid with near-ties: the insertion order changes the rows' order
    only."""
    import pythoncdt

    from c1mesh.engine.triangulation import canonical_ties
    rng = np.random.default_rng(8)
    xy = np.round(rng.random((3000, 2)) * 40) / 2 + rng.integers(0, 2, (3000, 1)) * 1e-3
    xy = np.ascontiguousarray(xy[np.sort(np.unique(xy, axis=0, return_index=True)[1])])
    cdt = pythoncdt.Triangulation(pythoncdt.VertexInsertionOrder.AUTO,
                                  pythoncdt.IntersectingConstraintEdges.NOT_ALLOWED, 0.0)
    cdt.insert_vertices(xy)
    cdt.erase_super_triangle()
    rows = cdt.triangles_array(copy=True)
    across = rows["neighbors"].astype(np.int64)[:, [1, 2, 0]]
    across[across == np.iinfo(np.uint32).max] = -1
    given = canonical_ties(xy, rows["vertices"].astype(np.int64), across)[0]

    def faces(tri):
        return {tuple(np.roll(t, -int(np.argmin(t)))) for t in tri.tolist()}
    ours = delaunay(xy)
    assert faces(ours) == faces(given)
    assert not np.array_equal(ours, given)           # the rows' order did change
