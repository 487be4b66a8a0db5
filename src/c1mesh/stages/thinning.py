"""The thinned vertex set of a smoothing fit (`--spacing D`): one vertex per D × D cell.

A smoothing fit (c1mesh.stages.smoothing) needs no vertex at every data point: its
spline can be fitted to all points on a coarser vertex set, so that a survey of 100M
points gives a mesh or DEM of a few million vertices. The vertices stay data points —
in each D × D cell of the plane, the point nearest the cell's centre — so the
triangulation and its trim see a thinned scan of the same kind as the input, and the
trim's automatic --max-edge (a multiple of the median edge) scales with D.
"""
from __future__ import annotations

import numpy as np

from c1mesh.core.errors import InputError


def check_spacing(spacing: float | None) -> None:
    """InputError unless spacing is None or a finite positive length (checked before any work)."""
    if spacing is None:
        return
    if not np.isfinite(spacing) or spacing <= 0:
        raise InputError(f"--spacing must be a positive length, got {spacing!r}")


def thin_to_cells(xy: np.ndarray, spacing: float) -> np.ndarray:
    """Indices (ascending) of one point per occupied spacing × spacing cell of the plane.

    xy (N, 2) in the plane's length units; the cells are aligned at the points' lower-left
    corner. In each cell the point nearest the cell's centre is kept (ties: the lower
    index), so the choice does not depend on the order of the other points. NaN rows are
    never kept. `thin_cells` with the points' corner and indices.
    """
    check_spacing(spacing)
    xy = np.asarray(xy, dtype=float)
    finite = np.flatnonzero(np.isfinite(xy).all(axis=1))
    if finite.size == 0:
        return finite
    p = xy[finite]
    return finite[thin_cells(p, spacing, p.min(axis=0), finite)]


def thin_cells(xy: np.ndarray, spacing: float, origin: np.ndarray, tie: np.ndarray) -> np.ndarray:
    """Positions (ascending) into xy (m, 2, finite) of the point nearest the centre of each
    spacing × spacing cell they occupy, the cells aligned at origin (2,); ties: the lower
    `tie` (m,) (distinct numbers, e.g. survey numbers). A point's cell and distance depend
    only on it, the spacing and the origin, so a tile that holds every point of a cell
    (its own cell grown by one spacing: survey.thinning_runs) keeps the same point as
    the whole survey does."""
    cell = np.floor((xy - origin) / spacing)
    offset = xy - (cell + 0.5) * spacing - origin
    distance2 = offset[:, 0] ** 2 + offset[:, 1] ** 2
    order = np.lexsort((tie, distance2, cell[:, 0], cell[:, 1]))    # by cell, then nearest, then tie
    first = np.ones(order.size, dtype=bool)
    first[1:] = (cell[order[1:]] != cell[order[:-1]]).any(axis=1)
    return np.sort(order[first])


__all__ = ["check_spacing", "thin_cells", "thin_to_cells"]
