"""Contour lines of the fitted C1 spline whose vertices lie on its true level sets.

Tracing. The spline is sampled at the nodes of a grid (the DEM's cell centres, or for a
mesh output a grid at the mesh's resolution): a node inside the trimmed triangulation
holds the spline's height, a node outside it (a trimmed hole, past the rim) holds nothing.
contourpy, the library behind matplotlib's contours, traces each level through the cells
whose four nodes hold a height (marching squares; `corner_mask=False`, so every vertex
lies on a grid edge between two nodes that hold heights). Its lines are what
`gdal_contour` draws from the same DEM: each vertex where the straight line between the
two node heights meets the level.

Snapping. Each vertex is then moved along its grid edge to where the spline itself takes
the level: a safeguarded Newton iteration on t ↦ s(a + t(b − a)) − level, whose derivative
is the spline's analytic gradient along the edge (∇s · (b − a)), with a bisection step
whenever Newton would leave the bracket [t where s < level, t where s > level]. The
iteration stops at |s − level| ≤ NEWTON_TOLERANCE × the interval. A vertex stays on its
grid edge (not moved along ∇s, which converges as fast) because that is what keeps the
lines apart: on one edge the vertices of increasing levels are solved in order, each
bracketed between the previous level's vertex and the edge's higher node, so their order
along the edge is the order of their levels; with contourpy's saddle rule (one middle
height per cell for every level) the chords in one cell then never cross, and chords of
different cells meet only at shared vertices. Lines therefore cross neither each other
nor themselves, and a level set that closes inside the data comes out closed.

Splitting. A vertex whose iteration ends outside the triangulation (its grid edge
crosses a hole narrower than a cell), or off the level by more than EXACT × the interval,
is dropped and its line split there; so is a chord whose midpoint lies outside the
triangulation. Every vertex written is on the spline's level set to EXACT × the interval
(measured again at the end: ContourLines.max_level_error).

Frames and units: the interpolator works in the fit's local frame (world − origin, axes
the world's, z up: a height field over the world XY plane); vertices are returned in
world x, y and levels in world heights.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.geo.raster_grid import RasterGrid, SplineSampler

EXACT = 1e-6
"""A vertex is kept when |spline − level| ≤ EXACT × the interval (issue 40's bound)."""
NEWTON_TOLERANCE = 1e-10
"""The snapping iteration stops at |spline − level| ≤ NEWTON_TOLERANCE × the interval."""
NEWTON_STEPS = 80
"""Most steps of the snapping iteration (bisection alone halves the bracket 80 times)."""
MAX_LEVELS = 100_000
"""Most contour levels one fit may draw (a tiny --interval is refused, not drawn for hours)."""
MAX_GRID_NODES = 200_000_000
"""Most grid nodes the tracing grid may have (8 bytes of height each, plus contourpy's)."""
BYTES_PER_NODE = 60
"""Peak memory of the tracing per grid node (bytes): the node's height and triangle (16;
in tiles its height, tile and triangle, 16) and `trace`'s masked copy and contourpy's
own arrays, measured at 36 bytes a node on a 3000 x 3000 grid; rounded up. A fit in
tiles checks its budget against it (pipeline.bounded_fit)."""
_ROW_BLOCK = 1 << 20
"""Grid nodes evaluated at a time (bounds the temporaries of the evaluation)."""
ON_EDGE = 1e-9
"""How far (in cells) a traced vertex's coordinate may be from a whole number and still
name its grid row or column."""
CLOSEPOLY = 79
"""The path code (matplotlib's) that ends a closed line in contourpy's SeparateCode lines."""


@dataclass(frozen=True)
class ContourGrid:
    """The nodes the spline is sampled at: the cell centres of a north-up raster grid
    (c1mesh.geo.raster_grid.RasterGrid), node (row i, column j) at local
    (west + (j + ½)R − ox, north − (i + ½)R − oy), rows running south. Local = world − the
    fit's origin (ox, oy, oz); R in world length units."""

    raster: RasterGrid
    origin: tuple[float, float, float]

    @classmethod
    def of_raster(cls, raster_grid: RasterGrid, origin) -> "ContourGrid":
        """The grid of `raster_grid`'s cell centres in the frame of `origin` (3,); InputError
        when it has more than MAX_GRID_NODES nodes."""
        width, height = raster_grid.width, raster_grid.height
        if width * height > MAX_GRID_NODES:
            raise InputError(f"contours on a {width} x {height} grid (resolution {raster_grid.resolution:g}) "
                             "need too much memory; give a coarser --resolution")
        return cls(raster_grid, tuple(float(v) for v in origin))

    @property
    def width(self) -> int:
        return self.raster.width

    @property
    def height(self) -> int:
        return self.raster.height

    def local(self, columns: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(M, 2) local x, y of grid positions given as (fractional) column and row indices (M,)."""
        r = self.raster.resolution
        return np.column_stack([self.raster.west - self.origin[0] + (columns + 0.5) * r,
                                self.raster.north - self.origin[1] - (rows + 0.5) * r])


@dataclass(frozen=True)
class ContourLines:
    """Contour lines in world coordinates.

    lines: one (n, 2) float64 array of world x, y per line (n ≥ 2; a closed line repeats
    its first vertex at the end); levels (L,) world height of each line; closed (L,) bool.
    max_level_error: the largest |spline(v) − level| over all vertices v written,
    evaluated afresh (world height units); dropped: vertices dropped (outside the
    triangulation or not on the level set), each splitting its line.
    """

    lines: tuple
    levels: np.ndarray
    closed: np.ndarray
    interval: float
    level_values: np.ndarray
    max_level_error: float
    dropped: int

    def facts(self) -> dict:
        """The report's "contours" section (without the file, which the writer adds)."""
        levels = self.level_values
        return {"interval": self.interval, "lines": len(self.lines), "closed": int(self.closed.sum()),
                "vertices": int(sum(line.shape[0] for line in self.lines)),
                "levels": {"count": int(levels.size), "lowest": float(levels[0]) if levels.size else None,
                           "highest": float(levels[-1]) if levels.size else None},
                "max_level_error": self.max_level_error, "dropped_vertices": self.dropped}


# ----------------------------------------------------------------------------- levels
def contour_levels(lowest: float, highest: float, interval: float) -> np.ndarray:
    """The levels k·interval (k integer) from `lowest` to `highest` (world heights), as the
    nearest double to the decimal the user expects (0.3, not 0.30000000000000004).
    InputError when there would be more than MAX_LEVELS."""
    if not (interval > 0 and math.isfinite(interval)):
        raise InputError(f"--interval must be a positive height, got {interval}")
    if not (math.isfinite(lowest) and math.isfinite(highest)) or highest < lowest:
        return np.empty(0)
    first, last = math.ceil(lowest / interval), math.floor(highest / interval)
    count = last - first + 1
    if count > MAX_LEVELS:
        raise InputError(f"--interval {interval:g} gives {count} contour levels over the heights "
                         f"{lowest:g} to {highest:g}, more than {MAX_LEVELS}; give a larger --interval")
    return np.array([float(f"{k * interval:.12g}") for k in range(first, last + 1)])


# ---------------------------------------------------------------------------- sampling
def sample_grid(sampler: SplineSampler, grid: ContourGrid) -> tuple[np.ndarray, np.ndarray]:
    """(heights, triangles), each (height, width): the spline's height (local) at each
    grid node and the triangle it lies in; NaN and −1 at nodes outside the triangulation.
    sampler: a SplineSampler of the spline without data points, so that nothing is
    continued past the triangulation (c1mesh.geo.raster_grid)."""
    heights = np.full(grid.height * grid.width, np.nan)
    triangles = np.full(grid.height * grid.width, -1, dtype=np.int64)
    rows_per_block = max(1, _ROW_BLOCK // grid.width)
    for start in range(0, grid.height, rows_per_block):
        rows = range(start, min(start + rows_per_block, grid.height))
        cell, tri, l0, l1, _ = sampler.cells(grid.raster, rows, range(grid.width))
        heights[start * grid.width + cell] = sampler.evaluate(tri, l0, l1, gradients=False)[0]
        triangles[start * grid.width + cell] = tri
    return heights.reshape(grid.height, grid.width), triangles.reshape(grid.height, grid.width)


class SplineSurface:
    """The spline and its analytic gradient at arbitrary local points, each point's
    triangle remembered between calls (a vertex moving along its grid edge mostly stays in
    it), evaluated as the DEM grid is (SplineSampler.evaluate)."""

    def __init__(self, interp, sampler: SplineSampler):
        self.interp, self.sampler = interp, sampler

    def at(self, xy: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(values (M,), gradients (M, 2), triangles (M,)) at xy (M, 2); tri (M,) the
        triangles the points were in last time (−1: unknown). NaN and −1 outside."""
        tri = tri.copy()
        known = np.flatnonzero(tri >= 0)
        l0, l1 = self.sampler.barycentric(tri[known], xy[known, 0], xy[known, 1])
        left = (np.minimum(np.minimum(l0, l1), 1.0 - l0 - l1) < -SplineSampler.TOLERANCE)
        tri[known[left]] = -1
        lost = np.flatnonzero(tri < 0)
        if lost.size:
            tri[lost] = self.interp.find_simplex(xy[lost])
        values, gradients = np.full(xy.shape[0], np.nan), np.full(xy.shape, np.nan)
        inside = np.flatnonzero(tri >= 0)
        if inside.size:
            l0, l1 = self.sampler.barycentric(tri[inside], xy[inside, 0], xy[inside, 1])
            values[inside], gradients[inside] = self.sampler.evaluate(tri[inside], l0, l1, gradients=True)
        return values, gradients, tri


class JoinedSurface:
    """Several splines' SplineSurfaces as one (the tiles of a survey fitted in tiles, each
    holding its own triangles, c1mesh.pipeline.bounded_dem): a triangle number names a
    part's triangle offset by the triangles of the parts before it; a point lost from its
    triangle is searched for in the parts in their order, the first that holds it wins."""

    def __init__(self, parts: list):
        self.parts = parts
        self.offsets = np.cumsum([0] + [part.interp.triangles.shape[0] for part in parts])

    def at(self, xy: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """SplineSurface.at over the parts: (values (M,), gradients (M, 2), triangles (M,))."""
        values, gradients, found = np.full(xy.shape[0], np.nan), np.full(xy.shape, np.nan), tri.copy()
        part_of = np.searchsorted(self.offsets, tri, side="right") - 1
        for k, part in enumerate(self.parts):          # first where each point was
            here = np.flatnonzero((tri >= 0) & (part_of == k))
            self._take(k, here, part.at(xy[here], tri[here] - self.offsets[k]), (values, gradients, found))
        found[(tri < 0) | np.isnan(values)] = -1
        for k, part in enumerate(self.parts):          # then the lost points, part by part
            lost = np.flatnonzero(found < 0)
            if not lost.size:
                break
            self._take(k, lost, part.at(xy[lost], np.full(lost.size, -1)), (values, gradients, found))
        return values, gradients, found

    def _take(self, k: int, where: np.ndarray, result, into) -> None:
        """Write part k's (values, gradients, triangles) at `where` into `into` where it found a triangle."""
        value, gradient, tri = result
        inside = tri >= 0
        into[0][where[inside]], into[1][where[inside]] = value[inside], gradient[inside]
        into[2][where[inside]] = tri[inside] + self.offsets[k]


def spline_values(interp, xy: np.ndarray) -> np.ndarray:
    """Spline values at xy (M, 2) by the interpolator's own evaluation (rsd's shape
    functions), NaN outside the triangulation whatever its fill value."""
    if isinstance(interp.fill_value, float) and math.isnan(interp.fill_value):
        return interp(xy)
    return np.where(interp.find_simplex(xy) >= 0, interp(xy), np.nan)


# ----------------------------------------------------------------------------- tracing
@dataclass(frozen=True)
class _Traced:
    """contourpy's lines of all levels, flattened: vertex k of line line_of[k], at index
    position (column, row) = positions[k]; line_level (lines,) the index into the levels,
    line_closed (lines,) bool (a closed line's repeated last vertex is left out)."""

    positions: np.ndarray
    line_of: np.ndarray
    line_level: np.ndarray
    line_closed: np.ndarray


def trace(heights: np.ndarray, levels_local: np.ndarray) -> _Traced:
    """Trace every level through the cells whose four nodes hold a height (contourpy's
    serial algorithm, no corner triangles), in index coordinates (column, row)."""
    import contourpy

    generator = contourpy.contour_generator(z=np.ma.masked_invalid(heights), name="serial",
                                            corner_mask=False, line_type="SeparateCode")
    positions, line_of, line_level, line_closed = [], [], [], []
    for index, level in enumerate(levels_local):
        points, codes = generator.lines(float(level))
        for xy, code in zip(points, codes):
            closed = bool(code[-1] == CLOSEPOLY)
            if closed:
                xy = xy[:-1]
            line_of.append(np.full(xy.shape[0], len(line_level), dtype=np.int64))
            positions.append(xy)
            line_level.append(index)
            line_closed.append(closed)
    if not positions:
        return _Traced(np.empty((0, 2)), np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, bool))
    return _Traced(np.concatenate(positions), np.concatenate(line_of), np.asarray(line_level, np.int64),
                   np.asarray(line_closed, bool))


@dataclass(frozen=True)
class _Edges:
    """The grid edge under each traced vertex: nodes a and b as (row, column) int arrays
    (M, 2), t0 (M,) contourpy's position along a → b, key (M,) one integer per edge,
    valid (M,) False for a vertex on no grid edge (none is expected: corner_mask=False)."""

    a: np.ndarray
    b: np.ndarray
    t0: np.ndarray
    key: np.ndarray
    valid: np.ndarray

    def take(self, rows: np.ndarray) -> "_Edges":
        """The edges of the vertices `rows` (indices)."""
        return _Edges(self.a[rows], self.b[rows], self.t0[rows], self.key[rows], self.valid[rows])


def grid_edges(positions: np.ndarray, width: int, height: int) -> _Edges:
    """The grid edge each vertex (column, row) lies on: the coordinate that is a whole
    number (to ON_EDGE: contourpy interpolates a·(1 − t) + b·t, which may miss a whole a = b
    by an ulp) names the row of an east-west edge or the column of a north-south one. A
    vertex on a node is put on an edge that starts or ends there."""
    column, row = positions[:, 0], positions[:, 1]
    row_off, column_off = np.abs(row - np.rint(row)), np.abs(column - np.rint(column))
    on_row = row_off <= column_off
    valid = np.minimum(row_off, column_off) <= ON_EDGE
    j0 = np.clip(np.floor(column), 0, max(width - 2, 0)).astype(np.int64)
    i0 = np.clip(np.floor(row), 0, max(height - 2, 0)).astype(np.int64)
    a = np.column_stack([np.where(on_row, np.rint(row), i0), np.where(on_row, j0, np.rint(column))]).astype(np.int64)
    b = a + np.where(on_row[:, None], [0, 1], [1, 0])
    t0 = np.clip(np.where(on_row, column - j0, row - i0), 0.0, 1.0)
    key = (a[:, 0] * width + a[:, 1]) * 2 + (~on_row)
    return _Edges(a, b, t0, key, valid)


# ---------------------------------------------------------------------------- snapping
@dataclass(frozen=True)
class _Roots:
    """Where the spline takes the level on each vertex's grid edge: t (M,) along a → b,
    residual (M,) spline − level (NaN: the iteration left the triangulation)."""

    t: np.ndarray
    residual: np.ndarray


@dataclass(frozen=True)
class _Segments:
    """Where to look for each root (all local frame, M of each): the segment start + t·step
    (start, step (M, 2)), the level (M,), a bracket f(t_below) < 0 < f(t_above) of
    f(t) = s(start + t·step) − level (M,) each, the first guess t_guess (M,) and the
    triangle it probably lies in (M,; −1 unknown)."""

    start: np.ndarray
    step: np.ndarray
    level: np.ndarray
    t_below: np.ndarray
    t_above: np.ndarray
    t_guess: np.ndarray
    triangle: np.ndarray


def _solve(surface, segments: _Segments, tolerance: float) -> _Roots:
    """The roots of f on the segments: Newton steps with the analytic derivative
    ∇s·step, bisection when Newton would leave the bracket, until |f| ≤ tolerance or
    NEWTON_STEPS."""
    start, step, level = segments.start, segments.step, segments.level
    t_below, t_above = segments.t_below.copy(), segments.t_above.copy()
    t = np.clip(segments.t_guess, np.minimum(t_below, t_above), np.maximum(t_below, t_above))
    residual = np.full(t.shape, np.nan)
    triangle = segments.triangle.copy()
    active = np.arange(t.size)
    for _ in range(NEWTON_STEPS):
        if active.size == 0:
            break
        value, gradient, triangle[active] = surface.at(start[active] + t[active, None] * step[active],
                                                       triangle[active])
        value = value - level[active]
        residual[active] = value
        going = np.isfinite(value) & (np.abs(value) > tolerance)
        active, value, gradient = active[going], value[going], gradient[going]
        below = value < 0
        t_below[active[below]] = t[active[below]]
        t_above[active[~below]] = t[active[~below]]
        slope = np.einsum("md,md->m", gradient, step[active])
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = t[active] - value / slope
        ok = np.isfinite(newton) & _between(newton, t_below[active], t_above[active])
        t[active] = np.where(ok, newton, 0.5 * (t_below[active] + t_above[active]))
        active = active[t_below[active] != t_above[active]]
    return _Roots(t, residual)


def _between(t: np.ndarray, one: np.ndarray, other: np.ndarray) -> np.ndarray:
    """t strictly between one and other (either order)."""
    return (t > np.minimum(one, other)) & (t < np.maximum(one, other))


def snap(surface, grid: ContourGrid, heights: np.ndarray, edges: _Edges, level: np.ndarray,
         tolerance: float, hint: np.ndarray) -> _Roots:
    """Move each vertex along its grid edge onto the spline's level set (module docstring).

    surface: a SplineSurface (or JoinedSurface) holding every point of the edges;
    heights: the grid's node heights (local, sample_grid); level (M,) each vertex's level
    (local); hint (M,): the triangle of the surface each vertex's search starts in (−1:
    unknown).
    On one edge, levels are solved in increasing order, each bracketed by the last root
    found below it and the edge's higher node, so roots keep the order of their levels.
    """
    za, zb = heights[edges.a[:, 0], edges.a[:, 1]], heights[edges.b[:, 0], edges.b[:, 1]]
    t_high = (zb > za).astype(np.float64)                     # the higher node: where s > level
    start = grid.local(edges.a[:, 1].astype(np.float64), edges.a[:, 0].astype(np.float64))
    end = grid.local(edges.b[:, 1].astype(np.float64), edges.b[:, 0].astype(np.float64))
    order = np.lexsort((level, edges.key))
    first = np.ones(order.size, bool)
    first[1:] = edges.key[order[1:]] != edges.key[order[:-1]]
    group_start = np.maximum.accumulate(np.where(first, np.arange(order.size), 0))
    rank = np.empty(order.size, np.int64)
    rank[order] = np.arange(order.size) - group_start
    last_root = 1.0 - t_high                                   # below every level: the lower node
    t = np.empty(level.size)
    residual = np.full(level.size, np.nan)
    for r in range(int(rank.max()) + 1 if rank.size else 0):
        now = order[rank[order] == r]
        roots = _solve(surface, _Segments(start[now], end[now] - start[now], level[now], last_root[now],
                                          t_high[now], edges.t0[now], hint[now]), tolerance)
        t[now], residual[now] = roots.t, roots.residual
        following = _next_in_edge(order, first, now)
        has_next = following >= 0
        found = np.where(np.isfinite(roots.residual), roots.t, last_root[now])   # a failed root: keep the last
        last_root[following[has_next]] = found[has_next]
    return _Roots(t, residual)


def _next_in_edge(order: np.ndarray, first: np.ndarray, members: np.ndarray) -> np.ndarray:
    """The vertex after each of `members` in the (edge, level) order on the same edge, −1
    for a member that is the last of its edge."""
    where = np.empty(order.size, np.int64)
    where[order] = np.arange(order.size)
    position = where[members] + 1
    inside = position < order.size
    position = np.where(inside, position, 0)
    return np.where(inside & ~first[position], order[position], -1)


# --------------------------------------------------------------------------- assembling
def contour_surface(interp, grid: ContourGrid, interval: float) -> ContourLines:
    """Contour lines of the spline `interp` (in the local frame of grid.origin, world
    axes) every `interval` of world height, traced on `grid` and snapped onto the
    spline's level sets (module docstring): contour_heights with the one spline."""
    sampler = SplineSampler(interp, grid.origin)
    heights, node_triangle = sample_grid(sampler, grid)
    return contour_heights(heights, grid, interval, OneSpline(interp, sampler, node_triangle))


class OneSpline:
    """The splines contour_heights snaps onto, when one interpolator holds the whole
    surface (the in-memory fit): `values` at local points (NaN outside) and `patches`,
    here one, of every vertex with its SplineSurface and the triangle of the grid node
    nearer to it (node_triangle (height, width): sample_grid's) to start from."""

    def __init__(self, interp, sampler: SplineSampler, node_triangle: np.ndarray):
        self.interp, self.surface, self.node_triangle = interp, SplineSurface(interp, sampler), node_triangle

    def values(self, xy: np.ndarray) -> np.ndarray:
        return spline_values(self.interp, xy)

    def patches(self, grid: ContourGrid, edges: "_Edges"):
        """[(vertices (M,), surface, hint (M,))]: every vertex, in one patch."""
        near = np.where((edges.t0 < 0.5)[:, None], edges.a, edges.b)
        hint = self.node_triangle[near[:, 0], near[:, 1]]
        return [(np.arange(edges.a.shape[0]), self.surface, hint)]


def contour_heights(heights: np.ndarray, grid: ContourGrid, interval: float, splines) -> ContourLines:
    """Contour lines every `interval` of world height through the grid nodes' spline
    heights (heights (height, width), local, NaN outside the triangulation: sample_grid's),
    snapped onto the level sets of `splines` (OneSpline, or the tiles' splines of a survey
    fitted in tiles: c1mesh.pipeline.bounded_dem), which give every vertex's grid edge a
    surface holding it (`patches`) and evaluate the spline anywhere (`values`)."""
    oz = grid.origin[2]
    finite = heights[np.isfinite(heights)]
    if finite.size == 0 or grid.width < 2 or grid.height < 2:
        return _empty(interval)
    levels = contour_levels(float(finite.min()) + oz, float(finite.max()) + oz, interval)
    traced = trace(heights, levels - oz)
    edges = grid_edges(traced.positions, grid.width, grid.height)
    vertex_level = (levels - oz)[traced.line_level[traced.line_of]]
    t, residual = np.zeros(vertex_level.size), np.full(vertex_level.size, np.nan)
    for members, surface, hint in splines.patches(grid, edges):
        roots = snap(surface, grid, heights, edges.take(members), vertex_level[members],
                     NEWTON_TOLERANCE * interval, hint)
        t[members], residual[members] = roots.t, roots.residual
    start = grid.local(edges.a[:, 1].astype(np.float64), edges.a[:, 0].astype(np.float64))
    end = grid.local(edges.b[:, 1].astype(np.float64), edges.b[:, 0].astype(np.float64))
    local = start + t[:, None] * (end - start)
    good = edges.valid & np.isfinite(residual) & (np.abs(residual) <= EXACT * interval)
    pieces = _split(splines.values, local, good, traced)
    return _assemble(splines.values, grid.origin, pieces, levels, interval, int((~good).sum()))


@dataclass(frozen=True)
class _Piece:
    """A piece of a traced line: its vertices (local, (n, 2)), the index of its level, closed."""

    xy: np.ndarray
    level: int
    closed: bool


def _split(values, local: np.ndarray, good: np.ndarray, traced: _Traced) -> list[_Piece]:
    """The traced lines cut at dropped vertices and at chords whose midpoint lies outside
    the triangulation; pieces of fewer than two vertices are left out."""
    bounds = np.flatnonzero(np.diff(traced.line_of)) + 1
    starts = np.concatenate([[0], bounds]) if traced.line_of.size else np.empty(0, np.int64)
    stops = np.concatenate([bounds, [traced.line_of.size]]) if traced.line_of.size else np.empty(0, np.int64)
    chord_ok = _chords_inside(values, local, traced.line_of, traced.line_closed, starts, stops)
    pieces = []
    for line, (lo, hi) in enumerate(zip(starts, stops)):
        closed = bool(traced.line_closed[traced.line_of[lo]])
        keep, links = good[lo:hi], chord_ok[lo:hi]         # links[k]: chord k → k + 1 (closing: last)
        pieces += _cut(local[lo:hi], keep, links, closed, int(traced.line_level[traced.line_of[lo]]))
    return pieces


def _chords_inside(values, local, line_of, line_closed, starts, stops) -> np.ndarray:
    """(M,) bool: the chord from vertex k to the next one of its line (the first, for the
    last vertex of a closed line) has its midpoint inside the triangulation; False for the
    last vertex of an open line (no chord)."""
    following = np.arange(1, local.shape[0] + 1)
    if starts.size:
        following[stops - 1] = starts                          # closing chord of closed lines
    has_chord = np.ones(local.shape[0], bool)
    if starts.size:
        has_chord[stops - 1] = line_closed[line_of[stops - 1]]
    ok = np.zeros(local.shape[0], bool)
    which = np.flatnonzero(has_chord)
    if which.size:
        middle = 0.5 * (local[which] + local[following[which]])
        ok[which] = np.isfinite(values(middle))
    return ok


def _cut(xy: np.ndarray, keep: np.ndarray, links: np.ndarray, closed: bool, level: int) -> list[_Piece]:
    """One traced line cut into pieces: a vertex not kept, or a chord not linked, ends a
    piece; repeated vertices (two grid edges snapped to the node they share) count once."""
    n = xy.shape[0]
    if closed and keep.all() and links.all():
        whole = _distinct(xy, closed=True)
        return [_Piece(whole, level, True)] if whole.shape[0] >= 3 else []
    if closed:                                  # start right after a break, so no piece wraps
        breaks = np.flatnonzero(~keep | ~links)
        shift = int(breaks[0]) + 1
        xy, keep, links = np.roll(xy, -shift, 0), np.roll(keep, -shift), np.roll(links, -shift)
    pieces, current = [], []
    for k in range(n):
        if keep[k]:
            current.append(k)
        if not keep[k] or not links[k] or k == n - 1:
            piece = _distinct(xy[current], closed=False)
            if piece.shape[0] >= 2:
                pieces.append(_Piece(piece, level, False))
            current = []
    return pieces


def _distinct(xy: np.ndarray, closed: bool) -> np.ndarray:
    """The vertices (n, 2) without those equal to the one before (for a closed line, the
    last is also compared with the first)."""
    if xy.shape[0] < 2:
        return xy
    before = np.roll(xy, 1, axis=0)
    repeated = (xy == before).all(axis=1)
    if not closed:
        repeated[0] = False
    return xy[~repeated]


def _assemble(values, origin, pieces: list[_Piece], levels: np.ndarray, interval: float,
              dropped: int) -> ContourLines:
    """The pieces in world coordinates (a closed one repeating its first vertex), and the
    largest |spline − level| over their vertices, evaluated afresh at the world
    coordinates written (so the rounding of local + origin is in it)."""
    shift = np.asarray(origin[:2], dtype=np.float64)
    lines = tuple(np.vstack([p.xy, p.xy[:1]]) + shift if p.closed else p.xy + shift for p in pieces)
    line_levels = np.array([levels[p.level] for p in pieces], dtype=np.float64)
    worst = 0.0
    if lines:
        every = np.concatenate(lines)
        wanted = np.repeat(line_levels, [line.shape[0] for line in lines])
        worst = float(np.max(np.abs(values(every - shift) + float(origin[2]) - wanted)))
    return ContourLines(lines, line_levels, np.array([p.closed for p in pieces], dtype=bool),
                        float(interval), levels, worst, dropped)


def _empty(interval: float) -> ContourLines:
    return ContourLines((), np.empty(0), np.empty(0, bool), float(interval), np.empty(0), 0.0, 0)
