"""`c1mesh info`: what is in a point file and whether it looks like a height field."""
from __future__ import annotations

import numpy as np

from c1mesh.errors import C1MeshError
from c1mesh.formats import read_cloud
from c1mesh.frame import choose_frame, height_field


def describe(source, fmt: str | None = None, estimate_limit: int = 2_000_000,
             intrinsics=None, depth_scale: float = 0.001) -> dict:
    """Facts about a point file as a JSON-ready dict.

    Normals are estimated (Open3D) for the height-field check when the file has none and
    it has at most ``estimate_limit`` points; otherwise that check is reported as skipped.
    """
    from c1mesh.formats.depth import is_depth_image, read_depth_source
    if is_depth_image(source, fmt):
        from c1mesh.pipeline import FitOptions
        cloud = read_depth_source(source, FitOptions(intrinsics=intrinsics, depth_scale=depth_scale))
    else:
        cloud = read_cloud(source, fmt)
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
    if pts.shape[0]:
        facts["bounds"] = {"min": pts.min(axis=0).tolist(), "max": pts.max(axis=0).tolist()}
    facts.update(_view_facts(cloud))
    if facts["fit_frame"] == "axis":
        facts.update(_height_field_check(cloud, finite, estimate_limit))
    return facts


def _view_facts(cloud) -> dict:
    """Organised or not, the viewpoint, and the frame `c1mesh fit` would use by default."""
    from c1mesh.perspective import frame_kind
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


def _height_field_check(cloud, finite, estimate_limit) -> dict:
    normals = cloud.normals
    source = "file"
    if normals is None:
        if finite.sum() > estimate_limit or finite.sum() < 3:
            return {"suggested_axis": None, "height_field": None,
                    "height_field_note": "skipped: no normals in the file"}
        from c1mesh.normals import estimate_normals
        towards = choose_frame(cloud.points[finite], None, "auto").axes[2]
        normals = np.full(cloud.points.shape, np.nan)
        normals[finite] = estimate_normals(cloud.points[finite], towards=towards)
        source = "estimated"
    try:
        frame = choose_frame(cloud.points, normals, "auto")
        height_field(cloud.points, normals, frame)
    except C1MeshError as exc:
        return {"suggested_axis": None, "height_field": False, "height_field_note": str(exc),
                "normals_used": source}
    return {"suggested_axis": [round(float(v), 6) for v in frame.axes[2]], "height_field": True,
            "normals_used": source}
