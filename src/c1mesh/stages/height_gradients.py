"""Vertex gradients of a height field estimated from the heights themselves.

Where a scan carries no normals (LAS/LAZ, bare xyz), the pipeline estimates them by PCA of
the k nearest neighbours in 3-D (c1mesh.stages.normals) and turns them into gradients. A PCA
plane is the best plane through the neighbourhood, so on curved ground its slope is off
by O(h) and across a step it is smeared over the whole neighbourhood; the spline, which
interpolates the heights exactly, then meets gradients that its own heights contradict.

`height_gradients` fits, at every point, a weighted least-squares polynomial in the plane
offsets (dx, dy) to the height differences of its k nearest neighbours in (x, y), and
returns the polynomial's gradient at the point. The polynomial passes through the point's
own height (the spline interpolates it), so the fit is exact for every quadratic
(degree 2) or plane (degree 1): exact data keep their convergence orders.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.threads import parallel_blocks
from c1mesh.core.threads import workers as thread_count
from c1mesh.core.tile import bounds, finite_rows
from c1mesh.stages.height_field import gradients_to_normals
from c1mesh.stages import _height_gradients as kernel

GRADIENT_MODES = ("auto", "normals", "heights")
"""Where a fit's vertex gradients come from: "normals" (file or PCA normals), "heights"
(`height_gradients`), "auto" (heights where the normals were estimated, else normals)."""

NEIGHBOUR_FACTOR = 1.5
"""The quadratic fit uses this many times the k of the PCA normals (5 unknowns, not 3)."""
BLOCK = 1 << 15
"""Points per block: a block's neighbour indices and offsets (block, k) stay at a few MB."""
PER_CELL = 12
"""Points per occupied cell of the neighbour search's grid (PlaneGrid), on average: for the
24 neighbours of the default fit, the 3 × 3 cells around a point usually hold them all."""
COUNTING_CELLS = 8
"""plane_grid sorts its points by cell with a counting sort while the grid has at most
this many cells per point (a far outlier's grid can have many more: then numpy's sort)."""
RIDGE = 1e-9
"""Relative ridge on the normal equations: a neighbourhood whose offsets lie on one line
(a scan line) leaves the slope and curvature across it undetermined; the ridge sets them
to 0 there instead of failing, and changes well-posed fits by ~1e-9 relative."""


def use_height_gradients(mode: str, normal_source: str) -> bool:
    """Whether a fit takes its gradients from the heights: mode is one of GRADIENT_MODES,
    normal_source "file" or "estimated" (c1mesh.pipeline.driver.cloud_normals)."""
    if mode not in GRADIENT_MODES:
        raise InputError(f"gradients must be one of {', '.join(GRADIENT_MODES)}, got {mode!r}")
    return mode == "heights" or (mode == "auto" and normal_source == "estimated")


def height_neighbours(k: int) -> int:
    """Neighbours of the quadratic height fit for a normal-estimation k (default 16 -> 24)."""
    return int(np.ceil(NEIGHBOUR_FACTOR * k))


def height_normals(points: np.ndarray, frame, k: int, workers: int | None = None) -> np.ndarray:
    """World unit normals (N, 3) of the height field fitted to world points (N, 3) in a
    given frame (c1mesh.stages.frame.ScanFrame): `height_gradients` of the local heights turned
    into upward normals. NaN rows for points with a non-finite coordinate. workers: the
    fit's threads (None: the thread knob's count; the result is the same for any).

    What the pipeline uses instead of PCA normals when the height axis is given (LAS/LAZ:
    z): the frame needs no normals then, and the height field's gradients are the fit's.
    """
    pts = np.asarray(points, dtype=np.float64)
    finite = finite_rows(pts)
    local = frame.to_local(pts if finite.all() else pts[finite])
    normals = np.full(pts.shape, np.nan)
    normals[finite] = frame.vectors_to_world(fitted_normals(local, None, k, workers)[0])
    return normals


def fitted_normals(local: np.ndarray, at: np.ndarray | None, k: int,
                   workers: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(normals (m, 3), reach (m,)): upward unit normals, in the frame, of the height fit
    (`gradients_at`) at the points `at` (m,) rows of local (n, 3) frame coordinates (None:
    every point), each one's k nearest plane neighbours taken among all n; reach, each
    one's plane distance to its k-th neighbour. The in-memory fit's normals (`height_normals`,
    at every point) and a tile's (c1mesh.survey.tile_normals: at its own points, whose
    reach says whether what the tile read held their neighbourhoods). workers: as
    `height_gradients` takes them."""
    gradients, reach = gradients_at(local[:, :2], local[:, 2], at, k=k, workers=workers)
    return gradients_to_normals(gradients), reach


def height_gradients(xy: np.ndarray, z: np.ndarray, k: int = 16, degree: int = 2,
                     workers: int | None = None) -> np.ndarray:
    """Gradients (n, 2) of heights z (n,) over plane points xy (n, 2), one per point.
    (`gradients_at` gives them at some of the points, with each one's neighbour reach.)

    For point i with neighbours j (the k nearest other points in the plane), the offsets
    d_j = xy_j − xy_i and height differences Δ_j = z_j − z_i are fitted by
        Δ ≈ g·d + ½ dᵀ H d            (degree 2; degree 1 drops H)
    in weighted least squares with weights w_j = 1 / (1 + |d_j|² / r²), r the median
    neighbour distance (closer neighbours say more about the slope at the point). The
    result is g. Offsets are scaled by r before the solve (conditioning at any unit).
    The neighbours and the order of the sums depend only on the coordinates
    (`nearest_neighbours`: distance ties broken by the offsets), so the result does not
    change, to the bit, when the points are renumbered or points outside the
    neighbourhoods are dropped: a tile gives the survey's gradients.
    The fit is exact for any quadratic (degree 2) or affine (degree 1) height function
    whenever the neighbours determine it; where they do not (fewer than 5 non-collinear
    neighbours), the ridge RIDGE keeps the solve finite and the quadratic terms small.
    workers: threads, each taking blocks of BLOCK points (its neighbour search and its
    fit); None: the thread knob's count (c1mesh.core.threads.workers), as every pool of
    the package.
    Units: xy in one unit (the plan's), z in any unit; the gradients are in z units per
    xy unit. Nothing compares heights with plane distances, so heights in feet over a
    plan in 50 ft cells (R's `topo`) or in metres over kilometres are fitted as well as
    heights in the units of the plan.
    Raises InputError for bad shapes, fewer than 3 distinct plane positions (no slope
    can be fitted), or degree not 1 or 2.
    """
    return gradients_at(xy, z, None, k, degree, workers)[0]


def gradients_at(xy: np.ndarray, z: np.ndarray, at: np.ndarray | None, k: int = 16,
                 degree: int = 2, workers: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(gradients (m, 2), reach (m,)) of `height_gradients` at the points `at` (m,) indices
    into xy (None: every point), with the neighbours still taken among all n points;
    reach is each point's plane distance to its k-th (farthest) neighbour. The same bits
    as height_gradients' rows `at`: a tile fits its own points only, and its reach says
    whether the buffer it read held every neighbourhood."""
    workers = thread_count(workers)
    xy = np.asarray(xy, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or z.shape != (xy.shape[0],):
        raise InputError(f"height_gradients needs xy (n, 2) and z (n,), got {xy.shape} and {z.shape}")
    if degree not in (1, 2):
        raise InputError(f"height_gradients fits degree 1 or 2, got {degree}")
    n = xy.shape[0]
    check_positions(n, _distinct_positions(xy, 3))
    k = int(min(max(k, 2 if degree == 1 else 5), n - 1))
    # Points in the search grid's cell order: neighbours then sit close in memory.
    grid, order = plane_grid(xy)
    xy, z = np.ascontiguousarray(xy[order]), np.ascontiguousarray(z[order])
    if at is None:
        centres, slot = np.arange(n), order
    else:
        rank = np.empty(n, dtype=np.int64)
        rank[order] = np.arange(n)
        wanted = rank[np.asarray(at, dtype=np.int64)]
        slot = _ascending_order(wanted, n)                   # centres in cell order too
        centres = wanted[slot]
    m = centres.size
    out = np.empty((m, 2))
    reach2 = np.empty(m)

    def fit(block: slice) -> None:
        centre = centres[block]
        neighbours, offsets = nearest_neighbours(grid, xy, z, centre, k)
        reach2[slot[block]] = offsets[2][:, -1]
        out[slot[block]] = _fit_block(z, centre, neighbours, offsets, degree)
    # Each block is a search and a fit of its own (both release the GIL), so blocks run in
    # the knob's threads: every block gets the same neighbours and sums at any count.
    parallel_blocks(fit, m, BLOCK, threads=workers)
    return out, np.sqrt(reach2)


def _ascending_order(values: np.ndarray, n: int) -> np.ndarray:
    """np.argsort(values, kind="stable") of values (m,) in [0, n): for distinct values (a
    tile's own points), each value's position marked over [0, n) and read back in order,
    two linear passes where the sort took 1 s of the 12M survey's normals; else the sort."""
    where = np.full(n, -1, dtype=np.int64)
    where[values] = np.arange(values.size)
    order = where[where >= 0]
    return order if order.size == values.size else np.argsort(values, kind="stable")


def check_positions(points: int, positions: int) -> None:
    """InputError when `points` lie at fewer than 3 distinct (x, y) `positions`: no slope
    can be fitted. The tiled fit counts the positions of the whole survey while it streams
    it (c1mesh.pipeline.bounded_fit) and says the same."""
    if positions < 3:
        raise InputError(f"fitting slopes to heights needs at least 3 distinct (x, y) positions, "
                         f"got {points} point{'s' if points != 1 else ''} at {positions}")


def _distinct_positions(xy: np.ndarray, enough: int) -> int:
    """How many distinct rows points xy (n, 2) have, counted up to `enough`."""
    return len(distinct_rows(xy, enough))


def distinct_rows(xy: np.ndarray, enough: int, seen: list | None = None) -> list:
    """The first distinct rows of points xy (n, 2), up to `enough` of them, after those
    already `seen` (a list of rows; O(n · enough) comparisons, no sort). A stream of
    chunks finds a survey's first distinct positions by passing each chunk the list the
    last one returned. The rows are compared DISTINCT_CHUNK at a time, so the usual case
    (the first rows already differ) reads only the first of them, not three passes over
    every row (0.07 s at 1M points)."""
    seen = list(seen or [])
    for start in range(0, xy.shape[0], DISTINCT_CHUNK):
        if len(seen) >= enough:
            break
        part = xy[start:start + DISTINCT_CHUNK]
        new = np.ones(part.shape[0], dtype=bool)
        for row in seen:
            new &= (part != row).any(axis=1)
        while len(seen) < enough and new.any():
            seen.append(part[int(np.argmax(new))])
            new &= (part != seen[-1]).any(axis=1)
    return seen


DISTINCT_CHUNK = 1 << 14
"""Rows per step of `distinct_rows`."""


@dataclass(frozen=True)
class PlaneGrid:
    """The cells of the neighbour search over plane points sorted by cell (plane_grid):
    cell (i, j), of side `size` from the corner (x0, y0), is number j·nx + i; `cells` (c,)
    the occupied numbers ascending, whose points are the rows starts[c] ... starts[c+1] − 1;
    cell_x, cell_y (n,) each point's i and j. Plane units."""

    x0: float
    y0: float
    size: float
    nx: int
    ny: int
    cells: np.ndarray
    starts: np.ndarray
    cell_x: np.ndarray
    cell_y: np.ndarray


def plane_grid(xy: np.ndarray, per_cell: int = PER_CELL) -> tuple[PlaneGrid, np.ndarray]:
    """(the grid of points xy (n, 2), order (n,)): the PlaneGrid of the points xy[order],
    which order sorts by cell. The side starts from the bounding box's area over n/per_cell
    cells and halves while the occupied cells hold more than 2·per_cell points on average,
    so a survey with a far outlier, or a strip across its box, gets cells sized to where
    its points are; only occupied cells are stored (memory O(n) whatever the box)."""
    n = len(xy)
    low, high = bounds(xy)
    extent = high - low
    area = float(extent[0] * extent[1])
    size = float(np.sqrt(area * per_cell / n)) if area > 0 else float(extent.max() * per_cell / n)
    if not size > 0:
        size = 1.0                                    # every point at one position
    while True:
        cell_x = np.floor((xy[:, 0] - low[0]) / size).astype(np.int64)
        cell_y = np.floor((xy[:, 1] - low[1]) / size).astype(np.int64)
        nx, ny = int(cell_x.max()) + 1, int(cell_y.max()) + 1
        number = cell_y * nx + cell_x
        order = _stable_order(number, nx * ny)
        number = number[order]
        first = np.flatnonzero(np.r_[True, number[1:] != number[:-1]])
        crowded = n > 2 * per_cell * len(first) and size > extent.max() * 1e-9
        if not crowded or nx * ny > (1 << 60) // 4:
            break
        size /= 2
    grid = PlaneGrid(float(low[0]), float(low[1]), size, nx, ny, number[first],
                     np.append(first, n).astype(np.int64), cell_x[order], cell_y[order])
    return grid, order


def _stable_order(number: np.ndarray, cells: int) -> np.ndarray:
    """np.argsort(number, kind="stable") of cell numbers in [0, cells): by the kernel's
    counting sort where the cells are no more than COUNTING_CELLS per number (0.01 s
    against numpy's 0.11 s at 1M points), else numpy's."""
    if cells > COUNTING_CELLS * max(number.size, 1):
        return np.argsort(number, kind="stable")
    order = np.empty(number.size, dtype=np.int64)
    kernel.cell_order(np.ascontiguousarray(number, dtype=np.int64), np.zeros(cells + 1, dtype=np.int64), order)
    return order


def nearest_neighbours(grid: PlaneGrid, xy: np.ndarray, z: np.ndarray, centre: np.ndarray,
                       k: int) -> tuple[np.ndarray, tuple]:
    """(indices (b, k), their offsets (dx, dy, dx² + dy²) each (b, k)) of the k nearest
    other points of the points `centre` (b,), by a rule that depends only on the
    coordinates: nearest by squared plane distance, ties broken by the offset (dx, then
    dy, then the height), each row in that order (points equal in all of these are the
    same datum twice, taken in index order).

    Why: a search structure breaks distance ties by its own numbering, so on a grid
    (LiDAR's 1 cm) a point whose k-th and (k+1)-th neighbours are equally far would get a
    different neighbour set in a tile than in the whole survey; and the least-squares
    sums, added in row order, must be added in the same order to agree to the bit.
    grid, xy (n, 2), z (n,): plane_grid's grid and the points and heights in its order
    (contiguous); k < n. The search is the kernel's ring search over the grid's cells
    (stages/_height_gradients.pyx, grid_neighbours).
    """
    centre = np.ascontiguousarray(centre, dtype=np.int64)
    neighbours = np.empty((centre.size, k), np.int64)
    ux, uy, dist2 = (np.empty((centre.size, k)) for _ in range(3))
    kernel.grid_neighbours(xy, z, centre, grid.cell_x, grid.cell_y, grid.cells, grid.starts,
                           grid.nx, grid.ny, grid.x0, grid.y0, grid.size, neighbours, ux, uy, dist2)
    return neighbours, (ux, uy, dist2)


def _fit_block(z: np.ndarray, centre: np.ndarray, neighbours: np.ndarray, offsets: tuple,
               degree: int) -> np.ndarray:
    """Gradients (b, 2) of the weighted local fits at points `centre` (b,) with their
    neighbour indices (b, k) and offsets (dx, dy, dx² + dy²), each (b, k); see
    `height_gradients`. The kernel (stages/_height_gradients.pyx) solves each point's
    system in this thread, without the GIL; the sums over neighbours run in the columns'
    order."""
    ux, uy, dist2 = offsets
    out = np.empty((centre.size, 2))
    kernel.fit_block(z, np.ascontiguousarray(centre, dtype=np.int64), neighbours, ux, uy, dist2,
                     degree, RIDGE, np.finfo(float).tiny, out)
    return out
