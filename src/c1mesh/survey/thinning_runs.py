"""The thinned vertices of a smoothing fit in tiles (`--spacing D` beyond --memory): the
stage's thin_cells (c1mesh.stages.thinning) scheduled over the height spill.

In memory the vertices are, in each D × D cell aligned at the height field's lower-left
corner, the point nearest the cell's centre (ties: the lower survey number). Here the
corner is the survey's (a reduce over the tiles' spills), and each tile thins the heights
in its cell grown by D: every cell that holds one of its own points lies within that, so
the tile sees all of the cell's points and keeps the point the whole survey keeps; it
writes those of the kept points that lie in its own cell to a new spill, which the
triangulation, the trim and the refinement then take as the survey's vertices, while the
smoothing fits every height of the old one (c1mesh.survey.smoothing_runs)."""
from __future__ import annotations

import numpy as np

from c1mesh.stages.thinning import thin_cells
from c1mesh.survey.tile_spill import TileSpill


def survey_corner(heights) -> np.ndarray:
    """(2,) the least x and y of the height spill's records (frame units)."""
    corner = np.full(2, np.inf)
    for t in range(len(heights.grid)):
        if heights.counts[t]:
            records = heights.tile(t)
            corner = np.minimum(corner, [records["x"].min(), records["y"].min()])
    return corner


def thinned_spill(heights, spacing: float, directory, stem: str) -> TileSpill:
    """A new TileSpill of the height records that are the survey's thinned vertices at
    `spacing` (module docstring), in survey order per tile; the caller closes it."""
    grid, corner = heights.grid, survey_corner(heights)
    thinned = TileSpill(grid, directory, stem + ".thinned", record=heights.record).__enter__()
    try:
        for t in range(len(grid)):
            if not heights.counts[t]:
                continue
            records = heights.records(grid.grown(t, spacing * (1 + 1e-9)))
            xy = np.column_stack([records["x"], records["y"]])
            kept = thin_cells(xy, spacing, corner, records["index"])
            thinned.append(t, records.take(kept[grid.tile_of(xy[kept]) == t]))    # structured rows: take
    except BaseException:
        thinned.close()
        raise
    return thinned
