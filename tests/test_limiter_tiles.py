"""The limiter as a stage of tiles (c1mesh.stages.limiter: floor_summary, reduce_floor,
tile_limits) on a small noisy mesh cut into 2 to 4 tiles by hand, against the one tile
of the in-memory fit and against a plain Python loop over the edges.

A tile here is built from the mesh's graph, not by the survey's machinery: its own
vertices (a strip of x), and every vertex within HALO_RINGS edges of them with the
triangles whose corners all are among those, which holds the star of every vertex within
3 rings of the own ones (what the limiter's reconciliations read).
"""
import numpy as np
import pytest

from c1mesh.core.tile import VERTEX, Tile
from c1mesh.engine.topology import edge_table
from c1mesh.engine.triangulation import delaunay
from c1mesh.stages.curtains import noise_floor
from c1mesh.stages.limiter import (NoiseFloors, control_overshoot, floor_summary, floor_summary_after,
                                   reconcile_gradients, reconcile_heights, reconciled_summary, reduce_floor,
                                   tile_limits)

HALO_RINGS = 4


@pytest.fixture(params=[0, 1])
def noisy(request):
    """(xy, z, gradients, triangles): 400 random points with noisy heights and gradients,
    plus near-coincident pairs whose heights reconcile_heights moves."""
    rng = np.random.default_rng(70 + request.param)
    xy = rng.random((400, 2))
    xy = np.vstack([xy, xy[:5] + [1e-3, 0.0]])
    z = np.sin(3 * xy[:, 0]) * xy[:, 1] + 0.02 * rng.standard_normal(len(xy))
    g = np.column_stack([3 * np.cos(3 * xy[:, 0]) * xy[:, 1], np.sin(3 * xy[:, 0])])
    g += 0.3 * rng.standard_normal(g.shape)
    return xy, z, g, delaunay(xy)


def _loop_median(xy, z, g, triangles) -> float:
    """The median |trapezoid residual| over every edge once, in Python floats: each edge
    a→b from its lower number, e = (z_b − z_a) − ½ (g_a·d + g_b·d), d = xy_b − xy_a;
    the middle value of the sorted list, or the mean of the two middle ones."""
    edges = sorted({tuple(sorted((int(t[i]), int(t[(i + 1) % 3])))) for t in triangles.tolist() for i in range(3)})
    sizes = []
    for a, b in edges:
        dx, dy = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]
        sizes.append(abs((z[b] - z[a]) - 0.5 * ((g[a, 0] * dx + g[a, 1] * dy) + (g[b, 0] * dx + g[b, 1] * dy))))
    sizes.sort()
    half = len(sizes) // 2
    return sizes[half] if len(sizes) % 2 else (sizes[half - 1] + sizes[half]) / 2


def _tiles(xy, z, g, triangles, count):
    """count (Tile, owned triangles (k, 3) survey numbers): strips of x own the vertices
    (each vertex in one); each tile holds the vertices within HALO_RINGS edges of its own
    ones and the triangles among those, and owns those whose lowest corner it owns."""
    n = len(xy)
    strip = np.minimum((xy[:, 0] * count).astype(int), count - 1)
    edges = edge_table(triangles, n).edges
    tiles = []
    for k in range(count):
        held = strip == k
        for _ in range(HALO_RINGS):
            grown = held.copy()
            grown[edges[held[edges[:, 0]], 1]] = True
            grown[edges[held[edges[:, 1]], 0]] = True
            held = grown
        rows = np.flatnonzero(held)                      # ascending survey numbers
        local = np.full(n, -1)
        local[rows] = np.arange(len(rows))
        inside = held[triangles].all(axis=1)
        records = np.empty(len(rows), VERTEX)
        records["index"], records["x"], records["y"], records["z"] = rows, xy[rows, 0], xy[rows, 1], z[rows]
        records["gx"], records["gy"] = g[rows, 0], g[rows, 1]
        owned = triangles[inside & (strip[triangles.min(axis=1)] == k)]      # lowest corner own
        tiles.append((Tile(records, local[triangles[inside]], strip[rows] == k), owned))
    return tiles


@pytest.mark.parametrize("count", [2, 3, 4])
def test_floors_over_tiles_are_the_one_tiles_and_the_loops(noisy, count):
    xy, z, g, triangles = noisy
    one = Tile.whole(xy, z, g, triangles)
    first = reduce_floor(lambda: (floor_summary(one),))
    assert first == _loop_median(xy, z, g, triangles)                     # bits
    assert noise_floor(xy, z, g, triangles) == first                      # the curtains' floor
    table = edge_table(triangles, len(xy))
    heights, lifted = reconcile_heights(xy, z, g, triangles, table, noise_floor=first)
    reconciled, moved = reconcile_gradients(xy, heights, g, table.edges, noise_floor=first)
    assert lifted.any() and moved.any()
    second = reduce_floor(lambda: (floor_summary(one, first),))
    assert second == _loop_median(xy, heights, reconciled, triangles)

    tiles = _tiles(xy, z, g, triangles, count)
    owners = np.zeros(len(xy), dtype=int)
    for tile, _ in tiles:
        owners[tile.records["index"][tile.own]] += 1
    assert (owners == 1).all()                                            # the own masks partition
    summaries = [floor_summary(tile) for tile, _ in tiles]
    assert sum(len(s) for s in summaries) == len(table.edges)             # each edge in one tile
    assert reduce_floor(lambda: iter(summaries)) == first
    summaries = [floor_summary(tile, first) for tile, _ in tiles]
    assert reduce_floor(lambda: iter(summaries)) == second


def _loop_sizes(tile: Tile) -> list[float]:
    """The |trapezoid residuals| of the tile's own edges (lower end own), sorted, by a
    Python loop over its triangles' sides."""
    r = tile.records
    edges = {tuple(sorted((int(t[i]), int(t[(i + 1) % 3])))) for t in tile.triangles.tolist() for i in range(3)}
    sizes = []
    for a, b in edges:
        if not tile.own[a]:
            continue
        dx, dy = r["x"][b] - r["x"][a], r["y"][b] - r["y"][a]
        sizes.append(abs((r["z"][b] - r["z"][a]) - 0.5 * ((r["gx"][a] * dx + r["gy"][a] * dy)
                                                          + (r["gx"][b] * dx + r["gy"][b] * dy))))
    return sorted(sizes)


@pytest.mark.parametrize("count", [1, 3])
def test_the_summary_after_a_removal_is_the_summary_of_the_triangles_left(noisy, count):
    """floor_summary_after: a tile's summary taken before some triangles were removed,
    without the edges only they held, has the values of the summary of the triangles
    left, each as often, against a Python loop over their sides. The removed triangles:
    every fifth (interior edges keep their other triangle, so only some of their edges
    go), and a fan around one vertex (every edge to it goes, one twice)."""
    xy, z, g, triangles = noisy
    for tile, _ in _tiles(xy, z, g, triangles, count):
        k = len(tile.triangles)
        centre = tile.triangles[k // 2, 0]
        removed = (np.arange(k) % 5 == 0) | (tile.triangles == centre).any(axis=1)
        earlier = floor_summary(tile)
        after = Tile(tile.records, tile.triangles[~removed], tile.own)
        taken = floor_summary_after(after, earlier, tile.triangles[removed])
        assert len(taken) < len(earlier)
        assert np.sort(taken).tolist() == _loop_sizes(after)
        assert np.array_equal(np.sort(taken), np.sort(floor_summary(after)))


def test_the_summary_after_a_removal_drops_one_of_equal_sizes():
    """On a flat plane with zero gradients every residual is 0.0: the removed edges take
    as many zeros away as they were, no more."""
    xy = np.array([[0, 0], [1, 0], [0, 1], [1, 1], [2, 0], [2, 1]], dtype=float)
    triangles = np.array([[0, 1, 2], [1, 3, 2], [1, 4, 3], [4, 5, 3]])
    tile = Tile.whole(xy, np.zeros(6), np.zeros((6, 2)), triangles)
    earlier = floor_summary(tile)
    assert earlier.tolist() == [0.0] * 9
    after = Tile(tile.records, triangles[:3], tile.own)
    assert floor_summary_after(after, earlier, triangles[3:]).tolist() == [0.0] * 7     # (4, 5), (3, 5) went


@pytest.mark.parametrize("kept", [False, True])
@pytest.mark.parametrize("count", [2, 4])
def test_the_run_on_tiles_is_the_in_memory_limiter(noisy, count, kept):
    """tile_limits of each tile, with the floors of the one tile, gives the in-memory
    limiter's heights and gradients at its triangles' corners to the bit, and the tiles'
    counts add up to the in-memory report's; kept: each tile given its data as the second
    floor's summary reconciled it (reconciled_summary, what the survey's refinement reads
    back), not reconciling it again."""
    xy, z, g, triangles = noisy
    values, gradients, directions, report = control_overshoot(xy, z, g, triangles)
    one = Tile.whole(xy, z, g, triangles)
    first = reduce_floor(lambda: (floor_summary(one),))
    floors = NoiseFloors(first, reduce_floor(lambda: (floor_summary(one, first),)))
    counts = np.zeros(3, dtype=int)
    for tile, owned in _tiles(xy, z, g, triangles, count):
        limits = tile_limits(tile, owned, floors, reconciled_summary(tile, first)[1] if kept else None)
        corners = limits.records["index"]
        assert np.array_equal(corners[limits.triangles], owned)
        assert np.array_equal(limits.records["z"], values[corners])
        assert np.array_equal(limits.gradients, gradients[corners])
        counts += (limits.limited, limits.turned, limits.lifted)
    assert counts.tolist() == [report.gradients_limited, report.directions_changed, report.heights_reconciled]
    assert report.heights_reconciled > 0 and report.gradients_limited > 0


@pytest.mark.parametrize("grouped", [False, True])
@pytest.mark.parametrize("count", [2, 3])
def test_own_triangles_in_a_tile_are_their_corners_edges_and_table(noisy, count, grouped):
    """own_triangles_in against a Python loop: the corners are the halo rows the owned
    triangles use, ascending; the triangles number them; every edge of those triangles,
    sorted, is the halo edge `at` names; the table is edge_table of the renumbered
    triangles, field for field. Owned triangles out of the halo's order are refused.
    The halo's triangles in survey order (the owned ones interleaved: found by hash) and
    grouped by owning tile (as survey.halos reads them, the owned ones one run)."""
    from c1mesh.engine.topology import edge_table_sides
    from c1mesh.stages.limiter import own_triangles_in

    xy, z, g, triangles = noisy
    for tile, owned in _tiles(xy, z, g, triangles, count):
        if grouped:
            strip = np.minimum((xy[:, 0] * count).astype(int), count - 1)
            owner = strip[tile.records["index"][tile.triangles].min(axis=1)]
            tile = Tile(tile.records, tile.triangles[np.argsort(owner, kind="stable")], tile.own)
        table, other, _ = edge_table_sides(tile.triangles, len(tile.records))
        corners, local, at, sub = own_triangles_in(tile, table, other, owned)
        index = tile.records["index"].tolist()
        expected_corners = sorted({index.index(v) for v in owned.ravel().tolist()})
        assert corners.tolist() == expected_corners
        assert [[index[corners[v]] for v in row] for row in local.tolist()] == owned.tolist()
        pairs = sorted({tuple(sorted((row[i], row[(i + 1) % 3]))) for row in local.tolist() for i in range(3)})
        assert sub.edges.tolist() == [list(p) for p in pairs]
        halo_edges = table.edges.tolist()
        assert [halo_edges[e] for e in at.tolist()] == [[corners[a], corners[b]] for a, b in pairs]
        expected = edge_table(local, len(corners))
        for name in ("edges", "tri_edge", "forward", "owner", "owner_slot", "count"):
            assert np.array_equal(getattr(sub, name), getattr(expected, name)), name
        if len(owned) > 1:
            with pytest.raises(RuntimeError, match="in order"):
                own_triangles_in(tile, table, other, owned[::-1])
