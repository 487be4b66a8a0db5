"""The fit pipeline: a scan in, a refined C1 surface mesh out.

    load → normals → frame → height field → triangulate + trim (+ curtains) → interpolate → refine
    → write

Each stage is a library function; :func:`fit` chains them, times them, and returns the
mesh with a JSON-ready report. Nothing here prints or exits: the CLI does that.
"""
from __future__ import annotations

import contextlib
import math
from concurrent.futures import Future
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from c1mesh.core.cloud import PointCloud
from c1mesh.core.crs import resolve as resolve_crs
from c1mesh.core.errors import C1MeshError, InputError
from c1mesh.core.outputs import LAS_FORMATS
from c1mesh.core.plan import MeshTarget
from c1mesh.core.threads import background, take_rows
from c1mesh.core.threads import workers as thread_count
from c1mesh.core.tile import Tile, bounds, finite_rows, row_min
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.engine.properties import scheme_properties
from c1mesh.engine.refine import refined_counts
from c1mesh.engine.schemes import get_scheme
from c1mesh.engine.topology import edge_table
from c1mesh.engine.triangulation import delaunay
from c1mesh.formats import MeshSize, check_mesh_size, read_cloud
from c1mesh.formats.depth import DepthCamera, is_depth_image, read_depth_source
from c1mesh.geo.products import (
    add_contour_facts,
    contour_grid,
    geo_plan,
    level_for_edge,
    stage_contours,
)
from c1mesh.geo.products import finish as _finish_geo
from c1mesh.geo.raster import (
    SIDE_KINDS,
    dem_sampling,
    fill_distance,
    grid_facts,
    mosaic_paths,
    raster_axis,
    tile_targets,
    write_fit_rasters,
    write_input_rasters,
)
from c1mesh.geo.raster_grid import FillRule
from c1mesh.pipeline.depth_fit import fit_perspective
from c1mesh.pipeline.plan import (estimated_normals, fit_plan, resolve_options_axis, resolved_smoothing,
                                  smoothing_strength)
from c1mesh.pipeline.report import ReportCore, crs_facts
from c1mesh.pipeline.steps import (
    FitResult,
    FitRun,
    StageTimer,
    WorldSurface,
    compact_vertices,
    display_name,
    limited_interpolator,
    mesh_pieces,
    smoothed_interpolator,
    write_surface,
)
from c1mesh.stages.curtains import remove_curtains, view_rules_apply
from c1mesh.stages.frame import choose_frame
from c1mesh.stages.ground import choose_points, resolved_classes
from c1mesh.stages.height_field import height_field
from c1mesh.stages.height_gradients import height_gradients, height_neighbours, height_normals, use_height_gradients
from c1mesh.stages.hole_fill import LatticeVertices, filled_lattice, point_hull
from c1mesh.stages.holes import with_spanning_triangles
from c1mesh.stages.limiter import LimiterReport
from c1mesh.stages.limiter import check_mode as check_overshoot_mode
from c1mesh.stages.normals import estimate_normals
from c1mesh.stages.perspective import frame_kind
from c1mesh.stages.smoothing import (SmoothingControl, SmoothingData, SmoothingRun, gradient_data_weight,
                                     search_windows, smooth_tile)
from c1mesh.stages.surface import PLANE_LEVEL
from c1mesh.stages.lattice_mesh import (auto_spacing, check_cells_left, check_lattice_spacing, is_auto,
                                        lattice_mesh, lattice_offset, nearest_points,
                                        support_least_strength)
from c1mesh.stages.trim import TrimReport, check_triangles_left, trim_again, trim_mesh, used_points
from c1mesh.stages.warnings import auto_limit, fit_warnings, smoothing_suggestion
from c1mesh.survey.sizing import fits_in_memory, point_bytes

NORMAL_MODES = ("auto", "file", "estimate")
STAGES = ("read", "normals", "frame", "gradients", "triangulate", "interpolate", "refine", "write")


@dataclass
class FitOptions:
    """Everything `c1mesh fit` can be told, with the CLI's defaults.

    axis: "auto", "x", "y", "z" or "X,Y,Z"; normals: "auto" | "file" | "estimate";
    k: neighbours for normal estimation; classes: which LAS/LAZ points to fit: "auto"
    (the default: the ground class 2 when the file has any, else the ground that
    c1mesh.stages.ground's filter finds), "all", "filter" (the filter's ground even when
    the file has class 2) or a tuple of classification codes (None: all, as before);
    max_slope: degrees — points whose normal is within this of perpendicular to the axis
    are dropped; max_edge: "auto", None (no limit) or a length in the scan's units;
    scheme: shape-function tuple; level: each triangle becomes level² triangles, None =
    chosen: PLANE_LEVEL for a height field, about one output vertex per valid pixel in the
    perspective frame (depth_fit.perspective_level);
    overshoot: "limit" (default) limits gradients that disagree with the heights and picks
    edge directions that keep thin triangles tame (c1mesh.stages.limiter), "off" uses the data as is;
    workers: threads for every stage and for BLAS (c1mesh.core.threads.limit; None: the
    process-wide setting, by default the CPUs this process may use);
    output_format: mesh format of the output (default: its extension, PLY for a stream);
    memory: bytes (or a size such as "4G") the reader may read and decode, None = default;
    bounds: (xmin, ymin, xmax, ymax) world x/y box, closed: fit only the points inside
    (a COPC file decodes only the octree nodes that meet it: c1mesh.formats.copc).
    """

    input_format: str | None = None
    axis: Any = "auto"
    normals: str = "auto"
    k: int = 16
    classes: Any = "auto"
    max_slope: float = 85.0
    max_edge: Any = "auto"
    scheme: str = "sextic"
    level: int | None = None
    ascii: bool = False
    overshoot: str = "limit"
    # vertex gradients (c1mesh.stages.height_gradients): "auto" fits them to the heights where the
    # normals were estimated and takes the file's normals otherwise; "normals" | "heights".
    gradients: str = "auto"
    workers: int | None = None
    output_format: str | None = None
    memory: Any = None
    bounds: tuple[float, float, float, float] | None = None
    # Georeferencing and rasters (c1mesh.core.crs, c1mesh.geo.raster, c1mesh.geo.preview): crs assigns a
    # CRS (EPSG:XXXX, WKT, or a file) where the input has none; resolution is the GeoTIFF
    # cell size, or for meshes the target mean edge length (chooses the level); slope,
    # aspect, hillshade are extra GeoTIFF paths; preview a PNG path; contours a vector file
    # (.gpkg, .geojson, .shp) of contour lines every `interval` of height (c1mesh.geo.contours).
    crs: str | None = None
    resolution: float | None = None
    slope: str | None = None
    aspect: str | None = None
    hillshade: str | None = None
    slope_method: str = "auto"
    preview: str | None = None
    # support: a GeoTIFF path of each DEM cell's distance to the nearest point the fit used;
    # fill: the DEM's fill of the trim's holes (geo.raster.fill_distance): "hull" (every cell
    # inside the hull of the points), "off" (or 0: the holes stay nodata) or a distance D.
    support: str | None = None
    fill: Any = "hull"
    contours: str | None = None
    interval: float | None = None
    # z_factor: x, y units per height unit (ArcGIS's z-factor; gdaldem's -s is its inverse),
    # for the angles of slope, hillshade and the preview's shading (atan(|grad z| * z_factor))
    # and, for a header height column fitted in plan units, of max_slope. None: 1 where x, y
    # and z share one unit; unknown for a header height column (`angle_z_factor`).
    z_factor: float | None = None
    # perspective frame and organised scans (depth_fit.py): frame "auto" | "axis" |
    # "perspective"; viewpoint "x,y,z[,qw,qx,qy,qz]" or None (the file's, else the origin);
    # depth images: intrinsics (fx, fy, cx, cy) pixels, depth_scale metres per unit,
    # color: path of an RGB image of the same size.
    frame: str = "auto"
    viewpoint: str | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    depth_scale: float = 0.001
    color: str | None = None
    # the smoothing fit (c1mesh.stages.smoothing, docs/smoothing.md): smooth "off" (the
    # spline through every point), "auto" (strength by cross-validation over spatial
    # blocks) or a dimensionless strength s > 0; spacing: None (vertices at the points) or
    # a length D, the vertices on a D x D lattice (c1mesh.stages.lattice_mesh), fitted to all points.
    # "default": auto on the lattice where the gradients are estimated over a height field,
    # else off (c1mesh.pipeline.plan.resolved_smoothing).
    smooth: Any = "default"
    spacing: float | str | None = None
    # edf: whether a smoothing fit estimates its effective degrees of freedom (the report's
    # smoothing.edf, null without): a diagnostic that costs one more solve (1.0 s of a 1M-node
    # lattice fit), so the CLI asks for it only when it writes a report.
    edf: bool = True

    def __post_init__(self) -> None:
        """classes given as a list (or any iterable of codes) is the tuple of its codes."""
        if not isinstance(self.classes, (str, tuple)) and self.classes is not None:
            self.classes = tuple(int(code) for code in self.classes)


def load_cloud(source, options: FitOptions) -> PointCloud:
    """Read the input and keep the points options.classes chooses (`choose_classes`)."""
    if is_depth_image(source, options.input_format):
        return read_depth_source(source, DepthCamera(options.intrinsics, options.depth_scale, options.color),
                                 options.memory)
    codes = options.classes if isinstance(options.classes, tuple) else None
    cloud = read_cloud(source, options.input_format, classes=codes, memory=options.memory,
                       bounds=options.bounds)
    cloud = choose_classes(cloud, options, display_name(source))
    _check_fit_memory(len(cloud), options, source)
    if len(cloud) == 0:
        where = f"{getattr(source, 'name', source)}: " if options.bounds else ""
        raise InputError(f"{where}the input has no points" + (f" inside --bounds {','.join(map(str, options.bounds))}"
                                                             if options.bounds else ""))
    return cloud


def choose_classes(cloud: PointCloud, options: FitOptions, name: str) -> PointCloud:
    """The points of `cloud` that options.classes chooses (c1mesh.stages.ground.choose_points:
    the ground class 2, the ground filter's ground, all, or given codes), with the facts
    of the choice in cloud.selection (the report's "classes"; None for files without
    classes)."""
    if isinstance(options.classes, tuple):
        if cloud.classification is None:
            raise InputError("--classes needs a file with a classification field (LAS/LAZ)")
        keep = np.isin(cloud.classification, np.asarray(options.classes))
        if len(cloud) and not keep.any():             # none at all: "no points" below names --bounds
            found = np.unique(cloud.classification)[:20].tolist()
            raise InputError(f"no points of class {list(options.classes)}; the file has classes {found}")
        cloud = cloud.subset(keep)
    if cloud.classification is None and options.classes == "filter":
        raise InputError(f"{name}: --classes filter classifies LAS/LAZ points; this input has no classes")
    if len(cloud) == 0:
        return cloud
    keep, facts = choose_points(cloud.classification, cloud.points, cloud.crs, options.classes)
    if keep is not None:
        cloud = cloud.subset(keep)
        if not len(cloud):
            raise InputError(f"{name}: the ground filter found no ground among {len(keep)} points")
    cloud.selection = facts
    return cloud


def _check_fit_memory(count: int, options: FitOptions, source=None) -> None:
    """Refuse, before any stage runs, a cloud whose in-memory fit needs more than the
    --memory bytes (sizing.point_bytes per point). LAS/LAZ files beyond it never get
    here (they are fitted in tiles); other formats would otherwise run over the budget,
    and so would LAS/LAZ data the tiled fit cannot reread (`_tiles_advice`)."""
    plan = fit_plan(options)
    memory, per_point = plan.memory, point_bytes(plan.surface)
    if not fits_in_memory(count, memory, per_point):
        raise InputError(f"{count} points need about {count * per_point / 1e6:.0f} MB to fit in "
                         f"memory, more than --memory {memory / 1e6:.0f} MB; {_tiles_advice(source, options)}")


def _tiles_advice(source, options: FitOptions) -> str:
    """What to do about an input too large for the in-memory fit that was not fitted in
    tiles (survey.sizing.needs_tiles): LAS/LAZ files are, but not LAS/LAZ data on a
    stream, which the tiled fit cannot read more than once; other formats never are."""
    stream = source is None or not isinstance(source, (str, Path))
    if stream and (options.input_format or "").lower().lstrip(".") in LAS_FORMATS:
        return ("a LAS/LAZ input is fitted in tiles only from a file, which is read more than once, not from "
                "a stream: save it as a .las or .laz file, or raise --memory")
    return "only LAS/LAZ inputs are fitted in tiles: raise --memory, thin the input, or convert it to LAS/LAZ"


def _check_normals_mode(mode: str) -> None:
    if mode not in NORMAL_MODES:
        raise InputError(f"--normals must be one of {', '.join(NORMAL_MODES)}, got {mode!r}")


def cloud_normals(cloud: PointCloud, options: FitOptions) -> tuple[np.ndarray, str]:
    """The normals to use and where they came from ("file" or "estimated")."""
    _check_normals_mode(options.normals)
    if options.normals == "file" and cloud.normals is None:
        raise InputError("the input has no normals; use --normals estimate (or auto)")
    if cloud.normals is not None and options.normals != "estimate":
        return cloud.normals, "file"
    finite = np.isfinite(cloud.points).all(axis=1)
    if finite.sum() < 3:
        raise InputError(f"only {int(finite.sum())} points have finite coordinates; need at least 3")
    points = cloud.points if finite.all() else cloud.points[finite]   # one copy at most
    towards = choose_frame(points, None, options.axis).axes[2]
    normals = np.full(cloud.points.shape, np.nan)
    normals[finite] = estimate_normals(points, k=options.k, towards=towards)
    return normals, "estimated"


@dataclass
class SurfaceModel:
    """The C1 spline of a cloud before refinement (what `build_surface` returns).

    normal_source: "file" or "estimated"; frame: the ScanFrame; hf: the HeightField of the
    cloud; trim_report: trim.TrimReport; used: (n,) ascending indices into hf of
    the points some triangle uses; interp: the RSDInterpolator over hf.xy[used] (its
    triangles index those n points); overshoot: the limiter's report (c1mesh.stages.limiter);
    gradient_source: "heights" (c1mesh.stages.height_gradients) or "normals".
    smoothing: the c1mesh.stages.smoothing.SmoothFit of a smoothing fit, else None.
    max_slope_not_applied: why max_slope dropped nothing (heights in units of their own
    and no z_factor: slopes are no angles), else None.
    trimmed: for a fit built with fill=True (a DEM that spans its holes), (T,) bool over
    interp's triangles: those the trim kept (the mesh's); the others span holes the trim
    opened (long edges, curtains). None: every triangle is the trim's.
    lattice: the report facts (stages.lattice_mesh.lattice_facts) of a fit whose vertices
    are the nodes of the --spacing lattice, fitted to all of hf's points (`on_lattice`);
    `used` then holds the point nearest each node (not ascending, not distinct) and
    trim_report counts the lattice's triangles. None: the vertices are points.
    """

    normal_source: str
    frame: Any
    hf: Any
    trim_report: Any
    used: np.ndarray
    interp: RSDInterpolator
    overshoot: Any = None
    gradient_source: str = "normals"
    max_slope_not_applied: str | None = None
    smoothing: Any = None
    trimmed: np.ndarray | None = None
    lattice: dict | None = None

    @property
    def on_lattice(self) -> bool:
        """Whether the vertices are lattice nodes (not points): `lattice` holds its facts."""
        return self.lattice is not None


def _fit_heights_first(cloud: PointCloud, options: FitOptions) -> bool:
    """Whether the normals come from the height fit instead of PCA: they are to be
    estimated, the gradients to come from the heights, and the height axis is given
    (not "auto", whose frame is chosen from the normals)."""
    _check_normals_mode(options.normals)
    estimated = options.normals == "estimate" or (cloud.normals is None and options.normals == "auto")
    auto_axis = isinstance(options.axis, str) and options.axis.strip().lower() == "auto"
    return estimated and not auto_axis and use_height_gradients(options.gradients, "estimated")


def height_column_axis(cloud: PointCloud, options: FitOptions) -> tuple[FitOptions, str | None]:
    """The options with axis "auto" resolved to z where a text table's header names its
    third column as a height (PointCloud.height_column) and the normals are to be
    estimated, and a phrase for the report (None when nothing was resolved).

    A named height is the height whatever its units; file normals instead say that x, y
    and z share one metric (a normal is a direction in it), so with them "auto" keeps
    choosing the axis from the normals (a tilted scan exported with a header).
    """
    auto_axis = isinstance(options.axis, str) and options.axis.strip().lower() == "auto"
    estimated = options.normals == "estimate" or (cloud.normals is None and options.normals == "auto")
    if cloud.height_column is None or not auto_axis or not estimated:
        return options, None
    return replace(options, axis="z"), f"z: the header's height column '{cloud.height_column}'"


def _plan_heights(cloud: PointCloud, frame) -> bool:
    """Whether the heights are a header's height column over the plan (x, y): the frame's
    axis is ±z and the file names z as a height. Then its units need not be those of x
    and y, and nothing may treat (x, y, z) as one metric (height_field.height_field's
    common_metric, the curtain rules' angles)."""
    return cloud.height_column is not None and bool(np.array_equal(np.abs(frame.axes[2]), [0.0, 0.0, 1.0]))


def plan_unit_heights(cloud: PointCloud, options: FitOptions) -> bool:
    """Whether build_surface fits these heights in plan units (`_plan_heights`: a header's
    height column over x, y, the gradients fitted to the heights), so that no angle is
    known without a z_factor. Reads nothing; the frame of a given axis is cheap."""
    options = height_column_axis(cloud, options)[0]
    if cloud.height_column is None or not _fit_heights_first(cloud, options):
        return False
    return _plan_heights(cloud, choose_frame(cloud.points, None, options.axis))


def angle_z_factor(cloud: PointCloud, options: FitOptions) -> float | None:
    """x, y units per height unit for slope angles: options.z_factor when given, 1 when x,
    y and z share one unit, None (unknown) for heights in units of their own."""
    if options.z_factor is not None:
        return float(options.z_factor)
    return None if plan_unit_heights(cloud, options) else 1.0


def check_angles(cloud: PointCloud, options: FitOptions, name) -> None:
    """InputError, before any work, for slope or hillshade rasters of heights whose units
    are not those of x and y and no z_factor to relate them (angles would be wrong)."""
    if (options.slope or options.hillshade) and angle_z_factor(cloud, options) is None:
        raise InputError(
            f"{name}: the header's height column '{cloud.height_column}' may be in other units "
            "than x and y, so slope and hillshade angles are unknown; give --z-factor F, the "
            "x, y units per height unit (1 if they share a unit; 0.02 for x, y in 50 ft and z "
            "in ft); --aspect needs none")


def _drop_too_steep(hf, max_slope: float, z_factor: float) -> None:
    """Drop the points of a plan-unit height field (heights in units of their own) whose
    slope atan(|grad| * z_factor) exceeds max_slope degrees, as height_field.height_field does
    for one metric; counted as "too_steep". Changes hf in place."""
    steep = np.hypot(hf.gradients[:, 0], hf.gradients[:, 1]) * z_factor > np.tan(np.radians(max_slope))
    if not steep.any():
        return
    keep = ~steep
    hf.xy, hf.z, hf.gradients, hf.source_index = hf.xy[keep], hf.z[keep], hf.gradients[keep], hf.source_index[keep]
    hf.dropped["too_steep"] += int(steep.sum())
    if hf.xy.shape[0] < 3:
        raise InputError(f"only {hf.xy.shape[0]} points have a slope below --max-slope {max_slope:g}°")


def build_surface(cloud: PointCloud, options: FitOptions, timer: "StageTimer | None" = None,
                  check_triangulation: Callable[[np.ndarray, np.ndarray, Any], None] | None = None,
                  fill: bool = False) -> SurfaceModel:
    """normals → frame → height field → triangulate + trim → interpolate, for one cloud.

    The stages every fit shares, whole-file or tiled (c1mesh.survey.tiles), so a stage added
    here reaches both. timer: a StageTimer that books each stage (None: untimed).
    check_triangulation(points (n, 2), triangles (T, 3), topology.EdgeTable): called with the
    interpolator's triangulation once it is known, before the interpolation, so a caller
    can refuse what it would refine (`_output_size_check`) before the heavy stages.
    fill=True (a DEM's fill, geo.raster.FillRule): the spline also spans the holes the trim
    opened, over the triangles of the Delaunay triangulation that only the long-edge and
    curtain rules removed (filled_mesh); SurfaceModel.trimmed says which are the trim's.
    """
    timer = timer or StageTimer(None)
    scheme = get_scheme(options.scheme)
    check_overshoot_mode(options.overshoot)
    smoothing_strength(options)                    # a bad --smooth or --spacing: before any work
    options = height_column_axis(cloud, options)[0]
    heights_first = _fit_heights_first(cloud, options)
    plan_heights = False          # heights in units of their own over the plan (x, y)
    with contextlib.ExitStack() as stages:
        with timer.stage("normals"):
            guess = None             # () -> the _TrimmedGuess of _guessed_triangles, or None
            guessed_sort: Future = Future()      # its height field's PlaneSort, set before its Delaunay
            if heights_first:        # the frame needs no normals: the fit's serve the height field
                options = resolved_smoothing(options, estimated=True)
                frame = choose_frame(cloud.points, None, options.axis)
                plan_heights = _plan_heights(cloud, frame)
                threads = thread_count()
                if threads > 1 and options.spacing is None:   # one thread: no guess to waste
                    # the guess's Delaunay is the longer of the two: a core of its own
                    guess = stages.enter_context(background(
                        partial(_guessed_triangles, cloud.points, frame, options, plan_heights, guessed_sort)))
                    threads -= 1
                normals = height_normals(cloud.points, frame, k=height_neighbours(options.k), workers=threads)
                normal_source = "estimated"
            else:
                normals, normal_source = cloud_normals(cloud, options)
                options = resolved_smoothing(options, estimated=estimated_normals(normal_source))
        strength = smoothing_strength(options)
        with timer.stage("frame"):
            if not heights_first:    # else the frame is chosen: the axis is given, normals do not change it
                frame = choose_frame(cloud.points, normals, options.axis)
                if thread_count() > 1 and options.spacing is None:   # the Delaunay beside the height field
                    guess = stages.enter_context(background(
                        partial(_projected_triangles, cloud.points, frame, options.max_edge)))
            # the guess's sort of the same positions, when it is ready (the bits do not depend on it)
            hf = height_field(cloud.points, normals, frame, max_slope_deg=options.max_slope,
                              common_metric=not plan_heights,
                              sort=guessed_sort.result() if guessed_sort.done() else None)
            del normals              # hf holds the gradients: 24 bytes a point less from here on
            hf.sort = guessed_sort = None
            max_slope_not_applied = None
            if plan_heights and options.z_factor is not None:
                _drop_too_steep(hf, options.max_slope, float(options.z_factor))
            elif plan_heights:
                max_slope_not_applied = (f"the header's height column '{cloud.height_column}' may be in "
                                         "other units than x and y, so slopes are no angles; give --z-factor")
        with timer.stage("gradients"):
            gradient_source = "heights" if heights_first else "normals"
            if not heights_first and use_height_gradients(options.gradients, normal_source):
                hf.gradients = height_gradients(hf.xy, hf.z, k=height_neighbours(options.k))
                gradient_source = "heights"
        if options.spacing is not None:       # the smoothing's vertices on a lattice (stages.lattice_mesh)
            stages.close()
            if is_auto(options.spacing):      # the tiles' rule: their box and count of the chosen points
                local = frame.to_local(cloud.points)[:, :2]
                options = replace(options, spacing=auto_spacing(*bounds(local[finite_rows(local)]),
                                                                 len(cloud.points)))
            return _lattice_model(hf, strength, options, (check_triangulation, fill), timer,
                                  (normal_source, frame, gradient_source, max_slope_not_applied))
        with timer.stage("triangulate"):
            xy, z, grads = hf.xy, hf.z, hf.gradients
            guessed = None if guess is None else guess()
            if guessed is not None and np.array_equal(guessed.xy, xy):
                mesh, trim_report = guessed.mesh, guessed.report
            else:
                mesh, trim_report = trim_mesh(xy, delaunay(xy), max_edge=options.max_edge)
            guess = guessed = None
            stages.close()           # the guess's thread is done: its arrays are freed now
            if not plan_heights:     # its angles and noise widths compare heights with plane lengths
                mesh, trim_report = remove_curtains(xy, z, grads, mesh, trim_report,
                                                    view_rules_apply(_fitted_classes(cloud, options), frame.axes))
            check_triangles_left(mesh.triangles.shape[0])
            trimmed, trim_only = None, mesh
            if fill:
                mesh, trimmed = filled_mesh(xy, z, grads, mesh, trim_report.max_edge, curtains=not plan_heights)
            local, triangles = compact_vertices(xy, mesh.triangles)
            used = local                      # ascending, as compact_vertices numbers
    smoothing = None
    with timer.stage("interpolate"):
        table, mesh = mesh.edge_table(local), None      # the trim's edge sort serves the interpolator
        points = take_rows(hf.xy, used)
        if check_triangulation is not None:
            check_triangulation(points, triangles, table)
        if strength is None:
            interp, overshoot = limited_interpolator(points, take_rows(hf.z, used), take_rows(hf.gradients, used),
                                                     triangles, scheme, options.overshoot, heights=not plan_heights,
                                                     table=table)
        else:
            interp, overshoot, smoothing = _smoothed(
                _FitMesh(hf, used, triangles, table), _HoleSpan(trim_only, trimmed) if fill else None,
                strength, options, gradient_data_weight(normal_source, gradient_source), not plan_heights)
    return SurfaceModel(normal_source, frame, hf, trim_report, used, interp, overshoot, gradient_source,
                        max_slope_not_applied, smoothing, trimmed)


def _lattice_model(hf, strength, options: FitOptions, checks: tuple, timer: "StageTimer",
                   facts: tuple) -> SurfaceModel:
    """The SurfaceModel of a smoothing fit on the lattice of --spacing (stages.lattice_mesh):
    every point of the height field hf fitted, the spline's vertices the lattice's nodes,
    solved by multigrid from MULTIGRID_FROM nodes (smooth_fit with the lattice) on the
    support's cells grown to whole blocks, and kept on the support's (the same spline). No
    Delaunay and no trim: the mesh is the lattice's cells near the data. Its `used` are the
    points nearest the nodes (their colours, and their inputs' ownership); no gradient data
    (the nodes are no points), unit normal edge directions (the cells are all one shape);
    "auto" searches no lower than the lattice's least_strength (its cells ring below it).
    checks: build_surface's check_triangulation and fill; a DEM's fill spans the cells of the
    points' hull that the support leaves open (the lattice closes gaps of a few cells),
    their nodes chosen by the energy alone with the support's held (stages.hole_fill;
    `trimmed` then marks the support's triangles). Memory: the fit
    runs smooth_tile on the whole mesh and keeps only its values on the support (no edge
    table and no interpolator of the whole mesh: the run asks for no edge directions), and
    the support's mesh and edge table are built after the fit unless the check needs them
    first."""
    normal_source, frame, gradient_source, max_slope_not_applied = facts
    check_triangulation, fill = checks
    with timer.stage("triangulate"):
        check_lattice_spacing(options.spacing, hf.spacing)
        mesh = lattice_mesh(hf.xy, options.spacing, hf.spacing, lattice_offset(frame.origin, options.spacing))
        check_cells_left(int(mesh.shown.sum()), mesh.grid)
        support = None                  # made after the fit unless the check needs it now (0.2 GiB at 1M nodes)
        if check_triangulation is not None:
            support = _support_mesh(mesh)
            check_triangulation(mesh.points[support[0]], *support[1:])
    scheme = get_scheme(options.scheme)
    windows = search_windows(hf.xy) if strength == "auto" else None    # the survey's
    least = support_least_strength(options.spacing, hf.spacing, int(mesh.shown.sum()), hf.xy.shape[0])
    control = SmoothingControl(strength, scheme, windows=windows, least_strength=least, edf=options.edf,
                               fold_net=True)
    run = SmoothingRun(control, hf.spacing, "off", 0.0)
    count = mesh.points.shape[0]
    with timer.stage("interpolate"), background(lambda: point_hull(hf.xy) if fill else None) as hull:
        tile = Tile.whole(mesh.points, np.zeros(count), np.zeros((count, 2)), mesh.triangles)
        solved = smooth_tile(tile, run, data=SmoothingData(hf.z, hf.spacing, hf.xy), lattice=mesh.solver_lattice())
        overshoot, smoothing = LimiterReport(directions_changed=solved.solve.turned), solved.fit
        shown, triangles, table = _support_mesh(mesh) if support is None else support
        vertices = LatticeVertices(mesh.nodes[shown], solved.values[shown], solved.gradients[shown], triangles)
        sources, trimmed = mesh.sources[shown], None
        if fill:                        # a DEM's fill: the hull's cells beyond the support (stages.hole_fill)
            vertices, trimmed = filled_lattice(mesh.grid, vertices, hull(), scheme)
            sources = np.concatenate([sources, nearest_points(mesh.grid.positions(vertices.nodes[sources.size:]),
                                                              hf.xy, np.arange(hf.xy.shape[0]))])
            table = table if trimmed.all() else edge_table(vertices.triangles, vertices.nodes.size)
        interp = RSDInterpolator(mesh.grid.positions(vertices.nodes), vertices.values, vertices.gradients,
                                 triangles=vertices.triangles, scheme=scheme, edge_table=table)
    kept = triangles.shape[0]
    return SurfaceModel(normal_source, frame, hf, TrimReport(kept, kept), sources, interp, overshoot,
                        gradient_source, max_slope_not_applied, smoothing, trimmed, mesh.facts())


def _support_mesh(mesh) -> tuple:
    """(shown, triangles, table): a LatticeMesh's support (shown_mesh: the output's node
    rows (u,) and triangles (S, 3) into them) and its topology.edge_table."""
    shown, triangles = mesh.shown_mesh()
    return shown, triangles, edge_table(triangles, shown.size)


@dataclass(frozen=True)
class _TrimmedGuess:
    """A triangulation made ahead of the height field, in a background thread (a second
    core's work), and its trim: xy (n, 2) the plane points guessed, mesh and report what
    trim_mesh(xy, delaunay(xy), max_edge) gives. The trim needs only the positions, so it
    runs there too, beside the true height field's merge of normals (0.15-0.2 s at 1M
    points). build_surface takes them only when the true height field's xy equal xy, bit
    for bit, so no output depends on the guess."""

    xy: np.ndarray
    mesh: Any
    report: TrimReport


def _trimmed_guess(xy: np.ndarray, max_edge) -> _TrimmedGuess | None:
    """The _TrimmedGuess of xy, or None when the Delaunay or the trim fails (the true
    height field's, made again in build_surface, says why if it fails too)."""
    try:
        mesh, report = trim_mesh(xy, delaunay(xy), max_edge=max_edge)
    except C1MeshError:
        return None
    return _TrimmedGuess(xy, mesh, report)


def _guessed_triangles(points: np.ndarray, frame, options: FitOptions, plan_heights: bool,
                       sort: Future) -> _TrimmedGuess | None:
    """The triangulation and trim (_TrimmedGuess) of the height field the points would
    give if no normal dropped any of them (every normal along the frame's height axis):
    the Delaunay, one thread of a library for 0.8-1 s at 1M points, then runs beside the
    height normals (a second core's work) instead of after them. The positions, the
    duplicate merge and the spacing depend on the points alone, so the guess is the height
    field's xy whenever the normals drop no point (too steep, unusable). None when the
    guessed height field or its triangulation fails.
    sort: set to the guessed height field's PlaneSort (None if it failed) before the
    Delaunay starts, for the true height field to take back (height_field's `sort`)."""
    up = np.broadcast_to(frame.vectors_to_world(np.array([[0.0, 0.0, 1.0]])), points.shape)
    try:
        guessed = height_field(points, up, frame, max_slope_deg=options.max_slope, common_metric=not plan_heights)
    except C1MeshError:
        sort.set_result(None)
        return None
    sort.set_result(guessed.sort)
    xy, guessed = guessed.xy, None
    return _trimmed_guess(xy, options.max_edge)


def _projected_triangles(points: np.ndarray, frame, max_edge) -> _TrimmedGuess | None:
    """The triangulation and trim (_TrimmedGuess) of every point's position in the
    frame's plane: the height field's xy (computed the same way, bit for bit) when it
    keeps every point, which it does unless a normal is unusable or too steep, or points
    are stacked or merged. A fit with given normals starts it once the frame is chosen, so
    the Delaunay (one thread of a library for 0.8-1.2 s at 1M points) runs while the
    height field is made on the other core, not after it. None for non-finite points or
    when the Delaunay or trim fails."""
    pts = np.asarray(points, dtype=np.float64)
    if not np.isfinite(pts).all():
        return None
    xy = np.ascontiguousarray(frame.to_local(np.ascontiguousarray(pts))[:, :2])
    return _trimmed_guess(xy, max_edge)


@dataclass(frozen=True)
class _FitMesh:
    """What the interpolation stage fits: the height field hf, the used (n,) ascending
    indices into hf of the triangulation's points, its triangles (T, 3) over them and their
    edge table."""

    hf: Any
    used: np.ndarray
    triangles: np.ndarray
    table: Any


@dataclass(frozen=True)
class _HoleSpan:
    """A DEM's fill (filled_mesh): the trimmed TrimmedMesh over the triangulated points and
    trimmed (T,) bool over the filled triangles, those the trim kept."""

    trim_only: Any
    trimmed: np.ndarray


def _smoothed(mesh: _FitMesh, span: _HoleSpan | None, strength, options, weight: float, heights: bool):
    """The smoothing fit's (interpolator, limiter report, SmoothFit) over mesh; weight: of
    the gradient data (gradient_data_weight); heights: limit with the heights (not for a
    plan-unit height column).

    span None: fitted over mesh's triangles. A DEM's fill: the smoothing fits the trimmed
    triangles, as without a fill, and the holes' triangles are spanned by the spline of its
    vertex values and gradients (the data's at points only those triangles use), the
    gradients at their vertices limited as an exact fit's are (steps.limited_interpolator):
    fitted over the holes' long triangles, the smoothing spline dug pits of up to 9.7 ft
    into autzen_trim's ground beside a bank (0.36 ft so)."""
    hf, used, scheme = mesh.hf, mesh.used, get_scheme(options.scheme)
    windows = search_windows(hf.xy) if strength == "auto" else None    # the survey's
    run = SmoothingRun(SmoothingControl(strength, scheme, windows=windows, edf=options.edf), hf.spacing,
                       options.overshoot, weight)

    def tile(vertices, triangles):          # the in-memory fit's one tile (core.tile)
        return Tile.whole(hf.xy[vertices], hf.z[vertices], hf.gradients[vertices], triangles)
    if span is None:
        return smoothed_interpolator(tile(used, mesh.triangles), run, None, mesh.table)
    inner_used, inner = compact_vertices(hf.xy, span.trim_only.triangles)
    fitted, overshoot, smoothing = smoothed_interpolator(tile(inner_used, inner), run, None,
                                                         span.trim_only.edge_table(inner_used))
    at = np.searchsorted(used, inner_used)              # the trimmed mesh's vertices are the filled one's
    values, gradients = hf.z[used].copy(), hf.gradients[used].copy()
    values[at], gradients[at] = fitted.values, fitted.gradients
    limited = limited_interpolator(hf.xy[used], values, gradients, mesh.triangles, scheme, options.overshoot,
                                   heights=heights, table=mesh.table)[0]
    spanning = np.zeros(used.size, dtype=bool)          # vertices of the holes' triangles: limited there
    spanning[mesh.triangles[~span.trimmed].ravel()] = True
    gradients = np.where(spanning[:, None], limited.gradients, gradients)
    interp = RSDInterpolator(hf.xy[used], values, gradients, triangles=mesh.triangles, scheme=scheme,
                             directions=limited.directions, edge_table=mesh.table)
    return interp, overshoot, smoothing


def filled_mesh(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray, mesh, max_edge: float | None,
                curtains: bool = True):
    """The triangles of a DEM that spans the trim's holes, and which of them the trim kept.

    xy (n, 2), z (n,), gradients (n, 2): the triangulated points; mesh: the trimmed
    TrimmedMesh (trim_mesh, then remove_curtains), max_edge its long-edge limit. Returns (TrimmedMesh, trimmed (T',) bool
    over its triangles). The filled mesh is the union of the trimmed one and the
    triangulation trimmed without max_edge and without the view-ray curtain rules (they
    open the holes under buildings, trees and water): what stays out are the slivers and
    bowties on the hull's rim and the triangles thinner than the noise, which the spline
    cannot span (it divides by their width; curtains.py). The union is a subset of one
    triangulation, so it stays edge-manifold. Its long triangles are stages.holes'
    (with_spanning_triangles), as a survey fitted in tiles finds them."""
    mesh = with_spanning_triangles(xy, mesh, max_edge)
    whole, report = trim_again(mesh, max_edge=None)
    if curtains:
        whole, _ = remove_curtains(xy, z, gradients, whole, report, view_rules=False)
    alive = whole.alive | mesh.alive
    return mesh.with_alive(alive), mesh.alive[alive]


def _fitted_classes(cloud: PointCloud, options: FitOptions) -> tuple[int, ...] | None:
    """The classification codes of the points fitted: options.classes when it names codes,
    else what the loader chose (cloud.selection: the filter's ground counts as class 2)."""
    return options.classes if isinstance(options.classes, tuple) else resolved_classes(cloud.selection)


def fit_in_memory(source, output, options: FitOptions, on_stage: Callable[[str], None] | None,
                  keep_mesh: bool) -> FitResult:
    """Fit one input in memory, as one tile: c1mesh.pipeline.run.fit's execution for every
    fit that is not run in tiles (its caller checked the output and set the threads).

    source: path, binary stream (then options.input_format is required) or a PointCloud
    already loaded (classes already selected: a survey's cloud, c1mesh.survey.tiles);
    output: path, binary stream, or None to only return the mesh. Returns the mesh (world
    coordinates, unit vertex normals on the axis side, colours when the input has them)
    and a report dict (counts, frame, trimming, scheme properties, C1 certificate,
    timings; the schema of c1mesh.pipeline.report). The perspective frame branches to
    c1mesh.pipeline.depth_fit; a raster output is a DEM sampled from the spline.
    keep_mesh=False (with an output) streams the mesh to the output block by block
    instead of assembling it: the result's mesh is then None, and memory and time drop
    (the CLI does this). The spline is then evaluated by a second thread ahead of the
    writer: "refine" reports the time the writer waited for evaluated blocks and
    "write" the rest of the writing.
    """
    geo = geo_plan(output, options)
    if geo.height_field:
        options = replace(options, axis=raster_axis(options.axis))
    options, axis_reason = resolve_options_axis(source, options)
    timer = StageTimer(on_stage)
    with timer.stage("read"):
        cloud = source if isinstance(source, PointCloud) else load_cloud(source, options)
        crs, crs_source = resolve_crs(cloud.crs, geo.user_crs, display_name(source))
    selection = cloud.selection
    if not isinstance(options.classes, tuple):  # later stages see codes: the filter's ground as 2
        options = replace(options, classes=resolved_classes(selection))
    if geo.contours is not None:      # GeoJSON needs an EPSG code: refused now, not after the fit
        geo = replace(geo, contours=geo.contours.with_crs(crs, geo.user_crs))
    options, column_reason = height_column_axis(cloud, options)
    axis_reason = column_reason or axis_reason
    check_angles(cloud, options, display_name(source))
    angles = {"z_factor": angle_z_factor(cloud, options)}   # None: unknown (geo.finish: unshaded preview)
    if frame_kind(options.frame, cloud.grid_shape is not None, dem=geo.height_field) == "perspective":
        return fit_perspective(cloud, source, output, options, timer, keep_mesh, crs, crs_source)
    fill = fill_distance(options.fill) if geo.rasters.items() else None
    model = build_surface(cloud, options, timer,
                          None if geo.rasters.items() else _output_size_check(output, options, cloud),
                          fill=fill is not None)
    frame, hf, trim_report, used, interp = model.frame, model.hf, model.trim_report, model.used, model.interp
    if geo.rasters.items():
        data_xy = (cloud.points - frame.origin)[:, :2]      # the raster frame's axes are the world's
        rule = None if fill is None else FillRule(model.trimmed, fill)
        dem = dem_sampling(interp, frame, options.resolution, data_xy, trim_report.max_edge, rule, fit_points(model))
        with _Contours(geo, interp, frame, dem[0], timer) as contours:
            with timer.stage("raster"):
                raster_report = write_fit_rasters(geo.rasters, *dem, options, crs, model.smoothing is not None)
        report = _report(FitRun(source, output, options, cloud, timer, angles["z_factor"],
                                crs_facts(crs, crs_source)), model)
        report["raster"] = {**raster_report, "fill": fill_facts(options.fill, fill, model)}
        report.update({} if selection is None else {"classes": selection})
        contours.add_to(report)
        return _finish_geo(FitResult(None, report),
                           interp, frame, crs, crs_source, options, dem=dem)
    level, level_from = plane_level(interp.points, interp.triangles, options)
    options = replace(options, level=level)
    colors = None if cloud.colors is None else cloud.colors[hf.source_index[used]]
    grid = contour_grid(interp, frame, None, level, options.resolution) if geo.contours else None
    # the report's pieces and C1 certificate (0.2 s at 1M points) need the surface alone: with
    # a second thread they are found while the mesh is refined and written, not after it
    with _Contours(geo, interp, frame, grid, timer) as contours, \
            background(lambda: surface_facts(cloud, model, options)) as facts:
        mesh, stream = write_surface(WorldSurface(interp, frame, colors), output,
                                     MeshTarget(options.output_format, options.ascii, crs), level, timer, keep_mesh)
        found = facts()
    frame_report = frame_facts(frame)
    frame_report["axis_choice"] = axis_reason if axis_reason != "auto" else frame.axis_reason
    report = _report(FitRun(source, output, options, cloud, timer, angles["z_factor"], crs_facts(crs, crs_source)),
                     model, stream, frame_report, level_from, found)
    report.update({} if selection is None else {"classes": selection})
    contours.add_to(report)
    return _finish_geo(FitResult(mesh, report), interp, frame, crs, crs_source, options)


def fit_dem_tiles(survey, outputs, options: FitOptions, timer: StageTimer | None = None) -> dict:
    """`--seamless -O DIR --suffix .tif`: the survey (survey.tiles.Survey) fitted once, one
    DEM per input (outputs[i], a window of the survey's DEM grid: dem_windows), with its
    side rasters DIR/NAME.slope.tif, ... (tile_targets), and their VRT mosaics
    (mosaic_paths); returns the report. Every cell is sampled from the one spline at its
    index in the survey's grid (Horn's differences too), so a cell two tiles share is equal
    in both and each mosaic equals the survey's raster (`--seamless -o`) cell for cell. An
    input whose points and triangles are nowhere (no points of --classes) gets no DEM. On
    failure every raster and mosaic already written is removed."""
    timer = timer or StageTimer(None)
    options = replace(options, axis=raster_axis(options.axis))
    plain = replace(options, **{kind: None for kind in SIDE_KINDS})        # their paths are mosaics here
    sides = side_rasters(options)
    crs, crs_source = resolve_crs(survey.cloud.crs, geo_plan(outputs[0], plain).user_crs, survey.names[0])
    fill = fill_distance(options.fill)
    model = build_surface(survey.cloud, options, timer, fill=fill is not None)
    mosaics = mosaic_paths(outputs, sides)
    with timer.stage("raster"):
        data_xy = (survey.cloud.points - model.frame.origin)[:, :2]
        grid, sampler = dem_sampling(model.interp, model.frame, options.resolution, data_xy,
                                     model.trim_report.max_edge,
                                     None if fill is None else FillRule(model.trimmed, fill), fit_points(model))
        tiles = write_input_rasters(
            outputs, [tile_targets(output, sides) for output in outputs], dem_windows(grid, survey, model),
            lambda targets, window: write_fit_rasters(targets, window, sampler, options, crs,
                                                      model.smoothing is not None),
            grid, mosaics, crs)
    report = _report(FitRun(survey.names[0], outputs[0], options, survey.cloud, timer,
                            angle_z_factor(survey.cloud, options), crs_facts(crs, crs_source)), model)
    report.update(input=list(survey.names), output=list(outputs))
    report["raster"] = {"grid": grid_facts(grid), "mosaics": mosaics, "tiles": tiles, "fill": fill_facts(options.fill, fill, model)}
    return report


def side_rasters(options: FitOptions) -> dict:
    """{kind: the path --slope, --aspect, --hillshade, --support give (None: not asked)},
    in SIDE_KINDS' order."""
    return {"slope": options.slope, "aspect": options.aspect, "hillshade": options.hillshade,
            "support": options.support}


def dem_windows(grid, survey, model: SurfaceModel) -> list:
    """Per input of the survey, the window of the survey's DEM grid (RasterGrid.window) its
    DEM covers, or None: every cell holding one of its points and every cell whose centre
    lies in the bounding box of a triangle it owns (the triangle's lowest-numbered corner
    point is its: survey.tiles' ownership rule). Every cell the survey's DEM gives a value
    lies in some window: in a triangle, or holding a point (the nearest-triangle rule)."""
    interp, origin = model.interp, model.frame.origin
    corner = model.hf.source_index[model.used]                   # interpolator vertex -> survey point
    owner = survey.input_of(row_min(corner[interp.triangles]))
    windows = []
    for tile in range(len(survey.names)):
        points = survey.cloud.points[survey.offsets[tile]:survey.offsets[tile + 1], :2]
        owned = interp.points[interp.triangles[owner == tile]].reshape(-1, 2) + origin[:2]
        xy = np.concatenate([points, owned])
        if not len(xy):
            windows.append(None)
            continue
        windows.append(grid.window_over(*bounds(xy)))
    return windows


def fit_points(model: SurfaceModel) -> np.ndarray:
    """(k, 2) the points the fit used, in the frame's plane: the spline's vertices (the
    points it interpolates), or the data of a smoothing fit on the --spacing lattice (its
    vertices are no points). The support layer measures distances to these."""
    return model.hf.xy if model.on_lattice else model.hf.xy[model.used]


def fill_facts(option, distance: float | None, model: SurfaceModel) -> dict:
    """The report's raster.fill: the --fill asked for (its default: geo.raster.DEFAULT_FILL),
    the distance it resolved to (null: off; "inf": the whole hull) and the triangles that
    span the trim's holes."""
    spans = 0 if model.trimmed is None else int((~model.trimmed).sum())
    shown = None if distance is None else ("inf" if math.isinf(distance) else distance)
    return {"option": option, "distance": shown, "triangles_spanning_holes": spans}


class _Contours:
    """The fit's contours around the writing of its other outputs: traced and written to a
    temporary file on entry (stage "contours"), committed when the block ends without
    error, removed when it fails, so no contour file outlives a failed fit and no failed
    contouring leaves a mesh or DEM. `report`: {"contours": ...} or {} without --contours."""

    def __init__(self, geo, interp, frame, grid, timer: StageTimer):
        self.geo, self.interp, self.frame, self.grid, self.timer = geo, interp, frame, grid, timer
        self.staged, self.report = None, {}

    def __enter__(self) -> "_Contours":
        if self.geo.contours is not None:
            with self.timer.stage("contours"):
                self.staged, facts = stage_contours(self.geo.contours, self.interp, self.frame, self.grid)
            self.report = {"contours": facts}
        return self

    def add_to(self, report: dict) -> None:
        """Put the "contours" section into the fit's report (geo.products.add_contour_facts)."""
        add_contour_facts(report, self.report.get("contours"))

    def __exit__(self, kind, value, tb) -> None:
        if self.staged is None:
            return
        if kind is None:
            self.staged.commit()
        else:
            self.staged.discard()


def _output_size_check(output, options: FitOptions, cloud: PointCloud):
    """build_surface's check_triangulation for a mesh output (None without one): InputError
    when the refinement of the triangulation at the fit's level (plane_level) would be
    more than the output format holds (c1mesh.formats.check_mesh_size). The counts are
    exact (refine.refined_counts: points, edges, triangles and the level), so a fit
    too large for 32-bit counts or indices stops before interpolating and refining."""
    if output is None:
        return None
    channels = 0 if cloud.colors is None else int(cloud.colors.shape[1])

    def check(points: np.ndarray, triangles: np.ndarray, table) -> None:
        level = plane_level(points, triangles, options)[0]
        vertices, faces = refined_counts(points.shape[0], table.edges.shape[0], triangles.shape[0], level)
        check_mesh_size(output, options.output_format, MeshSize(vertices, faces, True, channels))
    return check


def plane_level(points: np.ndarray, triangles: np.ndarray, options: FitOptions) -> tuple[int, str]:
    """The refinement level of a height-field fit of the triangulation points (n, 2),
    triangles (T, 3), and where it came from: "option" (--level), "resolution" (the level
    whose mean output edge is --resolution, geo.level_for_edge) or "default" (PLANE_LEVEL)."""
    if options.resolution is not None:
        return level_for_edge(points, triangles, options.resolution), "resolution"
    if options.level is not None:
        return options.level, "option"
    return PLANE_LEVEL, "default"


def frame_facts(frame) -> dict:
    """The report's frame of a height-field (axis frame) fit."""
    return {"kind": "axis", "origin": frame.origin.tolist(), "axes": frame.axes.tolist()}


def trim_facts(trim_report) -> dict:
    """The report's triangles of a Delaunay triangulation and its trim."""
    return {"before_trim": trim_report.triangles_before, "after_trim": trim_report.triangles_after,
            "removed": dict(trim_report.removed), "max_edge": trim_report.max_edge}


def surface_facts(cloud, model: SurfaceModel, options, pieces_in_warnings: bool = True) -> dict:
    """The report's facts of a built surface that every in-memory axis-frame path shares
    (the plane fit, the DEM, --seamless -O): the pieces, the C1 certificate, the scheme
    and the warnings. pieces_in_warnings=False words the warnings without the piece
    count, as the tiled fit (which cannot count pieces) words them: the DEM and -O do."""
    interp, trim_report = model.interp, model.trim_report
    pieces = mesh_pieces(interp.points, interp.triangles, interp.edge_table)
    return {"pieces": pieces, "c1_certificate": interp.c1_certificate(),
            "scheme": scheme_properties(interp.scheme).as_dict(),
            "warnings": fit_warnings(len(cloud), points_on_surface(model), trim_report.triangles_before,
                                     trim_report.removed.get("long_edge", 0), trim_report.max_edge,
                                     auto_limit(options.max_edge),
                                     pieces["count"] if pieces_in_warnings else None,
                                     model.hf.dropped.get("duplicate", 0))}


def points_on_surface(model: SurfaceModel) -> int:
    """The points the surface uses: its vertices, or with --spacing the points its
    triangles cover (the data of the fit), for the unused-points warning. A DEM's fill
    (model.trimmed) counts the trimmed triangles' vertices: the warning is about the trim,
    and says the same for the mesh and the DEM of one fit."""
    if model.on_lattice:
        return int(model.hf.xy.shape[0] - model.smoothing.outside)
    if model.trimmed is not None:
        return used_points(model.interp.triangles, model.trimmed, model.interp.points.shape[0])
    return int(model.used.size)


def _report(run: FitRun, model: SurfaceModel, mesh=None, frame_report: dict | None = None,
            level_from: str | None = None, facts: dict | None = None) -> dict:
    """The report of an in-memory axis-frame fit (c1mesh.pipeline.report's schema). mesh:
    the written MeshStream of a plane mesh fit (its counts), with its frame_report and
    level_from; None for a raster (DEM) fit: no refinement, so level, level_from and
    output_mesh are null, and the caller adds the raster section. facts: the model's
    surface_facts if found already (None: found here)."""
    hf, used, options = model.hf, model.used, run.options
    points = {"read": len(run.cloud), "kept": int(used.size), "spacing": float(hf.spacing)}
    if mesh is not None:
        dropped = dict(hf.dropped)
        dropped["unreferenced_after_trim"] = int(hf.xy.shape[0] - points_on_surface(model))
        points = {"read": len(run.cloud), "dropped": dropped, "kept": int(used.size),
                  "normals_flipped": int(hf.flipped), "stacked": int(hf.stacked), "spacing": float(hf.spacing)}
    report = ReportCore(
        input=display_name(run.source), output=display_name(run.output), points=points,
        normals=model.normal_source, gradients=model.gradient_source,
        frame=frame_facts(model.frame) if frame_report is None else frame_report,
        triangles=trim_facts(model.trim_report), level=None if mesh is None else options.level,
        level_from=level_from,
        output_mesh=None if mesh is None else {"vertices": int(mesh.vertex_count), "faces": int(mesh.face_count)},
        **(surface_facts(run.cloud, model, options, pieces_in_warnings=mesh is not None) if facts is None
           else facts), crs=run.crs,
        seconds=run.timer.seconds, threads=thread_count(), z_factor=run.z_factor).as_dict()
    report["overshoot"] = model.overshoot.as_dict()
    if model.max_slope_not_applied is not None:          # why max_slope dropped nothing
        report["max_slope_not_applied"] = model.max_slope_not_applied
    return {**report, **smoothing_facts(model)}


def smoothing_facts(model: SurfaceModel) -> dict:
    """The report's optional sections about smoothing: "smoothing" (the SmoothFit's
    strength, λ, CV curve, effective degrees of freedom, residuals) for a smoothing fit;
    else "suggestion" where the limiter found the heights noisy (stages.warnings)."""
    if model.smoothing is not None:
        return {"smoothing": {**model.smoothing.as_dict(), "lattice": model.lattice}}
    text = smoothing_suggestion(model.overshoot.gradients_limited, int(model.used.size))
    return {} if text is None else {"suggestion": text}
