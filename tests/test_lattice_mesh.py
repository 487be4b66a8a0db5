"""The lattice route's mesh (c1mesh.stages.lattice_mesh) against brute-force loops: the
kept cells of the support rule, the cells' triangles, the nearest points, and a tile's
window deciding its cells as the whole survey does."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from c1mesh.core.errors import InputError
from c1mesh.stages.lattice_mesh import (KEPT_BLOCK, MIN_BLOCK_POINTS, REACH_CELLS, SUPPORT_SPACINGS, cell_triangles,
                                        kept_cells, lattice_mesh, nearest_points, node_grid, support_reach)


def _clustered(seed: int, n: int = 400) -> np.ndarray:
    """Points in a few clusters and a sprinkle of lone points over 40 x 30 units: sparse
    cells, lone points (unsupported) and holes wider than the support's reach."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform([0, 0], [40, 30], (5, 2))
    clusters = centres[rng.integers(0, 5, n)] + rng.normal(0, 2.5, (n, 2))
    return np.concatenate([clusters, rng.uniform([0, 0], [40, 30], (12, 2))])


def _brute_kept(grid, xy) -> set:
    """The support rule cell by cell: supported = holds a point and its (2R+1)² block holds
    MIN_BLOCK_POINTS; kept = within R cells (Chebyshev) of a supported cell."""
    rows, cols = grid.cells
    i, j = grid.cell_of(xy)
    counts = {}
    for a, b in zip(i.tolist(), j.tolist()):
        counts[(a, b)] = counts.get((a, b), 0) + 1
    R = grid.reach
    supported = [c for c in counts if sum(counts.get((c[0] + di, c[1] + dj), 0)
                                          for di in range(-R, R + 1) for dj in range(-R, R + 1)) >= MIN_BLOCK_POINTS]
    kept = set()
    for a, b in supported:
        for di, dj in itertools.product(range(-R, R + 1), repeat=2):
            if 0 <= a + di < cols and 0 <= b + dj < rows:
                kept.add((b + dj) * cols + a + di)
    return kept


@pytest.mark.parametrize("seed, h", [(0, 0.6), (1, 0.6), (2, 1.2)])
def test_kept_cells_are_the_support_rule(seed, h):
    xy = _clustered(seed)
    grid = node_grid(xy.min(axis=0), xy.max(axis=0), 1.3, h)
    assert grid.reach == max(2, int(np.ceil(SUPPORT_SPACINGS * h / 1.3)))
    kept = kept_cells(grid, xy)
    assert kept.tolist() == sorted(_brute_kept(grid, xy))
    assert len(kept) and (np.diff(kept) > 0).all()


@pytest.mark.parametrize("seed", [0, 3])
def test_a_window_decides_its_cells_as_the_whole_grid_does(seed):
    """A tile's window, with only the points within 2R cells of it, keeps exactly the cells
    of the window that the whole survey keeps."""
    xy = _clustered(seed)
    grid = node_grid(xy.min(axis=0), xy.max(axis=0), 1.0, 0.7)
    R = grid.reach
    whole = set(kept_cells(grid, xy).tolist())
    rows, cols = grid.cells
    for i0, j0 in [(0, 0), (7, 5), (cols - 9, rows - 6), (13, 11)]:
        window = (i0, i0 + 9, j0, j0 + 6)
        i, j = grid.cell_of(xy)
        near = (i >= i0 - 2 * R) & (i < i0 + 9 + 2 * R) & (j >= j0 - 2 * R) & (j < j0 + 6 + 2 * R)
        mine = {c for c in whole if i0 <= c % cols < i0 + 9 and j0 <= c // cols < j0 + 6}
        assert set(kept_cells(grid, xy[near], window).tolist()) == mine


def test_every_data_point_of_a_supported_cell_lies_in_the_mesh_and_nodes_sit_on_the_lattice():
    xy = _clustered(4)
    mesh = lattice_mesh(xy, 1.5, 0.5)
    D = 1.5
    np.testing.assert_array_equal(mesh.points / D, np.round(mesh.points / D))
    corners = mesh.points[mesh.triangles[mesh.shown]]
    a, b = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    np.testing.assert_allclose((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]) / 2, D * D / 2)      # counter-clockwise
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    inside = np.zeros(len(xy), bool)
    for k, p in enumerate(xy):
        inside[k] = ((lo <= p) & (p <= hi)).all(axis=1).any()
    grid = mesh.grid
    i, j = grid.cell_of(xy)
    held = np.isin(j * grid.cells[1] + i, kept_cells(grid, xy))
    np.testing.assert_array_equal(inside, held)           # a point is in the mesh iff its cell is kept
    assert (~held).sum() > 0                                # lone points stay out


def test_the_shown_mesh_is_the_shown_triangles_on_the_nodes_they_use():
    """shown_mesh: ascending rows of the nodes some shown triangle uses, and the shown
    triangles renumbered into them (the same corners, checked by position)."""
    mesh = lattice_mesh(_clustered(5), 1.5, 0.5)
    used, triangles = mesh.shown_mesh()
    shown = mesh.triangles[mesh.shown]
    assert 0 < mesh.shown.sum() < mesh.shown.size                          # the blocks add hidden cells
    assert used.tolist() == sorted({int(v) for v in shown.ravel()})
    np.testing.assert_array_equal(mesh.points[used][triangles], mesh.points[shown])


def test_cell_triangles_split_every_cell_by_the_same_diagonal():
    grid = node_grid([0.0, 0.0], [2.5, 1.5], 1.0, 0.5)
    nx = grid.shape[1]
    tri = cell_triangles(grid, np.array([0, 4]))
    a = 0
    assert tri[:2].tolist() == [[a, a + 1, a + nx + 1], [a, a + nx + 1, a + nx]]
    j, i = divmod(4, nx - 1)
    a = j * nx + i
    assert tri[2:].tolist() == [[a, a + 1, a + nx + 1], [a, a + nx + 1, a + nx]]


def test_nearest_points_take_the_lowest_index_on_ties():
    xy = np.array([[0.0, 0.0], [2.0, 0.0], [1.0, 1.0], [1.0, -1.0]])
    index = np.array([40, 7, 9, 30])
    positions = np.array([[1.0, 0.0], [0.1, 0.0], [5.0, 5.0]])
    # (1, 0) is 1 from all four: the lowest index, 7; (0.1, 0) is nearest (0, 0); (5, 5) nearest (1, 1)
    assert nearest_points(positions, xy, index).tolist() == [7, 40, 9]
    rng = np.random.default_rng(5)
    xy, q = rng.uniform(0, 10, (300, 2)), rng.uniform(0, 10, (50, 2))
    index = rng.permutation(1000)[:300]
    d = np.linalg.norm(q[:, None] - xy[None], axis=2)
    np.testing.assert_array_equal(nearest_points(q, xy, index), index[d.argmin(axis=1)])


def _clusters_and_strips(kind: str, rng) -> np.ndarray:
    """Points whose buckets are mostly empty or degenerate: two far clusters, a line, one
    repeated point, a thin strip."""
    if kind == "clusters":
        return np.concatenate([rng.normal(0, 0.5, (150, 2)), rng.normal(60, 0.5, (150, 2))])
    if kind == "line":
        return np.column_stack([rng.uniform(0, 50, 200), np.full(200, 3.0)])
    if kind == "one":
        return np.tile([[2.0, -1.0]], (20, 1))
    return np.column_stack([rng.uniform(0, 1000, 400), rng.uniform(0, 0.01, 400)])


@pytest.mark.parametrize("kind", ["clusters", "line", "one", "strip"])
def test_nearest_points_by_buckets_are_the_brute_force_nearest(monkeypatch, kind):
    """The bucket search finds the brute-force nearest (lowest index on ties) for positions
    inside, between and far outside the points, block by block in any thread count."""
    from c1mesh.core.threads import limit
    from c1mesh.stages import lattice_mesh as module
    monkeypatch.setattr(module, "NEAREST_BLOCK", 7)
    rng = np.random.default_rng(11)
    xy = _clusters_and_strips(kind, rng)
    lo, hi = xy.min(axis=0) - 200, xy.max(axis=0) + 200
    q = np.concatenate([rng.uniform(lo, hi, (60, 2)), xy[:10] + 1e-3, [[1e6, -1e6], [-3e5, 40.0]]])
    index = rng.permutation(5 * xy.shape[0])[:xy.shape[0]]
    d2 = ((q[:, None] - xy[None]) ** 2).sum(axis=2)
    want = [index[d2[k] == d2[k].min()].min() for k in range(len(q))]
    for threads in (1, 2):
        with limit(threads):
            assert nearest_points(q, xy, index).tolist() == want


def test_a_far_outlier_does_not_crowd_the_buckets_of_nearest_points():
    """One point far off a dense square widens the box: the buckets still hold about
    NEAREST_BUCKET_POINTS each where the points are (the side halves), and the nearest
    points are brute force's, near the square and near the outlier."""
    from c1mesh.stages import lattice_mesh as module
    rng = np.random.default_rng(12)
    xy = np.concatenate([rng.uniform(0, 10, (300, 2)), [[1e3, 1e3]]])       # within the table's bound
    lower = xy.min(axis=0)
    size, cols, rows, ci, cj = module._buckets(xy, lower, xy.max(axis=0) - lower)
    occupied = np.unique(cj * cols + ci).size
    assert xy.shape[0] <= 2 * module.NEAREST_BUCKET_POINTS * occupied
    q = np.concatenate([rng.uniform(-5, 15, (80, 2)), [[1e3 + 3, 1e3 - 2], [5e2, 5e2]]])
    index = np.arange(xy.shape[0]) + 7
    d2 = ((q[:, None] - xy[None]) ** 2).sum(axis=2)
    assert nearest_points(q, xy, index).tolist() == [index[d2[k] == d2[k].min()].min() for k in range(len(q))]


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_a_bad_spacing_is_an_input_error(bad):
    with pytest.raises(InputError, match="--spacing"):
        node_grid([0, 0], [1, 1], bad, 1.0)


def test_the_reach_is_whole_cells_of_the_point_spacing_within_its_bounds():
    assert support_reach(1.0, 1.0) == int(np.ceil(SUPPORT_SPACINGS))
    assert support_reach(2.0, 1.9) == int(np.ceil(SUPPORT_SPACINGS * 1.9 / 2.0))
    assert support_reach(100.0, 1.0) == REACH_CELLS[0]          # a coarse lattice: at least 2 cells
    assert support_reach(0.01, 1.0) == REACH_CELLS[1]           # a fine one: at most 8


@pytest.mark.parametrize("marked", [True, False])
def test_numbered_triangles_are_the_sorted_corners(monkeypatch, marked):
    """Both ways of numbering the nodes (a table over their span, or a sort beyond
    MARKED_NODES) give np.unique's numbers."""
    from c1mesh.stages import lattice_mesh
    if not marked:
        monkeypatch.setattr(lattice_mesh, "MARKED_NODES", 0)
    xy = _clustered(6)
    grid = node_grid(xy.min(axis=0), xy.max(axis=0), 1.1, 0.6)
    cells = kept_cells(grid, xy)
    nodes, triangles = lattice_mesh.numbered_triangles(grid, cells)
    want, local = np.unique(cell_triangles(grid, cells), return_inverse=True)
    np.testing.assert_array_equal(nodes, want)
    np.testing.assert_array_equal(triangles, local.reshape(-1, 3))


def test_nearest_points_on_a_grid_of_ties_take_the_lowest_index():
    """Nodes halfway between grid points are equally near 2 or 4 of them: the lowest index
    wins, whatever the points' order."""
    i, j = np.meshgrid(np.arange(6.0), np.arange(5.0))
    xy = np.column_stack([i.ravel(), j.ravel()])
    rng = np.random.default_rng(7)
    index = rng.permutation(xy.shape[0]) + 100
    q = np.column_stack([rng.integers(0, 10, 40) / 2, rng.integers(0, 8, 40) / 2])
    d = np.round(np.linalg.norm(q[:, None] - xy[None], axis=2), 12)
    want = [index[d[k] == d[k].min()].min() for k in range(len(q))]
    assert nearest_points(q, xy, index).tolist() == want


def test_a_survey_decided_in_bands_of_rows_keeps_the_whole_grids_cells(monkeypatch):
    """lattice_mesh decides a box of more than BAND_CELLS cells band by band: the same mesh."""
    from c1mesh.stages import lattice_mesh as module
    xy = _clustered(8)
    whole = lattice_mesh(xy, 0.9, 0.5)
    monkeypatch.setattr(module, "BAND_CELLS", 200)          # bands of a few rows
    banded = lattice_mesh(xy, 0.9, 0.5)
    np.testing.assert_array_equal(banded.nodes, whole.nodes)
    np.testing.assert_array_equal(banded.triangles, whole.triangles)


@pytest.mark.parametrize("seed", [0, 9])
def test_the_solve_keeps_every_aligned_block_that_holds_a_support_cell(seed):
    """kept_cells(blocks=True): the KEPT_BLOCK x KEPT_BLOCK blocks of cells aligned at node
    (0, 0) that hold a cell of the support, each whole (brute force over the support's
    cells); a window decides its blocks as the whole grid does; lattice_mesh solves on them
    and shows the support's triangles."""
    xy = _clustered(seed)
    grid = node_grid(xy.min(axis=0), xy.max(axis=0), 0.8, 0.5)
    rows, cols = grid.cells
    support = kept_cells(grid, xy)
    blocks = {(c % cols // KEPT_BLOCK, c // cols // KEPT_BLOCK) for c in support.tolist()}
    want = sorted(j * cols + i for bi, bj in blocks
                  for j in range(bj * KEPT_BLOCK, (bj + 1) * KEPT_BLOCK)
                  for i in range(bi * KEPT_BLOCK, (bi + 1) * KEPT_BLOCK) if i < cols and j < rows)
    solve = kept_cells(grid, xy, blocks=True)
    assert solve.tolist() == want and len(solve) > len(support)
    window = (5, 31, 3, 20)
    mine = [c for c in want if 5 <= c % cols < 31 and 3 <= c // cols < 20]
    assert kept_cells(grid, xy, window, blocks=True).tolist() == mine
    mesh = lattice_mesh(xy, 0.8, 0.5)
    np.testing.assert_array_equal(mesh.shown, np.repeat(np.isin(solve, support), 2))
