"""The lattice fit's DEM holes, filled by the smoothing's energy alone (issue 38;
docs/smoothing.md, "Holes in the lattice's DEM").

A smoothing fit on the lattice (stages.lattice_mesh) keeps the cells within R of the data,
so its DEM has holes under buildings and water that the exact fit's DEM spans (its default
fill, --fill hull: every cell inside the convex hull of the points). Here the same cells
are filled after the fit, as a stage with a declared reduce:

- the *hull* is a survey-wide value: the convex hull of the points (`point_hull`), whose
  reduce over tiles is the hull of the tiles' hulls' corners (`joined_hull`);
- the *holes* (`find_holes`) are the cells whose centres lie in the hull (`hull_cells`)
  and that the support does not keep; their corners are either *free* (on no support cell)
  or on the *rim* (a corner of a support cell, whose fitted value and gradient are held);
- each hole is then one small problem (`fill_holes`): the free nodes' values and gradients
  minimise the spline's energy over the holes' cells (smoothing_energy: the integral of
  the squared second derivatives), with the rim's fitted data fixed. The spline is C1
  across the rim by construction (the rim's nodes are shared), the fill is as smooth as
  the energy that chose the fit, and a hole whose rim lies on a plane is filled with that
  plane. In tiles the reduce gathers every hole's cells and rim and solves each hole
  whole, so the fill does not depend on the tiling.

What it costs the fill: the rim is held where a solve of the fit with the holes' cells
(and no data there) would let the energy move it, so near the rim the two differ.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.core.lazy import LazyModule
from c1mesh.stages import _hole_fill as _kernel
from c1mesh.stages.lattice_mesh import NodeGrid, cell_triangles
from c1mesh.stages.smoothing import lattice_shapes, shared_directions
from c1mesh.stages.smoothing_system import Factor, assemble_energy, available_solvers
from c1mesh.engine.schemes import DEFAULT_SCHEME, get_scheme

sp = LazyModule("scipy.sparse")


def point_hull(xy: np.ndarray) -> np.ndarray:
    """(h, 2) the corners of the convex hull of the points xy (m, 2, finite), counter-
    clockwise; (0, 2) when they span no area (fewer than 3, or on one line). qhull runs on
    the points outside the octagon of their extremes only (Akl and Toussaint's filter, a
    kernel pass: 1M points in 0.17 s by qhull alone, about 10 ms so)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)       # a view of a height field's columns: no copy
    if xy.shape[0] < 3:
        return np.empty((0, 2))
    corners = np.empty(8, dtype=np.int64)
    _kernel.octagon_corners(xy, corners)
    octagon = np.ascontiguousarray(xy[corners])
    candidates = xy
    if np.unique(octagon, axis=0).shape[0] >= 3:
        keep = np.empty(xy.shape[0], dtype=np.uint8)
        _kernel.outside_octagon(xy, octagon, keep)
        candidates = xy[keep.view(bool)]
    return _hull_of(candidates)


def joined_hull(hulls: list) -> np.ndarray:
    """The reduce of point_hull over parts of the points (a tiled survey's tiles): the hull
    of the parts' hulls' corners, which is the hull of all the points."""
    corners = [h for h in hulls if len(h)]
    return _hull_of(np.concatenate(corners)) if corners else np.empty((0, 2))


def _hull_of(xy: np.ndarray) -> np.ndarray:
    """qhull's counter-clockwise hull corners of xy (k, 2), or (0, 2) for no area."""
    from scipy.spatial import ConvexHull, QhullError

    if xy.shape[0] < 3:
        return np.empty((0, 2))
    try:
        return np.ascontiguousarray(xy[ConvexHull(xy).vertices])
    except QhullError:                      # on one line: no area, no hull cells
        return np.empty((0, 2))


def hull_rows(grid: NodeGrid, hull: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, last) int64 (rows,) each: in every row of the grid's cells, the first and the
    last column whose centre lies in the convex polygon hull (h, 2, counter-clockwise; on
    its boundary counts as in); last < first where none does. The row's centre line meets
    the polygon in one interval [left, right] (each edge crossing the line gives an x; the
    least and the largest bound it), whose centres are the row's cells. A hull larger than
    the grid (a tile's) is cut to the grid's cells."""
    rows, cols = grid.cells
    if len(hull) < 3 or rows <= 0 or cols <= 0:
        return np.zeros(max(rows, 0), dtype=np.int64), np.full(max(rows, 0), -1, dtype=np.int64)
    D, (ox, oy), (i0, j0) = grid.spacing, grid.offset, grid.first
    y = oy + (j0 + np.arange(rows) + 0.5) * D                       # (rows,) the centre lines
    p, q = hull, np.roll(hull, -1, axis=0)                          # the edges p -> q
    low, high = np.minimum(p[:, 1], q[:, 1]), np.maximum(p[:, 1], q[:, 1])
    meets = (y[:, None] >= low) & (y[:, None] <= high)              # (rows, h)
    flat = p[:, 1] == q[:, 1]                                       # a level edge: its start (its
    t = (y[:, None] - p[:, 1]) / np.where(flat, np.inf, q[:, 1] - p[:, 1])   # end starts the next edge)
    x = p[:, 0] + t * (q[:, 0] - p[:, 0])
    left = np.where(meets, x, np.inf).min(axis=1)
    right = np.where(meets, x, -np.inf).max(axis=1)
    first = np.ceil((left - ox) / D - i0 - 0.5)
    last = np.floor((right - ox) / D - i0 - 0.5)
    first = np.clip(np.where(np.isfinite(first), first, cols), 0, cols).astype(np.int64)
    last = np.clip(np.where(np.isfinite(last), last, -1), -1, cols - 1).astype(np.int64)
    return first, last


def hull_cells(grid: NodeGrid, hull: np.ndarray) -> np.ndarray:
    """(k,) ascending numbers of the grid's cells whose centres lie in the convex polygon
    hull (hull_rows)."""
    first, last = hull_rows(grid, hull)
    return span_cells(grid, np.arange(first.size, dtype=np.int64), first, last)


def span_cells(grid: NodeGrid, rows: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """(k,) ascending numbers of the cells in columns first[r] .. last[r] of each row rows[r]
    (ascending row numbers; last < first: none of that row)."""
    count = np.maximum(last - first + 1, 0)
    start = np.repeat(first - np.concatenate([[0], np.cumsum(count)[:-1]]), count)
    return np.repeat(rows, count) * grid.cells[1] + (np.arange(int(count.sum()), dtype=np.int64) + start)


@dataclass(frozen=True)
class Holes:
    """The cells a fill spans: cells (k,) ascending numbers of the hull's cells the support
    does not keep; free (m,) ascending node numbers of their corners on no support cell (the
    fill's unknowns); rim (r,) ascending node numbers of their corners on a support cell
    (held at the fit's values and gradients)."""

    cells: np.ndarray
    free: np.ndarray
    rim: np.ndarray

    @property
    def empty(self) -> bool:
        """Whether there is nothing to fill."""
        return self.cells.size == 0


def cell_corners(grid: NodeGrid, cells: np.ndarray) -> np.ndarray:
    """(k, 4) the node numbers of the cells' corners (i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1)."""
    nx = grid.shape[1]
    j, i = np.divmod(np.asarray(cells, dtype=np.int64), nx - 1)
    a = j * nx + i
    return np.column_stack([a, a + 1, a + nx, a + nx + 1])


def support_cells(grid: NodeGrid, first_corners: np.ndarray) -> np.ndarray:
    """(k,) ascending numbers of the cells of lattice triangles given by their first corners
    (T,) node numbers (cell_triangles' order: a cell's two triangles both start at its node
    (i, j), number j nx + i, whose cell is j (nx − 1) + i). A fit's triangles come in
    ascending cells, which are then told apart in one pass; others are sorted."""
    nodes = np.ascontiguousarray(first_corners, dtype=np.int64)
    out = np.empty(nodes.size, dtype=np.int64)
    count = _kernel.ascending_cells(nodes, grid.shape[1], out)          # one pass (a kernel)
    if count < 0:
        nodes = np.unique(nodes)
        return nodes - nodes // grid.shape[1]
    return out[:count]


def find_holes(grid: NodeGrid, support: np.ndarray, hull: np.ndarray) -> Holes:
    """The Holes of a fit whose support cells are support (k,) ascending cell numbers, in
    the convex polygon hull (point_hull, or joined_hull of a survey's tiles). A corner of
    a hole's cell is on the rim when one of the four cells around it is a support cell."""
    first, last = hull_rows(grid, hull)
    cols = grid.cells[1]
    row = np.arange(first.size, dtype=np.int64)
    held = (np.searchsorted(support, row * cols + last, side="right")
            - np.searchsorted(support, row * cols + first, side="left"))     # support cells in the row's span
    short = np.flatnonzero(held < last - first + 1)                # rows with a hull cell left open
    inside = span_cells(grid, short, first[short], last[short])
    cells = inside[~np.isin(inside, support)]
    return classify_corners(grid, cells, support)


def classify_corners(grid: NodeGrid, cells: np.ndarray, support: np.ndarray) -> Holes:
    """The Holes of the holes' cells (k,) ascending: a corner is on the rim when one of
    the four cells around it is among the support cells (m,), else free. A tile passes its
    own holes' cells and the support around them."""
    if not cells.size:
        empty = np.empty(0, dtype=np.int64)
        return Holes(empty, empty, empty)
    corners = np.unique(cell_corners(grid, cells))
    on_rim = np.zeros(corners.size, dtype=bool)
    rows, cols = grid.cells
    j, i = np.divmod(corners, grid.shape[1])
    for dj in (-1, 0):
        for di in (-1, 0):
            ci, cj = i + di, j + dj
            real = (ci >= 0) & (ci < cols) & (cj >= 0) & (cj < rows)
            on_rim[real] |= np.isin(cj[real] * cols + ci[real], support)
    return Holes(cells, corners[~on_rim], corners[on_rim])


def joined_hole_parts(parts: list) -> Holes:
    """The reduce of the tiles' Holes (each its own cells, classify_corners): the cells
    (disjoint) and the corners (shared along the tiles' borders, classified alike) joined."""
    if not parts:
        empty = np.empty(0, dtype=np.int64)
        return Holes(empty, empty, empty)
    return Holes(np.sort(np.concatenate([p.cells for p in parts])), np.unique(np.concatenate([p.free for p in parts])),
                 np.unique(np.concatenate([p.rim for p in parts])))


def fill_holes(grid: NodeGrid, holes: Holes, rim_values: np.ndarray, rim_gradients: np.ndarray,
               scheme=None) -> tuple[np.ndarray, np.ndarray]:
    """(values (m,), gradients (m, 2)) of the holes' free nodes (holes.free's order) that
    minimise the energy of the RSD spline of `scheme` (None: the default) over the holes'
    cells, the rim's nodes held at rim_values (r,) and rim_gradients (r, 2) (holes.rim's
    order; heights in z's units, gradients dz/dx, dz/dy in the frame's plane).

    In units of D (positions / D, gradients × D) about the nodes' mean, heights about the
    rim's mean, the energy K (3n, 3n) over every corner of the holes' cells is split into
    the free unknowns F and the held ones C, and K_FF u_F = −K_FC u_C is solved. A group of
    free nodes joined to no rim node (no fitted neighbour) has no unique fill: ValueError."""
    rim_values = np.asarray(rim_values, dtype=np.float64).reshape(-1)
    rim_gradients = np.asarray(rim_gradients, dtype=np.float64).reshape(-1, 2)
    if rim_values.shape[0] != holes.rim.size or rim_gradients.shape[0] != holes.rim.size:
        raise ValueError(f"the rim has {holes.rim.size} nodes, got {rim_values.shape[0]} values "
                         f"and {rim_gradients.shape[0]} gradients")
    if not holes.free.size:
        return np.empty(0), np.empty((0, 2))
    nodes = np.union1d(holes.free, holes.rim)
    triangles = np.searchsorted(nodes, cell_triangles(grid, holes.cells))
    D = grid.spacing
    positions = grid.positions(nodes)
    npts = (positions - positions.mean(axis=0)) / D
    shapes = lattice_shapes(grid.solver_lattice(nodes), triangles)
    dirs = shared_directions(npts, triangles, shapes)
    K = assemble_energy(npts, triangles, dirs, get_scheme(DEFAULT_SCHEME if scheme is None else scheme), shapes).tocsr()
    free = np.isin(nodes, holes.free, assume_unique=True)
    F = (3 * np.flatnonzero(free)[:, None] + np.arange(3)).ravel()
    C = (3 * np.flatnonzero(~free)[:, None] + np.arange(3)).ravel()
    base = float(rim_values.mean()) if rim_values.size else 0.0
    held = np.column_stack([rim_values - base, rim_gradients * D]).ravel()
    rows = K[F]
    if _unheld_groups(triangles, free):
        raise ValueError("a hole's cells touch no fitted node: its fill is not unique")
    u = Factor(rows[:, F].tocsr(), available_solvers()[0]).solve(-(rows[:, C] @ held))
    u = u.reshape(-1, 3)
    return u[:, 0] + base, u[:, 1:] / D


def _unheld_groups(triangles: np.ndarray, free: np.ndarray) -> bool:
    """Whether some connected group of the triangles (sharing a node) has no held node."""
    from scipy.sparse.csgraph import connected_components

    n = free.size
    a = np.concatenate([triangles[:, 0], triangles[:, 1]])
    b = np.concatenate([triangles[:, 1], triangles[:, 2]])
    graph = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n))
    count, label = connected_components(graph, directed=False)
    held = np.zeros(count, dtype=bool)
    held[label[~free]] = True
    return not held.all()


@dataclass(frozen=True)
class LatticeVertices:
    """A lattice spline's vertex data: nodes (n,) node numbers, values (n,), gradients (n, 2)
    (frame units), triangles (T, 3) into the rows of nodes."""

    nodes: np.ndarray
    values: np.ndarray
    gradients: np.ndarray
    triangles: np.ndarray


def filled_lattice(grid: NodeGrid, fitted: LatticeVertices, hull: np.ndarray,
                   scheme=None) -> tuple[LatticeVertices, np.ndarray]:
    """(the spline's vertex data with the holes filled, fitted (T',) bool: True on the
    fitted triangles, False on the fill's) of a fit on the lattice: fitted holds the support's
    nodes and triangles (cell_triangles' order), hull the points' (point_hull). The fitted
    rows come first and unchanged; then the free nodes (ascending) and the holes' cells'
    triangles (cell_triangles' order)."""
    support = support_cells(grid, fitted.nodes[fitted.triangles[:, 0]])
    holes = find_holes(grid, support, hull)
    if holes.empty:
        return fitted, np.ones(fitted.triangles.shape[0], dtype=bool)
    by_number = _order(fitted.nodes)
    rim = by_number[np.searchsorted(fitted.nodes, holes.rim, sorter=by_number)]
    values, gradients = fill_holes(grid, holes, fitted.values[rim], fitted.gradients[rim], scheme)
    nodes = np.concatenate([fitted.nodes, holes.free])
    order = np.argsort(nodes, kind="stable")
    added = order[np.searchsorted(nodes, cell_triangles(grid, holes.cells), sorter=order)]
    triangles = np.concatenate([fitted.triangles, added])
    kept = np.repeat([True, False], [fitted.triangles.shape[0], added.shape[0]])
    return LatticeVertices(nodes, np.concatenate([fitted.values, values]),
                           np.concatenate([fitted.gradients, gradients]), triangles), kept


def _order(nodes: np.ndarray) -> np.ndarray:
    """The stable order that sorts node numbers (n,)."""
    return np.argsort(nodes, kind="stable")


__all__ = ["Holes", "LatticeVertices", "filled_lattice", "cell_corners", "fill_holes", "find_holes", "hull_cells",
           "classify_corners", "hull_rows", "joined_hole_parts", "span_cells", "joined_hull", "point_hull",
           "support_cells"]
