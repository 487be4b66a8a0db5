"""Writing contour lines as a vector file (GeoPackage, GeoJSON or ESRI Shapefile) with
pyogrio, GDAL's vectorised Python binding: one LineString feature per line, its level in a
float64 attribute `level`, the CRS of the fit. GeoPackage and shapefile (.prj) hold any
CRS; GeoJSON only names one by its EPSG code (the 2008 "crs" member, which GDAL and QGIS
read; RFC 7946 readers assume WGS 84), so a CRS without one is refused for it
(`vector_crs`) right after the input is read, before the fit.

The file is written beside its target under a temporary name and renamed into place by
`commit` (a shapefile's .shp, .shx, .dbf, .prj and .cpg one after another), so a failed or
interrupted fit leaves no partial file: every temporary name is listed for the CLI's signal
handler (c1mesh.core.outputs.register_temp) before GDAL creates it. An existing file keeps
its permission bits, as c1mesh.core.outputs does for meshes.
"""
from __future__ import annotations

import contextlib
import os
import stat
import tempfile
import warnings
from pathlib import Path

import numpy as np

from c1mesh.core.errors import DependencyError, InputError
from c1mesh.core.outputs import CONTOUR_FORMATS, contour_path_problem, plan_outputs, register_temp, unregister_temp

DRIVERS = {"gpkg": "GPKG", "geojson": "GeoJSON", "shp": "ESRI Shapefile"}
"""GDAL's driver of each contour extension (c1mesh.core.outputs.CONTOUR_FORMATS)."""
LAYER = "contours"
"""The layer name (GeoPackage table, GeoJSON name; a shapefile's is its file name)."""
SHAPEFILE_PARTS = ("shp", "shx", "dbf", "prj", "cpg")
"""The files GDAL writes for one shapefile."""
SHAPEFILE_INDEXES = ("qix", "sbn", "sbx")
"""Spatial indexes of a shapefile that a new one makes stale (removed when it replaces it,
as is a .prj or .cpg the new one does not have)."""
SQLITE_SIDE_FILES = ("-journal", "-wal", "-shm")
"""SQLite's files beside a GeoPackage while it is written."""
assert set(DRIVERS) == set(CONTOUR_FORMATS)


def pyogrio_module():
    """pyogrio, imported on first use; DependencyError naming the install command."""
    try:
        import pyogrio.raw
    except ImportError as exc:
        raise DependencyError('Writing contours needs pyogrio: pip install "pyogrio>=0.7".') from exc
    return pyogrio


def contour_extension(path) -> str:
    """The contour format of `path` ('gpkg', 'geojson' or 'shp'); InputError for another."""
    problem = contour_path_problem(str(path))
    if problem:
        raise InputError(problem)
    return Path(path).suffix.lower().lstrip(".")


def vector_crs(path, crs: str | None, user_crs: str | None = None) -> str | None:
    """The CRS to write into the contour file `path`: the fit's (WKT) for a GeoPackage or
    shapefile; for GeoJSON its EPSG code ("EPSG:n"), taken from the CRS itself or from
    the user's --crs naming the same CRS. InputError for a GeoJSON whose CRS has no EPSG
    code (GDAL would write none, and readers would take the lines for WGS 84)."""
    if crs is None or contour_extension(path) != "geojson":
        return crs
    import pyproj

    for candidate in (crs, user_crs):
        code = pyproj.CRS.from_user_input(candidate).to_epsg() if candidate else None
        if code is not None:
            return f"EPSG:{code}"
    name = pyproj.CRS.from_user_input(crs).name
    raise InputError(f"the contours '{path}': GeoJSON names its CRS by an EPSG code, and the input's CRS "
                     f"({name}) has none; write .gpkg or .shp, or give --crs EPSG:XXXX naming the same CRS")


def linestring_wkb(xy: np.ndarray) -> bytes:
    """Little-endian WKB of a 2D LineString through the (n, 2) vertices."""
    head = np.array([1], "u1").tobytes() + np.array([2, xy.shape[0]], "<u4").tobytes()
    return head + np.ascontiguousarray(xy, dtype="<f8").tobytes()


class StagedContours:
    """A contour file written under temporary names now and renamed into place by
    `commit()`; leaving the `with` block without committing removes what was written."""

    def __init__(self, path):
        self.path = str(path)
        self.ext = contour_extension(path)
        (target,) = plan_outputs([("contours", path)])
        if target.kind != "atomic":
            raise InputError(f"the contours '{path}' must be a regular file (GDAL writes it in place)")
        self.real = Path(target.real)
        self._moves: dict[Path, Path] = {}          # final path -> temporary path
        self._listed: list[Path] = []               # every temporary name GDAL may create

    def __enter__(self) -> "StagedContours":
        return self

    def __exit__(self, kind, value, tb) -> None:
        self.discard()

    def write(self, lines, levels: np.ndarray, crs: str | None) -> None:
        """Write the lines ((n, 2) world x, y arrays) with their levels (float64) and the
        CRS (WKT or None) to the temporary file(s)."""
        pyogrio = pyogrio_module()
        temp = self._reserve()
        geometry = np.empty(len(lines), dtype=object)
        geometry[:] = [linestring_wkb(line) for line in lines]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)    # GDAL's notes (an empty layer)
            warnings.simplefilter("ignore", UserWarning)       # pyogrio's "'crs' was not provided"
            pyogrio.raw.write(str(temp), geometry, [np.asarray(levels, dtype=np.float64)], fields=["level"],
                              crs=crs, driver=DRIVERS[self.ext], layer=LAYER, geometry_type="LineString")
        if not temp.exists():
            raise InputError(f"GDAL did not write the contours '{self.path}'")

    def _reserve(self) -> Path:
        """Reserve a unique temporary name beside the target, list every file GDAL may
        create from it (before it exists, so a signal finds nothing unlisted); returns the
        name to give GDAL."""
        stem = self.real.name[:-len(self.ext) - 1]
        fd, reserved = tempfile.mkstemp(dir=self.real.parent, prefix=f".{stem}.", suffix=f".tmp.{self.ext}")
        os.close(fd)
        reserved = Path(reserved)
        base = str(reserved)[:-len(self.ext) - 1]
        if self.ext == "shp":
            self._moves = {self.real.with_suffix("." + part): Path(f"{base}.{part}") for part in SHAPEFILE_PARTS}
            self._list(*self._moves.values())
        else:
            self._moves = {self.real: reserved}
            self._list(reserved, *(Path(f"{reserved}{side}") for side in SQLITE_SIDE_FILES))
        os.unlink(reserved)                 # GDAL creates the file itself
        return reserved

    def _list(self, *paths: Path) -> None:
        for path in paths:
            register_temp(path)
            self._listed.append(path)

    def commit(self) -> None:
        """Rename the written files into place (an existing target's permission bits kept)."""
        stale = []
        for final, temp in self._moves.items():
            if not temp.exists():           # a part GDAL did not write (.prj without a CRS)
                stale.append(final)
                continue
            with contextlib.suppress(OSError):
                os.chmod(temp, stat.S_IMODE(os.stat(final).st_mode))
            os.replace(temp, final)
        if self.ext == "shp":               # the replaced shapefile's parts the new one lacks
            stale += [self.real.with_suffix("." + part) for part in SHAPEFILE_INDEXES]
        for path in stale:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
        self._moves = {}
        self.discard()                      # whatever is left (none expected) and the listing

    def discard(self) -> None:
        """Remove every temporary file not committed, and stop listing them."""
        for path in self._listed:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            unregister_temp(path)
        self._listed, self._moves = [], {}
