"""Folded faces of a fitted lattice spline, and the local stiffness that removes them (issue 38).

A smoothing fit on a lattice (stages.lattice_mesh) rings beside a bank or a ditch narrower
than its cells. Its refined mesh then folds a face: the face's geometric normal points more
than 90° from a corner's written normal (c1mesh.testing.quality.folded_faces), a black
speck or a crease in a shaded view. The survey-wide least strength (lattice_mesh.
least_strength) makes that rare but not impossible: whether a fit folds depends on where
the step falls among the cells (benchmarks.folds; docs/smoothing.md, "Folds at steps").

The net here is local and in the fit: after a solve, the cells within one cell of a face
that folds at FOLD_LEVEL get STIFFENING times the energy (their triangles' weight in the
functional), the fit is solved again at the same strength, and a cell that folds again
gets STIFFENING times more, for at most ROUNDS rounds (smoothing.smooth_fit). A fit that
folds no face is not touched. The check costs nothing on smooth terrain: a face can fold
only where the spline's gradient turns by more than 2 within a triangle (two gradients a, b
with a·b < −1 are more than 2 apart), and the spline's gradient keeps within about 4 times
the corners' spread from the triangle's linear slope (measured on the lattice's two
shapes: 2.8, and √2 more for a sub-face's secant), so only the triangles whose corner
gradients spread more than SPREAD from that slope are refined and looked at.
"""
from __future__ import annotations

import numpy as np

from c1mesh.core.threads import parallel_blocks
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.stages import _folds as kernel
from c1mesh.stages.surface import PLANE_LEVEL

FOLD_LEVEL = PLANE_LEVEL
"""The refinement level whose faces the net checks: the default mesh's."""
STIFFENING = 4.0
"""The factor on the energy of a folding cell's neighbourhood, each round it folds."""
ROUNDS = 4
"""The most solves the net adds to a fit."""
SPREAD = 1.0 / 6.0
"""A triangle is looked at when a corner's gradient lies more than this from the
triangle's linear slope (1 / (2 × 4), with a margin of 1.5)."""


CANDIDATE_BLOCK = 1 << 16
"""Triangles per block of the candidates' kernel (in the thread knob's threads)."""


def fold_candidates(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                    triangles: np.ndarray) -> np.ndarray:
    """Indices (k,) of the triangles (T, 3) of vertices points (N, 2) with values (N,) and
    gradients (N, 2) that may fold a face: a corner's gradient more than SPREAD from the
    gradient of the linear interpolant of the corners' values (_folds.spread_candidates,
    blocks of CANDIDATE_BLOCK in the thread knob's threads: 2M triangles in about 20 ms)."""
    xy = np.ascontiguousarray(points, dtype=np.float64)
    z = np.ascontiguousarray(values, dtype=np.float64)
    g = np.ascontiguousarray(gradients, dtype=np.float64)
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    marked = np.empty(tri.shape[0], dtype=np.uint8)
    parallel_blocks(lambda part: kernel.spread_candidates(xy, z, g, tri, SPREAD, marked, part.start, part.stop),
                    tri.shape[0], CANDIDATE_BLOCK)
    return np.flatnonzero(marked)


def folded_triangles(points: np.ndarray, values: np.ndarray, gradients: np.ndarray, triangles: np.ndarray,
                     scheme, level: int = FOLD_LEVEL) -> np.ndarray:
    """Indices (ascending) of the triangles whose level-`level` refinement of the RSD spline
    (vertex values and gradients, unit-normal edge directions, `scheme`) folds a face: a
    sub-face whose normal points more than 90° from one of its corners' (−∇F, 1). Only
    fold_candidates are refined; a triangle's patch needs only its own corners' data."""
    candidates = fold_candidates(points, values, gradients, triangles)
    if not candidates.size:
        return candidates
    corners = triangles[candidates]
    used, local = np.unique(corners, return_inverse=True)
    spline = RSDInterpolator(points[used], values[used], gradients[used],
                             triangles=local.reshape(corners.shape), scheme=scheme)
    mesh = spline.refine(level)
    p = np.column_stack([mesh.points, mesh.values])
    normals = np.column_stack([-mesh.gradients, np.ones(mesh.values.shape[0])])
    faces = p[mesh.triangles]
    geometric = np.cross(faces[:, 1] - faces[:, 0], faces[:, 2] - faces[:, 0])
    facing = np.einsum("fd,fkd->fk", geometric, normals[mesh.triangles])
    folded = (facing < 0).any(axis=1)
    return candidates[np.unique(mesh.parent[folded])]


class CellStiffness:
    """The net's stiffness over the cells of a lattice of spacing D: each cell's level (0:
    none), a triangle's energy multiplied by STIFFENING to the highest level among the
    cells within one cell of its own. A triangle's cell is its lowest corner in x and in y
    (both triangles of a lattice cell share it) in units of D, rounded: the same numbers in
    every tile of a survey (the lattice and its nodes' bits are the survey's)."""

    def __init__(self, points: np.ndarray, triangles: np.ndarray, spacing: float):
        corners = points[triangles]
        self.cells = np.floor(corners.min(axis=1) / spacing + 0.5).astype(np.int64)      # (T, 2)
        self.levels: dict[tuple[int, int], int] = {}

    def fold(self, folded: np.ndarray) -> None:
        """Raise the cells of the folded triangles (indices) one level above the highest
        level around them."""
        for cell in {tuple(c) for c in self.cells[folded].tolist()}:
            self.levels[cell] = self._around(*cell) + 1

    def _around(self, i: int, j: int) -> int:
        return max(self.levels.get((i + di, j + dj), 0) for di in (-1, 0, 1) for dj in (-1, 0, 1))

    def multipliers(self) -> np.ndarray:
        """(T,) each triangle's energy factor: STIFFENING ** the highest level within one cell."""
        out = np.ones(self.cells.shape[0])
        if not self.levels:
            return out
        lo = self.cells.min(axis=0) - 1
        shape = tuple(self.cells.max(axis=0) - lo + 2)
        grid = np.zeros(shape, dtype=np.int64)
        for (i, j), level in self.levels.items():
            if 0 <= i - lo[0] < shape[0] and 0 <= j - lo[1] < shape[1]:
                grid[i - lo[0], j - lo[1]] = level
        near = np.zeros_like(grid)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                shifted = grid[1 + di:shape[0] - 1 + di, 1 + dj:shape[1] - 1 + dj]
                near[1:-1, 1:-1] = np.maximum(near[1:-1, 1:-1], shifted)
        level = near[self.cells[:, 0] - lo[0], self.cells[:, 1] - lo[1]]
        return np.where(level > 0, STIFFENING ** level.astype(float), 1.0)


__all__ = ["CellStiffness", "FOLD_LEVEL", "ROUNDS", "SPREAD", "STIFFENING", "fold_candidates", "folded_triangles"]
