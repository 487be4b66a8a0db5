"""Curtains in the axis frame: triangles that hang along the height axis or fold against their data.

A height field over a plane sees the scan along the plane's axis e3, as a depth camera sees
it along its rays (a parallel projection instead of a central one). Where the surface is
not a graph over the plane (a silhouette the surface curves past, an ear in front of the
head, two layers of points), the Delaunay triangulation in (x, y) joins points across the
gap with triangles that hang nearly parallel to e3 — curtains. Seen from above they are
the black streaks and folded specks of issue 10; issue 11's rule for depth jumps, "holes,
not curtains", applies to them as well. A triangle is dropped as

* "shadow_edge": one of its edges runs within `SHADOW_ANGLE` of e3 (grid.depth_jumps' rule,
  PCL's shadow angle, with e3 as the view ray);
* "grazing": its plane's normal is more than `GRAZING_ANGLE` from e3 (seen edge-on);
* "facing_away": its plane's normal is more than 90° from the data normal of one of its
  corners (both taken on the axis side, normal signs are not trusted). The linear
  triangle is then already folded against its data, by the measure of
  quality.folded_faces: the points it joins belong to surface patches that face apart
  (the front and the back of a silhouette, a point from another layer), and any
  interpolant of those normals over it turns by more than 90° inside it.

All three are properties of the input triangle and its data, not of the spline, so exact
data of a height field over the plane whose slopes are below tan(90° - GRAZING_ANGLE) and
whose curvature the triangles resolve lose nothing. Holes are left where curtains were;
`remove_curtains` then lets triangulation.trim peel the slivers and bowties the holes
expose, so the result keeps trim's guarantees (edge-manifold, no bowtie vertex).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from c1mesh.grid import GRAZING_ANGLE, SHADOW_ANGLE

REASONS = ("shadow_edge", "grazing", "facing_away")
"""Why a triangle is a curtain, in the order the rules are applied (a triangle counts once)."""


def curtain_triangles(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray, triangles: np.ndarray,
                      shadow_angle: float = SHADOW_ANGLE, grazing_angle: float = GRAZING_ANGLE
                      ) -> dict[str, np.ndarray]:
    """(T,) bool masks of the curtain triangles by reason (each triangle under its first reason).

    xy (n, 2), z (n,) and gradients (n, 2) of a height field (frame.HeightField: local
    coordinates, heights along e3, data gradients ∇z from the normals); triangles (T, 3)
    indices into them. Angles in degrees.
    """
    p = np.concatenate([xy, z[:, None]], axis=1)[triangles]                # (T, 3, 3)
    cos_shadow = np.cos(np.radians(shadow_angle))
    shadow = np.zeros(triangles.shape[0], dtype=bool)
    for k in range(3):
        edge = p[:, (k + 1) % 3] - p[:, k]
        shadow |= np.abs(edge[:, 2]) > cos_shadow * np.linalg.norm(edge, axis=1)
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal *= np.where(normal[:, 2] < 0, -1.0, 1.0)[:, None]               # on the axis side
    length = np.linalg.norm(normal, axis=1)
    with np.errstate(invalid="ignore"):
        grazing = ~(normal[:, 2] >= np.cos(np.radians(grazing_angle)) * length) & ~shadow
    # data normals on the axis side: (-g, 1); the plane's normal faces away from one of
    # them when their dot product is negative (the lengths do not change its sign).
    corner = gradients[triangles]                                           # (T, 3, 2)
    facing = normal[:, None, 2] - np.einsum("td,tkd->tk", normal[:, :2], corner)
    away = (facing < 0).any(axis=1) & ~shadow & ~grazing
    return {"shadow_edge": shadow, "grazing": grazing, "facing_away": away}


def remove_curtains(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray, triangles: np.ndarray,
                    trim_report):
    """Triangles (T', 3) without curtains, and the trim report (triangulation.TrimReport)
    with the curtains counted by reason in its "removed" (and the slivers and bowties the
    holes exposed added to trim's own counts).

    triangles: the trimmed triangulation (triangulation.trim), so that a triangle trim
    removes as too long or thin is counted there, not here.
    """
    from c1mesh.triangulation import trim

    masks = curtain_triangles(xy, z, gradients, triangles)
    curtain = masks["shadow_edge"] | masks["grazing"] | masks["facing_away"]
    removed = dict(trim_report.removed)
    removed.update({reason: int(masks[reason].sum()) for reason in REASONS})
    if not curtain.any():
        return triangles, replace(trim_report, removed=removed)
    kept, cleanup = trim(xy, triangles[~curtain], max_edge=None)
    for reason, count in cleanup.removed.items():
        removed[reason] = removed.get(reason, 0) + count
    used = np.count_nonzero(np.bincount(kept.ravel(), minlength=xy.shape[0]))
    return kept, replace(trim_report, triangles_after=int(kept.shape[0]), removed=removed,
                         unreferenced_points=int(xy.shape[0] - used))
