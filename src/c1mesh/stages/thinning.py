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
    never kept.
    """
    check_spacing(spacing)
    xy = np.asarray(xy, dtype=float)
    finite = np.flatnonzero(np.isfinite(xy).all(axis=1))
    if finite.size == 0:
        return finite
    p = xy[finite]
    cell = np.floor((p - p.min(axis=0)) / spacing)
    offset = p - (cell + 0.5) * spacing - p.min(axis=0)
    distance2 = offset[:, 0] ** 2 + offset[:, 1] ** 2
    columns = cell[:, 0].max() + 1
    key = cell[:, 1] * columns + cell[:, 0]           # exact in float64 below 2**53 cells
    order = np.lexsort((finite, distance2, key))       # by cell, then nearest, then index
    first = np.ones(order.size, dtype=bool)
    first[1:] = key[order[1:]] != key[order[:-1]]
    return np.sort(finite[order[first]])


__all__ = ["check_spacing", "thin_to_cells"]
