"""The tiled fit's survey-sized state replaced by halo- and band-sized state.

- core.tile.tile_rows (a binary search over one halo) against a dense table over the
  survey (the RowMap it replaced: 4 bytes a survey point in every process);
- join: the join that forgets a border key once no later tile can meet it must
  number every vertex as the join that keeps every key, on real tile refinements of a
  triangulation with a hole (border keys inside the survey) at levels with edge keys.
"""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.survey.buffered_delaunay import TileGrid
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.survey.join import KeyExpiry, SharedKeys, border_keys, global_numbers, stored_keys
from c1mesh.core.tile import tile_rows
from c1mesh.engine.triangulation import delaunay
from c1mesh.stages.trim import trim


def test_tile_rows_equal_a_dense_table_over_the_survey():
    rng = np.random.default_rng(3)
    survey = 50_000
    index = np.sort(rng.choice(survey, 4_000, replace=False))
    dense = np.full(survey, -1, dtype=np.int64)
    dense[index] = np.arange(len(index))
    queries = rng.integers(0, survey, (20_000, 3))
    queries[:500] = index[rng.integers(0, len(index), (500, 3))]       # many present
    queries[500, 0], queries[501, 0] = survey - 1, 0                    # beyond either end
    queries[502, 0] = index[-1] + 1 if index[-1] + 1 < survey else 0
    rows = tile_rows(index, queries)
    assert rows.shape == queries.shape
    assert np.array_equal(rows, dense[queries])
    assert (rows >= 0).sum() > 1_500 and (rows < 0).sum() > 10_000
    assert np.array_equal(tile_rows(index[:0], queries[:4]), np.full((4, 3), -1))


def _survey(seed: int):
    """Random points with a round hole (its rim gives border keys inside the survey),
    trimmed Delaunay triangles, heights and exact gradients of a smooth function."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 100, (2_500, 2))
    xy = xy[np.hypot(xy[:, 0] - 55, xy[:, 1] - 45) > 12]
    triangles, _ = trim(xy, delaunay(xy), max_edge=6.0, min_circle_ratio=0.0)
    z = np.sin(xy[:, 0] / 11) * np.cos(xy[:, 1] / 7)
    gradients = np.column_stack([np.cos(xy[:, 0] / 11) * np.cos(xy[:, 1] / 7) / 11,
                                 -np.sin(xy[:, 0] / 11) * np.sin(xy[:, 1] / 7) / 7])
    return xy, z, gradients, triangles


def _outside(xy: np.ndarray, cell) -> np.ndarray:
    """How far each point lies beyond the cell, along the farther axis (0 inside)."""
    x0, y0, x1, y1 = cell
    return np.maximum.reduce([x0 - xy[:, 0], xy[:, 0] - x1, y0 - xy[:, 1], xy[:, 1] - y1, np.zeros(len(xy))])


def _tile_keys(xy, z, gradients, triangles, side, level):
    """Per tile in ascending order (tile, its border keys as stored_keys gives them, its
    refinement's vertex count), each tile refining the triangles whose lowest-numbered
    corner lies in its cell, as the tiled fit does; and the KeyExpiry of the grid with
    each tile's exact reach (its own corners' farthest distance beyond its cell)."""
    grid = TileGrid((0.0, 0.0, 100.0, 100.0), side, side)
    owner = grid.tile_of(xy[triangles.min(axis=1)])
    reaches = [float(_outside(xy[np.unique(triangles[owner == t])], grid.cell(t)).max(initial=0.0))
               for t in range(len(grid))]
    expiry = KeyExpiry(grid, reaches)
    tiles = []
    for t in range(len(grid)):
        own = triangles[owner == t]
        if not len(own):
            continue
        corners = np.unique(own)
        interp = RSDInterpolator(xy[corners], z[corners], gradients[corners],
                                 triangles=np.searchsorted(corners, own))
        refinement = interp.refinement(level)
        stored = border_keys(refinement, corners, xy[corners], expiry)
        tiles.append((t, stored_keys(stored), int(refinement.vertex_count)))
    return tiles


def _numbers_keeping_every_key(tiles):
    """The join's numbering before keys were forgotten: one dict of every border key."""
    shared, written, out = {}, 0, []
    for _, (keys, points, _), count in tiles:
        number = np.full(count, -1, dtype=np.int64)
        for k, p in zip(keys, points):
            if k in shared:
                number[p] = shared[k]
        new = number < 0
        number[new] = written + np.arange(int(new.sum()))
        for k, p in zip(keys, points):
            shared.setdefault(k, int(number[p]))
        written += int(new.sum())
        out.append(number)
    return out, len(shared)


@pytest.mark.parametrize("level, seed", [(1, 0), (3, 1), (4, 2)])
def test_join_that_forgets_keys_numbers_every_vertex_as_the_join_that_keeps_them(level, seed):
    xy, z, gradients, triangles = _survey(seed)
    tiles = _tile_keys(xy, z, gradients, triangles, 6, level)
    expected, distinct = _numbers_keeping_every_key(tiles)
    shared, written, numbers = SharedKeys(), 0, []
    for t, (keys, points, last), count in tiles:
        assert min(last) >= t                                  # a key's own tile can meet it
        number = global_numbers(keys, points, last, t, count, shared, written)
        shared.forget(t)
        assert all(end > t for end in shared.expiring)         # only keys a later tile can meet
        written += int((number >= written).sum())
        numbers.append(number)
    for got, want in zip(numbers, expected):
        assert np.array_equal(got, want)
    # every corner point of the survey has one number, whichever tile wrote or met it
    corner_number = {}
    for (_, (keys, points, _), _), number in zip(tiles, numbers):
        for k, p in zip(keys, points):
            if not isinstance(k, tuple):
                assert corner_number.setdefault(k, int(number[p])) == int(number[p])
    assert len(corner_number) > 300
    first_tile, last_tile = {}, {}
    for t, (keys, _, last), _ in tiles:
        for k, end in zip(keys, last):
            first_tile.setdefault(k, t)
            last_tile[k] = end
    assert len(first_tile) == distinct
    assert shared.added == sum(last_tile[k] > first_tile[k] for k in first_tile)  # the rest never held
    assert shared.peak < shared.added and not shared.numbers      # forgotten as the join went


def test_a_key_lasts_until_the_last_tile_whose_grown_cell_holds_its_point():
    grid = TileGrid((0.0, 0.0, 30.0, 30.0), 3, 3)                 # cells 10 wide, t = i + 3 j
    expiry = KeyExpiry(grid, [1.0] * 9)
    xy = np.array([[5.0, 5.0],       # deep in tile 0: no other grown cell
                   [5.0, 10.5],      # tile 3, within 1 of tile 0's cell: tiles 0 and 3
                   [10.5, 10.5],     # tile 4, within 1 of tiles 0, 1, 3: last 4
                   [9.5, 9.5],       # tile 0, within 1 of tiles 1, 3, 4: last 4
                   [15.0, 19.0],     # tile 4, within 1 of tile 7
                   [29.0, 21.0],     # tile 8, within 1 of tile 5 (lower): last 8
                   [15.0, 31.0]])    # outside the box by 1: tile 7's grown cell (closed)
    assert expiry.last_tiles(xy).tolist() == [0, 3, 4, 4, 7, 8, 7]
    assert expiry.last_tiles(np.array([[45.0, 45.0]])).tolist() == [-1]
