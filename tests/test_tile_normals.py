"""Tile-local normal estimation (c1mesh.survey.tile_normals) against normals.estimate_normals on
the whole survey at once."""
from __future__ import annotations

import numpy as np
import pytest

import c1mesh.survey.buffered_delaunay as bd
from c1mesh.survey.tile_normals import tile_normals

pytest.importorskip("open3d")


class _Reader3:
    def __init__(self, xyz):
        self.xyz = xyz

    def __call__(self, rect):
        x0, y0, x1, y1 = rect
        x, y = self.xyz[:, 0], self.xyz[:, 1]
        index = np.flatnonzero((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1))
        return index, self.xyz[index]


def _terrain(n=4000, seed=6, gap=False):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 60, (n, 2))
    if gap:                                     # sparse strip: neighbourhoods reach far
        xy = xy[(xy[:, 0] < 28) | (xy[:, 0] > 32) | (rng.uniform(size=len(xy)) < 0.03)]
    z = 2 * np.sin(xy[:, 0] / 9) * np.cos(xy[:, 1] / 13) + rng.normal(0, 0.05, len(xy))
    return np.column_stack([xy, z])


def _every_tile(xyz, normals_of):
    """normals_of(reader, grid, tile) over a 3 x 4 grid of the terrain xyz (m, 3): (normals
    (m, 3) each point's from its tile, seen (m,) how many tiles gave one, rounds per tile)."""
    grid = bd.TileGrid((*xyz[:, :2].min(axis=0), *xyz[:, :2].max(axis=0)), 3, 4)
    found = np.full(xyz.shape, np.nan)
    seen = np.zeros(len(xyz), dtype=int)
    rounds = []
    for tile in range(len(grid)):
        result = normals_of(_Reader3(xyz), grid, tile)
        found[result.index] = result.normals
        seen[result.index] += 1
        rounds.append(result.rounds)
    return found, seen, rounds


@pytest.mark.parametrize("gap", [False, True])
def test_tile_normals_are_the_whole_surveys(gap):
    from c1mesh.stages.normals import estimate_normals

    xyz = _terrain(gap=gap)
    whole = estimate_normals(xyz, k=16)
    found, seen, rounds = _every_tile(xyz, lambda read, grid, tile: tile_normals(read, grid, tile, 16, buffer=1.0))
    assert (seen == 1).all()                                    # every point once
    assert np.allclose(found, whole, rtol=0, atol=1e-9)
    assert max(rounds) > 1                                      # a 1.0 buffer is too small somewhere


def test_a_buffer_too_small_without_the_check_gives_other_normals(monkeypatch):
    """The neighbourhood check is what makes them equal: trusting a thin buffer changes
    the normals of points near the tile borders."""
    import c1mesh.survey.tile_normals as tn
    from c1mesh.stages.normals import estimate_normals

    xyz = _terrain()
    grid = bd.TileGrid((*xyz[:, :2].min(axis=0), *xyz[:, :2].max(axis=0)), 3, 4)
    monkeypatch.setattr(tn, "_neighbourhoods_inside", lambda *args: True)
    found = np.full(xyz.shape, np.nan)
    for tile in range(len(grid)):
        result = tile_normals(_Reader3(xyz), grid, tile, 16, buffer=0.3)
        found[result.index] = result.normals
    assert not np.allclose(found, estimate_normals(xyz, k=16), rtol=0, atol=1e-6)


@pytest.mark.parametrize("gap", [False, True])
def test_tile_height_normals_are_the_whole_surveys_to_the_bit(gap):
    """The height fit's normals per tile (what a LAS tile fit uses), with a first buffer too
    small for some points, so later reads refit only those: every point's normal equals
    the whole survey's fit, bit for bit (a fit depends on its neighbourhood only)."""
    from c1mesh.stages.height_gradients import fitted_normals
    from c1mesh.survey.tile_normals import tile_height_normals

    xyz = _terrain(gap=gap)
    whole, _ = fitted_normals(xyz, None, 24)
    found, seen, rounds = _every_tile(xyz, lambda read, grid, tile: tile_height_normals(read, grid, tile, 24,
                                                                                          buffer=0.5))
    assert (seen == 1).all()
    assert np.array_equal(found, whole)
    assert max(rounds) > 1
