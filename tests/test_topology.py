"""Edge numbering (c1mesh.engine.topology) against plain numpy constructions of the same things."""
import numpy as np
import pytest

from c1mesh.core.errors import InputError
from c1mesh.engine.topology import (edge_slots, edge_table, edge_table_sides, live_edges, sub_table,
                                    table_from_slots, triangle_neighbours, unique_edges)
from c1mesh.engine.triangulation import delaunay


@pytest.fixture
def shuffled_mesh():
    """A Delaunay mesh with triangles in random order and random corner rotations and
    orientations (edge_table must not rely on any of them)."""
    rng = np.random.default_rng(3)
    xy = rng.random((400, 2))
    tri = delaunay(xy)
    tri = tri[rng.permutation(len(tri))]
    tri = np.take_along_axis(tri, (np.arange(3) + rng.integers(0, 3, (len(tri), 1))) % 3, axis=1)
    flip = rng.random(len(tri)) < 0.5
    tri[flip] = tri[flip][:, ::-1]
    return tri, len(xy)


def test_edge_table_matches_a_unique_of_sorted_pairs(shuffled_mesh):
    tri, n = shuffled_mesh
    table = edge_table(tri, n)
    slot_major = np.concatenate([tri[:, [(k + 1) % 3, (k + 2) % 3]] for k in range(3)])
    pairs = np.sort(slot_major, axis=1)
    edges, inverse, count = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    assert np.array_equal(table.edges, edges)              # lexicographic, i < j
    assert np.array_equal(table.tri_edge, inverse.reshape(3, -1).T)
    assert np.array_equal(table.count, count)
    assert np.array_equal(table.forward, (slot_major[:, 0] < slot_major[:, 1]).reshape(3, -1).T)
    # the owner is the occurrence of lowest (slot, triangle), and it holds the edge there
    position = np.arange(len(pairs))
    first = np.full(len(edges), len(pairs))
    np.minimum.at(first, inverse.ravel(), position)
    assert np.array_equal(table.owner_slot * len(tri) + table.owner, first)
    assert np.array_equal(table.tri_edge[table.owner, table.owner_slot], np.arange(len(edges)))


def test_edge_in_three_triangles_is_refused():
    tri = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])
    with pytest.raises(InputError, match=r"edge \(0, 1\) belongs to 3 triangles"):
        edge_table(tri, 5)
    with pytest.raises(InputError, match="not edge-manifold"):
        triangle_neighbours(tri, 5)


FIELDS = ("edges", "tri_edge", "forward", "owner", "owner_slot", "count")


def test_edge_table_sides_gives_each_edges_second_slot_and_the_neighbours(shuffled_mesh):
    """The second slot of every edge and the triangle across every slot, against a loop
    over the slots holding each unordered vertex pair."""
    tri, n = shuffled_mesh
    table, other, neighbours = edge_table_sides(tri, n)
    plain = edge_table(tri, n)
    assert all(np.array_equal(getattr(table, f), getattr(plain, f)) for f in FIELDS)
    slots = {}
    for t in range(len(tri)):
        for k in range(3):
            slots.setdefault(frozenset((tri[t, (k + 1) % 3], tri[t, (k + 2) % 3])), []).append((t, k))
    expected_nb = np.full((len(tri), 3), -1)
    for pair in slots.values():
        if len(pair) == 2:
            (t1, k1), (t2, k2) = pair
            expected_nb[t1, k1], expected_nb[t2, k2] = t2, t1
    assert np.array_equal(neighbours, expected_nb)
    assert np.array_equal(triangle_neighbours(tri, n), expected_nb)      # without the table
    for e, (i, j) in enumerate(table.edges):
        pair = slots[frozenset((i, j))]
        first = (table.owner[e], table.owner_slot[e])
        rest = [3 * t + k for t, k in pair if (t, k) != first]
        assert other[e] == (rest[0] if rest else -1)


@pytest.mark.parametrize("drop", [0.0, 0.03, 0.5, 1.0])
def test_sub_table_is_the_edge_table_of_the_kept_triangles(shuffled_mesh, drop):
    """sub_table(keep) = edge_table(tri[keep]) field for field (dtype too), also with the
    vertices renumbered as pipeline.steps.compact_vertices does."""
    tri, n = shuffled_mesh
    table, other, _ = edge_table_sides(tri, n)
    keep = np.random.default_rng(5).random(len(tri)) >= drop
    sub, expected = sub_table(table, keep, other), edge_table(tri[keep], n)
    for f in FIELDS:
        assert np.array_equal(getattr(sub, f), getattr(expected, f)), f
        assert getattr(sub, f).dtype == getattr(expected, f).dtype, f
    used = np.flatnonzero(np.bincount(tri[keep].ravel(), minlength=n))
    remap = np.full(n, -1)
    remap[used] = np.arange(used.size)
    sub, expected = sub_table(table, keep, other, used), edge_table(remap[tri[keep]], used.size)
    for f in FIELDS:
        assert np.array_equal(getattr(sub, f), getattr(expected, f)), f


def test_live_edges_counts_the_kept_triangles_of_each_edge_by_a_loop(shuffled_mesh):
    """live_edges' kernel against a loop over every kept triangle's three edges."""
    tri, n = shuffled_mesh
    table, other, _ = edge_table_sides(tri, n)
    keep = np.random.default_rng(9).random(len(tri)) < 0.6
    owner_kept, count = live_edges(table, keep, other)
    expected = np.zeros(len(table.edges), dtype=np.int64)
    for t in np.flatnonzero(keep):
        for k in range(3):
            expected[table.tri_edge[t, k]] += 1
    assert count.dtype == np.int8 and np.array_equal(count, expected)
    assert owner_kept.dtype == bool and np.array_equal(owner_kept, keep[table.owner])
    assert 0 < (count == 1).sum() and 0 < (count == 2).sum() and 0 < (count == 0).sum()
    with pytest.raises(InputError, match="keep must have shape"):
        live_edges(table, keep[1:], other)


def test_edge_table_of_a_fan_and_of_no_triangles():
    """A fan of 200 triangles around vertex 0 (one vertex in every edge of the sort's widest
    bucket), against the edges listed by hand; and the empty mesh."""
    m = 200
    tri = np.array([[0, i + 1, (i + 1) % m + 1] for i in range(m)])      # closed fan
    table, other, neighbours = edge_table_sides(tri, m + 1)
    spokes = [(0, i) for i in range(1, m + 1)]
    rim = sorted(tuple(sorted((i + 1, (i + 1) % m + 1))) for i in range(m))
    assert table.edges.tolist() == [list(e) for e in sorted(spokes + rim)]
    assert table.count.tolist() == [2] * m + [1] * m          # spokes shared, rim on the boundary
    assert neighbours[:, 0].tolist() == [-1] * m               # across the rim: nothing
    assert neighbours[:, 1].tolist() == [(i + 1) % m for i in range(m)]
    assert neighbours[:, 2].tolist() == [(i - 1) % m for i in range(m)]
    empty = edge_table(np.zeros((0, 3), dtype=np.int64), 0)
    assert all(getattr(empty, f).shape[0] == 0 for f in FIELDS)


def test_indices_outside_the_points_are_refused_before_the_kernel():
    for bad in ([[0, 1, 5]], [[0, -1, 2]]):
        with pytest.raises(InputError, match="indices"):
            edge_table(np.array(bad), 5)
        with pytest.raises(InputError, match="indices"):
            triangle_neighbours(np.array(bad), 5)


@pytest.mark.parametrize("mark", ["all", "some", "none"])
def test_unique_edges_are_a_loops_set_of_pairs_with_a_counted_lower_end(shuffled_mesh, mark):
    """unique_edges against a Python set of every triangle's three corner pairs, lower end
    first, sorted; with counted, those whose lower end it marks. A fan's centre (a bucket
    past the insertion sort's size, qsorted) and an unused vertex are among them."""
    tri, n = shuffled_mesh
    fan = np.array([[0, k + 1, k + 2] for k in range(40)])      # vertex 0: 41 higher neighbours
    tri = np.concatenate([tri + 42, fan])
    n = n + 43                                                   # the last vertex unused
    rng = np.random.default_rng(4)
    counted = {"all": None, "some": rng.random(n) < 0.5, "none": np.zeros(n, dtype=bool)}[mark]
    pairs = {tuple(sorted((a, b))) for t in tri.tolist() for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    expected = sorted(p for p in pairs if counted is None or counted[p[0]])
    edges = unique_edges(tri, n, counted)
    assert edges.dtype == np.int64 and edges.shape == (len(expected), 2)
    assert edges.tolist() == [list(p) for p in expected]
    with pytest.raises(InputError):
        unique_edges(tri, n, np.ones(n - 1, dtype=bool))


@pytest.mark.parametrize("workers", [1, 2])
def test_the_edge_tables_blocks_of_vertices_give_the_one_block_table(shuffled_mesh, monkeypatch, workers):
    """The bucket sorts and the fill run over blocks of vertices in threads, each block
    numbering its edges from the blocks before it, and the sub-table's passes over blocks
    of edges and triangles the same way: with blocks of 7 rows (57 blocks of vertices)
    the tables and the neighbours are still those of the loops above."""
    from c1mesh.core import threads
    from c1mesh.engine import topology
    monkeypatch.setattr(topology, "BLOCK", 7)
    with threads.limit(workers):
        test_edge_table_matches_a_unique_of_sorted_pairs(shuffled_mesh)
        test_edge_table_sides_gives_each_edges_second_slot_and_the_neighbours(shuffled_mesh)
        test_live_edges_counts_the_kept_triangles_of_each_edge_by_a_loop(shuffled_mesh)
        for drop in (0.0, 0.03, 0.5, 1.0):
            test_sub_table_is_the_edge_table_of_the_kept_triangles(shuffled_mesh, drop)


def test_the_edge_named_is_the_first_of_the_most_shared_in_any_block(monkeypatch):
    """Edge (0, 1) in 3 triangles (the first block), (20, 21) in 4 (a later one) and
    (30, 31) in 4 (later still): the message names the first edge of the largest count."""
    from c1mesh.engine import topology
    monkeypatch.setattr(topology, "BLOCK", 7)
    tri = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]] + [[20, 21, 22 + i] for i in range(4)]
                   + [[30, 31, 32 + i] for i in range(4)])
    with pytest.raises(InputError, match=r"edge \(20, 21\) belongs to 4 triangles"):
        edge_table(tri, 40)


@pytest.mark.parametrize("drop", [0, 7])
def test_the_table_given_back_from_its_slots_is_the_table(shuffled_mesh, drop):
    """table_from_slots(edge_slots(...)) gives edge_table_sides' table and second slots
    field for field (a mesh with every 7th triangle dropped: more boundary edges); the
    slots are each edge's owner slot 3t + k and its second, as a loop over the table
    finds them; slots outside the triangles are refused before the kernel writes."""
    tri, n = shuffled_mesh
    if drop:
        tri = tri[np.arange(len(tri)) % drop != 0]
    table, other, _ = edge_table_sides(tri, n)
    slots = edge_slots(table, other)
    assert slots.dtype == np.int32
    assert slots.tolist() == [[3 * int(t) + int(k), int(o)] for t, k, o in zip(table.owner, table.owner_slot, other)]
    again, other_again = table_from_slots(tri, n, slots)
    assert all(np.array_equal(getattr(again, f), getattr(table, f)) for f in FIELDS)
    assert np.array_equal(other_again, other)
    bad = slots.copy()
    bad[0, 1] = 3 * len(tri)
    with pytest.raises(InputError, match="slots"):
        table_from_slots(tri, n, bad)
