"""The `c1mesh` command: a thin click layer over the library.

Exit codes (cli/README.md): 0 success, 1 failure, 2 usage error, 3 batch where some
inputs failed. Errors are one line on stderr; --debug shows the traceback. Progress goes
to stderr only when stderr is a terminal.
"""
from __future__ import annotations

import json
import os
import signal
import sys
import traceback
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import click

from c1mesh import __version__
from c1mesh.errors import C1MeshError

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_PARTIAL = 0, 1, 2, 3


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


def _parse_max_edge(value: str):
    if value.lower() == "auto":
        return "auto"
    if value.lower() == "none":
        return None
    try:
        length = float(value)
    except ValueError:
        raise click.BadParameter(f"expected auto, none or a positive length, got {value!r}")
    if not length > 0:
        raise click.BadParameter(f"expected a positive length, got {value!r}")
    return length


def _parse_intrinsics(value: str | None):
    from c1mesh.errors import InputError
    from c1mesh.formats.depth import parse_intrinsics
    try:
        return parse_intrinsics(value)
    except InputError as exc:
        raise click.BadParameter(str(exc))


def _stderr_is_terminal() -> bool:
    try:
        return os.isatty(sys.stderr.fileno())
    except (AttributeError, OSError, ValueError):
        return False


class _Group(click.Group):
    """A click group whose unexpected failures are still one line on stderr and exit 1."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except Exception as exc:  # noqa: BLE001 — the safety net under every command
            _fail(_message(exc), debug="--debug" in sys.argv)


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
@click.option("--input-format", help="Input format (ply, obj, xyz, txt, csv, pcd, las, laz); required for stdin (-).")
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
@click.option("--report", help="Write a JSON report to FILE, or - for stderr.")
@click.option("-j", "--jobs", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Parallel processes for several inputs.")
@click.option("-q", "--quiet", is_flag=True, help="No progress and no summary.")
@click.option("-v", "--verbose", is_flag=True, help="Print a summary line per input on stderr.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
def fit(inputs, output, output_dir, suffix, input_format, classes, normals, k, axis, max_slope,
        max_edge, scheme, level, ascii_ply, frame_kind, viewpoint, intrinsics, depth_scale, color_image,
        report, jobs, quiet, verbose, debug):
    """Fit a refined C1 surface mesh to each INPUT scan (- reads stdin)."""
    from c1mesh.pipeline import FitOptions

    options = FitOptions(input_format=input_format, axis=axis, normals=normals, k=k,
                         classes=_parse_classes(classes), max_slope=max_slope,
                         max_edge=_parse_max_edge(max_edge), scheme=scheme, level=level, ascii=ascii_ply,
                         frame=frame_kind, viewpoint=viewpoint, depth_scale=depth_scale, color=color_image,
                         intrinsics=_parse_intrinsics(intrinsics))
    if scheme == "quintic" and not quiet:
        click.echo("c1mesh: warning: the quintic scheme does not reproduce planes and its normals "
                   "do not converge; use sextic unless you need the 2022 procedure", err=True)
    jobs_list = _plan(inputs, output, output_dir, suffix, input_format)
    if len(jobs_list) == 1:
        _fit_one(*jobs_list[0], options, report, quiet, verbose, debug)
        return
    _fit_batch(jobs_list, options, report, jobs, quiet, verbose, debug)


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
        Path(output_dir).mkdir(parents=True, exist_ok=True) if not Path(output_dir).exists() else None
        return pairs
    if not output:
        raise click.UsageError("give -o OUTPUT (or -O DIR for several inputs)")
    return [(inputs[0], output)]


def _check_paths(src: str, dst: str) -> None:
    if src != "-" and dst != "-" and os.path.exists(dst) and os.path.exists(src) \
            and os.path.samefile(src, dst):
        raise C1MeshError(f"output '{dst}' is the input file; refusing to overwrite an input")


def _run(src: str, dst: str, options, on_stage=None) -> dict:
    """Fit one input to one output; returns the report."""
    from c1mesh.pipeline import fit as fit_pipeline

    _check_paths(src, dst)
    source = sys.stdin.buffer if src == "-" else src
    target = sys.stdout.buffer if dst == "-" else dst
    result = fit_pipeline(source, target, options, on_stage=on_stage, keep_mesh=False)
    if dst == "-":
        sys.stdout.buffer.flush()
    return result.report


def _fit_one(src, dst, options, report, quiet, verbose, debug) -> None:
    from c1mesh.pipeline import STAGES

    show = _stderr_is_terminal() and not quiet
    try:
        if show:
            with click.progressbar(length=len(STAGES), label=f"fitting {src}", file=sys.stderr,
                                   item_show_func=lambda s: s) as bar:
                result = _run(src, dst, options, on_stage=lambda name: bar.update(1, name))
        else:
            result = _run(src, dst, options)
    except (C1MeshError, OSError, MemoryError, ValueError) as exc:
        _fail(_message(exc), debug)
    except Exception as exc:  # noqa: BLE001 — any other failure is still one line
        _fail(_message(exc), debug)
    _write_report(report, result, debug)
    if verbose and not quiet:
        click.echo(_summary(result), err=True)


def _summary(report: dict) -> str:
    pts, mesh = report["points"], report["output_mesh"]
    total = sum(report["seconds"].values())
    return (f"{report['input']}: {pts['kept']} of {pts['read']} points -> {mesh['vertices']} vertices, "
            f"{mesh['faces']} faces in {total:.2f} s")


def _write_report(report_target, payload, debug) -> None:
    if not report_target:
        return
    text = json.dumps(payload, indent=2)
    if report_target == "-":
        click.echo(text, err=True)
        return
    from c1mesh.formats import atomic_output
    try:
        with atomic_output(report_target, "w") as handle:
            handle.write(text + "\n")
    except (C1MeshError, OSError) as exc:
        _fail(f"cannot write report '{report_target}': {_message(exc)}", debug)


def _batch_worker(args):
    src, dst, options = args
    try:
        return src, _run(src, dst, options), None
    except Exception as exc:  # noqa: BLE001 — reported per file, the batch goes on
        return src, None, _message(exc)


def _fit_batch(pairs, options, report, jobs, quiet, verbose, debug) -> None:
    work = [(src, dst, options) for src, dst in pairs]
    results = []
    show = _stderr_is_terminal() and not quiet
    if jobs > 1:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            iterator = pool.map(_batch_worker, work)
            results = _collect(iterator, len(work), show, verbose and not quiet)
    else:
        results = _collect(map(_batch_worker, work), len(work), show, verbose and not quiet)
    failures = [(src, err) for src, _, err in results if err]
    _write_report(report, {"inputs": [{"input": src, "report": rep, "error": err} for src, rep, err in results]},
                  debug)
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
@click.option("--intrinsics", help="Depth images: the camera's fx,fy,cx,cy in pixels.")
@click.option("--depth-scale", type=click.FloatRange(0, min_open=True), default=0.001, show_default=True,
              help="Depth images: metres per depth unit.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
def info(path, input_format, intrinsics, depth_scale, debug):
    """Describe a point file: points, fields, normals, bounds, suggested axis, height field?"""
    from c1mesh.inspect import describe

    if path == "-" and not input_format:
        raise click.UsageError("reading stdin (-) needs --input-format")
    try:
        facts = describe(sys.stdin.buffer if path == "-" else path, input_format,
                         intrinsics=_parse_intrinsics(intrinsics), depth_scale=depth_scale)
    except Exception as exc:  # noqa: BLE001
        _fail(_message(exc), debug)
    click.echo(json.dumps(facts, indent=2))


# ------------------------------------------------------------------------------- schemes
@main.command()
def schemes():
    """List the shape-function tuples with their computed properties."""
    from c1mesh.properties import scheme_properties
    from c1mesh.schemes import DEFAULT_SCHEME, NAMED_TUPLES

    click.echo(f"{'name':<9} {'degree':>6}  {'constants':<9}  {'affine':<6}  description")
    for name, tup in NAMED_TUPLES.items():
        p = scheme_properties(tup)
        mark = " (default)" if name == DEFAULT_SCHEME else ""
        click.echo(f"{name:<9} {p.degree:>6}  {'yes' if p.reproduces_constants else 'no':<9}  "
                   f"{'yes' if p.reproduces_affine else 'no':<6}  {tup.description}{mark}")


if __name__ == "__main__":  # pragma: no cover
    main()
