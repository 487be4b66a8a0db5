"""Synthetic scenes seen from a viewpoint at the origin, with exact normals, written as files."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from c1mesh.cloud import SurfaceMesh
from c1mesh.formats import write_mesh


def pixel_rays(n: int, half_width: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of an n×n pixel grid spanning [-half_width, half_width]², rows = v, cols = u."""
    t = np.linspace(-half_width, half_width, n)
    u, v = np.meshgrid(t, t)
    return u, v


def cylinder_from_inside(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points and outward-from-axis normals (n*n, 3) of x²+y²=1, 1 <= z <= 5, seen from the origin
    on the axis looking along +z; pixels whose ray misses that part of the wall are NaN."""
    u, v = pixel_rays(n)
    r = np.hypot(u, v)
    with np.errstate(divide="ignore"):
        z = 1.0 / r
    z[(z < 1.0) | (z > 5.0)] = np.nan
    points = np.stack([u * z, v * z, z], axis=-1).reshape(-1, 3)
    normals = np.column_stack([points[:, 0], points[:, 1], np.zeros(len(points))])
    return points, normals


def tilted_plane(n: int, normal=(0.3, -0.2, 1.0), offset: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Points and normals (n*n, 3) of the plane normal·X = offset seen from the origin."""
    nrm = np.asarray(normal, dtype=float)
    u, v = pixel_rays(n, 0.5)
    z = offset / (nrm[0] * u + nrm[1] * v + nrm[2])
    points = np.stack([u * z, v * z, z], axis=-1).reshape(-1, 3)
    return points, np.tile(nrm, (len(points), 1))


def write_organised_pcd(path: Path, points: np.ndarray, normals: np.ndarray, shape: tuple[int, int]) -> Path:
    """An ascii PCD with WIDTH x HEIGHT = shape (columns, rows) and VIEWPOINT at the origin."""
    height, width = shape
    rows = np.column_stack([points, normals])
    body = "\n".join(" ".join("nan" if not np.isfinite(x) else repr(float(x)) for x in row) for row in rows)
    header = ("VERSION 0.7\nFIELDS x y z normal_x normal_y normal_z\nSIZE 8 8 8 8 8 8\nTYPE F F F F F F\n"
              f"COUNT 1 1 1 1 1 1\nWIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\n"
              f"POINTS {width * height}\nDATA ascii\n")
    path.write_text(header + body + "\n")
    return path


def write_unorganised_ply(path: Path, points: np.ndarray, normals: np.ndarray) -> Path:
    """The finite points with their normals as a PLY point cloud (no grid, no viewpoint)."""
    keep = np.isfinite(points).all(axis=1)
    write_mesh(SurfaceMesh(points[keep], np.zeros((0, 3), dtype=np.int64), normals[keep]), path)
    return path
