"""Mesh-only writers: binary STL, OFF and glTF binary (.glb).

STL stores float32 corners and one facet normal per triangle by definition of the
format; GLB stores float32 positions (via trimesh). Use PLY or OBJ when large world
coordinates must keep double precision.
"""
from __future__ import annotations

import io
from typing import IO

import numpy as np

from c1mesh.cloud import SurfaceMesh
from c1mesh.errors import DependencyError


def _facet_normals(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(K, 3) unit normals of triangles, counter-clockwise = outward; zero for degenerate ones."""
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def write_stl(mesh: SurfaceMesh, f: IO[bytes], ascii: bool = False) -> None:
    """Binary STL: 80-byte header, uint32 count, then per triangle normal, 3 corners, attribute."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    rows = np.zeros(len(faces), np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")]))
    rows["n"] = _facet_normals(v, faces)
    rows["v"] = v[faces]
    f.write(b"binary STL written by c1mesh".ljust(80, b" "))
    f.write(np.uint32(len(faces)).astype("<u4").tobytes())
    f.write(rows.tobytes())


def write_off(mesh: SurfaceMesh, f: IO[bytes], ascii: bool = True) -> None:
    """OFF text: vertex coordinates with round-trip (repr) precision, then '3 a b c' faces.

    Plain OFF has no normals; colours are not written (COFF is read inconsistently).
    """
    out = io.StringIO()
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    out.write(f"OFF\n{len(mesh.vertices)} {len(faces)} 0\n")
    out.writelines(" ".join(map(repr, row)) + "\n" for row in np.asarray(mesh.vertices, np.float64).tolist())
    out.writelines(f"3 {a} {b} {c}\n" for a, b, c in faces.tolist())
    f.write(out.getvalue().encode("ascii"))


def write_glb(mesh: SurfaceMesh, f: IO[bytes], ascii: bool = False) -> None:
    """glTF binary via trimesh, with vertex normals and colours when present (float32 positions)."""
    try:
        import trimesh
    except ImportError as exc:
        raise DependencyError('Writing .glb needs trimesh: pip install "trimesh>=4".') from exc
    tm = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices, np.float64),
        faces=np.asarray(mesh.faces, np.int64).reshape(-1, 3),
        vertex_normals=mesh.vertex_normals,
        vertex_colors=mesh.vertex_colors,
        process=False,
    )
    f.write(tm.export(file_type="glb", include_normals=mesh.vertex_normals is not None))
