"""Ground points of an airborne LiDAR survey: SMRF, slope-adaptive, plus raised segments,
tile by tile.

The filter (`classify_ground`) is the Simple Morphological Filter of Pingel, Clarke &
McBride (2013, "An improved simple morphological filter for the terrain classification of
airborne LIDAR data", ISPRS J. 77), written here from the paper with scipy.ndimage, with
two additions that make one parameter set hold on steep ground and on large roofs
(issue 39; the measurements are in benchmarks/RESULTS.md):

1. The minimum surface: the lowest height in each cell of a grid of `cell` metres whose
   cells are aligned to the global origin (cell (i, j) covers [i·cell, (i+1)·cell) ×
   [j·cell, (j+1)·cell)), so that any tile of a survey sees the same cells.
2. SMRF's progressive opening: the minimum surface is opened (grey erosion then dilation,
   flat square window of radius r cells, empty cells ignored) for r = 1 … ceil(window /
   cell); a cell whose opened height drops by more than slope · r · cell between radius
   r − 1 and r is an object. Each opening is taken of the minimum surface itself: for
   square windows that is the paper's iterated opening (a square opened by a smaller
   square is itself), and it keeps each step a local operation of radius 2r.
3. Raised segments (not in SMRF): the cells of the median surface (the median height of
   each cell, small gaps closed by their lowest neighbour) are joined into segments where
   4-neighbours differ by less than `step` metres; cells inside a jump (a wall's returns)
   join none. A segment whose bounding box is smaller than `segment_extent` metres and
   which stands `step` or more above its neighbours on at least `raised_fraction` of its
   border is an object. This finds a flat roof too wide for any opening, and one cut by
   the edge of the survey (where an opening cannot see ground on its far side); ground,
   even steep, has no such steps around it.
4. Slope-adaptive SMRF (not in SMRF): SMRF's slope is a constant, and no constant serves
   both flat towns (0.15 finds low objects) and steep ground (where it cuts every ridge:
   the opening of a ridge of slope s drops by s · r). A first pass at `steep_slope`
   gives a DEM whose slope, a low percentile of it around each cell, is the ground's; the
   second pass uses max(slope, ground slope) per cell, and the final threshold too.
5. The provisional DEM: ground cells keep their minimum; every other cell gets the value
   of a local weighted plane fit (normalised convolution, Gaussian weights of σ =
   fill_scales cells truncated at 4σ: the smallest σ whose neighbourhood holds enough
   ground) to the ground cells. The paper inpaints with a global spring model; the
   bounded fit keeps the filter local.
6. A point is ground when |z − DEM(x, y)| ≤ threshold + scalar · slope (bilinear DEM
   between cell centres, slope as rise over run), as in the paper.

Every step has a bounded reach (`reach_cells`), so a tile that holds its points plus
`halo_width(params)` metres around them classifies them exactly as the whole survey does
(tests/test_ground.py checks that bit for bit on four tiles). Everything is in metres:
callers convert feet first (c1mesh.core.crs.metres_per_unit). With
GroundParameters(**PDAL_SMRF) it is plain SMRF at PDAL's defaults, for comparison.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from c1mesh.core.crs import metres_per_unit
from c1mesh.core.errors import InputError
from c1mesh.core.lazy import LazyModule
from c1mesh.stages.trim import connected_sets

ndimage = LazyModule("scipy.ndimage")

#: The truncation (in σ) of the Gaussian weights of the DEM's plane fit.
_FILL_TRUNCATE = 4
#: The scales of the first pass's DEM, which serves only the ground slope near ground.
_FIRST_SCALES = (1, 2, 4)
#: The share of a full neighbourhood's weight that must be ground for a scale to be used.
_FILL_ENOUGH = 0.05
#: Ridge on the fitted plane's slopes, relative to the neighbourhood's weight × σ².
_RIDGE = 0.01


@dataclass(frozen=True)
class GroundParameters:
    """The filter's parameters, all lengths in metres.

    cell: grid cell; slope: SMRF's slope (rise over run) of the opening's threshold, the
    least one (steeper ground raises it: steep_slope, slope_window, slope_percentile);
    window: SMRF's largest window radius; threshold, scalar: a point is ground within
    threshold + scalar · ground slope of the DEM (SMRF's elevation threshold and scalar);
    step: the height jump between neighbour cells that separates segments;
    segment_extent: the largest raised segment (bounding-box side) taken as an object
    (0: none, plain SMRF); raised_fraction: the share of a segment's border that must step
    down from it; steep_slope: the SMRF slope of the first pass, whose DEM gives the
    ground slope; slope_window: the radius (m) over which the ground slope is the
    slope_percentile-th percentile of that DEM's slope; adaptive: False for SMRF's single
    pass with the DEM's own slope (as the paper and PDAL do); fill_scales: the Gaussian
    scales (cells, smallest first) of the DEM's plane fit under objects, whose largest
    sets how far from ground a DEM is known (4 × 16 m by default) and most of the halo.
    The defaults are the ones measured in benchmarks/RESULTS.md (issue 39).
    """

    cell: float = 1.0
    slope: float = 0.15
    window: float = 18.0
    threshold: float = 0.25
    scalar: float = 1.0
    step: float = 1.5
    segment_extent: float = 80.0
    raised_fraction: float = 0.75
    steep_slope: float = 0.5
    slope_window: float = 5.0
    slope_percentile: float = 25.0
    adaptive: bool = True
    fill_scales: tuple[int, ...] = (1, 2, 4, 8, 16)

    def as_dict(self) -> dict:
        return asdict(self)


PDAL_SMRF = dict(slope=0.15, window=18.0, threshold=0.5, scalar=1.25, segment_extent=0.0, adaptive=False)
"""GroundParameters(**PDAL_SMRF): plain SMRF at PDAL's filters.smrf defaults (a peer)."""


def _cells(length: float, cell: float) -> int:
    return int(math.ceil(length / cell - 1e-9))


def reach_cells(params: GroundParameters) -> int:
    """How many cells away a point's class can depend on: the final DEM's fit, then an
    object flag (SMRF's opening reaches 2 · window, a raised segment its extent and the
    closed gaps) that in the adaptive filter also depends on the ground slope (its window,
    the gradient and the first pass's DEM fit, then that pass's flags), plus the cells of
    the bilinear DEM and its slope."""
    radius = _cells(params.window, params.cell)
    flags = max(2 * radius, _cells(params.segment_extent, params.cell) + 2 * _GAP_PASSES + 2)
    slope = _cells(params.slope_window, params.cell) + 1 + _FILL_TRUNCATE * _FIRST_SCALES[-1] + flags
    return _FILL_TRUNCATE * params.fill_scales[-1] + (slope if params.adaptive else flags) + 3


def halo_width(params: GroundParameters) -> float:
    """Metres of points around a tile that make its classes those of the whole survey:
    the reach plus two cells (a halo edge cuts the cells it crosses)."""
    return (reach_cells(params) + 2) * params.cell


@dataclass(frozen=True)
class _Grid:
    """A window of the global grid: cell (row, col) of the window is global cell
    (row0 + row, col0 + col), rows along y and columns along x."""

    row0: int
    col0: int
    shape: tuple[int, int]
    cell: float


def classify_ground(points: np.ndarray, owned: np.ndarray | None = None,
                    params: GroundParameters = GroundParameters()) -> np.ndarray:
    """(m,) bool: which `owned` points (all when None) of `points` are ground.

    points: (n, 3) x, y, z in metres (a tile and its halo); owned: (n,) bool, the tile's
    own points. With at least halo_width(params) metres of the survey's points around the
    owned ones, the answer is the one the whole survey gives them. Points with a
    non-finite coordinate are not ground.
    """
    points = np.asarray(points, dtype=np.float64)
    owned = np.ones(len(points), dtype=bool) if owned is None else np.asarray(owned, dtype=bool)
    finite = np.isfinite(points).all(axis=1)
    ground = np.zeros(len(points), dtype=bool)
    if finite.sum() == 0:
        return ground[owned]
    grid, row, col = _grid_of(points[finite], params.cell)
    check_density(grid.shape, int(finite.sum()), params)
    zmin = _minimum_surface(grid, row, col, points[finite, 2])
    data = np.isfinite(zmin)
    raised = _raised_segments(_median_surface(grid, row, col, points[finite, 2]), data, params)
    if params.adaptive:
        slope = _ground_slope(zmin, data, raised, grid, params)
        objects = _smrf_objects(zmin, data, params, np.maximum(params.slope, slope)) | raised
        dem, _ = _provisional_dem(zmin, data & ~objects, grid, params.fill_scales)
    else:
        objects = _smrf_objects(zmin, data, params) | raised
        dem, slope = _provisional_dem(zmin, data & ~objects, grid, params.fill_scales)
    ground[finite] = _near_dem(points[finite], dem, slope, grid, params)
    return ground[owned]


#: The most grid cells per point the filter allocates (beyond a floor of MAX_CELLS_FLOOR):
#: a sparse survey would otherwise make a grid of gigabytes for a few points.
MAX_CELLS_PER_POINT = 64
MAX_CELLS_FLOOR = 4_000_000


def check_density(shape: tuple[int, int], count: int, params: GroundParameters) -> None:
    """InputError when a grid of `shape` cells is too large for `count` points: fewer than
    one point per MAX_CELLS_PER_POINT cells (over MAX_CELLS_FLOOR cells), far too sparse
    for a ground filter of params.cell-metre cells and a waste of memory."""
    cells = shape[0] * shape[1]
    if cells > max(MAX_CELLS_FLOOR, MAX_CELLS_PER_POINT * count):
        area = cells * params.cell ** 2
        raise InputError(f"{count} points over {area / 1e6:.3g} km² are too sparse for the ground filter "
                         f"(under one point per {MAX_CELLS_PER_POINT * params.cell ** 2:g} m², "
                         f"{MAX_CELLS_PER_POINT} cells of its {params.cell:g} m grid)")


def _ground_slope(zmin: np.ndarray, data: np.ndarray, raised: np.ndarray, grid: _Grid,
                  params: GroundParameters) -> np.ndarray:
    """(rows, cols) the slope of the ground around each cell (rise over run): the
    slope_percentile-th percentile, over slope_window, of the slope of a first pass's DEM
    (SMRF at steep_slope, which cuts no ridge of steep terrain, and raised segments). A
    low percentile, so that objects the first pass keeps do not make flat ground steep;
    0 where that DEM is unknown."""
    first = _smrf_objects(zmin, data, replace(params, slope=params.steep_slope)) | raised
    _, slope = _provisional_dem(zmin, data & ~first, grid, _FIRST_SCALES)
    size = 2 * _cells(params.slope_window, params.cell) + 1
    return ndimage.percentile_filter(slope, params.slope_percentile, size=size, mode="nearest")


def _grid_of(points: np.ndarray, cell: float) -> tuple[_Grid, np.ndarray, np.ndarray]:
    """The window of the global grid covering `points` and each point's (row, col) in it."""
    cols = np.floor(points[:, 0] / cell).astype(np.int64)
    rows = np.floor(points[:, 1] / cell).astype(np.int64)
    grid = _Grid(int(rows.min()), int(cols.min()),
                 (int(rows.max() - rows.min()) + 1, int(cols.max() - cols.min()) + 1), cell)
    return grid, rows - grid.row0, cols - grid.col0


def _median_surface(grid: _Grid, row: np.ndarray, col: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(rows, cols) the median z in each cell (the upper middle of an even count), +inf
    where a cell holds no point. Unlike the minimum, a few returns from a wall do not
    pull a roof's edge cells down to the ground beside it."""
    flat = row * grid.shape[1] + col
    order = np.lexsort((z, flat))
    cells, first, count = np.unique(flat[order], return_index=True, return_counts=True)
    median = np.full(grid.shape[0] * grid.shape[1], np.inf)
    median[cells] = z[order][first + count // 2]
    return median.reshape(grid.shape)


def _minimum_surface(grid: _Grid, row: np.ndarray, col: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(rows, cols) the lowest z in each cell, +inf where a cell holds no point."""
    zmin = np.full(grid.shape[0] * grid.shape[1], np.inf)
    np.minimum.at(zmin, row * grid.shape[1] + col, z)
    return zmin.reshape(grid.shape)


def _opening(zmin: np.ndarray, radius: int) -> np.ndarray:
    """Grey opening of the minimum surface by a (2·radius + 1)² flat square that ignores
    empty cells: erosion takes the lowest data cell in the window (+inf when none), the
    dilation the highest finite erosion. At a data cell the result is finite and ≤ zmin."""
    size = 2 * radius + 1
    eroded = ndimage.minimum_filter(zmin, size=size, mode="constant", cval=np.inf)
    eroded[~np.isfinite(eroded)] = -np.inf
    return ndimage.maximum_filter(eroded, size=size, mode="constant", cval=-np.inf)


def _smrf_objects(zmin: np.ndarray, data: np.ndarray, params: GroundParameters, slope=None) -> np.ndarray:
    """(rows, cols) bool: SMRF's object cells, whose opened height drops by more than
    slope · r · cell between window radii r − 1 and r (slope: params.slope, or a
    (rows, cols) array of per-cell slopes)."""
    slope = params.slope if slope is None else slope
    objects = np.zeros(zmin.shape, dtype=bool)
    previous = zmin
    for radius in range(1, _cells(params.window, params.cell) + 1):
        current = _opening(zmin, radius)
        with np.errstate(invalid="ignore"):
            objects |= data & (previous - current > slope * radius * params.cell)
        previous = current
    return objects


def _raised_segments(zmid: np.ndarray, data: np.ndarray, params: GroundParameters) -> np.ndarray:
    """(rows, cols) bool: the data cells of raised segments of the median surface `zmid`:
    segments (`_segments`) smaller than segment_extent whose border pairs (neighbour
    cells in another segment) have the segment `step` or more above the neighbour in at
    least raised_fraction of them."""
    extent = _cells(params.segment_extent, params.cell)
    if extent <= 0 or not data.any():
        return np.zeros(zmid.shape, dtype=bool)
    surface = _close_gaps(zmid)
    labels, count, pairs, joined = _segments(surface, params.step)
    first, second = labels.flat[pairs[0][~joined]] - 1, labels.flat[pairs[1][~joined]] - 1
    rise = surface.flat[pairs[0][~joined]] - surface.flat[pairs[1][~joined]]
    up = (np.bincount(first[rise >= params.step], minlength=count)
          + np.bincount(second[-rise >= params.step], minlength=count))
    border = np.bincount(first, minlength=count) + np.bincount(second, minlength=count)
    raised = _small_segments(labels, count, extent) & (border > 0) & (up >= params.raised_fraction * border)
    return data & (labels > 0) & raised[np.maximum(labels - 1, 0)]


def _segments(surface: np.ndarray, step: float) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """(labels (rows, cols) 1… per segment, 0 for empty cells; the number of segments; the
    (2, k) flat indices of 4-neighbour pairs of cells; (k,) whether each pair is joined):
    cells join when they differ by less than `step` and neither is inside a jump."""
    cells = np.isfinite(surface)
    index = np.full(surface.shape, -1, dtype=np.int64)
    index[cells] = np.arange(int(cells.sum()))
    pairs, distance = _neighbour_pairs(cells)
    bridge = _bridges(surface, step).ravel()
    joined = (np.abs(surface.flat[pairs[0]] - surface.flat[pairs[1]]) < step * distance) \
        & ~bridge[pairs[0]] & ~bridge[pairs[1]]
    a, b, n = index.flat[pairs[0]][joined], index.flat[pairs[1]][joined], int(cells.sum())
    label = connected_sets(n, a, b)
    count = int(label.max()) + 1 if n else 0
    labels = np.zeros(surface.shape, dtype=np.int64)
    labels[cells] = label + 1
    return labels, count, pairs, joined


#: The neighbours a segment joins: right and down (each pair once).
_NEIGHBOURS = ((0, 1), (1, 0))
#: Empty cells filled (by the lowest data cell around) before segmenting: passes of 3 × 3.
_GAP_PASSES = 2


def _bridges(surface: np.ndarray, step: float) -> np.ndarray:
    """(rows, cols) bool: cells within a jump, with a 4-neighbour more than step / 2 above
    and one more than step / 2 below (a wall's returns between ground and roof). They
    join no segment: one such cell would otherwise join a roof to the ground beside it.
    Ground up to 63° steep (rise of step / 2 per cell) has none."""
    cross = ndimage.generate_binary_structure(2, 1)
    finite = np.where(np.isfinite(surface), surface, np.nan)
    above = ndimage.maximum_filter(np.where(np.isfinite(surface), surface, -np.inf), footprint=cross,
                                   mode="constant", cval=-np.inf)
    below = ndimage.minimum_filter(surface, footprint=cross, mode="constant", cval=np.inf)
    with np.errstate(invalid="ignore"):
        return (above - finite > step / 2) & (finite - below > step / 2)


def _close_gaps(zmin: np.ndarray) -> np.ndarray:
    """The minimum surface with each empty cell within _GAP_PASSES cells of data given the
    lowest height of the data cells around it (3 × 3, pass by pass): a sparse scan's
    holes then do not cut a roof into single cells with no border."""
    surface = zmin.copy()
    for _ in range(_GAP_PASSES):
        lowest = ndimage.minimum_filter(surface, size=3, mode="constant", cval=np.inf)
        empty = ~np.isfinite(surface)
        surface[empty] = lowest[empty]
    return surface


def _neighbour_pairs(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((2, k) flat indices, (k,) distances in cells) of the pairs of data cells at the
    offsets _NEIGHBOURS."""
    flat = np.arange(data.size).reshape(data.shape)
    rows, cols = data.shape
    firsts, seconds, distances = [], [], []
    for dr, dc in _NEIGHBOURS:
        a = (slice(0, rows - dr), slice(max(0, -dc), cols - max(0, dc)))
        b = (slice(dr, rows), slice(max(0, dc), cols - max(0, -dc)))
        both = data[a] & data[b]
        firsts.append(flat[a][both])
        seconds.append(flat[b][both])
        distances.append(np.full(int(both.sum()), math.hypot(dr, dc)))
    return np.stack([np.concatenate(firsts), np.concatenate(seconds)]), np.concatenate(distances)


def _small_segments(labels: np.ndarray, count: int, extent: int) -> np.ndarray:
    """(count,) bool: segments whose bounding box is fewer than `extent` cells on each side."""
    small = np.zeros(count, dtype=bool)
    for number, box in enumerate(ndimage.find_objects(labels, max_label=count)):
        if box is not None:
            small[number] = box[0].stop - box[0].start < extent and box[1].stop - box[1].start < extent
    return small


def _provisional_dem(zmin: np.ndarray, ground: np.ndarray, grid: _Grid,
                     scales: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(dem, slope), each (rows, cols): the minimum surface at ground cells and a local
    weighted plane fit to the ground cells elsewhere (NaN where no ground is within reach);
    slope is the DEM's gradient magnitude (rise over run, central differences)."""
    dem = np.where(ground, zmin, np.nan)
    todo = ~ground
    weight = ground.astype(np.float64)
    heights = np.where(ground, zmin, 0.0)
    for scale in scales:
        if not todo.any():
            break
        value, take = _plane_fit(weight, heights, scale, todo, last=scale == scales[-1])
        dem[take] = value[take]
        todo &= ~take
    rows, cols = np.gradient(np.where(np.isfinite(dem), dem, np.nan), grid.cell)
    slope = np.hypot(rows, cols)
    return dem, np.where(np.isfinite(slope), slope, 0.0)


def _moments(values: np.ndarray, scale: int, order_x: int, order_y: int) -> np.ndarray:
    """Σ values(q) · dx^order_x · dy^order_y · exp(−|d|²/2σ²) over q within 4σ of each cell,
    d = q − cell in cells (separable correlations; outside the window counts as zero)."""
    radius = _FILL_TRUNCATE * scale
    offsets = np.arange(-radius, radius + 1, dtype=np.float64)
    bell = np.exp(-0.5 * (offsets / scale) ** 2)
    along_x = ndimage.correlate1d(values, bell * offsets ** order_x, axis=1, mode="constant", cval=0.0)
    return ndimage.correlate1d(along_x, bell * offsets ** order_y, axis=0, mode="constant", cval=0.0)


def _plane_fit(weight: np.ndarray, heights: np.ndarray, scale: int, todo: np.ndarray,
               last: bool) -> tuple[np.ndarray, np.ndarray]:
    """(value, done): at the `todo` cells with enough ground weight around them
    (_FILL_ENOUGH of a full neighbourhood; any, for the last scale), the height of the
    plane fitted by weighted least squares to the ground cells at Gaussian scale `scale`."""
    m = {(i, j): _moments(weight, scale, i, j) for i, j in ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))}
    zw = heights * weight
    z = [_moments(zw, scale, *order) for order in ((0, 0), (1, 0), (0, 1))]
    full = 2 * math.pi * scale ** 2
    enough = todo & (m[0, 0] > (1e-9 if last else _FILL_ENOUGH) * full)
    ridge = _RIDGE * m[0, 0] * scale ** 2 + 1e-12
    matrix = np.stack([np.stack([m[0, 0], m[1, 0], m[0, 1]], -1),
                       np.stack([m[1, 0], m[2, 0] + ridge, m[1, 1]], -1),
                       np.stack([m[0, 1], m[1, 1], m[0, 2] + ridge], -1)], -2)
    value = np.full(weight.shape, np.nan)
    if enough.any():
        solved = np.linalg.solve(matrix[enough], np.stack(z, -1)[enough][..., None])
        value[enough] = solved[:, 0, 0]
    return value, enough


def _near_dem(points: np.ndarray, dem: np.ndarray, slope: np.ndarray, grid: _Grid,
              params: GroundParameters) -> np.ndarray:
    """(n,) bool: points within threshold + scalar · slope of the bilinear DEM (cell centres
    as nodes; a point whose DEM is unknown is not ground)."""
    fy = points[:, 1] / grid.cell - 0.5 - grid.row0
    fx = points[:, 0] / grid.cell - 0.5 - grid.col0
    r0 = np.clip(np.floor(fy).astype(np.int64), 0, max(grid.shape[0] - 2, 0))
    c0 = np.clip(np.floor(fx).astype(np.int64), 0, max(grid.shape[1] - 2, 0))
    r1 = np.minimum(r0 + 1, grid.shape[0] - 1)
    c1 = np.minimum(c0 + 1, grid.shape[1] - 1)
    ty, tx = np.clip(fy - r0, 0.0, 1.0), np.clip(fx - c0, 0.0, 1.0)
    corners = np.stack([dem[r0, c0], dem[r0, c1], dem[r1, c0], dem[r1, c1]])
    weights = np.stack([(1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx])
    known = np.isfinite(corners)
    total = (weights * known).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = (np.where(known, corners, 0.0) * weights).sum(axis=0) / total
    own_row = np.clip(np.floor(fy + 0.5).astype(np.int64), 0, grid.shape[0] - 1)
    own_col = np.clip(np.floor(fx + 0.5).astype(np.int64), 0, grid.shape[1] - 1)
    allowed = params.threshold + params.scalar * slope[own_row, own_col]
    with np.errstate(invalid="ignore"):
        return (total > 0) & (np.abs(points[:, 2] - height) <= allowed)


FILTER_NAME = "SMRF, slope-adaptive, with raised segments (c1mesh.stages.ground)"
"""The filter's name in reports."""
CLASS_CHOICES = ("auto", "all", "filter")
"""The word values of the fit's class choice (else a tuple of LAS codes): auto, the file's
ground class 2 when it has any, else the ground filter's ground; all, every point; filter,
the filter's ground even when the file has class 2."""


def filter_file_points(points: np.ndarray, crs: str | None,
                       params: GroundParameters = GroundParameters()) -> tuple[np.ndarray, dict]:
    """((n,) bool ground, the report's facts about the filter) of points in their file's
    units: converted to metres by the CRS's linear units first (c1mesh.core.crs;
    metres when there is no CRS), so the filter's metre parameters mean metres."""
    xy_unit, z_unit, unit = metres_per_unit(crs)
    metres = np.asarray(points, dtype=np.float64) * np.array([xy_unit, xy_unit, z_unit])
    ground = classify_ground(metres, None, params)
    facts = {"name": FILTER_NAME, "parameters": params.as_dict(), "units": unit if crs else "metre (no CRS)",
             "metres_per_unit": [xy_unit, z_unit], "halo_m": halo_width(params),
             "points": int(len(ground)), "ground": int(ground.sum())}
    return ground, facts


def choose_points(classification: np.ndarray | None, points: np.ndarray, crs: str | None,
                  choice) -> tuple[np.ndarray | None, dict | None]:
    """(which points a fit keeps, (n,) bool or None for all; the report's "classes"
    facts, None for a file without classes) by the class choice (CLASS_CHOICES, or a
    tuple of codes, which the reader has applied already: every point is kept).

    facts: selected (the codes kept, [2] for the filter's ground, or "all"), points_read
    and points_kept (for given codes the reader kept them: both count the kept), source
    ("option": --classes, "file": the file's class 2, "filter": the ground filter, run
    because the file has no class 2 or because --classes filter asked), filter (its
    name, parameters and counts, when it ran)."""
    if classification is None:
        return None, None
    counts = lambda keep: {"points_read": int(len(classification)),  # noqa: E731
                           "points_kept": int(len(classification) if keep is None else keep.sum())}
    if isinstance(choice, tuple):
        return None, {"selected": [int(c) for c in choice], "source": "option", **counts(None)}
    if choice == "all" or choice is None:
        return None, {"selected": "all", "source": "option", **counts(None)}
    if choice == "auto" and np.any(classification == 2):
        keep = classification == 2
        return keep, {"selected": [2], "source": "file", **counts(keep)}
    ground, facts = filter_file_points(points, crs)
    why = "asked (--classes filter)" if choice == "filter" else "the file has no ground class 2"
    return ground, {"selected": [2], "source": "filter", "reason": why, **counts(ground), "filter": facts}


def resolved_classes(facts: dict | None) -> tuple[int, ...] | None:
    """The classes a fit's later stages see (tuple of codes, None: all): the filter's
    ground counts as class 2 (ground), as in the file."""
    if facts is None or facts["selected"] == "all":
        return None
    return tuple(facts["selected"])
