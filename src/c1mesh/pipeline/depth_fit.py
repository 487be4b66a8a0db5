"""The fit pipeline in the perspective frame: a scan seen from one viewpoint.

    normals → inverse depth over the rays → triangulate (pixel grid, or Delaunay in (u, v))
    → drop depth jumps → the smoothing fit of w over the chart (the default where the
    normals are estimated), or with --smooth off or the file's normals limit overshoot
    → interpolate w(u, v) → refine in (u, v) → map back → write

The smoothing fit is the plane fit's stage (c1mesh.stages.smoothing.smooth_tile) on the
chart's one tile: the vertices' (u, v), their inverse depths w and gradients ∇w, with the
chart's spacing (`chart_spacing`) as its length unit. Stereo and time-of-flight depth is
noisy and quantised in depth; fitting w rather than interpolating it removes the stair
steps without moving the vertices off their rays.

pipeline.driver.fit_in_memory reads the input and branches here when the frame is perspective
(--frame perspective, or auto with an organised scan and no GeoTIFF output); the stages
after that reuse the pipeline's interpolator, and its refine, write and preview code
(pipeline.write_surface, geo.finish). Without --level the level is chosen from the data
(perspective_level). Nothing here prints or exits.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from c1mesh.core.cloud import MeshStream, PointCloud
from c1mesh.core.errors import InputError
from c1mesh.core.plan import MeshTarget
from c1mesh.core.threads import workers as thread_count
from c1mesh.core.tile import Tile
from c1mesh.engine.schemes import get_scheme
from c1mesh.engine.triangulation import delaunay
from c1mesh.geo.products import finish, level_for_edge, level_for_vertices
from c1mesh.pipeline.report import ReportCore, crs_facts, scheme_facts
from c1mesh.pipeline.steps import (
    FitResult,
    FitRun,
    WorldSurface,
    compact_vertices,
    display_name,
    limited_interpolator,
    mesh_pieces,
    smoothed_interpolator,
    write_surface,
)
from c1mesh.pipeline.plan import estimated_normals, resolved_smoothing, smoothing_strength
from c1mesh.stages.grid import counter_clockwise, depth_jumps, grid_mesh, grid_normals
from c1mesh.stages.limiter import check_mode
from c1mesh.stages.normals import estimate_normals
from c1mesh.stages.height_field import kd_tree
from c1mesh.stages.perspective import PerspectiveFrame, frame_from_viewpoint, inverse_depth_gradients, parse_viewpoint
from c1mesh.stages.smoothing import (SmoothingControl, SmoothingRun, chart_search_vertices, gradient_data_weight,
                                     search_windows)
from c1mesh.stages.trim import trim


@dataclass
class ViewField:
    """A scan as inverse depth over the view rays, one entry per usable input point.

    uv: (N, 2) ray parameters (x/z, y/z); w: (N,) inverse depth 1/z; gradients: (N, 2) ∇w;
    camera: (N, 3) camera coordinates; usable: (N,) bool, the points that may be vertices
    (all arrays keep every input row, so grid indices stay valid); dropped: counts by reason.
    """

    uv: np.ndarray
    w: np.ndarray
    gradients: np.ndarray
    camera: np.ndarray
    usable: np.ndarray
    dropped: dict[str, int] = field(default_factory=dict)


def perspective_frame(cloud: PointCloud, viewpoint: str | None) -> tuple[PerspectiveFrame, str]:
    """The frame from --viewpoint, else the file's viewpoint, else the origin; and which it was.

    The orientation is kept when it sees most of the points in front (camera z > 0).
    Otherwise (PCL's sample frames carry VIEWPOINT 0 0 0 0 1 0 0, a half turn that puts
    every point behind the camera) the viewing axis is turned to the mean direction from
    the viewpoint to the points, keeping the camera's x axis as far as possible; the
    surface does not depend on the orientation, only the chart (u, v) does.
    """
    if viewpoint is not None:
        frame, source = frame_from_viewpoint(parse_viewpoint(viewpoint)), "option"
    elif cloud.viewpoint is not None:
        frame, source = frame_from_viewpoint(cloud.viewpoint), "file"
    else:
        frame, source = frame_from_viewpoint(None), "origin"
    camera = frame.to_camera(cloud.points)
    finite = np.isfinite(camera).all(axis=1)
    if not finite.any() or np.mean(camera[finite, 2] > 0) >= 0.5:
        return frame, source
    rays = camera[finite] / np.linalg.norm(camera[finite], axis=1)[:, None]
    look = rays.mean(axis=0)
    if not np.linalg.norm(look) > 1e-6:
        raise InputError("the points surround the viewpoint (no direction sees most of them); "
                         "a perspective frame needs a scan seen from one side; try --frame axis")
    look /= np.linalg.norm(look)
    right = np.eye(3)[0] if abs(look[0]) < 0.9 else np.eye(3)[1]
    right = right - (right @ look) * look
    right /= np.linalg.norm(right)
    turn = np.column_stack([right, np.cross(look, right), look])      # new camera axes in the old
    return PerspectiveFrame(frame.origin, frame.rotation @ turn), source + " (orientation from the points)"


def camera_normals(cloud: PointCloud, camera: np.ndarray, frame: PerspectiveFrame, mode: str,
                   k: int) -> tuple[np.ndarray, str]:
    """Normals (N, 3) in camera coordinates and where they came from.

    Organised scans: the file's normals, with missing ones (and all, under --normals
    estimate) from plane fits to grid neighbours (grid.grid_normals). Unorganised: the
    file's, or Open3D's k-neighbour estimate. Estimated normals face the viewpoint.
    """
    if mode == "file" and cloud.normals is None:
        raise InputError("the input has no normals; use --normals estimate (or auto)")
    have = cloud.normals is not None and mode != "estimate"
    normals = frame.vectors_to_local(cloud.normals) if have else np.full(camera.shape, np.nan)
    finite = np.isfinite(camera).all(axis=1)        # the others are dropped, normals or not
    missing = finite & (~np.isfinite(normals).all(axis=1) | ~(np.abs(normals).sum(axis=1) > 0))
    if not missing.any():
        return normals, "file"
    if cloud.grid_shape is not None:
        height, width = cloud.grid_shape
        valid = (np.isfinite(camera).all(axis=1) & (camera[:, 2] > 0)).reshape(height, width)
        estimate = grid_normals(camera.reshape(height, width, 3), valid).reshape(-1, 3)
        source = "grid"
    else:
        if finite.sum() < 3:
            raise InputError(f"only {int(finite.sum())} points have finite coordinates; need at least 3")
        estimate = estimate_normals(camera, k=k, towards=-np.where(finite[:, None], camera, 0.0))
        source = "estimated"
    normals[missing] = estimate[missing]
    return normals, source if np.array_equal(missing, finite) else f"file+{source}"


def view_field(camera: np.ndarray, normals: np.ndarray, max_slope_deg: float) -> ViewField:
    """(u, v), w = 1/z and ∇w of camera points (N, 3) with camera normals (N, 3).

    Points are unusable when non-finite ("non_finite"), at or behind the viewpoint
    ("behind_viewpoint"), without a usable normal ("bad_normal"), or seen within
    90° - max_slope_deg of edge-on ("too_steep": ∇w is unreliable there, infinite at 90°).
    """
    finite = np.isfinite(camera).all(axis=1)
    front = finite & (camera[:, 2] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 1.0 / camera[:, 2]
        uv = camera[:, :2] * w[:, None]
    uvw = np.column_stack([uv, w])
    gradients, cosine = inverse_depth_gradients(uvw, normals)
    has_normal = front & np.isfinite(cosine) & np.isfinite(normals).all(axis=1) \
        & (np.abs(normals).sum(axis=1) > 0)
    steep = has_normal & ~(cosine >= np.cos(np.radians(max_slope_deg)))
    usable = has_normal & ~steep
    dropped = {"non_finite": int((~finite).sum()), "behind_viewpoint": int((finite & ~front).sum()),
               "bad_normal": int((front & ~has_normal).sum()), "too_steep": int(steep.sum())}
    if usable.sum() < 3:
        raise InputError(f"only {int(usable.sum())} of {len(w)} points are in front of the viewpoint "
                         "with a usable normal; check --viewpoint")
    return ViewField(uv, w, gradients, camera, usable, dropped)


def view_triangles(field: ViewField, grid_shape: tuple[int, int] | None, max_edge) -> tuple[np.ndarray, dict, str]:
    """Triangles (T, 3) over the usable points, counter-clockwise in (u, v), without depth jumps.

    Organised: the pixel grid (grid.grid_triangles); otherwise Delaunay in (u, v) then
    trimmed of long edges, slivers and bowties (trim.trim). Returns the triangles
    (indices into the field's rows), the report entry and the method ("grid" | "delaunay").
    """
    if grid_shape is not None:
        height, width = grid_shape
        tri, jumps = grid_mesh(field.camera.reshape(height, width, 3), field.uv.reshape(height, width, 2),
                               field.usable.reshape(height, width))
        before = int(tri.shape[0]) + sum(jumps.removed.values())
        removed = dict(jumps.removed)
        method = "grid"
    else:
        index = _nearest_per_ray(field)
        tri = index[delaunay(field.uv[index])]
        method = "delaunay"
        before = int(tri.shape[0])
        tri, flat = counter_clockwise(field.uv, tri)
        tri, jumps = depth_jumps(field.camera, tri)
        removed = {"zero_area": flat, **jumps.removed}
    limit = None
    if method == "delaunay" and tri.shape[0]:
        used = np.flatnonzero(np.bincount(tri.ravel(), minlength=field.w.size))
        remap = np.full(field.w.size, -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        kept, trim_report = trim(field.uv[used], remap[tri], max_edge=max_edge)
        tri = used[kept]
        removed.update(trim_report.removed)
        limit = trim_report.max_edge
    report = {"method": method, "before_trim": before, "after_trim": int(tri.shape[0]),
              "removed": removed, "shadow_angle": jumps.shadow_angle,
              "grazing_angle": jumps.grazing_angle, "max_edge": limit}
    return tri, report, method


def _nearest_per_ray(field: ViewField) -> np.ndarray:
    """Indices of the usable points, one per distinct (u, v) (to 1e-9 of their extent): the nearest.

    A viewpoint sees one point per ray; farther points on the same ray (merged scans,
    duplicates) are hidden behind it, and Delaunay would keep an arbitrary one of them.
    They are counted in field.dropped["hidden_on_same_ray"].
    """
    index = np.flatnonzero(field.usable)
    index = index[np.argsort(-field.w[index], kind="stable")]
    uv = field.uv[index]
    tolerance = 1e-9 * max(float(np.ptp(uv, axis=0).max()), np.finfo(float).tiny)
    _, first = np.unique(np.round(uv / tolerance), axis=0, return_index=True)
    field.dropped["hidden_on_same_ray"] = int(index.size - first.size)
    field.usable[index] = False
    field.usable[index[first]] = True
    return np.sort(index[first])


def fit_perspective(cloud: PointCloud, source, output, options, timer, keep_mesh: bool,
                    crs: str | None = None, crs_source: str | None = None):
    """driver.fit_in_memory after the read stage, in the perspective frame; returns a FitResult.

    The refine, write and preview stages are the plane fit's (pipeline.write_surface,
    geo.finish); crs: the CRS to carry (usually none: a depth frame's coordinates are the
    camera's, unless a --crs or the file names one), crs_source where it came from.
    """
    get_scheme(options.scheme)              # an unknown --scheme fails here, before any stage
    check_mode(options.overshoot)
    frame, viewpoint_source = perspective_frame(cloud, options.viewpoint)
    camera = frame.to_camera(cloud.points)
    with timer.stage("normals"):
        normals, normal_source = camera_normals(cloud, camera, frame, options.normals, options.k)
    with timer.stage("frame"):
        field_ = view_field(camera, normals, options.max_slope)
    with timer.stage("triangulate"):
        triangles, tri_report, method = view_triangles(field_, cloud.grid_shape, options.max_edge)
        if triangles.shape[0] == 0:
            raise InputError("no triangles are left after removing depth jumps")
        used, triangles = compact_vertices(field_.uv, triangles)
    with timer.stage("interpolate"):
        interp, overshoot, smoothing = chart_interpolator(field_, used, triangles, options, normal_source)
    level, level_from = perspective_level(interp, field_, used, options)
    options = replace(options, level=level)
    colors = None if cloud.colors is None else cloud.colors[used]
    mesh, stream = write_surface(WorldSurface(interp, frame, colors), output,
                                 MeshTarget(options.output_format, options.ascii, crs), level, timer, keep_mesh,
                                 faces_facing=facing_viewpoint)
    run = FitRun(source, output, options, cloud, timer, 1.0 if options.z_factor is None else float(options.z_factor),
                 crs_facts(crs, crs_source))
    model = PerspectiveModel(field_, used, interp, overshoot, normal_source, frame, viewpoint_source, tri_report,
                             smoothing)
    report = perspective_report(run, model, stream, level_from)
    return finish(FitResult(mesh, report), interp, frame, crs, crs_source, options)


def chart_interpolator(field_: ViewField, used: np.ndarray, triangles: np.ndarray, options, normal_source: str):
    """(RSDInterpolator of w over the chart, the overshoot report, the SmoothFit or None).

    used: the field's rows the triangles (T, 3) number. With --smooth off, or by default
    where the normals came from the file: the exact interpolant of w with the limiter (its
    height reconciliation off: the chart's u, v and w do not share a unit). With --smooth
    given, or by default where the normals are estimated (pipeline.plan.estimated_normals
    and resolved_smoothing): the smoothing stage on the chart's one tile
    (`chart_spacing` its length unit; the normals' ∇w enter as data by where the normals
    came from, smoothing.gradient_data_weight), of whose remedies only the edge
    directions apply. A search for the strength runs on windows holding a larger share of
    the chart than of a survey (smoothing.chart_search_vertices: a frame is a scene of
    several surfaces)."""
    scheme = get_scheme(options.scheme)
    uv, w, gradients = field_.uv[used], field_.w[used], field_.gradients[used]
    strength = smoothing_strength(resolved_smoothing(options, estimated_normals(normal_source), perspective=True))
    if strength is None:
        interp, overshoot = limited_interpolator(uv, w, gradients, triangles, scheme, options.overshoot,
                                                 heights=False)
        return interp, overshoot, None
    if options.spacing is not None:
        raise InputError("--spacing thins a height field's vertices (--frame axis or auto); the perspective "
                         "frame's smoothing fit keeps every point as a vertex")
    windows = search_windows(uv, chart_search_vertices(uv.shape[0])) if strength == "auto" else None
    run = SmoothingRun(SmoothingControl(strength, scheme, windows=windows, edf=options.edf), chart_spacing(uv),
                       options.overshoot, gradient_data_weight(normal_source, "normals"))
    return smoothed_interpolator(Tile.whole(uv, w, gradients, triangles), run)


def chart_spacing(uv: np.ndarray) -> float:
    """The chart's spacing h (u, v units): the median distance from a vertex (n, 2) to its
    nearest other one, the smoothing strength's length unit as the plane fit's spacing is
    (there in 3D; here the chart's w is not a length)."""
    distances, _ = kd_tree(uv).query(uv, k=2)
    return float(np.median(distances[:, 1]))


@dataclass(frozen=True)
class PerspectiveModel:
    """The spline of a perspective fit before refinement: field (the ViewField), used
    (ascending rows of the field some triangle uses), interp (the RSDInterpolator over
    them), overshoot (the limiter's report), normal_source, frame (the
    PerspectiveFrame), viewpoint_source (where the viewpoint came from), triangles (the
    report's triangles entry: view_triangles'), smoothing (the SmoothFit of --smooth, or
    None)."""

    field: ViewField
    used: np.ndarray
    interp: object
    overshoot: object
    normal_source: str
    frame: PerspectiveFrame
    viewpoint_source: str
    triangles: dict
    smoothing: object = None


def perspective_report(run: FitRun, model: PerspectiveModel, stream, level_from: str) -> dict:
    """The report of a perspective fit (c1mesh.pipeline.report's schema). Its gradients are
    of the inverse depth, from the normals; its warnings are [] (the warning rules are the
    height axis's); its z_factor is run's (--z-factor's, else 1: camera x, y, z share one
    unit)."""
    field_, used, interp, frame, options = model.field, model.used, model.interp, model.frame, run.options
    dropped = dict(field_.dropped)
    dropped["unreferenced_after_trim"] = int(field_.usable.sum() - used.size)
    report = ReportCore(
        input=display_name(run.source), output=display_name(run.output),
        points={"read": len(run.cloud), "dropped": dropped, "kept": int(used.size),
                "measured": measured_points(field_),
                "organised": None if run.cloud.grid_shape is None else list(run.cloud.grid_shape)},
        normals=model.normal_source, gradients="normals",
        frame={"kind": "perspective", "origin": frame.origin.tolist(), "viewpoint": frame.origin.tolist(),
               "viewpoint_from": model.viewpoint_source, "axes": frame.axes.tolist()},
        triangles=model.triangles, level=options.level, level_from=level_from,
        output_mesh={"vertices": int(stream.vertex_count), "faces": int(stream.face_count)},
        scheme=scheme_facts(options.scheme), c1_certificate=interp.c1_certificate(),
        pieces=mesh_pieces(interp.points, interp.triangles, interp.edge_table), warnings=[], crs=run.crs,
        seconds=run.timer.seconds, threads=thread_count(), z_factor=run.z_factor).as_dict()
    report["overshoot"] = model.overshoot.as_dict()
    if model.smoothing is not None:
        report["smoothing"] = {**model.smoothing.as_dict(), "lattice": None}     # no --spacing in the chart
    return report


def measured_points(field_: ViewField) -> int:
    """Input points that are measurements: finite and in front of the viewpoint (a depth
    image's valid pixels; the others are its 'no measurement' zeros or NaN rows)."""
    return int(field_.w.size - field_.dropped["non_finite"] - field_.dropped["behind_viewpoint"])


def perspective_level(interp, field_: ViewField, used: np.ndarray, options) -> tuple[int, str]:
    """The refinement level of a perspective fit and where it came from.

    "option": --level; "resolution": the level whose mean output edge (world units,
    measured on the camera points: the same lengths) is --resolution (geo.level_for_edge);
    "data": the level whose vertex count is nearest one per measured input point
    (geo.level_for_vertices): a depth frame is already sampled at the sensor's pixel
    spacing, so finer levels add vertices (level² faces per triangle), not data. On a
    640 x 480 frame that is level 1, not the plane fit's 4 (16x the vertices).
    """
    if options.resolution is not None:
        return level_for_edge(field_.camera[used], interp.triangles, options.resolution), "resolution"
    if options.level is not None:
        return int(options.level), "option"
    return level_for_vertices(interp, measured_points(field_)), "data"


def facing_viewpoint(stream: MeshStream) -> MeshStream:
    """The stream with every face's winding reversed.

    Triangles counter-clockwise in (u, v) map to 3D faces whose right-hand normal points
    away from the viewpoint (u, v grow along the camera's x and y, and the camera looks
    along +z); the vertex normals face the viewpoint, so the faces are turned to agree.
    """
    blocks = stream.face_blocks

    def reversed_blocks():
        for faces in blocks():
            yield np.ascontiguousarray(faces[:, ::-1])
    return replace(stream, face_blocks=reversed_blocks)
