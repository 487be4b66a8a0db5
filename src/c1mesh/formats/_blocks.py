"""Helpers of the streaming mesh writers: every writer takes a SurfaceMesh or a MeshStream
and writes it block by block, so writing holds a few blocks, never the whole mesh.

A MeshStream's blocks are as large as its producer makes them (a refinement block is
~2^18 rows); text writers turn each row into Python floats and strings (~100 bytes of
objects per number), so blocks are cut into chunks of TEXT_ROWS rows before formatting.

Each format's size limit lives beside its writer (`ply_size_problem`, `off_size_problem`,
...): a function of a MeshSize (or MeshStream) that says why the format cannot hold a mesh
of that size, or None. The writer refuses by it before writing a byte, and
c1mesh.formats.check_mesh_size lets a fit refuse before it refines.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Iterator, Sequence

import numpy as np

from c1mesh.core.cloud import MeshStream, SurfaceMesh
from c1mesh.core.errors import InputError
from c1mesh.core.tile import bounds

STREAM_BLOCK = 1 << 18
"""Rows per block when a SurfaceMesh in memory is written as a stream (views, no copies)."""

TEXT_ROWS = 1 << 12
"""Rows formatted as text at a time: ~0.5 MB of text, ~3 MB of transient Python objects."""

BINARY_ROWS = 1 << 14
"""Rows packed into binary records at a time (STL: 0.8 MB of 50-byte records, plus ~3 MB
of float64 temporaries for the corners and normals)."""


def as_stream(mesh: SurfaceMesh | MeshStream) -> MeshStream:
    """`mesh` as a MeshStream (a SurfaceMesh is sliced into views of STREAM_BLOCK rows)."""
    return mesh.stream(STREAM_BLOCK) if isinstance(mesh, SurfaceMesh) else mesh


def vertex_chunks(stream: MeshStream, rows: int) -> Iterator[tuple]:
    """One pass over the stream's vertex blocks, cut into (vertices, normals, colors)
    chunks of at most `rows` rows (normals/colors None where the stream has none)."""
    for vertices, normals, colors in stream.vertex_blocks():
        normals = normals if stream.has_normals else None
        colors = colors if stream.color_channels else None
        for start in range(0, len(vertices), rows):
            part = slice(start, start + rows)
            yield (vertices[part], None if normals is None else normals[part],
                   None if colors is None else colors[part])


def face_chunks(stream: MeshStream, rows: int) -> Iterator[np.ndarray]:
    """One pass over the stream's face blocks as int64 (k, 3) chunks of at most `rows` faces."""
    for faces in stream.face_blocks():
        faces = np.asarray(faces).reshape(-1, 3)
        for start in range(0, len(faces), rows):
            yield faces[start:start + rows].astype(np.int64)


def text_rows(rows: Iterable[Sequence], prefix: str = "") -> bytes:
    """ASCII lines `prefix` + the numbers of each row joined by spaces, with round-trip
    precision (repr of a Python float: the shortest text that reads back bit-exact)."""
    return "".join(prefix + " ".join(map(repr, row)) + "\n" for row in rows).encode("ascii")


def vertex_bounds(stream: MeshStream) -> tuple[np.ndarray, np.ndarray]:
    """(lowest, highest) (3,) float64 corner of the vertices' bounding box, from one pass;
    (zeros, zeros) for a stream without vertices."""
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    for vertices, _, _ in stream.vertex_blocks():
        if len(vertices):
            vertices = np.asarray(vertices, dtype=np.float64)
            lowest, highest = bounds(vertices)
            np.minimum(low, lowest, out=low)
            np.maximum(high, highest, out=high)
    if stream.vertex_count == 0:
        return np.zeros(3), np.zeros(3)
    return low, high


def vertex_table(mesh: SurfaceMesh | MeshStream) -> np.ndarray:
    """All vertex positions (M, 3) float64, for a writer whose faces name vertices anywhere
    in the mesh (STL): the arrays of a SurfaceMesh as they are, or one pass of a stream
    copied into a table of 24 bytes per vertex (positions only: no normals, colours or faces)."""
    if isinstance(mesh, SurfaceMesh):
        return np.asarray(mesh.vertices, dtype=np.float64)
    table = np.empty((mesh.vertex_count, 3))
    start = 0
    for vertices, _, _ in mesh.vertex_blocks():
        table[start:start + len(vertices)] = vertices
        start += len(vertices)
    return table


# --------------------------------------------------------------------- size limits
INT32_MOST = 2**31 - 1
"""The largest signed 32-bit integer: the most elements a count or index read as C int holds."""
UINT32_MOST = 2**32 - 1
"""The largest unsigned 32-bit integer."""


@dataclass(frozen=True)
class MeshSize:
    """What a writer's size limit looks at, known before the mesh is computed: vertex
    and face counts, whether vertices carry normals, colour channels (a MeshStream has
    the same attributes, so each format's limit reads either)."""

    vertex_count: int
    face_count: int
    has_normals: bool = True
    color_channels: int = 0


def too_many(count: int, what: str, most: int, why: str) -> str | None:
    """'`why`: `count` `what` are more than `most`', or None when count <= most: one
    clause of a format's size limit (each writer module defines its own)."""
    if count <= most:
        return None
    return f"{why}: {count:,} {what} are more than {most:,}"


def refuse_size(problem: str | None) -> None:
    """InputError with a format's size problem (None: nothing to refuse) and the remedy.
    An InputError, not a usage error: whether a level is too high depends on the input."""
    if problem is not None:
        raise InputError(f"{problem}; use a lower --level, or split the scan")
