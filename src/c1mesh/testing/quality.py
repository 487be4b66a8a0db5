"""Surface quality measures on real scans: overshoot per triangle and folded faces.

Used by the tests and the noisy-data benchmark (benchmarks/noisy.py) to compare c1mesh
with peers on the same triangles; see docs/overshoot.md.
"""
from __future__ import annotations

import numpy as np

from c1mesh.engine.refine import lattice_pattern
from c1mesh.stages.height_field import gradients_to_normals

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


def reduced_hct_folded_faces(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray,
                             triangles: np.ndarray, subdiv: int = 2) -> tuple[int, int]:
    """(folded faces, faces) of matplotlib's reduced HCT as a refined mesh: the peer for
    `folded_faces` on the same data.

    xy (n, 2), z (n,), gradients (n, 2) in a height-field frame, triangles (T, 3). The
    surface is CubicTriInterpolator(kind='user') with these gradients, refined by
    UniformTriRefiner `subdiv` times (2: 16 faces per triangle, as c1mesh's level 4), with
    the interpolator's own gradients as the written normals.
    """
    import matplotlib.tri as mtri

    t = mtri.Triangulation(xy[:, 0], xy[:, 1], triangles=triangles)
    interp = mtri.CubicTriInterpolator(t, z, kind="user", dz=(gradients[:, 0], gradients[:, 1]))
    fine, values = mtri.UniformTriRefiner(t).refine_field(z, triinterpolator=interp, subdiv=subdiv)
    gx, gy = (np.ma.filled(a, 0.0) for a in interp.gradient(fine.x, fine.y))
    vertices = np.column_stack([fine.x, fine.y, np.ma.filled(values, np.nan)])
    faces = fine.triangles
    p = vertices[faces]
    ccw = ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
           - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])) > 0
    faces = np.where(ccw[:, None], faces, faces[:, ::-1])
    normals = gradients_to_normals(np.column_stack([gx, gy]))
    return folded_faces(vertices, faces, normals), len(faces)
