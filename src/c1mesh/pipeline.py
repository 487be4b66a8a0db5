"""The fit pipeline: a scan in, a refined C1 surface mesh out.

    load → normals → frame → height field → triangulate + trim → interpolate → refine → write

Each stage is a library function; :func:`fit` chains them, times them, and returns the
mesh with a JSON-ready report. Nothing here prints or exits: the CLI does that.
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from c1mesh.cloud import PointCloud, SurfaceMesh
from c1mesh.errors import InputError
from c1mesh.formats import read_cloud, write_mesh
from c1mesh.frame import choose_frame, gradients_to_normals, height_field
from c1mesh.interpolator import RSDInterpolator
from c1mesh.properties import scheme_properties
from c1mesh.schemes import get_scheme
from c1mesh.triangulation import delaunay, trim

NORMAL_MODES = ("auto", "file", "estimate")
STAGES = ("read", "normals", "frame", "triangulate", "interpolate", "refine", "write")


@dataclass
class FitOptions:
    """Everything `c1mesh fit` can be told, with the CLI's defaults.

    axis: "auto", "x", "y", "z" or "X,Y,Z"; normals: "auto" | "file" | "estimate";
    k: neighbours for normal estimation; classes: LAS classification codes to keep;
    max_slope: degrees — points whose normal is within this of perpendicular to the axis
    are dropped; max_edge: "auto", None (no limit) or a length in the scan's units;
    scheme: shape-function tuple; level: each triangle becomes level² triangles.
    """

    input_format: str | None = None
    axis: Any = "auto"
    normals: str = "auto"
    k: int = 16
    classes: tuple[int, ...] | None = None
    max_slope: float = 85.0
    max_edge: Any = "auto"
    scheme: str = "sextic"
    level: int = 4
    ascii: bool = False


@dataclass
class FitResult:
    mesh: SurfaceMesh
    report: dict = field(default_factory=dict)


class _Timer:
    """Per-stage wall-clock timings, plus an optional progress callback per finished stage."""

    def __init__(self, on_stage: Callable[[str], None] | None):
        self.seconds: dict[str, float] = {}
        self.on_stage = on_stage

    @contextmanager
    def stage(self, name: str):
        start = time.perf_counter()
        yield
        self.seconds[name] = round(time.perf_counter() - start, 6)
        if self.on_stage:
            self.on_stage(name)


def load_cloud(source, options: FitOptions) -> PointCloud:
    """Read the input and keep only the requested LAS classes."""
    cloud = read_cloud(source, options.input_format)
    if options.classes:
        if cloud.classification is None:
            raise InputError("--classes needs a file with a classification field (LAS/LAZ)")
        keep = np.isin(cloud.classification, np.asarray(options.classes))
        if not keep.any():
            found = np.unique(cloud.classification)[:20].tolist()
            raise InputError(f"no points of class {list(options.classes)}; the file has classes {found}")
        cloud = cloud.subset(keep)
    if len(cloud) == 0:
        raise InputError("the input has no points")
    return cloud


def cloud_normals(cloud: PointCloud, options: FitOptions) -> tuple[np.ndarray, str]:
    """The normals to use and where they came from ("file" or "estimated")."""
    if options.normals not in NORMAL_MODES:
        raise InputError(f"--normals must be one of {', '.join(NORMAL_MODES)}, got {options.normals!r}")
    if options.normals == "file" and cloud.normals is None:
        raise InputError("the input has no normals; use --normals estimate (or auto)")
    if cloud.normals is not None and options.normals != "estimate":
        return cloud.normals, "file"
    from c1mesh.normals import estimate_normals
    finite = np.isfinite(cloud.points).all(axis=1)
    if finite.sum() < 3:
        raise InputError(f"only {int(finite.sum())} points have finite coordinates; need at least 3")
    towards = choose_frame(cloud.points[finite], None, options.axis).axes[2]
    normals = np.full(cloud.points.shape, np.nan)
    normals[finite] = estimate_normals(cloud.points[finite], k=options.k, towards=towards)
    return normals, "estimated"


def surface_mesh(refined, frame, colors: np.ndarray | None) -> SurfaceMesh:
    """World-coordinate mesh from a refinement in the scan frame (heights = spline values).

    Consumes ``refined``: its per-point arrays are released as soon as they have been
    turned into world vertices and normals, and the work is done in blocks, so the peak
    memory stays close to the refinement plus the mesh (no full-size temporaries).
    """
    count = refined.values.shape[0]
    vertices = np.empty((count, 3))
    normals = np.empty((count, 3))
    local = np.empty((min(_BLOCK, count), 3))          # reused block buffer
    for start in range(0, count, _BLOCK):
        block = slice(start, start + _BLOCK)
        buf = local[:min(_BLOCK, count - start)]
        buf[:, :2] = refined.points[block]
        buf[:, 2] = refined.values[block]
        frame.to_world(buf, out=vertices[block])
        gradients_to_normals(refined.gradients[block], out=buf)
        frame.vectors_to_world(buf, out=normals[block])
    refined.points = refined.values = refined.gradients = None
    vertex_colors = None
    if colors is not None:
        vertex_colors = np.clip(np.rint(refined.linear(colors.astype(float))), 0, 255).astype(np.uint8)
    return SurfaceMesh(vertices=vertices, faces=refined.triangles, vertex_normals=normals,
                       vertex_colors=vertex_colors)


_BLOCK = 1 << 18   # vertices per block when converting to world coordinates


def _compact(xy, triangles):
    """Drop points no triangle uses; returns (used point indices, re-indexed triangles)."""
    used = np.unique(triangles)
    remap = np.full(xy.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return used, remap[triangles]


def fit(source, output=None, options: FitOptions | None = None,
        on_stage: Callable[[str], None] | None = None) -> FitResult:
    """Fit a refined C1 surface mesh to a scan.

    source: path or binary stream (then options.input_format is required); output: path,
    binary stream, or None to only return the mesh. Returns the mesh (world coordinates,
    unit vertex normals on the axis side, colours when the input has them) and a report
    dict (counts, frame, trimming, scheme properties, C1 certificate, timings).
    """
    options = options or FitOptions()
    scheme = get_scheme(options.scheme)
    timer = _Timer(on_stage)
    with timer.stage("read"):
        cloud = load_cloud(source, options)
    with timer.stage("normals"):
        normals, normal_source = cloud_normals(cloud, options)
    with timer.stage("frame"):
        frame = choose_frame(cloud.points, normals, options.axis)
        hf = height_field(cloud.points, normals, frame, max_slope_deg=options.max_slope)
    with timer.stage("triangulate"):
        triangles = delaunay(hf.xy)
        triangles, trim_report = trim(hf.xy, triangles, max_edge=options.max_edge)
        if triangles.shape[0] == 0:
            raise InputError("no triangles are left after trimming; try --max-edge none")
        used, triangles = _compact(hf.xy, triangles)
    with timer.stage("interpolate"):
        interp = RSDInterpolator(hf.xy[used], hf.z[used], hf.gradients[used], triangles=triangles,
                                 scheme=scheme)
    with timer.stage("refine"):
        refined = interp.refine(options.level)
        colors = None if cloud.colors is None else cloud.colors[hf.source_index[used]]
        mesh = surface_mesh(refined, frame, colors)
    with timer.stage("write"):
        if output is not None:
            write_mesh(mesh, output, ascii=options.ascii)
    report = _report(source, output, options, cloud, normal_source, frame, hf, trim_report,
                     used, interp, mesh, timer)
    return FitResult(mesh, report)


def _report(source, output, options, cloud, normal_source, frame, hf, trim_report, used,
            interp, mesh, timer) -> dict:
    props = scheme_properties(interp.scheme)
    dropped = dict(hf.dropped)
    dropped["unreferenced_after_trim"] = int(hf.xy.shape[0] - used.size)
    return {
        "input": _name(source),
        "output": _name(output),
        "points": {"read": len(cloud), "dropped": dropped, "kept": int(used.size),
                   "normals_flipped": int(hf.flipped), "stacked": int(hf.stacked),
                   "spacing": float(hf.spacing)},
        "normals": normal_source,
        "frame": {"origin": frame.origin.tolist(), "axes": frame.axes.tolist()},
        "triangles": {"before_trim": trim_report.triangles_before,
                      "after_trim": trim_report.triangles_after,
                      "removed": dict(trim_report.removed),
                      "max_edge": trim_report.max_edge},
        "level": options.level,
        "output_mesh": {"vertices": int(mesh.vertices.shape[0]), "faces": int(mesh.faces.shape[0])},
        "scheme": props.as_dict(),
        "c1_certificate": interp.c1_certificate(),
        "seconds": timer.seconds,
    }


def _name(obj) -> str | None:
    if obj is None:
        return None
    if isinstance(obj, (str, Path)):
        return str(obj)
    return getattr(obj, "name", "<stream>")
