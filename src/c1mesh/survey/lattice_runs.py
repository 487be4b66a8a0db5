"""The lattice route in tiles (`--smooth` with `--spacing D` beyond --memory): the stage
c1mesh.stages.lattice_mesh scheduled over the height spill.

In memory the smoothing's vertices are the nodes of the lattice of spacing D over the height
field's bounding box, its mesh the cells near the data (kept_cells), each node's source the
nearest point. Here the lattice is the survey's (its box a reduce over the tiles' spills,
`survey_bounds`), and each tile reads the heights within `lattice_read` cells of its own:
that holds every point kept_cells and nearest_points need for the cells and nodes around it.
A tile owns the cells whose centre lies in its cell and the nodes that lie in it
(TileGrid.tile_of, as every record's tile is chosen). It writes its nodes (NODE records:
node number as the index, position, source) to a new spill and its cells' triangles (node
numbers) to a .npy: a TiledMesh of the nodes, which the smoothing, the refinement and the
DEM take as they take the trimmed triangulation of points, while the smoothing fits every
height of the old spill (c1mesh.survey.smoothing_runs).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from c1mesh.core.tile import corner_rows, plane_bounds
from c1mesh.stages.hole_fill import (Holes, classify_corners, fill_holes, hull_rows, joined_hole_parts, joined_hull,
                                     point_hull, span_cells)
from c1mesh.stages.limiter import TileLimits
from c1mesh.survey.smoothing_runs import WrappedSmoother
from c1mesh.stages.lattice_mesh import (KEPT_BLOCK, REACH_CELLS, NodeGrid, cell_triangles, kept_cells, lattice_facts,
                                        nearest_points, node_grid)
from c1mesh.survey.tile_spill import TileSpill, save_array

NODE = np.dtype([("index", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("gx", "<f8"), ("gy", "<f8"),
                 ("source", "<i8")])
"""One lattice node of a tiled fit: its node number (as the survey number of a point), its
position in the frame's plane, a height and gradient (0: the smoothing fits them) and the
survey number of the nearest point (its colour; its input with -O)."""
LATTICE_MARGIN = REACH_CELLS[1] + KEPT_BLOCK + 2
"""Spacings by which a lattice fit grows the tile grid's box, before the point spacing h
and so R are known: the solve's cells reach R + KEPT_BLOCK <= LATTICE_MARGIN - 2 cells beyond the data,
and every node then lies in the box (TileGrid.tile_of would clip it to a border tile)."""


MARGIN_HALOS = 8
"""A tile's smoothing halo on the lattice is at least MARGIN_HALOS times the widest data-free
margin of its solve, R + KEPT_BLOCK cells (the support's reach and a block): the nodes
there carry no data, and their values reach across the margin (a 60 x 60 survey at D = 1,
R = 2, s = 3 in 9 tiles: 1.1e-3 from the in-memory heights with a halo of 35, 3.5 margins;
2e-13 at 50; autzen_trim at D = 2, R = 4: 1.0e-5 ft at 187 ft, 7.8 margins)."""


def lattice_halo(lattice: NodeGrid) -> float:
    """The least smoothing halo on the lattice (frame units): MARGIN_HALOS margins."""
    return MARGIN_HALOS * (lattice.reach + KEPT_BLOCK) * lattice.spacing


def lattice_read(lattice: NodeGrid) -> int:
    """Cells beyond its own a tile reads: kept_cells needs the points within 2R + KEPT_BLOCK
    cells of the cells it decides (its own, one more for the nodes on its border: + 1),
    nearest_points those within R + KEPT_BLOCK + 2; two more for rounding at the edges."""
    return 2 * lattice.reach + KEPT_BLOCK + 4


def survey_bounds(heights, hull: bool = False):
    """((2,), (2,)): the least and the largest x and y of the height spill's records; with
    hull, also the corners of their convex hull (hole_fill.point_hull, (h, 2)), the reduce
    of the tiles' hulls (hole_fill.joined_hull), read in the same pass."""
    hulls = []

    def parts():
        for t in range(len(heights.grid)):
            if heights.counts[t]:
                records = heights.tile(t)
                xy = np.column_stack([records["x"], records["y"]])
                if hull:
                    hulls.append(point_hull(xy))
                yield xy
    lower, upper = plane_bounds(parts())
    return (lower, upper, joined_hull(hulls)) if hull else (lower, upper)


@dataclass(frozen=True)
class LatticeTiles:
    """The lattice mesh in tiles: nodes (TileSpill of NODE records; the caller closes it),
    files (per tile the .npy of its solve cells' triangles, node numbers; None: no cells and
    no nodes; a tile with nodes and no cells has an empty one, so that the smoothing solves
    its nodes in its halo), shown_files (those of its support cells: the output's; None:
    none), buffers (per tile how far beyond its cell its triangles' corners lie), triangles
    (the shown triangles' count), grid (the NodeGrid). With a DEM's fill (lattice_tiles'
    hull), each shown file holds its support cells' triangles first (kept: per tile how
    many) and then those of its own cells of the holes (stages.hole_fill), whose free
    corners are nodes of the spill too; holes: the survey's Holes (None: no fill)."""

    nodes: TileSpill
    files: list
    shown_files: list
    buffers: np.ndarray
    triangles: int
    grid: NodeGrid
    kept: tuple | None = None
    holes: Holes | None = None
    fill_nodes: int = 0

    def facts(self) -> dict:
        """The report's smoothing.lattice, as the in-memory fit's (lattice_facts): the solve's
        nodes, without the fill's (fill_nodes: the holes' free corners no solve cell has)."""
        return lattice_facts(self.grid, int(self.nodes.counts.sum()) - self.fill_nodes)


def _window(lattice: NodeGrid, rect) -> tuple[int, int, int, int]:
    """(i0, i1, j0, j1): the lattice cells meeting rect (x0, y0, x1, y1), one more each side."""
    D, (fi, fj), (ox, oy) = lattice.spacing, lattice.first, lattice.offset
    rows, cols = lattice.cells
    i0 = max(math.floor((rect[0] - ox) / D) - fi - 1, 0)
    j0 = max(math.floor((rect[1] - oy) / D) - fj - 1, 0)
    i1 = min(math.floor((rect[2] - ox) / D) - fi + 2, cols)
    j1 = min(math.floor((rect[3] - oy) / D) - fj + 2, rows)
    return i0, max(i1, i0), j0, max(j1, j0)


def _tile_lattice(heights, tiles, lattice: NodeGrid, t: int, hull_rows: tuple | None = None) -> tuple:
    """(NODE records of tile t's nodes, ascending numbers; (k, 3) its solve cells'
    triangles; (k', 3) its support cells' triangles, the shown; its own Holes, None without
    hull_rows; how many of its nodes are the fill's only). hull_rows: hole_fill.hull_rows of
    the survey's hull, for a DEM's fill: the tile's nodes then include its holes' free
    corners."""
    D = lattice.spacing
    records = heights.records(tiles.grown(t, lattice_read(lattice) * D))
    xy = np.column_stack([records["x"], records["y"]])
    window = _window(lattice, tiles.cell(t))
    solve, shown = kept_cells(lattice, xy, window, blocks=True), kept_cells(lattice, xy, window)
    holes = None if hull_rows is None else _own_holes(lattice, tiles, t, window, shown, hull_rows)
    corners = np.unique(cell_triangles(lattice, solve))
    solved = corners
    if holes is not None:
        corners = np.union1d(corners, holes.free)
    positions = lattice.positions(corners)
    own = tiles.tile_of(positions) == t
    corners, positions = corners[own], positions[own]
    nodes = np.zeros(corners.size, NODE)
    nodes["index"], nodes["x"], nodes["y"] = corners, positions[:, 0], positions[:, 1]
    nodes["source"] = nearest_points(positions, xy, records["index"])
    fill_only = int(corners.size - np.isin(corners, solved, assume_unique=True).sum())
    return nodes, _own_triangles(lattice, tiles, t, solve), _own_triangles(lattice, tiles, t, shown), holes, fill_only


def _own_holes(lattice: NodeGrid, tiles, t: int, window: tuple, support: np.ndarray, hull_rows: tuple) -> Holes:
    """Tile t's share of the survey's Holes (hole_fill.find_holes): the hull's cells in its
    window the support leaves open whose centres lie in its cell, and their corners, free
    or on the rim. support: the window's support cells (kept_cells), which hold every cell
    around a corner of the tile's own cells (the window reaches one cell beyond them)."""
    i0, i1, j0, j1 = window
    first, last = hull_rows
    cells = span_cells(lattice, np.arange(j0, j1, dtype=np.int64), np.maximum(first[j0:j1], i0),
                       np.minimum(last[j0:j1], i1 - 1))
    cells = cells[~np.isin(cells, support)]
    cells = cells[tiles.tile_of(lattice.centres(cells)) == t]
    return classify_corners(lattice, cells, support)


def _own_triangles(lattice: NodeGrid, tiles, t: int, cells: np.ndarray) -> np.ndarray:
    """(k, 3) the triangles of the cells (ascending numbers) whose centre lies in tile t."""
    return cell_triangles(lattice, cells[tiles.tile_of(lattice.centres(cells)) == t])


def lattice_tiles(heights, spacing: float, point_spacing: float, temps, stem: str,
                  offset=(0.0, 0.0), fill: bool = False) -> LatticeTiles:
    """The lattice mesh of the height spill at `spacing` (module doc), its points' spacing
    h = point_spacing (height_runs.survey_stacking's, the in-memory fit's), its nodes at
    the multiples of D from `offset` (lattice_mesh.lattice_offset of the survey's frame),
    tile by tile in this process (each tile's work is a few numpy passes over its heights).
    fill: a DEM's fill (stages.hole_fill): the survey's hull is found with its bounds, and
    each tile adds its holes' cells to its shown ones (LatticeTiles)."""
    tiles = heights.grid
    lower, upper, *hull = survey_bounds(heights, hull=fill)
    lattice = node_grid(lower, upper, spacing, point_spacing, offset)
    rows = hull_rows(lattice, hull[0]) if fill else None
    nodes = TileSpill(tiles, heights.directory, stem + ".lattice", record=NODE).__enter__()
    files, shown_files, kept, parts, count, fill_nodes = [], [], [], [], 0, 0
    try:
        for t in range(len(tiles)):
            own_nodes, solve, shown, holes, fill_only = _tile_lattice(heights, tiles, lattice, t, rows)
            fill_nodes += fill_only
            nodes.append(t, own_nodes)
            kept.append(len(shown))
            count += len(shown)
            if holes is not None:
                parts.append(holes)
                shown = np.concatenate([shown, cell_triangles(lattice, holes.cells)])
            path = shown_path = None
            if len(solve) or len(own_nodes):       # a tile with nodes solves them, with or without cells
                path = temps.new(f"lattice-{t}.npy")
                save_array(path, solve)
            if len(shown):
                shown_path = temps.new(f"lattice-shown-{t}.npy")
                save_array(shown_path, shown)
            files.append(path)
            shown_files.append(shown_path)
    except BaseException:
        nodes.close()
        raise
    return LatticeTiles(nodes, files, shown_files, np.full(len(tiles), 2.0 * spacing), count, lattice,
                        tuple(kept) if fill else None, joined_hole_parts(parts) if fill else None, fill_nodes)


class LatticeFill(WrappedSmoother):
    """A DEM's fill of a smoothing fit on the lattice in tiles (stages.hole_fill), after
    the smoothing (smoother: its TiledSmoother): the reduce reads the rim nodes' fitted
    data from the tiles' files, solves every hole whole in this process (fill_holes), and
    keeps the free nodes' records (NODE, ascending numbers), which take the place of any
    fitted ones; a DEM task takes its tile's data through `tile`, as from the smoother."""

    def __init__(self, smoother, lattice: LatticeTiles, scheme):
        self.smoother = smoother
        self.limited = self.turned = self.lifted = 0         # bounded_fit adds the DEM tasks' counts
        holes = lattice.holes
        rim = np.zeros(holes.rim.size, NODE)
        found = np.zeros(holes.rim.size, dtype=bool)
        record = smoother.halos.heights.record
        for path, _ in smoother.paths.values():
            fitted = np.fromfile(path, dtype=record)
            at = np.searchsorted(holes.rim, fitted["index"])
            hit = np.flatnonzero((at < holes.rim.size) & (holes.rim[np.minimum(at, holes.rim.size - 1)]
                                                          == fitted["index"]))
            rim[at[hit]], found[at[hit]] = fitted[hit], True
        if not found.all():
            raise RuntimeError(f"{int((~found).sum())} rim nodes of the DEM's holes have no fitted data")
        values, gradients = fill_holes(lattice.grid, holes, rim["z"], np.column_stack([rim["gx"], rim["gy"]]),
                                       scheme)
        filled = np.zeros(holes.free.size, NODE)
        filled["index"] = holes.free
        positions = lattice.grid.positions(holes.free)
        filled["x"], filled["y"], filled["z"] = positions[:, 0], positions[:, 1], values
        filled["gx"], filled["gy"], filled["source"] = gradients[:, 0], gradients[:, 1], -1
        self.filled = filled

    def tile(self, tile: int, triangles: np.ndarray):
        """limiter.TileLimits of tile's own triangles (k, 3) node numbers: the smoother's,
        the free nodes' records in place of any fitted ones."""
        fitted = self.smoother._fitted_near(tile)
        fitted = fitted[~np.isin(fitted["index"], self.filled["index"])]
        needed = self.filled[np.isin(self.filled["index"], triangles)].astype(fitted.dtype)
        records = np.concatenate([fitted, needed])
        records = records.take(np.argsort(records["index"], kind="stable"))
        rows, local = corner_rows(records["index"], triangles)
        if np.any(rows < 0):
            raise RuntimeError(f"tile {tile}: a corner of its triangles has no fitted or filled data")
        records = records.take(rows)
        return TileLimits(records, local, np.column_stack([records["gx"], records["gy"]]), None, 0, 0, 0)


__all__ = ["LATTICE_MARGIN", "LatticeFill", "LatticeTiles", "MARGIN_HALOS", "NODE", "lattice_halo", "lattice_read", "lattice_tiles",
           "survey_bounds"]
