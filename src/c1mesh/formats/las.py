"""LAS / LAZ airborne LiDAR via laspy (imported only when such a file is read).

Points are the scaled coordinates (las.x/y/z, file units, float64). Classification
codes go to `classification`. RGB (16-bit in LAS) becomes uint8 (>> 8 when any value
exceeds 255); point formats that carry RGB fields which are all zero are treated as
having no colours. Extra-bytes dimensions named like normals (nx / normal_x ...) become
normals. Every other dimension (intensity, return_number, gps_time, ...) goes to extra.
"""
from __future__ import annotations

import io
import struct

import numpy as np

from c1mesh.cloud import PointCloud
from c1mesh.errors import DependencyError, FormatError
from c1mesh.formats._common import NORMAL_NAMES, colors_to_uint8, find_columns

_INSTALL = 'pip install "laspy[lazrs]"'
_COORDS = {"X", "Y", "Z", "x", "y", "z"}
_RGB = ("red", "green", "blue")


def _laspy():
    """Import laspy or raise DependencyError with the install command."""
    try:
        import laspy
    except ImportError as exc:
        raise DependencyError(f"Reading LAS/LAZ files needs laspy: {_INSTALL}.") from exc
    return laspy


def _is_compressed(data: bytes) -> bool:
    """LAZ sets bit 7 (or 6) of the point data format id, byte 104 of the LAS header."""
    return len(data) > 104 and data[:4] == b"LASF" and bool(data[104] & 0xC0)


def _read(data: bytes, name: str):
    """laspy read of the bytes; its errors become FormatError / DependencyError."""
    laspy = _laspy()
    if _is_compressed(data) and not laspy.LazBackend.detect_available():
        raise DependencyError(f"Reading the LAZ file '{name}' needs a LAZ backend: {_INSTALL}.")
    _check_header(data, name)
    try:
        with laspy.open(io.BytesIO(data)) as reader:
            _check_length(reader.header, len(data), name)
            _check_laz_chunks(data, reader.header, name)
            return reader.read()
    except FormatError:
        raise
    except Exception as exc:  # laspy raises LaspyException, ValueError, struct errors, ...
        if "LazBackend" in str(exc) or "lazrs" in str(exc).lower():
            raise DependencyError(f"Reading the LAZ file '{name}' needs a LAZ backend: {_INSTALL}.") from exc
        raise FormatError(f"LAS/LAZ file '{name}' cannot be read: {exc}.") from exc


def _check_header(data: bytes, name: str) -> None:
    """Sanity-check the public header block before laspy sees it.

    laspy trusts the header's sizes and counts; a corrupt one can make it try to allocate
    tens of gigabytes, so implausible values are rejected here as FormatError.
    """
    if not data.startswith(b"LASF"):
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
    ]
    for bad, what in problems:
        if bad:
            raise FormatError(f"LAS file '{name}' has a corrupt header: {what}.")


def _check_length(header, size: int, name: str) -> None:
    """FormatError when an uncompressed body is shorter than the header's point count needs.

    Checked up front because laspy only logs a truncated LAS body and returns fewer points,
    and would allocate memory for an absurd point count before noticing a LAZ body is short.
    """
    if header.are_points_compressed:
        if header.point_count * header.point_format.size > 1000 * size + (1 << 20):
            raise FormatError(f"LAZ file '{name}' claims {header.point_count} points, far more than {size} bytes can hold.")
        return
    need = header.offset_to_point_data + header.point_count * header.point_format.size
    if size < need:
        raise FormatError(
            f"LAS file '{name}' is truncated: {size} bytes, but its {header.point_count} points need {need}."
        )


def _check_laz_chunks(data: bytes, header, name: str) -> None:
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
    import lazrs

    source = io.BytesIO(data)
    source.seek(header.offset_to_point_data)
    try:
        chunks = lazrs.read_chunk_table(source, lazrs.LazVlr(vlr.record_data))
    except Exception as exc:  # lazrs.LazrsError and I/O errors on a cut table
        raise corrupt from exc
    if sum(nbytes for _, nbytes in chunks) > len(data) - header.offset_to_point_data:
        raise corrupt


def read_las(data: bytes, name: str) -> PointCloud:
    """Read a LAS or LAZ file held in `data` (`name` is for messages)."""
    las = _read(data, name)
    if len(las.points) != las.header.point_count:
        raise FormatError(f"LAS/LAZ file '{name}' has {len(las.points)} points, not the {las.header.point_count} its header says.")
    dims = list(las.point_format.dimension_names)
    cloud = PointCloud(points=np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]).astype(np.float64))
    used = set(_COORDS)
    if "classification" in dims:
        cloud.classification = np.asarray(las.classification).copy()
        used.add("classification")
    if all(c in dims for c in _RGB):
        rgb = np.column_stack([np.asarray(las[c]) for c in _RGB])
        cloud.colors = colors_to_uint8(rgb) if rgb.any() else None
        used |= set(_RGB)
    nrm = find_columns(dims, NORMAL_NAMES)
    if None not in nrm:
        cloud.normals = np.column_stack([np.asarray(las[dims[i]]) for i in nrm]).astype(np.float64)
        used |= {dims[i] for i in nrm}
    cloud.extra = {d: np.asarray(las[d]).copy() for d in dims if d not in used}
    from c1mesh.crs import las_crs
    cloud.crs = las_crs(las.header)
    return cloud
