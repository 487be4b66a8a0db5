"""The fit's plan: what the layers below pipeline need of the user's options, as small
frozen values.

`c1mesh.pipeline.plan.fit_plan` resolves them once from the options (pipeline.driver's
FitOptions, the CLI's and the library's one bag of settings) before any point is read:
the smoothing strength parsed, the CRS parsed, the budget in bytes. stages/, geo/ and
survey/ then receive the pieces they use and never read the options bag, so every path
of a fit (in memory, in tiles, on Dask) is told the same things in the same types.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence, Union

Strength = Union[None, str, float]
"""A smoothing strength as stages.smoothing.parse_strength reads it: None (the exact fit,
the spline through every point), "auto" (chosen by cross-validation) or a strength s > 0,
or DEFAULT_SMOOTH until the fit knows where its gradients come from."""
DEFAULT_SMOOTH = "default"
"""FitOptions.smooth's default: the smoothing fit where the gradients are estimated, on the
lattice (--smooth auto --spacing auto) in a height-field frame (LAS/LAZ, XYZ or CSV without
normals) and every pixel a vertex in the perspective frame; the exact interpolant (off)
where the file has normals (issue 38; pipeline.plan.resolved_smoothing)."""


@dataclass(frozen=True)
class PointSelection:
    """Which points of the inputs the fit reads.

    input_format: the reader's name for streams (None: the path's extension); classes:
    LAS classification codes to keep, or a choice stages.ground.choose_points reads
    ("auto": class 2 where the survey has it, else the ground filter; "all"; "filter";
    None: all); bounds: (xmin, ymin, xmax, ymax) world
    x/y box, closed (None: everything)."""

    input_format: str | None = None
    classes: tuple[int, ...] | str | None = None
    bounds: tuple[float, float, float, float] | None = None


@dataclass(frozen=True)
class HeightSettings:
    """How the scan becomes heights and gradients over its frame (stages.frame,
    stages.height_field, stages.height_gradients).

    axis: the height axis ("auto", "x", "y", "z" signed, or "X,Y,Z"); normals: "auto" |
    "file" | "estimate"; k: neighbours of the normal estimate; max_slope: degrees, points
    whose normal is within this of perpendicular to the axis are dropped; gradients:
    "auto" | "normals" | "heights" (stages.height_gradients.use_height_gradients)."""

    axis: object = "auto"
    normals: str = "auto"
    k: int = 16
    max_slope: float = 85.0
    gradients: str = "auto"


@dataclass(frozen=True)
class SurfaceSettings:
    """The spline: the triangulation's trim, the shape functions, the refinement and the fit.

    max_edge: "auto", None (no limit) or a length in the frame's units; scheme: the
    shape-function tuple's name (engine.schemes); level: each triangle becomes level²
    triangles (None: chosen by the fit); overshoot: "limit" | "off" (stages.limiter);
    strength: the smoothing strength (`Strength`); spacing: None (vertices at the points)
    or a length D, the vertices of a smoothing fit on a D x D lattice (stages.lattice_mesh);
    edf: whether the smoothing fit estimates its effective degrees of freedom (a reported
    diagnostic, one more solve: stages.smoothing.SmoothingControl.edf)."""

    max_edge: object = "auto"
    scheme: str = "sextic"
    level: int | None = None
    overshoot: str = "limit"
    strength: Strength = None
    spacing: float | None = None
    edf: bool = True


@dataclass(frozen=True)
class MeshTarget:
    """How a mesh output is written: format (formats' registry name; None: the path's
    extension), ascii (PLY as text), crs (a CRS the user assigned, as given: EPSG code,
    WKT or a file, c1mesh.core.crs.parse_crs; None: the inputs' own); resolution (--resolution
    of a mesh: its level is the one whose mean output edge is nearest it,
    geo.products.level_for_edge; None: the level as given)."""

    format: str | None = None
    ascii: bool = False
    crs: str | None = None
    resolution: float | None = None


@dataclass(frozen=True)
class DemPlan:
    """A DEM output and its side rasters (c1mesh.geo.raster), as the tiled DEM writer
    (c1mesh.pipeline.bounded_dem) is told them: dem, slope, aspect, hillshade, support: the
    GeoTIFF paths (None: not written); resolution: the cell size (world units);
    slope_method: "auto" | "spline" | "horn"; z_factor: x, y units per height unit
    (None: 1); fill: the fill distance (geo.raster.fill_distance: None off, inf the hull);
    preview: the PNG path of the DEM's preview (None: none); contours: the vector file of
    contour lines traced on the DEM's grid every `interval` of height (None: none)."""

    dem: str
    resolution: float
    slope: str | None = None
    aspect: str | None = None
    hillshade: str | None = None
    support: str | None = None
    slope_method: str = "auto"
    z_factor: float | None = None
    fill: float | None = None
    preview: str | None = None
    contours: str | None = None
    interval: float | None = None


@dataclass(frozen=True)
class MeshProducts:
    """What a mesh output draws beside it from the whole spline, each on a grid of its
    own: preview (the PNG path; None: none; c1mesh.geo.preview.SplineView), contours (the
    vector file of contour lines every `interval` of height; None: none; traced on the
    grid at the mesh's --resolution, else its mean output edge), z_factor (x, y units
    per height unit for the preview's shading; None: 1)."""

    preview: str | None = None
    contours: str | None = None
    interval: float | None = None
    z_factor: float | None = None


@dataclass(frozen=True)
class FitPlan:
    """Everything the stages, the writers and the tile scheduler are told about one fit.

    memory: the budget in bytes (None: no budget, always one piece in memory); threads:
    the one thread knob (None: the process's setting, core.threads); dem: the DEM
    output (DemPlan; None: the output is a mesh); products: a mesh output's preview and
    contours (MeshProducts; None: neither, or the output is a DEM, whose DemPlan has
    them)."""

    select: PointSelection = PointSelection()
    heights: HeightSettings = HeightSettings()
    surface: SurfaceSettings = SurfaceSettings()
    mesh: MeshTarget = MeshTarget()
    memory: int | None = None
    threads: int | None = None
    dem: DemPlan | None = None
    products: MeshProducts | None = None


@dataclass(frozen=True)
class TiledRun:
    """Where and how the tiles of a memory-bounded fit run, and whom they tell.

    per_tile: points per tile (overrides the budget's choice; for tests); directory:
    where the spill files go (None: beside a path output, else $TMPDIR); scheduler: a
    Dask scheduler's address (None: local); jobs: local processes (None: one per thread
    of the knob); outputs: with `--seamless -O`, one path per input (None: one mesh);
    on_stage(stage) after each stage; on_tile(pass, tiles done, tiles) as tiles finish;
    on_output(row) with each output's report row as it is written (`--seamless -O` in
    memory, whose tiles are the inputs)."""

    per_tile: int | None = None
    directory: object = None
    scheduler: str | None = None
    jobs: int | None = 1
    outputs: Sequence[str] | None = None
    on_stage: Callable[[str], None] | None = None
    on_tile: Callable[[str, int, int], None] | None = None
    on_output: Callable[[dict], None] | None = None
