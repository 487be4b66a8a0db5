"""Plane geometry for the buffered tile Delaunay (c1mesh.survey.buffered_delaunay) and the
tile normals (c1mesh.survey.tile_normals): the strips of the survey's box a tile has not
read, the survey's hull clipped to them, circumcircles and the tests that a disk or a
half-plane stays clear of what was not read. Coordinates are relative to the tile's
centre (frame units); every test is conservative (touching counts as reaching)."""
from __future__ import annotations

import numpy as np


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
    reach = radius * (1 + 1e-9) + 1e-12 * np.abs(xy).max()
    clear = np.ones(len(triangles), dtype=bool)
    for s, (x0, y0, x1, y1) in enumerate(strips):
        dx = np.maximum(np.maximum(x0 - centre[:, 0], centre[:, 0] - x1), 0.0)
        dy = np.maximum(np.maximum(y0 - centre[:, 1], centre[:, 1] - y1), 0.0)
        hits = np.hypot(dx, dy) <= reach
        if regions is not None and hits.any():
            candidates = np.flatnonzero(hits)
            hits[candidates] = disks_meet_polygon(centre[candidates], reach[candidates], regions[s])
        clear &= ~hits
    return clear


def disks_meet_polygon(centre: np.ndarray, reach: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(k,) True where the closed disk (centre, reach) meets the convex polygon (m, 2)
    (counter-clockwise; empty: meets nothing): its centre is inside, or an edge is within reach."""
    if len(polygon) == 0:
        return np.zeros(len(centre), dtype=bool)
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
    return meets | inside


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
    """Circumcentres (k, 2) and radii (k,) of triangles (k, 3) into xy (n, 2); a degenerate
    (collinear) triangle gets an infinite radius."""
    a, b, c = xy[triangles[:, 0]], xy[triangles[:, 1]], xy[triangles[:, 2]]
    b, c = b - a, c - a
    d = 2.0 * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    bb, cc = (b * b).sum(axis=1), (c * c).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (c[:, 1] * bb - b[:, 1] * cc) / d
        uy = (b[:, 0] * cc - c[:, 0] * bb) / d
    radius = np.hypot(ux, uy)
    radius[~np.isfinite(radius)] = np.inf
    return a + np.column_stack([ux, uy]), radius


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


def smallest_empty_circle(xy, simplices, neighbors, t, k, a, b, centres) -> np.ndarray:
    """(e, 2) centres of the smallest circle through each edge's ends (a, b) that is empty
    of the triangulated points: on the edge's bisector, between the circumcentres of its
    two triangles (or from triangle t's circumcentre outwards, for a hull edge), the point
    nearest the edge's midpoint."""
    mid = (xy[a] + xy[b]) / 2
    c1 = centres[t]
    other = neighbors[t, k]
    hull_edge = other < 0
    c2 = np.where(hull_edge[:, None], c1, centres[np.maximum(other, 0)])
    span = c2 - c1
    length2 = (span * span).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip(((mid - c1) * span).sum(axis=1) / length2, 0.0, 1.0)
    s[length2 == 0] = 0.0
    best = c1 + s[:, None] * span
    if hull_edge.any():                          # the pencil runs from c1 away from the third corner
        h = np.flatnonzero(hull_edge)
        apex = xy[simplices[t[h], k[h]]]
        edge = xy[b[h]] - xy[a[h]]
        outward = np.column_stack([edge[:, 1], -edge[:, 0]])
        flip = ((apex - xy[a[h]]) * outward).sum(axis=1) > 0
        outward[flip] *= -1.0
        beyond = ((mid[h] - c1[h]) * outward).sum(axis=1) > 0
        best[h] = np.where(beyond[:, None], mid[h], c1[h])
    return best


def centres_clear(centre, radius, strips, regions, scale) -> np.ndarray:
    """(e,) True where the disk (centre, radius) stays clear of every unread strip clipped
    to the survey's hull (conservative, as disks_clear)."""
    reach = radius * (1 + 1e-9) + 1e-12 * scale
    clear = np.ones(len(centre), dtype=bool)
    for s, (x0, y0, x1, y1) in enumerate(strips):
        dx = np.maximum(np.maximum(x0 - centre[:, 0], centre[:, 0] - x1), 0.0)
        dy = np.maximum(np.maximum(y0 - centre[:, 1], centre[:, 1] - y1), 0.0)
        hits = np.hypot(dx, dy) <= reach
        if hits.any():
            candidates = np.flatnonzero(hits)
            hits[candidates] = disks_meet_polygon(centre[candidates], reach[candidates], regions[s])
        clear &= ~hits
    return clear
