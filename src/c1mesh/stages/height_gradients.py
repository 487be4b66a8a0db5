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

import numpy as np
from scipy.spatial import cKDTree

from c1mesh.core.errors import InputError
from c1mesh.core.threads import parallel_blocks
from c1mesh.core.threads import workers as thread_count
from c1mesh.stages.height_field import gradients_to_normals
from c1mesh.stages import _height_gradients as kernel

GRADIENT_MODES = ("auto", "normals", "heights")
"""Where a fit's vertex gradients come from: "normals" (file or PCA normals), "heights"
(`height_gradients`), "auto" (heights where the normals were estimated, else normals)."""

NEIGHBOUR_FACTOR = 1.5
"""The quadratic fit uses this many times the k of the PCA normals (5 unknowns, not 3)."""
BLOCK = 1 << 15
"""Points per block: a block's neighbour indices and offsets (block, k) stay at a few MB."""
TIE_EXTRA = 8
"""Candidates queried beyond the k + 1 nearest where a distance ties at the k-th: enough
to see every point tied with the k-th on a 1 cm grid (the query doubles when not)."""
TIE_MARGIN = 1e-12
"""Relative margin between our squared distances and the KD tree's (which sums the same
squares, possibly rounded differently): a k-th distance closer than this to the first
unqueried one counts as a tie."""
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


def height_normals(points: np.ndarray, frame, k: int) -> np.ndarray:
    """World unit normals (N, 3) of the height field fitted to world points (N, 3) in a
    given frame (c1mesh.stages.frame.ScanFrame): `height_gradients` of the local heights turned
    into upward normals. NaN rows for points with a non-finite coordinate.

    What the pipeline uses instead of PCA normals when the height axis is given (LAS/LAZ:
    z): the frame needs no normals then, and the height field's gradients are the fit's.
    """
    pts = np.asarray(points, dtype=np.float64)
    finite = np.isfinite(pts).all(axis=1)
    local = frame.to_local(pts if finite.all() else pts[finite])
    normals = np.full(pts.shape, np.nan)
    normals[finite] = frame.vectors_to_world(gradients_to_normals(height_gradients(local[:, :2], local[:, 2], k=k)))
    return normals


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
    # Points in a KD tree's leaf order: neighbours then sit close in memory, and the
    # queries and gathers below run about twice as fast as in the input's order.
    order = cKDTree(xy, balanced_tree=False, compact_nodes=False).indices
    xy, z = xy[order], z[order]
    tree = cKDTree(xy, balanced_tree=False, compact_nodes=False)
    if at is None:
        centres, slot = np.arange(n), order
    else:
        rank = np.empty(n, dtype=np.int64)
        rank[order] = np.arange(n)
        wanted = rank[np.asarray(at, dtype=np.int64)]
        slot = np.argsort(wanted, kind="stable")             # centres in leaf order too
        centres = wanted[slot]
    m = centres.size
    out = np.empty((m, 2))
    reach2 = np.empty(m)
    query_threads = workers if m <= BLOCK else 1    # one block: its query has the threads

    def fit(block: slice) -> None:
        centre = centres[block]
        neighbours, offsets = nearest_neighbours(tree, xy, z, centre, k, query_threads)
        reach2[slot[block]] = offsets[2].max(axis=1)
        out[slot[block]] = _fit_block(z, centre, neighbours, offsets, degree)
    # Each block is a query and a fit of its own (both release the GIL), so blocks run in
    # the knob's threads: every block gets the same neighbours and sums at any count.
    parallel_blocks(fit, m, BLOCK, threads=workers)
    return out, np.sqrt(reach2)


def check_positions(points: int, positions: int) -> None:
    """InputError when `points` lie at fewer than 3 distinct (x, y) `positions`: no slope
    can be fitted. The tiled fit counts the positions of the whole survey while it streams
    it (c1mesh.survey.tiled_fit) and says the same."""
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
    last one returned."""
    seen = list(seen or [])
    new = np.ones(xy.shape[0], dtype=bool)
    for row in seen:
        new &= (xy != row).any(axis=1)
    while len(seen) < enough and new.any():
        seen.append(xy[int(np.argmax(new))])
        new &= (xy != seen[-1]).any(axis=1)
    return seen


def nearest_neighbours(tree, xy: np.ndarray, z: np.ndarray, centre: np.ndarray, k: int,
                       workers: int = -1) -> tuple[np.ndarray, tuple]:
    """(indices (b, k), their offsets (dx, dy, dx² + dy²) each (b, k)) of the k nearest
    other points of the points `centre` (b,), by a rule that depends only on the
    coordinates: nearest by squared plane distance, ties broken by the offset (dx, then
    dy, then the height), each row in that order.

    Why: a KD tree breaks distance ties by its own point numbering, so on a grid (LiDAR's
    1 cm) a point whose k-th and (k+1)-th neighbours are equally far got a different
    neighbour set in a tile than in the whole survey; and the least-squares sums, added
    in row order, must be added in the same order to agree to the bit.
    tree: cKDTree of xy (n, 2); z (n,) the heights; k < n.
    """
    n = len(xy)
    if n < k + 2:
        neighbours = _sorted_neighbours(tree, xy, z, centre, k, workers)
        return neighbours, _offsets(xy, centre, neighbours)
    _, index = tree.query(xy[centre], k=k + 2, workers=workers)
    ux, uy, dist2 = _offsets(xy, centre, index)
    # The tree's order is the canonical one when the point itself comes first, the
    # distances then strictly increase, and the (k+1)-th is clearly farther than the k-th.
    plain = ((index[:, 0] == centre) & (dist2[:, 1] > 0)
             & (dist2[:, 2:k + 1] > dist2[:, 1:k]).all(axis=1)
             & (dist2[:, k] < dist2[:, k + 1] * (1 - TIE_MARGIN)))
    neighbours = index[:, 1:k + 1]
    offsets = ux[:, 1:k + 1], uy[:, 1:k + 1], dist2[:, 1:k + 1]
    tied = np.flatnonzero(~plain)
    if tied.size:
        neighbours[tied] = _sorted_neighbours(tree, xy, z, centre[tied], k, workers)
        for array, fixed in zip(offsets, _offsets(xy, centre[tied], neighbours[tied])):
            array[tied] = fixed
    return neighbours, offsets


def _sorted_neighbours(tree, xy, z, centre, k, workers):
    """`nearest_neighbours` the slow way: query k + 1 + TIE_EXTRA candidates, sort them by
    (distance², dx, dy, z), and keep the first k when the k-th is clearly closer than the
    last candidate (so no unqueried point ties with it); double the query where not."""
    n = len(xy)
    out = np.empty((centre.size, k), np.int64)
    todo = _clump_neighbours(tree, xy, z, centre, k, out, workers)
    count = k + 1 + TIE_EXTRA
    while todo.size:
        count = min(count, n)
        _, index = tree.query(xy[centre[todo]], k=count, workers=workers)
        ux, uy, dist2 = _offsets(xy, centre[todo], index)
        dist2[index == centre[todo, None]] = -1.0                 # the point itself sorts first
        rank = np.lexsort((z[index], uy, ux, dist2), axis=-1)
        index, dist2 = np.take_along_axis(index, rank, 1), np.take_along_axis(dist2, rank, 1)
        done = (count == n) | (dist2[:, k] < dist2[:, -1] * (1 - TIE_MARGIN))
        out[todo[done]] = index[done, 1:k + 1]
        todo = todo[~done]
        count *= 2
    return out


def _clump_neighbours(tree, xy, z, centre, k, out, workers) -> np.ndarray:
    """Fill out's rows of the centres that share their exact position with at least k other
    points (a clump of duplicates): their k neighbours are then k of those others, the
    lowest heights first, as `_sorted_neighbours`' order puts them (distance 0, offset 0,
    then height); points with the same height there are the same datum, interchangeable
    in every sum, and are taken in index order. Returns the rows (into centre) still to do.

    Why: the doubling query cannot see past a clump's ties, and a clump of m points made
    m queries of m neighbours each (15,000 duplicates asked for 1 GB per array)."""
    at = tree.query_ball_point(xy[centre], r=0.0, return_length=True, workers=workers)
    clumped = np.flatnonzero(at > k)
    if not clumped.size:
        return np.arange(centre.size)
    positions, which = np.unique(xy[centre[clumped]], axis=0, return_inverse=True)
    for p, position in enumerate(positions):
        members = np.sort(np.asarray(tree.query_ball_point(position, r=0.0), dtype=np.int64))
        head = members[np.argsort(z[members], kind="stable")][:k + 1]
        for row in clumped[which.ravel() == p]:
            out[row] = head[head != centre[row]][:k]          # without the centre itself
    return np.setdiff1d(np.arange(centre.size), clumped)


def _offsets(xy, centre, neighbours):
    """(dx, dy, dx² + dy²), each (b, k): plane offsets of the neighbours (b, k) from their
    centre (b,) over the points xy (n, 2): the kernel loops over both, no gathered copies."""
    neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
    ux, uy, dist2 = (np.empty(neighbours.shape) for _ in range(3))
    kernel.offsets(np.ascontiguousarray(xy, dtype=np.float64), np.ascontiguousarray(centre, dtype=np.int64),
                   neighbours, ux, uy, dist2)
    return ux, uy, dist2


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
