"""Mesh-only writers: binary STL, OFF and glTF binary (.glb).

STL stores float32 corners and one facet normal per triangle by definition of the
format. GLB stores float32 positions relative to a local origin kept as a double in the
node's translation (write_glb). Use PLY or OBJ when every digit of large world
coordinates must be kept.
"""
from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import IO, Iterator

import numpy as np

from c1mesh.core.cloud import MeshStream, SurfaceMesh
from c1mesh.core.errors import FormatError
from c1mesh.formats._background import background_writes
from c1mesh.formats._blocks import (
    BINARY_ROWS,
    INT32_MOST,
    TEXT_ROWS,
    UINT32_MOST,
    as_stream,
    face_chunks,
    refuse_size,
    text_rows,
    too_many,
    vertex_bounds,
    vertex_chunks,
    vertex_table,
)


def _facet_normals(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(K, 3) unit normals of triangles, counter-clockwise = outward; zero for degenerate ones."""
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


_STL_ROW = np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def stl_size_problem(size) -> str | None:
    """Why a binary STL cannot hold a mesh of size.face_count triangles (a _blocks.MeshSize
    or MeshStream), or None: its header counts triangles in a uint32, so at most 2³² − 1.
    Vertices are not counted or indexed (each facet repeats its corners): no limit."""
    return too_many(size.face_count, "triangles", UINT32_MOST, "STL counts triangles in a uint32")


def write_stl(mesh: SurfaceMesh | MeshStream, f: IO[bytes], ascii: bool = False) -> None:
    """Binary STL: 80-byte header, uint32 count, then per triangle normal, 3 corners, attribute.

    Written face block by face block. A face may name any vertex, so the vertex positions
    are held as one float64 table (24 bytes a vertex, about a quarter of the file's 50
    bytes a face; nothing else of the mesh's size): facet normals are computed from the
    doubles, then stored as float32 with the corners. A mesh beyond `stl_size_problem` is
    refused (InputError) before a byte is written.
    """
    stream = as_stream(mesh)
    refuse_size(stl_size_problem(stream))
    table = vertex_table(mesh)
    with background_writes(f) as write:
        write(b"binary STL written by c1mesh".ljust(80, b" "))
        write(np.uint32(stream.face_count).astype("<u4").tobytes())
        for faces in face_chunks(stream, BINARY_ROWS):
            rows = np.zeros(len(faces), _STL_ROW)
            rows["n"] = _facet_normals(table, faces)
            rows["v"] = table[faces]
            write(memoryview(rows).cast("B"))


def off_size_problem(size) -> str | None:
    """Why an OFF cannot hold a mesh of size.vertex_count vertices and size.face_count
    faces (a _blocks.MeshSize or MeshStream), or None.

    Geomview's OFF definition has its counts and vertex indices as 32-bit ints: its
    binary form stores them so, and its reader (like most since) reads the text form's
    into C ints. So at most 2³¹ − 1 vertices and 2³¹ − 1 faces.
    """
    return (too_many(size.vertex_count, "vertices", INT32_MOST,
                     "OFF counts elements and indexes vertices with 32-bit ints")
            or too_many(size.face_count, "faces", INT32_MOST, "OFF counts elements with 32-bit ints"))


def write_off(mesh: SurfaceMesh | MeshStream, f: IO[bytes], ascii: bool = True) -> None:
    """OFF text: vertex coordinates with round-trip (repr) precision, then '3 a b c' faces.

    Plain OFF has no normals; colours are not written (COFF is read inconsistently).
    Written block by block (formats/_blocks.py): memory stays a few blocks of text.
    A mesh beyond `off_size_problem` is refused (InputError) before a byte is written.
    """
    stream = as_stream(mesh)
    refuse_size(off_size_problem(stream))
    with background_writes(f) as write:
        write(f"OFF\n{stream.vertex_count} {stream.face_count} 0\n".encode("ascii"))
        for vertices, _, _ in vertex_chunks(stream, TEXT_ROWS):
            write(text_rows(np.asarray(vertices, np.float64).tolist()))
        for faces in face_chunks(stream, TEXT_ROWS):
            write("".join(f"3 {a} {b} {c}\n" for a, b, c in faces.tolist()).encode("ascii"))


@dataclass(frozen=True)
class _GlbPart:
    """One bufferView + accessor of the GLB: `count` elements of `width` bytes each."""

    name: str          # POSITION, NORMAL, COLOR_0 or indices
    count: int
    width: int
    target: int        # 34962 vertex attributes, 34963 indices
    component: int     # 5126 float, 5121 unsigned byte, 5125 unsigned int
    kind: str          # VEC3, VEC4, SCALAR
    normalized: bool = False


def _glb_parts(stream: MeshStream) -> list[_GlbPart]:
    """The GLB's parts in the order their bytes follow each other in the BIN chunk."""
    m = stream.vertex_count
    parts = [_GlbPart("POSITION", m, 12, 34962, 5126, "VEC3")]
    if stream.has_normals:
        parts.append(_GlbPart("NORMAL", m, 12, 34962, 5126, "VEC3"))
    if stream.color_channels:   # glTF wants 4-byte aligned elements: RGB is padded to RGBA
        parts.append(_GlbPart("COLOR_0", m, 4, 34962, 5121, "VEC4", normalized=True))
    parts.append(_GlbPart("indices", 3 * stream.face_count, 4, 34963, 5125, "SCALAR"))
    return parts


def _glb_document(parts: list[_GlbPart], origin: np.ndarray, low: np.ndarray, high: np.ndarray,
                  crs: str | None) -> tuple[dict, int]:
    """(glTF JSON document, BIN chunk length) from the parts' counts alone, so the JSON
    chunk can be written before any vertex. low/high: the float32 offsets' bounds."""
    views, accessors, offset = [], [], 0
    for i, part in enumerate(parts):
        length = part.count * part.width           # every width is 4 or 12: no padding
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": length, "target": part.target})
        accessor = {"bufferView": i, "componentType": part.component, "count": part.count, "type": part.kind}
        if part.normalized:
            accessor["normalized"] = True
        if i == 0 and part.count:
            accessor["min"] = low.astype(float).tolist()
            accessor["max"] = high.astype(float).tolist()
        accessors.append(accessor)
        offset += length
    extras = {"generator": "c1mesh", "origin": origin.tolist()}
    if crs:
        extras["crs"] = crs
    attributes = {part.name: i for i, part in enumerate(parts[:-1])}
    document = {
        "asset": {"version": "2.0", "generator": "c1mesh", "extras": extras},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": origin.tolist()}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": len(parts) - 1, "mode": 4}]}],
        "buffers": [{"byteLength": offset}], "bufferViews": views, "accessors": accessors,
    }
    return document, offset


_GLB_LENGTH = "GLB stores its length in a uint32 (4 GiB; write PLY instead)"


def glb_size_problem(size) -> str | None:
    """Why a GLB cannot hold a mesh of this size (a _blocks.MeshSize or MeshStream), or None.

    glTF 2.0 indexes vertices with uint32 indices (write_glb's choice, the widest), and
    its specification reserves the largest, 2³² − 1, as the primitive restart value: so
    at most 2³² − 1 vertices (indices 0 .. 2³² − 2). The file's length and its BIN
    chunk's are uint32 too: the BIN chunk alone (_glb_parts, from the counts) plus the
    28 bytes of headers must stay within 2³² − 1 bytes (write_glb checks the exact total,
    JSON included, once the JSON is written out).
    """
    binary = sum(part.count * part.width for part in _glb_parts(size))
    return (too_many(size.vertex_count, "vertices", UINT32_MOST,
                     "GLB indexes vertices with uint32s below the reserved 2³² − 1")
            or too_many(28 + binary, "bytes", UINT32_MOST, _GLB_LENGTH))


def write_glb(mesh: SurfaceMesh | MeshStream, f: IO[bytes], ascii: bool = False,
              crs: str | None = None) -> None:
    """glTF 2.0 binary: one mesh, one node whose translation is the local origin.

    Positions are float32 offsets from the bounding-box centre (float64; 0 for no vertex), and the
    origin sits in the node's translation as a JSON double, so world positions keep
    ~7 significant digits of the mesh's half extent instead of of its world coordinates
    (LiDAR at 1e6 ft would lose 0.06 ft). Normals are float32, colours normalised
    uint8 (COLOR_0), indices uint32. No axis swap: the world frame is written as is.
    The CRS (WKT) and the origin are in asset.extras.

    Streamed: every byte length follows from the counts, so the JSON chunk is written
    first, then the BIN chunk one block at a time. The bounding box takes one pass over
    the vertices before, and each vertex attribute its own pass (they are separate
    bufferViews); float32(x - origin) is monotonic in x, so the float32 bounds of the
    offsets are the offsets of the float64 bounds. A mesh beyond `glb_size_problem` is
    refused (InputError) before a byte is written.
    """
    stream = as_stream(mesh)
    refuse_size(glb_size_problem(stream))
    low, high = vertex_bounds(stream)
    origin = 0.5 * (low + high) if stream.vertex_count else np.zeros(3)
    parts = _glb_parts(stream)
    document, binary_length = _glb_document(parts, origin, (low - origin).astype("<f4"),
                                            (high - origin).astype("<f4"), crs)
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + binary_length
    refuse_size(too_many(total, "bytes", UINT32_MOST, _GLB_LENGTH))
    with background_writes(f) as write:
        write(struct.pack("<4sII", b"glTF", 2, total))
        write(struct.pack("<I4s", len(text), b"JSON") + text)
        write(struct.pack("<I4s", binary_length, b"BIN\0"))
        for part in parts:
            for data in _glb_part_blocks(part.name, stream, origin):
                write(memoryview(np.ascontiguousarray(data)).cast("B"))


def _glb_part_blocks(name: str, stream: MeshStream, origin: np.ndarray) -> Iterator[np.ndarray]:
    """The arrays of one GLB part, block by block, in their file dtypes (fresh arrays)."""
    if name == "indices":
        for faces in face_chunks(stream, BINARY_ROWS):
            yield faces.astype("<u4").ravel()
        return
    for vertices, normals, colors in vertex_chunks(stream, BINARY_ROWS):
        if name == "POSITION":
            yield (np.asarray(vertices, dtype=np.float64) - origin).astype("<f4")
        elif name == "NORMAL":
            yield np.array(normals, "<f4")          # a copy: the stream may reuse its buffer
        else:
            colors = np.array(colors, np.uint8)
            if colors.shape[1] == 3:
                colors = np.column_stack([colors, np.full(len(colors), 255, np.uint8)])
            yield colors



def read_glb_vertices(data: bytes) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """(world positions (M, 3) float64, normals (M, 3) or None, CRS WKT or None) of the
    first mesh of a GLB as write_glb writes it: float32 accessors in one buffer, the origin
    in the node's translation (the positions are float32 POSITION plus it), the CRS in
    asset.extras. FormatError for anything else."""
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
    return positions, normals, document.get("asset", {}).get("extras", {}).get("crs")
