"""Synthetic LiDAR scenes with true ground classes, and the ISPRS filter-test scores.

Two kinds of tile where ground filters fail (issue 39), made in code from a seed:

- `steep_scene`: rough terrain whose median slope is 26° (measured on its height
  function, scaled to it), with trees whose crowns hide part of the ground beneath;
- `roof_scene`: a crop that one flat 50 × 60 m roof fills, with the ground in a single
  10 m strip beside it (a little sloped) and a few points on the wall between.

`filter_scores` scores a classification as the ISPRS filter test does (Sithole &
Vosselman 2004): Type I (ground rejected, of the true ground), Type II (objects accepted
as ground, of the true objects), total error and Cohen's kappa.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class Scene:
    """points (n, 3) in metres, ground (n,) bool: the truth; name for tables."""

    name: str
    points: np.ndarray
    ground: np.ndarray


def _terrain(xy: np.ndarray, seed: int) -> np.ndarray:
    """Rough terrain heights (unscaled): a sum of random plane waves, 20-120 m long."""
    rng = np.random.default_rng(seed)
    z = np.zeros(len(xy))
    for _ in range(8):
        angle, length, phase = rng.uniform(0, np.pi), rng.uniform(20, 120), rng.uniform(0, 2 * np.pi)
        direction = np.array([np.cos(angle), np.sin(angle)])
        z += length * np.sin(2 * np.pi * xy @ direction / length + phase)
    return z


def _median_tan(size: float, seed: int) -> float:
    """The median gradient magnitude of _terrain over a 0.5 m lattice of the square."""
    axis = np.arange(0.0, size, 0.5)
    x, y = np.meshgrid(axis, axis)
    z = _terrain(np.column_stack([x.ravel(), y.ravel()]), seed).reshape(x.shape)
    gy, gx = np.gradient(z, 0.5)
    return float(np.median(np.hypot(gx, gy)))


def steep_scene(size: float = 120.0, density: float = 2.0, seed: int = 0,
                median_slope_deg: float = 26.0, noise: float = 0.03) -> Scene:
    """Steep wooded terrain over a size × size m square: ground points at `density` per m²
    (fewer under crowns: 30% get through), trees of 6-20 m with crowns 2-4 m wide; noise:
    the standard deviation of the ground's heights about the terrain (m)."""
    rng = np.random.default_rng(seed + 1)
    scale = np.tan(np.radians(median_slope_deg)) / _median_tan(size, seed)
    height = lambda xy: scale * _terrain(xy, seed)  # noqa: E731
    xy = rng.uniform(0, size, (int(density * size * size), 2))
    trees = _trees(rng, size, count=int(size * size / 80))
    covered = _under_crowns(xy, trees)
    xy = xy[~covered | (rng.random(len(xy)) < 0.3)]
    ground = np.column_stack([xy, height(xy) + rng.normal(0, noise, len(xy))])
    canopy = _crown_points(rng, trees, height, density)
    return Scene("synthetic steep", np.vstack([ground, canopy]),
                 np.concatenate([np.ones(len(ground), bool), np.zeros(len(canopy), bool)]))


def _trees(rng, size: float, count: int) -> np.ndarray:
    """(count, 4): x, y, crown radius, tree height."""
    return np.column_stack([rng.uniform(0, size, (count, 2)), rng.uniform(2, 4, count),
                            rng.uniform(6, 20, count)])


def _under_crowns(xy: np.ndarray, trees: np.ndarray) -> np.ndarray:
    """(n,) bool: the points of xy under some tree's crown."""
    covered = np.zeros(len(xy), bool)
    for point, near in enumerate(cKDTree(trees[:, :2]).query_ball_point(xy, r=float(trees[:, 2].max()))):
        for tree in near:
            if np.sum((xy[point] - trees[tree, :2]) ** 2) < trees[tree, 2] ** 2:
                covered[point] = True
                break
    return covered


def _crown_points(rng, trees: np.ndarray, height, density: float) -> np.ndarray:
    """Returns from the crowns: half-ellipsoids of the crown radius, 40% of the tree's
    height deep, top at the tree's height above the ground under its stem; a few returns
    deeper inside (lower branches, 1 m and more above the ground)."""
    parts = []
    for x, y, radius, tall in trees:
        count = int(density * 2 * np.pi * radius ** 2)
        r = radius * np.sqrt(rng.random(count))
        angle = rng.uniform(0, 2 * np.pi, count)
        base = height(np.array([[x, y]]))[0]
        top = base + tall - 0.4 * tall * (1 - np.sqrt(np.clip(1 - (r / radius) ** 2, 0, 1)))
        depth = np.where(rng.random(count) < 0.2, rng.uniform(0, tall - 1, count), 0.0)
        parts.append(np.column_stack([x + r * np.cos(angle), y + r * np.sin(angle), top - depth * 0.9]))
    return np.vstack(parts)


def roof_scene(density: float = 2.0, seed: int = 0, roof_height: float = 7.0) -> Scene:
    """A 60 × 60 m crop: ground in the strip 0 ≤ x < 10 (sloping 2% along y and 1% along
    x), a flat roof over 10 ≤ x ≤ 60, 0 ≤ y ≤ 60, `roof_height` m above the ground at its
    wall, and 60 returns on the wall at x = 10."""
    rng = np.random.default_rng(seed)
    ground_at = lambda x, y: 100.0 + 0.01 * x + 0.02 * y  # noqa: E731
    strip = rng.uniform((0, 0), (10, 60), (int(density * 600), 2))
    roof = rng.uniform((10, 0), (60, 60), (int(density * 3000), 2))
    wall_y, wall_h = rng.uniform(0, 60, 60), rng.uniform(0.5, roof_height, 60)
    roof_z = ground_at(10.0, 30.0) + roof_height
    points = np.vstack([
        np.column_stack([strip, ground_at(strip[:, 0], strip[:, 1]) + rng.normal(0, 0.03, len(strip))]),
        np.column_stack([roof, roof_z + rng.normal(0, 0.03, len(roof))]),
        np.column_stack([np.full(60, 10.0) + rng.uniform(0, 0.2, 60), wall_y, ground_at(10.0, wall_y) + wall_h]),
    ])
    truth = np.concatenate([np.ones(len(strip), bool), np.zeros(len(roof) + 60, bool)])
    return Scene("synthetic roof", points, truth)


def median_slope_deg(scene: Scene, cell: float = 1.0) -> float:
    """The median slope in degrees of the true ground, from a TIN-free estimate: plane
    fits to the ground points of each 3 × 3 m block (at least 6 points)."""
    xy, z = scene.points[scene.ground, :2], scene.points[scene.ground, 2]
    block = np.floor(xy / (3 * cell)).astype(np.int64)
    _, which = np.unique(block, axis=0, return_inverse=True)
    slopes = []
    for number in range(which.max() + 1):
        rows = which.ravel() == number
        if rows.sum() >= 6:
            design = np.column_stack([xy[rows] - xy[rows].mean(0), np.ones(rows.sum())])
            gx, gy, _ = np.linalg.lstsq(design, z[rows], rcond=None)[0]
            slopes.append(np.degrees(np.arctan(np.hypot(gx, gy))))
    return float(np.median(slopes))


@dataclass(frozen=True)
class FilterScores:
    """ISPRS filter-test scores in percent (kappa in percent too), and the counts."""

    type_1: float
    type_2: float
    total: float
    kappa: float
    points: int

    def as_dict(self) -> dict:
        return {"type_1": self.type_1, "type_2": self.type_2, "total": self.total,
                "kappa": self.kappa, "points": self.points}


def filter_scores(truth: np.ndarray, found: np.ndarray) -> FilterScores:
    """Sithole & Vosselman's scores of a ground classification `found` against `truth`
    (both (n,) bool, True = ground): Type I = ground rejected / ground, Type II = objects
    accepted / objects, total = wrong / all, and Cohen's kappa of the 2 × 2 table."""
    truth, found = np.asarray(truth, bool), np.asarray(found, bool)
    a = int(np.sum(truth & found))      # ground kept
    b = int(np.sum(truth & ~found))     # ground rejected (Type I)
    c = int(np.sum(~truth & found))     # objects accepted (Type II)
    d = int(np.sum(~truth & ~found))    # objects rejected
    n = a + b + c + d
    observed = (a + d) / n
    expected = ((a + b) * (a + c) + (c + d) * (b + d)) / n ** 2
    kappa = (observed - expected) / (1 - expected) if expected < 1 else 1.0
    return FilterScores(100 * b / max(a + b, 1), 100 * c / max(c + d, 1), 100 * (b + c) / n, 100 * kappa, n)
