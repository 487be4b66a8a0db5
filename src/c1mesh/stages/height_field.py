"""A scan seen as a height field z = f(x, y) over the plane of a ScanFrame
(c1mesh.stages.frame): heights and gradients of the points that are kept, and the test
that decides a cloud is not a height field.

In the frame, a surface normal n with n·e3 > 0 gives the gradient of the height field
    ∇f = (-n·e1 / n·e3, -n·e2 / n·e3)
(see "From a scan to a height field" in docs/rsd-math.md; `normal_gradients`, and back
`gradients_to_normals`).

Normal signs. A normal and its negative give the same gradient, so the sign never
changes the surface. The signs stored in files are unreliable: PCL's pcl_bun0.pcd is
oriented towards its VIEWPOINT 0 0 0, which lies inside the bunny, so 7% of its normals
point away from the scanner although the scan is a height field. `height_field`
therefore ignores normal signs by default (normals on the -e3 side are flipped and
counted in `HeightField.flipped`) and decides "not a height field" from geometry: points
whose normal is within `90° - max_slope_deg` of the plane are dropped as too steep, and
if more than `max_stacked` of the rest lie above or below other points (walls,
overhangs, tree canopy over ground, several layers), the cloud is rejected. Callers who
know their signs are right may pass `max_facing_away` to also reject clouds where that
fraction of normals clearly faces away from e3.

In tiles. The stage is written once for a tile; the in-memory fit is one tile that owns
every point. A tile's vertices come from its own points (`tile_heights`: `slope_test`,
`normal_gradients`, `position_groups`). The stacking test has two summaries per tile,
on a PositionTile (its own positions and those around them): `sample_spacings`, whose
median over the tiles is the spacing h (`spacing_steps` says which positions measure
it), then `stacked_points` with that h, whose sum `check_stacking` tests against the
usable points. `height_field` runs these on its one tile and does besides what a tiled
fit (c1mesh.survey.height_runs, which schedules the tiles) does not: it drops points with
non-finite coordinates, counts every drop, may trust file normals' signs, merges
near-duplicate positions and takes heights without a common metric.

This module does not import c1mesh.stages.frame (which re-exports `height_field`,
`normal_gradients` and `gradients_to_normals` for its older importers): a frame is used
through its methods only.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from c1mesh.core.errors import InputError, NotAHeightFieldError
from c1mesh.core.lazy import LazyModule
from c1mesh.core.tile import VERTEX
from c1mesh.stages import _height_field as kernel

spatial = LazyModule("scipy.spatial")

_AXIS_HINT = "try --axis x|y|z or X,Y,Z, or --classes 2 for LiDAR ground"
STACK_MARGIN = 3.0
"""Height jump, in point spacings, beyond what the slopes explain that counts as stacking."""
MERGE_TOL = 1e-6
"""Points closer in (x, y) than MERGE_TOL × the spacing h are duplicates (`height_field`)."""


@dataclass
class HeightField:
    """A scan as heights over the frame's (e1, e2) plane, one entry per kept point.

    xy:           (n, 2) float64 local plane coordinates (frame units = world units).
    z:            (n,) float64 local heights.
    gradients:    (n, 2) float64 ∇f = (df/dx, df/dy) in the local frame.
    source_index: (n,) int64 index of each kept point in the input arrays, ascending; for
                  merged duplicates, the first (lowest-index) point of the group.
    frame:        the ScanFrame used (c1mesh.stages.frame).
    dropped:      input points not kept, by reason: "non_finite" (coordinates),
                  "bad_normal" (zero/NaN/Inf normal), "too_steep" (normal within
                  90° - max_slope_deg of the plane), "duplicate" (merged into another point).
    flipped:      normals that pointed to the -e3 side and were flipped (signs are ignored).
    stacked:      kept points that lie above or below another point (see `height_field`).
    spacing:      median 3D distance (local units) from a point to its nearest neighbour
                  (one point per distinct (x, y)): the typical point spacing h on the surface;
                  the plane distance, in the units of x and y, for a height field built
                  with common_metric=False.
    sort:         the PlaneSort its positions gave (`height_field` takes it back for the
                  same positions); a caller that does not pass it on drops it (24 bytes a
                  point).
    """

    xy: np.ndarray
    z: np.ndarray
    gradients: np.ndarray
    source_index: np.ndarray
    frame: ScanFrame
    dropped: dict[str, int] = field(default_factory=dict)
    flipped: int = 0
    stacked: int = 0
    spacing: float = float("nan")
    sort: PlaneSort | None = None


@dataclass(frozen=True)
class PlaneSort:
    """What a height field learns from its kept points' plane positions alone, not from
    their normals: index (n,) the input rows it was made for (finite, usable normal, not
    too steep), order (n,) their sort_xy, the spacing h, and strips (Strips of the
    distinct positions, width h(1 + STRIP_MARGIN): the stacking pass's index).

    Why: the fit's guessed triangulation (c1mesh.pipeline.driver) builds the height field
    of the same points with stand-in normals on a second core while the normals are
    estimated; the true height field takes its sort back when it keeps the same rows,
    and skips three sorts and the spacing's nearest-neighbour pass (0.2-0.4 s at 1M
    points), with the same bits."""

    index: np.ndarray
    order: np.ndarray
    spacing: float
    strips: Strips


def height_field(points: ArrayLike, normals: ArrayLike, frame: ScanFrame,
                 max_slope_deg: float = 85.0, max_stacked: float = 0.10,
                 max_facing_away: float | None = None, common_metric: bool = True,
                 sort: PlaneSort | None = None) -> HeightField:
    """Project a scan with normals to heights and gradients over the frame's plane.

    points, normals: (N, 3) world coordinates and normals (any length, any sign).
    max_slope_deg:   points whose normal makes more than this angle with e3 (the surface
                     is steeper than this there) are dropped as "too_steep": their
                     gradient (> tan 85° ≈ 11 by default) is not trustworthy.
    max_stacked:     largest fraction of the kept points allowed to be "stacked": within
                     one point spacing h of another point in (x, y) but more than
                     3 h + |∇f|·distance apart in z, i.e. more than their slopes explain.
                     More means walls, overhangs or several layers -> NotAHeightFieldError.
                     Stacked points below the limit are kept (and counted).
                     Measured: pcl_bun0 5.5%, the Open3D room fragment 24%, LiDAR with
                     all returns (trees over ground) 20% (autzen) and 61% (4_6_crop),
                     LiDAR ground (class 2) 0%.
    max_facing_away: None (default) ignores normal signs. A fraction f trusts them: more
                     than f of the normals more than 180° - max_slope_deg from e3 (clearly
                     on the far side of the plane) -> NotAHeightFieldError.
    Duplicates:      points closer in (x, y) than MERGE_TOL × the spacing h (the median
                     nearest-neighbour distance) are duplicates; the
                     first (lowest input index) of each group is kept with its own z and
                     normal (not an average: duplicates with different z are stacking, which
                     averaging would hide), the others are counted as "duplicate".
    common_metric:   True when x, y and the heights share one unit, so that slopes are
                     angles and 3-D distances mean something. False for heights in a unit
                     of their own (a text table's height column: R's `topo` has x, y in
                     50 ft and z in ft), whose normals only carry gradients fitted to the
                     heights in plane units (c1mesh.stages.height_gradients): then no point is
                     "too_steep" and max_facing_away is not applied (angles depend on the
                     units), the spacing h is measured in the plane, and only points that
                     share their exact (x, y) with a different height count as stacked
                     (a jump "larger than the slopes explain" needs a margin in height
                     units; a second height at one plane position is stacking in any unit).
    sort:            the PlaneSort of an earlier height field of the same points in the
                     same frame with the same common_metric (its `sort`): used when it
                     was made for the rows kept here, else ignored. The result is the
                     same, bit for bit.
    Raises InputError for bad shapes or when fewer than 3 non-collinear points remain,
    NotAHeightFieldError when the cloud is not a graph over the plane.
    """
    pts = as_n3(points, "points")
    if normals is None:
        raise InputError("a height field needs normals; estimate them with c1mesh.stages.normals.estimate_normals")
    nrm = as_n3(normals, "normals", len(pts))
    if not 0.0 < max_slope_deg < 90.0:
        raise InputError(f"max_slope_deg must be between 0 and 90 degrees, got {max_slope_deg}")
    dropped = dict.fromkeys(("non_finite", "bad_normal", "too_steep", "duplicate"), 0)

    finite = np.isfinite(pts[:, 0]) & np.isfinite(pts[:, 1]) & np.isfinite(pts[:, 2])
    dropped["non_finite"] = int((~finite).sum())
    n_local = frame.vectors_to_local(nrm)
    cos_max = np.cos(np.radians(max_slope_deg)) if common_metric else 0.0
    usable, up, steep = slope_test(n_local, cos_max)
    usable &= finite
    dropped["bad_normal"] = int((finite & ~usable).sum())
    index = np.flatnonzero(usable)
    _check_facing_away(up[index], cos_max, max_facing_away if common_metric else None, max_slope_deg, frame)

    steep = steep[index]
    dropped["too_steep"] = int(steep.sum())
    index = index[~steep]
    if index.size < 3 and dropped["too_steep"]:
        raise NotAHeightFieldError(
            f"only {index.size} of {len(pts)} points have a normal less than {max_slope_deg:g}° from "
            f"the height axis {_fmt(frame.axes[2])}, so the surface is too steep to be a height "
            f"field over that plane; " + _AXIS_HINT)
    if index.size < 3:
        raise InputError(f"only {index.size} of {len(pts)} points have finite coordinates and a "
                         "usable (nonzero, finite) normal; a height field needs at least 3")
    local = frame.to_local(_gather_rows(pts, index, ascending=True))
    check_extent(local)
    gradients, flipped = normal_gradients(_gather_rows(n_local, index, ascending=True))

    if sort is not None and not np.array_equal(sort.index, index):
        sort = None                       # other rows kept (a normal dropped one): sorted anew
    keep, n_stacked, sort = _stack_and_merge(local, gradients, index, max_stacked, frame, common_metric, sort)
    dropped["duplicate"] = int(index.size - keep.size)
    xy = _gather_rows(local, keep, 2, ascending=True)
    _check_spread(xy)
    return HeightField(xy=xy, z=local[:, 2][keep], gradients=_gather_rows(gradients, keep, ascending=True),
                       source_index=index[keep].astype(np.int64), frame=frame, dropped=dropped,
                       flipped=flipped, stacked=n_stacked, spacing=sort.spacing, sort=sort)


def slope_test(normals: np.ndarray, cos_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The height field's test of normals (n, 3) in the frame: (usable (n,) bool, finite
    and nonzero; up (n,) n·e3 / |n|, the cosine of each usable one's angle with the height
    axis, NaN elsewhere; steep (n,) bool, usable with |up| < cos_max: the surface there
    is steeper than the height field keeps). The in-memory fit (`height_field`, which also
    counts the drops and may test the signs) and each tile (`tile_heights`) test so."""
    length = _row_norms(normals)
    usable = np.isfinite(length) & (length > 0)
    up = np.full(len(normals), np.nan)
    np.divide(normals[:, 2], length, out=up, where=usable)
    return usable, up, usable & (np.abs(up) < cos_max)


@dataclass(frozen=True)
class TileHeights:
    """A tile's height-field vertices (`tile_heights`): records (g,) core.tile VERTEX
    records, one per distinct plane position of its usable points (the first point there),
    ascending survey numbers; size (g,) int64 how many usable points share each position,
    z_range (g,) the spread of their heights; usable, how many usable points the tile
    has, duplicates included (its part of the stacking test's denominator)."""

    records: np.ndarray
    size: np.ndarray
    z_range: np.ndarray
    usable: int


def tile_heights(points: np.ndarray, normals: np.ndarray, cos_max: float) -> TileHeights:
    """The height-field vertices of a tile's own points: points (n,) records with index, x,
    y, z in the frame (ascending survey numbers), normals (n, 3) theirs in the frame. The
    points whose normal is usable and not too steep (`slope_test`) are grouped by exact
    plane position (`position_groups`); each position keeps its first point, with the
    gradient of that point's normal (`normal_gradients`). `height_field` does more on its
    one tile (module docstring)."""
    usable, _, steep = slope_test(normals, cos_max)
    keep = np.flatnonzero(usable & ~steep)
    local = np.column_stack([points["x"][keep], points["y"][keep], points["z"][keep]])
    gradients, _ = normal_gradients(_gather_rows(normals, keep))
    groups = position_groups(local, gradients)
    slot = np.full(len(keep), -1, dtype=np.int64)         # the groups by first point, without a sort
    slot[groups.first] = np.arange(len(groups.first))
    order = slot[slot >= 0]
    first = groups.first[order]
    records = np.empty(len(first), VERTEX)
    records["index"] = points["index"][keep[first]]
    for k, name in enumerate(("x", "y", "z", "gx", "gy")):
        records[name] = groups.columns[k][order]
    size = np.bincount(groups.group, minlength=len(first))[order]
    return TileHeights(records, size, groups.z_range[order], len(keep))


def normal_gradients(n: np.ndarray) -> tuple[np.ndarray, int]:
    """∇f = (-n_x / n_z, -n_y / n_z) (n, 2) of local normals n (n, 3) with n_z != 0, and how
    many had n_z < 0. Flipping a normal first changes no bit of its gradient (signs of
    numerator and denominator flip together), so no flipped copy is made."""
    nz = n[:, 2]
    gradients = np.empty((n.shape[0], 2))
    np.divide(-n[:, 0], nz, out=gradients[:, 0])
    np.divide(-n[:, 1], nz, out=gradients[:, 1])
    return gradients, int(np.count_nonzero(nz < 0))


def gradients_to_normals(gradients: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
    """Unit upward normals (n, 3) = (-fx, -fy, 1)/norm in the local frame from gradients (n, 2).

    ``out`` (n, 3) float64, if given, receives the result.
    """
    g = np.asarray(gradients, dtype=np.float64)
    out = np.empty((g.shape[0], 3)) if out is None else out
    inv = 1.0 / np.sqrt(g[:, 0] * g[:, 0] + g[:, 1] * g[:, 1] + 1.0)
    np.multiply(g[:, 0], -inv, out=out[:, 0])
    np.multiply(g[:, 1], -inv, out=out[:, 1])
    out[:, 2] = inv
    return out


def as_n3(a: ArrayLike, name: str, n: int | None = None) -> np.ndarray:
    """`a` as an (N, 3) float64 array (N == n when given), or InputError."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and arr.shape[0] != n):
        want = "(N, 3)" if n is None else f"({n}, 3)"
        raise InputError(f"{name} must be an array of shape {want}, got shape {arr.shape}")
    return arr


MAX_EXTENT = 1e150
"""Largest spread of local coordinates: squared distances of larger ones overflow float64."""


def check_extent(local: np.ndarray) -> None:
    """InputError when local coordinates (n, 3) spread so far that distances overflow.

    Coordinates near 1e155 (a little-endian body read as big-endian, a wrong scale
    factor) make every squared distance inf, and KD-tree queries then find no neighbours.
    """
    span = max(float(np.ptp(local[:, k])) for k in range(local.shape[1])) if local.size else 0.0
    if not span <= MAX_EXTENT:
        raise InputError(f"the points spread over {span:.3g} units, too far for distances to be "
                         "computed in float64; the coordinates are probably garbage (check the "
                         "file's byte order, scale and offset)")


def _fmt(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{c:.3g}" for c in v) + ")"


def _check_facing_away(up: np.ndarray, cos_max: float, max_facing_away: float | None,
                       max_slope_deg: float, frame: ScanFrame) -> None:
    """NotAHeightFieldError if signs are trusted and too many normals face away from e3."""
    if max_facing_away is None or up.size == 0:
        return
    fraction = float(np.mean(up < -cos_max))
    if fraction > max_facing_away:
        raise NotAHeightFieldError(
            f"{fraction:.0%} of the normals point more than {180 - max_slope_deg:g}° away from the "
            f"height axis {_fmt(frame.axes[2])} (at most {max_facing_away:.0%} allowed), so the "
            f"surface is seen from below there and is not a height field; " + _AXIS_HINT)


def _stack_and_merge(local: np.ndarray, gradients: np.ndarray, index: np.ndarray, max_stacked: float,
                     frame: ScanFrame, common_metric: bool = True,
                     sort: PlaneSort | None = None) -> tuple[np.ndarray, int, PlaneSort]:
    """Stacking test and duplicate merging on local points (n, 3) with their gradients and
    input indices (n,) ascending.

    Returns (keep, stacked, sort): ascending indices into `local` of the points kept
    (one per duplicate group, the first), the number of stacked points, and the
    PlaneSort (the spacing h among it). Exact duplicates in (x, y) are grouped by sorting
    (`position_groups`); the distinct positions are one PositionTile, whose summaries
    give h and the stacked count; the pass over the pairs within h that flags the
    stacked ones also merges those within MERGE_TOL × h (the in-memory fit's own step).
    Without a common metric (see `height_field`) h is the plane spacing and only exact
    duplicates with different heights count as stacked. sort: these positions' PlaneSort,
    made before (its sort, h and strips are taken, not made).
    """
    groups = position_groups(local, gradients, None if sort is None else sort.order)
    first, (x, y, z, gx, gy) = groups.first, groups.columns
    if first.size < 3:
        raise InputError(f"the points occupy only {first.size} distinct positions in the plane; "
                         "a height field needs at least 3")
    tile = PositionTile.whole(Positions(x, y, z, gx, gy, groups.z_range), index[first],
                              np.bincount(groups.group, minlength=first.size))
    if sort is None:
        sort = _plane_sort(tile, index, groups.order, common_metric)
    stacked, root = stacked_points(tile, sort.spacing, common_metric, MERGE_TOL * sort.spacing, sort.strips)
    check_stacking(stacked, local.shape[0], max_stacked, frame.axes[2])
    kept = np.zeros(local.shape[0], dtype=bool)          # ascending without a sort
    kept[first[root == np.arange(first.size)]] = True
    return np.flatnonzero(kept), stacked, sort


def _plane_sort(tile: PositionTile, index: np.ndarray, order: np.ndarray, common_metric: bool) -> PlaneSort:
    """The PlaneSort of the distinct positions of `tile` (every one owned) of the rows
    index (n,), sorted by order (n,): the spacing h from `sample_spacings` in strips of
    the mean spacing, and the stacking pass's strips of width h."""
    x, y = tile.positions.x, tile.positions.y
    strips = strip_index(x, y, _mean_spacing(x, y))
    for step in spacing_steps(x.size):
        spacings = sample_spacings(tile, step, common_metric, strips)
        if spacings.size:
            break
    spacing = float(np.median(spacings, overwrite_input=True))          # a temporary
    return PlaneSort(index, order, spacing, strip_index(x, y, spacing * (1 + STRIP_MARGIN)))


@dataclass
class PositionGroups:
    """Points grouped by exact plane position (`position_groups`), m groups of n points.

    group:   (n,) int64 each point's group.
    first:   (m,) int64 each group's first (lowest-index) point.
    columns: (5, m) float64 rows x, y, z, df/dx, df/dy of the first points (local units).
    z_range: (m,) float64 each group's largest minus smallest height.
    order:   (n,) int64 the points by (x, y, index) (`sort_xy`).
    """

    group: np.ndarray
    first: np.ndarray
    columns: np.ndarray
    z_range: np.ndarray
    order: np.ndarray


def _gather_rows(a: np.ndarray, rows: np.ndarray, columns: int | None = None,
                 ascending: bool = False) -> np.ndarray:
    """a[rows, :columns] (len(rows), columns; all columns by default), C-contiguous,
    gathered column by column: 1-D gathers are ~25x faster than numpy's 2-D fancy index at
    1M rows. ascending: rows ascend strictly, so as many rows as a has are all of them,
    copied rather than gathered."""
    columns = a.shape[1] if columns is None else columns
    if ascending and rows.size == a.shape[0]:
        return np.ascontiguousarray(a[:, :columns])
    out = np.empty((rows.size, columns), dtype=a.dtype)
    for k in range(columns):
        out[:, k] = a[:, k][rows]
    return out


def _row_norms(a: np.ndarray) -> np.ndarray:
    """np.linalg.norm(a, axis=1) of a (n, 3), bit for bit (the squares summed left to
    right), from columns: 7x faster than numpy's reduction over rows of 3."""
    x, y, z = a[:, 0], a[:, 1], a[:, 2]
    return np.sqrt(x * x + y * y + z * z)


def position_groups(local: np.ndarray, gradients: np.ndarray, order: np.ndarray | None = None) -> PositionGroups:
    """The groups of points local (n, 3) with gradients (n, 2) that share an exact plane
    position (x, y) (-0.0 equals 0.0), numbered in (x, y) order. The kernel
    (stages/_height_field.pyx) sorts by (x, y, index) (`sort_xy`; order: that sort of
    these positions, made before) and walks the runs."""
    local = np.ascontiguousarray(local, dtype=np.float64)
    gradients = np.ascontiguousarray(gradients, dtype=np.float64)
    n = local.shape[0]
    order = sort_xy(local[:, 0], local[:, 1]) if order is None else order
    group, first = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    columns, z_range = np.empty((5, n)), np.empty(n)
    m = kernel.position_groups(local, gradients, order, group, first, columns, z_range)
    return PositionGroups(group, first[:m], columns[:, :m], z_range[:m], order)


def sort_xy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """np.lexsort((y, x)) of the points (x, y) (n,) each: by x, then y, then index, with
    -0.0 equal to 0.0. A stable radix sort by x, then the runs of tied x by y
    (stages/_height_field.pyx): ~10x faster than lexsort where LiDAR's quantised
    coordinates tie."""
    x, y = (np.ascontiguousarray(c, dtype=np.float64) for c in (x, y))
    n = x.size
    order = np.empty(n, dtype=np.int64)
    kernel.sort_xy(x, y, order, np.empty(n, dtype=np.uint64), np.empty(n, dtype=np.uint64),
                   np.empty(n, dtype=np.int64))
    return order


def _stable_sort(order: np.ndarray, values: np.ndarray, sort) -> None:
    """Reorder the permutation order (n,) in place, stably, by values[order]."""
    n = order.size
    sort(values, order, np.empty(n, dtype=np.uint64), np.empty(n, dtype=np.uint64),
         np.empty(n, dtype=np.int64))


STRIP_MARGIN = 1e-6
"""Relative margin of the strips (`stacked_positions`) over the radius h, above the rounding
of their numbers, so that points two strips apart are surely more than h apart."""
STRIPS_MAX = 2.0 ** 20
"""At most this many strips across the positions' x extent: beyond it, the strip numbers'
rounding would approach the margin (a far outlier widens the strips, it does not break them)."""


@dataclass(frozen=True)
class Positions:
    """The distinct plane positions of a height field (the first point of each group of
    exact duplicates), in any order, each (m,): x, y in the plane, the height z and the
    gradient ∇f = (gx, gy) there, and z_range, the spread of heights over the group."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    gx: np.ndarray
    gy: np.ndarray
    z_range: np.ndarray


def stacked_positions(positions: Positions, spacing: float, common_metric: bool = True,
                      merge_radius: float = -1.0, rank: np.ndarray | None = None,
                      strips: Strips | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Which distinct plane positions are stacked, and which merge.

    positions: the Positions (m of them). A position is stacked when its group's heights
    spread more than STACK_MARGIN h, or a position within h in the plane (dx² + dy² <= h²,
    cKDTree.query_pairs' test) differs in height by more than STACK_MARGIN h + the larger
    slope |∇f| times their distance (without a common metric: when its group holds two
    heights). Positions within merge_radius (<= h) of each other are merged, in chains.

    Returns (bad (m,) bool, root (m,) int64: for each position, the position of least
    rank (m,) (default: index) among those it merges with; itself when it merges with
    none). The kernel (stages/_height_field.pyx) finds the pairs in strips of x at least
    h wide (`strips` when they are, and at most twice that; else made here), sorted by y.
    On a tile of a survey, give the positions within h of its cell: the flags of its own
    positions are then those of the whole survey (`stacked_points`).
    """
    x, y, z, gx, gy = (np.ascontiguousarray(c, dtype=np.float64)
                       for c in (positions.x, positions.y, positions.z, positions.gx, positions.gy))
    m = x.size
    bad = np.asarray(positions.z_range > (STACK_MARGIN * spacing if common_metric else 0.0))
    root = np.empty(m, dtype=np.int64)
    if m == 0:
        return bad, root
    window = spacing * (1 + STRIP_MARGIN)
    if strips is None or not window <= strips.width <= 2 * window:
        strips = strip_index(x, y, window)
    slope = np.sqrt(gx * gx + gy * gy)                  # np.linalg.norm of the (gx, gy) rows, bit for bit
    rank = np.arange(m, dtype=np.int64) if rank is None else np.ascontiguousarray(rank, dtype=np.int64)
    kernel.close_pairs(x, y, z, slope, strips.strip, strips.order, spacing * spacing, window,
                       STACK_MARGIN * spacing, merge_radius, common_metric, rank, bad.view(np.uint8), root)
    return bad, root


@dataclass
class Strips:
    """Points (m,) in strips of x, sorted by (strip, y): near points are in the same or
    the next strips and near in y (the kernels' index; `strip_index`).

    width:  the strips' width (x's unit).
    strip:  (m,) int64 each point's strip number (ascending with x).
    order:  (m,) int64 the points by (strip, y, index).
    starts: (R + 1,) int64 where each of the R occupied strips begins in order, and m.
    """

    width: float
    strip: np.ndarray
    order: np.ndarray
    starts: np.ndarray


def strip_index(x: np.ndarray, y: np.ndarray, width: float) -> Strips:
    """Strips of points x, y (m >= 1,) at least `width` wide (wider where STRIPS_MAX
    strips would not span x), by two stable radix sorts (y, then strip number); or, where
    the strip numbers already ascend with the index (points sorted by x, as the height
    field's positions are), by sorting each strip's run by y alone (0.15 s -> 0.05 s at
    1M positions; the same order)."""
    low = x.min()
    width = max(float(width), float(x.max() - low) / STRIPS_MAX)
    if width > 0:
        strip = np.floor((x - low) / width).astype(np.int64)
    else:                                                 # one point, or all on one x
        strip = np.zeros(x.size, dtype=np.int64)
    if x.size > 1 and not np.any(strip[1:] < strip[:-1]):
        starts = np.concatenate([[0], np.flatnonzero(strip[1:] != strip[:-1]) + 1, [x.size]]).astype(np.int64)
        order = np.empty(x.size, dtype=np.int64)
        kernel.sort_runs_by_float(np.ascontiguousarray(y, dtype=np.float64), starts, order,
                                  np.empty(x.size, dtype=np.uint64), np.empty(x.size, dtype=np.uint64),
                                  np.empty(x.size, dtype=np.int64))
        return Strips(width, strip, order, starts)
    order = np.arange(x.size, dtype=np.int64)
    _stable_sort(order, y, kernel.sort_by_float)
    _stable_sort(order, strip, kernel.sort_by_int)
    sorted_strip = strip[order]
    starts = np.concatenate([[0], np.flatnonzero(sorted_strip[1:] != sorted_strip[:-1]) + 1, [x.size]])
    return Strips(width, strip, order, starts.astype(np.int64))


def _mean_spacing(x: np.ndarray, y: np.ndarray) -> float:
    """sqrt(bounding box area / points) of x, y (m,): the spacing of points spread evenly
    over their box, the strips' width for the nearest-neighbour search (a corridor along
    y gets strips as narrow as its spacing, where one slab of x would hold most points)."""
    dx, dy = float(np.ptp(x)), float(np.ptp(y))
    if dx > 0 and dy > 0:
        return float(np.sqrt(dx * dy / x.size))
    return max(dx, dy) / x.size


def check_stacking(stacked: int, points: int, max_stacked: float, axis: np.ndarray) -> None:
    """NotAHeightFieldError when more than max_stacked of the points (usable, not too steep,
    duplicates included) are stacked over the plane with normal axis (3,)."""
    if stacked > max_stacked * points:
        raise NotAHeightFieldError(
            f"{stacked / points:.0%} of the points lie above or below other points over the plane "
            f"with normal {_fmt(axis)} (at most {max_stacked:.0%} allowed), as walls, "
            f"overhangs or several layers do, so this is not a height field; " + _AXIS_HINT)


@dataclass(frozen=True)
class PositionTile:
    """What a tile's stacking test reads: the distinct plane positions (Positions, m of
    them, any order) of its own usable points and of those around it within reach;
    index (m,) int64 the survey number of each one's first point; size (m,) int64 how many
    usable points share each; own (m,) bool those in the tile's cell. The in-memory fit
    is one PositionTile that owns every position (`whole`)."""

    positions: Positions
    index: np.ndarray
    size: np.ndarray
    own: np.ndarray

    @classmethod
    def whole(cls, positions: Positions, index: np.ndarray, size: np.ndarray) -> "PositionTile":
        """The in-memory fit's one tile: every position owned."""
        return cls(positions, index, size, np.ones(len(index), dtype=bool))


SPACING_SAMPLES = 20000
"""About how many distinct positions measure the spacing h (`spacing_steps`)."""


def spacing_steps(positions: int, samples: int = SPACING_SAMPLES) -> tuple[int, ...]:
    """The steps of `spacing_sample` for a survey of `positions` distinct positions, in the
    order to try them: positions // samples (at least 1), then 1 (every position) if no
    position's survey number anywhere is a multiple of the first. The spacing h is the
    median, over every tile, of the `sample_spacings` at the first step that picks a
    position in some tile."""
    step = max(1, positions // samples)
    return (step,) if step == 1 else (step, 1)


def spacing_sample(index: np.ndarray, step: int) -> np.ndarray:
    """(m,) bool: which positions, by the survey number index (m,) of their first point,
    measure the spacing h: the multiples of step (`spacing_steps`). The rule depends on
    the survey numbering alone, not on the order of a sort or on the tiles, so every
    tile of a survey picks the positions the whole survey picks."""
    return index % step == 0


def sample_spacings(tile: PositionTile, step: int, common_metric: bool = True,
                    strips: Strips | None = None) -> np.ndarray:
    """The spacing's summary of one tile: (s,) the 3D distance from each own position that
    spacing_sample picks to its nearest other position of the tile (own or not; inf when
    there is none), in the tile's order; without a common metric (see `height_field`)
    the plane distance. The spacing h is the median over every tile's (the reduce).
    strips: a strip_index of the positions (made here when None). Each distance is
    cKDTree's bits (stages/_height_field.pyx). A tile's distance is the survey's when
    its positions hold every one nearer than it (c1mesh.survey.height_runs reads so).

    3D, not in the plane: where layers overlap, (x, y) neighbours come from the other
    layer and the plane spacing shrinks, which would blunt the stacking test.
    """
    query = np.flatnonzero(tile.own & spacing_sample(tile.index, step))
    if not query.size:
        return np.empty(0)
    p = tile.positions
    x, y = (np.ascontiguousarray(c, dtype=np.float64) for c in (p.x, p.y))
    z = np.ascontiguousarray(p.z, dtype=np.float64) if common_metric else np.zeros(x.size)
    strips = strip_index(x, y, _mean_spacing(x, y)) if strips is None else strips
    run_x = x[strips.order]
    low = np.minimum.reduceat(run_x, strips.starts[:-1])
    high = np.maximum.reduceat(run_x, strips.starts[:-1])
    query_run = np.searchsorted(strips.strip[strips.order][strips.starts[:-1]], strips.strip[query])
    nearest = np.empty(query.size)
    kernel.nearest_distances(x, y, z, strips.order, strips.starts, low, high, query, query_run, nearest)
    return nearest


def stacked_points(tile: PositionTile, spacing: float, common_metric: bool = True,
                   merge_radius: float = -1.0, strips: Strips | None = None) -> tuple[int, np.ndarray]:
    """The stacking test's summary of one tile: (how many usable points, duplicates
    included, lie at its own positions that stacked_positions flags with the survey's
    spacing h; root (m,), stacked_positions' merge roots, the least survey number first).
    Its own positions' flags are the survey's when the tile holds every position within
    h of them. The reduce sums the counts of every tile and tests the sum against the
    usable points (`check_stacking`). merge_radius: the in-memory fit's near-duplicate
    merge (`height_field`'s MERGE_TOL × h), which the pass that flags the pairs within h
    also does; a tiled fit does not merge (-1). strips: as stacked_positions takes them."""
    bad, root = stacked_positions(tile.positions, spacing, common_metric, merge_radius, tile.index, strips)
    return int(tile.size[bad & tile.own].sum()), root


def kd_tree(points: np.ndarray) -> "scipy.spatial.cKDTree":
    """KD tree built the fast way (sliding midpoint, no node compaction): half the build time."""
    return spatial.cKDTree(points, balanced_tree=False, compact_nodes=False)


def _check_spread(xy: np.ndarray) -> None:
    """InputError unless xy (n, 2) has at least 3 points that are not all on one line."""
    if xy.shape[0] < 3:
        raise InputError(f"only {xy.shape[0]} distinct points remain; a height field needs at least 3")
    sv = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    if sv[1] <= 1e-10 * sv[0]:
        raise InputError("all points lie on one line in the plane of the height axis, so they span "
                         "no surface; check the input or choose another --axis")
