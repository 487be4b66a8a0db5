"""benchmarks/ground.py's harness against independent truths: the DEM comparison's cell
alignment against a brute-force loop, autzen_trim's left-out points against the issue's
count (66% of class 1), and the bars' verdicts."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks import ground as bench  # noqa: E402


def test_dem_gaps_compare_the_same_cells():
    """Two DEMs with different extents on one whole-metre grid: the gaps are those of the
    cells both cover, found here by a loop over absolute cell positions."""
    rng = np.random.default_rng(3)
    a = np.ma.masked_array(rng.random((5, 7)), mask=rng.random((5, 7)) < 0.2)
    b = np.ma.masked_array(rng.random((6, 4)), mask=rng.random((6, 4)) < 0.2)
    first, second = (a, 10, 50), (b, 12, 48)             # (heights, west, north)
    expected = []
    for row in range(5):
        for col in range(7):
            x, y = 10 + col, 50 - row                     # the cell's west and north edges
            brow, bcol = 48 - y, x - 12
            if 0 <= brow < 6 and 0 <= bcol < 4 and not a.mask[row, col] and not b.mask[brow, bcol]:
                expected.append(abs(a.data[row, col] - b.data[brow, bcol]))
    assert sorted(bench._dem_gaps(first, second)) == sorted(expected)


def test_autzen_leaves_out_two_thirds_of_class_1():
    """Issue 39 measured 66% of autzen_trim's class-1 points within 0.3 m of its class-2
    surface; the benchmark leaves exactly those out and scores the rest."""
    tile = bench.real_tile(bench.SAMPLES / "autzen_trim.laz")
    left_out = ~tile.scored
    assert not (left_out & tile.ground).any()
    assert round(100 * left_out.sum() / (~tile.ground).sum()) == 66


def test_verdicts_follow_the_bars():
    steep = bench.Tile("synthetic steep", np.zeros((1, 3)), np.ones(1, bool), np.ones(1, bool))
    assert bench.verdict(steep, 4.9, 70.0).startswith("pass")
    assert bench.verdict(steep, 4.9, 60.0).startswith("FAIL")
    assert bench.verdict(steep, 5.1, 90.0).startswith("FAIL")
