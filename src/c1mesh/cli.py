"""The `c1mesh` command: a thin click layer over the library.

Exit codes (cli/README.md): 0 success, 1 failure, 2 usage error, 3 batch where some
inputs failed, 128+N killed by signal N (SIGINT 130, SIGTERM 143, SIGHUP 129). Errors
are one line on stderr; --debug shows the traceback. Progress goes to stderr only when
stderr is a terminal. Every output path is checked (c1mesh.outputs) before any input is
read. Nothing heavy (numpy, scipy, open3d) is imported until a command runs, so --help
and usage errors are quick.
"""
from __future__ import annotations

import json
import math
import os
import signal
import sys
import traceback
import warnings
from pathlib import Path

import click

from c1mesh import __version__
from c1mesh.errors import C1MeshError, InputError
from c1mesh.outputs import STDIO, Outputs, mesh_format, plan_outputs, remove_live_temps

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_PARTIAL = 0, 1, 2, 3
_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


def _fail(message: str, debug: bool = False) -> None:
    """One line on stderr (plus the traceback under --debug), then exit 1."""
    if debug:
        traceback.print_exc()
    click.echo(f"c1mesh: error: {message}", err=True)
    sys.exit(EXIT_FAILURE)


def _message(exc: BaseException) -> str:
    """A one-line description of an exception for the user."""
    if isinstance(exc, C1MeshError):
        text = str(exc)
    elif isinstance(exc, MemoryError):
        text = "out of memory; try a lower --level or split the input"
    elif isinstance(exc, OSError):
        where = f"'{exc.filename}': " if exc.filename else ""
        text = f"{where}{exc.strerror or exc or type(exc).__name__}"
    else:
        text = f"unexpected {type(exc).__name__}: {exc}"
    return " ".join(text.split())


def _parse_classes(value: str | None) -> tuple[int, ...] | None:
    if not value:
        return None
    try:
        return tuple(int(v) for v in value.split(",") if v.strip())
    except ValueError:
        raise click.BadParameter(f"expected comma-separated integers such as 2,9, got {value!r}")


def _parse_memory(ctx, param, value):
    """--memory: a size such as 512M or 8G (None = the reader's default)."""
    if value is None:
        return None
    from c1mesh.formats._limits import parse_memory
    try:
        return parse_memory(value)
    except C1MeshError as exc:
        raise click.BadParameter(str(exc))


def _parse_bounds(ctx, param, value):
    """--bounds: XMIN,YMIN,XMAX,YMAX (None = the whole input)."""
    if value is None:
        return None
    from c1mesh.formats.copc import parse_box
    try:
        return parse_box(value)
    except C1MeshError as exc:
        raise click.BadParameter(str(exc))


_MEMORY_HELP = ("Most bytes of input to read and decode, e.g. 512M or 8G; larger or endless inputs "
                "are refused [default: half the RAM, at most 8G]. With fit, a LAS/LAZ file whose "
                "points need more (1.8 kB per point) is fitted in tiles (estimated normals, long-edge trim).")


def _parse_max_edge(value: str):
    if value.lower() == "auto":
        return "auto"
    if value.lower() == "none":
        return None
    try:
        length = float(value)
    except ValueError:
        raise click.BadParameter(f"expected auto, none or a positive length, got {value!r}")
    if not (length > 0 and math.isfinite(length)):
        raise click.BadParameter(f"expected a positive finite length (or none), got {value!r}")
    return length


def _parse_intrinsics(value: str | None) -> tuple[float, ...] | None:
    """--intrinsics fx,fy,cx,cy (pixels, fx and fy > 0); plain Python, so usage errors stay fast."""
    if value is None:
        return None
    try:
        parts = tuple(float(p) for p in value.split(","))
    except ValueError:
        parts = ()
    if len(parts) != 4 or not all(math.isfinite(p) for p in parts) or parts[0] <= 0 or parts[1] <= 0:
        raise click.BadParameter(f"expected fx,fy,cx,cy in pixels with fx, fy > 0, got {value!r}",
                                 param_hint="'--intrinsics'")
    return parts


def _check_axis(value: str) -> None:
    """Usage error for an --axis that can never be a direction (checked again, and
    normalised, by c1mesh.frame)."""
    text = value.strip().lower().lstrip("+-")
    if text in ("auto", "x", "y", "z"):
        return
    try:
        parts = [float(part) for part in text.split(",")]
    except ValueError:
        parts = []
    if len(parts) != 3:
        raise click.BadParameter(f"expected auto, x, y, z (optionally signed) or X,Y,Z, got {value!r}",
                                 param_hint="'--axis'")
    if not all(math.isfinite(p) for p in parts) or not any(parts):
        raise click.BadParameter(f"the axis {value!r} has no direction (zero, NaN or Inf)",
                                 param_hint="'--axis'")


def _stderr_is_terminal() -> bool:
    try:
        return os.isatty(sys.stderr.fileno())
    except (AttributeError, OSError, ValueError):
        return False


class _Group(click.Group):
    """A click group whose unexpected failures are still one line on stderr and exit 1."""

    def invoke(self, ctx):
        previous = {sig: signal.signal(sig, _interrupted) for sig in _SIGNALS}
        try:
            with warnings.catch_warnings():
                # numpy's overflow / invalid-value RuntimeWarnings are not news to a user:
                # a failing run prints its one error line and nothing else.
                warnings.simplefilter("ignore", RuntimeWarning)
                return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except Exception as exc:  # noqa: BLE001 — the safety net under every command
            _fail(_message(exc), debug="--debug" in sys.argv)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)


def _interrupted(signum, frame) -> None:
    """SIGINT/SIGTERM/SIGHUP: stop the batch's worker processes, remove this process's
    temporary output files, print one line and exit 128+signum at once (no traceback, no
    waiting for threads that may be deep in a write)."""
    if hasattr(signal, "SIGPIPE"):   # the pool's feeder thread writes to the workers' closing pipes
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    multiprocessing = sys.modules.get("multiprocessing")
    if multiprocessing is not None:
        children = multiprocessing.active_children()
        for child in children:
            child.terminate()
        for child in children:
            child.join(10)
    remove_live_temps()
    try:
        os.write(2, f"c1mesh: error: interrupted ({signal.Signals(signum).name})\n".encode())
    except OSError:
        pass
    os._exit(128 + signum)


def _worker_interrupted(signum, frame) -> None:
    """A batch worker's signal handler: remove its temporary files and end quietly (the
    parent prints the one line)."""
    remove_live_temps()
    os._exit(128 + signum)


def _worker_start() -> None:
    for sig in _SIGNALS:
        signal.signal(sig, _worker_interrupted)
    warnings.simplefilter("ignore", RuntimeWarning)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
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
@click.option("-o", "--output", help="Output mesh (.ply .obj .stl .off .glb), or - for binary PLY on stdout.")
@click.option("-O", "--output-dir", type=click.Path(file_okay=False),
              help="Directory for outputs of several inputs (each named input stem + --suffix).")
@click.option("--suffix", default=".c1.ply", show_default=True, help="Output name suffix with -O.")
@click.option("--input-format", help="Input format (ply, obj, xyz, txt, csv, pcd, las, laz, copc); required for stdin (-).")
@click.option("--classes", help="Keep only these LAS classification codes, e.g. 2 or 2,9 (2 = ground).")
@click.option("--normals", type=click.Choice(["auto", "file", "estimate"]), default="auto", show_default=True,
              help="auto: the file's normals if present, else estimated (Open3D).")
@click.option("--k", "k", type=click.IntRange(3, 1000), default=16, show_default=True,
              help="Neighbours for normal estimation.")
@click.option("--axis", default="auto", show_default=True,
              help="Height axis: auto, x, y, z or X,Y,Z (auto: mean normal, or PCA without normals).")
@click.option("--max-slope", type=click.FloatRange(0, 90, min_open=True, max_open=True), default=85.0,
              show_default=True, help="Drop points whose normal is within this many degrees of the plane.")
@click.option("--max-edge", default="auto", show_default=True,
              help="Remove triangles with a longer edge: auto, none, or a length in the scan's units.")
@click.option("--scheme", type=click.Choice(["sextic", "quintic", "ex39b"]), default="sextic",
              show_default=True, help="Shape-function tuple (see `c1mesh schemes`).")
@click.option("--level", type=click.IntRange(1, 64), default=4, show_default=True,
              help="Each triangle is split into level² triangles.")
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
@click.option("--report", help="Write a JSON report to FILE, or - for stderr.")
@click.option("--memory", callback=_parse_memory, help=_MEMORY_HELP)
@click.option("--bounds", callback=_parse_bounds, metavar="XMIN,YMIN,XMAX,YMAX",
              help="Fit only the points in this x/y box (file units); a COPC file is read by its "
                   "octree, decoding only the nodes that meet the box.")
@click.option("-j", "--jobs", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Parallel processes for several inputs, or for the tiles of --seamless -O "
                   "and of a fit larger than --memory (as many tiles at once as --memory allows).")
@click.option("--threads", type=click.IntRange(1, 1024), default=None,
              help="Threads in all (BLAS included); with --jobs N each process gets "
                   "max(1, THREADS // N).  [default: the CPUs this process may use]")
@click.option("--seamless", is_flag=True,
              help="Treat the inputs as one survey: -o writes one mesh, -O one mesh per input that "
                   "joins its neighbours exactly (docs/tiles.md).")
@click.option("--scheduler", help="With --seamless -O, or a fit larger than --memory: run the tiles on this "
                                  "Dask scheduler (tcp://HOST:PORT); for the latter its workers must see "
                                  "the output's folder (the spill files).")
@click.option("-q", "--quiet", is_flag=True, help="No progress and no summary.")
@click.option("-v", "--verbose", is_flag=True, help="Print a summary line per input on stderr.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
@click.option("--crs", help="CRS of an input that has none: EPSG:XXXX, WKT, or a .prj/.wkt file.")
@click.option("--resolution", type=float,
              help="GeoTIFF cell size (-o *.tif); for meshes the target mean edge length (instead of --level).")
@click.option("--slope", help="Also write a slope GeoTIFF (degrees) on the DEM's grid.")
@click.option("--aspect", help="Also write an aspect GeoTIFF (degrees clockwise from north).")
@click.option("--hillshade", help="Also write a hillshade GeoTIFF (uint8).")
@click.option("--slope-method", type=click.Choice(["auto", "spline", "horn"]), default="auto",
              show_default=True, help="Gradient for slope/aspect/hillshade: the spline's, or Horn's of the DEM.")
@click.option("--preview", help="Also render a PNG preview (hillshade coloured by height).")
@click.pass_context
def fit(ctx, inputs, output, output_dir, suffix, input_format, classes, normals, k, axis, max_slope,
        max_edge, scheme, level, ascii_ply, frame_kind, viewpoint, intrinsics, depth_scale, color_image,
        overshoot, gradients, report, memory, jobs, quiet, verbose, debug,
        threads, crs, resolution, slope, aspect, hillshade, slope_method, preview, seamless, scheduler,
        bounds):
    """Fit a refined C1 surface mesh to each INPUT scan (- reads stdin)."""
    classes, max_edge = _parse_classes(classes), _parse_max_edge(max_edge)
    intrinsics = _parse_intrinsics(intrinsics)
    _check_axis(axis)
    if seamless or scheduler:
        from c1mesh.pipeline import FitOptions

        if output_dir and (resolution is not None or slope or aspect or hillshade or preview):
            raise click.UsageError("--resolution, --slope, --aspect, --hillshade and --preview make one "
                                   "survey-wide output: use them with --seamless -o, not -O")
        options = FitOptions(input_format=input_format, axis=axis, normals=normals, k=k, classes=classes,
                             max_slope=max_slope, max_edge=max_edge, scheme=scheme, level=level,
                             ascii=ascii_ply, memory=memory, crs=crs, overshoot=overshoot,
                             gradients=gradients, resolution=resolution, slope=slope, aspect=aspect,
                             hillshade=hillshade, slope_method=slope_method, preview=preview, bounds=bounds)
        if output and not output_dir:
            options = _check_geo(ctx, [(inputs[0], output)], options, debug)
        _fit_seamless(inputs, output, output_dir, suffix, input_format, options, report, jobs, threads,
                      scheduler, quiet, debug)
        return
    pairs = _plan(inputs, output, output_dir, suffix, input_format)
    _check_conflicts(pairs, input_format, classes, ascii_ply)
    if scheme == "quintic" and not quiet:
        click.echo("c1mesh: warning: the quintic scheme does not reproduce planes and its normals "
                   "do not converge; use sextic unless you need the 2022 procedure", err=True)
    try:
        targets = _check_outputs(pairs, report, output_dir)
    except (C1MeshError, OSError) as exc:
        _fail(_message(exc), debug)
    from c1mesh.pipeline import FitOptions

    options = FitOptions(input_format=input_format, axis=axis, normals=normals, k=k, classes=classes,
                         max_slope=max_slope, max_edge=max_edge, scheme=scheme, level=level, ascii=ascii_ply,
                         memory=memory, crs=crs, resolution=resolution, slope=slope, aspect=aspect,
                         hillshade=hillshade, slope_method=slope_method, preview=preview,
                         overshoot=overshoot, gradients=gradients, frame=frame_kind, viewpoint=viewpoint,
                         intrinsics=intrinsics,
                         depth_scale=depth_scale, color=color_image, bounds=bounds)
    options = _check_geo(ctx, pairs, options, debug)
    options.workers = _threads_per_process(threads, min(jobs, len(pairs)))
    if len(pairs) == 1:
        _fit_one(*pairs[0], targets, options, report, quiet, verbose, debug, jobs)
        return
    _fit_batch(pairs, targets[-1], options, report, jobs, quiet, verbose, debug)


def _threads_per_process(threads: int | None, jobs: int) -> int:
    """--threads shared by the --jobs processes, so together they do not oversubscribe
    (Open3D's OpenMP threads included)."""
    from c1mesh.threads import openmp_at_start, per_process
    count = per_process(threads, jobs)
    openmp_at_start(count)
    return count


def _plan(inputs, output, output_dir, suffix, input_format) -> list[tuple[str, str]]:
    """(input, output) pairs; usage errors (exit 2) for inconsistent options."""
    if len(inputs) > 1 and output:
        raise click.UsageError("several inputs need -O/--output-dir, not -o")
    if output and output_dir:
        raise click.UsageError("use either -o/--output or -O/--output-dir")
    if "-" in inputs and not input_format:
        raise click.UsageError("reading stdin (-) needs --input-format")
    if "-" in inputs and len(inputs) > 1:
        raise click.UsageError("stdin (-) can only be the single input")
    if output_dir:
        pairs = [(src, str(Path(output_dir) / (("stdin" if src == "-" else Path(src).stem) + suffix)))
                 for src in inputs]
        outputs = [dst for _, dst in pairs]
        clash = sorted({d for d in outputs if outputs.count(d) > 1})
        if clash:
            raise click.UsageError(f"several inputs would write the same output {clash[0]}; rename them "
                                   "or run them separately")
        return pairs
    if not output:
        raise click.UsageError("give -o OUTPUT (or -O DIR for several inputs)")
    return [(inputs[0], output)]


def _fit_seamless(inputs, output, output_dir, suffix, input_format, options, report, jobs, threads,
                  scheduler, quiet, debug) -> None:
    """`fit --seamless`: the inputs as one survey (c1mesh.tiles), one line on any failure."""
    if STDIO in inputs:
        raise click.UsageError("--seamless reads files, not stdin (-)")
    if output and output_dir:
        raise click.UsageError("use either -o/--output or -O/--output-dir")
    if not output and not output_dir:
        raise click.UsageError("give -o OUTPUT (one mesh) or -O DIR (one mesh per input)")
    pairs = _plan(inputs, None, output_dir, suffix, input_format) if output_dir else [(inputs[0], output)]
    _check_conflicts(pairs, input_format, options.classes, options.ascii)
    try:
        if options.crs:
            from dataclasses import replace

            from c1mesh.crs import parse_crs
            options = replace(options, crs=parse_crs(options.crs))
        if output_dir and not Path(output_dir).exists():
            Path(output_dir).mkdir(parents=True)
        named = [("output", dst) for _, dst in pairs] + [("report", None if report in (None, STDIO) else report)]
        targets = plan_outputs(named, list(inputs))
        from c1mesh.raster import is_raster_path
        for (_, dst), target in zip(pairs, targets):
            if not is_raster_path(dst):
                mesh_format(dst, target=target)
    except (C1MeshError, OSError) as exc:
        _fail(_message(exc), debug)
    from c1mesh.tiles import fit_seamless

    options.workers = _threads_per_process(threads, 1)
    mesh = sys.stdout.buffer if output == STDIO else output
    outputs = [d for _, d in pairs] if output_dir else None
    try:
        if _stderr_is_terminal() and not quiet:
            progress, callbacks = _survey_progress(list(inputs), options, len(pairs) if output_dir else 0)
            with progress:
                result = fit_seamless(inputs, options, mesh, outputs, scheduler, jobs, **callbacks)
        else:
            result = fit_seamless(inputs, options, mesh, outputs, scheduler, jobs)
    except Exception as exc:  # noqa: BLE001 — a failed tile names itself; no output is left
        _fail(_message(exc), debug)
    _warn(result, quiet)
    _write_report(report, targets[-1], result, debug)


def _stage_bar(length: int, label: str):
    """A click progress bar on stderr of `length` steps, showing each step's name."""
    return click.progressbar(length=length, label=label, file=sys.stderr, item_show_func=lambda s: s)


def _caption(bar, text: str) -> None:
    """Show text beside a click progress bar without advancing it: bar.update(0, text)
    sets the text but draws nothing until the next step (a tiled fit's tile counts then
    never appeared)."""
    bar.current_item = text
    bar.render_progress()


def _survey_progress(inputs, options, outputs: int):
    """A --seamless fit's progress bar on stderr and the fit_seamless callbacks that move
    it: for a survey fitted in tiles beyond --memory (c1mesh.tiled_fit), its stages with
    each pass's tile count, as a single large input shows them; in memory, the outputs
    of -O as their tiles are written, or the stages of the one -o fit."""
    from c1mesh.pipeline import STAGES
    from c1mesh.tiled_fit import TILED_STAGES
    from c1mesh.tiles import survey_needs_tiles

    if survey_needs_tiles(inputs, options):
        progress = _stage_bar(len(TILED_STAGES), "fitting survey")
        return progress, {"on_stage": lambda name: progress.update(1, name),
                          "on_tile_pass": lambda name, done, tiles: _caption(progress,
                                                                             f"{name}: tile {done} of {tiles}")}
    if outputs:
        progress = _stage_bar(outputs, "tiles")
        return progress, {"on_tile": lambda row: progress.update(1, row["tile"])}
    progress = _stage_bar(len(STAGES), "fitting survey")
    return progress, {"on_stage": lambda name: progress.update(1, name)}


def _check_geo(ctx, jobs_list, options, debug):
    """Georeferencing options checked before any input is read (c1mesh.geo.check_before):
    conflicts are usage errors (exit 2), a bad CRS or unwritable path exit 1. Returns the
    options with the CRS parsed to WKT."""
    from click.core import ParameterSource

    from c1mesh.geo import check_before

    if options.resolution is not None and ctx.get_parameter_source("level") != ParameterSource.DEFAULT:
        raise click.UsageError("give either --level or --resolution, not both")
    extras = (options.slope, options.aspect, options.hillshade, options.preview)
    if len(jobs_list) > 1 and any(extras):
        raise click.UsageError("--slope, --aspect, --hillshade and --preview name one file: "
                               "use them with a single input")
    extra = [(label, path) for label, path in (("slope raster", options.slope),
                                               ("aspect raster", options.aspect),
                                               ("hillshade raster", options.hillshade),
                                               ("preview", options.preview)) if path]
    try:
        if extra:   # against the inputs, the outputs and each other (c1mesh.outputs)
            plan_outputs([("output", dst) for _, dst in jobs_list] + extra, [src for src, _ in jobs_list])
        return check_before([dst for _, dst in jobs_list], options)
    except C1MeshError as exc:
        _fail(_message(exc), debug)


def _check_conflicts(pairs, input_format, classes, ascii_ply) -> None:
    """Usage errors for options that cannot apply to these inputs and outputs."""
    mesh_formats = {"ply" if dst == STDIO else Path(dst).suffix.lower().lstrip(".") for _, dst in pairs}
    if ascii_ply and mesh_formats - {"ply"}:
        raise click.UsageError(f"--ascii applies to PLY output only, not .{sorted(mesh_formats - {'ply'})[0]}")
    if classes:
        kinds = {(input_format or Path(src).suffix).lower().lstrip(".") for src, _ in pairs}
        if kinds - {"las", "laz", "copc"}:
            raise click.UsageError("--classes needs LAS/LAZ input (a classification field), not "
                                   f".{sorted(kinds - {'las', 'laz', 'copc'})[0] or '(no extension)'}")


def _check_outputs(pairs, report, output_dir):
    """All output targets (the meshes, then the report or None), checked against the inputs
    and each other before any input is read (c1mesh.outputs); raises C1MeshError/OSError."""
    if any(src == STDIO for src, _ in pairs):
        _check_stdin()
    if output_dir and not Path(output_dir).exists():
        try:
            Path(output_dir).mkdir(parents=True)
        except OSError as exc:
            raise InputError(f"Cannot create the output directory '{output_dir}': "
                             f"{exc.strerror or exc}.") from exc
    named = [("output", dst) for _, dst in pairs] + [("report", None if report in (None, STDIO) else report)]
    targets = plan_outputs(named, [src for src, _ in pairs])
    from c1mesh.raster import is_raster_path
    for (_, dst), target in zip(pairs, targets):
        if not is_raster_path(dst):     # GeoTIFF DEMs: checked by _check_geo
            mesh_format(dst, target=target)
    return targets + [None] if report in (None, STDIO) else targets


def _check_stdin() -> None:
    try:
        os.fstat(sys.stdin.fileno())
    except (AttributeError, OSError, ValueError):
        raise InputError("Standard input is closed; give an input file or pipe points into '-'.") from None


def _check_stdout() -> None:
    try:
        os.fstat(sys.stdout.fileno())
    except (AttributeError, OSError, ValueError):
        raise InputError("Standard output is closed; c1mesh info prints its answer there.") from None


def _run(src: str, target, options, on_stage=None, jobs: int = 1, on_tile=None) -> dict:
    """Fit one input to one output (a path, or a file object then with options.output_format);
    an input fitted in tiles runs them on `jobs` local processes."""
    from c1mesh.pipeline import fit as fit_pipeline
    from c1mesh.tiled_fit import fit_tiled, needs_tiles

    source = sys.stdin.buffer if src == STDIO else src
    if needs_tiles(source, options):          # larger than --memory allows: c1mesh.tiled_fit
        return fit_tiled(source, target, options, options.memory, on_stage=on_stage, jobs=jobs,
                         on_tile=on_tile)
    return fit_pipeline(source, target, options, on_stage=on_stage, keep_mesh=False).report


def _fit_one(src, dst, targets, options, report, quiet, verbose, debug, jobs: int = 1) -> None:
    """Fit one input; the mesh and the report are committed together, or neither is."""
    from dataclasses import replace

    from c1mesh.pipeline import STAGES

    from c1mesh.raster import is_raster_path

    mesh_target, report_target = targets
    raster = is_raster_path(dst)
    options = replace(options, output_format=None if raster else mesh_format(dst, target=mesh_target))
    show = _stderr_is_terminal() and not quiet

    def run(target):
        if not show:
            return _run(src, target, options, jobs=jobs)
        with _stage_bar(len(STAGES), f"fitting {src}") as bar:
            return _run(src, target, options, on_stage=lambda name: bar.update(1, name), jobs=jobs,
                        on_tile=lambda name, done, tiles: _caption(bar, f"{name}: tile {done} of {tiles}"))
    try:
        with Outputs() as outputs:
            if raster:      # c1mesh.raster writes the GeoTIFFs, each atomically
                result = run(dst)
            else:
                with outputs.open(mesh_target) as mesh_file:
                    result = run(mesh_file)
                _write_prj(outputs, dst, mesh_target, options.output_format, result)
            result["output"] = dst
            if report_target is not None:
                with outputs.open(report_target, "w") as handle:
                    handle.write(json.dumps(result, indent=2) + "\n")
            outputs.commit()
    except Exception as exc:  # noqa: BLE001 — any failure is one line
        _fail(_message(exc), debug)
    if report == STDIO:
        click.echo(json.dumps(result, indent=2), err=True)
    _warn(result, quiet)
    if verbose and not quiet:
        click.echo(_summary(result), err=True)


def _write_prj(outputs, dst, mesh_target, fmt, result) -> None:
    """The .prj sidecar (ESRI WKT) of a mesh file written in the same transaction as the mesh,
    when a CRS was carried (c1mesh.crs; not for stdout or devices)."""
    from c1mesh.crs import esri_wkt, prj_path
    from c1mesh.formats import PRJ_SIDECAR

    crs = (result.get("crs") or {}).get("wkt")
    if not crs or fmt not in PRJ_SIDECAR or mesh_target.kind != "atomic":
        return
    (target,) = plan_outputs([("CRS sidecar", prj_path(dst))])
    with outputs.open(target, "w") as handle:
        handle.write(esri_wkt(crs) + "\n")


def _summary(report: dict) -> str:
    pts, mesh = report["points"], report.get("output_mesh")
    total = sum(report["seconds"].values())
    made = (f"{mesh['vertices']} vertices, {mesh['faces']} faces" if mesh else
            f"{report['raster']['cells_with_data']} of {report['raster']['cells']} raster cells")
    line = f"{report['input']}: {pts['kept']} of {pts['read']} points -> {made} in {total:.2f} s"
    frame = report.get("frame", {})
    if "axis_choice" in frame:
        e3 = ", ".join(f"{c:.3g}" for c in frame["axes"][2])
        line += f"; height axis ({e3}), {frame['axis_choice']}"
    if "overshoot" in report:
        over = report["overshoot"]
        line += (f"; heights reconciled at {over['heights_reconciled']}, "
                 f"gradients limited at {over['gradients_limited']} vertices")
    return line


def _warn(report: dict, quiet: bool) -> None:
    """The report's warnings on stderr, one line each (not with -q)."""
    if quiet:
        return
    name = report.get("input", report.get("inputs"))
    name = ", ".join(map(str, name)) if isinstance(name, (list, tuple)) else name
    for text in report.get("warnings", []):
        click.echo(f"c1mesh: warning: {name}: {text}", err=True)


def _write_report(report, target, payload, debug) -> None:
    """The batch's JSON report to its checked target (or stderr for -)."""
    if not report:
        return
    text = json.dumps(payload, indent=2)
    if report == STDIO:
        click.echo(text, err=True)
        return
    try:
        with Outputs() as outputs:
            with outputs.open(target, "w") as handle:
                handle.write(text + "\n")
            outputs.commit()
    except (C1MeshError, OSError) as exc:
        _fail(f"cannot write report '{report}': {_message(exc)}", debug)


def _batch_worker(args):
    src, dst, options = args
    try:
        return src, _run(src, dst, options), None
    except Exception as exc:  # noqa: BLE001 — reported per file, the batch goes on
        return src, None, _message(exc)


def _fit_batch(pairs, report_target, options, report, jobs, quiet, verbose, debug) -> None:
    work = [(src, dst, options) for src, dst in pairs]
    results = []
    show = _stderr_is_terminal() and not quiet
    if jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=jobs, initializer=_worker_start) as pool:
            iterator = pool.map(_batch_worker, work)
            results = _collect(iterator, len(work), show, verbose and not quiet)
    else:
        results = _collect(map(_batch_worker, work), len(work), show, verbose and not quiet)
    for _, rep, _ in results:
        if rep:
            _warn(rep, quiet)
    failures = [(src, err) for src, _, err in results if err]
    _write_report(report, report_target,
                  {"inputs": [{"input": src, "report": rep, "error": err} for src, rep, err in results]}, debug)
    if failures:
        for src, err in failures:
            click.echo(f"c1mesh: failed: {src}: {err}", err=True)
        click.echo(f"c1mesh: {len(failures)} of {len(results)} inputs failed", err=True)
        sys.exit(EXIT_PARTIAL)


def _collect(iterator, total, show, verbose):
    results = []
    if show:
        with click.progressbar(iterator, length=total, label="fitting", file=sys.stderr) as bar:
            for item in bar:
                results.append(item)
    else:
        for item in iterator:
            results.append(item)
            if verbose and item[1]:
                click.echo(_summary(item[1]), err=True)
    return results


# ---------------------------------------------------------------------------------- info
@main.command()
@click.argument("path")
@click.option("--input-format", help="Input format; required for stdin (-).")
@click.option("--memory", callback=_parse_memory, help=_MEMORY_HELP)
@click.option("--intrinsics", help="Depth images: the camera's fx,fy,cx,cy in pixels.")
@click.option("--depth-scale", type=click.FloatRange(0, min_open=True), default=0.001, show_default=True,
              help="Depth images: metres per depth unit.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
def info(path, input_format, memory, intrinsics, depth_scale, debug):
    """Describe a point file: points, fields, normals, bounds, suggested axis, height field?"""
    from c1mesh.inspect import describe

    if path == "-" and not input_format:
        raise click.UsageError("reading stdin (-) needs --input-format")
    try:
        if path == STDIO:
            _check_stdin()
        _check_stdout()
        facts = describe(sys.stdin.buffer if path == "-" else path, input_format, memory=memory,
                         intrinsics=_parse_intrinsics(intrinsics), depth_scale=depth_scale)
    except Exception as exc:  # noqa: BLE001
        _fail(_message(exc), debug)
    click.echo(json.dumps(facts, indent=2))


# ------------------------------------------------------------------------------- preview
@main.command()
@click.argument("path")
@click.option("-o", "--output", required=True, help="The PNG to write.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
def preview(path, output, debug):
    """Render PATH (a GeoTIFF DEM or a mesh with normals) as a shaded PNG."""
    from c1mesh.geo import check_preview_path
    from c1mesh.preview import render_file

    try:
        check_preview_path(output)
        render_file(path, output)
    except Exception as exc:  # noqa: BLE001
        _fail(_message(exc), debug)


# ------------------------------------------------------------------------------- schemes
@main.command()
def schemes():
    """List the shape-function tuples with their computed properties."""
    from c1mesh.properties import scheme_properties
    from c1mesh.schemes import DEFAULT_SCHEME, NAMED_TUPLES

    click.echo(f"{'name':<9} {'degree':>6}  {'constants':<9}  {'affine':<6}  description")
    for name, tup in NAMED_TUPLES.items():
        p = scheme_properties(tup)
        description = tup.description.replace(" (default)", "")   # the mark is added here, once
        mark = " (default)" if name == DEFAULT_SCHEME else ""
        click.echo(f"{name:<9} {p.degree:>6}  {'yes' if p.reproduces_constants else 'no':<9}  "
                   f"{'yes' if p.reproduces_affine else 'no':<6}  {description}{mark}")


if __name__ == "__main__":  # pragma: no cover
    main()
