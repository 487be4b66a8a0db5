"""Warnings about a fit whose result is probably wrong, one rule for every path (the
in-memory fit, DEMs, --seamless -o and -O, the memory-bounded survey fit)."""
from __future__ import annotations


UNUSED_POINTS_WARN = 0.2
"""More than this fraction of the points in no triangle of the surface draws the wrong-axis
warning. A right axis leaves few: 0.4% on Autzen ground (points alone inside building
footprints), 8.6% on the bunny range scan (its silhouette); a wrong one on a 52-point
terrain 31-67% (the points fold over each other seen along it)."""
LONG_EDGE_WARN = 0.1
"""More than this fraction of the triangles removed by the --max-edge rule draws the
max-edge warning: a courtyard or a building footprint is spanned by a few long triangles
(Autzen ground at the auto limit: 3.1%), but a limit near the point spacing cuts
triangles inside dense data (uniform points at 1.6x their spacing: 38%)."""


def fit_warnings(points: int, used: int, triangles: int, long_edge: int, max_edge,
                 auto_limit: bool = False, pieces: int | None = None, merged: int = 0) -> list[str]:
    """Plain-language warnings about a fit whose result is probably wrong (the CLI prints
    them on stderr), the same for the in-memory and the tiled fit.

    points: the points the fit was given (after --classes and --bounds); used: those that
    are vertices of the trimmed surface; triangles: the triangles of the whole Delaunay
    triangulation before the trim; long_edge: how many of them the --max-edge rule removed
    (limit max_edge, length units or None; auto_limit: it is --max-edge auto's);
    pieces: connected pieces of the result, when known (named in the message); merged:
    the points merged into another point at the same plane position (the height field's
    duplicates), which lie on the surface at that point's vertex, so they count as used:
    a scan that holds every point twice is no sign of a wrong axis.

    Holes the trim leaves over gaps in the data (courtyards, building footprints under
    LiDAR ground) remove few triangles and leave few points out, so they draw no warning.
    A --max-edge near the data's spacing removes triangles between dense points; the
    auto limit (trim.AUTO_EDGE_FACTOR x the median edge) does that only where the
    points are far from evenly spread over the plane, and a wrong height axis, which also
    leaves many points folded over others and off the surface, is the likely cause. At
    most one warning: the first that applies of these.
    """
    used = min(points, used + merged)
    unused = f"{points - used} of the {points} points are in no triangle"
    dense = bool(triangles) and max_edge is not None and long_edge / triangles > LONG_EDGE_WARN
    if dense and not auto_limit:
        split = "" if pieces is None else f" (the surface fell into {pieces} pieces)"
        return [f"--max-edge {max_edge:.6g} removed {long_edge / triangles:.0%} of the triangles, also "
                f"between dense points, and {unused}; try a larger --max-edge, auto or none{split}"]
    if dense or (points and 1.0 - used / points > UNUSED_POINTS_WARN):
        removed = f"--max-edge auto removed {long_edge / triangles:.0%} of the triangles and " if dense else ""
        return [f"{removed}{unused} of the surface: seen along the height axis the points fold "
                "over each other or bunch up; check --axis (and --classes)"]
    return []


NOISY_GRADIENTS = 0.1
"""More than this fraction of the vertices whose gradient the limiter changed draws the
suggestion to smooth: the limiter acts only on edges whose heights and gradients fail the
trapezoid test, which exact smooth data pass (0 of 3,000 vertices on hill.ply, 0 of 2,000
on the wave), while noisy LiDAR ground fails it at most vertices (71% on Autzen ground,
76% on 4_6_crop)."""


def smoothing_suggestion(gradients_limited: int, vertices: int) -> str | None:
    """The report's suggestion to fit with --smooth auto where the heights look like noise
    (NOISY_GRADIENTS), else None. gradients_limited: the limiter's count
    (c1mesh.stages.limiter.LimiterReport); vertices: the surface's vertex count."""
    if vertices <= 0 or gradients_limited / vertices <= NOISY_GRADIENTS:
        return None
    return (f"the heights look noisy: the limiter changed the gradients of {gradients_limited / vertices:.0%} "
            "of the vertices; --smooth auto fits the spline to the points instead of through them "
            "(held-out heights are usually closer, the surface smoother)")


def auto_limit(max_edge) -> bool:
    """Whether the --max-edge option asks for the auto limit."""
    return isinstance(max_edge, str) and max_edge.strip().lower() == "auto"
