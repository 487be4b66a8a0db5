"""Bounded reads of input paths and streams, before any format decodes them.

A regular file is refused from its size when it is larger than the reading budget; a FIFO,
a device or a pipe has its first 64 KiB checked to start like the format it is read as, then
is read piece by piece up to the cap of non-regular inputs (formats._limits). Used by the
registry (formats.read_cloud) and by the depth-image reader (formats.depth).
"""
from __future__ import annotations

import io
import os
import stat
from pathlib import Path
from typing import IO, Callable

from c1mesh.core.errors import FormatError, InputError
from c1mesh.core.outputs import LAS_FORMATS
from c1mesh.formats._common import decode_text
from c1mesh.formats._limits import budget, check_alloc, read_bounded
from c1mesh.formats.pcd import check_pcd_head


def is_stream(obj: object) -> bool:
    """True for file-like objects (stdin/stdout buffers, BytesIO), False for paths."""
    return not isinstance(obj, (str, bytes, os.PathLike)) and (hasattr(obj, "read") or hasattr(obj, "write"))


_TIFF_MAGIC = (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+")   # classic and BigTIFF, both byte orders
_IMAGE_MAGIC = {"png": (b"\x89PNG\r\n\x1a\n",), "tif": _TIFF_MAGIC, "tiff": _TIFF_MAGIC}


def head_check(key: str, name: str) -> Callable[[bytes], None]:
    """A check of the first bytes of a stream read as format `key`: FormatError unless they
    start like such a file (the readers repeat the full check), so that a stream of garbage
    (/dev/urandom as PLY, /dev/zero as text) fails after 64 KiB, not at the reading limit."""
    def check(head: bytes) -> None:
        if key == "ply" and not head.startswith((b"ply\n", b"ply\r\n")):
            raise FormatError(f"'{name}' is not a PLY file: it does not start with the 'ply' magic line.")
        if key == "pcd":
            check_pcd_head(head, name)
        if key in LAS_FORMATS and not head.startswith(b"LASF"):
            raise FormatError(f"'{name}' is not a LAS/LAZ file: it does not start with 'LASF'.")
        if key in ("xyz", "txt", "csv", "obj"):
            decode_text(head, name, "OBJ" if key == "obj" else "Point")
        if key in _IMAGE_MAGIC and not head.startswith(_IMAGE_MAGIC[key]):
            raise FormatError(f"'{name}' is not a {key.upper()} image: it does not start with its signature.")
    return check


def limit_of_stream(stream: IO[bytes]) -> int | None:
    """The reading budget for a stream that cannot be endless: a regular file (stdin
    redirected from a file) or a BytesIO, already in memory; None (the cap of non-regular
    inputs, formats._limits.stream_limit) for anything else (a pipe, a socket, a device)."""
    if isinstance(stream, io.BytesIO):
        return budget()
    try:
        info = os.fstat(stream.fileno())
    except (AttributeError, OSError, ValueError):   # io.UnsupportedOperation is an OSError
        return None
    return budget() if stat.S_ISREG(info.st_mode) else None


def read_path(path: Path, key: str | None = None) -> bytes:
    """All bytes of `path` within the reading budget; InputError for missing files and directories.

    A regular file larger than the budget is refused from its size; anything else (a FIFO,
    /dev/zero, a /dev/stdin that is a pipe) has its first 64 KiB checked to start like a
    file of format `key` (if given), then is read piece by piece and refused once it
    passes the limit of non-regular inputs (formats._limits.stream_limit: 256 MiB, or the
    budget with --memory).
    """
    try:
        info = path.stat()
    except FileNotFoundError:
        raise InputError(f"Input file '{path}' does not exist.") from None
    except OSError as exc:
        raise InputError(f"Cannot read input file '{path}': {exc.strerror or exc}.") from exc
    if stat.S_ISDIR(info.st_mode):
        raise InputError(f"Input path '{path}' is a directory, not a point file.")
    try:
        if stat.S_ISREG(info.st_mode):
            check_alloc(info.st_size, str(path), "reading the file")
            return path.read_bytes()
        with open(path, "rb") as stream:
            return read_bounded(stream, str(path), head_check=head_check(key, str(path)) if key else None)
    except OSError as exc:
        raise InputError(f"Cannot read input file '{path}': {exc.strerror or exc}.") from exc
