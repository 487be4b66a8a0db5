"""Parsing the `c1mesh` command's option values and naming its outputs, in plain Python
(no numpy), so that --help and usage errors stay quick. A bad value raises
click.BadParameter; c1mesh.cli.usage collects them into one usage error.
"""
from __future__ import annotations

import math
from pathlib import Path

import click

from c1mesh.core.errors import C1MeshError
from c1mesh.core.outputs import CONTOUR_FORMATS, INPUT_FORMATS, MESH_FORMATS, RASTER_FORMATS, STDIO

CLASSES_HELP = ("LAS/LAZ points to fit: auto (the ground class 2 when the file has any, else the ground "
                "the ground filter finds: docs/ground.md), all (every point, for a top surface), filter "
                "(the filter's ground even when the file has class 2), or codes such as 2 or 2,9.")


def parse_classes(value: str | None):
    """--classes: "auto" (the default, also for no value), "all", "filter", or a tuple of
    comma-separated LAS classification codes."""
    if not value or value.strip().lower() == "auto":
        return "auto"
    if value.strip().lower() in ("all", "filter"):
        return value.strip().lower()
    try:
        codes = tuple(int(v) for v in value.split(",") if v.strip())
    except ValueError:
        raise click.BadParameter(f"expected auto, all, filter or comma-separated codes such as 2,9, got {value!r}")
    if not codes or any(not 0 <= c <= 255 for c in codes):
        raise click.BadParameter(f"expected classification codes 0-255 such as 2,9, got {value!r}")
    return codes


def parse_memory_option(ctx, param, value):
    """--memory: a size such as 512M or 8G (None = the reader's default)."""
    if value is None:
        return None
    from c1mesh.formats._limits import parse_memory
    try:
        return parse_memory(value)
    except C1MeshError as exc:
        raise click.BadParameter(str(exc))


def parse_bounds_option(ctx, param, value):
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


OUTPUT_HELP = (f"Output: a mesh ({_extensions(MESH_FORMATS)}) or a GeoTIFF DEM ({_extensions(RASTER_FORMATS)}, "
                "with --resolution), or - for binary PLY on stdout.")


CONTOURS_HELP = (f"Also write contour lines ({_extensions(CONTOUR_FORMATS)}) every --interval of height, with "
                 "the CRS and a 'level' attribute: traced on the DEM's grid (a mesh: at its resolution), each "
                 "vertex moved onto the spline's level set; the fit's heights must be over the world XY plane.")


INPUT_FORMAT_HELP = (f"Input format ({', '.join(INPUT_FORMATS)}) [default: the file's extension]; "
                      "required for stdin (-).")


MEMORY_HELP = ("Most bytes of input to read and decode, e.g. 512M or 8G; larger or endless inputs "
                "are refused [default: half the RAM, at most 8G]. With fit, a LAS/LAZ file whose "
                "points need more (1.8 kB per point) is fitted in tiles (estimated normals, long-edge trim).")


def parse_max_edge(value: str):
    """--max-edge: 'auto', None for 'none', or a positive finite length in the scan's units."""
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


SMOOTH_HELP = ("off: the spline through every point; auto: fitted to the points, its strength "
               "chosen by cross-validation over spatial blocks; or a strength s > 0 (dimensionless: "
               "λ = s·h², h the mean point spacing; docs/smoothing.md). For noisy heights such as LiDAR ground.  "
               "[default: auto on the lattice (--spacing auto) where the normals are estimated over a height "
               "field: LAS/LAZ, XYZ or CSV without normals; auto, every pixel a vertex, in the perspective "
               "frame where the normals come from the pixel grid or are estimated; off where the file has "
               "normals]")


def parse_smooth(value: str):
    """--smooth: 'off' -> None, 'auto', 'default' (core.plan.DEFAULT_SMOOTH, resolved by
    the fit), or a positive finite strength (plain Python)."""
    word = value.strip().lower()
    if word == "default":
        return "default"
    if word in ("off", "auto"):
        return None if word == "off" else "auto"
    strength = _number(word)
    if not (strength > 0 and math.isfinite(strength)):
        raise click.BadParameter(f"expected off, auto or a positive strength, got {value!r}",
                                 param_hint="'--smooth'")
    return strength


def parse_spacing(value):
    """--spacing: 'auto' or a positive finite length (None: not given)."""
    if value is None:
        return None
    word = str(value).strip().lower()
    if word == "auto":
        return "auto"
    length = _number(word)
    if not (length > 0 and math.isfinite(length)):
        raise click.BadParameter(f"expected auto or a positive finite length, got {value!r}", param_hint="'--spacing'")
    return length


def parse_fill(value: str):
    """--fill: 'hull', 'off' (also 0) or a positive finite distance (plain Python; the
    library resolves it: c1mesh.geo.raster.fill_distance)."""
    word = str(value).strip().lower()
    if word in ("hull", "off"):
        return word
    distance = _number(word)
    if not (distance >= 0 and math.isfinite(distance)):
        raise click.BadParameter(f"expected hull, off or a distance >= 0, got {value!r}", param_hint="'--fill'")
    return "off" if distance == 0 else distance


def _number(word: str) -> float:
    """An option's word as a number, NaN when it is none (the caller's range check then
    refuses it, with its own message)."""
    try:
        return float(word)
    except ValueError:
        return math.nan


def _numbers(value: str) -> tuple[float, ...]:
    """The comma-separated numbers of an option's value; () when one of them is no number
    (the caller's length check then refuses it)."""
    try:
        return tuple(float(p) for p in value.split(","))
    except ValueError:
        return ()


def parse_intrinsics(value: str | None) -> tuple[float, ...] | None:
    """--intrinsics fx,fy,cx,cy (pixels, fx and fy > 0); plain Python, so usage errors stay fast."""
    if value is None:
        return None
    parts = _numbers(value)
    if len(parts) != 4 or not all(math.isfinite(p) for p in parts) or parts[0] <= 0 or parts[1] <= 0:
        raise click.BadParameter(f"expected fx,fy,cx,cy in pixels with fx, fy > 0, got {value!r}",
                                 param_hint="'--intrinsics'")
    return parts


def parse_viewpoint_option(value: str | None) -> tuple[float, ...] | None:
    """--viewpoint x,y,z[,qw,qx,qy,qz]: three or seven finite numbers, the quaternion (when
    given) not zero; plain Python, so usage errors stay fast (parsed again, into the frame,
    by c1mesh.stages.perspective.parse_viewpoint)."""
    if value is None:
        return None
    parts = _numbers(value)
    if len(parts) not in (3, 7) or not all(math.isfinite(p) for p in parts):
        raise click.BadParameter(f"expected x,y,z or x,y,z,qw,qx,qy,qz (finite numbers), got {value!r}",
                                 param_hint="'--viewpoint'")
    if len(parts) == 7 and not any(parts[3:]):
        raise click.BadParameter(f"the orientation qw,qx,qy,qz of {value!r} is zero, not a rotation",
                                 param_hint="'--viewpoint'")
    return parts


def check_axis(value: str) -> None:
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


def extension(path: str) -> str:
    """The lower-case extension of an output path without its dot ('' for none); stdout is PLY."""
    return "ply" if path == STDIO else Path(path).suffix.lower().lstrip(".")


def output_paths(params: dict) -> list[str]:
    """The mesh or DEM outputs a fit command line names: -o, or each input's path under -O."""
    if params["output_dir"]:
        return [str(Path(params["output_dir"]) / (("stdin" if src == STDIO else Path(src).stem) + params["suffix"]))
                for src in params["inputs"]]
    return [params["output"]] if params["output"] else []


def plan(inputs, output, output_dir, suffix) -> list[tuple[str, str]]:
    """(input, output) pairs of a command line that passed check_usage."""
    params = {"inputs": inputs, "output": output, "output_dir": output_dir, "suffix": suffix}
    return list(zip(inputs, output_paths(params)))
