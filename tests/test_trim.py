"""The trim's rules (slivers, bow-ties) as tile functions and their loop (c1mesh.stages.trim),
against a brute-force trim written from the rules' definitions in plain Python: on one tile
(the in-memory trim, trim_mesh, retrim) and on many (a TrimRun over a grid of cells)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from c1mesh.engine.triangulation import delaunay
from c1mesh.stages.curtains import curtain_triangles, point_rows, remove_curtain_run
from c1mesh.stages import trim as trim_stage
from c1mesh.stages.trim import (Cuts, Place, TrimTile, circle_ratio, retrim, retrim_run, trim, trim_mesh,
                                trim_run)


def _ratio(xy, t):
    """2 r_in / R_circ of triangle t, from its area (a cross product): 16 A^2 / (P abc)."""
    (ax, ay), (bx, by), (cx, cy) = (xy[v] for v in t)
    sides = [math.hypot(bx - cx, by - cy), math.hypot(cx - ax, cy - ay), math.hypot(ax - bx, ay - by)]
    area = abs((bx - ax) * (cy - ay) - (by - ay) * (cx - ax)) / 2
    product = sides[0] * sides[1] * sides[2]
    return 0.0 if product == 0 else 16 * area ** 2 / (sum(sides) * product)


def _edges(t):
    return [frozenset((t[0], t[1])), frozenset((t[1], t[2])), frozenset((t[2], t[0]))]


def _brute_settle(tri, alive, thin):
    """trim's definition, round by round on sets: peel live thin triangles with an edge no
    other live triangle has until none is left; then at every vertex where the live
    triangles form more than one fan (joined through edges at the vertex), keep the
    largest (ties: the fan holding the least sorted corner triple), all vertices decided
    on the same mesh; repeat until no fan is cut. alive: set of triangle indices, changed
    in place. Returns (slivers, bow-tie triangles) removed, and the slivers peeled after a
    bow-tie cut."""
    sliver = bowtie = 0
    later = None
    while True:
        while True:
            count = {}
            for t in alive:
                for e in _edges(tri[t]):
                    count[e] = count.get(e, 0) + 1
            gone = {t for t in alive if thin[t] and any(count[e] == 1 for e in _edges(tri[t]))}
            if not gone:
                break
            alive -= gone
            sliver += len(gone)
        around = {}
        for t in alive:
            for v in tri[t]:
                around.setdefault(v, []).append(t)
        cut = set()
        for v, ts in around.items():
            fans, left = [], set(ts)
            while left:
                fan, stack = set(), [left.pop()]
                while stack:
                    t = stack.pop()
                    fan.add(t)
                    for u in list(left):
                        if len(set(tri[t]) & set(tri[u])) == 2:        # an edge, and v is on it
                            left.discard(u)
                            stack.append(u)
                fans.append(fan)
            if len(fans) > 1:
                best = min(fans, key=lambda f: (-len(f), min(tuple(sorted(tri[t])) for t in f)))
                cut |= set().union(*(f for f in fans if f is not best))
        if not cut:
            return sliver, bowtie, 0 if later is None else sliver - later
        later = sliver if later is None else later
        alive -= cut
        bowtie += len(cut)


def _brute_trim(xy, tri, max_edge, min_ratio):
    """(kept (T,) bool, removed counts) of trim by its definition."""
    tri = [tuple(t) for t in tri.tolist()]
    pts = [tuple(p) for p in xy.tolist()]
    longest = [max(math.hypot(pts[a][0] - pts[b][0], pts[a][1] - pts[b][1]) for a, b in ((t[0], t[1]), (t[1], t[2]),
                                                                                      (t[2], t[0]))) for t in tri]
    alive = {t for t in range(len(tri)) if max_edge is None or longest[t] <= max_edge}
    thin = [_ratio(pts, t) < min_ratio for t in tri]
    ambiguous = [abs(_ratio(pts, t) - min_ratio) < 1e-9 * min_ratio for t in tri]
    assert not any(ambiguous)                  # rounding cannot decide a sliver here
    long_edge = len(tri) - len(alive)
    sliver, bowtie, later = _brute_settle(tri, alive, thin)
    kept = np.zeros(len(tri), dtype=bool)
    kept[list(alive)] = True
    return kept, {"long_edge": long_edge, "sliver": sliver, "bowtie": bowtie}, later


def _mesh(seed):
    """Random points with near-collinear runs (hull slivers), a max_edge that cuts holes
    (bow-ties where holes meet) and a min_circle_ratio up to 0.55, at which many
    triangles are thin (the rules do not rely on thin triangles being rare):
    (xy, triangles, max_edge, min_ratio)."""
    rng = np.random.default_rng(seed)
    xy = rng.random((200, 2))
    xy[:25, 1] = 0.3 + 1e-4 * rng.random(25)
    xy[25:40, 0] = 0.97 + 2e-4 * rng.random(15)
    tri = delaunay(xy)
    lengths = trim_stage.edge_lengths(xy, tri).max(axis=1)
    return xy, tri, float(np.quantile(lengths, (0.6, 0.7, 0.8, 0.9, 0.97)[seed % 5])), (0.01, 0.3, 0.45, 0.55)[seed % 4]


SEEDS = range(20)


@pytest.mark.parametrize("seed", SEEDS)
def test_trim_is_the_brute_force_trim(seed):
    xy, tri, max_edge, min_ratio = _mesh(seed)
    kept, removed, _ = _brute_trim(xy, tri, max_edge, min_ratio)
    ours, report = trim(xy, tri, max_edge=max_edge, min_circle_ratio=min_ratio)
    assert np.array_equal(ours, tri[kept]) and report.removed == removed
    mesh, mesh_report = trim_mesh(xy, tri, max_edge=max_edge, min_circle_ratio=min_ratio)
    assert np.array_equal(mesh.alive, kept) and mesh_report == report


def test_the_brute_force_cases_exercise_every_rule():
    """Hundreds of long-edge, sliver and bow-tie triangles, and slivers that only a bow-tie
    cut exposes (a second round of the loop)."""
    totals = {"long_edge": 0, "sliver": 0, "bowtie": 0}
    again = 0
    for seed in SEEDS:
        _, removed, later = _brute_trim(*_mesh(seed))
        totals = {k: totals[k] + removed[k] for k in totals}
        again += later > 0
    assert min(totals.values()) > 100 and again >= 3


@pytest.mark.parametrize("seed", SEEDS)
def test_retrim_is_the_brute_force_trim_of_what_the_holes_left(seed):
    xy, tri, max_edge, min_ratio = _mesh(seed)
    mesh, _ = trim_mesh(xy, tri, max_edge=max_edge, min_circle_ratio=min_ratio)
    rng = np.random.default_rng(100 + seed)
    drop = np.flatnonzero(mesh.alive)[rng.random(int(mesh.alive.sum())) < 0.1]
    after, counts = retrim(mesh, drop, min_ratio)
    alive = set(np.flatnonzero(mesh.alive).tolist()) - set(drop.tolist())
    triangles = [tuple(t) for t in tri.tolist()]
    sliver, bowtie, _ = _brute_settle(triangles, alive, [_ratio(xy.tolist(), t) < min_ratio for t in triangles])
    assert set(np.flatnonzero(after.alive).tolist()) == alive
    assert counts == {"long_edge": 0, "sliver": sliver, "bowtie": bowtie}


class _Cells:
    """A TrimRun over side x side cells of a mesh held in memory: each step reads its
    tile afresh (the live triangles over the vertices they use, renumbered in ascending
    order, as a halo's rows are), owning the vertices in its cell; removed triangles are
    found by their corners."""

    def __init__(self, xy, tri, alive, side):
        self.xy, self.tri, self.alive, self.side = xy, tri, alive, side
        cell = np.minimum((xy * side).astype(np.int64), side - 1)
        self.home = cell[:, 0] + side * cell[:, 1]
        self.row = {tuple(sorted(t)): i for i, t in enumerate(tri.tolist())}
        self.steps = []

    def map(self, step, tiles=None):
        chosen = range(self.side ** 2) if tiles is None else sorted(tiles)
        self.steps.append(len(chosen))
        return [step(self.tile(t)) for t in chosen]

    def tile(self, t):
        live = self.tri[self.alive]
        used = np.unique(live)
        local = np.searchsorted(used, live)
        return TrimTile(local, np.ones(len(local), dtype=bool), len(used), self.xy[used],
                        Place(used, self.home[used], t))

    def remove(self, cuts):
        for corners in cuts.corners.tolist():
            self.alive[self.row[tuple(sorted(corners))]] = False


@pytest.mark.parametrize("side", [1, 3, 5])
def test_the_trim_over_tiles_is_the_brute_force_trim(side):
    """trim_run and retrim_run over a grid of cells (each thin triangle listed by the
    cell of its lowest corner, each bow-tie decided by its vertex's cell) remove what the
    brute force does; later bow-tie rounds look at the cells of the removed corners only."""
    fewer = 0
    for seed in SEEDS:
        xy, tri, max_edge, min_ratio = _mesh(seed)
        kept, removed, _ = _brute_trim(xy, tri, max_edge, min_ratio)
        alive = trim_stage.edge_lengths(xy, tri).max(axis=1) <= max_edge
        run = _Cells(xy, tri, alive, side)
        thin, counts = trim_run(run, min_ratio)
        assert np.array_equal(run.alive, kept) and counts == {k: removed[k] for k in ("sliver", "bowtie")}
        assert len(np.unique(np.sort(thin.triangles.corners, axis=1), axis=0)) == len(thin.alive)
        fewer += min(run.steps) < side ** 2
        cut = np.flatnonzero(run.alive)[np.random.default_rng(seed).random(int(run.alive.sum())) < 0.1]
        triangles = [tuple(t) for t in tri.tolist()]
        expected = set(np.flatnonzero(run.alive).tolist()) - set(cut.tolist())
        sliver, bowtie, _ = _brute_settle(triangles, expected, [_ratio(xy.tolist(), t) < min_ratio
                                                                for t in triangles])
        cuts = Cuts(tri[cut], run.home[tri[cut]], cut)
        assert retrim_run(run, cuts, min_ratio, thin) == {"sliver": sliver, "bowtie": bowtie}
        assert set(np.flatnonzero(run.alive).tolist()) == expected
    assert side == 1 or fewer > 10


class _RowCells(_Cells):
    """_Cells whose tiles carry the point rows (x, y, z, gx, gy) the curtain rule reads."""

    def __init__(self, rows, tri, alive, side):
        super().__init__(rows[:, :2], tri, alive, side)
        self.rows = rows

    def tile(self, t):
        tile = super().tile(t)
        return TrimTile(tile.source, tile.alive, tile.size, self.rows[tile.place.numbers], tile.place)


@pytest.mark.parametrize("side", [1, 3])
def test_the_curtains_over_tiles_and_their_retrim_are_the_brute_force_trim(side):
    """remove_curtain_run over a grid of cells (each cell finds the curtains it holds, and
    the bow-ties their cut leaves before the peel) removes the trimmed mesh's triangles
    that curtain_triangles marks, then what the brute-force loop removes from the holes."""
    exercised = 0
    for seed in SEEDS:
        xy, tri, max_edge, min_ratio = _mesh(seed)
        kept, _, _ = _brute_trim(xy, tri, max_edge, min_ratio)
        rng = np.random.default_rng(300 + seed)
        z, gradients = 0.02 * rng.random(len(xy)), 0.1 * rng.normal(size=(len(xy), 2))
        lengths = trim_stage.edge_lengths(xy, tri)
        a, b, c = (xy[tri[:, k]] for k in range(3))
        u, v = b - a, c - a
        widths = np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]) / lengths.max(axis=1)
        floor = float(np.quantile(widths[kept], 0.1))
        masks = curtain_triangles(xy, z, gradients, tri, floor=floor)
        curtains = kept & np.logical_or.reduce(list(masks.values()))
        expected = set(np.flatnonzero(kept & ~curtains).tolist())
        triangles = [tuple(t) for t in tri.tolist()]
        thin = [_ratio(xy.tolist(), t) < min_ratio for t in triangles]
        sliver, bowtie, _ = _brute_settle(triangles, expected, thin)
        run = _RowCells(point_rows(xy, z, gradients), tri, kept.copy(), side)
        counts, cleanup = remove_curtain_run(run, floor, True, None, min_ratio)
        assert sum(counts.values()) == int(curtains.sum())
        assert cleanup == {"sliver": sliver, "bowtie": bowtie}
        assert set(np.flatnonzero(run.alive).tolist()) == expected
        exercised += bowtie > 0
    assert exercised >= 3


def _numpy_circle_ratio(lengths):
    """circle_ratio as numpy expressions: (p-2a)(p-2b)(p-2c) / (abc), clipped, NaN as 0."""
    a, b, c = lengths[:, 0], lengths[:, 1], lengths[:, 2]
    p = a + b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (p - 2 * a) * (p - 2 * b) * (p - 2 * c) / (a * b * c)
    return np.nan_to_num(np.clip(ratio, 0.0, 1.0), nan=0.0)


def test_circle_ratio_and_thin_rows_are_the_numpy_expression_to_the_bit():
    rng = np.random.default_rng(3)
    xy = rng.random((3000, 2))
    xy[:500, 1] = 0.5 + 1e-6 * rng.random(500)
    tri = delaunay(xy)
    lengths = np.vstack([trim_stage.edge_lengths(xy, tri),
                         [[0, 0, 0], [0, 1, 1], [1, 1, 2], [1, 1, 3], [np.inf, 1, 1], [1e-300, 1e-300, 1e-300]]])
    want = _numpy_circle_ratio(lengths)
    assert np.array_equal(circle_ratio(lengths), want)
    alive = rng.random(len(lengths)) < 0.7
    for min_ratio in (0.0, 0.01, 0.3, 1.0):
        rows = trim_stage._thin_rows(lengths, alive, min_ratio)
        assert np.array_equal(rows, np.flatnonzero(alive & (want < min_ratio)))
    assert 50 < len(trim_stage._thin_rows(lengths, alive, 0.01)) < len(lengths) // 10


def test_thin_rows_from_coordinates_are_the_numpy_expression_of_hypots_lengths():
    """trim._thin_rows_at (sqrt lengths screen, hypot's decide) picks the rows the numpy
    circle ratio of numpy's hypot lengths puts below min_ratio: over a Delaunay mesh with a
    band of near-collinear points, needles with a side a thousandth, a millionth and 1e-9
    of another (beside the screen's 1e-6), repeated corners, state-plane-sized
    coordinates, and min_ratio from 0 to 1 (the screen off below 1e-6)."""
    rng = np.random.default_rng(5)
    xy = rng.random((3000, 2))
    xy[:500, 1] = 0.5 + 1e-6 * rng.random(500)
    tri = delaunay(xy)
    extra = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 1e-3], [0.5, 1e-6], [0.5, 1e-9], [0.5, 2e-2],
                      [0.5, 5e-3]])
    xy = np.vstack([xy, extra])
    base = len(xy) - len(extra)
    needles = np.array([[base, base + 1, base + j] for j in range(2, len(extra))]
                       + [[base, base, base + 1], [base + 2, base + 3, base + 4]])
    tri = np.vstack([tri, needles])
    for shift in (0.0, 2.0e6):
        points = xy * 40.0 + shift
        hypots = np.column_stack([np.hypot(*(points[tri[:, (k + 2) % 3]] - points[tri[:, (k + 1) % 3]]).T)
                                  for k in range(3)])
        want = _numpy_circle_ratio(hypots)
        alive = rng.random(len(tri)) < 0.8
        alive[-len(needles):] = True
        for min_ratio in (0.0, 1e-7, 1e-3, 0.01, 0.0101, 0.3, 1.0):
            rows = trim_stage._thin_rows_at(points, tri, alive, min_ratio)
            assert np.array_equal(rows, np.flatnonzero(alive & (want < min_ratio))), (shift, min_ratio)
        assert len(trim_stage._thin_rows_at(points, tri, alive, 0.01)) > 50


@pytest.mark.parametrize("n, m", [(1, 0), (7, 0), (50, 30), (400, 380), (1000, 3000)])
def test_connected_sets_number_the_sets_as_scipys_connected_components(n, m):
    """trim.connected_sets (a union-find kernel) against scipy's connected_components of
    the same undirected pairs, labels and all: isolated items, chains, self-pairs, repeats."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from c1mesh.stages.trim import connected_sets
    rng = np.random.default_rng(n + m)
    a, b = rng.integers(0, n, m), rng.integers(0, n, m)
    graph = coo_matrix((np.ones(m, dtype=np.int8), (a, b)), shape=(n, n))
    assert np.array_equal(connected_sets(n, a, b), connected_components(graph, directed=False)[1])


@pytest.mark.parametrize("numbering", ["survey", "ascending rows", "shuffled rows"])
def test_kept_triangles_against_a_set_of_corner_sets(numbering):
    """trim.kept_triangles against Python sets: a triangle goes when its corners, as a set,
    are a removed row's, whatever the corners' order in either; removed rows that are no
    triangle here change nothing. The triangles as survey numbers, or as rows into numbers
    that ascend (a halo's: the kernel first marks the removed corners' rows) or do not."""
    rng = np.random.default_rng(11)
    xy = rng.random((400, 2))
    triangles = delaunay(xy)
    survey = np.sort(rng.choice(10_000, size=len(xy), replace=False))      # the points' survey numbers
    if numbering == "shuffled rows":
        survey = rng.permutation(survey)
    gone = rng.choice(len(triangles), size=40, replace=False)
    removed = survey[triangles[gone]]
    removed = np.array([rng.permutation(row) for row in removed])              # any corner order
    removed = np.vstack([removed, [[10_001, 10_002, 10_003]], survey[[[0, 1, 2]]]])   # no triangles
    if numbering == "survey":
        kept = trim_stage.kept_triangles(survey[triangles], removed)
    else:
        kept = trim_stage.kept_triangles(triangles, removed, survey)
    sets = {frozenset(row) for row in removed.tolist()}
    expected = [frozenset(row) not in sets for row in survey[triangles].tolist()]
    assert kept.tolist() == expected
    assert (~kept).sum() >= 40
