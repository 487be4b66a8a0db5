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

This module does not import c1mesh.stages.frame (which re-exports `height_field`,
`normal_gradients` and `gradients_to_normals` for its older importers): a frame is used
through its methods only.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from c1mesh.core.errors import InputError, NotAHeightFieldError

_AXIS_HINT = "try --axis x|y|z or X,Y,Z, or --classes 2 for LiDAR ground"
STACK_MARGIN = 3.0
"""Height jump, in point spacings, beyond what the slopes explain that counts as stacking."""


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


def height_field(points: ArrayLike, normals: ArrayLike, frame: ScanFrame,
                 max_slope_deg: float = 85.0, max_stacked: float = 0.10,
                 max_facing_away: float | None = None, merge_tol: float = 1e-6,
                 common_metric: bool = True) -> HeightField:
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
    merge_tol:       points closer in (x, y) than merge_tol × the spacing h (the median
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

    finite = np.all(np.isfinite(pts), axis=1)
    dropped["non_finite"] = int((~finite).sum())
    n_local = frame.vectors_to_local(nrm)
    length = np.linalg.norm(n_local, axis=1)
    usable = finite & np.isfinite(length) & (length > 0)
    dropped["bad_normal"] = int((finite & ~usable).sum())
    index = np.flatnonzero(usable)
    up = n_local[index, 2] / length[index]
    cos_max = np.cos(np.radians(max_slope_deg)) if common_metric else 0.0
    _check_facing_away(up, cos_max, max_facing_away if common_metric else None, max_slope_deg, frame)

    steep = np.abs(up) < cos_max
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
    local = frame.to_local(pts[index])
    check_extent(local)
    gradients, flipped = normal_gradients(n_local[index])

    keep, n_stacked, spacing = _stack_and_merge(local, gradients, index, max_stacked, merge_tol, frame,
                                                common_metric)
    dropped["duplicate"] = int(index.size - keep.size)
    xy = local[keep, :2]
    _check_spread(xy)
    return HeightField(xy=xy, z=local[keep, 2], gradients=gradients[keep],
                       source_index=index[keep].astype(np.int64), frame=frame, dropped=dropped,
                       flipped=flipped, stacked=n_stacked, spacing=spacing)


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
    span = float(np.max(np.ptp(local, axis=0))) if local.size else 0.0
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
                     merge_tol: float, frame: ScanFrame,
                     common_metric: bool = True) -> tuple[np.ndarray, int, float]:
    """Stacking test and duplicate merging on local points (n, 3) with their gradients and
    input indices (n,) ascending.

    Returns (keep, stacked, spacing): ascending indices into `local` of the points kept
    (one per duplicate group, the first), the number of stacked points, and the spacing h.
    Exact duplicates in (x, y) are grouped by sorting; distinct positions go into one KD
    tree whose pairs within h serve both the stacking test (`stacked_positions`) and the
    near-duplicate merge. Without a common metric (see `height_field`) h is the plane
    spacing and only exact duplicates with different heights count as stacked.
    """
    xy, z = local[:, :2], local[:, 2]
    order, xs, ys = _sort_xy(xy)
    new = np.ones(order.size, dtype=bool)
    new[1:] = (xs[1:] != xs[:-1]) | (ys[1:] != ys[:-1])
    del xs, ys
    group = np.empty(order.size, dtype=np.int64)
    group[order] = np.cumsum(new) - 1                    # exact-duplicate group of each point
    first = order[new]                                   # lowest index of each group (stable sort)
    n_groups = first.size
    if n_groups < 3:
        raise InputError(f"the points occupy only {n_groups} distinct positions in the plane; "
                         "a height field needs at least 3")
    z_min = np.full(n_groups, np.inf)
    z_max = np.full(n_groups, -np.inf)
    np.minimum.at(z_min, group, z)
    np.maximum.at(z_max, group, z)

    plane_tree = kd_tree(xy[first])
    sample = spacing_sample(index[first], n_groups)
    if common_metric:
        spacing = _spacing(local[first], sample, plane_tree=plane_tree)
    else:
        spacing = _plane_spacing(xy[first], sample, plane_tree)
    bad, (i, j, dist) = stacked_positions(xy[first], z[first], gradients[first], z_max - z_min, spacing,
                                          plane_tree, common_metric)
    stacked = int(bad[group].sum())
    check_stacking(stacked, z.size, max_stacked, frame.axes[2])

    near = dist <= merge_tol * spacing
    graph = coo_matrix((np.ones(int(near.sum()), dtype=np.int8), (i[near], j[near])),
                       shape=(n_groups, n_groups))
    label = connected_components(graph, directed=False)[1]
    keep = np.full(label.max() + 1, np.iinfo(np.int64).max)
    np.minimum.at(keep, label, first)
    kept = np.zeros(xy.shape[0], dtype=bool)             # ascending without a sort: 10x faster
    kept[keep] = True
    return np.flatnonzero(kept), stacked, spacing


def stacked_positions(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray, z_range: np.ndarray,
                      spacing: float, plane_tree: cKDTree,
                      common_metric: bool = True) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Which distinct plane positions are stacked, and the pairs that decided it.

    xy (m, 2), z (m,), gradients (m, 2): the distinct positions (the first point of each
    group of exact duplicates) with their height and gradient; z_range (m,) the spread of
    heights over each group; plane_tree a KD tree of xy. A position is stacked when its
    group's heights spread more than STACK_MARGIN h, or a position within h in the plane
    differs in height by more than STACK_MARGIN h + the larger slope times their
    distance (without a common metric: when its group holds two heights).

    Returns (bad (m,) bool, (i, j, dist): the pairs within h and their plane distances).
    On a tile of a survey, give the positions within h of its cell: the flags of its own
    positions are then those of the whole survey (c1mesh.survey.tiled_heights).
    """
    pairs = plane_tree.query_pairs(spacing, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    dist = np.linalg.norm(xy[i] - xy[j], axis=1)
    if not common_metric:
        return z_range > 0, (i, j, dist)
    slope = np.maximum(np.linalg.norm(gradients[i], axis=1), np.linalg.norm(gradients[j], axis=1))
    jump = np.abs(z[i] - z[j]) > STACK_MARGIN * spacing + slope * dist
    bad = z_range > STACK_MARGIN * spacing
    bad[i[jump]] = True
    bad[j[jump]] = True
    return bad, (i, j, dist)


def check_stacking(stacked: int, points: int, max_stacked: float, axis: np.ndarray) -> None:
    """NotAHeightFieldError when more than max_stacked of the points (usable, not too steep,
    duplicates included) are stacked over the plane with normal axis (3,)."""
    if stacked > max_stacked * points:
        raise NotAHeightFieldError(
            f"{stacked / points:.0%} of the points lie above or below other points over the plane "
            f"with normal {_fmt(axis)} (at most {max_stacked:.0%} allowed), as walls, "
            f"overhangs or several layers do, so this is not a height field; " + _AXIS_HINT)


SPACING_SAMPLES = 20000
"""About how many distinct positions measure the spacing h (`spacing_sample`)."""


def spacing_sample(index: np.ndarray, positions: int, samples: int = SPACING_SAMPLES) -> np.ndarray:
    """(m,) bool: which distinct positions, by the input index (m,) of their first point,
    measure the spacing h: those whose index is a multiple of positions // samples (every
    one when that is 0 or 1; every one too when no index is a multiple). The rule depends
    on the input numbering alone, not on the order of a sort, so that a tile of a survey
    (whose survey numbers are the input's indices) picks the same positions as the
    whole: c1mesh.survey.tiled_heights measures the same h."""
    step = max(1, positions // samples)
    sample = index % step == 0
    return sample if sample.any() else np.ones(len(index), dtype=bool)


def kd_tree(points: np.ndarray) -> cKDTree:
    """KD tree built the fast way (sliding midpoint, no node compaction): half the build time."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def _sort_xy(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """np.lexsort((y, x)) of points xy (n, 2) (by x, then y, then index), and the sorted x, y.

    An unstable SIMD argsort on x, with only the points whose x ties re-sorted by (x, y,
    index): the same permutation as lexsort, ~8x faster when x rarely ties (scans). The
    tied points are put in index order and then sorted stably by y and by x, two one-key
    sorts that compose to lexsort's order and beat its three-key sort where LiDAR's
    quantised coordinates make x tie for most points.
    """
    x, y = xy[:, 0], xy[:, 1]
    order = np.argsort(x)
    xs = x[order]
    tie = xs[1:] == xs[:-1]
    if tie.any():
        run = np.zeros(order.size, dtype=bool)
        run[1:] |= tie
        run[:-1] |= tie
        sub = np.sort(order[run])
        sub = sub[np.argsort(y[sub], kind="stable")]
        order[run] = sub[np.argsort(x[sub], kind="stable")]
    return order, xs, y[order]


def _spacing(points: np.ndarray, sample: np.ndarray, plane_tree: cKDTree | None = None) -> float:
    """Median 3D nearest-neighbour distance of distinct points (n, 3), over the points of
    `sample` (n,) bool (`spacing_sample`).

    3D, not in the plane: where layers overlap, (x, y) neighbours come from the other
    layer and the plane spacing shrinks, which would blunt the stacking test.
    ``plane_tree``, a KD tree of points[:, :2] in the same order, saves building a 3D tree
    where the plane neighbours decide (see `_nearest_via_plane`); the result is the same.
    """
    query = points[sample]
    if plane_tree is not None and points.shape[0] > 64:
        nearest = _nearest_via_plane(points, query, plane_tree)
    else:
        nearest = kd_tree(points).query(query, k=2)[0][:, 1]
    return float(np.median(nearest))


def _plane_spacing(xy: np.ndarray, sample: np.ndarray, plane_tree: cKDTree) -> float:
    """Median plane distance from distinct points xy (n >= 2, 2) to their nearest other
    point, over the points of `sample` (n,) bool, queried in their KD tree `plane_tree`."""
    query = xy[sample]
    return float(np.median(plane_tree.query(query, k=2)[0][:, 1]))


def _nearest_via_plane(points: np.ndarray, query: np.ndarray, plane_tree: cKDTree) -> np.ndarray:
    """3D distance from each query point (a row of points) to its nearest other point.

    Candidates are the k nearest in the plane; the 3D minimum over them is exact when it
    does not exceed the k-th plane distance (every other point is farther in the plane,
    hence in 3D). Rows that fail get a larger k, then a 3D tree (layered clouds). Distances
    are computed as cKDTree does (sqrt of dx² + dy² + dz², in that order), so the values
    are bit-identical to a 3D tree query.
    """
    nearest = np.empty(query.shape[0])
    todo = np.arange(query.shape[0])
    n = points.shape[0]
    for k in (6, 64):
        plane, idx = plane_tree.query(query[todo, :2], k=min(k, n))
        missing = idx >= n                                # cKDTree's "no neighbour" (inf distances)
        diff = points[np.minimum(idx, n - 1)] - query[todo, None, :]
        d3 = np.sqrt(diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]
                     + diff[..., 2] * diff[..., 2])
        d3[missing] = np.inf
        best = np.partition(d3, 1, axis=1)[:, 1]          # [:, 0] is the point itself
        done = (best <= plane[:, -1]) & ~missing.any(axis=1)
        nearest[todo[done]] = best[done]
        todo = todo[~done]
        if todo.size == 0:
            return nearest
    nearest[todo] = kd_tree(points).query(query[todo], k=2)[0][:, 1]
    return nearest


def _check_spread(xy: np.ndarray) -> None:
    """InputError unless xy (n, 2) has at least 3 points that are not all on one line."""
    if xy.shape[0] < 3:
        raise InputError(f"only {xy.shape[0]} distinct points remain; a height field needs at least 3")
    sv = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    if sv[1] <= 1e-10 * sv[0]:
        raise InputError("all points lie on one line in the plane of the height axis, so they span "
                         "no surface; check the input or choose another --axis")
