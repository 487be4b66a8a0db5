"""Normal estimation for scans that come without normals (LiDAR, bare xyz files).

Open3D fits a plane to the k nearest neighbours of every point (PCA of the
neighbourhood); the plane's normal is defined only up to sign, so the result is oriented
towards a given direction, normally the height axis e3 of the scan frame.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from c1mesh.errors import DependencyError, InputError


def estimate_normals(points: ArrayLike, k: int = 16,
                     towards: ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Unit normals (N, 3) of a scan, oriented so that n·towards >= 0.

    points:  (N, 3) world coordinates; rows with a non-finite coordinate get NaN normals.
    k:       neighbours per local plane fit (Open3D KDTreeSearchParamKNN), at least 3.
    towards: (3,) direction, or (N, 3) per-point directions, the normals should face.
    The points are centred (median) before they go to Open3D, so that LiDAR coordinates
    around 1e5-1e7 keep their float64 precision in the neighbourhood covariances.
    Raises InputError for bad shapes or fewer than 3 finite points, DependencyError when
    Open3D cannot be imported.
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
    o3d = _import_open3d()
    centred = pts[finite] - np.median(pts[finite], axis=0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centred))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=int(k)))
    normals = np.full(pts.shape, np.nan)
    normals[finite] = orient_normals(np.asarray(cloud.normals),
                                     towards[finite] if towards.ndim == 2 else towards)
    return normals


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
