"""Synthetic scenes seen from a viewpoint at the origin, with exact normals, written as files."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from c1mesh.core.cloud import SurfaceMesh
from c1mesh.formats import write_mesh
from c1mesh.testing.samples import cylinder_from_inside, tilted_plane, write_organised_pcd as _write_pcd

__all__ = ["cylinder_from_inside", "tilted_plane", "write_organised_pcd", "write_unorganised_ply"]


def write_organised_pcd(path: Path, points: np.ndarray, normals: np.ndarray, shape: tuple[int, int]) -> Path:
    _write_pcd(points, normals, shape, path)
    return path


def write_unorganised_ply(path: Path, points: np.ndarray, normals: np.ndarray) -> Path:
    """The finite points with their normals as a PLY point cloud (no grid, no viewpoint)."""
    keep = np.isfinite(points).all(axis=1)
    write_mesh(SurfaceMesh(points[keep], np.zeros((0, 3), dtype=np.int64), normals[keep]), path)
    return path
