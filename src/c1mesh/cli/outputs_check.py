"""Checks of the outputs and standard streams before any input is read (cli/README.md,
Output paths): every output against the inputs and each other (c1mesh.core.outputs), the
georeferencing options (c1mesh.geo.products), closed stdin/stdout. Failures exit 1.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

from c1mesh.cli.shell import fail, message
from c1mesh.core.errors import C1MeshError, InputError
from c1mesh.core.outputs import STDIO, mesh_format, plan_outputs


def check_geo(jobs_list, options, debug, report=None):
    """Georeferencing options checked before any input is read (c1mesh.geo.products.check_before;
    their conflicts are usage errors, found by c1mesh.cli.usage.check_usage): a bad CRS or an unwritable
    path exit 1. report: the --report path (a shapefile's parts must not be it). Returns the
    options with the CRS parsed to WKT."""
    from c1mesh.geo.products import check_before

    extra = [(label, path) for label, path in (("slope raster", options.slope),
                                               ("aspect raster", options.aspect),
                                               ("hillshade raster", options.hillshade),
                                               ("support raster", options.support),
                                               ("preview", options.preview),
                                               ("contours", options.contours)) if path]
    if options.contours and Path(options.contours).suffix.lower() == ".shp":    # its .shx .dbf .prj .cpg
        extra += [("contours part", str(Path(options.contours).with_suffix(part)))
                  for part in (".shx", ".dbf", ".prj", ".cpg")]
        extra += [("report", report)] if report not in (None, STDIO) else []
    try:
        if extra:   # against the inputs, the outputs and each other (c1mesh.core.outputs)
            plan_outputs([("output", dst) for _, dst in jobs_list] + extra, [src for src, _ in jobs_list])
        return check_before([dst for _, dst in jobs_list], options)
    except C1MeshError as exc:
        fail(message(exc), debug)


def check_outputs(pairs, report, output_dir):
    """All output targets (the meshes, then the report or None), checked against the inputs
    and each other before any input is read (c1mesh.core.outputs); raises C1MeshError/OSError."""
    if any(src == STDIO for src, _ in pairs):
        check_stdin()
    if output_dir and not Path(output_dir).exists():
        try:
            Path(output_dir).mkdir(parents=True)
        except OSError as exc:
            raise InputError(f"Cannot create the output directory '{output_dir}': "
                             f"{exc.strerror or exc}.") from exc
    named = [("output", dst) for _, dst in pairs] + [("report", None if report in (None, STDIO) else report)]
    targets = plan_outputs(named, [src for src, _ in pairs])
    from c1mesh.geo.raster import is_raster_path
    for (_, dst), target in zip(pairs, targets):
        if not is_raster_path(dst):     # GeoTIFF DEMs: checked by check_geo
            mesh_format(dst, target=target)
    return targets + [None] if report in (None, STDIO) else targets


def check_stdin() -> None:
    """InputError when standard input is closed (an input named -)."""
    try:
        os.fstat(sys.stdin.fileno())
    except (AttributeError, OSError, ValueError):
        raise InputError("Standard input is closed; give an input file or pipe points into '-'.") from None


def check_stdout() -> None:
    """InputError when standard output is closed (c1mesh info prints there)."""
    try:
        os.fstat(sys.stdout.fileno())
    except (AttributeError, OSError, ValueError):
        raise InputError("Standard output is closed; c1mesh info prints its answer there.") from None
