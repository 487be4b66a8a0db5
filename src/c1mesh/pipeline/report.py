"""The fit report's schema, declared once, and the one function that builds its common part.

Every fit path (the plane fit, the raster/DEM fit, the perspective fit, `--seamless -o`,
`--seamless -O`, the memory-bounded tiled fit) builds its report from a `ReportCore`,
whose fields are exactly `REQUIRED`: a path that forgets a key fails
with a TypeError, so the paths cannot drift apart. A value that has no meaning on a
path is passed as None (JSON null); `REQUIRED` says where. Path-specific facts go in
the sections of `OPTIONAL`, present only when they apply. `validate_report` lists what
is wrong with a report (tests; cli/README.md documents the same table).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from c1mesh.core.crs import describe
from c1mesh.engine.properties import scheme_properties
from c1mesh.engine.schemes import get_scheme

REQUIRED: dict[str, tuple[str, str, str]] = {
    "input": ("the input path (a list for --seamless)", "path", "never null"),
    "output": ("the output path (a list for -O), null when the mesh only was returned",
               "path", "null without an output"),
    "points": ("point counts: read (after --classes, --bounds), kept (vertices of the surface), "
               "and per path dropped by reason, spacing", "points; spacing in length units", "never null"),
    "normals": ("where the normals came from: file, estimated, grid, file+grid, file+estimated",
                "—", "never null"),
    "gradients": ("where the vertex gradients came from: heights or normals (perspective: normals, "
                  "of the inverse depth)", "—", "never null"),
    "frame": ("the fit's frame: kind (axis or perspective), origin (perspective: the viewpoint), axes "
              "(rows e1, e2, e3; e3 the height axis or the viewing direction)", "length units", "never null"),
    "triangles": ("the triangulation: after_trim, max_edge (the trim's limit, null: none), "
                  "and per path before_trim, removed by reason", "triangles; max_edge in length units",
                  "never null"),
    "level": ("refinement level: each triangle became level² triangles",
              "—", "null for a raster (DEM) output: the spline is sampled, not refined"),
    "level_from": ("where the level came from: option, default, resolution, data",
                   "—", "null for a raster (DEM) output"),
    "output_mesh": ("the written mesh's vertices and faces", "count",
                    "null for a raster (DEM) output and for --seamless -O in memory (per output: tiles)"),
    "scheme": ("the shape functions' proven properties (engine.properties)", "—", "never null"),
    "c1_certificate": ("measured value and gradient jumps across sampled interior edges, relative",
                       "fraction", "null for the memory-bounded tiled fit (no one interpolator is held)"),
    "pieces": ("connected pieces of the surface: count, largest_fraction (of the triangles), "
               "area_fraction (of the points' convex hull)", "count; fraction",
               "null for the memory-bounded tiled fit"),
    "warnings": ("plain-language warnings about a result that is probably wrong (also on stderr)",
                 "—", "never null; always [] in the perspective frame (the rules are the height axis's)"),
    "crs": ("the CRS carried: its name, EPSG code, units and WKT, and source (file or option)",
            "—", "null: no CRS"),
    "seconds": ("wall-clock seconds per stage", "s", "never null"),
    "threads": ("threads every stage and BLAS could use", "count", "never null"),
    "z_factor": ("x, y units per height unit used for angles", "length/height",
                 "null: unknown (a header height column without --z-factor)"),
}
"""Every report's top-level keys: key -> (meaning, units, where it is null)."""

REQUIRED_PARTS: dict[str, tuple[str, ...]] = {
    "points": ("read", "kept"),
    "frame": ("kind", "origin", "axes"),
    "triangles": ("after_trim", "max_edge"),
}
"""Keys every report's sections carry (besides each path's own)."""

OPTIONAL: dict[str, str] = {
    "raster": "a raster (DEM) output: the GeoTIFFs written, cells, cells_with_data",
    "contours": "--contours: the file, interval, lines, closed lines, vertices, levels (count, lowest, "
                "highest), max_level_error (largest |spline − level| over the vertices written, heights), "
                "dropped_vertices (off the surface: their lines split), grid_resolution, seconds",
    "overshoot": "every in-memory fit (zeros under --overshoot off), the tiled fit under --overshoot "
                 "limit: the vertices and edges the limiter changed",
    "resolution": "--resolution was given (its value: the DEM's cell size, or the mesh's target mean edge)",
    "max_slope_not_applied": "a header height column without --z-factor: why --max-slope dropped nothing",
    "ownership": "--seamless -O: the rule that gives each triangle to one output",
    "scheduler": "tiles ran (--seamless -O, the tiled fit), or --scheduler was given and not used",
    "tiles": "--seamless -O in memory: one row per output; the tiled fit: the number of grid tiles",
    "tile_tasks": "the tiled fit: per tile, what each pass's task did",
    "note": "the tiled fit: that it was fitted in tiles",
    "max_edge": "the tiled fit: the trim's limit (also in triangles.max_edge)",
    "shared_vertex_keys": "the tiled fit: vertices shared between tiles",
    "shared_vertex_keys_held": "the tiled fit: most shared vertices held at once",
    "output_meshes": "the tiled fit with -O: each output's vertices and faces",
    "smoothing": "--smooth auto or a strength: strength (s), lam (λ), cv_curve ([s, held-out RMS in height "
                 "units] pairs), "
                 "search_limit_reached (--smooth auto: true when s is not an interior minimum of cv_curve "
                 "but at the search's limit, 1e-6 (with --spacing the lattice's least strength) or 1e7; null for a "
                 "given strength), edf (the effective degrees of freedom, Hutchinson's estimate; the CLI estimates "
                 "it only when it writes a report: FitOptions.edf), residual_rms, "
                 "residual_max (heights), solver, seconds, outside (data points outside the "
                 "triangulation), gradient_weight (of the gradient data: 1 file normals, "
                 "0.5 gradients fitted to the heights, 0: none), search_windows (--smooth auto: side "
                 "and centres, frame units, of the squares the search ran on, the same on every path; "
                 "no centres: the whole mesh; null for a given strength), lattice (--spacing: the "
                 "vertices' lattice: spacing D, reach_cells R of its support, nodes of the solve; null: "
                 "vertices at the points), fold_rounds and stiffened_cells (the fold net's solves and "
                 "the lattice cells it stiffened where the fit folded a face; 0 without --spacing or folds; "
                 "in tiles the most rounds a tile took and the union of the tiles' cells); the tiled fit adds "
                 "spacing (h) and tiled (halo, halo_smoothing_lengths)",
    "classes": "a LAS/LAZ input: which points were fitted: selected (the classification codes kept, "
               "[2] for the ground filter's ground, or \"all\"), source (option: --classes; file: the "
               "file's ground class 2, the default; filter: the ground filter, run because the file has "
               "no class 2 or --classes filter asked, with reason), filter (its name, parameters in "
               "metres, the file's units and metres per unit, halo_m, points and ground counts)",
    "suggestion": "an exact fit whose heights look noisy (the limiter changed over 10% of the "
                  "gradients): the advice to fit with --smooth auto",
}
"""Sections present only where they apply: key -> when."""


@dataclass(frozen=True)
class ReportCore:
    """The report's required part (REQUIRED, whose table says what each field means, its
    units and where it is null). Every path builds one, and no field has a default, so a
    path that forgets a key is a TypeError here, not a silent gap in one path's JSON."""

    input: Any
    output: Any
    points: dict
    normals: str
    gradients: str
    frame: dict
    triangles: dict
    level: int | None
    level_from: str | None
    output_mesh: dict | None
    scheme: dict
    c1_certificate: dict | None
    pieces: dict | None
    warnings: list
    crs: dict | None
    seconds: dict
    threads: int
    z_factor: float | None

    def as_dict(self) -> dict:
        """The JSON-ready dict, keys in REQUIRED's order (the fields' shallow values)."""
        return {name: getattr(self, name) for name in REQUIRED}


def crs_facts(crs: str | None, source: str | None) -> dict | None:
    """The report's crs: c1mesh.core.crs.describe's facts of WKT `crs` plus where it came
    from ("file" | "option"); None without a CRS."""
    facts = describe(crs)
    if facts is not None:
        facts["source"] = source
    return facts


def scheme_facts(scheme_name: str) -> dict:
    """The report's scheme: the proven properties of the named shape-function scheme."""
    return scheme_properties(get_scheme(scheme_name)).as_dict()


def validate_report(report: Mapping[str, Any]) -> list[str]:
    """What is wrong with a fit report, one line per problem ([] when it follows the
    schema): a required key or section key missing, a section that is not a dict, or a
    top-level key that neither REQUIRED nor OPTIONAL declares."""
    problems = [f"missing required key {key!r}" for key in REQUIRED if key not in report]
    for section, keys in REQUIRED_PARTS.items():
        value = report.get(section)
        if section not in report:
            continue
        if not isinstance(value, Mapping):
            problems.append(f"{section!r} is {type(value).__name__}, not an object")
            continue
        problems += [f"missing {section}.{key}" for key in keys if key not in value]
    problems += [f"undeclared key {key!r} (add it to REQUIRED or OPTIONAL)" for key in report
                 if key not in REQUIRED and key not in OPTIONAL]
    return problems


__all__ = ["REQUIRED", "REQUIRED_PARTS", "OPTIONAL", "ReportCore", "crs_facts", "scheme_facts",
           "validate_report"]
