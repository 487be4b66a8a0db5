"""Wavefront OBJ: read `v`/`vn` lines as a point cloud, write a triangle mesh.

A point-cloud export usually has one `vn` per `v`, in the same order; then those are the
normals. Otherwise normals are taken from the `v//vn` pairs of the faces (vertices no
face mentions get NaN normals); without either, normals are None. `v x y z r g b`
colours (floats 0..1) become uint8. Everything else (faces, groups, materials) is ignored.
"""
from __future__ import annotations

import re
from typing import IO

import numpy as np

from c1mesh.core.cloud import MeshStream, PointCloud, SurfaceMesh
from c1mesh.core.errors import FormatError
from c1mesh.formats._background import background_writes
from c1mesh.formats._blocks import (INT32_MOST, TEXT_ROWS, as_stream, face_chunks, refuse_size, text_rows, too_many,
                                    vertex_chunks)
from c1mesh.formats._common import colors_to_uint8, decode_text, is_number, loadtxt

_KEYWORD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def _group_lines(text: str, name: str) -> dict[str, list[tuple[int, str, int, int]]]:
    """Lines by keyword: (line number, rest of line, #v before it, #vn before it)."""
    groups: dict[str, list[tuple[int, str, int, int]]] = {"v": [], "vn": [], "f": []}
    for number, line in enumerate(text.splitlines(), start=1):
        parts = line.split(None, 1)
        if not parts or parts[0].startswith("#"):
            continue
        key = parts[0]
        if not _KEYWORD.match(key):
            raise FormatError(f"OBJ file '{name}' line {number} does not start with an OBJ keyword: {line[:40]!r}.")
        if key in groups:
            groups[key].append((number, parts[1] if len(parts) > 1 else "", len(groups["v"]), len(groups["vn"])))
    return groups


def _numbers(rows: list[tuple[int, str, int, int]], name: str, widths: tuple[int, ...]) -> np.ndarray:
    """Parse the numeric rest of each row into an (n, w) float64 table, w in `widths`."""
    if not rows:
        return np.zeros((0, widths[0]))
    try:
        table = loadtxt([r[1] for r in rows], comments="#")
    except ValueError:
        table = None
    if table is not None and table.shape[1] in widths:
        return table
    for number, rest, _, _ in rows:  # slow path only to name the offending line
        words = rest.split("#")[0].split()
        if len(words) not in widths or not all(is_number(w) for w in words):
            raise FormatError(f"OBJ file '{name}' line {number} needs {' or '.join(map(str, widths))} numbers: {rest!r}.")
    raise FormatError(f"OBJ file '{name}' mixes vertex lines of different lengths.")


def _normals_from_faces(faces: list[tuple[int, str, int, int]], vn: np.ndarray, n: int, name: str) -> np.ndarray | None:
    """(n, 3) normals from `v//vn` face corners, NaN where no face names one; None if none do."""
    normals = np.full((n, 3), np.nan)
    found = False
    for number, rest, nv, nvn in faces:
        for corner in rest.split():
            parts = corner.split("/")
            if len(parts) < 3 or not parts[2]:
                continue
            try:
                vi, ni = int(parts[0]), int(parts[2])
                normals[vi - 1 if vi > 0 else nv + vi] = vn[ni - 1 if ni > 0 else nvn + ni]
            except (ValueError, IndexError):
                raise FormatError(f"OBJ file '{name}' line {number} has a bad face corner {corner!r}.") from None
            found = True
    return normals if found else None


def read_obj(data: bytes, name: str) -> PointCloud:
    """Read the vertices (with colours and normals where present) of an OBJ file."""
    groups = _group_lines(decode_text(data, name, "OBJ"), name)
    if not groups["v"]:
        raise FormatError(f"OBJ file '{name}' has no 'v' vertex lines.")
    v = _numbers(groups["v"], name, (3, 4, 6))
    vn = _numbers(groups["vn"], name, (3,))
    colors = colors_to_uint8(v[:, 3:6]) if v.shape[1] == 6 else None
    if len(vn) == len(v):
        normals = vn
    elif len(vn):
        normals = _normals_from_faces(groups["f"], vn, len(v), name)
    else:
        normals = None
    return PointCloud(points=np.ascontiguousarray(v[:, :3]), normals=normals, colors=colors)


def obj_size_problem(size) -> str | None:
    """Why an OBJ cannot hold a mesh of size.vertex_count vertices (a _blocks.MeshSize or
    MeshStream), or None.

    OBJ has no counts, and its specification gives its 1-based vertex references no
    width; but readers in wide use (tinyobjloader, Assimp) parse them into
    32-bit ints, so the last vertex must be numbered at most 2³¹ − 1. Faces are not
    counted or referred to: no limit.
    """
    return too_many(size.vertex_count, "vertices", INT32_MOST,
                    "OBJ face lines refer to vertices by numbers read as 32-bit ints")


def write_obj(mesh: SurfaceMesh | MeshStream, f: IO[bytes], ascii: bool = True) -> None:
    """Write `mesh` as OBJ text: `v` with round-trip (repr) precision, `vn`, 1-based faces.

    Colours go on the `v` lines as floats 0..1 (a widely read extension; alpha is dropped).
    Written block by block (formats/_blocks.py), so memory stays a few blocks of text; the
    `vn` lines follow all `v` lines, so a mesh with normals takes a second vertex pass.
    A mesh beyond `obj_size_problem` is refused (InputError) before a byte is written.
    """
    stream = as_stream(mesh)
    refuse_size(obj_size_problem(stream))
    with background_writes(f) as write:
        write(b"# written by c1mesh\n")
        for vertices, _, colors in vertex_chunks(stream, TEXT_ROWS):
            rows = np.asarray(vertices, dtype=np.float64).tolist()
            if colors is not None:
                rgb = (np.asarray(colors)[:, :3] / 255.0).tolist()
                rows = [v + c for v, c in zip(rows, rgb)]
            write(text_rows(rows, "v "))
        if stream.has_normals:
            for _, normals, _ in vertex_chunks(stream, TEXT_ROWS):
                write(text_rows(np.asarray(normals, dtype=np.float64).tolist(), "vn "))
        pattern = "f {0}//{0} {1}//{1} {2}//{2}\n" if stream.has_normals else "f {0} {1} {2}\n"
        for faces in face_chunks(stream, TEXT_ROWS):
            write("".join(pattern.format(*face) for face in (faces + 1).tolist()).encode("ascii"))
