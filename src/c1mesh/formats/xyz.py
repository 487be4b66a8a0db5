"""Plain-text point tables (.xyz, .txt, .csv): one point per line.

Values are separated by whitespace, or by semicolons / commas when the first data line
has one (semicolon first, so '1,5;2,5' is reported rather than misread). Double quotes
around values and names (R's write.csv) are ignored, and so is a UTF-8 byte-order mark.
Blank lines and lines starting with '#' are skipped. Leading lines that do not start
with a number are header lines; the last of them names the columns, in any order and
any case (x y z, also lon/lat/elev, easting/northing/height or h; nx ny nz or normal_x..,
r g b or red green blue [alpha], classification; CloudCompare's '//X,Y,Z' works too;
other names, such as the unnamed index column of R and pandas, go to `extra`). A lone
integer first line equal to the number of rows (the .pts point count) is skipped.
A header's third coordinate is by its name a height (z, elev, elevation, height, h, alt,
altitude): the cloud records the name as `PointCloud.height_column`, and a fit without
the file's normals takes that column as the height axis, in units that need not be
those of x and y (c1mesh.pipeline.driver).

Without a header the column count decides (see `_layout`):
  3: x y z                 4: x y z scalar
  6: x y z + triple        9: x y z + triple + triple
  7: x y z scalar r g b when the last three columns are colours (.pts order), else
     x y z triple scalar.
A triple is normals when its rows have unit length (90% of them within 1%), colours
when every value is in 0..1 or an integer in 0..255; a triple that is neither, or a
7-column table that fits neither order, is an error that names the columns and asks
for a header. With two triples one must be normals and the other colours.
`scalar` is stored as extra["scalar"].
"""
from __future__ import annotations

import re

import numpy as np

from c1mesh.core.cloud import PointCloud
from c1mesh.core.errors import FormatError
from c1mesh.formats._common import COLOR_NAMES, NORMAL_NAMES, colors_to_uint8, decode_text, find_columns, is_number, loadtxt

_SPLIT = re.compile(r"[\s,;]+")
_DECIMAL_COMMA = re.compile(r"(^|;)\s*-?[0-9]+,[0-9]+\s*(;|$)")
"""A semicolon-separated value written with a decimal comma ('6,370'): Excel's export in
many locales, reported rather than misread (a comma could also group thousands)."""
#: Header names of the coordinate columns, lower-case, per axis.
XYZ_NAMES = (
    ("x", "lon", "long", "longitude", "easting", "east"),
    ("y", "lat", "latitude", "northing", "north"),
    ("z", "elev", "elevation", "height", "h", "alt", "altitude"),
)


def _data_lines(text: str) -> list[tuple[int, str]]:
    """Non-blank, non-comment lines with their 1-based line numbers."""
    return [(n, ln) for n, ln in enumerate(text.splitlines(), start=1) if ln.strip() and not ln.lstrip().startswith("#")]


def _unquote(lines: list[tuple[int, str]]) -> list[tuple[int, str]]:
    """The lines without double quotes (R and pandas quote names and sometimes values)."""
    return [(n, ln.replace('"', "")) for n, ln in lines] if any('"' in ln for _, ln in lines[:50]) else lines


def _split_header(lines: list[tuple[int, str]]) -> tuple[list[str] | None, list[tuple[int, str]]]:
    """Return (column names from the last leading non-numeric line or None, data lines).

    Names are split with the data's delimiter, so an empty first name (pandas' index
    column, ',x,y,z') keeps its place.
    """
    first = 0
    while first < len(lines) and not is_number(_SPLIT.split(lines[first][1].strip())[0]):
        first += 1
    if first == 0:
        return None, lines
    header = lines[first - 1][1].strip().lstrip("/")
    sample = lines[first][1] if first < len(lines) else header
    delimiter = ";" if ";" in sample else "," if "," in sample else None
    words = header.split(delimiter) if delimiter else header.split()
    return [w.strip().strip("'").lower() for w in words], lines[first:]


def _drop_count_line(lines: list[tuple[int, str]]) -> list[tuple[int, str]]:
    """Skip a .pts-style first line holding just the number of points."""
    if lines and re.fullmatch(r"[0-9]+", lines[0][1].strip()) and int(lines[0][1]) == len(lines) - 1:
        return lines[1:]
    return lines


def _parse_table(lines: list[tuple[int, str]], name: str) -> np.ndarray:
    """(n, k) float64 table of the data lines; FormatError names the first bad line."""
    first = lines[0][1]
    delimiter = ";" if ";" in first else "," if "," in first else None
    try:
        return loadtxt([ln for _, ln in lines], delimiter=delimiter, comments="#")
    except ValueError:
        pass
    if delimiter == ";" and _DECIMAL_COMMA.search(first) and "." not in first:
        raise FormatError(f"Point file '{name}' line {lines[0][0]} writes decimal commas "
                          f"({first.strip()!r}): write the values with decimal points.")
    width = len(first.split("#")[0].split(delimiter))
    for number, line in lines:
        values = line.split("#")[0]
        words = values.split(delimiter)
        if len(words) != width:
            raise FormatError(f"Point file '{name}' line {number} has {len(words)} values, expected {width}.")
        if not all(is_number(w) for w in words):
            raise FormatError(f"Point file '{name}' line {number} has a value that is not a number: {line.strip()!r}.")
    raise FormatError(f"Point file '{name}' could not be parsed as a table of numbers.")


def _is_unit(block: np.ndarray) -> bool:
    """True when the rows have unit length (90% of the finite rows within 1%): normals."""
    rows = block[np.isfinite(block).all(axis=1)]
    return bool(len(rows)) and float(np.mean(np.abs(np.linalg.norm(rows, axis=1) - 1.0) < 0.01)) >= 0.9


def _is_color(block: np.ndarray) -> bool:
    """True when every finite value is in 0..1, or is an integer in 0..255: colours."""
    values = block[np.isfinite(block)]
    if not values.size or values.min() < 0:
        return False
    return bool(values.max() <= 1.0 or (values.max() <= 255 and np.all(values == np.round(values))))


def _ambiguous(name: str, k: int, what: str) -> FormatError:
    return FormatError(
        f"Point file '{name}' has {k} columns and no header, and {what}; add a header line naming "
        "the columns, e.g. 'x y z nx ny nz red green blue'."
    )


def _triple(table: np.ndarray, start: int, name: str) -> str:
    """'normals' or 'colors' for the columns start..start+2 (1-based in messages)."""
    block = table[:, start:start + 3]
    if _is_unit(block):
        return "normals"
    if _is_color(block):
        return "colors"
    raise _ambiguous(name, table.shape[1], f"columns {start + 1}-{start + 3} are neither unit normals "
                     "nor colours (0..1 or integers 0..255)")


def _layout(table: np.ndarray, name: str) -> dict[str, int | list[int]]:
    """Column positions {'normals', 'colors', 'scalar'} for a table without header."""
    k = table.shape[1]
    if k == 3:
        return {}
    if k == 4:
        return {"scalar": 3}
    if k == 6:
        return {_triple(table, 3, name): [3, 4, 5]}
    if k == 7:
        if _is_unit(table[:, 3:6]):
            return {"normals": [3, 4, 5], "scalar": 6}
        if _is_color(table[:, 4:7]):
            return {"scalar": 3, "colors": [4, 5, 6]}
        if _is_color(table[:, 3:6]):
            return {"colors": [3, 4, 5], "scalar": 6}
        raise _ambiguous(name, k, "neither columns 4-6 nor 5-7 are unit normals or colours")
    if k == 9:
        first, second = table[:, 3:6], table[:, 6:9]
        if _is_unit(first) and _is_color(second):
            return {"normals": [3, 4, 5], "colors": [6, 7, 8]}
        if _is_color(first) and _is_unit(second):
            return {"colors": [3, 4, 5], "normals": [6, 7, 8]}
        raise _ambiguous(name, k, "columns 4-6 and 7-9 are not one triple of unit normals and one of colours")
    raise FormatError(
        f"Point file '{name}' has {k} columns and no header; without a header only 3, 4, 6, 7 or 9 columns "
        "are understood, so add a header line naming the columns (x y z nx ny nz red green blue)."
    )


def _cloud_from_named(table: np.ndarray, names: list[str], name: str) -> PointCloud:
    """Split a table into PointCloud fields by header names."""
    if len(names) != table.shape[1]:
        raise FormatError(f"Point file '{name}' has {len(names)} header names but {table.shape[1]} values per line.")
    xyz = find_columns(names, XYZ_NAMES)
    if None in xyz:
        raise FormatError(f"Point file '{name}' has a header without x, y and z columns "
                          f"(or lon, lat, elev): {' '.join(names)[:200]!r}.")
    nrm = find_columns(names, NORMAL_NAMES)
    rgba = find_columns(names, COLOR_NAMES)
    cls = find_columns(names, (("classification", "class"),))[0]
    cloud = PointCloud(points=table[:, xyz], height_column=names[xyz[2]])
    used = set(xyz)
    if None not in nrm:
        cloud.normals, used = table[:, nrm], used | set(nrm)
    if None not in rgba[:3]:
        channels = [i for i in rgba if i is not None]
        cloud.colors, used = colors_to_uint8(table[:, channels]), used | set(channels)
    if cls is not None:
        cloud.classification, used = table[:, cls].astype(np.int64), used | {cls}
    cloud.extra = {(n or f"column_{i + 1}"): table[:, i].copy() for i, n in enumerate(names) if i not in used}
    return cloud


def _cloud_from_layout(table: np.ndarray, layout: dict[str, int | list[int]]) -> PointCloud:
    cloud = PointCloud(points=table[:, :3])
    if "normals" in layout:
        cloud.normals = table[:, layout["normals"]]
    if "colors" in layout:
        cloud.colors = colors_to_uint8(table[:, layout["colors"]])
    if "scalar" in layout:
        cloud.extra["scalar"] = table[:, layout["scalar"]].copy()
    return cloud


def read_xyz(data: bytes, name: str) -> PointCloud:
    """Read a whitespace- or comma-separated point table (see the module doc for columns)."""
    names, lines = _split_header(_unquote(_data_lines(decode_text(data, name, "Point"))))
    lines = _drop_count_line(lines) if names is None else lines
    if not lines:
        raise FormatError(f"Point file '{name}' has no numeric data lines.")
    table = _parse_table(lines, name)
    if names is not None:
        return _cloud_from_named(table, names, name)
    return _cloud_from_layout(table, _layout(table, name))
