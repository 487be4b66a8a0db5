"""Plane geometry for the buffered tile Delaunay (c1mesh.survey.buffered_delaunay) and the
tile normals (c1mesh.survey.tile_normals): the strips of the survey's box a tile has not
read, the survey's hull clipped to them, circumcircles and the tests that a disk or a
half-plane stays clear of what was not read. Coordinates are relative to the tile's
centre (frame units); every test is conservative (touching counts as reaching)."""
from __future__ import annotations

import numpy as np

from c1mesh.survey import _strip_geometry as kernel


def unread_strips(read_box, box, centre) -> np.ndarray:
    """(s, 4) the parts of B outside the read rectangle E, as rectangles (x0, y0, x1, y1)
    relative to centre: the left, right, bottom and top strips of B that E does not reach."""
    ex0, ey0, ex1, ey1 = read_box
    bx0, by0, bx1, by1 = box
    strips = []
    if ex0 > bx0:
        strips.append((bx0, by0, ex0, by1))
    if ex1 < bx1:
        strips.append((ex1, by0, bx1, by1))
    if ey0 > by0:
        strips.append((bx0, by0, bx1, ey0))
    if ey1 < by1:
        strips.append((bx0, ey1, bx1, by1))
    out = np.array(strips, dtype=np.float64).reshape(-1, 4)
    return out - np.tile(centre, 2)


def disks_clear(xy: np.ndarray, triangles: np.ndarray, strips: np.ndarray,
                 regions: list[np.ndarray] | None = None) -> np.ndarray:
    """(k,) True where a triangle's circumdisk stays clear of every unread strip (with a
    relative margin of 1e-9 of the radius, so rounding never clears a disk that touches
    one). regions: each strip clipped to the survey's hull (convex polygons, (m, 2)), or
    None: a disk that reaches a strip's rectangle must then also reach its polygon."""
    centre, radius = circumcircles(xy, triangles)
    return _clear(centre, radius, strips, regions, float(np.abs(xy).max()))


def disks_meet_polygon(centre: np.ndarray, reach: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(k,) True where the closed disk (centre, reach) meets the convex polygon (m, 2)
    (counter-clockwise; empty: meets nothing): its centre is inside, or an edge is within
    reach. A disk with a non-finite centre or reach (a collinear triangle's, a half-plane)
    counts as meeting it: the test must never clear what it cannot measure."""
    if len(polygon) == 0:
        return np.zeros(len(centre), dtype=bool)
    unmeasured = ~(np.isfinite(centre).all(axis=1) & np.isfinite(reach))
    centre = np.where(unmeasured[:, None], 0.0, centre)
    if len(polygon) < 3:
        polygon = np.concatenate([polygon, polygon[:1]])
    a, b = polygon, np.roll(polygon, -1, axis=0)
    meets = np.zeros(len(centre), dtype=bool)
    inside = np.ones(len(centre), dtype=bool)
    for (ax, ay), (bx, by) in zip(a, b):
        ex, ey = bx - ax, by - ay
        px, py = centre[:, 0] - ax, centre[:, 1] - ay
        inside &= ex * py - ey * px >= 0.0
        t = np.clip((px * ex + py * ey) / max(ex * ex + ey * ey, 1e-300), 0.0, 1.0)
        meets |= np.hypot(px - t * ex, py - t * ey) <= reach
    return meets | inside | unmeasured


def clip_to_hull(strips: np.ndarray, hull: np.ndarray) -> list[np.ndarray]:
    """Each strip rectangle (x0, y0, x1, y1) intersected with the convex polygon hull
    (m, 2, counter-clockwise), by clipping the hull against the rectangle's four sides."""
    regions = []
    for x0, y0, x1, y1 in strips:
        polygon = hull
        for axis, bound, keep_below in ((0, x0, False), (0, x1, True), (1, y0, False), (1, y1, True)):
            polygon = _clip_half(polygon, axis, bound, keep_below)
        regions.append(polygon)
    return regions


def _clip_half(polygon: np.ndarray, axis: int, bound: float, keep_below: bool) -> np.ndarray:
    """The convex polygon cut to coordinate[axis] <= bound (keep_below) or >= bound."""
    if len(polygon) == 0:
        return polygon
    side = polygon[:, axis] - bound
    if keep_below:
        side = -side
    out = []
    for i in range(len(polygon)):
        p, q = polygon[i], polygon[(i + 1) % len(polygon)]
        sp, sq = side[i], side[(i + 1) % len(polygon)]
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            out.append(p + (q - p) * (sp / (sp - sq)))
    return np.array(out).reshape(-1, 2)


def circumcircles(xy: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Circumcentres (k, 2) and radii (k,) of triangles (k, 3) into xy (n, 2): the first
    corner a plus u, where 2 (b − a)·u = |b − a|² and 2 (c − a)·u = |c − a|² (solved by
    Cramer's rule); a degenerate (collinear) triangle gets an infinite radius. One pass of
    the kernel (survey/_strip_geometry.pyx)."""
    tri = np.ascontiguousarray(triangles, dtype=np.int64).reshape(-1, 3)
    centre, radius = np.empty((len(tri), 2)), np.empty(len(tri))
    kernel.circumcircles(np.ascontiguousarray(xy, dtype=np.float64), tri, centre, radius)
    return centre, radius


def hull_edges_final(xy, index, simplices, neighbors, own, strips, hull_edges) -> bool:
    """True when every hull edge of the tile's triangulation that ends at one of the tile's
    own points is a hull edge of the survey: an edge of the survey's hull (hull_edges, a
    set of (lower, higher) survey numbers), or, without it, an edge with no strip corner on
    or beyond its line (a strip is convex: it meets the open half-plane beyond the edge only
    if a corner lies there)."""
    tri, slot = np.nonzero(neighbors < 0)
    if tri.size == 0 or len(strips) == 0:
        return True
    a = simplices[tri, (slot + 1) % 3]
    b = simplices[tri, (slot + 2) % 3]
    opposite = simplices[tri, slot]
    mine = own[a] | own[b]
    a, b, opposite = a[mine], b[mine], opposite[mine]
    if a.size == 0:
        return True
    if hull_edges is not None:
        ia, ib = index[a], index[b]
        return all(edge in hull_edges for edge in zip(np.minimum(ia, ib).tolist(), np.maximum(ia, ib).tolist()))
    edge = xy[b] - xy[a]
    normal = np.column_stack([edge[:, 1], -edge[:, 0]])
    inward = ((xy[opposite] - xy[a]) * normal).sum(axis=1)
    normal[inward > 0] *= -1.0                             # point away from the triangle
    length = np.hypot(normal[:, 0], normal[:, 1])
    scale = np.abs(strips).max()
    for x0, y0, x1, y1 in strips:
        for corner in ((x0, y0), (x1, y0), (x0, y1), (x1, y1)):
            beyond = ((np.asarray(corner) - xy[a]) * normal).sum(axis=1)
            if (beyond > -1e-12 * scale * length).any():
                return False
    return True


def smallest_empty_circle(xy, simplices, neighbors, t, k, a, b, centres) -> tuple[np.ndarray, np.ndarray]:
    """(centres (e, 2), radii (e,)) of the smallest circle through each edge's ends (a, b)
    that is empty of the triangulated points: on the edge's bisector, between the
    circumcentres of its two triangles (or from triangle t's circumcentre outwards, for a
    hull edge: t's edge opposite its corner k), the point nearest the edge's midpoint.
    xy (n, 2); simplices, neighbors (T, 3); t, k, a, b (e,); centres (T, 2) the
    triangles' circumcentres. One pass of the kernel (survey/_strip_geometry.pyx)."""
    best, radius = np.empty((len(t), 2)), np.empty(len(t))
    ints = (np.ascontiguousarray(x, dtype=np.int64) for x in (simplices, neighbors, t, k, a, b))
    kernel.smallest_empty_circles(np.ascontiguousarray(xy, dtype=np.float64), *ints,
                                  np.ascontiguousarray(centres, dtype=np.float64), best, radius)
    return best, radius


def triangle_flags(xy: np.ndarray, simplices: np.ndarray, own: np.ndarray, index: np.ndarray,
                   bound: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(longest (T,), at_own (T,) bool, mine (T,) bool) of a tile's triangles simplices
    (T, 3) into its points xy (n, 2) (survey coordinates: trim's bits), own (n,) bool and
    survey numbers index (n,): each triangle's longest edge; whether a corner is own and
    longest <= bound (its disk must be certified); whether its lowest-numbered corner is
    own and longest <= bound (the tile keeps it). One pass of the kernel."""
    return _flags(xy, simplices, None, own, index, bound)[:3]


def flags_and_edges(xy: np.ndarray, simplices: np.ndarray, neighbors: np.ndarray, own: np.ndarray,
                    index: np.ndarray, bound: float):
    """triangle_flags' three arrays, and from the same pass (edges (E, 4) int64 rows
    (t, k, a, b), lengths (E,)): each edge of the triangulation once (on the hull, or
    towards a higher-numbered triangle: neighbors (T, 3)), at most `bound` long, whose
    lower-numbered end is own; t, k the triangle and the corner it is opposite, a, b its
    ends (corners k + 1, k + 2), lengths hypot(a − b) in xy's unit."""
    return _flags(xy, simplices, neighbors, own, index, bound)


def _flags(xy, simplices, neighbors, own, index, bound):
    T = len(simplices)
    longest, at_own, mine = np.empty(T), np.empty(T, dtype=np.uint8), np.empty(T, dtype=np.uint8)
    rows = 0 if neighbors is None else 3 * T
    edges, lengths = np.empty((rows, 4), dtype=np.int64), np.empty(rows)
    count = kernel.triangle_flags(np.ascontiguousarray(xy, dtype=np.float64),
                                  np.ascontiguousarray(simplices, dtype=np.int64),
                                  np.ascontiguousarray(np.empty((0, 3)) if neighbors is None else neighbors,
                                                       dtype=np.int64),
                                  np.ascontiguousarray(own, dtype=bool).view(np.uint8),
                                  np.ascontiguousarray(index, dtype=np.int64), float(bound), longest, at_own,
                                  mine, edges, lengths)
    return longest, at_own.view(bool), mine.view(bool), edges[:count], lengths[:count].copy()


def centres_clear(centre, radius, strips, regions, scale) -> np.ndarray:
    """(e,) True where the disk (centre, radius) stays clear of every unread strip clipped
    to the survey's hull (conservative, as disks_clear); scale: the largest coordinate
    magnitude of the tile's points, whose 1e-12 is added to every radius."""
    return _clear(np.ascontiguousarray(centre, dtype=np.float64), np.ascontiguousarray(radius, dtype=np.float64),
                  strips, regions, float(scale))


def _clear(centre: np.ndarray, radius: np.ndarray, strips: np.ndarray, regions, scale: float) -> np.ndarray:
    """(k,) True where the disk (centre (k, 2), radius (k,)) grown by 1e-9 of its radius
    and 1e-12 of scale reaches no strip rectangle, strips (s, 4) (the kernel's test), or, given
    regions (the strips clipped to the hull), no region of a rectangle it reaches."""
    strips = np.ascontiguousarray(strips, dtype=np.float64).reshape(-1, 4)
    hits = np.empty((len(centre), len(strips)), dtype=np.uint8)
    kernel.strip_hits(centre, radius, scale, strips, hits)
    clear = np.ones(len(centre), dtype=bool)
    for s in range(len(strips)):
        candidates = np.flatnonzero(hits[:, s])
        if regions is not None and candidates.size:
            reach = radius[candidates] * (1 + 1e-9) + 1e-12 * scale
            candidates = candidates[disks_meet_polygon(centre[candidates], reach, regions[s])]
        clear[candidates] = False
    return clear
