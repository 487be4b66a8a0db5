"""The `c1mesh` click group and its commands (fit, info, preview, schemes): their options
and help texts, each command a thin call into c1mesh.cli.fitting or the library.
"""
from __future__ import annotations

import json
import signal
import sys

import click

from c1mesh import __version__
from c1mesh.cli.fitting import Console, Destination, Workers, fit_batch, fit_one, fit_survey, threads_per_process
from c1mesh.cli.options import (
    CLASSES_HELP,
    CONTOURS_HELP,
    INPUT_FORMAT_HELP,
    MEMORY_HELP,
    OUTPUT_HELP,
    SMOOTH_HELP,
    parse_bounds_option,
    parse_classes,
    parse_fill,
    parse_spacing,
    parse_intrinsics,
    parse_max_edge,
    parse_memory_option,
    parse_smooth,
    plan,
)
from c1mesh.cli.outputs_check import check_geo, check_outputs, check_stdin, check_stdout
from c1mesh.cli.shell import Group, fail, message
from c1mesh.cli.usage import check_usage
from c1mesh.core.errors import C1MeshError
from c1mesh.core.outputs import STDIO


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="c1mesh")
def main() -> None:
    """Smooth C1 surface meshes from scanned points with normals."""
    # Behave like other shell tools when a reader closes the pipe early (`| head`):
    # end quietly with SIGPIPE instead of a BrokenPipeError.
    if hasattr(signal, "SIGPIPE"):
        signal.signal(signal.SIGPIPE, signal.SIG_DFL)


# ---------------------------------------------------------------------------------- fit
@main.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--output", help=OUTPUT_HELP)
@click.option("-O", "--output-dir", type=click.Path(file_okay=False),
              help="Directory for outputs of several inputs (each named input stem + --suffix).")
@click.option("--suffix", default=".c1.ply", show_default=True,
              help="Output name suffix with -O; its extension picks the format, as for -o.")
@click.option("--input-format", help=INPUT_FORMAT_HELP)
@click.option("--classes", default="auto", show_default=True, help=CLASSES_HELP)
@click.option("--normals", type=click.Choice(["auto", "file", "estimate"]), default="auto", show_default=True,
              help="auto: the file's normals if present, else estimated (Open3D).")
@click.option("--k", "k", type=click.IntRange(3, 1000), default=16, show_default=True,
              help="Neighbours for normal estimation.")
@click.option("--axis", default="auto", show_default=True,
              help="Height axis: auto, x, y, z or X,Y,Z (auto: z for LAS/LAZ and for a CSV whose header "
                   "names a height column (z, elev, elevation, height, h, alt, altitude) when normals are "
                   "estimated; else the mean normal, or PCA without normals).")
@click.option("--max-slope", type=click.FloatRange(0, 90, min_open=True, max_open=True), default=85.0,
              show_default=True, help="Drop points whose surface is steeper than this many degrees; for a "
                   "CSV header height column only with --z-factor (else a note says it was not applied).")
@click.option("--max-edge", default="auto", show_default=True,
              help="Remove triangles with a longer edge: auto, none, or a length in the scan's units.")
@click.option("--scheme", type=click.Choice(["sextic", "quintic", "ex39b"]), default="sextic",
              show_default=True, help="Shape-function tuple (see `c1mesh schemes`).")
@click.option("--level", type=click.IntRange(1, 64), default=None,
              help="Each triangle is split into level² triangles.  [default: 4; in the perspective "
                   "frame the level giving about one vertex per valid pixel or point: 1 for a depth frame]")
@click.option("--ascii", "ascii_ply", is_flag=True, help="Write ASCII PLY instead of binary.")
@click.option("--frame", "frame_kind", type=click.Choice(["auto", "axis", "perspective"]), default="auto",
              show_default=True, help="axis: height over a plane (--axis); perspective: inverse depth over "
              "the view rays from --viewpoint; auto: perspective for organised scans and depth images.")
@click.option("--viewpoint", help="Sensor position x,y,z[,qw,qx,qy,qz] for --frame perspective "
              "(default: the file's VIEWPOINT, else the origin).")
@click.option("--intrinsics", help="Depth images: the camera's fx,fy,cx,cy in pixels.")
@click.option("--depth-scale", type=click.FloatRange(0, min_open=True), default=0.001, show_default=True,
              help="Depth images: metres per depth unit.")
@click.option("--color", "color_image", help="Depth images: an RGB image of the same size for vertex colours.")
@click.option("--overshoot", type=click.Choice(["limit", "off"]), default="limit", show_default=True,
              help="limit: ease the heights of near-coincident noisy points, tame gradients that "
                   "disagree with the heights, and thin triangles (keeps C1); off: use the data as is.")
@click.option("--gradients", type=click.Choice(["auto", "normals", "heights"]), default="auto",
              show_default=True, help="Vertex gradients: heights: a local quadratic fit to the "
                   "neighbours' heights; normals: from the normals; auto: heights where normals are estimated.")
@click.option("--smooth", default="default", metavar="off|auto|S", help=SMOOTH_HELP)
@click.option("--spacing", default=None, metavar="auto|D",
              help="With --smooth: the vertices on a D x D lattice (D in the scan's units) over the "
                   "points, fitted to all of them; solved by multigrid. auto: the points' mean spacing, "
                   "whatever --resolution is.  [default: auto for the default smoothing fit; with "
                   "--smooth given, a vertex at every point]")
@click.option("--report", help="Write a JSON report to FILE, or - for stderr.")
@click.option("--memory", callback=parse_memory_option, help=MEMORY_HELP)
@click.option("--bounds", callback=parse_bounds_option, metavar="XMIN,YMIN,XMAX,YMAX",
              help="Fit only the points in this x/y box (file units); a COPC file is read by its "
                   "octree, decoding only the nodes that meet the box.")
@click.option("-j", "--jobs", type=click.IntRange(1, 256), default=None,
              help="Parallel processes for several inputs, or for the tiles of --seamless -O "
                   "and of a fit larger than --memory (as many tiles at once as --memory allows). "
                   "[default: 1; a fit larger than --memory: one per thread of --threads]")
@click.option("--threads", type=click.IntRange(1, 1024), default=None,
              help="Threads in all (BLAS included); with --jobs N each process gets "
                   "max(1, THREADS // N).  [default: the CPUs this process may use]")
@click.option("--seamless", is_flag=True,
              help="Treat the inputs as one survey: -o writes one mesh, -O one mesh per input that "
                   "joins its neighbours exactly (docs/tiles.md), or with --suffix .tif --resolution R "
                   "one DEM per input and their mosaic DIR/mosaic.vrt.")
@click.option("--scheduler", help="With --seamless -O, or a fit larger than --memory: run the tiles on this "
                                  "Dask scheduler (tcp://HOST:PORT); for the latter its workers must see "
                                  "the output's folder (the spill files). A fit within --memory runs here, "
                                  "with a note.")
@click.option("-q", "--quiet", is_flag=True, help="No progress and no summary.")
@click.option("-v", "--verbose", is_flag=True, help="Print a summary line per input on stderr.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
@click.option("--crs", help="CRS of an input that has none: EPSG:XXXX, WKT, or a .prj/.wkt file.")
@click.option("--resolution", type=float,
              help="GeoTIFF cell size (-o *.tif); for meshes the target mean edge length (instead of --level).")
@click.option("--slope", help="Also write a slope GeoTIFF (degrees) on the DEM's grid.")
@click.option("--aspect", help="Also write an aspect GeoTIFF (degrees clockwise from north).")
@click.option("--hillshade", help="Also write a hillshade GeoTIFF (uint8).")
@click.option("--support", help="Also write a support GeoTIFF (float32): each DEM cell's distance, in "
                                "CRS units, from its centre to the nearest point the fit used.")
@click.option("--fill", default="hull", show_default=True, metavar="hull|off|D",
              help="DEM cells in holes the trim opened (under buildings, trees, water): hull fills every "
                   "cell inside the hull of the points, D only cells within D (CRS units) of a point, "
                   "off (or 0) leaves them nodata. Meshes keep the trim's holes.")
@click.option("--z-factor", "z_factor", type=float, default=None,
              help="x, y units per height unit (ArcGIS's z-factor, 1/gdaldem -s) for --slope, --hillshade, "
                   "the preview's shading and a height column's --max-slope.  [default: 1; required for "
                   "--slope/--hillshade of a CSV header height column, whose units may differ]")
@click.option("--slope-method", type=click.Choice(["auto", "spline", "horn"]), default="auto",
              show_default=True, help="Gradient for slope/aspect/hillshade: the spline's, or Horn's of the DEM.")
@click.option("--preview", help="Also render a PNG preview (hillshade coloured by height).")
@click.option("--contours", help=CONTOURS_HELP)
@click.option("--interval", type=float, help="Height between two contour lines (--contours): levels are its "
              "multiples, in the units of z.")
@click.pass_context
def fit(ctx, inputs, output, output_dir, suffix, input_format, classes, normals, k, axis, max_slope,
        max_edge, scheme, level, ascii_ply, frame_kind, viewpoint, intrinsics, depth_scale, color_image,
        overshoot, gradients, report, memory, jobs, quiet, verbose, debug,
        threads, crs, resolution, slope, aspect, hillshade, z_factor, slope_method, preview, seamless,
        scheduler, bounds, smooth, spacing, support, fill, contours, interval):
    """Fit a refined C1 surface mesh to each INPUT scan (- reads stdin)."""
    check_usage(ctx)       # every usage error at once, before any input is read
    classes, max_edge = parse_classes(classes), parse_max_edge(max_edge)
    intrinsics = parse_intrinsics(intrinsics)
    smooth_option = "off" if parse_smooth(smooth) is None else parse_smooth(smooth)
    console = Console(report, quiet, verbose, debug)
    if seamless:
        from c1mesh.pipeline.driver import FitOptions

        options = FitOptions(input_format=input_format, axis=axis, normals=normals, k=k, classes=classes,
                             max_slope=max_slope, max_edge=max_edge, scheme=scheme, level=level,
                             ascii=ascii_ply, memory=memory, crs=crs, overshoot=overshoot,
                             gradients=gradients, resolution=resolution, slope=slope, aspect=aspect,
                             hillshade=hillshade, slope_method=slope_method, preview=preview, bounds=bounds,
                             z_factor=z_factor, smooth=smooth_option, spacing=parse_spacing(spacing), support=support,
                             fill=parse_fill(fill), contours=contours, interval=interval,
                             edf=report is not None)
        if output and not output_dir:
            options = check_geo([(inputs[0], output)], options, debug, report)
        fit_survey(inputs, Destination(output, output_dir, suffix), options, console,
                   Workers(jobs, threads, scheduler))
        return
    pairs = plan(inputs, output, output_dir, suffix)
    if scheme == "quintic" and not quiet:
        click.echo("c1mesh: warning: the quintic scheme does not reproduce planes and its normals "
                   "do not converge; use sextic unless you need the 2022 procedure", err=True)
    try:
        targets = check_outputs(pairs, report, output_dir)
    except (C1MeshError, OSError) as exc:
        fail(message(exc), debug)
    from c1mesh.pipeline.driver import FitOptions

    options = FitOptions(input_format=input_format, axis=axis, normals=normals, k=k, classes=classes,
                         max_slope=max_slope, max_edge=max_edge, scheme=scheme, level=level, ascii=ascii_ply,
                         memory=memory, crs=crs, resolution=resolution, slope=slope, aspect=aspect,
                         hillshade=hillshade, slope_method=slope_method, preview=preview,
                         overshoot=overshoot, gradients=gradients, frame=frame_kind, viewpoint=viewpoint,
                         intrinsics=intrinsics, z_factor=z_factor,
                         depth_scale=depth_scale, color=color_image, bounds=bounds,
                         smooth=smooth_option, spacing=parse_spacing(spacing), support=support, fill=parse_fill(fill),
                         contours=contours, interval=interval, edf=report is not None)
    options = check_geo(pairs, options, debug, report)
    options.workers = threads_per_process(threads, min(jobs or 1, len(pairs)))
    if len(pairs) == 1:
        fit_one(*pairs[0], targets, options, console, Workers(jobs, threads, scheduler))
        return
    fit_batch(pairs, targets[-1], options, console, Workers(jobs, threads, scheduler))


# -------------------------------------------------------------------------------- ground
@main.command()
@click.argument("input_path", metavar="INPUT")
@click.option("-o", "--output", required=True, help="The LAS/LAZ file to write (.las or .laz).")
@click.option("--report", help="Write a JSON report to FILE, or - for stderr.")
@click.option("-q", "--quiet", is_flag=True, help="No summary line.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
def ground(input_path, output, report, quiet, debug):
    """Write INPUT's points with the ground filter's classes: 2 ground, 1 the rest (docs/ground.md)."""
    from c1mesh.cli.fitting import classify_ground_file

    check_usage(click.get_current_context())
    classify_ground_file(input_path, output, report, quiet, debug)


# ---------------------------------------------------------------------------------- info
@main.command()
@click.argument("path")
@click.option("--input-format", help=INPUT_FORMAT_HELP)
@click.option("--memory", callback=parse_memory_option, help=MEMORY_HELP)
@click.option("--intrinsics", help="Depth images: the camera's fx,fy,cx,cy in pixels.")
@click.option("--depth-scale", type=click.FloatRange(0, min_open=True), default=0.001, show_default=True,
              help="Depth images: metres per depth unit.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
def info(path, input_format, memory, intrinsics, depth_scale, debug):
    """Describe a point file: points, fields, normals, bounds, suggested axis, height field?"""
    from c1mesh.pipeline.inspect import describe

    check_usage(click.get_current_context())
    try:
        if path == STDIO:
            check_stdin()
        check_stdout()
        facts = describe(sys.stdin.buffer if path == "-" else path, input_format, memory=memory,
                         intrinsics=parse_intrinsics(intrinsics), depth_scale=depth_scale)
    except Exception as exc:  # noqa: BLE001
        fail(message(exc), debug)
    click.echo(json.dumps(facts, indent=2))


# ------------------------------------------------------------------------------- preview
@main.command()
@click.argument("path")
@click.option("-o", "--output", required=True, help="The PNG to write.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
def preview(path, output, debug):
    """Render PATH (a GeoTIFF DEM or a mesh with normals) as a shaded PNG."""
    from c1mesh.geo.preview import render_file
    from c1mesh.geo.products import check_preview_path

    check_usage(click.get_current_context())
    try:
        check_preview_path(output)
        render_file(path, output)
    except Exception as exc:  # noqa: BLE001
        fail(message(exc), debug)


# ------------------------------------------------------------------------------- schemes
@main.command()
def schemes():
    """List the shape-function tuples with their computed properties."""
    from c1mesh.engine.properties import scheme_properties
    from c1mesh.engine.schemes import DEFAULT_SCHEME, NAMED_TUPLES

    click.echo(f"{'name':<9} {'degree':>6}  {'constants':<9}  {'affine':<6}  description")
    for name, tup in NAMED_TUPLES.items():
        p = scheme_properties(tup)
        description = tup.description.replace(" (default)", "")   # the mark is added here, once
        mark = " (default)" if name == DEFAULT_SCHEME else ""
        click.echo(f"{name:<9} {p.degree:>6}  {'yes' if p.reproduces_constants else 'no':<9}  "
                   f"{'yes' if p.reproduces_affine else 'no':<6}  {description}{mark}")
