"""The plan of a fit (c1mesh.core.plan), resolved once from the options before any point
is read.

FitOptions (pipeline.driver) is what a user sets; a FitPlan is what the stages, the
writers and the tile scheduler are told: typed, frozen, parsed. Bad values (a --smooth
that is no strength, a --spacing without smoothing) are InputErrors here, before any work.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.plan import (
    DEFAULT_SMOOTH,
    DemPlan,
    FitPlan,
    HeightSettings,
    MeshProducts,
    MeshTarget,
    PointSelection,
    Strength,
    SurfaceSettings,
)
from c1mesh.formats._limits import parse_memory
from c1mesh.geo.products import MAX_LEVEL
from c1mesh.geo.raster import fill_distance, is_raster_path
from c1mesh.stages.frame import resolve_axis
from c1mesh.stages.smoothing import SmoothingError, parse_strength
from c1mesh.stages.lattice_mesh import check_spacing


def smoothing_strength(options) -> Strength:
    """options.smooth as c1mesh.stages.smoothing.parse_strength reads it: None (off),
    "auto" or a strength s > 0, or DEFAULT_SMOOTH until the fit knows where its gradients
    come from (resolved_smoothing); InputError for anything else, and for a --spacing without
    smoothing (an exact fit has its vertices at the points). Checked before any work."""
    if is_default_smooth(options.smooth):
        check_spacing(options.spacing)
        return DEFAULT_SMOOTH
    try:
        strength = options.smooth if isinstance(options.smooth, (int, float)) else parse_strength(options.smooth)
        if isinstance(strength, (int, float)):
            strength = parse_strength(repr(float(strength)))
    except SmoothingError as exc:
        raise InputError(f"--smooth: {exc}") from None
    check_spacing(options.spacing)
    if options.spacing is not None and strength is None:
        raise InputError("--spacing thins the vertices of a smoothing fit: give --smooth auto or a strength")
    return strength


def is_default_smooth(smooth) -> bool:
    """Whether FitOptions.smooth is the default (DEFAULT_SMOOTH)."""
    return isinstance(smooth, str) and smooth.strip().lower() == DEFAULT_SMOOTH


ESTIMATED_NORMALS = ("estimated", "grid")
"""The report's normal sources that read no normal from the file: Open3D's or the height
field's estimate, and an organised frame's pixel-grid estimate ("file+..." mixes keep the
file's, so the exact fit)."""


def estimated_normals(normal_source: str) -> bool:
    """Whether a fit's normals (the report's `normals`) are all estimated: the default then
    smooths (resolved_smoothing)."""
    return normal_source in ESTIMATED_NORMALS


def default_smoothing(spacing, estimated: bool, perspective: bool = False) -> tuple:
    """(smooth, spacing) the default smooth resolves to, given --spacing (None: not given),
    whether the gradients are estimated (normals not in the file) and the frame: for
    estimated gradients "auto", on the lattice (spacing "auto" unless one is given) over a
    height field and on the pixel grid in the perspective frame; "auto" wherever a spacing
    is given (a lattice is a smoothing fit's: the user asked for one; the perspective frame
    refuses it, as with --smooth given); else "off"."""
    if spacing is not None:
        return "auto", spacing
    if estimated:
        return "auto", None if perspective else "auto"
    return "off", None


def resolved_smoothing(options, estimated: bool, perspective: bool = False):
    """options with a default smooth resolved (`default_smoothing`) once the fit knows
    whether its gradients are estimated and its frame; any other smooth as it is."""
    if not is_default_smooth(options.smooth):
        return options
    smooth, spacing = default_smoothing(options.spacing, estimated, perspective)
    return replace(options, smooth=smooth, spacing=spacing)


def refinement_level(level) -> int | None:
    """options.level: None (the fit chooses) or a whole number 1 ... MAX_LEVEL, as the
    CLI's --level takes it; InputError for anything else (a library caller's "a" or 2.5)
    before any work, not a ValueError from deep in the refinement."""
    if level is None:
        return None
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or not 1 <= level <= MAX_LEVEL:
        raise InputError(f"--level must be a whole number from 1 to {MAX_LEVEL}, got {level!r}")
    return int(level)


def resolve_options_axis(source, options):
    """(options with "auto" resolved to z for a LAS/LAZ source, the report's phrase for
    how the height axis is chosen): stages.frame.resolve_axis."""
    axis, reason = resolve_axis(source, options.axis, options.input_format)
    return (options if axis is options.axis else replace(options, axis=axis)), reason


def fit_plan(options, output=None) -> FitPlan:
    """The FitPlan of pipeline.driver.FitOptions `options` (their axis as given: resolve
    "auto" for LAS/LAZ first, resolve_options_axis) for a fit writing `output` (a
    GeoTIFF path: the plan's dem; None or a mesh: none)."""
    dem = None
    if is_raster_path(output) and options.resolution is not None:
        dem = DemPlan(str(output), float(options.resolution), options.slope, options.aspect, options.hillshade,
                      options.support, options.slope_method, options.z_factor, fill_distance(options.fill),
                      None if not options.preview else str(options.preview),
                      None if options.contours is None else str(options.contours),
                      None if options.contours is None or options.interval is None else float(options.interval))
    classes = options.classes if isinstance(options.classes, (str, type(None))) else tuple(options.classes)
    return FitPlan(
        select=PointSelection(options.input_format, classes or None,
                              None if options.bounds is None else tuple(options.bounds)),
        heights=HeightSettings(options.axis, options.normals, options.k, options.max_slope, options.gradients),
        surface=SurfaceSettings(options.max_edge, options.scheme, refinement_level(options.level), options.overshoot,
                                smoothing_strength(options), options.spacing, options.edf),
        mesh=MeshTarget(options.output_format, options.ascii, options.crs,
                        None if dem is not None or options.resolution is None else float(options.resolution)),
        memory=None if options.memory is None else parse_memory(options.memory), threads=options.workers, dem=dem,
        products=mesh_products(options) if dem is None else None)


def mesh_products(options) -> MeshProducts | None:
    """The preview and contours a mesh output draws beside it (None: neither)."""
    if not options.preview and options.contours is None:
        return None
    return MeshProducts(str(options.preview) if options.preview else None,
                        None if options.contours is None else str(options.contours),
                        None if options.contours is None or options.interval is None else float(options.interval),
                        None if options.z_factor is None else float(options.z_factor))
