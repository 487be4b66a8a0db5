"""Delaunay triangulation of the projected scan, by the CDT library (`pythoncdt`, the
Python binding of artem-ogre/CDT: MPL-2.0, wheels on PyPI).

Why this library: on this project's 2-core machine it triangulates 1M uniform points in
1.5-1.8 s on one thread (0.8-0.9 s given them by grid cells, `_cdt`), against qhull's
10.8 s (scipy.spatial.Delaunay) and 3 s for the threaded qhull tiles this module used to
join; its output does not depend on timing; it also returns every triangle's neighbours.

* The points are triangulated as they are given, not shifted: CDT's predicates are exact
  (robust) on any floating-point input, so the triangulation is the exact Delaunay
  triangulation of those coordinates, the same whatever subset (a tile) holds them.
  Shifting (to a tile's centre, say) would round the coordinates, and then the shifted
  triangulation's orientations and in-circle decisions need not hold for the survey's:
  a mm-quantised grid rotated by 30 degrees gave 18-37 triangles inverted in the survey's
  coordinates, and tiles that did not join.
* Exact duplicate points: the first (lowest index) of each is triangulated, the others
  are in no triangle (CDT refuses duplicates; the fit merges them before anyway, this is
  for other callers, such as c1mesh.RSDInterpolator).
* Ties. Where four or more points are exactly cocircular (grids, quantised coordinates)
  the Delaunay triangulation is not unique, and CDT's choice depends on the order and
  the set of points it is given, so two tiles could cut one grid square with different
  diagonals and their join would not be a mesh. `canonical_ties` cuts every polygon of
  cocircular points (a face of the Delaunay subdivision) as the fan from its
  lowest-numbered point, deciding cocircularity in exact arithmetic (and, as a safety
  net, flipping any edge exact arithmetic finds not Delaunay). The triangulation is then
  a function of the points and their numbers alone; in a tile, whose points keep the
  survey's order, a triangle whose circle no unread point reaches is one of the whole
  survey's.

Trimming what should not be meshed is a fit stage: c1mesh.stages.trim.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from c1mesh.core.errors import InputError
from c1mesh.core.threads import parallel_blocks, take_rows
from c1mesh.engine import _ties
from c1mesh.engine.topology import triangle_neighbours


def delaunay(xy: ArrayLike) -> np.ndarray:
    """Delaunay triangles (T, 3) int64 of plane points xy (n, 2), counter-clockwise, indices
    into xy (module docstring: exactness, duplicates, ties). Raises InputError for
    non-finite or fewer than 3 points, or when all points lie on one line."""
    return delaunay_with_neighbours(xy)[0]


def delaunay_with_neighbours(xy: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """`delaunay`'s triangles (T, 3) and their neighbours: (T, 3) int64 the triangle across
    the edge opposite corner k, or -1 on the hull (topology.triangle_neighbours' layout)."""
    pts = as_xy(xy)
    if pts.shape[0] < 3:
        raise InputError(f"a triangulation needs at least 3 points, got {pts.shape[0]}")
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
    return canonical_ties(pts, triangles, neighbours)


SCREEN_BOUND = 1e-6
"""The in-circle screen's bound, relative to the determinant's permanent: quads below it
are decided exactly. Far above the rounding of the determinant (~1e-15) and of the
differences of the coordinates (state-plane feet at centimetre spacings: ~1e-9)."""


def canonical_ties(xy: np.ndarray, triangles: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Delaunay triangles (T, 3) and neighbours of xy (n, 2) with every face of
    cocircular points the fan from its lowest-numbered point (module docstring), from a
    Delaunay triangulation of xy (CDT's): any edge exact arithmetic finds not Delaunay is
    flipped first (Lawson, in rounds of flips that share no triangle; CDT's exact
    predicates leave none). Triangles keep their slots where the Delaunay triangulation is
    unique; all counter-clockwise."""
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    across = np.ascontiguousarray(neighbours, dtype=np.int64)
    changed, decided = False, {}
    while True:
        t, u, quads, det = _screened_edges(xy, tri, across, decided)
        illegal = det > 0
        if not illegal.any():
            break
        tri = tri if changed else tri.copy()
        _flip(tri, *_independent(t[illegal], u[illegal], quads[illegal], len(tri)))
        across, changed = triangle_neighbours(tri, len(xy)), True
    tied = det == 0
    if tied.any():
        tri = tri if changed else tri.copy()
        _fan_faces(xy, tri, t[tied], u[tied], quads[tied])
        across, changed = triangle_neighbours(tri, len(xy)), True
    return (tri, across) if changed else (triangles, neighbours)


def _screened_edges(xy: np.ndarray, tri: np.ndarray, across: np.ndarray, decided: dict) -> tuple:
    """The interior edges the screen (_ties.screen) flags, each once: triangles t and u
    across it (m,), quads (m, 4) (a: t's corner across the edge, b and c: the edge's ends
    in t's order, d: u's far corner; the quad runs a, b, d, c counter-clockwise) and the sign of the in-circle determinant
    (m,) int64: 1 when u's far corner is inside t's circle, 0 on it (exact for rectangles
    and near ties, the screen's own sign for the clearly illegal). decided: the exact
    signs of the quads already tested (a round of flips leaves most of them as they were)."""
    flag = np.zeros(tri.shape, dtype=np.int8)
    parallel_blocks(lambda part: _ties.screen(xy, tri, across, SCREEN_BOUND, part.start, part.stop, flag),
                    len(tri), 1 << 15)
    t, k = np.nonzero(flag)
    u = across[t, k]
    far = tri[u].sum(axis=1) - tri[t, (k + 1) % 3] - tri[t, (k + 2) % 3]       # u's corner off the edge
    quads = np.column_stack([tri[t, k], tri[t, (k + 1) % 3], tri[t, (k + 2) % 3], far])
    kind = flag[t, k]
    det = np.where(kind == _ties.ILLEGAL, 1, 0).astype(np.int64)
    near = np.flatnonzero(kind == _ties.NEAR)
    keys = list(map(tuple, quads[near].tolist()))
    new = [i for i, key in enumerate(keys) if key not in decided]
    for i, sign in zip(new, _incircle_signs(xy, quads[near[new]]).tolist()):
        decided[keys[i]] = sign
    det[near] = [decided[key] for key in keys]
    return t, u, quads, det


def _independent(t: np.ndarray, u: np.ndarray, quads: np.ndarray, size: int) -> tuple:
    """The edges (t, u, quads) that are the first listed edge of both their triangles: no
    two share a triangle, and the first edge is always among them."""
    first = np.full(size, len(t), dtype=np.int64)
    np.minimum.at(first, t, np.arange(len(t)))
    np.minimum.at(first, u, np.arange(len(t)))
    chosen = (first[t] == np.arange(len(t))) & (first[u] == np.arange(len(t)))
    return t[chosen], u[chosen], quads[chosen]


def _flip(tri: np.ndarray, t: np.ndarray, u: np.ndarray, quads: np.ndarray) -> None:
    """Replace edge b-c of each quad (a, b, c, d) by a-d, in triangles t and u of tri."""
    a, b, c, d = quads.T
    tri[t] = np.column_stack([a, b, d])             # quad a, b, d, c counter-clockwise
    tri[u] = np.column_stack([a, d, c])


def _incircle_signs(xy: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """(m,) int64 the sign of the in-circle determinant of each quad (m, 4) (a, b, c, d),
    in exact integers: 1 when d lies inside the circle through a, b, c (counter-clockwise),
    0 on it, -1 outside. Every coordinate of the points involved is a float, so an integer
    multiple of one power of two; the determinant of those integers (Python's, in numpy
    object arrays: one vectorised pass) has the sign of the true one."""
    if not len(quads):
        return np.zeros(0, dtype=np.int64)
    points, local = np.unique(quads, return_inverse=True)
    ratios = [value.as_integer_ratio() for value in xy[points].ravel().tolist()]
    scale = max(den for _, den in ratios)
    whole = np.empty(len(ratios), dtype=object)
    whole[:] = [num * (scale // den) for num, den in ratios]
    whole = whole.reshape(-1, 2)[local.reshape(quads.shape)]          # (m, 4, 2) integers
    diff = whole[:, :3] - whole[:, 3:4]                                 # a - d, b - d, c - d
    x, y = diff[..., 0], diff[..., 1]
    lift = x * x + y * y
    det = (lift[:, 0] * (x[:, 1] * y[:, 2] - x[:, 2] * y[:, 1])
           + lift[:, 1] * (x[:, 2] * y[:, 0] - x[:, 0] * y[:, 2])
           + lift[:, 2] * (x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0]))
    return np.array([(value > 0) - (value < 0) for value in det], dtype=np.int64)


def _fan_faces(xy: np.ndarray, tri: np.ndarray, t: np.ndarray, u: np.ndarray, quads: np.ndarray) -> None:
    """Rewrite tri (T, 3) in place: the faces joined by the cocircular edges between
    triangles t and u (quads (m, 4): t's corner across the edge, the edge's two ends, u's
    far corner) as fans from their lowest-numbered points. Faces of two triangles (grid
    squares) at once; larger ones (points on a circle) one by one."""
    count = np.bincount(np.concatenate([t, u]), minlength=len(tri))
    square = (count[t] == 1) & (count[u] == 1)
    a, b, c, d = quads[square].T
    flip = np.minimum(a, d) < np.minimum(b, c)      # the diagonal b-c misses the lowest point
    _flip(tri, t[square][flip], u[square][flip], quads[square][flip])
    for slots in _faces(t[~square], u[~square]):
        _fan(xy, tri, slots)


def _faces(t: np.ndarray, u: np.ndarray) -> list[np.ndarray]:
    """The triangles (ascending) of each face joined by edges t[i]-u[i] (union-find)."""
    parent: dict[int, int] = {}

    def root(x: int) -> int:
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for x, y in zip(t.tolist(), u.tolist()):
        parent[root(x)] = root(y)
    faces: dict[int, list[int]] = {}
    for x in sorted(parent):
        faces.setdefault(root(x), []).append(x)
    return [np.array(f, dtype=np.int64) for f in faces.values()]


def _fan(xy: np.ndarray, tri: np.ndarray, slots: np.ndarray) -> None:
    """The triangles tri[slots] (one convex face, its points on one circle) rewritten as the
    fan from the face's lowest-numbered point, counter-clockwise, in slot order."""
    corners = np.unique(tri[slots])
    offsets = xy[corners] - xy[corners].mean(axis=0)
    ring = corners[np.argsort(np.arctan2(offsets[:, 1], offsets[:, 0]), kind="stable")]
    ring = np.roll(ring, -int(np.argmin(ring)))
    tri[slots] = np.column_stack([np.full(len(ring) - 2, ring[0]), ring[1:-1], ring[2:]])


def _cdt(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CDT's Delaunay triangles (T, 3) int64 of distinct points xy (n, 2), counter-clockwise,
    and their neighbours (T, 3) int64 ((0, 3) each when the points are collinear). CDT
    keeps the triangle across edge (v_i, v_i+1) at slot i, and "none" as the largest
    uint32; slot k here is across the edge opposite corner k, -1 for none. CDT's own
    erase_super_triangle is replaced by a kernel pass over the rows before it
    (_ties.drop_super_triangle: the same rows, 0.35 s less at 1M points).

    CDT is given the points by cells of INSERTION_CELL points (_ties.cell_order), not in
    the caller's order: its own insertion order (a randomised k-d split) then reads
    memory near what it read last. 1M points in random order took 1.2-1.3 s, and 0.75-0.85 s
    so; points already in scan order gain little. The triangles are the same (the Delaunay
    triangulation, its ties cut by canonical_ties), in another order."""
    import pythoncdt

    order = _ties.cell_order(xy, INSERTION_CELL)
    triangulation = pythoncdt.Triangulation(pythoncdt.VertexInsertionOrder.AUTO,
                                            pythoncdt.IntersectingConstraintEdges.NOT_ALLOWED, 0.0)
    triangulation.insert_vertices(take_rows(xy, order))
    rows = triangulation.triangles_array(copy=False)
    dropped = _ties.drop_super_triangle(np.ascontiguousarray(rows["vertices"]),
                                        np.ascontiguousarray(rows["neighbors"]), len(xy), order)
    if dropped is not None:
        return dropped
    triangulation.erase_super_triangle()       # rows the kernel does not know: CDT's own erase
    rows = triangulation.triangles_array(copy=False)
    across = rows["neighbors"][:, [1, 2, 0]].astype(np.int64)
    across[across == np.iinfo(np.uint32).max] = -1
    return order[rows["vertices"].astype(np.int64)], across


INSERTION_CELL = 16.0
"""Points per cell of the order CDT is given the points in (`_cdt`): 4 to 256 measured
alike (0.75-0.83 s at 1M points), the caller's random order 1.2-1.3 s."""


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
