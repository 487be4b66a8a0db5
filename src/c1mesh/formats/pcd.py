"""PCD (Point Cloud Library format, v0.6/v0.7): ascii, binary and binary_compressed.

Fields: x y z -> points; normal_x normal_y normal_z -> normals; rgb / rgba (a packed
0xAARRGGBB word stored as float or uint32) -> colors (N, 3) for rgb, (N, 4) for rgba;
everything else (curvature, intensity, label, ...) -> extra, a field with COUNT k > 1
as k columns name_0 .. name_{k-1}; padding fields named '_' are dropped. Organised
clouds (WIDTH x HEIGHT) are flattened row by row; NaN points are kept (the pipeline
drops and counts them). binary bodies are little-endian rows (array of structs);
binary_compressed bodies are LZF-compressed columns (struct of arrays), each field's
values for all points one after another.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.core.cloud import PointCloud
from c1mesh.core.errors import FormatError
from c1mesh.formats._common import NORMAL_NAMES, find_columns, loadtxt
from c1mesh.formats._limits import check_alloc, check_expansion
from c1mesh.formats.lzf import MAX_EXPANSION, LZFError, lzf_decompress

_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
MAX_HEADER_BYTES = 1 << 20
MAX_FIELDS = 10_000
_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8",
          ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8"}


@dataclass
class Header:
    """The parsed header: per-field names, numpy types and counts; point count; data kind."""

    names: list[str]
    types: list[str]
    counts: list[int]
    points: int
    data: str

    def dtype(self) -> np.dtype:
        """Little-endian row dtype; internal field names f0, f1, ... (PCD names may repeat)."""
        return np.dtype([(f"f{i}", "<" + t, (c,)) for i, (t, c) in enumerate(zip(self.types, self.counts))])


# ----------------------------------------------------------------------------- header
def _header_lines(data: bytes, name: str) -> tuple[dict[str, list[str]], int]:
    """Header keywords -> values up to and including DATA; return them and the body offset."""
    values: dict[str, list[str]] = {}
    offset = 0
    while "DATA" not in values:
        nl = data.find(b"\n", offset, MAX_HEADER_BYTES)
        if nl < 0:
            where = f" within its first {MAX_HEADER_BYTES} bytes" if len(data) > MAX_HEADER_BYTES else ""
            raise FormatError(f"PCD file '{name}' has no 'DATA' line{where}; the header is incomplete "
                              "or this is not a PCD file.")
        words, offset = data[offset:nl].decode("latin-1").split(), nl + 1
        if not words or words[0].startswith("#"):
            continue
        if words[0].upper() not in _KEYS:
            raise FormatError(f"'{name}' is not a valid PCD file: unknown header line {' '.join(words)[:60]!r}.")
        values[words[0].upper()] = words[1:]
    return values, offset


def _ints(values: dict[str, list[str]], key: str, name: str, default: list[int] | None = None) -> list[int]:
    if key not in values:
        if default is None:
            raise FormatError(f"PCD file '{name}' has no {key} line in its header.")
        return default
    try:
        if any(len(v) > 20 for v in values[key]):
            raise ValueError
        return [int(v) for v in values[key]]
    except ValueError:
        raise FormatError(f"PCD file '{name}' has a non-integer {key} line: {' '.join(values[key])!r}.") from None


def _one(values: dict[str, list[str]], key: str, name: str, default: int) -> int:
    """The single integer of header line `key`, or `default` when the line is absent."""
    found = _ints(values, key, name, [default])
    if len(found) != 1:
        raise FormatError(f"PCD file '{name}' needs exactly one number on its {key} line.")
    return found[0]


def _parse_header(data: bytes, name: str) -> tuple[Header, int]:
    """Parse and validate the header; return it and the offset of the body."""
    values, offset = _header_lines(data, name)
    names = values.get("FIELDS") or []
    if not names:
        raise FormatError(f"PCD file '{name}' has no FIELDS line in its header.")
    if len(names) > MAX_FIELDS:
        raise FormatError(f"PCD file '{name}' declares {len(names)} FIELDS, more than {MAX_FIELDS}.")
    sizes = _ints(values, "SIZE", name)
    kinds = [t.upper() for t in values.get("TYPE", [])]
    counts = _ints(values, "COUNT", name, [1] * len(names))
    if not len(names) == len(sizes) == len(kinds) == len(counts):
        raise FormatError(f"PCD file '{name}' has FIELDS, SIZE, TYPE and COUNT lines of different lengths.")
    bad = [f"{t}{s}" for t, s in zip(kinds, sizes) if (t, s) not in _TYPES]
    if bad:
        raise FormatError(f"PCD file '{name}' has unsupported field types {', '.join(bad)}.")
    width = _one(values, "WIDTH", name, 0)
    height = _one(values, "HEIGHT", name, 1)
    points = _one(values, "POINTS", name, width * height)
    if min(sizes + counts) < 1 or min(width, height, points) < 0:
        raise FormatError(f"PCD file '{name}' has a negative or zero size, count or point number in its header.")
    if max(counts) > 1 << 20:
        raise FormatError(f"PCD file '{name}' has a COUNT of {max(counts)} values per field; it is corrupt.")
    if "WIDTH" in values and points != width * height:
        raise FormatError(f"PCD file '{name}' has POINTS {points}, but WIDTH x HEIGHT is {width * height}.")
    kind = (values["DATA"] or [""])[0].lower()
    if kind not in ("ascii", "binary", "binary_compressed"):
        raise FormatError(f"PCD file '{name}' has unknown DATA kind {kind!r}; expected ascii, binary or binary_compressed.")
    types = [_TYPES[t, s] for t, s in zip(kinds, sizes)]
    return Header(names, types, counts, points, kind), offset


def check_pcd_head(head: bytes, name: str) -> None:
    """FormatError unless `head` (the first bytes of a stream) starts like a PCD header:
    comment lines, then a line starting with a PCD keyword (a head of comments passes)."""
    lines = head.split(b"\n")
    for number, line in enumerate(lines, start=1):
        words = line.decode("latin-1").split()
        if not words or words[0].startswith("#"):
            continue
        if words[0].upper() in _KEYS:
            return
        if number == len(lines) and len(words) == 1 and any(k.startswith(words[0].upper()) for k in _KEYS):
            return   # a keyword cut off where the head ends
        raise FormatError(f"'{name}' is not a PCD file: it does not start with a PCD header line.")


# ----------------------------------------------------------------------------- bodies
def _truncated(name: str, header: Header, detail: str) -> FormatError:
    return FormatError(f"PCD file '{name}' is truncated: {detail} for the {header.points} points the header promises.")


#: Bytes per point of what the reader builds besides the body: xyz and normals as float64.
_KEPT_BYTES_PER_POINT = 48


def _binary(data: bytes, offset: int, header: Header, name: str) -> list[np.ndarray]:
    """Per-field (N, count) arrays of an uncompressed binary body (rows of structs)."""
    dtype = header.dtype()
    if len(data) - offset < header.points * dtype.itemsize:
        raise _truncated(name, header, f"{len(data) - offset} data bytes, {header.points * dtype.itemsize} needed")
    rows = np.frombuffer(data, dtype, header.points, offset)
    return [rows[f] for f in dtype.names]


def _compressed(data: bytes, offset: int, header: Header, name: str) -> list[np.ndarray]:
    """Per-field (N, count) arrays of an LZF-compressed body (one column after another)."""
    if len(data) - offset < 8:
        raise _truncated(name, header, "no compressed-size words")
    packed, unpacked = np.frombuffer(data, "<u4", 2, offset).tolist()
    itemsize = header.dtype().itemsize
    if unpacked != header.points * itemsize:
        raise FormatError(f"PCD file '{name}' promises {unpacked} uncompressed bytes, not {header.points * itemsize}.")
    if unpacked > MAX_EXPANSION * packed:  # LZF expands at most 88-fold (3 bytes -> 264)
        raise FormatError(f"PCD file '{name}' claims {unpacked} bytes from {packed} compressed ones; it is corrupt.")
    if len(data) - offset - 8 < packed:
        raise _truncated(name, header, f"{len(data) - offset - 8} compressed bytes, {packed} needed")
    check_expansion(packed, unpacked, name, f"the compressed body of {header.points} points")
    check_alloc(unpacked + header.points * _KEPT_BYTES_PER_POINT, name,
                f"decoding the {header.points} compressed points")
    try:
        raw = lzf_decompress(data[offset + 8: offset + 8 + packed], unpacked) if unpacked else b""
    except LZFError as exc:
        raise FormatError(f"PCD file '{name}' has corrupt compressed data: {exc}.") from None
    columns, start = [], 0
    for t, c in zip(header.types, header.counts):
        col = np.frombuffer(raw, "<" + t, header.points * c, start).reshape(header.points, c)
        columns.append(col)
        start += col.nbytes
    return columns


def _ascii(data: bytes, offset: int, header: Header, name: str) -> list[np.ndarray]:
    """Per-field (N, count) arrays of an ascii body; float fields stay float64 (the text's precision)."""
    if header.points * sum(header.counts) * 2 > len(data) - offset + 1:   # a digit and a separator per value
        raise _truncated(name, header, f"{len(data) - offset} data bytes")
    lines = [ln for ln in data[offset:].decode("latin-1").splitlines() if ln.strip()]
    if len(lines) < header.points:
        raise _truncated(name, header, f"{len(lines)} data lines")
    width = sum(header.counts)
    try:
        table = loadtxt(lines[: header.points], comments=None)
    except ValueError as exc:
        raise FormatError(f"PCD file '{name}' has a malformed ascii data line: {exc}.") from None
    if header.points and table.shape[1] != width:
        raise FormatError(f"PCD file '{name}' has {table.shape[1]} values per ascii data line, but its "
                          f"FIELDS and COUNT lines describe {width}.")
    table = table.reshape(-1, width)
    columns, start = [], 0
    for field, t, c in zip(header.names, header.types, header.counts):
        col = table[:, start:start + c]
        if field.lower() in ("rgb", "rgba"):
            col = _ascii_packed_color(col)
        elif t[0] != "f":
            col = col.astype(t)
        columns.append(col)
        start += c
    return columns


def _ascii_packed_color(col: np.ndarray) -> np.ndarray:
    """Packed colours in ascii: PCL writes the uint32 word; old writers wrote the float."""
    finite = col[np.isfinite(col)]
    if np.all(finite == np.floor(finite)) and np.all(finite >= 0):
        return np.nan_to_num(col).astype(np.uint32)
    return col.astype(np.float32).view(np.uint32)


# ----------------------------------------------------------------------------- fields
def _unpack_colors(word: np.ndarray, with_alpha: bool) -> np.ndarray:
    """(N,) packed 0xAARRGGBB (float32 bits or integers) -> (N, 3|4) uint8 r, g, b[, a]."""
    word = word.view(np.uint32) if word.dtype == np.float32 else word.astype(np.uint32)
    shifts = (16, 8, 0, 24) if with_alpha else (16, 8, 0)
    return np.column_stack([(word >> s) & 0xFF for s in shifts]).astype(np.uint8)


def _cloud(header: Header, columns: list[np.ndarray], name: str) -> PointCloud:
    """Split the per-field columns into PointCloud fields."""
    scalars = {n: columns[i][:, 0] for i, n in enumerate(header.names) if header.counts[i] == 1}
    order = list(scalars)
    xyz = find_columns(order, (("x",), ("y",), ("z",)))
    if None in xyz:
        raise FormatError(f"PCD file '{name}' has no x, y and z fields.")
    def take(idx: list[int]) -> np.ndarray:
        """(N, 3) float64 of three scalar fields, filled column by column (no float32 stack)."""
        out = np.empty((header.points, 3))
        for j, i in enumerate(idx):
            out[:, j] = scalars[order[i]]
        return out

    cloud = PointCloud(points=take(xyz))
    used = {order[i] for i in xyz}
    nrm = find_columns(order, NORMAL_NAMES)
    if None not in nrm:
        cloud.normals = take(nrm)
        used |= {order[i] for i in nrm}
    packed = next((n for n in order if n.lower() in ("rgb", "rgba")), None)
    if packed is not None and scalars[packed].dtype.itemsize == 4:
        cloud.colors = _unpack_colors(scalars[packed], packed.lower() == "rgba")
        used.add(packed)
    cloud.extra = _extra(header, columns, used)
    return cloud


def _extra(header: Header, columns: list[np.ndarray], used: set[str]) -> dict[str, np.ndarray]:
    """Every field not used above, by name (name_i for COUNT > 1), '_' padding dropped."""
    extra = {}
    for n, c, col in zip(header.names, header.counts, columns):
        if n in used or n == "_":
            continue
        for j in range(c):
            extra[n if c == 1 else f"{n}_{j}"] = np.ascontiguousarray(col[:, j], dtype=col.dtype.newbyteorder("="))
    return extra


def read_pcd(data: bytes, name: str) -> PointCloud:
    """Read a PCD file held in `data` (`name` is for messages)."""
    header, offset = _parse_header(data, name)
    if header.data != "binary_compressed":   # (the compressed body checks its decoded size)
        check_alloc(len(data) + header.points * _KEPT_BYTES_PER_POINT, name,
                    f"decoding the {header.points} points")
    body = {"ascii": _ascii, "binary": _binary, "binary_compressed": _compressed}[header.data]
    cloud = _cloud(header, body(data, offset, header, name), name)
    _organisation(cloud, data, name)
    return cloud


# ----------------------------------------------------------------------------- organisation
def _organisation(cloud: PointCloud, data: bytes, name: str) -> None:
    """Set cloud.grid_shape from WIDTH x HEIGHT (HEIGHT > 1) and cloud.viewpoint from VIEWPOINT."""
    values, _ = _header_lines(data, name)
    width, height = _one(values, "WIDTH", name, 0), _one(values, "HEIGHT", name, 1)
    if height > 1 and width * height == len(cloud):
        cloud.grid_shape = (height, width)
    if "VIEWPOINT" in values:
        try:
            viewpoint = np.array([float(v) for v in values["VIEWPOINT"]])
        except ValueError:
            raise FormatError(f"PCD file '{name}' has a non-numeric VIEWPOINT line.") from None
        if viewpoint.shape != (7,) or not np.isfinite(viewpoint).all():
            raise FormatError(f"PCD file '{name}' needs 7 finite numbers on its VIEWPOINT line (x y z qw qx qy qz).")
        cloud.viewpoint = viewpoint
