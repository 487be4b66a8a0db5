"""Delaunay triangulation of the projected scan, by the CDT library (`pythoncdt`, the
Python binding of artem-ogre/CDT: MPL-2.0, wheels on PyPI).

Why this library: on this project's 2-core machine it triangulates 1M uniform points in
1.5-1.8 s on one thread, against qhull's 10.8 s (scipy.spatial.Delaunay) and 3 s for the
threaded qhull tiles this module used to join; its output does not depend on timing; it
also returns every triangle's neighbours.

* The points are centred on their bounding box first (as LiDAR state-plane coordinates
  lose the digits the in-circle test needs otherwise).
* Exact duplicate points: the first (lowest index) of each is triangulated, the others
  are in no triangle (CDT refuses duplicates; the fit merges them before anyway, this is
  for other callers, such as c1mesh.RSDInterpolator).
* For cocircular points (grids) the Delaunay triangulation is not unique; CDT chooses one
  of the valid ones.

Trimming what should not be meshed is a fit stage: c1mesh.stages.trim.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from c1mesh.core.errors import InputError


def delaunay(xy: ArrayLike) -> np.ndarray:
    """Delaunay triangles (T, 3) int64 of plane points xy (n, 2), counter-clockwise, indices
    into xy (module docstring: centring, duplicates, ties). Raises InputError for
    non-finite or fewer than 3 points, or when all points lie on one line."""
    return delaunay_with_neighbours(xy)[0]


def delaunay_with_neighbours(xy: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """`delaunay`'s triangles (T, 3) and the neighbours CDT keeps for them: (T, 3) int64 the
    triangle across the edge opposite corner k, or -1 on the hull (topology.triangle_neighbours'
    layout, without its edge sort)."""
    pts = as_xy(xy)
    if pts.shape[0] < 3:
        raise InputError(f"a triangulation needs at least 3 points, got {pts.shape[0]}")
    pts = pts - (pts.min(axis=0) + pts.max(axis=0)) / 2
    try:
        triangles, neighbours = _cdt(pts)
    except RuntimeError as exc:
        if "uplicate" not in str(exc):
            raise
        first = first_of_duplicates(pts)
        triangles, neighbours = _cdt(pts[first])
        triangles = first[triangles]
    if not len(triangles):
        raise InputError("the points cannot be triangulated: they all lie on one line (or "
                         "coincide); a surface needs points spread over an area")
    return triangles, neighbours


def _cdt(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CDT's Delaunay triangles (T, 3) int64 of distinct points xy (n, 2), counter-clockwise,
    and their neighbours (T, 3) int64 ((0, 3) each when the points are collinear). CDT
    keeps the triangle across edge (v_i, v_i+1) at slot i, and "none" as the largest
    uint32; slot k here is across the edge opposite corner k, -1 for none."""
    import pythoncdt

    triangulation = pythoncdt.Triangulation(pythoncdt.VertexInsertionOrder.AUTO,
                                            pythoncdt.IntersectingConstraintEdges.NOT_ALLOWED, 0.0)
    triangulation.insert_vertices(np.ascontiguousarray(xy, dtype=np.float64))
    triangulation.erase_super_triangle()
    rows = triangulation.triangles_array(copy=False)
    across = rows["neighbors"][:, [1, 2, 0]].astype(np.int64)
    across[across == np.iinfo(np.uint32).max] = -1
    return rows["vertices"].astype(np.int64), across


def first_of_duplicates(xy: np.ndarray) -> np.ndarray:
    """Ascending indices (m,) of the first (lowest index) point at each distinct position of
    xy (n, 2)."""
    order = np.lexsort((np.arange(len(xy)), xy[:, 1], xy[:, 0]))
    new = np.ones(len(xy), dtype=bool)
    new[1:] = np.any(xy[order][1:] != xy[order][:-1], axis=1)
    return np.sort(order[new])


def as_xy(xy: ArrayLike) -> np.ndarray:
    pts = np.asarray(xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise InputError(f"plane points must be an array of shape (n, 2), got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise InputError("plane points must be finite; drop NaN/Inf points before triangulating")
    return pts
