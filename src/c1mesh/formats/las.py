"""LAS / LAZ airborne LiDAR via laspy (imported only when such a file is read).

Points are the scaled coordinates (las.x/y/z, file units, float64). Classification
codes go to `classification`. RGB (16-bit in LAS) becomes uint8 (>> 8 when any value
exceeds 255); point formats that carry RGB fields which are all zero are treated as
having no colours. Extra-bytes dimensions named like normals (nx / normal_x ...) become
normals. Other dimensions (intensity, gps_time, ...) are not kept: the fit never uses
them, and copying them would multiply the memory a tile needs.

The body is decoded in chunks (laspy's chunk iterator) and a `classes` filter is
applied per chunk, so memory holds the compressed file plus the kept points only. A
`bounds` box is applied per chunk too; a COPC file (c1mesh.formats.copc) then decodes
only the octree nodes that meet the box.
Every header count is checked against the file size (and, for LAZ, the chunk table)
before laspy allocates anything.
"""
from __future__ import annotations

import contextlib
import io
import mmap
import struct
from typing import IO, Callable, Union

import numpy as np

from c1mesh.core.cloud import PointCloud
from c1mesh.core.crs import las_crs
from c1mesh.core.errors import DependencyError, FormatError, InputError
from c1mesh.formats._common import NORMAL_NAMES, colors_to_uint8, find_columns
from c1mesh.formats._limits import check_alloc
from c1mesh.formats.copc import Copc, header_meets, inside, is_copc_header, laspy_module, laz_backend, lazrs_module

Buffer = Union[bytes, "mmap.mmap"]   # anything with len(), slicing and the buffer protocol
_INSTALL = 'pip install "laspy[lazrs]"'
_RGB = ("red", "green", "blue")


def _laspy():
    """Import laspy or raise DependencyError with the install command."""
    try:
        return laspy_module()
    except ImportError as exc:
        raise DependencyError(f"Reading LAS/LAZ files needs laspy: {_INSTALL}.") from exc


def _is_compressed(data: bytes) -> bool:
    """LAZ sets bit 7 (or 6) of the point data format id, byte 104 of the LAS header."""
    return len(data) > 104 and data[:4] == b"LASF" and bool(data[104] & 0xC0)


def _open(data: Buffer, name: str, open_stream: Callable[[], IO[bytes]]):
    """A laspy reader over a fresh stream of the file, after the header checks on `data`."""
    laspy = _laspy()
    if _is_compressed(data) and not laspy.LazBackend.detect_available():
        raise DependencyError(f"Reading the LAZ file '{name}' needs a LAZ backend: {_INSTALL}.")
    _check_header(data, name)
    with laspy_errors(name):
        reader = laspy.open(open_stream(), decompression_selection=_wanted_fields(),
                            laz_backend=laz_backend())
        try:
            _check_length(reader.header, len(data), name)
            _check_laz_chunks(data, reader.header, name, open_stream)
        except BaseException:
            reader.close()
            raise
        return reader


def _wanted_fields():
    """The LAZ fields the reader decodes: xyz, classification, RGB and extra bytes (normals)."""
    selection = _laspy().DecompressionSelection
    return (selection.XY_RETURNS_CHANNEL | selection.Z | selection.CLASSIFICATION
            | selection.RGB | selection.ALL_EXTRA_BYTES)


@contextlib.contextmanager
def laspy_errors(name: str):
    """Turn laspy's and lazrs's exceptions into FormatError / DependencyError naming the file."""
    try:
        yield
    except (InputError, DependencyError):
        raise
    except MemoryError:
        raise FormatError(f"LAS/LAZ file '{name}' cannot be read: out of memory while decoding its points "
                          "(the header's point count is probably corrupt).") from None
    except (KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except BaseException as exc:  # laspy: LaspyException, ValueError, struct errors; lazrs: a Rust panic
        text = str(exc).strip() or type(exc).__name__
        if "LazBackend" in text or "lazrs" in text.lower() and "backend" in text.lower():
            raise DependencyError(f"Reading the LAZ file '{name}' needs a LAZ backend: {_INSTALL}.") from exc
        raise FormatError(f"LAS/LAZ file '{name}' cannot be read: {' '.join(text.split())}.") from exc


def _check_header(data: Buffer, name: str) -> None:
    """Sanity-check the public header block before laspy sees it.

    laspy trusts the header's sizes and counts; a corrupt one can make it try to allocate
    tens of gigabytes, so implausible values are rejected here as FormatError.
    """
    if data[:4] != b"LASF":
        raise FormatError(f"'{name}' is not a LAS/LAZ file: it does not start with the 'LASF' signature.")
    if len(data) < 227:
        raise FormatError(f"LAS file '{name}' is truncated: {len(data)} bytes, shorter than a LAS header.")
    major, minor = data[24], data[25]
    header_size, offset, n_vlrs = struct.unpack_from("<HII", data, 94)
    problems = [
        (major != 1 or minor > 4, f"version {major}.{minor} is not LAS 1.0-1.4"),
        (not 227 <= header_size <= len(data), f"header size {header_size} is impossible"),
        (not header_size <= offset <= len(data), f"point data offset {offset} lies outside the file"),
        (n_vlrs * 54 > offset - header_size, f"{n_vlrs} variable-length records cannot fit before the points"),
        ((data[104] & 0x3F) > 10, f"point format {data[104] & 0x3F} does not exist"),
        *_evlr_problems(data, major, minor, header_size, offset),
    ]
    for bad, what in problems:
        if bad:
            raise FormatError(f"LAS file '{name}' has a corrupt header: {what}.")


def _evlr_problems(data: bytes, major: int, minor: int, header_size: int, offset: int) -> list[tuple[bool, str]]:
    """LAS 1.4 extended VLRs (start u64 at byte 235, count u32 at 243) must lie in the file.

    Each EVLR has a 60-byte header, so the count is bounded by the bytes after its start;
    a count of 0xFFFFFFFF would otherwise make laspy loop over billions of records.
    """
    if (major, minor) < (1, 4) or header_size < 247:
        return []
    start, count = struct.unpack_from("<QI", data, 235)
    if count == 0:
        return []
    return [(not offset <= start <= len(data), f"extended VLRs start at byte {start}, outside the file"),
            (count * 60 > len(data) - min(start, len(data)),
             f"{count} extended VLRs cannot fit in the {len(data) - min(start, len(data))} bytes after their start")]


def _check_length(header, size: int, name: str) -> None:
    """FormatError when an uncompressed body is shorter than the header's point count needs.

    Checked up front because laspy only logs a truncated LAS body and returns fewer points,
    and would allocate memory for an absurd point count before noticing a LAZ body is short.
    """
    if header.are_points_compressed:
        if header.point_count * header.point_format.size > _MAX_LAZ_RATIO * size + (1 << 20):
            raise FormatError(f"LAZ file '{name}' claims {header.point_count} points, far more than {size} bytes can hold.")
        return
    need = header.offset_to_point_data + header.point_count * header.point_format.size
    if size < need:
        raise FormatError(
            f"LAS file '{name}' is truncated: {size} bytes, but its {header.point_count} points need {need}."
        )


def _check_laz_chunks(data: Buffer, header, name: str, open_stream: Callable[[], IO[bytes]]) -> None:
    """FormatError when a LAZ chunk table is implausible.

    The LAZ decompressor (lazrs) sizes its buffers from the chunk table at the end of the
    file; a corrupt table makes it abort the whole process on a failed multi-gigabyte
    allocation, so the table is read and checked here first.
    """
    vlr = next((v for v in header.vlrs if type(v).__name__ == "LasZipVlr"), None)
    if vlr is None or len(data) < header.offset_to_point_data + 8:
        return  # lazrs itself reports these
    table_at = struct.unpack_from("<q", data, header.offset_to_point_data)[0]
    if not header.offset_to_point_data < table_at <= len(data) - 8:
        return  # no table (streamed writer) or one lazrs cannot reach: it reports that itself
    n_chunks = struct.unpack_from("<I", data, table_at + 4)[0]
    corrupt = FormatError(f"LAZ file '{name}' has a corrupt chunk table.")
    if n_chunks > max(header.point_count, 1) or n_chunks > table_at - header.offset_to_point_data:
        raise corrupt  # every chunk holds at least one point and one byte before the table
    lazrs = lazrs_module()
    with open_stream() as source:
        source.seek(header.offset_to_point_data)
        try:
            chunks = lazrs.read_chunk_table(source, lazrs.LazVlr(vlr.record_data))
        except Exception as exc:  # lazrs.LazrsError and I/O errors on a cut table
            raise corrupt from exc
    if sum(nbytes for _, nbytes in chunks) > len(data) - header.offset_to_point_data:
        raise corrupt
    if header.point_count > sum(npoints for npoints, _ in chunks):
        raise FormatError(f"LAZ file '{name}' claims {header.point_count} points, but its chunk table holds "
                          f"{sum(npoints for npoints, _ in chunks)}.")


#: Bytes per point of what the reader keeps: xyz float64, classification, rgb, normals.
_KEPT_BYTES_PER_POINT = 24 + 1 + 3 + 24
#: Record bytes per compressed byte a LAZ file may claim. Real tiles compress 5-10x; 200x
#: leaves room for very repetitive data while refusing headers that promise gigabytes.
_MAX_LAZ_RATIO = 200
_CHUNK = 1 << 20   # points decoded at a time


def read_las(data: Buffer, name: str, classes=None,
             open_stream: Callable[[], IO[bytes]] | None = None, bounds=None) -> PointCloud:
    """Read a LAS or LAZ file whose bytes are `data` (`name` is for messages).

    `data` may be a memory map of the file (read_cloud maps regular files, so the body is
    never copied into memory) and `open_stream` then opens the file again for laspy;
    by default the stream is a BytesIO over `data`. `classes`: classification codes to
    keep (None keeps all), applied per decoded chunk; the kept points are checked against
    the reading budget as they accumulate. `bounds`: keep only the points in this closed
    x/y box (formats.copc.Box, world units), in file order; a COPC file then decodes only
    the octree nodes that meet the box, a file whose header extent misses it nothing.
    """
    open_stream = open_stream or (lambda: io.BytesIO(data))
    keep = None if classes is None else np.asarray(list(classes), dtype=np.int64)
    with _open(data, name, open_stream) as reader, laspy_errors(name), \
            _point_chunks(reader, data, name, open_stream, bounds) as (chunks, expected):
        if keep is None and bounds is None:
            check_alloc(reader.header.point_count * _KEPT_BYTES_PER_POINT, name,
                        f"the header's {reader.header.point_count} points")
        crs = las_crs(reader.header)
        kept = 0
        dims = list(reader.header.point_format.dimension_names)
        nrm = find_columns(dims, NORMAL_NAMES)
        has_rgb = all(c in dims for c in _RGB)
        parts: dict[str, list[np.ndarray]] = {"points": [], "classification": [], "rgb": [], "normals": []}
        decoded, in_box, found = 0, 0, set()
        for chunk in chunks:
            decoded += len(chunk)
            classification = np.asarray(chunk.classification)
            box = None if bounds is None else inside(np.asarray(chunk.x), np.asarray(chunk.y), bounds)
            in_region = classification if box is None else classification[box]
            rows = _rows(classification, keep, box)
            in_box += len(in_region)
            found.update(np.unique(in_region).tolist())
            take = (lambda a: np.asarray(a)) if rows is None else (lambda a: np.asarray(a)[rows])  # noqa: E731
            parts["points"].append(np.column_stack([take(chunk.x), take(chunk.y), take(chunk.z)]).astype(np.float64))
            parts["classification"].append(take(chunk.classification).copy())
            kept += len(parts["classification"][-1])
            check_alloc(kept * _KEPT_BYTES_PER_POINT, name, f"the {kept} points kept so far")
            if has_rgb:
                parts["rgb"].append(np.column_stack([take(chunk[c]) for c in _RGB]))
            if None not in nrm:
                parts["normals"].append(np.column_stack([take(chunk[dims[i]]) for i in nrm]).astype(np.float64))
        if decoded != expected:
            raise FormatError(f"LAS/LAZ file '{name}' has {decoded} points, not the "
                              f"{expected} its {'hierarchy' if bounds is not None else 'header'} says.")
    cloud = _assemble(parts)
    cloud.crs = crs
    if keep is not None and in_box and not len(cloud):
        raise no_class_error(keep.tolist(), found, bounds is not None)
    return cloud


def no_class_error(classes: list[int], found: set[int], bounded: bool) -> InputError:
    """The error of a read whose points (inside --bounds when bounded) hold none of the
    classification codes `classes`: it lists the codes `found` instead. The tiled fit's
    reader (c1mesh.survey.inputs.las_chunks) raises the same."""
    return InputError(f"no points of class {list(classes)}; the file has classes {sorted(found)[:20]}"
                      + (" inside the bounds" if bounded else ""))


def _rows(classification: np.ndarray, keep: np.ndarray | None, box: np.ndarray | None) -> np.ndarray | None:
    """(m,) bool: a chunk's points of the kept classes (keep) inside the bounds (box: (m,)
    bool), or None when every point is kept."""
    rows = None if keep is None else np.isin(classification, keep)
    if box is not None:
        rows = box if rows is None else rows & box
    return rows


@contextlib.contextmanager
def _point_chunks(reader, data: Buffer, name: str, open_stream: Callable[[], IO[bytes]], bounds):
    """(point records to decode, how many points they hold): the whole body by laspy's
    chunk iterator; with bounds, nothing when the header's extent misses the box, only
    the octree nodes meeting the box for a COPC file, else the whole body (filtered by
    the caller)."""
    header = reader.header
    if bounds is None:
        yield reader.chunk_iterator(_CHUNK), header.point_count
    elif not header_meets(header, bounds):
        yield iter(()), 0
    elif is_copc_header(header) and header.are_points_compressed:
        with Copc(open_stream, name, len(data)) as copc:
            if copc.complete:
                nodes = copc.nodes(bounds)
                yield copc.records(nodes, _CHUNK, _wanted_fields()), sum(n.point_count for n in nodes)
            else:      # a node the hierarchy does not reach: only the chunk table has every point
                yield reader.chunk_iterator(_CHUNK), header.point_count
    else:
        yield reader.chunk_iterator(_CHUNK), header.point_count


def _assemble(parts: dict[str, list[np.ndarray]]) -> PointCloud:
    """One PointCloud from the per-chunk arrays (empty parts give empty arrays)."""
    join = lambda key, shape, dtype: np.concatenate(parts[key]) if parts[key] else np.zeros(shape, dtype)  # noqa: E731
    cloud = PointCloud(points=join("points", (0, 3), np.float64))
    cloud.classification = join("classification", (0,), np.uint8)
    if parts["rgb"]:
        rgb = join("rgb", (0, 3), np.uint16)
        cloud.colors = colors_to_uint8(rgb) if rgb.any() else None
    if parts["normals"]:
        cloud.normals = join("normals", (0, 3), np.float64)
    return cloud


def read_las_records(path: str) -> "laspy.LasData":
    """Every point record of the LAS/LAZ file at `path`, with all its dimensions (laspy's
    LasData), after the same header, length and chunk-table checks as read_las; for
    rewriting a file with new classes (`c1mesh ground`). Errors name the file."""
    name = str(path)
    try:
        handle = open(path, "rb")
    except OSError as exc:
        raise InputError(f"cannot read '{name}': {exc.strerror or exc}") from None
    with handle, contextlib.ExitStack() as stack:
        size = handle.seek(0, io.SEEK_END)
        data = b"" if size == 0 else stack.enter_context(mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ))
        if not data:
            raise FormatError(f"'{name}' is empty, not a LAS/LAZ file.")
        with _open(data, name, lambda: open(path, "rb")) as reader, laspy_errors(name):
            header = reader.header
            check_alloc(header.point_count * header.point_format.size, name,
                        f"the header's {header.point_count} point records")
            return reader.read()


def write_las_records(records, handle: IO[bytes], compress: bool, name: str) -> None:
    """Write laspy LasData `records` to the binary file `handle`: LAZ when `compress`."""
    with laspy_errors(name):
        records.write(handle, do_compress=compress, laz_backend=laz_backend() if compress else None)
