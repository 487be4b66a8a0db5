"""The height-field stage cut into tiles (c1mesh.stages.height_field): each tile's summaries
(its vertices, sampled nearest-neighbour spacings and stacked points), reduced over a small
survey split into tiles, equal the in-memory fit's one tile and a brute-force reference
that loops over every point and every pair."""
from __future__ import annotations

import math

import numpy as np
import pytest

import c1mesh.survey.height_runs as height_runs
from c1mesh.stages.frame import ScanFrame
from c1mesh.stages.height_field import (
    Positions,
    PositionTile,
    height_field,
    sample_spacings,
    spacing_steps,
    stacked_points,
    tile_heights,
)
from c1mesh.core.tile import VERTEX
from c1mesh.survey.buffered_delaunay import TileGrid
from c1mesh.survey.distributed import TaskRunner
from c1mesh.survey.tile_spill import RECORD, TileSpill

COS_MAX = math.cos(math.radians(85.0))


def _survey(seed: int):
    """300 points (survey numbers 0..299) on a gentle slope over the box (0, 0, 10, 10): 30
    repeat earlier positions, every other one 5 m off (stacked as a group), 10 lie 4 m up
    (a second layer), two pairs jump 4 m across tile borders, 6 have normals the height
    field drops (too steep, zero, NaN), point 0 among them."""
    rng = np.random.default_rng(seed)
    n = 300
    xy = rng.uniform(0, 10, (n, 2))
    xy[270:] = xy[rng.choice(np.arange(10, 200), 30, replace=False)]
    z = 0.1 * xy[:, 0] + 0.05 * np.sin(xy[:, 1])
    z[270:] += np.where(np.arange(30) % 2 == 1, 5.0, 1e-3)
    z[250:260] += 4.0
    xy[[245, 246]] = [[0.0, 0.0], [10.0, 10.0]]                  # the box: tile borders at 10/side
    xy[[247, 248, 260, 261]] = [[4.99, 1.0], [5.01, 1.0], [10 / 3 - 0.01, 2.0], [10 / 3 + 0.01, 2.0]]
    z[[248, 261]] += 4.0                                         # jumps across the borders
    normals = np.column_stack([np.full(n, -0.1), -0.05 * np.cos(xy[:, 1]), np.ones(n)])
    normals[rng.random(n) < 0.3] *= -1.0                          # signs are not trusted
    normals[[0, 240, 241, 242]] = [1.0, 0.0, 0.01]
    normals[243] = 0.0
    normals[244] = np.nan
    return xy, z, normals


def _brute(xy, z, normals, step):
    """(usable points, the distinct positions {(x, y): [points]}, spacing h, stacked points)
    by loops in Python floats, in the operations' order: each nearest distance over every
    other position, each pair of positions within h for the stacking test."""
    usable = []
    for i, (a, b, c) in enumerate(normals.tolist()):
        length = math.sqrt(a * a + b * b + c * c)
        if math.isfinite(length) and length > 0 and abs(c / length) >= COS_MAX:
            usable.append(i)
    groups: dict = {}
    for i in usable:
        groups.setdefault((float(xy[i, 0]) + 0.0, float(xy[i, 1])), []).append(i)
    first = sorted(g[0] for g in groups.values())
    x, y, h = xy[:, 0].tolist(), xy[:, 1].tolist(), z.tolist()
    nearest = []
    for i in first:
        if i % step == 0:
            nearest.append(min(math.sqrt((x[i] - x[j]) * (x[i] - x[j]) + (y[i] - y[j]) * (y[i] - y[j])
                                         + (h[i] - h[j]) * (h[i] - h[j])) for j in first if j != i))
    spacing = float(np.median(nearest))
    size = {g[0]: len(g) for g in groups.values()}
    spread = {g[0]: max(h[k] for k in g) - min(h[k] for k in g) for g in groups.values()}
    slope = {}
    for i in first:
        gx, gy = -normals[i, 0] / normals[i, 2], -normals[i, 1] / normals[i, 2]
        slope[i] = math.sqrt(gx * gx + gy * gy)
    bad = {i for i in first if spread[i] > 3.0 * spacing}
    for a, i in enumerate(first):
        for j in first[a + 1:]:
            d2 = (x[i] - x[j]) * (x[i] - x[j]) + (y[i] - y[j]) * (y[i] - y[j])
            if d2 <= spacing * spacing and abs(h[i] - h[j]) > 3.0 * spacing + max(slope[i], slope[j]) * math.sqrt(d2):
                bad |= {i, j}
    return usable, groups, spacing, sum(size[i] for i in bad)


def _records(xy, z, rows):
    records = np.empty(len(rows), RECORD)
    records["index"], records["x"], records["y"], records["z"] = rows, xy[rows, 0], xy[rows, 1], z[rows]
    return records


def _tiles(xy, z, normals, side):
    """The grid of side x side tiles over the survey and each tile's tile_heights."""
    grid = TileGrid((*xy.min(axis=0), *xy.max(axis=0)), side, side)
    home = grid.tile_of(xy)
    return grid, [tile_heights(_records(xy, z, np.flatnonzero(home == t)), normals[home == t], COS_MAX)
                  for t in range(len(grid))]


def _position_tile(parts, grid, tile, reach):
    """The PositionTile of tile: every part's vertices within reach of its cell."""
    x0, y0, x1, y1 = grid.grown(tile, reach)
    records = np.concatenate([p.records for p in parts])
    size = np.concatenate([p.size for p in parts])
    z_range = np.concatenate([p.z_range for p in parts])
    near = (records["x"] >= x0) & (records["x"] <= x1) & (records["y"] >= y0) & (records["y"] <= y1)
    records, size, z_range = records[near], size[near], z_range[near]
    own = grid.tile_of(np.column_stack([records["x"], records["y"]])) == tile
    positions = Positions(records["x"], records["y"], records["z"], records["gx"], records["gy"], z_range)
    return PositionTile(positions, records["index"], size, own)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tile_heights_are_the_distinct_usable_positions(seed):
    """Every tile's vertices together: one per distinct position of a usable point that is
    not too steep, its first point's, with its gradient, size and height spread."""
    xy, z, normals = _survey(seed)
    usable, groups, _, _ = _brute(xy, z, normals, 1)
    _, parts = _tiles(xy, z, normals, 3)
    records = np.concatenate([p.records for p in parts])
    order = np.argsort(records["index"])
    records = records[order]
    size, z_range = np.concatenate([p.size for p in parts])[order], np.concatenate([p.z_range for p in parts])[order]
    assert sum(p.usable for p in parts) == len(usable) == 300 - 6
    assert records["index"].tolist() == sorted(g[0] for g in groups.values())
    assert records.dtype == VERTEX
    for k, i in enumerate(records["index"]):
        group = groups[(float(xy[i, 0]) + 0.0, float(xy[i, 1]))]
        assert size[k] == len(group) and z_range[k] == max(z[group]) - min(z[group])
        assert (records["x"][k], records["y"][k], records["z"][k]) == (xy[i, 0], xy[i, 1], z[i])
        assert records["gx"][k] == -normals[i, 0] / normals[i, 2] and records["gy"][k] == -normals[i, 1] / normals[i, 2]
    assert (size > 1).sum() == 30


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("step", [1, 3])
def test_tile_summaries_reduce_to_the_one_tile_values_and_the_loops(seed, step):
    """Spacings: each tile reads its cell grown by the longest nearest distance (so every
    nearer position is read); the median of all equals the one tile's and the loop's.
    Stacked points: each tile reads its cell grown by h; the sum equals them too."""
    xy, z, normals = _survey(seed)
    usable, _, want_spacing, want_stacked = _brute(xy, z, normals, step)
    assert 10 < want_stacked < 100
    whole = tile_heights(_records(xy, z, np.arange(len(xy))), normals, COS_MAX)
    one = PositionTile.whole(Positions(whole.records["x"], whole.records["y"], whole.records["z"],
                                       whole.records["gx"], whole.records["gy"], whole.z_range),
                             whole.records["index"], whole.size)
    one_spacings = sample_spacings(one, step)
    assert float(np.median(one_spacings)) == want_spacing
    assert stacked_points(one, want_spacing)[0] == want_stacked
    for side in (2, 3, 4):
        grid, parts = _tiles(xy, z, normals, side)
        reach = float(one_spacings.max()) * 1.01
        spacings = np.concatenate([sample_spacings(_position_tile(parts, grid, t, reach), step)
                                   for t in range(len(grid))])
        assert np.array_equal(np.sort(spacings), np.sort(one_spacings))
        assert float(np.median(spacings)) == want_spacing
        stacked = sum(stacked_points(_position_tile(parts, grid, t, want_spacing * (1 + 1e-9)), want_spacing)[0]
                      for t in range(len(grid)))
        assert stacked == want_stacked
        assert sum(p.usable for p in parts) == len(usable)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_in_memory_height_field_is_the_one_tile(seed):
    """height_field's spacing and stacked count (its one PositionTile) are the loops'."""
    xy, z, normals = _survey(seed)
    _, _, want_spacing, want_stacked = _brute(xy, z, normals, 1)
    frame = ScanFrame(origin=np.zeros(3), axes=np.eye(3))
    hf = height_field(np.column_stack([xy, z]), normals, frame, max_stacked=1.0)
    assert hf.spacing == want_spacing and hf.stacked == want_stacked
    assert hf.dropped["too_steep"] == 4 and hf.dropped["bad_normal"] == 2


class _Temps:
    def __init__(self, directory):
        self.directory = directory

    def new(self, name):
        return self.directory / name


@pytest.mark.parametrize("steps, step", [((1,), 1), ((3, 1), 3), ((1000, 1), 1)])
def test_the_scheduled_stacking_test_is_the_loops(tmp_path, monkeypatch, steps, step):
    """height_runs.survey_stacking over spill files, its reach doubling from a tenth of
    the spacing: the loops' h and stacked count. With a step no survey number is a
    multiple of (point 0 is dropped), every position measures h, as in memory."""
    xy, z, normals = _survey(0)
    usable, _, want_spacing, want_stacked = _brute(xy, z, normals, step)
    grid, parts = _tiles(xy, z, normals, 3)
    monkeypatch.setattr(height_runs, "spacing_steps", lambda positions: steps)
    monkeypatch.setattr(height_runs, "INITIAL_SPACINGS", 0.1)
    heights = TileSpill(grid, tmp_path, "h", record=height_runs.HEIGHT).__enter__()
    groups = TileSpill(grid, tmp_path, "g", record=height_runs.GROUP).__enter__()
    for t, part in enumerate(parts):
        rims, count, group_rims = height_runs.write_heights(part, heights, groups, t)
        heights.set_tile(t, len(part.records), rims)
        groups.set_tile(t, count, group_rims)
    spill = height_runs.HeightSpill(heights, groups, sum(p.usable for p in parts))
    try:
        with TaskRunner() as runner:
            spacing, stacked = height_runs.survey_stacking(spill, grid, np.array([0.0, 0.0, 1.0]), runner, str,
                                                           _Temps(tmp_path), max_stacked=1.0)
    finally:
        spill.close()
    assert (spacing, stacked) == (want_spacing, want_stacked)
    assert spill.usable == len(usable)


def test_spacing_steps_sample_every_position_below_twice_the_samples():
    assert spacing_steps(39999) == (1,)
    assert spacing_steps(40000) == (2, 1)
    assert spacing_steps(10, samples=3) == (3, 1)


@pytest.mark.parametrize("layout", ["shuffled", "x_sorted", "quantised_sorted", "one_x"])
def test_strips_hold_the_points_by_strip_then_y_then_index(layout):
    """strip_index against a brute-force lexsort of (strip number, y, index), with -0.0 as
    0.0: points in any order (two radix sorts), sorted by x as the height field's
    positions are (each strip's run sorted alone), quantised with ties in x and y
    and zeros of both signs, and all on one x."""
    from c1mesh.stages.height_field import strip_index
    rng = np.random.default_rng(11)
    n = 20_000
    x, y = rng.random(n) * 50, rng.random(n) * 30 - 15
    if layout == "quantised_sorted":
        x, y = np.round(x * 4) / 4, np.round(y * 2) / 2
        y[rng.random(n) < 0.05] = -0.0
    if layout == "one_x":
        x = np.full(n, 3.0)
    if layout != "shuffled":
        order = np.lexsort((y, x))
        x, y = x[order], y[order]
    strips = strip_index(x, y, 0.37)
    strip = np.floor((x - x.min()) / strips.width).astype(np.int64) if strips.width > 0 else np.zeros(n, np.int64)
    want = np.lexsort((np.arange(n), y + 0.0, strip))
    assert np.array_equal(strips.strip, strip)
    assert np.array_equal(strips.order, want)
    runs = strip[want]
    assert np.array_equal(strips.starts, np.r_[0, np.flatnonzero(runs[1:] != runs[:-1]) + 1, n])
