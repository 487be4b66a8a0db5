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

from c1mesh.core.tile import plane_bounds
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


def survey_bounds(heights) -> tuple[np.ndarray, np.ndarray]:
    """((2,), (2,)): the least and the largest x and y of the height spill's records."""
    def parts():
        for t in range(len(heights.grid)):
            if heights.counts[t]:
                records = heights.tile(t)
                yield np.column_stack([records["x"], records["y"]])
    return plane_bounds(parts())


@dataclass(frozen=True)
class LatticeTiles:
    """The lattice mesh in tiles: nodes (TileSpill of NODE records; the caller closes it),
    files (per tile the .npy of its solve cells' triangles, node numbers; None: no cells and
    no nodes; a tile with nodes and no cells has an empty one, so that the smoothing solves
    its nodes in its halo), shown_files (those of its support cells: the output's; None:
    none), buffers (per tile how far beyond its cell its triangles' corners lie), triangles
    (the shown triangles' count), grid (the NodeGrid)."""

    nodes: TileSpill
    files: list
    shown_files: list
    buffers: np.ndarray
    triangles: int
    grid: NodeGrid

    def facts(self) -> dict:
        """The report's smoothing.lattice, as the in-memory fit's (lattice_facts)."""
        return lattice_facts(self.grid, int(self.nodes.counts.sum()))


def _window(lattice: NodeGrid, rect) -> tuple[int, int, int, int]:
    """(i0, i1, j0, j1): the lattice cells meeting rect (x0, y0, x1, y1), one more each side."""
    D, (fi, fj), (ox, oy) = lattice.spacing, lattice.first, lattice.offset
    rows, cols = lattice.cells
    i0 = max(math.floor((rect[0] - ox) / D) - fi - 1, 0)
    j0 = max(math.floor((rect[1] - oy) / D) - fj - 1, 0)
    i1 = min(math.floor((rect[2] - ox) / D) - fi + 2, cols)
    j1 = min(math.floor((rect[3] - oy) / D) - fj + 2, rows)
    return i0, max(i1, i0), j0, max(j1, j0)


def _tile_lattice(heights, tiles, lattice: NodeGrid, t: int) -> tuple:
    """(NODE records of tile t's nodes, ascending numbers; (k, 3) its solve cells'
    triangles; (k', 3) its support cells' triangles, the shown)."""
    D = lattice.spacing
    records = heights.records(tiles.grown(t, lattice_read(lattice) * D))
    xy = np.column_stack([records["x"], records["y"]])
    window = _window(lattice, tiles.cell(t))
    solve, shown = kept_cells(lattice, xy, window, blocks=True), kept_cells(lattice, xy, window)
    corners = np.unique(cell_triangles(lattice, solve))
    positions = lattice.positions(corners)
    own = tiles.tile_of(positions) == t
    corners, positions = corners[own], positions[own]
    nodes = np.zeros(corners.size, NODE)
    nodes["index"], nodes["x"], nodes["y"] = corners, positions[:, 0], positions[:, 1]
    nodes["source"] = nearest_points(positions, xy, records["index"])
    return nodes, _own_triangles(lattice, tiles, t, solve), _own_triangles(lattice, tiles, t, shown)


def _own_triangles(lattice: NodeGrid, tiles, t: int, cells: np.ndarray) -> np.ndarray:
    """(k, 3) the triangles of the cells (ascending numbers) whose centre lies in tile t."""
    return cell_triangles(lattice, cells[tiles.tile_of(lattice.centres(cells)) == t])


def lattice_tiles(heights, spacing: float, point_spacing: float, temps, stem: str,
                  offset=(0.0, 0.0)) -> LatticeTiles:
    """The lattice mesh of the height spill at `spacing` (module doc), its points' spacing
    h = point_spacing (height_runs.survey_stacking's, the in-memory fit's), its nodes at
    the multiples of D from `offset` (lattice_mesh.lattice_offset of the survey's frame),
    tile by tile in this process (each tile's work is a few numpy passes over its heights)."""
    tiles = heights.grid
    lower, upper = survey_bounds(heights)
    lattice = node_grid(lower, upper, spacing, point_spacing, offset)
    nodes = TileSpill(tiles, heights.directory, stem + ".lattice", record=NODE).__enter__()
    files, shown_files, count = [], [], 0
    try:
        for t in range(len(tiles)):
            own_nodes, solve, shown = _tile_lattice(heights, tiles, lattice, t)
            nodes.append(t, own_nodes)
            path = shown_path = None
            if len(solve) or len(own_nodes):       # a tile with nodes solves them, with or without cells
                path = temps.new(f"lattice-{t}.npy")
                save_array(path, solve)
            if len(shown):
                shown_path = temps.new(f"lattice-shown-{t}.npy")
                save_array(shown_path, shown)
                count += len(shown)
            files.append(path)
            shown_files.append(shown_path)
    except BaseException:
        nodes.close()
        raise
    return LatticeTiles(nodes, files, shown_files, np.full(len(tiles), 2.0 * spacing), count, lattice)


__all__ = ["LATTICE_MARGIN", "LatticeTiles", "MARGIN_HALOS", "NODE", "lattice_halo", "lattice_read", "lattice_tiles",
           "survey_bounds"]
