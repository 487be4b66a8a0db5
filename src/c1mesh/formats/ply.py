"""PLY (Stanford polygon format): read a point cloud, write a triangle mesh.

Reading takes the `vertex` element: x y z, optional normals (nx ny nz), optional colours
(red green blue [alpha]); every other vertex property goes to `extra`. Other elements
(faces, edges, ...) are skipped, wherever they are in the file, but their size is still
checked so that a truncated file is reported. Binary bodies are decoded with numpy
structured dtypes (no per-point Python work); ascii bodies with `np.loadtxt`.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field
from typing import IO

import numpy as np

from c1mesh.core.cloud import MeshStream, PointCloud, SurfaceMesh
from c1mesh.core.errors import FormatError
from c1mesh.core.crs import crs_from_ply_header, ply_comment
from c1mesh.formats._background import background_writes
from c1mesh.formats._blocks import (INT32_MOST, TEXT_ROWS, face_chunks, refuse_size, text_rows, too_many,
                                    vertex_chunks)
from c1mesh.formats._common import COLOR_NAMES, NORMAL_NAMES, colors_to_uint8, find_columns, loadtxt, native
from c1mesh.formats._limits import check_alloc

#: PLY scalar type names (both spellings) -> numpy type code without byte order.
PLY_TYPES = {
    "char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2",
    "int": "i4", "uint": "u4", "float": "f4", "double": "f8",
    "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2",
    "int32": "i4", "uint32": "u4", "float32": "f4", "float64": "f8",
}
_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}
_ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "="}


@dataclass
class Prop:
    """One property: scalar (`count_type` None) or list (count type, then `type` items)."""

    name: str
    type: str
    count_type: str | None = None


@dataclass
class Element:
    """One header element: name, number of rows, properties in file order."""

    name: str
    count: int
    props: list[Prop] = field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p.count_type is not None for p in self.props)


# ----------------------------------------------------------------------------- header
#: Largest header accepted (long comments are fine up to this), and most properties / elements.
MAX_HEADER_BYTES = 1 << 20
MAX_PROPERTIES = 10_000
MAX_ELEMENTS = 10_000


def _parse_header(data: bytes, name: str) -> tuple[str, list[Element], int]:
    """Return (format, elements, offset of the body) or raise FormatError.

    Linear in the header size: property names are checked for repeats with a set per
    element. Element row counts are checked against the body size in `_check_counts`.
    """
    if not data.startswith((b"ply\n", b"ply\r\n")):
        raise FormatError(f"'{name}' is not a PLY file: it does not start with the 'ply' magic line.")
    fmt, elements, offset, number = None, [], data.index(b"\n") + 1, 1
    seen: set[str] = set()
    limit = min(len(data), MAX_HEADER_BYTES)
    while True:
        nl = data.find(b"\n", offset, limit)
        if nl < 0:
            where = "" if limit == len(data) else f" within its first {MAX_HEADER_BYTES} bytes"
            raise FormatError(f"PLY file '{name}' has no 'end_header' line{where}; the header is incomplete.")
        words, offset, number = data[offset:nl].decode("latin-1").split(), nl + 1, number + 1
        if words == ["end_header"]:
            break
        fmt = _header_line(words, fmt, elements, seen, name, number)
    if fmt is None:
        raise FormatError(f"PLY file '{name}' has no 'format' line in its header.")
    _check_counts(fmt, elements, len(data) - offset, name)
    return fmt, elements, offset


def _header_line(words: list[str], fmt: str | None, elements: list[Element], seen: set[str],
                 name: str, number: int) -> str | None:
    """Apply one header line to (fmt, elements); return the possibly updated fmt.

    `seen` holds the property names of the current element (reset by each 'element').
    """
    bad = f"PLY file '{name}' has a bad header line {number}: {' '.join(words)[:80]!r}."
    if not words or words[0] in ("comment", "obj_info"):
        return fmt
    if words[0].lstrip("+-").replace(".", "", 1).isdigit():
        raise FormatError(f"PLY file '{name}' has data at header line {number}: the 'end_header' line is missing.")
    if words[0] == "format":
        if len(words) != 3 or words[1] not in _ENDIAN or fmt is not None:
            raise FormatError(bad)
        return words[1]
    if words[0] == "element" and len(words) == 3 and re.fullmatch(r"[0-9]{1,20}", words[2]) is not None:
        if words[1] == "vertex" and any(el.name == "vertex" for el in elements):
            raise FormatError(f"PLY file '{name}' header line {number} repeats the element 'vertex'.")
        if len(elements) >= MAX_ELEMENTS:
            raise FormatError(f"PLY file '{name}' declares more than {MAX_ELEMENTS} elements; it is not a point file.")
        elements.append(Element(words[1], int(words[2])))
        seen.clear()
    elif words[0] == "property" and elements:
        prop = _parse_property(words, bad)
        if prop.name in seen:
            raise FormatError(f"PLY file '{name}' header line {number} repeats the property '{prop.name}'.")
        if len(seen) >= MAX_PROPERTIES:
            raise FormatError(f"PLY file '{name}' element '{elements[-1].name}' has more than {MAX_PROPERTIES} properties.")
        seen.add(prop.name)
        elements[-1].props.append(prop)
    else:
        raise FormatError(bad)
    return fmt


def _min_row_bytes(el: Element, fmt: str) -> int:
    """Fewest body bytes one row of `el` can take: scalars and list counts in binary,
    one character plus a separator per property in ascii."""
    if fmt == "ascii":
        return 2 * len(el.props)
    return sum(np.dtype(PLY_TYPES[p.count_type or p.type]).itemsize for p in el.props)


def _check_counts(fmt: str, elements: list[Element], body: int, name: str) -> None:
    """FormatError when the elements' row counts cannot fit in the `body` bytes.

    Checked before any allocation, so a header claiming 2**63 rows fails at once.
    """
    need = 0
    for el in elements:
        if el.count and not el.props:
            raise FormatError(f"PLY file '{name}' element '{el.name}' has {el.count} rows but no properties.")
        need += el.count * _min_row_bytes(el, fmt)
        if need > body + 1:  # +1: the last ascii row may lack its newline
            raise FormatError(f"PLY file '{name}' is truncated or corrupt: element '{el.name}' claims "
                              f"{el.count} rows, more than the {body} body bytes can hold.")


def _parse_property(words: list[str], bad: str) -> Prop:
    """Parse 'property <type> <name>' or 'property list <integer count type> <type> <name>'."""
    if len(words) == 3 and words[1] in PLY_TYPES:
        return Prop(words[2], words[1])
    if len(words) == 5 and words[1] == "list" and PLY_TYPES.get(words[2], "f")[0] != "f" and words[3] in PLY_TYPES:
        return Prop(words[4], words[3], words[2])
    raise FormatError(bad)


# ----------------------------------------------------------------------------- binary body
def _count_field(index: int) -> str:
    """Name of the count field of the list property at `index`. It holds a space, which a
    PLY header's whitespace-separated property names cannot, so no property collides."""
    return f"count of {index}"


def _row_dtype(el: Element, endian: str, list_lengths: list[int]) -> np.dtype:
    """Structured dtype of one row, lists given fixed lengths (one per list property)."""
    fields, lengths = [], iter(list_lengths)
    for i, p in enumerate(el.props):
        if p.count_type is None:
            fields.append((p.name, endian + PLY_TYPES[p.type]))
        else:
            fields.append((_count_field(i), endian + PLY_TYPES[p.count_type]))
            fields.append((p.name, endian + PLY_TYPES[p.type], (next(lengths),)))
    return np.dtype(fields)


def _first_row_lengths(el: Element, buf: bytes, offset: int, endian: str) -> list[int]:
    """Lengths of the list properties in the row starting at `offset`."""
    lengths = []
    for p in el.props:
        if p.count_type is None:
            offset += np.dtype(PLY_TYPES[p.type]).itemsize
            continue
        ct = np.dtype(endian + PLY_TYPES[p.count_type])
        if offset + ct.itemsize > len(buf):
            return lengths
        n = int(np.frombuffer(buf, ct, 1, offset)[0])
        offset += ct.itemsize + n * np.dtype(PLY_TYPES[p.type]).itemsize
        if n < 0 or offset > len(buf):
            return lengths  # impossible or past the end; the ragged walk reports it
        lengths.append(n)
    return lengths


def _read_binary_element(el: Element, buf: bytes, offset: int, endian: str, name: str) -> tuple[np.ndarray | None, int]:
    """Decode element `el` at `offset`; return (rows or None if ragged lists, end offset).

    Fixed-size rows (no lists, or every row's lists as long as the first row's) become
    one structured array; ragged lists are walked row by row only to find the end.
    """
    n_lists = sum(p.count_type is not None for p in el.props)
    lengths = _first_row_lengths(el, buf, offset, endian) if n_lists and el.count else []
    lengths += [0] * (n_lists - len(lengths))
    dtype = _row_dtype(el, endian, lengths)
    if dtype.itemsize == 0:
        return np.zeros(el.count, dtype), offset
    end = offset + el.count * dtype.itemsize
    if end <= len(buf):
        rows = np.frombuffer(buf, dtype, el.count, offset)
        counts = [_count_field(i) for i, p in enumerate(el.props) if p.count_type is not None]
        if all((rows[f] == n).all() for f, n in zip(counts, lengths)):
            return rows, end
    if not el.has_lists:
        raise _truncated(name, el)
    return None, _walk_ragged(el, buf, offset, endian, name)


def _walk_ragged(el: Element, buf: bytes, offset: int, endian: str, name: str) -> int:
    """Offset just past element `el` whose list lengths vary from row to row.

    A plain Python loop over rows (struct, not numpy, per count): used only for elements
    that are skipped anyway, e.g. mixed triangle/quad faces stored before the vertices.
    """
    lists = [i for i, p in enumerate(el.props) if p.count_type is not None]
    if len(lists) == 1 and PLY_TYPES[el.props[lists[0]].count_type] == "u1":
        return _walk_uchar_lists(el, lists[0], buf, offset, name)
    steps = []  # per property: (item size, struct code of the count or None for a scalar)
    for p in el.props:
        size = np.dtype(PLY_TYPES[p.type]).itemsize
        code = None if p.count_type is None else endian + _STRUCT[PLY_TYPES[p.count_type]]
        steps.append((size, code, struct.calcsize(code) if code else 0))
    try:
        for _ in range(el.count):
            for size, code, csize in steps:
                if code is None:
                    offset += size
                else:
                    n = int(struct.unpack_from(code, buf, offset)[0])
                    if n < 0:
                        raise FormatError(f"PLY file '{name}' has a negative list length in element '{el.name}'.")
                    offset += csize + size * n
    except struct.error:  # a count lies past the end of the data
        raise _truncated(name, el) from None
    if offset > len(buf):
        raise _truncated(name, el)
    return offset


def _walk_uchar_lists(el: Element, index: int, buf: bytes, offset: int, name: str) -> int:
    """`_walk_ragged` for the usual face element: one list with a uchar count.

    Each row is `before` bytes, the count byte, count items, `after` bytes; indexing the
    bytes object directly costs a fraction of a struct call per row.
    """
    size = lambda props: sum(np.dtype(PLY_TYPES[p.type]).itemsize for p in props)  # noqa: E731
    before, after = size(el.props[:index]), size(el.props[index + 1:])
    item = np.dtype(PLY_TYPES[el.props[index].type]).itemsize
    step, end = before + 1 + after, len(buf)
    try:
        for _ in range(el.count):
            offset += step + item * buf[offset + before]
    except IndexError:  # a count lies past the end of the data
        raise _truncated(name, el) from None
    if offset > end:
        raise _truncated(name, el)
    return offset


def _truncated(name: str, el: Element) -> FormatError:
    return FormatError(
        f"PLY file '{name}' is truncated: the body ends before the {el.count} '{el.name}' rows the header promises."
    )


def _binary_vertices(elements: list[Element], buf: bytes, offset: int, endian: str, name: str) -> np.ndarray:
    """Structured array of the vertex rows; every element is walked to detect truncation."""
    vertices = None
    for el in elements:
        rows, offset = _read_binary_element(el, buf, offset, endian, name)
        if el.name == "vertex":
            if rows is None:
                raise FormatError(f"PLY file '{name}' has vertex list properties of varying length; not supported.")
            vertices = rows
    return vertices


# ----------------------------------------------------------------------------- ascii body
def _ascii_vertices(elements: list[Element], buf: bytes, offset: int, name: str) -> np.ndarray:
    """Structured array of the vertex rows of an ascii body (one line per row)."""
    lines = [ln for ln in buf[offset:].decode("latin-1").splitlines() if ln.strip()]
    start = 0
    vertices = None
    for el in elements:
        if start + el.count > len(lines):
            raise _truncated(name, el)
        if el.name == "vertex":
            vertices = _parse_ascii_rows(el, lines[start:start + el.count], name)
        start += el.count
    return vertices


def _parse_ascii_rows(el: Element, lines: list[str], name: str) -> np.ndarray:
    """Parse the ascii lines of a list-free element into a structured array."""
    if el.has_lists:
        raise FormatError(f"PLY file '{name}' has list properties in its ascii vertex element; not supported.")
    dtype = _row_dtype(el, "=", [])
    if not lines:
        return np.zeros(0, dtype)
    try:
        table = loadtxt(lines, comments=None)
    except ValueError as exc:
        raise FormatError(f"PLY file '{name}' has a malformed ascii vertex row: {exc}.") from exc
    if table.shape[1] != len(el.props):
        raise FormatError(
            f"PLY file '{name}' has {table.shape[1]} values per vertex line but {len(el.props)} vertex properties."
        )
    rows = np.empty(len(lines), dtype)
    for i, p in enumerate(el.props):
        rows[p.name] = table[:, i]
    return rows


# ----------------------------------------------------------------------------- reader
#: Bytes per vertex the reader builds besides the file's bytes: points and normals as float64.
_KEPT_BYTES_PER_VERTEX = 48


def read_ply(data: bytes, name: str) -> PointCloud:
    """Read the vertex element of a PLY file held in `data` (`name` is for messages)."""
    fmt, elements, offset = _parse_header(data, name)
    vertex_el = next((el for el in elements if el.name == "vertex"), None)
    if vertex_el is None:
        raise FormatError(f"PLY file '{name}' has no 'vertex' element.")
    check_alloc(len(data) + vertex_el.count * _KEPT_BYTES_PER_VERTEX, name,
                f"decoding the {vertex_el.count} vertices")
    if fmt == "ascii":
        rows = _ascii_vertices(elements, data, offset, name)
    else:
        rows = _binary_vertices(elements, data, offset, _ENDIAN[fmt], name)
    cloud = _cloud_from_rows(rows, vertex_el, name)
    cloud.crs = crs_from_ply_header(data)
    return cloud


def _cloud_from_rows(rows: np.ndarray, el: Element, name: str) -> PointCloud:
    """Split structured vertex rows into PointCloud fields."""
    names = [p.name for p in el.props if p.count_type is None]
    xyz = find_columns(names, (("x",), ("y",), ("z",)))
    if None in xyz:
        raise FormatError(f"PLY file '{name}' has a vertex element without x, y and z properties.")
    used = set(xyz)
    column = lambda idx: rows[names[idx]].astype(np.float64)  # noqa: E731
    points = np.column_stack([column(i) for i in xyz])
    normals = None
    nrm = find_columns(names, NORMAL_NAMES)
    if None not in nrm:
        normals = np.column_stack([column(i) for i in nrm])
        used |= set(nrm)
    colors = None
    rgba = find_columns(names, COLOR_NAMES)
    if None not in rgba[:3]:
        channels = [i for i in rgba if i is not None]
        colors = colors_to_uint8(np.column_stack([rows[names[i]] for i in channels]))
        used |= set(channels)
    extra = {n: native(rows[n]) for i, n in enumerate(names) if i not in used}
    return PointCloud(points=points, normals=normals, colors=colors, extra=extra)


# ----------------------------------------------------------------------------- writer
def _vertex_dtype(stream: MeshStream, endian: str) -> np.dtype:
    """Vertex row: x y z double, [nx ny nz double], [red green blue [alpha] uchar]."""
    fields = [(c, endian + "f8") for c in ("x", "y", "z")]
    if stream.has_normals:
        fields += [(c, endian + "f8") for c in ("nx", "ny", "nz")]
    fields += [(c, "u1") for c in ("red", "green", "blue", "alpha")[:stream.color_channels]]
    return np.dtype(fields)


def _header(stream: MeshStream, dtype: np.dtype, fmt: str, crs: str | None = None) -> bytes:
    kinds = {"f8": "double", "u1": "uchar"}
    lines = ["ply", f"format {fmt} 1.0", "comment written by c1mesh"]
    lines += [ply_comment(crs)] if crs else []
    lines += [f"element vertex {stream.vertex_count}"]
    lines += [f"property {kinds[dtype[n].str[1:]]} {n}" for n in dtype.names]
    lines += [f"element face {stream.face_count}", "property list uchar int vertex_indices", "end_header", ""]
    return "\n".join(lines).encode("ascii")


def _vertex_rows(dtype: np.dtype, vertices, normals, colors) -> np.ndarray:
    """Packed vertex rows of one block: a copy of the rows, made from the columns, or in
    one memcpy when vertices and normals are the two halves of rows that already have the
    file's layout (`_interleaved`)."""
    rows = _interleaved(dtype, vertices, normals, colors)
    if rows is not None:
        return rows.copy().view(dtype).reshape(-1)
    rows = np.empty(len(vertices), dtype)
    for i, c in enumerate("xyz"):
        rows[c] = vertices[:, i]
    if normals is not None:
        for i, c in enumerate(("nx", "ny", "nz")):
            rows[c] = normals[:, i]
    if colors is not None:
        for i in range(colors.shape[1]):
            rows[("red", "green", "blue", "alpha")[i]] = colors[:, i]
    return rows


def _interleaved(dtype: np.dtype, vertices, normals, colors) -> np.ndarray | None:
    """The (n, 6) float64 rows [x y z nx ny nz] whose halves vertices (n, 3) and normals
    (n, 3) are, as stages.surface yields them, when that is the file's row (dtype: doubles
    in this machine's byte order, no colours); else None. Packing the six columns one by
    one cost 40 ns a vertex (0.6 s of a 16M-vertex output's main thread)."""
    if (colors is not None or normals is None or dtype.itemsize != 48
            or vertices.base is None or vertices.base is not normals.base):
        return None
    double = np.dtype("<f8")
    if dtype != np.dtype([(c, double) for c in ("x", "y", "z", "nx", "ny", "nz")]):
        return None
    if (vertices.dtype != double or normals.dtype != double or vertices.shape != normals.shape
            or vertices.strides != (48, 8) or normals.strides != (48, 8)):
        return None
    if normals.__array_interface__["data"][0] != vertices.__array_interface__["data"][0] + 24:
        return None
    return np.lib.stride_tricks.as_strided(vertices, shape=(len(vertices), 6), strides=(48, 8))


def ply_size_problem(size) -> str | None:
    """Why a PLY cannot hold a mesh of size.vertex_count vertices and size.face_count
    faces (a _blocks.MeshSize or MeshStream), or None.

    The header's element counts are text, but the format's reference reader (Turk's
    ply.c, and the copies of it in VTK and elsewhere) reads them with atoi into a C int,
    and write_ply's faces index vertices as `int` (int32): so at most 2³¹ − 1 vertices
    and 2³¹ − 1 faces.
    """
    return (too_many(size.vertex_count, "vertices", INT32_MOST,
                     "PLY counts elements and indexes vertices with 32-bit ints")
            or too_many(size.face_count, "faces", INT32_MOST, "PLY counts elements with 32-bit ints"))


def write_ply(mesh: SurfaceMesh | MeshStream, f: IO[bytes], ascii: bool = False,
              crs: str | None = None) -> None:
    """Write a mesh (or a MeshStream, block by block) as PLY to binary file object `f`.

    Binary little endian, or ascii. Coordinates and normals are doubles so that large
    world coordinates (state-plane feet, UTM metres) keep their full precision. Rows are
    packed in blocks and written by a second thread while the next block is computed
    (formats/_background.py), so writing adds only a few block-sized buffers to memory.
    `crs` (WKT) goes into the header as `comment crs <WKT>`, which read_ply reads back.
    A mesh beyond `ply_size_problem` is refused (InputError) before a byte is written.
    """
    stream = mesh.stream(_WRITE_BLOCK) if isinstance(mesh, SurfaceMesh) else mesh
    refuse_size(ply_size_problem(stream))
    dtype = _vertex_dtype(stream, "=" if ascii else "<")
    with background_writes(f) as write:
        write(_header(stream, dtype, "ascii" if ascii else "binary_little_endian", crs))
        if ascii:
            _write_ascii_body(stream, dtype, write)
            return
        for vertices, normals, colors in stream.vertex_blocks():
            rows = _vertex_rows(dtype, vertices, normals if stream.has_normals else None,
                                colors if stream.color_channels else None)
            write(memoryview(rows).cast("B"))
        face_dtype = np.dtype([("n", "u1"), ("v", "<i4", (3,))])
        for faces in stream.face_blocks():
            face_rows = np.empty(len(faces), face_dtype)
            face_rows["n"] = 3
            face_rows["v"] = faces
            write(memoryview(face_rows).cast("B"))


def _write_ascii_body(stream: MeshStream, dtype: np.dtype, write) -> None:
    """ASCII PLY vertex and face lines, formatted TEXT_ROWS rows at a time so that the
    Python floats and strings of a block stay a few MB (formats/_blocks.py)."""
    for vertices, normals, colors in vertex_chunks(stream, TEXT_ROWS):
        rows = _vertex_rows(dtype, vertices, normals, colors)
        cols = [rows[n].tolist() for n in rows.dtype.names]   # round-trip precision: repr of each double
        write(text_rows(zip(*cols)))
    for faces in face_chunks(stream, TEXT_ROWS):
        write("".join(f"3 {a} {b} {c}\n" for a, b, c in faces.tolist()).encode("ascii"))


_WRITE_BLOCK = 1 << 18   # rows packed per write
