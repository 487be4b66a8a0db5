"""The fit's georeferenced side, in one place the pipeline calls: the CRS to carry, the
rasters, contours and preview to write, and the level that gives a requested edge length.

`geo_plan` checks everything that can be checked without the input (the CRS parses, the
raster, contour and preview paths have the right extensions and writable directories,
options do not conflict), so the CLI can call it before any input is read.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from c1mesh.core import crs as crs_module
from c1mesh.core.errors import InputError
from c1mesh.core.outputs import DEM_AXES, contour_path_problem
from c1mesh.core.tile import bounds
from c1mesh.geo.contour_file import SHAPEFILE_PARTS, StagedContours, vector_crs
from c1mesh.geo.contours import ContourGrid, contour_surface
from c1mesh.geo.preview import render_fit
from c1mesh.geo.raster import RasterTargets, fill_distance, is_raster_path, targets_for
from c1mesh.geo.raster_grid import RasterGrid
from c1mesh.stages.surface import refined_vertex_count

PREVIEW_SUFFIX = ".png"
MAX_LEVEL = 64


@dataclass(frozen=True)
class ContourRequest:
    """--contours PATH --interval H: the vector file (.gpkg, .geojson, .shp), the height
    between two levels (world height units, > 0), and the CRS to write (contour_file.
    vector_crs: the fit's, or for GeoJSON its EPSG code), set once the input's is known."""

    path: str
    interval: float
    crs: str | None = None

    def with_crs(self, crs: str | None, user_crs: str | None) -> "ContourRequest":
        """This request writing the CRS `crs` (WKT; user_crs: --crs, which may name it by
        its EPSG code); InputError when the format cannot hold it (vector_crs)."""
        return replace(self, crs=vector_crs(self.path, crs, user_crs))


@dataclass
class GeoPlan:
    """What a fit writes besides (or instead of) the mesh."""

    rasters: RasterTargets
    user_crs: str | None
    preview: str | None
    contours: ContourRequest | None = None

    @property
    def height_field(self) -> bool:
        """Whether the outputs are heights over the world XY plane (GeoTIFFs, contours), so
        the fit's height axis is world z and its frame the axis frame."""
        return bool(self.rasters.items()) or self.contours is not None


def geo_plan(output, options) -> GeoPlan:
    """Validate the georeferencing options of a fit before any work (InputError if wrong)."""
    user_crs = crs_module.parse_crs(options.crs) if options.crs else None
    frame_error = dem_frame_error(options.frame, [output], options.slope, options.aspect, options.hillshade,
                                  options.support)
    if frame_error:
        raise InputError(frame_error)
    contours = contour_request(options)
    rasters = targets_for(output, options)
    fill_distance(options.fill)      # InputError for a bad --fill, before any work
    if options.resolution is not None and not options.resolution > 0:
        raise InputError(f"--resolution must be a positive length, got {options.resolution}")
    if options.preview is not None:
        check_preview_path(options.preview)
    if rasters.dem is not None:
        check_writable(rasters.dem)
    extra = [path for _, path in rasters.items() if path != rasters.dem]
    extra += [options.preview] if options.preview else []
    extra += [contours.path] if contours else []
    for path in extra:
        check_writable(path)
    named = [str(output)] if isinstance(output, (str, Path)) else []
    named += extra
    if len({str(Path(p).resolve()) for p in named}) != len(named):
        raise InputError("two outputs (-o, --slope, --aspect, --hillshade, --support, --preview, --contours) have "
                         "the same path")
    if contours:
        check_contour_parts(contours.path, named[:1] + [p for p in named[1:] if p != contours.path], output)
    return GeoPlan(rasters, user_crs, options.preview, contours)


def check_contour_parts(path, others, output) -> None:
    """InputError when the contour file `path` cannot be written in place of what is there
    (a directory, device or FIFO: GDAL writes regular files only), or when a shapefile's
    other parts (.shx .dbf .prj .cpg) would overwrite another output or the .prj sidecar of
    the mesh `output`."""
    target = Path(path)
    if target.exists() and not target.is_file():
        raise InputError(f"the contours '{path}' must be a regular file (GDAL writes it in place)")
    if target.suffix.lower() != ".shp":
        return
    taken = {str(Path(p).resolve()) for p in others}
    if isinstance(output, (str, Path)) and str(output) != "-" and not is_raster_path(output):
        taken.add(str(Path(output).with_suffix(".prj").resolve()))
    for part in SHAPEFILE_PARTS:
        sibling = target.with_suffix("." + part)
        if str(sibling.resolve()) in taken:
            raise InputError(f"the contours '{path}' write '{sibling}' too, which is another output "
                             "(or the mesh's .prj): give the shapefile another name")


def contour_request(options) -> ContourRequest | None:
    """The contours a fit writes (None: --contours not given), checked without the input:
    an --interval that is a positive height, a known extension, a frame and axis whose
    heights are over the world XY plane. InputError otherwise."""
    path, interval = options.contours, options.interval
    if path is None:
        if interval is not None:
            raise InputError("--interval is the height between contour lines: give --contours FILE")
        return None
    if interval is None:
        raise InputError("--contours needs --interval H, the height between two contour lines")
    if not (interval > 0 and math.isfinite(interval)):
        raise InputError(f"--interval must be a positive height, got {interval}")
    if contour_path_problem(path):
        raise InputError(contour_path_problem(path))
    if options.frame == "perspective":
        raise InputError(CONTOUR_FRAME_ERROR)
    axis = options.axis
    if not (isinstance(axis, str) and axis.strip().lower() in DEM_AXES):
        raise InputError(f"contours are levels of height over the world XY plane; --axis {axis} cannot be "
                         "used with --contours (use --axis z or auto)")
    return ContourRequest(str(path), float(interval))


CONTOUR_FRAME_ERROR = ("contours are levels of height over the world XY plane and have no meaning in the "
                       "perspective frame; drop --frame perspective (the surface is then fitted in the "
                       "axis frame)")
"""Why --contours and --frame perspective cannot go together (also a usage error)."""


def check_preview_path(path) -> None:
    """InputError unless `path` is a .png in a writable directory."""
    if Path(path).suffix.lower() != PREVIEW_SUFFIX:
        raise InputError(f"the preview '{path}' must be a .png file")
    check_writable(path)


def check_before(outputs, options):
    """The georeferenced side of a fit's outputs, checked before the input is read: the
    CRS, raster and preview paths, option conflicts (mesh outputs: c1mesh.core.outputs).
    Returns the options with the CRS parsed to WKT (so it is parsed once)."""
    if options.crs:
        options = replace(options, crs=crs_module.parse_crs(options.crs))
    for output in outputs:
        if output == "-":
            if targets_for(None, options).items():
                raise InputError("GeoTIFF outputs cannot go to stdout; give -o FILE.tif")
            request = contour_request(options)
            if request is not None:
                check_writable(request.path)
            continue
        geo_plan(output, options)      # mesh outputs: c1mesh.core.outputs checks them
    return options


def check_writable(path) -> None:
    """InputError unless `path` could be created: its directory exists and is writable."""
    target = Path(path)
    parent = target.parent
    if target.is_dir():
        raise InputError(f"Output path '{target}' is a directory; give a file name.")
    if not parent.is_dir():
        raise InputError(f"Output directory '{parent}' does not exist; create it first.")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"Output directory '{parent}' is not writable.")


def side_length_sum(points: np.ndarray, triangles: np.ndarray) -> float:
    """The sum of the lengths of the triangles' sides (T, 3) over points (n, 2): a tile's
    summary of the mean edge, which the tiles of a survey add up (pipeline.bounded_fit)."""
    total = 0.0
    for a, b in ((0, 1), (1, 2), (2, 0)):
        d = points[triangles[:, a]] - points[triangles[:, b]]
        total += float(np.sqrt((d * d).sum(axis=1)).sum())
    return total


def mean_edge_length(points: np.ndarray, triangles: np.ndarray) -> float:
    """Mean length of the triangles' edges (each shared edge counted from both sides)."""
    return side_length_sum(points, triangles) / (3 * triangles.shape[0])


def level_for_edge(points: np.ndarray, triangles: np.ndarray, resolution: float) -> int:
    """The refinement level whose output edges are closest to `resolution` on average:
    level L splits every edge into L, so the mean edge becomes mean_input_edge / L."""
    return level_for_mean_edge(mean_edge_length(points, triangles), resolution)


def level_for_mean_edge(mean_edge: float, resolution: float) -> int:
    """level_for_edge of a triangulation whose mean edge is mean_edge (length units)."""
    level = round(mean_edge / resolution)
    return int(min(max(level, 1), MAX_LEVEL))


def level_for_vertices(interp, target: int, most: int = MAX_LEVEL) -> int:
    """The level (1..most) whose refinement has the vertex count nearest `target` by
    ratio (|log(count / target)| smallest; ties: the lower level)."""
    best, best_gap = 1, math.inf
    for level in range(1, most + 1):
        count = refined_vertex_count(interp, level)
        gap = abs(math.log(count / max(target, 1)))
        if gap < best_gap:
            best, best_gap = level, gap
        if count >= target:          # counts grow with the level: later ones are farther
            break
    return best


def dem_frame_error(frame: str, outputs, slope=None, aspect=None, hillshade=None, support=None) -> str | None:
    """Why the fit cannot write its GeoTIFF outputs, or None.

    frame: --frame; outputs: the output paths (None and streams are skipped); slope,
    aspect, hillshade, support: the raster paths of those options (or None). A DEM
    (and slope, aspect, hillshade on its grid) is a height over a map plane: it has no
    meaning in the perspective frame (inverse depth over the view rays of a depth frame).
    --frame auto fits an organised input in the axis frame when a DEM is asked for
    (perspective.frame_kind), so only an explicit --frame perspective conflicts. A
    preview is no GeoTIFF: a depth frame may have one. Plain Python (no input read).
    """
    if frame != "perspective":
        return None
    named = [str(o) for o in outputs if is_raster_path(o)]
    named += [f"--{flag} {path}" for flag, path in (("slope", slope), ("aspect", aspect),
                                                   ("hillshade", hillshade), ("support", support)) if path]
    if not named:
        return None
    return (f"GeoTIFF outputs ({', '.join(named)}) are heights over a map plane and have no meaning "
            "in the perspective frame; drop --frame perspective (the DEM is fitted in the axis frame) "
            "or write a mesh")


def contour_grid(interp, frame, raster_grid: RasterGrid | None, level: int | None, resolution: float | None):
    """The grid the contours are traced on: the DEM's when one is written (raster_grid);
    for a mesh, the aligned grid at --resolution, else at the refined mesh's mean edge
    (mean input edge / level), covering the triangulation (world x, y)."""
    if raster_grid is not None:
        return raster_grid
    step = resolution if resolution is not None else mean_edge_length(interp.points, interp.triangles) / level
    lo, hi = bounds(interp.points)
    lo, hi = lo + frame.origin[:2], hi + frame.origin[:2]
    return RasterGrid.covering(lo, hi, step)


def stage_contours(request: ContourRequest, interp, frame, grid: RasterGrid) -> tuple[Any, dict]:
    """Trace the contours of the fit's spline on `grid` (c1mesh.geo.contours) and write
    them, with request.crs, under a temporary name; returns (the StagedContours to
    commit() once the fit's other files are written, or to discard(); the report's
    "contours" section)."""
    start = time.perf_counter()
    lines = contour_surface(interp, ContourGrid.of_raster(grid, frame.origin), request.interval)
    return stage_lines(request, lines, grid, start)


def stage_lines(request: ContourRequest, lines, grid: RasterGrid, start: float) -> tuple[Any, dict]:
    """Write the traced ContourLines `lines` as stage_contours does: (StagedContours, the
    report's "contours" section); start: the perf_counter at which the tracing began."""
    staged = StagedContours(request.path)
    try:
        staged.write(lines.lines, lines.levels, request.crs)
    except BaseException:
        staged.discard()
        raise
    facts = {"file": request.path, **lines.facts(), "grid_resolution": grid.resolution,
             "seconds": round(time.perf_counter() - start, 6)}
    return staged, facts


def add_contour_facts(report: dict, facts: dict | None) -> None:
    """Put the "contours" section (facts; None: no --contours) into a fit's report, and a
    warning when no level lies within the surface's heights (the file is empty)."""
    if facts is None:
        return
    report["contours"] = facts
    if facts["levels"]["count"] == 0:
        report["warnings"].append(f"--interval {facts['interval']:g} gives no contour level within the "
                                  f"surface's heights: {facts['file']} holds no line")


def finish(result, interp, frame, crs, crs_source, options, dem=None):
    """Add the CRS to the report and render the preview when one was asked for (both
    frames: preview.render_fit). dem: (grid, sampler) of the DEM the fit wrote
    (raster.dem_sampling), whose cells the preview then draws; None: no DEM."""
    facts = crs_module.describe(crs)
    if facts is not None:
        facts["source"] = crs_source
    result.report["crs"] = facts
    if options.resolution is not None and "level" in result.report:
        result.report["resolution"] = options.resolution
    if options.preview:
        start = time.perf_counter()
        render_fit(interp, frame, options.preview, crs=crs, level=result.report.get("level"),
                   z_factor=result.report.get("z_factor", 1.0), dem=dem)      # None: unknown (pipeline)
        result.report["seconds"]["preview"] = round(time.perf_counter() - start, 6)
    return result


__all__ = ["GeoPlan", "ContourRequest", "contour_request", "contour_grid", "stage_contours", "geo_plan", "check_writable",
           "level_for_edge", "finish", "dem_frame_error", "level_for_vertices"]
