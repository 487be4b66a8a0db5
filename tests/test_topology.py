"""Edge numbering (c1mesh.engine.topology) against plain numpy constructions of the same things."""
import numpy as np
import pytest

from c1mesh.core.errors import InputError
from c1mesh.engine.topology import edge_table, sort_keys
from c1mesh.engine.triangulation import delaunay


@pytest.mark.parametrize("bound", [1000 * 1000, 2 ** 62])      # packed sort; no room: argsort
def test_sort_keys_is_a_stable_argsort(bound):
    rng = np.random.default_rng(8)
    key = rng.integers(0, 1000 * 1000, size=30000)
    key[::3] = key[1::3]                                   # pairs of equal keys
    key[:50] = key[50]                                     # and a long run of them
    order, sorted_key = sort_keys(key.copy(), bound)
    expected = np.argsort(key, kind="stable")
    assert np.array_equal(order, expected)
    assert np.array_equal(sorted_key, key[expected])


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
