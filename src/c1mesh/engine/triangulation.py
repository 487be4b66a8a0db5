"""Delaunay triangulation of the projected scan.

`delaunay` returns the same triangles as `scipy.spatial.Delaunay(xy).simplices` (as a set
of vertex triples, for points in general position), 2-2.5x faster at 1M uniform random
points and 1.6x at 100k (medians of 5, same run, on a loaded 2-core machine): qhull is
super-linear in practice (~3.5 µs/point on 10k points, ~10 µs/point on 1M, presumably
cache misses), so large inputs are triangulated tile by tile and joined exactly. Tiles
run in c1mesh.core.threads.workers() threads (qhull releases the GIL; results are collected in
tile order, so the output does not depend on timing or the count): 1.6x faster at 1M
points on 2 cores. (Tried and
dropped: Morton presorting, 1.3x; qhull options, no gain.)

* Split the points into ~`TILE_POINTS`-point tiles: x-quantile strips cut at y-quantiles,
  outer sides extended to infinity.
* Triangulate each tile with qhull. A tile triangle whose circumdisk lies strictly inside
  its tile's rectangle is "certified": the disk holds no tile point, and all other points
  lie outside the rectangle, so the disk is empty and the triangle belongs to the global
  Delaunay triangulation (DT).
* A point all of whose tile triangles are certified, and which is not on its tile's hull,
  has its complete global star already. Every global triangle that is not certified
  therefore has all three vertices among the other points, the "band" S. DT(S) contains
  those triangles (their disks are empty of all points, hence of S).
* The certified triangles leave uncovered regions bounded by "frontier" edges (edges of
  certified triangles whose neighbour is not certified). Frontier edges are global
  Delaunay edges between points of S, so they are edges of DT(S): flood-filling DT(S)
  from the uncovered side of the frontier, without crossing it, yields exactly the
  missing triangles.
* Check: the triangle count obeys Euler's formula for the vertices used and the hull, and
  the areas add up to the hull's area. If not (near-degenerate input, qhull errors in a
  tile), fall back to one plain qhull call, so the result is always a valid triangulation.

For cocircular points (grids) the Delaunay triangulation is not unique; then `delaunay`
returns a valid Delaunay triangulation that may choose other diagonals than plain qhull.
Exact duplicate points: qhull uses one copy (which one is unspecified); c1mesh's
height_field merges duplicates before triangulating.

Trimming what should not be meshed is a fit stage: c1mesh.stages.trim.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError

from c1mesh.core.errors import InputError
from c1mesh.core.threads import map_in_threads

TILE_POINTS = 10_000
"""Points per tile: qhull time per point is flat up to ~25k points and grows beyond."""
TILED_FROM = 50_000
"""Inputs with fewer points go to one plain qhull call (tiling gains nothing there)."""
# --- Delaunay -----------------------------------------------------------------------------

def delaunay(xy: ArrayLike) -> np.ndarray:
    """Delaunay triangles (T, 3) int64 of plane points xy (n, 2), counter-clockwise.

    The points are centred on their bounding box first; the result is then the same set
    of triangles as scipy.spatial.Delaunay on the centred points, which for points in
    general position is scipy.spatial.Delaunay(xy) (module docstring: ties, duplicates).
    Centring matters at LiDAR offsets: qhull on raw state-plane coordinates (~6.4e5,
    8.5e5 ft) is not Delaunay (3,858 edges of 4_6_crop.las fail the exact empty-circle
    test; none after centring). Raises InputError for non-finite or fewer than 3 points,
    or when all points lie on one line.
    """
    pts = as_xy(xy)
    if pts.shape[0] < 3:
        raise InputError(f"a triangulation needs at least 3 points, got {pts.shape[0]}")
    pts = pts - (pts.min(axis=0) + pts.max(axis=0)) / 2
    if pts.shape[0] >= TILED_FROM:
        try:
            return _delaunay_tiled(pts)
        except (_TilingFailed, QhullError):
            pass
    return _qhull(pts)


def as_xy(xy: ArrayLike) -> np.ndarray:
    pts = np.asarray(xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise InputError(f"plane points must be an array of shape (n, 2), got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise InputError("plane points must be finite; drop NaN/Inf points before triangulating")
    return pts


def _qhull(xy: np.ndarray) -> np.ndarray:
    """One plain scipy/qhull Delaunay call, triangles made counter-clockwise."""
    try:
        simplices = Delaunay(xy).simplices
    except QhullError as exc:
        raise InputError("the points cannot be triangulated: they all lie on one line (or "
                         "coincide); a surface needs points spread over an area") from exc
    tri = simplices.astype(np.int64)
    cw = _geometry(xy, tri)[0] < 0
    tri[cw] = tri[cw][:, ::-1]
    return tri


def _geometry(xy: np.ndarray, tri: np.ndarray):
    """Twice the signed area, circumcentre x and y, and circumradius of triangles (T, 3)."""
    p = xy[tri]
    a = p[:, 0]
    b = p[:, 1] - a
    c = p[:, 2] - a
    cross = b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]
    b2 = np.einsum("ij,ij->i", b, b)
    c2 = np.einsum("ij,ij->i", c, c)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (c[:, 1] * b2 - b[:, 1] * c2) / (2 * cross)
        uy = (b[:, 0] * c2 - c[:, 0] * b2) / (2 * cross)
    return cross, a[:, 0] + ux, a[:, 1] + uy, np.hypot(ux, uy)


class _TilingFailed(RuntimeError):
    """The tiled triangulation did not pass its consistency check."""


def _delaunay_tiled(xy: np.ndarray, per_tile: int = TILE_POINTS) -> np.ndarray:
    """Delaunay triangles of xy (n, 2), tile by tile (module docstring); _TilingFailed if unsure."""
    n = xy.shape[0]
    scale = float(np.ptp(xy, axis=0).max())
    certified, frontier, band = [], [], np.zeros(n, dtype=bool)
    area = 0.0
    # qhull releases the GIL: 2 threads about halve the time; the passes come back in tile
    # order (the same result at any thread count), and a failed tile stops the rest
    passes = map_in_threads(lambda tile: _tile_pass(xy, *tile, scale), list(_tiles(xy, per_tile)))
    for tri, keys, tile_area, not_final in passes:
        certified.append(tri)
        frontier.append(keys)
        area += tile_area
        band[not_final] = True
    filled, filled_area, hull_area, hull_edges = _fill_band(
        xy, np.flatnonzero(band), np.concatenate(frontier),
        whole=not any(len(tri) for tri in certified))
    out = np.concatenate(certified + [filled])             # one copy of the triangles
    used = np.count_nonzero(np.bincount(out.ravel(), minlength=n))
    if out.shape[0] != 2 * used - hull_edges - 2 or not np.isclose(
            area + filled_area, hull_area, rtol=1e-9, atol=0):
        raise _TilingFailed("tiled triangulation failed its Euler/area check")
    return out


def _tiles(xy: np.ndarray, per_tile: int):
    """Yield (point indices, (x0, x1, y0, y1)) of about per_tile points each, covering the plane.

    k x k tiles: k x-quantile strips, each cut at its own y-quantiles; a point on a cut
    belongs to the upper tile, outer sides are at infinity.
    """
    k = max(1, int(round(np.sqrt(xy.shape[0] / per_tile))))
    q = np.linspace(0, 1, k + 1)[1:-1]
    for idx, (x0, x1) in _split(np.arange(xy.shape[0]), xy[:, 0], q):
        for part, (y0, y1) in _split(idx, xy[idx, 1], q):
            yield part, (x0, x1, y0, y1)


def _split(idx: np.ndarray, values: np.ndarray, q: np.ndarray):
    """Split idx by the quantiles q of values: yield (indices, (low, high)) per slab."""
    cuts = np.quantile(values, q)
    slab = np.searchsorted(cuts, values, side="right")
    order = np.argsort(slab, kind="stable")
    edges = np.concatenate([[-np.inf], cuts, [np.inf]])
    parts = np.split(idx[order], np.searchsorted(slab[order], np.arange(1, len(cuts) + 1)))
    for i, part in enumerate(parts):
        yield part, (edges[i], edges[i + 1])


def _tile_pass(xy: np.ndarray, idx: np.ndarray, rect, scale: float):
    """Triangulate one tile; return its certified triangles (ccw, global indices), the keys
    u*n+v of its frontier half-edges u->v (ccw in the certified triangle), the certified
    doubled area and the global indices of the tile's non-final points (the band's share).
    Touches no shared state, so tiles can run in threads."""
    n = xy.shape[0]
    x0, x1, y0, y1 = rect
    local = Delaunay(xy[idx])
    s = local.simplices
    cross, cx, cy, r = _geometry(xy[idx], s)
    margin = 1e-6 * r + 1e-12 * scale          # circumcircles are computed, not exact
    ok = (cx - r - margin > x0) & (cx + r + margin < x1) & (cy - r - margin > y0) & \
         (cy + r + margin < y1)
    not_final = idx[np.concatenate([s[~ok].ravel(), local.convex_hull.ravel()])]
    nb = local.neighbors
    t, k = np.nonzero(ok[:, None] & ~((nb >= 0) & ok[nb]))   # certified | not-certified edges
    u, v = s[t, (k + 1) % 3], s[t, (k + 2) % 3]              # edge opposite vertex k
    cw = cross[t] < 0
    u, v = np.where(cw, v, u), np.where(cw, u, v)
    keys = idx[u].astype(np.int64) * n + idx[v]
    tri = idx[s[ok]].astype(np.int64)
    flip = cross[ok] < 0
    tri[flip] = tri[flip][:, ::-1]
    return tri, keys, float(np.abs(cross[ok]).sum()), not_final


def _fill_band(xy: np.ndarray, band: np.ndarray, frontier: np.ndarray, whole: bool):
    """Triangles of DT(band) on the uncovered side of the frontier (module docstring).

    Returns (triangles ccw with global indices, their doubled area, the doubled hull
    area, the number of hull edges). With whole=True (nothing certified) all of DT(band).
    """
    n = xy.shape[0]
    dt = Delaunay(xy[band])
    s = dt.simplices
    cross = _geometry(xy[band], s)[0]
    tri = band[s].astype(np.int64)
    a, b = tri[:, [1, 2, 0]], tri[:, [2, 0, 1]]              # edge opposite vertex k: a -> b
    cw = (cross < 0)[:, None]
    forward = np.where(cw, b * n + a, a * n + b)             # as a ccw half-edge of this triangle
    backward = np.where(cw, a * n + b, b * n + a)
    outside = np.isin(backward, frontier)                    # a certified triangle is across
    inside = np.isin(forward, frontier)                      # this triangle is a certified one
    nb = dt.neighbors
    t, k = np.nonzero((nb >= 0) & ~(outside | inside))
    graph = coo_matrix((np.ones(t.size, dtype=np.int8), (t, nb[t, k])), shape=(len(s),) * 2)
    label = connected_components(graph, directed=False)[1]
    seeded = np.zeros(label.max() + 1, dtype=bool)
    seeded[label[outside.any(axis=1)]] = True
    keep = np.ones(len(s), dtype=bool) if whole else seeded[label] & ~inside.any(axis=1)
    tri = tri[keep]
    flip = cross[keep] < 0
    tri[flip] = tri[flip][:, ::-1]
    return tri, float(np.abs(cross[keep]).sum()), float(np.abs(cross).sum()), len(dt.convex_hull)
