"""Surface quality measures on real scans: overshoot per triangle and folded faces.

Used by the tests and the noisy-data benchmark (benchmarks/noisy.py) to compare c1mesh
with peers on the same triangles; see docs/overshoot.md.
"""
from __future__ import annotations

import numpy as np

from c1mesh.refine import lattice_pattern

OVERSHOOT_EDGE_FRACTION = 0.25
"""A triangle overshoots when its surface leaves its corner heights' range by more than
this fraction of its longest edge (the measure of issue 10)."""


def interior_lattice(level: int = 10) -> np.ndarray:
    """Barycentric coordinates (P, 3) of the lattice points strictly inside a triangle
    (level L: points a/L with a1 + a2 + a3 = L, all a > 0): where each triangle's own
    surface is sampled, so every method is evaluated on the triangle the point lies in."""
    pattern = lattice_pattern(level)
    return pattern.lattice[pattern.interior] / level


def lattice_points(xy: np.ndarray, triangles: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Plane points (T, P, 2) of the barycentric pattern lam (P, 3) in every triangle."""
    return np.einsum("pk,tkd->tpd", lam, xy[triangles])


def overshoot(surface: np.ndarray, z: np.ndarray, xy: np.ndarray, triangles: np.ndarray,
              fraction: float = OVERSHOOT_EDGE_FRACTION) -> dict:
    """How far each triangle's surface leaves the range of its corner heights.

    surface (T, P): a method's heights at P sample points of each triangle; z (n,) the
    data heights; xy (n, 2); triangles (T, 3). Returns {"per_triangle" (T,) overshoot
    (>= 0, height units), "count" of triangles overshooting by more than fraction × their
    longest edge, "max" overshoot} (NaN samples are ignored).
    """
    corners = z[triangles]
    with np.errstate(invalid="ignore"):
        above = np.nanmax(surface, axis=1) - corners.max(axis=1)
        below = corners.min(axis=1) - np.nanmin(surface, axis=1)
    over = np.nan_to_num(np.maximum(np.maximum(above, below), 0.0))
    p = xy[triangles]
    longest = np.max([np.linalg.norm(p[:, k] - p[:, (k + 1) % 3], axis=1) for k in range(3)], axis=0)
    return {"per_triangle": over, "count": int(np.count_nonzero(over > fraction * longest)),
            "max": float(over.max(initial=0.0))}


def folded_faces(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> int:
    """Faces whose geometric normal is more than 90° from any of their corner normals.

    vertices (M, 3), faces (K, 3) counter-clockwise seen from the side the vertex normals
    (M, 3) point to. Issue 10's defect is a face whose geometric normal is more than 90°
    away from "the normals written at its corners": a shader lights each corner with its
    written normal, so one corner facing away from its own face already draws a black
    speck or a needle-like crease, even when the mean of the three corners agrees with the
    face. Comparing with every corner (not their mean) counts those too.
    """
    p = vertices[faces]
    geometric = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    facing = np.einsum("fd,fkd->fk", geometric, normals[faces])
    return int(np.count_nonzero((facing < 0).any(axis=1)))
