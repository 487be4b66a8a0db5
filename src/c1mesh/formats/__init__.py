"""Read point clouds and write meshes, one small module per format behind one registry.

`read_cloud` picks a reader by file extension (or `fmt`), loads the bytes once and hands
them to the format module; `write_mesh` picks a writer the same way and, for a path,
writes by the rules of c1mesh.core.outputs, so that a failed write never leaves a partial file.
Both also work on binary file objects (stdin / stdout), where `fmt` says the format.
"""
from __future__ import annotations

import io
import mmap
import os
from pathlib import Path
from typing import IO, Callable, Sequence, Union

import numpy as np

from c1mesh.core.cloud import MeshStream, PointCloud, SurfaceMesh
from c1mesh.core.crs import write_prj
from c1mesh.core.errors import FormatError, InputError
from c1mesh.formats._limits import read_bounded, reading_budget
from c1mesh.formats.copc import check_box, inside
from c1mesh.formats.depth import read_depth
from c1mesh.formats.las import read_las
from c1mesh.formats._blocks import MeshSize, refuse_size
from c1mesh.formats.meshes import (glb_size_problem, off_size_problem, stl_size_problem, write_glb, write_off,
                                   write_stl)
from c1mesh.formats.obj import obj_size_problem, read_obj, write_obj
from c1mesh.formats.pcd import read_pcd
from c1mesh.formats.ply import ply_size_problem, read_ply, write_ply
from c1mesh.formats.xyz import read_xyz
from c1mesh.formats.reading import head_check, is_stream, limit_of_stream, read_path
from c1mesh.core.outputs import INPUT_FORMATS, LAS_FORMATS, MESH_FORMATS, Outputs, atomic_output, format_key, mesh_format, plan_outputs

__all__ = ["read_cloud", "write_mesh", "check_output", "check_mesh_size", "MeshSize", "atomic_output",
           "SUPPORTED_INPUT", "SUPPORTED_OUTPUT"]

Source = Union[str, "os.PathLike[str]", IO[bytes]]

_READERS: dict[str, Callable[[bytes, str], PointCloud]] = {
    "ply": read_ply, "obj": read_obj, "xyz": read_xyz, "txt": read_xyz, "csv": read_xyz,
    "pcd": read_pcd, "las": read_las, "laz": read_las, "copc": read_las,
    "png": read_depth, "tif": read_depth, "tiff": read_depth,     # without intrinsics: an InputError asking for them
}
_WRITERS: dict[str, Callable[..., None]] = {
    "ply": write_ply, "obj": write_obj, "stl": write_stl, "off": write_off, "glb": write_glb,
}
#: Each writer's size limit, defined beside it: why the format cannot hold a mesh of a
#: MeshSize, or None (the writer refuses by it too; `check_mesh_size` asks before the work).
_SIZE_LIMITS: dict[str, Callable[[MeshSize], str | None]] = {
    "ply": ply_size_problem, "obj": obj_size_problem, "stl": stl_size_problem, "off": off_size_problem,
    "glb": glb_size_problem,
}
assert set(_SIZE_LIMITS) == set(_WRITERS), "every writer needs its size limit"
#: Input file extensions `read_cloud` understands (lower case, no dot).
SUPPORTED_INPUT: tuple[str, ...] = tuple(_READERS)
#: Output file extensions `write_mesh` understands (lower case, no dot).
SUPPORTED_OUTPUT: tuple[str, ...] = tuple(_WRITERS)
assert SUPPORTED_OUTPUT == MESH_FORMATS, "c1mesh.core.outputs.MESH_FORMATS must list the writers"
assert SUPPORTED_INPUT == INPUT_FORMATS, "c1mesh.core.outputs.INPUT_FORMATS must list the readers"


def _read_las_file(path: Path, classes: Sequence[int] | None, bounds=None) -> PointCloud:
    """A LAS/LAZ file through a memory map: laspy streams the body from the file in chunks,
    so memory holds the kept points, not the file."""
    name = str(path)
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                raise FormatError(f"Input '{name}' is empty.")
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data, np.errstate(all="ignore"):
                return read_las(data, name, classes=classes, open_stream=lambda: open(path, "rb"),
                                bounds=bounds)
    except OSError as exc:
        raise InputError(f"Cannot read input file '{path}': {exc.strerror or exc}.") from exc


def read_cloud(source: Source, fmt: str | None = None, classes: Sequence[int] | None = None,
               memory: int | str | None = None, bounds: Sequence[float] | None = None) -> PointCloud:
    """Read a point cloud from a path or a binary file object.

    The format comes from `fmt` if given, else from the path's extension (case-insensitive);
    for a file object `fmt` is required. Faces in the input are ignored. `classes` keeps
    only those classification codes while a LAS/LAZ file is decoded (other formats return
    every point; the caller filters). `memory` (bytes or a size such as '4G'; default half
    the RAM, at most 8 GiB) bounds the bytes read and decoded: a header or stream that
    needs more is refused before allocating; without `memory`, a device, pipe or stream
    (not a regular file, not a BytesIO) may deliver at most 256 MiB and a compressed PCD body may not expand more than 24-fold
    past 16 MiB (formats._limits), limits that an explicit `memory` lifts. `bounds`
    (xmin, ymin, xmax, ymax; world units, closed) keeps only the points in that x/y box,
    in file order: a COPC file decodes only the octree nodes that meet it
    (c1mesh.formats.copc), other LAS/LAZ are filtered chunk by chunk, other formats after
    reading. Raises InputError for missing/unreadable paths and unknown formats,
    FormatError for empty, malformed or over-budget files, DependencyError when an
    optional reader library is missing.
    """
    if bounds is not None:
        bounds = check_box(bounds)
    with reading_budget(memory):
        if is_stream(source):
            name = str(getattr(source, "name", "<stream>"))
            if fmt is None:
                raise InputError(f"Reading points from '{name}' needs an explicit format, one of {', '.join(SUPPORTED_INPUT)}.")
            key = format_key(fmt, name, SUPPORTED_INPUT, "input")
            try:
                data = read_bounded(source, name, limit_of_stream(source), head_check(key, name))
            except OSError as exc:
                raise InputError(f"Cannot read input stream '{name}': {exc.strerror or exc}.") from exc
        else:
            path = Path(source)
            name = str(path)
            key = format_key(fmt or path.suffix, name, SUPPORTED_INPUT, "input")
            if key in LAS_FORMATS and path.is_file():
                return _read_las_file(path, classes, bounds)
            data = read_path(path, key)
        if not data:
            raise FormatError(f"Input '{name}' is empty.")
        with np.errstate(all="ignore"):  # overflow / NaN in a body are data, not news
            if key in LAS_FORMATS:
                return read_las(data, name, classes=classes, bounds=bounds)
            return _in_box(_READERS[key](data, name), bounds)


def _in_box(cloud: PointCloud, bounds) -> PointCloud:
    """The cloud's points inside the closed x/y box (all of them for bounds None)."""
    if bounds is None:
        return cloud
    return cloud.subset(inside(cloud.points[:, 0], cloud.points[:, 1], bounds))


def _check_mesh(mesh: SurfaceMesh) -> None:
    """InputError unless the arrays have the shapes SurfaceMesh promises and faces index vertices."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"Mesh vertices must be an (M, 3) array, not shape {v.shape}.")
    if f.size and (f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer)):
        raise InputError(f"Mesh faces must be a (K, 3) integer array, not {f.dtype} of shape {f.shape}.")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(f"Mesh faces refer to vertex indices outside 0..{len(v) - 1}.")
    for label, arr, widths in (("vertex_normals", mesh.vertex_normals, (3,)), ("vertex_colors", mesh.vertex_colors, (3, 4))):
        if arr is not None and (np.ndim(arr) != 2 or len(arr) != len(v) or np.shape(arr)[1] not in widths):
            raise InputError(f"Mesh {label} must have one row of {' or '.join(map(str, widths))} values per vertex.")


def write_mesh(mesh: SurfaceMesh | MeshStream, target: Source, fmt: str | None = None,
               ascii: bool = False, crs: str | None = None, sidecar: bool = True) -> None:
    """Write `mesh` to a path or a binary file object.

    The format comes from `fmt` if given, else from the path's extension; a file object
    defaults to binary PLY. `ascii` selects ascii PLY (other formats have one encoding).
    A path is written by the rules of c1mesh.core.outputs: a regular file or new path to a
    temporary file beside it, renamed into place only when complete (an existing file's
    mode is kept); a character device or FIFO straight. Every format writes a MeshStream
    block by block, never assembling it (STL also holds the vertex positions: a face may
    name any vertex). `crs` (WKT) is written where the format has a place for it (PLY
    header comment, GLB asset extras) and, for a regular-file path of PLY/OBJ/STL/OFF, as an ESRI-WKT `.prj` sidecar (unless sidecar=False: a caller writing
    to a temporary name commits the sidecar itself). Raises InputError for unknown formats,
    missing or unwritable directories.
    """
    if isinstance(mesh, SurfaceMesh):
        _check_mesh(mesh)
    if is_stream(target):
        name = str(getattr(target, "name", "<stream>"))
        key = format_key(fmt or "ply", name, SUPPORTED_OUTPUT, "output")
        if isinstance(target, io.TextIOBase):
            target = getattr(target, "buffer", None)
            if target is None:
                raise InputError(f"Output stream '{name}' is in text mode; pass a binary stream such as sys.stdout.buffer.")
        _WRITERS[key](mesh, target, ascii=ascii, **_crs_argument(key, crs))
        target.flush()
        return
    (planned,) = plan_outputs([("output", target)])
    key = format_key(fmt or mesh_format(target, fmt, planned), str(target), SUPPORTED_OUTPUT, "output")
    with Outputs(deferred=False).open(planned) as f:
        _WRITERS[key](mesh, f, ascii=ascii, **_crs_argument(key, crs))
    if crs and sidecar and key in PRJ_SIDECAR and planned.kind == "atomic":
        write_prj(target, crs)


PRJ_SIDECAR = {"ply", "obj", "stl", "off"}
"""Formats whose CRS also goes to a `.prj` sidecar (ESRI WKT) beside the file."""


def _crs_argument(key: str, crs: str | None) -> dict:
    """The writer's crs keyword where its format stores a CRS itself."""
    return {"crs": crs} if crs and key in ("ply", "glb") else {}


def check_mesh_size(target: Source, fmt: str | None, size: MeshSize) -> None:
    """Raise InputError now if the mesh `write_mesh(..., target, fmt)` would write, of this
    size, is beyond its format's limit (32-bit counts and indices: each format's
    `*_size_problem`), so that a fit refuses before it refines. The format is chosen as
    write_mesh chooses it; the message names it, the count and the limit."""
    name = str(getattr(target, "name", "<stream>")) if is_stream(target) else str(target)
    key = fmt or ("" if is_stream(target) else Path(target).suffix)
    key = format_key(key if key.lstrip(".") else "ply", name, SUPPORTED_OUTPUT, "output")   # as mesh_format
    refuse_size(_SIZE_LIMITS[key](size))


def check_output(target: Source, fmt: str | None = None, inputs: tuple = ()) -> None:
    """Raise InputError now, before any work, if `write_mesh(..., target, fmt)` could not
    write there: unknown format, missing or unwritable directory, a directory or special
    file, or a path that is one of `inputs` (paths or streams; see c1mesh.core.outputs)."""
    if is_stream(target):
        format_key(fmt or "ply", str(getattr(target, "name", "<stream>")), SUPPORTED_OUTPUT, "output")
        return
    (planned,) = plan_outputs([("output", target)], inputs)
    format_key(fmt or mesh_format(target, fmt, planned), str(target), SUPPORTED_OUTPUT, "output")

