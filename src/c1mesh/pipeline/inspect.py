"""`c1mesh info`: what is in a point file and whether it looks like a height field."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from c1mesh.core.crs import describe as describe_crs
from c1mesh.core.errors import C1MeshError, InputError
from c1mesh.formats import read_cloud
from c1mesh.formats.copc import copc_summary
from c1mesh.formats.depth import DepthCamera, is_depth_image, read_depth_source
from c1mesh.formats.las import laspy_errors
from c1mesh.pipeline.driver import FitOptions, height_column_axis
from c1mesh.stages.frame import choose_frame
from c1mesh.stages.height_field import height_field
from c1mesh.stages.height_gradients import height_neighbours, height_normals
from c1mesh.stages.normals import estimate_normals
from c1mesh.stages.perspective import frame_kind

#: Points the height-field check looks at: a random subsample keeps `info` under a second.
SAMPLE = 20_000


def describe(source, fmt: str | None = None, sample: int = SAMPLE, memory=None,
             intrinsics=None, depth_scale: float = 0.001) -> dict:
    """Facts about a point file as a JSON-ready dict.

    The height-field check runs on a random subsample of at most `sample` finite points
    (fixed seed, so the answer is repeatable), with the file's normals or normals
    estimated (Open3D) on the subsample; the output says how many points it used, since
    on the full cloud the answer can differ. `memory` bounds the bytes read (read_cloud).
    """
    if is_depth_image(source, fmt):
        cloud = read_depth_source(source, DepthCamera(intrinsics, depth_scale), memory)
    else:
        cloud = read_cloud(source, fmt, memory=memory)
    finite = np.isfinite(cloud.points).all(axis=1)
    pts = cloud.points[finite]
    facts: dict = {
        "points": len(cloud),
        "finite_points": int(finite.sum()),
        "fields": _fields(cloud),
        "normals": cloud.normals is not None,
        "colors": cloud.colors is not None,
    }
    if cloud.classification is not None:
        classes, counts = np.unique(cloud.classification, return_counts=True)
        facts["classes"] = {int(c): int(n) for c, n in zip(classes, counts)}
    facts["crs"] = describe_crs(cloud.crs)
    if pts.shape[0]:
        facts["bounds"] = {"min": pts.min(axis=0).tolist(), "max": pts.max(axis=0).tolist()}
    copc = _copc_facts(source, fmt)
    if copc is not None:
        facts["copc"] = copc
    facts.update(_view_facts(cloud))
    if facts["fit_frame"] == "axis":
        facts.update(_height_field_check(cloud, finite, sample))
    return facts


def _fit_axis(cloud) -> str | None:
    """The axis `c1mesh fit` with default options resolves "auto" to before looking at
    normals, and why (pipeline.height_column_axis, the rule the fit applies: a text
    table's header height column); None when the fit chooses it from the normals."""
    options, reason = height_column_axis(cloud, FitOptions())
    return None if reason is None else (options.axis, reason)


def _copc_facts(source, fmt: str | None) -> dict | None:
    """A COPC file's octree (node count, levels, root cube, spacing) from its header and
    hierarchy alone; None for anything else (streams, other formats, plain LAS/LAZ)."""
    if not isinstance(source, (str, Path)) or (fmt or Path(source).suffix).lower().lstrip(".") not in ("laz", "copc"):
        return None

    with laspy_errors(str(source)):
        return copc_summary(source)


def _view_facts(cloud) -> dict:
    """Organised or not, the viewpoint, and the frame `c1mesh fit` would use by default."""
    kind = frame_kind("auto", cloud.grid_shape is not None)
    facts = {"organised": cloud.grid_shape is not None,
             "viewpoint": None if cloud.viewpoint is None else [float(v) for v in cloud.viewpoint],
             "fit_frame": kind}
    if cloud.grid_shape is not None:
        facts["grid"] = {"height": cloud.grid_shape[0], "width": cloud.grid_shape[1]}
        facts["fit_triangulation"] = "pixel grid (perspective frame, depth jumps become holes)"
    return facts


def _fields(cloud) -> list[str]:
    names = ["x", "y", "z"]
    if cloud.normals is not None:
        names += ["nx", "ny", "nz"]
    if cloud.colors is not None:
        names += ["red", "green", "blue", "alpha"][:cloud.colors.shape[1]]
    if cloud.classification is not None:
        names.append("classification")
    return names + list(cloud.extra)


def _height_field_check(cloud, finite, sample: int) -> dict:
    """Suggested axis and height-field verdict from a subsample of the finite points, as
    the default fit decides them: over a header's height column (heights in units of
    their own: gradients fitted to the heights, no 3-D angles; "axis_choice" says so), else
    over the axis chosen from the file's or estimated normals."""
    rows = np.flatnonzero(finite)
    if len(rows) > sample:
        rows = np.sort(np.random.default_rng(0).choice(rows, sample, replace=False))
    points = cloud.points[rows]
    scope = {"height_field_sample": len(rows),
             "height_field_scope": ("all finite points" if len(rows) == finite.sum() else
                                    f"an estimate from a random sample of {len(rows)} of "
                                    f"{int(finite.sum())} finite points")}
    given = _fit_axis(cloud)
    if given is not None:
        return {**_height_column_check(points, *given), **scope}
    normals, source = (None, "estimated") if cloud.normals is None else (cloud.normals[rows], "file")
    try:
        if normals is None:
            if len(rows) < 3:
                raise InputError(f"only {len(rows)} finite points; need at least 3")
            normals = estimate_normals(points, towards=choose_frame(points, None, "auto").axes[2])
        frame = choose_frame(points, normals, "auto")
        height_field(points, normals, frame)
    except C1MeshError as exc:
        return {"suggested_axis": None, "height_field": False, "height_field_note": str(exc),
                "normals_used": source, **scope}
    return {"suggested_axis": [round(float(v), 6) for v in frame.axes[2]], "height_field": True,
            "normals_used": source, **scope}


def _height_column_check(points: np.ndarray, axis: str, reason: str) -> dict:
    """The height-field verdict over the given axis of a header height column, with the
    normals the fit uses there (pipeline.build_surface: fitted to the heights, compared in
    plan units only, height_field.height_field's common_metric=False)."""
    facts = {"axis_choice": reason + " (heights in units of their own: the fit works in "
                                     "plan units and fits the gradients to the heights)",
             "normals_used": "fitted to the heights"}
    try:
        frame = choose_frame(points, None, axis)
        normals = height_normals(points, frame, k=height_neighbours(FitOptions().k))
        height_field(points, normals, frame, common_metric=False)
    except C1MeshError as exc:
        return {"suggested_axis": None, "height_field": False, "height_field_note": str(exc), **facts}
    return {"suggested_axis": [round(float(v), 6) for v in frame.axes[2]], "height_field": True, **facts}
