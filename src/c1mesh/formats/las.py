"""LAS / LAZ airborne LiDAR via laspy (imported only when such a file is read).

Points are the scaled coordinates (las.x/y/z, file units, float64). Classification
codes go to `classification`. RGB (16-bit in LAS) becomes uint8 (>> 8 when any value
exceeds 255); point formats that carry RGB fields which are all zero are treated as
having no colours. Extra-bytes dimensions named like normals (nx / normal_x ...) become
normals. Every other dimension (intensity, return_number, gps_time, ...) goes to extra.
"""
from __future__ import annotations

import io

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
    """laspy.read on the bytes; its errors become FormatError / DependencyError."""
    laspy = _laspy()
    if _is_compressed(data) and not laspy.LazBackend.detect_available():
        raise DependencyError(f"Reading the LAZ file '{name}' needs a LAZ backend: {_INSTALL}.")
    if not data.startswith(b"LASF"):
        raise FormatError(f"'{name}' is not a LAS/LAZ file: it does not start with the 'LASF' signature.")
    try:
        return laspy.read(io.BytesIO(data))
    except Exception as exc:  # laspy raises LaspyException, ValueError, struct errors, ...
        if "LazBackend" in str(exc) or "lazrs" in str(exc).lower():
            raise DependencyError(f"Reading the LAZ file '{name}' needs a LAZ backend: {_INSTALL}.") from exc
        raise FormatError(f"LAS/LAZ file '{name}' cannot be read: {exc}.") from exc


def read_las(data: bytes, name: str) -> PointCloud:
    """Read a LAS or LAZ file held in `data` (`name` is for messages)."""
    las = _read(data, name)
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
    return cloud
