"""Mesh-only writers: binary STL, OFF and glTF binary (.glb).

STL stores float32 corners and one facet normal per triangle by definition of the
format. GLB stores float32 positions relative to a local origin kept as a double in the
node's translation (write_glb). Use PLY or OBJ when every digit of large world
coordinates must be kept.
"""
from __future__ import annotations

import io
import json
import struct
from typing import IO

import numpy as np

from c1mesh.cloud import SurfaceMesh


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


def glb_origin(vertices: np.ndarray) -> np.ndarray:
    """The local origin of a GLB: the centre of the bounding box (3,) float64, so float32
    offsets from it lose at most half an ulp of half the mesh's extent."""
    if len(vertices) == 0:
        return np.zeros(3)
    return 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))


def write_glb(mesh: SurfaceMesh, f: IO[bytes], ascii: bool = False, crs: str | None = None) -> None:
    """glTF 2.0 binary: one mesh, one node whose translation is the local origin.

    Positions are float32 offsets from the bounding-box centre (glb_origin), and the
    origin sits in the node's translation as a JSON double, so world positions keep
    ~7 significant digits of the mesh's half extent instead of of its world coordinates
    (LiDAR at 1e6 ft would lose 0.06 ft). Normals are float32, colours normalised
    uint8 (COLOR_0), indices uint32. No axis swap: the world frame is written as is.
    The CRS (WKT) and the origin are in asset.extras.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    origin = glb_origin(v)
    local = (v - origin).astype("<f4")
    parts = [(local, 34962, 5126, "VEC3", False)]
    attributes = {"POSITION": 0}
    if mesh.vertex_normals is not None:
        attributes["NORMAL"] = len(parts)
        parts.append((np.asarray(mesh.vertex_normals, "<f4"), 34962, 5126, "VEC3", False))
    if mesh.vertex_colors is not None:
        colors = np.asarray(mesh.vertex_colors, np.uint8)
        if colors.shape[1] == 3:   # glTF wants 4-byte aligned elements: pad RGB to RGBA
            colors = np.column_stack([colors, np.full(len(colors), 255, np.uint8)])
        attributes["COLOR_0"] = len(parts)
        parts.append((colors, 34962, 5121, "VEC4", True))
    indices = len(parts)
    parts.append((faces.astype("<u4").ravel(), 34963, 5125, "SCALAR", False))
    views, accessors, chunks, offset = [], [], [], 0
    for i, (arr, target, component, kind, normalized) in enumerate(parts):
        data = np.ascontiguousarray(arr).tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data), "target": target})
        accessor = {"bufferView": i, "componentType": component, "count": int(len(arr)), "type": kind}
        if normalized:
            accessor["normalized"] = True
        if i == 0 and len(arr):
            accessor["min"] = local.min(axis=0).astype(float).tolist()
            accessor["max"] = local.max(axis=0).astype(float).tolist()
        accessors.append(accessor)
        chunks.append(data + b"\0" * (-len(data) % 4))
        offset += len(chunks[-1])
    extras = {"generator": "c1mesh", "origin": origin.tolist()}
    if crs:
        extras["crs"] = crs
    document = {
        "asset": {"version": "2.0", "generator": "c1mesh", "extras": extras},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": origin.tolist()}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": indices, "mode": 4}]}],
        "buffers": [{"byteLength": offset}], "bufferViews": views, "accessors": accessors,
    }
    _write_glb_chunks(f, json.dumps(document, separators=(",", ":")).encode("utf-8"), b"".join(chunks))


def _write_glb_chunks(f: IO[bytes], text: bytes, binary: bytes) -> None:
    """GLB container: 12-byte header, JSON chunk (space padded), BIN chunk (zero padded)."""
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    f.write(struct.pack("<4sII", b"glTF", 2, total))
    f.write(struct.pack("<I4s", len(text), b"JSON") + text)
    f.write(struct.pack("<I4s", len(binary), b"BIN\0") + binary)


def read_glb_positions(data: bytes) -> np.ndarray:
    """World positions (M, 3) float64 of the first mesh of a GLB written by write_glb:
    float32 POSITION plus the node's translation (used to check precision)."""
    return read_glb_vertices(data)[0]


def read_glb_vertices(data: bytes) -> tuple[np.ndarray, np.ndarray | None]:
    """(world positions (M, 3) float64, normals (M, 3) or None) of the first mesh of a
    GLB as write_glb writes it: float32 accessors in one buffer, the origin in the node's
    translation. FormatError for anything else."""
    from c1mesh.errors import FormatError
    try:
        length, _ = struct.unpack_from("<I4s", data, 12)
        document = json.loads(data[20:20 + length])
        binary = data[20 + length + 8:]
        attributes = document["meshes"][0]["primitives"][0]["attributes"]

        def column(name):
            accessor = document["accessors"][attributes[name]]
            view = document["bufferViews"][accessor["bufferView"]]
            start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
            return np.frombuffer(binary, "<f4", accessor["count"] * 3, start).reshape(-1, 3)
        node = next(n for n in document["nodes"] if n.get("mesh") == 0)
        positions = column("POSITION").astype(np.float64) + np.asarray(node.get("translation", [0.0] * 3))
        normals = column("NORMAL").astype(np.float64) if "NORMAL" in attributes else None
    except (struct.error, ValueError, KeyError, IndexError, StopIteration) as exc:
        raise FormatError(f"cannot read the GLB: {exc}") from exc
    return positions, normals
