"""Points binned to tiles on disk (c1mesh.survey.tile_spill): what a tile reads back is what the
in-memory reader gives, the tiles' Delaunay over the spill is scipy's, and no file stays."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Delaunay

import c1mesh.survey.buffered_delaunay as bd
from c1mesh.core import outputs
from c1mesh.stages.frame import choose_frame
from c1mesh.survey.tile_spill import spill


def _points(n=3000, seed=4):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 50, (n, 2))
    return np.column_stack([xy, np.sin(xy[:, 0] / 7) + 0.1 * xy[:, 1]])


def _chunks(points, size=256):
    return (points[i:i + size] for i in range(0, len(points), size))


def test_spilled_tiles_read_back_as_the_points_in_memory(tmp_path):
    points = _points()
    frame = choose_frame(points, axis="z")
    local = frame.to_local(points)
    grid = bd.TileGrid((*local[:, :2].min(axis=0), *local[:, :2].max(axis=0)), 4, 3)
    memory = bd.ArrayReader(local[:, :2])
    with spill(_chunks(points), frame, grid, tmp_path, "out.ply") as tiles:
        assert tiles.counts.sum() == len(points)
        (ax, ay), (bx, by) = np.sort(local[[10, 20], :2], axis=0)     # closed: points on its sides count
        for rect in [(-15, -15, -5, 5), (-30, -30, 30, 30), (24, -25, 60, -20), (-12.5, -20, -12.5, 15),
                     (ax, ay, bx, by), (ax, ay, ax, ay)]:
            index, xy = tiles.read(rect)
            expected_index, expected_xy = memory(rect)
            assert np.array_equal(index, expected_index)
            assert np.array_equal(xy, expected_xy)
        union = np.concatenate([t.triangles for t in bd.buffered_delaunay(tiles.read, grid, len(points))])
        assert {tuple(sorted(f)) for f in union.tolist()} == \
            {tuple(sorted(f)) for f in Delaunay(local[:, :2]).simplices.tolist()}
        assert len(list(tmp_path.iterdir())) == len(grid)
    assert list(tmp_path.iterdir()) == []


def test_spill_files_go_when_spilling_fails_and_are_listed_for_signals(tmp_path):
    points = _points()
    frame = choose_frame(points, axis="z")
    local = frame.to_local(points)
    grid = bd.TileGrid((*local[:, :2].min(axis=0), *local[:, :2].max(axis=0)), 2, 2)

    def failing():
        yield points[:100]
        raise OSError("disk full")
    with pytest.raises(OSError):
        spill(failing(), frame, grid, tmp_path)
    assert list(tmp_path.iterdir()) == []
    tiles = spill(_chunks(points), frame, grid, tmp_path)
    assert {str(p) for p in tiles.paths} <= outputs._LIVE_TEMPS
    outputs.remove_live_temps()                      # what the CLI's signal handler calls
    assert list(tmp_path.iterdir()) == []
    tiles.close()


def test_file_blocks_read_the_rest_of_a_file_in_blocks_of_at_most_rows(tmp_path):
    from c1mesh.survey.tile_spill import file_blocks

    values = np.arange(2_500, dtype="<f8")
    path = tmp_path / "values.bin"
    values.tofile(path)
    with open(path, "rb") as file:
        blocks = list(file_blocks(file, "<f8", 1_000))
    assert [len(b) for b in blocks] == [1_000, 1_000, 500]
    assert np.array_equal(np.concatenate(blocks), values)
    with open(path, "rb") as file:
        file.seek(8 * 2_400)                                   # from where the file stands
        rest = list(file_blocks(file, "<f8", 1_000))
    assert len(rest) == 1 and np.array_equal(rest[0], values[2_400:])
    with open(path, "rb") as file:
        file.seek(8 * 2_500)
        assert list(file_blocks(file, "<f8", 1_000)) == []


def test_the_spills_sort_keys_give_the_order_of_a_stable_sort_by_tile():
    """TileSpill.add orders each chunk by tile with 16-bit keys (numpy's radix sort): the
    same permutation as a stable sort of the int64 tile numbers, checked against Python's
    own stable sort."""
    from c1mesh.survey.tile_spill import _sort_keys

    rng = np.random.default_rng(11)
    for count, n in ((1, 5), (169, 20_000), (1 << 16, 3000), ((1 << 16) + 1, 3000)):
        tiles = rng.integers(0, count, n).astype(np.int64)
        want = sorted(range(n), key=lambda i: int(tiles[i]))
        assert np.argsort(_sort_keys(tiles, count), kind="stable").tolist() == want
