"""Coordinate reference systems: read from inputs, assigned by the user, written to outputs.

c1mesh never reprojects: points keep the coordinates of their file, and the CRS is a label
carried from the input to every output (native in GeoTIFF, a header comment in PLY, a
`.prj` sidecar beside PLY/OBJ/STL/OFF, the asset's extras in GLB). Inside the library a
CRS travels as a WKT2 string (``str``), so that numpy-only code never needs pyproj;
pyproj is imported here only when a CRS is parsed or converted. It lives in core because
the file formats (layer 2) read and write it (LAS VLRs, PLY comments, .prj sidecars).

Policy when the input has a CRS and the user passes ``--crs`` too: equal CRSs (same
definition, axis order ignored) are accepted; different ones are an error, since
relabelling coordinates without reprojecting them would put the surface in the wrong place.
"""
from __future__ import annotations

import os
from pathlib import Path

from c1mesh.core.errors import DependencyError, InputError
from c1mesh.core.outputs import atomic_output

PLY_COMMENT = "crs"
"""PLY header comment keyword: ``comment crs <one-line WKT2>``."""


def _pyproj():
    try:
        import pyproj
    except ImportError as exc:
        raise DependencyError('Coordinate reference systems need pyproj: pip install "pyproj>=3.4".') from exc
    return pyproj


def parse_crs(text: str) -> str:
    """The WKT2 of a user's CRS: "EPSG:XXXX", any WKT/PROJ string, or a file holding one.

    Raises InputError naming the text when pyproj cannot make a CRS of it.
    """
    pyproj = _pyproj()
    spec = text.strip()
    if not spec:
        raise InputError("--crs is empty; give EPSG:XXXX, a WKT string or a .prj/.wkt file")
    if os.path.isfile(spec):
        try:
            spec = Path(spec).read_text(encoding="utf-8", errors="replace").strip()
        except OSError as exc:
            raise InputError(f"cannot read the CRS file '{text}': {exc.strerror or exc}") from exc
    try:
        crs = pyproj.CRS.from_user_input(spec)
    except pyproj.exceptions.CRSError as exc:
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise InputError(f"cannot parse the CRS '{shown}': not an EPSG code, WKT, PROJ string "
                         "or a file holding one") from exc
    return to_wkt(crs)


def to_wkt(crs) -> str:
    """One-line WKT2 (2019) of a pyproj CRS."""
    return crs.to_wkt(version="WKT2_2019", pretty=False)


def las_crs(header) -> str | None:
    """WKT2 of the CRS in a laspy header (GeoKeys or WKT VLRs), None when it has none.

    A header whose CRS records pyproj cannot understand counts as having none.
    """
    try:
        _pyproj()
        crs = header.parse_crs()
    except DependencyError:
        return None
    except Exception:  # noqa: BLE001 — laspy raises assorted errors on odd GeoKeys
        return None
    return None if crs is None else to_wkt(crs)


def resolve(file_crs: str | None, user_crs: str | None, name: str) -> tuple[str | None, str | None]:
    """(CRS WKT, its source "file" | "option" | None) from the input's and the user's CRS.

    InputError when both are given and differ (c1mesh does not reproject).
    """
    if user_crs is None:
        return file_crs, ("file" if file_crs else None)
    if file_crs is None:
        return user_crs, "option"
    if not same_crs(file_crs, user_crs):
        pyproj = _pyproj()
        a, b = pyproj.CRS.from_user_input(file_crs), pyproj.CRS.from_user_input(user_crs)
        raise InputError(f"'{name}' is in {a.name}, but --crs says {b.name}; c1mesh does not "
                         "reproject: drop --crs, or reproject the input first (e.g. pdal translate)")
    return file_crs, "file"


def same_crs(a: str, b: str) -> bool:
    """Whether two CRSs (WKT or any pyproj input) are the same, axis order aside."""
    pyproj = _pyproj()
    return pyproj.CRS.from_user_input(a).equals(pyproj.CRS.from_user_input(b), ignore_axis_order=True)


def describe(wkt: str | None) -> dict | None:
    """JSON-ready facts about a CRS for `c1mesh info` and the report: name, EPSG code,
    horizontal units, geographic or projected, and the WKT itself."""
    if wkt is None:
        return None
    crs = _pyproj().CRS.from_user_input(wkt)
    units = [axis.unit_name for axis in crs.axis_info]
    return {"name": crs.name, "epsg": crs.to_epsg(), "geographic": bool(crs.is_geographic),
            "units": units[0] if units else None, "wkt": wkt}


def esri_wkt(wkt: str) -> str:
    """ESRI WKT (what .prj sidecars hold) of a CRS; WKT1 (GDAL) where ESRI has no form."""
    crs = _pyproj().CRS.from_user_input(wkt)
    for version in ("WKT1_ESRI", "WKT1_GDAL"):
        try:
            text = crs.to_wkt(version=version, pretty=False)
        except Exception:  # noqa: BLE001 — pyproj raises when a form does not exist
            text = None
        if text:
            return text
    return wkt


def prj_path(mesh_path) -> Path:
    """The sidecar path beside a mesh: surface.ply -> surface.prj."""
    return Path(mesh_path).with_suffix(".prj")


def write_prj(mesh_path, wkt: str) -> Path:
    """Write the ESRI-WKT sidecar of `mesh_path` atomically; returns its path."""
    target = prj_path(mesh_path)
    with atomic_output(target, "w") as handle:
        handle.write(esri_wkt(wkt) + "\n")
    return target


def ply_comment(wkt: str) -> str:
    """The PLY header line (without newline) that carries a CRS: `comment crs EPSG:XXXX`
    when an EPSG code defines exactly this CRS, else the one-line WKT2 with non-ASCII
    characters (° in scope remarks) escaped as \\uXXXX, since PLY headers are ASCII."""
    crs = _pyproj().CRS.from_user_input(wkt)
    code = crs.to_epsg(min_confidence=100)
    if code is not None and _pyproj().CRS.from_epsg(code) == crs:
        return f"comment {PLY_COMMENT} EPSG:{code}"
    text = " ".join(wkt.split()).encode("ascii", "backslashreplace").decode("ascii")
    return f"comment {PLY_COMMENT} {text}"


def crs_from_ply_header(data: bytes) -> str | None:
    """The CRS (WKT2) of a PLY file's `comment crs ...` header line, None when absent;
    InputError when the comment is there but cannot be parsed."""
    end = data.find(b"end_header")
    if end < 0:
        return None
    prefix = f"comment {PLY_COMMENT} "
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        if line.startswith(prefix):
            text = line[len(prefix):].strip()
            if "\\u" in text or "\\x" in text:
                text = text.encode("ascii").decode("unicode_escape")
            return parse_crs(text) if text else None
    return None


def metres_per_unit(wkt: str | None) -> tuple[float, float, str]:
    """(metres per horizontal unit, metres per vertical unit, the horizontal unit's name)
    of a CRS given as WKT: a US survey foot is 1200/3937 m, an international foot 0.3048 m.
    The vertical unit is that of the CRS's vertical part (a compound CRS), else the
    horizontal one, as LAS files without a vertical CRS keep heights in the plan's unit.
    No CRS, or one without a linear unit (geographic degrees), gives (1, 1, "metre"): the
    coordinates are taken as metres."""
    if not wkt:
        return 1.0, 1.0, "metre"
    crs = _pyproj().CRS.from_wkt(wkt)
    horizontal = [axis for axis in crs.axis_info if axis.direction.lower() in ("east", "north", "west", "south")]
    vertical = [axis for axis in crs.axis_info if axis.direction.lower() == "up"]
    if not horizontal or "degree" in horizontal[0].unit_name.lower():
        return 1.0, 1.0, "metre"
    xy = float(horizontal[0].unit_conversion_factor)
    z = float(vertical[0].unit_conversion_factor) if vertical else xy
    return xy, z, horizontal[0].unit_name
