"""Terrain with steep steps: issue 38's samples for folded faces beside banks and ditches.

A 2 % / 1 % tilt with banks and ditches narrower than a cell of the lattice route
(stages.lattice_mesh), sampled at one point a SPACING square with 2 cm noise, the kind of
LiDAR ground tile on which a smoothing fit on a lattice rings and folds faces (docs/
smoothing.md, "Folds at steps"). Used by tests/test_lattice_steps.py and benchmarks/folds.py.
"""
from __future__ import annotations

import numpy as np

from c1mesh.core.cloud import PointCloud
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit
from c1mesh.testing.quality import folded_faces

SPACING = 1.3
"""The samples' point spacing (m): one point a 1.3 m square."""


def ramp(t: np.ndarray) -> np.ndarray:
    """0 → 1 as t goes 0 → 1, smoothly (smoothstep), flat outside."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def bank_heights(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The noise-free terrain (m) at x, y (m): a 2 % / 1 % tilt, a 4 m bank over 1 m across
    x = 12, a 3 m ditch with 1 m walls across y = 24..26 and a 7 m bank over 1.4 m along
    x + y = 44."""
    return (0.02 * x + 0.01 * y + 4.0 * ramp(x - 12.0) - 3.0 * (ramp(y - 24.0) - ramp(y - 26.0))
            + 7.0 * ramp((x + y - 44.0) / 1.4))


def banks(seed: int, side: float = 36.0, shift: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """(n, 3) points of bank_heights over [0, side)², on a SPACING grid jittered by ±45 %
    with 2 cm noise (784 points at side 36). shift (m): the banks and the ditch moved by
    it while the sampling stays (the steps at other sub-cell positions of the lattice,
    which the points' median places; the points themselves are drawn as with no shift)."""
    rng = np.random.default_rng(seed)
    g = np.arange(0.0, side, SPACING)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    x = x + rng.uniform(-0.45, 0.45, x.size) * SPACING
    y = y + rng.uniform(-0.45, 0.45, y.size) * SPACING
    sx, sy = shift
    z = 0.02 * sx + 0.01 * sy + bank_heights(x - sx, y - sy)
    return np.column_stack([x, y, z + rng.normal(0.0, 0.02, x.size)])


def walls(seed: int, side: float = 36.0) -> np.ndarray:
    """banks(seed, side) plus three lines of points standing 0-6 m off the ground, 0.7 m
    apart and 0.2 m wide: walls or hedges left in the ground class (narrower than a cell)."""
    ground = banks(seed, side)
    rng = np.random.default_rng(seed + 1)
    lines = []
    for x0, y0, x1, y1, height in ((20.0, 4.0, 20.0, 14.0, 6.0), (4.0, 30.0, 14.0, 31.0, 3.0),
                                   (28.0, 30.0, 33.0, 20.0, 5.0)):
        n = int(np.hypot(x1 - x0, y1 - y0) / 0.7)
        t = rng.random(n)
        x = x0 + t * (x1 - x0) + rng.normal(0.0, 0.2, n)
        y = y0 + t * (y1 - y0) + rng.normal(0.0, 0.2, n)
        lines.append(np.column_stack([x, y, bank_heights(x, y) + rng.uniform(0.0, height, n)]))
    return np.concatenate([ground, *lines])


def lattice_folds(points: np.ndarray, workers: int | None = None) -> tuple[int, float]:
    """(folded faces by quality.folded_faces, chosen strength) of `c1mesh fit --smooth auto
    --spacing SPACING` of the points (n, 3) at the default level, in `workers` threads
    (None: the process's setting): the measure of tests/test_lattice_steps.py and
    benchmarks/folds.py."""
    result = fit(PointCloud(points=points), None, FitOptions(smooth="auto", spacing=SPACING, workers=workers))
    mesh = result.mesh
    return folded_faces(mesh.vertices, mesh.faces, mesh.vertex_normals), float(result.report["smoothing"]["strength"])


__all__ = ["SPACING", "bank_heights", "banks", "lattice_folds", "ramp", "walls"]
