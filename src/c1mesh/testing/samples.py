"""Analytic surfaces sampled with exact normals: inputs whose truth is known.

Used by the bundled samples in data_samples/, the examples, the tests and the benchmarks.
Each surface is z = f(x, y) on the unit square with its exact gradient; a sample is a
point cloud whose normals are the exact unit normals (−f_x, −f_y, 1)/|·|, optionally
rotated into a tilted frame and shifted by a large offset (as LiDAR coordinates are).

    python -m c1mesh.testing.samples data_samples/     # regenerates the bundled analytic samples
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from c1mesh.core.cloud import PointCloud


@dataclass(frozen=True)
class Surface:
    """z = f(xy) with gradient grad(xy); xy (..., 2) -> (...) and (..., 2)."""

    name: str
    f: Callable[[np.ndarray], np.ndarray]
    grad: Callable[[np.ndarray], np.ndarray]


def _hill(xy):
    x, y = xy[..., 0], xy[..., 1]
    return 0.3 * np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2) / 0.08) + 0.1 * x


def _hill_grad(xy):
    x, y = xy[..., 0], xy[..., 1]
    e = 0.3 * np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2) / 0.08)
    return np.stack([-e * 2 * (x - 0.5) / 0.08 + 0.1, -e * 2 * (y - 0.5) / 0.08], axis=-1)


def _wave(xy):
    return 0.1 * np.exp(xy[..., 0]) * np.sin(2 * xy[..., 1])


def _wave_grad(xy):
    e = 0.1 * np.exp(xy[..., 0])
    return np.stack([e * np.sin(2 * xy[..., 1]), 2 * e * np.cos(2 * xy[..., 1])], axis=-1)


def _paraboloid(xy):
    return 0.5 * ((xy[..., 0] - 0.5) ** 2 + (xy[..., 1] - 0.5) ** 2)


def _paraboloid_grad(xy):
    return np.stack([xy[..., 0] - 0.5, xy[..., 1] - 0.5], axis=-1)


def _plane(xy):
    return 0.3 * xy[..., 0] - 0.2 * xy[..., 1] + 1.0


def _plane_grad(xy):
    return np.broadcast_to(np.array([0.3, -0.2]), xy.shape).copy()


SURFACES: dict[str, Surface] = {s.name: s for s in (
    Surface("hill", _hill, _hill_grad),
    Surface("wave", _wave, _wave_grad),
    Surface("paraboloid", _paraboloid, _paraboloid_grad),
    Surface("plane", _plane, _plane_grad),
)}


def exact_normals(grad: np.ndarray) -> np.ndarray:
    """Unit normals (..., 3) of a graph with gradient grad (..., 2), pointing to +z."""
    n = np.concatenate([-grad, np.ones(grad.shape[:-1] + (1,))], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def unit_square_points(n: int, seed: int = 0, boundary: int = 16) -> np.ndarray:
    """n random points (n, 2) in the unit square including corners and ``boundary`` per side."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, boundary + 1)[:-1]
    rim = np.concatenate([np.stack([t, 0 * t], 1), np.stack([1 + 0 * t, t], 1),
                          np.stack([1 - t, 1 + 0 * t], 1), np.stack([0 * t, 1 - t], 1)])
    inner = rng.random((max(n - rim.shape[0], 0), 2))
    return np.vstack([rim, inner])


def sample_surface(name: str, n: int = 2000, seed: int = 0, rotation: np.ndarray | None = None,
                   offset=(0.0, 0.0, 0.0), scale: float = 1.0) -> PointCloud:
    """A point cloud of surface ``name`` with exact unit normals.

    World point = offset + rotation @ (scale·x, scale·y, scale·f(x, y)); normals rotated
    alike. ``rotation`` (3, 3) orthonormal (default identity) tilts the height axis.
    """
    surface = SURFACES[name]
    xy = unit_square_points(n, seed)
    local = np.column_stack([xy, surface.f(xy)]) * scale
    normals = exact_normals(surface.grad(xy))
    R = np.eye(3) if rotation is None else np.asarray(rotation, float)
    return PointCloud(points=local @ R.T + np.asarray(offset, float), normals=normals @ R.T)


def rotation_about(axis, degrees: float) -> np.ndarray:
    """Rotation matrix (3, 3) about ``axis`` by ``degrees`` (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(degrees)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def write_points_ply(cloud: PointCloud, path) -> None:
    """Binary little-endian PLY of points with double x y z and nx ny nz (for samples)."""
    n = len(cloud)
    header = ("ply\nformat binary_little_endian 1.0\ncomment c1mesh analytic sample, exact normals\n"
              f"element vertex {n}\n" + "".join(f"property double {c}\n" for c in ("x", "y", "z"))
              + "".join(f"property double {c}\n" for c in ("nx", "ny", "nz")) + "end_header\n")
    body = np.column_stack([cloud.points, cloud.normals]).astype("<f8")
    Path(path).write_bytes(header.encode("ascii") + body.tobytes())


def write_points_xyz(cloud: PointCloud, path) -> None:
    """Text x y z nx ny nz with a header line, full double precision."""
    np.savetxt(path, np.column_stack([cloud.points, cloud.normals]), fmt="%.17g",
               header="x y z nx ny nz", comments="")


# ------------------------------------------------------------- scenes seen from a viewpoint
def pixel_rays(n: int, half_width: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters (u, v) = (x/z, y/z), each (n, n), of an n×n pixel grid over
    [-half_width, half_width]²: rows are v, columns u (a pinhole camera at the origin)."""
    t = np.linspace(-half_width, half_width, n)
    u, v = np.meshgrid(t, t)
    return u, v


def cylinder_from_inside(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The wall x² + y² = 1, 1 <= z <= 5, seen from the origin on its axis looking along +z.

    Returns points and exact normals (n*n, 3), pixels row by row; pixels whose ray misses
    that part of the wall are NaN. No plane sees this as a height field; the view rays do
    (inverse depth w = sqrt(u² + v²), see docs/perspective.md).
    """
    u, v = pixel_rays(n)
    r = np.hypot(u, v)
    with np.errstate(divide="ignore"):
        z = 1.0 / r
    z[(z < 1.0) | (z > 5.0)] = np.nan
    points = np.stack([u * z, v * z, z], axis=-1).reshape(-1, 3)
    normals = np.column_stack([points[:, 0], points[:, 1], np.zeros(len(points))])
    return points, normals


def tilted_plane(n: int, normal=(0.3, -0.2, 1.0), offset: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Points and normals (n*n, 3) of the plane normal·X = offset seen from the origin
    through an n×n pixel grid over [-0.5, 0.5]² in (u, v)."""
    nrm = np.asarray(normal, dtype=float)
    u, v = pixel_rays(n, 0.5)
    z = offset / (nrm[0] * u + nrm[1] * v + nrm[2])
    points = np.stack([u * z, v * z, z], axis=-1).reshape(-1, 3)
    return points, np.tile(nrm, (len(points), 1))


def write_organised_pcd(points: np.ndarray, normals: np.ndarray, shape: tuple[int, int], path) -> None:
    """Binary PCD (float64 x y z normal_x normal_y normal_z) with WIDTH x HEIGHT = shape
    (rows, columns reversed as PCD wants) and VIEWPOINT at the origin: an organised scan."""
    height, width = shape
    header = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z normal_x normal_y normal_z\nSIZE 8 8 8 8 8 8\n"
              "TYPE F F F F F F\nCOUNT 1 1 1 1 1 1\n"
              f"WIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {width * height}\n"
              "DATA binary\n")
    body = np.column_stack([points, normals]).astype("<f8")
    Path(path).write_bytes(header.encode("ascii") + body.tobytes())


def write_bundled_samples(folder) -> list[Path]:
    """The analytic files shipped in data_samples/ (small, deterministic)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    made = []
    hill = sample_surface("hill", 3000, seed=1)
    write_points_ply(hill, folder / "hill.ply")
    tilted = sample_surface("wave", 2000, seed=2, rotation=rotation_about([1, 1, 0], 30),
                            offset=(640_000.0, 850_000.0, 120.0), scale=50.0)
    write_points_xyz(tilted, folder / "wave_tilted_offset.xyz")
    made += [folder / "hill.ply", folder / "wave_tilted_offset.xyz"]
    return made


if __name__ == "__main__":  # pragma: no cover
    for path in write_bundled_samples(sys.argv[1] if len(sys.argv) > 1 else "data_samples"):
        print(path)
