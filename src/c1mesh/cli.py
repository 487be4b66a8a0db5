"""The `c1mesh` command: a thin click layer over the library.

Exit codes (cli/README.md): 0 success, 1 failure, 2 usage error, 3 batch where some
inputs failed, 128+N killed by signal N (SIGINT 130, SIGTERM 143, SIGHUP 129). Errors
are one line on stderr; --debug shows the traceback. A usage error is everything the
command line shows on its own (values, conflicting options, output extensions): all of
its problems are named in that one line, before any input is read (`usage_error`). Progress goes to stderr only when
stderr is a terminal. Every output path is checked (c1mesh.core.outputs) before any input is
read. Nothing heavy (numpy, scipy, open3d) is imported until a command runs, so --help
and usage errors are quick.
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import os
import signal
import sys
import traceback
import warnings
from pathlib import Path
from typing import Sequence

import click

from c1mesh import __version__
from c1mesh.core.errors import C1MeshError, InputError
from c1mesh.core.outputs import (DEM_AXES, INPUT_FORMATS, LAS_FORMATS, MESH_FORMATS, OUTPUT_FORMATS,
                                 RASTER_FORMATS, STDIO, Outputs, mesh_format, plan_outputs, remove_live_temps)

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_PARTIAL = 0, 1, 2, 3
_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


def _fail(message: str, debug: bool = False) -> None:
    """One line on stderr (plus the traceback under --debug), then exit 1."""
    if debug:
        traceback.print_exc()
    click.echo(f"c1mesh: error: {message}", err=True)
    sys.exit(EXIT_FAILURE)


def _naming(src: str, text: str) -> str:
    """`text` led by the input it is about, unless it names it already (readers do; the
    fit's own errors, such as "not a height field", do not)."""
    name = "<stdin>" if src == STDIO else str(src)
    return text if name in text else f"{name}: {text}"


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


def _extensions(formats) -> str:
    """Formats as the extensions a user types: '.ply .obj'."""
    return " ".join(f".{fmt}" for fmt in formats)


_OUTPUT_HELP = (f"Output: a mesh ({_extensions(MESH_FORMATS)}) or a GeoTIFF DEM ({_extensions(RASTER_FORMATS)}, "
                "with --resolution), or - for binary PLY on stdout.")
_INPUT_FORMAT_HELP = (f"Input format ({', '.join(INPUT_FORMATS)}) [default: the file's extension]; "
                      "required for stdin (-).")
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
    normalised, by c1mesh.stages.frame)."""
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


def _extension(path: str) -> str:
    """The lower-case extension of an output path without its dot ('' for none); stdout is PLY."""
    return "ply" if path == STDIO else Path(path).suffix.lower().lstrip(".")


def _output_paths(params: dict) -> list[str]:
    """The mesh or DEM outputs a fit command line names: -o, or each input's path under -O."""
    if params["output_dir"]:
        return [str(Path(params["output_dir"]) / (("stdin" if src == STDIO else Path(src).stem) + params["suffix"]))
                for src in params["inputs"]]
    return [params["output"]] if params["output"] else []


def _input_format_problems(input_format: str | None) -> list[str]:
    if input_format and input_format.lower().lstrip(".") not in INPUT_FORMATS:
        return [f"Unsupported input format '{input_format}' for --input-format; supported: "
                f"{', '.join(INPUT_FORMATS)}"]
    return []


def _value_problems(params: dict) -> list[str]:
    """Option values that are wrong whatever the inputs and the other options."""
    problems = _input_format_problems(params["input_format"])
    for hint, parse, value in (("--classes", _parse_classes, params["classes"]),
                               ("--max-edge", _parse_max_edge, params["max_edge"]),
                               ("--intrinsics", _parse_intrinsics, params["intrinsics"]),
                               ("--axis", _check_axis, params["axis"])):
        try:
            parse(value)
        except click.BadParameter as exc:
            exc.param_hint = exc.param_hint or f"'{hint}'"
            problems.append(exc.format_message())
    resolution = params["resolution"]
    if resolution is not None and not (resolution > 0 and math.isfinite(resolution)):
        problems.append(f"--resolution must be a positive finite length, got {resolution}")
    z_factor = params["z_factor"]
    if z_factor is not None and not (z_factor > 0 and math.isfinite(z_factor)):
        problems.append(f"--z-factor must be a positive finite number (x, y units per height unit), got {z_factor}")
    return problems


def _io_problems(params: dict, outputs: list[str]) -> list[str]:
    """Inputs and outputs that do not fit together: stdin, -o against -O, clashing -O names."""
    inputs, output, output_dir, seamless = (params[k] for k in ("inputs", "output", "output_dir", "seamless"))
    problems = []
    if STDIO in inputs:
        if seamless:
            problems.append("--seamless reads files, not stdin (-)")
        elif len(inputs) > 1:
            problems.append("stdin (-) can only be the single input")
        elif not params["input_format"]:
            problems.append("reading stdin (-) needs --input-format")
    if output and output_dir:
        problems.append("use either -o/--output or -O/--output-dir")
    elif not output and not output_dir:
        problems.append("give -o OUTPUT (one mesh of the survey) or -O DIR (one mesh per input)" if seamless
                        else "give -o OUTPUT (or -O DIR for several inputs)")
    elif output and len(inputs) > 1 and not seamless:
        problems.append("several inputs need -O/--output-dir, not -o (or --seamless -o for one mesh of all)")
    clash = sorted({dst for dst in outputs if outputs.count(dst) > 1})
    if clash:
        problems.append(f"several inputs would write the same output {clash[0]}; rename them or run them "
                        "separately")
    return problems


def _format_problems(params: dict, outputs: list[str]) -> list[str]:
    """Output extensions c1mesh does not write, and options the formats cannot take."""
    problems = [f"Unsupported output format '{_extension(dst)}' for '{dst}'; supported: {', '.join(OUTPUT_FORMATS)}"
                for dst in outputs if _extension(dst) and _extension(dst) not in OUTPUT_FORMATS]
    if params["ascii_ply"]:
        others = sorted({_extension(dst) for dst in outputs} - {"ply", ""})
        if others:
            problems.append(f"--ascii applies to PLY output only, not .{others[0]}")
    if params["classes"]:
        kinds = {(params["input_format"] or Path(src).suffix).lower().lstrip(".") for src in params["inputs"]
                 if src != STDIO or params["input_format"]}
        others = sorted(kinds - set(LAS_FORMATS))
        if others:
            problems.append("--classes needs LAS/LAZ input (a classification field), not "
                            f".{others[0] or '(no extension)'}")
    return problems


def _raster_problems(params: dict, outputs: list[str], level_given: bool) -> list[str]:
    """GeoTIFF and preview options against the outputs, --resolution, --level and --axis."""
    dems = [dst for dst in outputs if _extension(dst) in RASTER_FORMATS]
    extras = {kind: params[kind] for kind in ("slope", "aspect", "hillshade") if params[kind]}
    resolution, preview = params["resolution"], params["preview"]
    if params["seamless"] and params["output_dir"] and (resolution is not None or extras or preview):
        return ["--resolution, --slope, --aspect, --hillshade and --preview make one survey-wide output: "
                "use them with --seamless -o, not -O"]
    if len(params["inputs"]) > 1 and not params["seamless"] and (extras or preview):
        return ["--slope, --aspect, --hillshade and --preview name one file: use them with a single input"]
    problems = []
    if resolution is not None and level_given:
        problems.append("give either --level or --resolution, not both")
    if (dems or extras) and resolution is None:
        problems.append("GeoTIFF outputs (-o *.tif, --slope, --aspect, --hillshade) need --resolution")
    if extras and not dems:
        problems.append("--slope, --aspect and --hillshade come with a DEM: give -o DEM.tif")
    problems += [f"the {kind} raster '{path}' must be a GeoTIFF (.tif or .tiff)"
                 for kind, path in extras.items() if _extension(path) not in RASTER_FORMATS]
    if preview and Path(preview).suffix.lower() != ".png":
        problems.append(f"the preview '{preview}' must be a .png file")
    if params["frame_kind"] == "perspective" and (dems or extras):   # geo loads numpy: only here
        from c1mesh.geo.products import dem_frame_error
        problems.append(dem_frame_error("perspective", dems, *(params[k] for k in ("slope", "aspect", "hillshade"))))
    if (dems or extras) and params["axis"].strip().lower() not in DEM_AXES:
        problems.append(f"a DEM is heights over the world XY plane; --axis {params['axis']} cannot be used "
                        "with GeoTIFF outputs (use --axis z or auto)")
    return problems


def _fit_usage_problems(ctx: click.Context) -> list[str]:
    """Everything wrong with a `fit` command line that the command line alone shows, all
    at once, so that one run names the whole fix (exit 2). Reads no input; the file system
    (missing directories, outputs equal to inputs) is checked later (exit 1)."""
    from click.core import ParameterSource

    params = ctx.params
    outputs = _output_paths(params)
    level_given = ctx.get_parameter_source("level") != ParameterSource.DEFAULT
    return (_value_problems(params) + _io_problems(params, outputs) + _format_problems(params, outputs)
            + _raster_problems(params, outputs, level_given))


def _info_usage_problems(ctx: click.Context) -> list[str]:
    """What is wrong with an `info` command line on its own (exit 2)."""
    problems = _input_format_problems(ctx.params["input_format"])
    if ctx.params["path"] == STDIO and not ctx.params["input_format"]:
        problems.append("reading stdin (-) needs --input-format")
    return problems


def _preview_usage_problems(ctx: click.Context) -> list[str]:
    """What is wrong with a `preview` command line on its own (exit 2)."""
    output = ctx.params["output"]
    return [] if Path(output).suffix.lower() == ".png" else [f"the preview '{output}' must be a .png file"]


_USAGE_CHECKS = {"fit": _fit_usage_problems, "info": _info_usage_problems, "preview": _preview_usage_problems}
"""Per command: every problem its command line shows on its own, checked before any work."""


def _check_usage(ctx: click.Context) -> None:
    """Raise one UsageError naming every problem of the command line (exit 2)."""
    problems = _USAGE_CHECKS[ctx.command.name](ctx)
    if problems:
        raise click.UsageError("; ".join(problems), ctx=ctx)


def usage_error(argv: Sequence[str]) -> str | None:
    """The one line `c1mesh ARGV...` prints for a usage error (it then exits 2), or None
    when the command line is well formed. Only parses and checks the arguments: reads no
    input, writes nothing (the text of a --help or --version in argv is discarded)."""
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            with main.make_context("c1mesh", list(argv)) as ctx:
                name, command, rest = main.resolve_command(ctx, [*ctx._protected_args, *ctx.args])
                with command.make_context(name, rest, parent=ctx) as sub:
                    if name in _USAGE_CHECKS:
                        _check_usage(sub)
    except click.exceptions.Exit:
        return None
    except click.exceptions.NoArgsIsHelpError:     # bare `c1mesh` prints the help and exits 2
        return f"c1mesh: error: give a command ({', '.join(main.commands)}); see 'c1mesh --help'"
    except click.UsageError as exc:
        return _usage_line(exc)
    return None


def _stderr_is_terminal() -> bool:
    try:
        return os.isatty(sys.stderr.fileno())
    except (AttributeError, OSError, ValueError):
        return False


def _usage_line(exc: click.UsageError) -> str:
    """A usage error as the one line cli/README.md promises: `c1mesh: error: ...`, with
    the command whose --help lists the options."""
    text = " ".join(exc.format_message().split()).rstrip(".")
    where = exc.ctx.command_path if exc.ctx is not None else "c1mesh"
    return f"c1mesh: error: {text}; see '{where} --help'"


class _Group(click.Group):
    """A click group whose usage errors are one line on stderr and exit 2, and whose
    unexpected failures are one line and exit 1."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        """click's main, except that a usage error prints one line instead of click's
        Usage/Try/Error block (a caller passing standalone_mode=False gets click's exceptions)."""
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.NoArgsIsHelpError as exc:    # bare `c1mesh`: the help, as click shows it
            exc.show()
            sys.exit(exc.exit_code)
        except click.UsageError as exc:
            click.echo(_usage_line(exc), err=True)
            sys.exit(EXIT_USAGE)
        except click.ClickException as exc:
            click.echo(f"c1mesh: error: {' '.join(exc.format_message().split())}", err=True)
            sys.exit(exc.exit_code)
        except click.exceptions.Abort:
            click.echo("c1mesh: error: aborted", err=True)
            sys.exit(EXIT_FAILURE)
        sys.exit(code if isinstance(code, int) else EXIT_OK)

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
@click.option("-o", "--output", help=_OUTPUT_HELP)
@click.option("-O", "--output-dir", type=click.Path(file_okay=False),
              help="Directory for outputs of several inputs (each named input stem + --suffix).")
@click.option("--suffix", default=".c1.ply", show_default=True,
              help="Output name suffix with -O; its extension picks the format, as for -o.")
@click.option("--input-format", help=_INPUT_FORMAT_HELP)
@click.option("--classes", help="Keep only these LAS classification codes, e.g. 2 or 2,9 (2 = ground).")
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
@click.option("--z-factor", "z_factor", type=float, default=None,
              help="x, y units per height unit (ArcGIS's z-factor, 1/gdaldem -s) for --slope, --hillshade, "
                   "the preview's shading and a height column's --max-slope.  [default: 1; required for "
                   "--slope/--hillshade of a CSV header height column, whose units may differ]")
@click.option("--slope-method", type=click.Choice(["auto", "spline", "horn"]), default="auto",
              show_default=True, help="Gradient for slope/aspect/hillshade: the spline's, or Horn's of the DEM.")
@click.option("--preview", help="Also render a PNG preview (hillshade coloured by height).")
@click.pass_context
def fit(ctx, inputs, output, output_dir, suffix, input_format, classes, normals, k, axis, max_slope,
        max_edge, scheme, level, ascii_ply, frame_kind, viewpoint, intrinsics, depth_scale, color_image,
        overshoot, gradients, report, memory, jobs, quiet, verbose, debug,
        threads, crs, resolution, slope, aspect, hillshade, z_factor, slope_method, preview, seamless,
        scheduler, bounds):
    """Fit a refined C1 surface mesh to each INPUT scan (- reads stdin)."""
    _check_usage(ctx)       # every usage error at once, before any input is read
    classes, max_edge = _parse_classes(classes), _parse_max_edge(max_edge)
    intrinsics = _parse_intrinsics(intrinsics)
    if seamless:
        from c1mesh.pipeline.driver import FitOptions

        options = FitOptions(input_format=input_format, axis=axis, normals=normals, k=k, classes=classes,
                             max_slope=max_slope, max_edge=max_edge, scheme=scheme, level=level,
                             ascii=ascii_ply, memory=memory, crs=crs, overshoot=overshoot,
                             gradients=gradients, resolution=resolution, slope=slope, aspect=aspect,
                             hillshade=hillshade, slope_method=slope_method, preview=preview, bounds=bounds,
                             z_factor=z_factor)
        if output and not output_dir:
            options = _check_geo([(inputs[0], output)], options, debug)
        _fit_seamless(inputs, output, output_dir, suffix, input_format, options, report, jobs, threads,
                      scheduler, quiet, debug)
        return
    pairs = _plan(inputs, output, output_dir, suffix)
    if scheme == "quintic" and not quiet:
        click.echo("c1mesh: warning: the quintic scheme does not reproduce planes and its normals "
                   "do not converge; use sextic unless you need the 2022 procedure", err=True)
    try:
        targets = _check_outputs(pairs, report, output_dir)
    except (C1MeshError, OSError) as exc:
        _fail(_message(exc), debug)
    from c1mesh.pipeline.driver import FitOptions

    options = FitOptions(input_format=input_format, axis=axis, normals=normals, k=k, classes=classes,
                         max_slope=max_slope, max_edge=max_edge, scheme=scheme, level=level, ascii=ascii_ply,
                         memory=memory, crs=crs, resolution=resolution, slope=slope, aspect=aspect,
                         hillshade=hillshade, slope_method=slope_method, preview=preview,
                         overshoot=overshoot, gradients=gradients, frame=frame_kind, viewpoint=viewpoint,
                         intrinsics=intrinsics, z_factor=z_factor,
                         depth_scale=depth_scale, color=color_image, bounds=bounds)
    options = _check_geo(pairs, options, debug)
    options.workers = _threads_per_process(threads, min(jobs, len(pairs)))
    if len(pairs) == 1:
        _fit_one(*pairs[0], targets, options, report, quiet, verbose, debug, jobs, scheduler)
        return
    _fit_batch(pairs, targets[-1], options, report, jobs, quiet, verbose, debug, scheduler)


def _threads_per_process(threads: int | None, jobs: int) -> int:
    """--threads shared by the --jobs processes, so together they do not oversubscribe
    (Open3D's OpenMP threads included)."""
    from c1mesh.core.threads import openmp_at_start, per_process
    count = per_process(threads, jobs)
    openmp_at_start(count)
    return count


def _plan(inputs, output, output_dir, suffix) -> list[tuple[str, str]]:
    """(input, output) pairs of a command line that passed _check_usage."""
    params = {"inputs": inputs, "output": output, "output_dir": output_dir, "suffix": suffix}
    return list(zip(inputs, _output_paths(params)))


def _fit_seamless(inputs, output, output_dir, suffix, input_format, options, report, jobs, threads,
                  scheduler, quiet, debug) -> None:
    """`fit --seamless`: the inputs as one survey (c1mesh.survey.tiles), one line on any failure."""
    pairs = _plan(inputs, None, output_dir, suffix) if output_dir else [(inputs[0], output)]
    try:
        if options.crs:
            from dataclasses import replace

            from c1mesh.core.crs import parse_crs
            options = replace(options, crs=parse_crs(options.crs))
        if output_dir and not Path(output_dir).exists():
            Path(output_dir).mkdir(parents=True)
        named = [("output", dst) for _, dst in pairs] + [("report", None if report in (None, STDIO) else report)]
        targets = plan_outputs(named, list(inputs))
        from c1mesh.geo.raster import is_raster_path
        for (_, dst), target in zip(pairs, targets):
            if not is_raster_path(dst):
                mesh_format(dst, target=target)
    except (C1MeshError, OSError) as exc:
        _fail(_message(exc), debug)
    from c1mesh.pipeline.survey_fit import fit_seamless
    from c1mesh.survey.tiled_fit import survey_needs_tiles

    options.workers = _threads_per_process(threads, 1)
    mesh = sys.stdout.buffer if output == STDIO else output
    outputs = [d for _, d in pairs] if output_dir else None
    unused = None
    if scheduler is not None and not output_dir and not survey_needs_tiles(list(inputs), options):
        scheduler, unused = None, _SCHEDULER_UNUSED.format(what="the survey")   # one fit, in this process
    try:
        if _stderr_is_terminal() and not quiet:
            progress, callbacks = _survey_progress(list(inputs), options, len(pairs) if output_dir else 0)
            with progress:
                result = fit_seamless(inputs, options, mesh, outputs, scheduler, jobs, **callbacks)
        else:
            result = fit_seamless(inputs, options, mesh, outputs, scheduler, jobs)
    except Exception as exc:  # noqa: BLE001 — a failed tile names itself; no output is left
        _fail(_message(exc), debug)
    if unused:
        result["scheduler"] = unused
    _warn(result, quiet)
    _write_report(report, targets[-1], result, debug)
    _note(result, quiet)


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
    it: for a survey fitted in tiles beyond --memory (c1mesh.survey.tiled_fit), its stages with
    each pass's tile count, as a single large input shows them; in memory, the outputs
    of -O as their tiles are written, or the stages of the one -o fit."""
    from c1mesh.pipeline.driver import STAGES
    from c1mesh.survey.tiled_fit import TILED_STAGES
    from c1mesh.survey.tiled_fit import survey_needs_tiles

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


def _check_geo(jobs_list, options, debug):
    """Georeferencing options checked before any input is read (c1mesh.geo.products.check_before;
    their conflicts are usage errors, found by _check_usage): a bad CRS or an unwritable
    path exit 1. Returns the options with the CRS parsed to WKT."""
    from c1mesh.geo.products import check_before

    extra = [(label, path) for label, path in (("slope raster", options.slope),
                                               ("aspect raster", options.aspect),
                                               ("hillshade raster", options.hillshade),
                                               ("preview", options.preview)) if path]
    try:
        if extra:   # against the inputs, the outputs and each other (c1mesh.core.outputs)
            plan_outputs([("output", dst) for _, dst in jobs_list] + extra, [src for src, _ in jobs_list])
        return check_before([dst for _, dst in jobs_list], options)
    except C1MeshError as exc:
        _fail(_message(exc), debug)


def _check_outputs(pairs, report, output_dir):
    """All output targets (the meshes, then the report or None), checked against the inputs
    and each other before any input is read (c1mesh.core.outputs); raises C1MeshError/OSError."""
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
    from c1mesh.geo.raster import is_raster_path
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


_SCHEDULER_UNUSED = ("not used: {what} fits in --memory, so it was fitted in one piece in this process "
                     "(the scheduler runs the tiles of a larger fit, or of --seamless -O)")
"""The report's `scheduler` when a --scheduler had no tiles to run; also the note on stderr."""


def _run(src: str, target, options, on_stage=None, jobs: int = 1, on_tile=None, scheduler=None) -> dict:
    """Fit one input to one output (a path, or a file object then with options.output_format);
    an input fitted in tiles runs them on the Dask `scheduler` if given, else on `jobs` local
    processes. An input that fits in memory is fitted here, and a scheduler given for it is
    recorded in the report as not used (the note `_note` prints)."""
    from c1mesh.pipeline.driver import fit as fit_pipeline
    from c1mesh.pipeline.survey_fit import fit_in_tiles
    from c1mesh.survey.tiled_fit import needs_tiles

    source = sys.stdin.buffer if src == STDIO else src
    if needs_tiles(source, options):          # larger than --memory allows: c1mesh.survey.tiled_fit
        return fit_in_tiles(source, target, options, on_stage=on_stage, jobs=jobs, on_tile=on_tile,
                            scheduler=scheduler)
    report = fit_pipeline(source, target, options, on_stage=on_stage, keep_mesh=False).report
    if scheduler is not None:
        report["scheduler"] = _SCHEDULER_UNUSED.format(what="the input")
    return report


def _fit_one(src, dst, targets, options, report, quiet, verbose, debug, jobs: int = 1,
             scheduler: str | None = None) -> None:
    """Fit one input; the mesh and the report are committed together, or neither is."""
    from dataclasses import replace

    from c1mesh.pipeline.driver import STAGES

    from c1mesh.geo.raster import is_raster_path

    mesh_target, report_target = targets
    raster = is_raster_path(dst)
    options = replace(options, output_format=None if raster else mesh_format(dst, target=mesh_target))
    show = _stderr_is_terminal() and not quiet

    def run(target):
        if not show:
            return _run(src, target, options, jobs=jobs, scheduler=scheduler)
        with _stage_bar(len(STAGES), f"fitting {src}") as bar:
            return _run(src, target, options, on_stage=lambda name: bar.update(1, name), jobs=jobs,
                        on_tile=lambda name, done, tiles: _caption(bar, f"{name}: tile {done} of {tiles}"),
                        scheduler=scheduler)
    try:
        with Outputs() as outputs:
            if raster:      # c1mesh.geo.raster writes the GeoTIFFs, each atomically
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
        _fail(_naming(src, _message(exc)), debug)
    if report == STDIO:
        click.echo(json.dumps(result, indent=2), err=True)
    _note(result, quiet)
    _warn(result, quiet)
    if verbose and not quiet:
        click.echo(_summary(result), err=True)


def _write_prj(outputs, dst, mesh_target, fmt, result) -> None:
    """The .prj sidecar (ESRI WKT) of a mesh file written in the same transaction as the mesh,
    when a CRS was carried (c1mesh.core.crs; not for stdout or devices)."""
    from c1mesh.core.crs import esri_wkt, prj_path
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


def _note(report: dict, quiet: bool) -> None:
    """`c1mesh: note:` lines on stderr (not with -q) for options given that did nothing: a
    --scheduler not used (the user asked for the cluster and should know the work stayed
    here), and a --max-slope given for heights whose slopes are no angles (the report's
    max_slope_not_applied; its default then goes unmentioned)."""
    if quiet:
        return
    used = report.get("scheduler")
    if isinstance(used, str) and used.startswith("not used"):
        click.echo(f"c1mesh: note: {_input_name(report)}: --scheduler {used}", err=True)
    why = report.get("max_slope_not_applied")
    if why and _option_given("max_slope"):
        click.echo(f"c1mesh: note: {_input_name(report)}: --max-slope was not applied: {why}", err=True)


def _option_given(name: str) -> bool:
    """Whether option `name` of the running command was given on its command line."""
    from click.core import ParameterSource

    ctx = click.get_current_context(silent=True)
    return ctx is not None and ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT)


def _input_name(report: dict) -> str:
    """The input(s) a report is about, for a message: one name, or the first and a count."""
    names = report.get("input")
    if isinstance(names, (list, tuple)):
        return names[0] if len(names) == 1 else f"{names[0]} and {len(names) - 1} more"
    return str(names)


def _warn(report: dict, quiet: bool) -> None:
    """The report's warnings on stderr, one line each (not with -q)."""
    if quiet:
        return
    name = report.get("input")
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
    src, dst, options, scheduler = args
    try:
        return src, _run(src, dst, options, scheduler=scheduler), None
    except Exception as exc:  # noqa: BLE001 — reported per file, the batch goes on
        return src, None, _message(exc)


def _fit_batch(pairs, report_target, options, report, jobs, quiet, verbose, debug, scheduler=None) -> None:
    work = [(src, dst, options, scheduler) for src, dst in pairs]
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
            _note(rep, quiet)
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
@click.option("--input-format", help=_INPUT_FORMAT_HELP)
@click.option("--memory", callback=_parse_memory, help=_MEMORY_HELP)
@click.option("--intrinsics", help="Depth images: the camera's fx,fy,cx,cy in pixels.")
@click.option("--depth-scale", type=click.FloatRange(0, min_open=True), default=0.001, show_default=True,
              help="Depth images: metres per depth unit.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
def info(path, input_format, memory, intrinsics, depth_scale, debug):
    """Describe a point file: points, fields, normals, bounds, suggested axis, height field?"""
    from c1mesh.pipeline.inspect import describe

    _check_usage(click.get_current_context())
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
    from c1mesh.geo.products import check_preview_path
    from c1mesh.geo.preview import render_file

    _check_usage(click.get_current_context())
    try:
        check_preview_path(output)
        render_file(path, output)
    except Exception as exc:  # noqa: BLE001
        _fail(_message(exc), debug)


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


def run() -> None:
    """The c1mesh-python console script, which the `c1mesh` launcher (bin/c1mesh) runs: named
    c1mesh in usage lines and shell completion (_C1MESH_COMPLETE) whatever its file name."""
    main(prog_name="c1mesh")


if __name__ == "__main__":  # pragma: no cover
    main()
