"""Usage errors (exit 2): everything wrong with a command line that the command line
alone shows, all named in one line before any input is read (cli/README.md, Exit codes);
also a binary `-o -` while standard output is a terminal. The file system (missing
directories, outputs equal to inputs) is checked later, by c1mesh.cli.outputs_check (exit 1).
"""
from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import click
from click.core import ParameterSource

from c1mesh.cli.options import (
    check_axis,
    extension,
    output_paths,
    parse_classes,
    parse_fill,
    parse_spacing,
    parse_intrinsics,
    parse_max_edge,
    parse_smooth,
    parse_viewpoint_option,
)
from c1mesh.core.outputs import (
    DEM_AXES,
    INPUT_FORMATS,
    LAS_FORMATS,
    OUTPUT_FORMATS,
    RASTER_FORMATS,
    STDIO,
    contour_path_problem,
    is_binary_output,
    is_file_output,
)


def input_format_problems(input_format: str | None) -> list[str]:
    """The problem with an --input-format c1mesh does not read ([] when none or known)."""
    if input_format and input_format.lower().lstrip(".") not in INPUT_FORMATS:
        return [f"Unsupported input format '{input_format}' for --input-format; supported: "
                f"{', '.join(INPUT_FORMATS)}"]
    return []


def _value_problems(params: dict) -> list[str]:
    """Option values that are wrong whatever the inputs and the other options."""
    problems = input_format_problems(params["input_format"])
    for hint, parse, value in (("--classes", parse_classes, params["classes"]),
                               ("--max-edge", parse_max_edge, params["max_edge"]),
                               ("--intrinsics", parse_intrinsics, params["intrinsics"]),
                               ("--viewpoint", parse_viewpoint_option, params["viewpoint"]),
                               ("--axis", check_axis, params["axis"]),
                               ("--smooth", parse_smooth, params["smooth"]),
                               ("--fill", parse_fill, params["fill"]),
                               ("--spacing", parse_spacing, params["spacing"])):
        try:
            parse(value)
        except click.BadParameter as exc:
            exc.param_hint = exc.param_hint or f"'{hint}'"
            problems.append(exc.format_message())
    resolution = params["resolution"]
    if resolution is not None and not (resolution > 0 and math.isfinite(resolution)):
        problems.append(f"--resolution must be a positive finite length, got {resolution}")
    problems += _smoothing_problems(params)
    z_factor = params["z_factor"]
    if z_factor is not None and not (z_factor > 0 and math.isfinite(z_factor)):
        problems.append(f"--z-factor must be a positive finite number (x, y units per height unit), got {z_factor}")
    return problems


def _smoothing_problems(params: dict) -> list[str]:
    """--smooth and --spacing against each other and the frame."""
    try:
        strength = parse_smooth(params["smooth"])
    except click.BadParameter:
        return []                                      # named by _value_problems
    if params["spacing"] is not None and strength is None:
        return ["--spacing thins the vertices of a smoothing fit: give --smooth auto or a strength"]
    if params["spacing"] is not None and params["frame_kind"] == "perspective":
        return ["--spacing thins a height field's vertices (--frame axis or auto); the perspective frame's "
                "smoothing fit keeps every point as a vertex"]
    return []


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
    return problems + _terminal_problems(params)


def _terminal_problems(params: dict) -> list[str]:
    """A binary mesh for stdout (-o -) while stdout is a terminal: refused, as gzip and zstd
    do, since it would only garble the screen; a text format (--ascii PLY) may go there."""
    binary = is_binary_output(extension(STDIO), params["ascii_ply"])
    if params["output"] != STDIO or not binary or not _stdout_is_terminal():
        return []
    return ["refusing to write binary output to a terminal; redirect it or use -o FILE"]


def _stdout_is_terminal() -> bool:
    """Whether standard output is a terminal (False when it is closed: checked later, exit 1)."""
    try:
        return os.isatty(sys.stdout.fileno())
    except (AttributeError, OSError, ValueError):
        return False


def _format_problems(params: dict, outputs: list[str]) -> list[str]:
    """Output extensions c1mesh does not write, and options the formats cannot take."""
    where = f"--suffix '{params['suffix']}'" if params["output_dir"] else None   # -O: one line, not one per input
    problems = list(dict.fromkeys(problem for dst in outputs if (problem := _extension_problem(dst, where))))
    if params["ascii_ply"]:
        others = sorted({extension(dst) for dst in outputs} - {"ply", ""})
        if others:
            problems.append(f"--ascii applies to PLY output only, not .{others[0]}")
    if _classes_choice(params["classes"]) != "auto":
        kinds = {(params["input_format"] or Path(src).suffix).lower().lstrip(".") for src in params["inputs"]
                 if src != STDIO or params["input_format"]}
        others = sorted(kinds - set(LAS_FORMATS))
        if others:
            problems.append("--classes needs LAS/LAZ input (a classification field), not "
                            f".{others[0] or '(no extension)'}")
    return problems


def _classes_choice(value):
    """parse_classes(value), or "auto" for a bad value (named by _value_problems)."""
    try:
        return parse_classes(value)
    except click.BadParameter:
        return "auto"


def _extension_problem(dst: str, where: str | None = None) -> str | None:
    """Why the output `dst` names no format c1mesh writes, or None: an unknown extension, or
    none on a file (a device, FIFO or /dev/stdout without one gets binary PLY; a directory is
    refused later, by name). `where` names the culprit instead of the path (-O's --suffix).
    The list is the registry's, meshes and GeoTIFF DEMs (c1mesh.core.outputs.OUTPUT_FORMATS)."""
    ext = extension(dst)
    if ext in OUTPUT_FORMATS or (not ext and not is_file_output(dst)):
        return None
    what = f"Unsupported output format '{ext}'" if ext else "No output format (no extension)"
    where = where or f"'{dst}'"
    return f"{what} for {where}; supported: {', '.join(OUTPUT_FORMATS)}"


SIDE_RASTERS = ("slope", "aspect", "hillshade", "support")
"""The GeoTIFFs on the DEM's grid that come with -o DEM.tif."""


def _tile_raster_problems(params: dict, dems: list[str], extras: dict) -> list[str]:
    """--seamless -O's rasters: per-tile DEMs (--suffix .tif) need --resolution; each side
    raster option names its mosaic (.vrt), the tiles' files being DIR/NAME.KIND.tif; no preview."""
    problems = []
    if params["preview"]:
        problems.append("--preview draws one output: use it with --seamless -o, not -O")
    if params["resolution"] is not None and not dems:
        problems.append("--resolution with --seamless -O is the cell size of per-tile DEMs: give --suffix .tif "
                        "(meshes per tile take --level)")
    if dems and params["resolution"] is None:
        problems.append("GeoTIFF outputs (-o *.tif, --slope, --aspect, --hillshade, --support) need --resolution")
    if extras and not dems:
        problems.append("--slope, --aspect, --hillshade and --support come with a DEM: use --seamless -o DEM.tif, "
                        "or -O DIR --suffix .tif --resolution R for per-tile DEMs")
        return problems
    problems += [f"with -O, --{kind} names the mosaic of the tiles' {kind} rasters: give a .vrt path, not "
                 f"'{path}'" for kind, path in extras.items() if extension(path) != "vrt"]
    return problems


def _raster_problems(params: dict, outputs: list[str], level_given: bool) -> list[str]:
    """GeoTIFF and preview options against the outputs, --resolution, --level and --axis."""
    dems = [dst for dst in outputs if extension(dst) in RASTER_FORMATS]
    extras = {kind: params[kind] for kind in SIDE_RASTERS if params[kind]}
    resolution, preview = params["resolution"], params["preview"]
    if params["seamless"] and params["output_dir"]:
        tile_problems = _tile_raster_problems(params, dems, extras)
        if tile_problems:
            return tile_problems
        extras = {}                          # mosaics (.vrt), checked there; the DEMs are checked below
    if len(params["inputs"]) > 1 and not params["seamless"] and (extras or preview):
        return ["--slope, --aspect, --hillshade, --support and --preview name one file: use them with a "
                "single input"]
    problems = []
    if resolution is not None and level_given:
        problems.append("give either --level or --resolution, not both")
    if (dems or extras) and resolution is None:
        problems.append("GeoTIFF outputs (-o *.tif, --slope, --aspect, --hillshade, --support) need --resolution")
    if extras and not dems:
        problems.append("--slope, --aspect, --hillshade and --support come with a DEM: give -o DEM.tif")
    problems += [f"the {kind} raster '{path}' must be a GeoTIFF (.tif or .tiff)"
                 for kind, path in extras.items() if extension(path) not in RASTER_FORMATS]
    if preview and Path(preview).suffix.lower() != ".png":
        problems.append(f"the preview '{preview}' must be a .png file")
    if params["frame_kind"] == "perspective" and (dems or extras):   # geo loads numpy: only here
        from c1mesh.geo.products import dem_frame_error
        problems.append(dem_frame_error("perspective", dems, *(params[k] for k in SIDE_RASTERS)))
    if (dems or extras) and params["axis"].strip().lower() not in DEM_AXES:
        problems.append(f"a DEM is heights over the world XY plane; --axis {params['axis']} cannot be used "
                        "with GeoTIFF outputs (use --axis z or auto)")
    return problems


def _contour_problems(params: dict) -> list[str]:
    """--contours and --interval against each other, the frame, the axis and the outputs."""
    path, interval = params["contours"], params["interval"]
    if path is None:
        return ["--interval is the height between contour lines: give --contours FILE"] if interval is not None else []
    problems = []
    if interval is None:
        problems.append("--contours needs --interval H, the height between two contour lines")
    elif not (interval > 0 and math.isfinite(interval)):
        problems.append(f"--interval must be a positive height, got {interval}")
    if contour_path_problem(path):
        problems.append(contour_path_problem(path))
    if params["seamless"] and params["output_dir"]:
        problems.append("--contours makes one survey-wide file: use it with --seamless -o, not -O")
    elif len(params["inputs"]) > 1 and not params["seamless"]:
        problems.append("--contours names one file: use it with a single input")
    if params["frame_kind"] == "perspective":     # geo loads numpy: only here
        from c1mesh.geo.products import CONTOUR_FRAME_ERROR
        problems.append(CONTOUR_FRAME_ERROR)
    if params["axis"].strip().lower() not in DEM_AXES:
        problems.append(f"contours are levels of height over the world XY plane; --axis {params['axis']} cannot "
                        "be used with --contours (use --axis z or auto)")
    return problems


def _fit_usage_problems(ctx: click.Context) -> list[str]:
    """Everything wrong with a `fit` command line that the command line alone shows, all
    at once, so that one run names the whole fix (exit 2). Reads no input; the file system
    (missing directories, outputs equal to inputs) is checked later (exit 1)."""
    params = ctx.params
    outputs = output_paths(params)
    level_given = ctx.get_parameter_source("level") != ParameterSource.DEFAULT
    return (_value_problems(params) + _io_problems(params, outputs) + _format_problems(params, outputs)
            + _raster_problems(params, outputs, level_given) + _contour_problems(params))


def _info_usage_problems(ctx: click.Context) -> list[str]:
    """What is wrong with an `info` command line on its own (exit 2)."""
    problems = input_format_problems(ctx.params["input_format"])
    if ctx.params["path"] == STDIO and not ctx.params["input_format"]:
        problems.append("reading stdin (-) needs --input-format")
    return problems


def _preview_usage_problems(ctx: click.Context) -> list[str]:
    """What is wrong with a `preview` command line on its own (exit 2)."""
    output = ctx.params["output"]
    return [] if Path(output).suffix.lower() == ".png" else [f"the preview '{output}' must be a .png file"]


def _ground_usage_problems(ctx: click.Context) -> list[str]:
    """What is wrong with a `ground` command line on its own (exit 2): LAS/LAZ in and out."""
    source, output = ctx.params["input_path"], ctx.params["output"]
    problems = []
    if Path(source).suffix.lower().lstrip(".") not in LAS_FORMATS:
        problems.append(f"ground classifies LAS/LAZ files, not '{source}'")
    if Path(output).suffix.lower() not in (".las", ".laz"):
        problems.append(f"the output '{output}' must be a .las or .laz file")
    return problems


USAGE_CHECKS = {"fit": _fit_usage_problems, "ground": _ground_usage_problems, "info": _info_usage_problems, "preview": _preview_usage_problems}
"""Per command: every problem its command line shows on its own, checked before any work."""


def check_usage(ctx: click.Context) -> None:
    """Raise one UsageError naming every problem of the command line (exit 2)."""
    problems = USAGE_CHECKS[ctx.command.name](ctx)
    if problems:
        raise click.UsageError("; ".join(problems), ctx=ctx)
