"""Points binned to tiles on disk (c1mesh.survey.tile_spill): what a tile reads back is what the
in-memory reader gives, the tiles' Delaunay over the spill is scipy's, and no file stays."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Delaunay

import c1mesh.survey.buffered_delaunay as bd
from c1mesh.core import outputs
from c1mesh.stages.frame import choose_frame
from c1mesh.survey.tile_spill import RECORD, TileSpill, spill


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


def _brute(records, rect):
    """The records in the closed rectangle, ascending survey numbers: a loop."""
    x0, y0, x1, y1 = rect
    kept = [r for r in records.tolist() if x0 <= r[1] <= x1 and y0 <= r[2] <= y1]
    return sorted(kept)


def test_a_spill_with_rims_reads_what_a_loop_over_every_record_keeps(tmp_path):
    """Tiles written whole with a rim (TileSpill.write_tile) read back, for rectangles that
    reach a neighbour's rim, its middle, a band's edge exactly, a corner, and with far
    reads, the records a loop over every record keeps, and the rim files go with the
    spill. The rim parts are read alone (not the tile) when the rectangle stays in them."""
    rng = np.random.default_rng(7)
    n = 4000
    records = np.empty(n, RECORD)
    records["index"] = rng.permutation(n)
    records["x"] = np.round(rng.uniform(0, 40, n), 1)          # 0.1 steps: records on band edges
    records["y"] = np.round(rng.uniform(0, 30, n), 1)
    records["z"] = rng.normal(size=n)
    grid = bd.TileGrid((0.0, 0.0, 40.0, 30.0), 4, 3)             # cells 10 x 10: rim 2 (of 2.5 allowed)
    spill = TileSpill(grid, tmp_path, "rims", rim=2.0).__enter__()
    tiles = grid.tile_of(np.column_stack([records["x"], records["y"]]))
    for t in range(len(grid)):
        mine = records[tiles == t]
        spill.set_tile(t, len(mine), spill.write_tile(t, mine[np.argsort(mine["index"])]))
    assert spill.rim == 2.0 and len(list(tmp_path.iterdir())) == 2 * len(grid)
    whole_reads = []
    original = spill.tile
    spill.tile = lambda t: whole_reads.append(t) or original(t)
    rects = [(8.0, 8.0, 22.0, 22.0), (10.0, 10.0, 20.0, 20.0), (9.0, 9.0, 12.0, 21.0), (12.0, 12.0, 18.0, 18.0),
             (11.9, 0.0, 12.0, 30.0), (0.0, 0.0, 40.0, 30.0), (19.9, 19.9, 20.1, 20.1), (5.0, 5.0, 5.0, 5.0),
             (-3.0, -3.0, 1.0, 1.0)]
    for rect in rects:
        got = spill.records(rect)
        assert sorted(got.tolist()) == _brute(records, rect) and np.all(np.diff(got["index"]) > 0)
    whole_reads.clear()
    spill.records((12.0, 12.0, 18.0, 18.0))                      # tile 5's middle: only it is read whole
    assert whole_reads == [5]
    whole_reads.clear()
    spill.records((19.0, 19.0, 21.0, 21.0))                      # four tiles' corners: none read whole
    assert whole_reads == []
    far = np.array([[25.0, 5.0, 3.0]])                           # a far read's square meets tile 2 only
    got, read = spill.records_near((9.0, 9.0, 21.0, 21.0), far)
    near = set(map(tuple, _brute(records, (9.0, 9.0, 21.0, 21.0))))
    near |= {r for r in map(tuple, records.tolist()) if max(abs(r[1] - 25.0), abs(r[2] - 5.0)) <= 3.0}
    assert sorted(got.tolist()) == sorted(near) and read == sorted(read)
    spill.close()
    assert list(tmp_path.iterdir()) == []


def test_merged_parts_are_the_stable_sort_of_their_concatenation():
    """tile_spill._merged (the kernel's two-way merges, shortest first) gives what a stable
    argsort of the parts' concatenation by survey number gives: for ascending parts of
    many sizes (empty, one record, interleaved, one long), and, through its fallback, for
    a part out of order and for a number in two parts."""
    from c1mesh.survey.tile_spill import _merged

    rng = np.random.default_rng(11)

    def parts_of(numbers, sizes):
        chunks = np.split(numbers, np.cumsum(sizes)[:-1])
        out = []
        for chunk in chunks:
            records = np.zeros(len(chunk), RECORD)
            records["index"] = np.sort(chunk)
            records["x"] = rng.normal(size=len(chunk))
            out.append(records)
        return out

    def sorted_concatenation(parts):
        records = np.concatenate(parts) if parts else np.empty(0, RECORD)
        return records.take(np.argsort(records["index"], kind="stable"))

    numbers = rng.permutation(5000)
    for sizes in ([5000], [0, 5000, 0], [4000, 3, 1, 996], [1] * 50 + [4950], [2500, 2500]):
        parts = parts_of(numbers, sizes)
        assert _merged(parts, RECORD).tobytes() == sorted_concatenation(parts).tobytes()
    assert len(_merged([], RECORD)) == 0
    alone = parts_of(numbers, [5000])[0][::-1].copy()            # one part, out of order
    assert _merged([alone], RECORD).tobytes() == sorted_concatenation([alone]).tobytes()
    shuffled = parts_of(numbers, [3000, 2000])
    shuffled[1] = shuffled[1][::-1].copy()                       # a part out of order
    assert _merged(shuffled, RECORD).tobytes() == sorted_concatenation(shuffled).tobytes()
    twice = parts_of(np.concatenate([numbers[:100], numbers[:100]]), [100, 100])   # each number twice
    assert _merged(twice, RECORD).tobytes() == sorted_concatenation(twice).tobytes()
