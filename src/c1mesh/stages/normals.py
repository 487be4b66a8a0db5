"""Normal estimation for scans that come without normals (LiDAR, bare xyz files).

Open3D fits a plane to the k nearest neighbours of every point (PCA of the
neighbourhood); the plane's normal is defined only up to sign, so the result is oriented
towards a given direction, normally the height axis e3 of the scan frame.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from c1mesh.core.errors import DependencyError, InputError
from c1mesh.core.lazy import LazyModule
from c1mesh.core.threads import workers

spatial = LazyModule("scipy.spatial")


def estimate_normals(points: ArrayLike, k: int = 16,
                     towards: ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Unit normals (N, 3) of a scan, oriented so that n·towards >= 0.

    points:  (N, 3) world coordinates; rows with a non-finite coordinate get NaN normals.
    k:       neighbours per local plane fit (Open3D KDTreeSearchParamKNN), at least 3.
    towards: (3,) direction, or (N, 3) per-point directions, the normals should face.
    The points are centred (median) before they go to Open3D, so that LiDAR coordinates
    around 1e5-1e7 keep their float64 precision in the neighbourhood covariances.
    Repeated positions are merged before the estimation and share one normal: Open3D's
    neighbour search degrades to quadratic time on many coincident points.
    Raises InputError for bad shapes or fewer than 3 distinct finite points,
    DependencyError when Open3D cannot be imported.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must be an array of shape (N, 3), got shape {pts.shape}")
    if int(k) < 3:
        raise InputError(f"normal estimation needs at least k=3 neighbours, got k={k}")
    finite = np.all(np.isfinite(pts), axis=1)
    if finite.sum() < 3:
        raise InputError(f"normal estimation needs at least 3 points with finite coordinates, "
                         f"got {int(finite.sum())}")
    towards = np.asarray(towards, dtype=np.float64)
    if towards.shape not in ((3,), pts.shape):
        raise InputError(f"towards must have shape (3,) or {pts.shape}, got {towards.shape}")
    distinct, inverse = unique_positions(pts if finite.all() else pts[finite])
    if len(distinct) < 3:
        raise InputError(f"the {int(finite.sum())} finite points occupy only {len(distinct)} distinct "
                         "positions; normal estimation needs at least 3")
    o3d = _import_open3d()
    centred = distinct - np.median(distinct, axis=0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centred))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=int(k)))
    normals = np.full(pts.shape, np.nan)
    normals[finite] = orient_normals(np.asarray(cloud.normals)[inverse],
                                     towards[finite] if towards.ndim == 2 else towards)
    return normals


def neighbourhood_reach(points: np.ndarray, at: np.ndarray, k: int) -> np.ndarray:
    """(m,) the 3-D distance from each point points[at] (at: (m,) rows or an (N,) mask) to
    its k-th nearest distinct position among points (N, 3), itself counted as Open3D's KNN
    counts it: the radius of the neighbourhood `estimate_normals` fits a plane to there;
    inf everywhere when the points hold fewer than k distinct positions. A tile whose read
    points hold every own point's neighbourhood gets the whole survey's normals
    (c1mesh.survey.tile_normals compares this reach with what it did not read)."""
    distinct, inverse = unique_positions(points)
    mine = inverse[at]
    if len(distinct) < k:
        return np.full(len(mine), np.inf)
    rows, back = np.unique(mine, return_inverse=True)
    distance, _ = spatial.cKDTree(distinct).query(distinct[rows], k, workers=workers())
    kth = distance[:, -1] if distance.ndim == 2 else distance
    return kth[back.ravel()]


def unique_positions(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct rows of `points` (M, 3), index (N,) of each point's row among them).

    Exact: rows are grouped by a 64-bit hash of their coordinate bits (one 1-D sort,
    several times faster than np.unique(axis=0); no copy when no hash repeats), and a
    new group starts wherever the hash or any coordinate changes. A hash collision between different positions can at
    worst leave one position twice in the result, never merge two positions.
    """
    pts = np.asarray(points, dtype=np.float64)
    key = np.zeros(len(pts), np.uint64)
    with np.errstate(over="ignore"):
        for column, (mix, shift) in enumerate(((0x9E3779B97F4A7C15, 29), (0xC2B2AE3D27D4EB4F, 31),
                                               (0x165667B19E3779F9, 27))):
            bits = (pts[:, column] + 0.0).view(np.uint64)   # + 0.0 turns -0.0 into 0.0
            key ^= bits * np.uint64(mix) + (key >> np.uint64(shift))
    order = np.argsort(key)
    sorted_key = key[order]
    del key
    starts = np.ones(len(order), bool)
    starts[1:] = sorted_key[1:] != sorted_key[:-1]
    if starts.all():   # all hashes differ: no repeats, no copy
        return pts, np.arange(len(pts))
    del sorted_key
    for column in range(3):   # a new group also where any coordinate changes (hash collisions)
        values = pts[order, column] + 0.0
        starts[1:] |= values[1:] != values[:-1]
    inverse = np.empty(len(order), np.int64)
    inverse[order] = np.cumsum(starts) - 1
    return pts[order[starts]] + 0.0, inverse


def orient_normals(normals: ArrayLike, towards: ArrayLike) -> np.ndarray:
    """Flip each normal (N, 3) whose dot product with `towards` ((3,) or (N, 3)) is negative.

    Returns a new array; normals perpendicular to `towards` (and NaN rows) are unchanged.
    """
    n = np.array(normals, dtype=np.float64)
    t = np.asarray(towards, dtype=np.float64)
    if n.ndim != 2 or n.shape[1] != 3 or t.shape not in ((3,), n.shape):
        raise InputError(f"orient_normals needs normals (N, 3) and towards (3,) or (N, 3), "
                         f"got {n.shape} and {t.shape}")
    dot = np.einsum("ij,ij->i", n, np.broadcast_to(t, n.shape))
    n[dot < 0] *= -1.0
    return n


def _import_open3d():
    """The open3d module, or DependencyError saying how to install what is missing."""
    try:
        import open3d
    except (ImportError, OSError) as exc:  # OSError: a missing system library (libusb)
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DependencyError(
            f"normal estimation needs open3d, which failed to import ({reason}): install the "
            "Debian package libusb-1.0-0 (apt-get install libusb-1.0-0) and `pip install open3d`"
        ) from exc
    return open3d
