"""What `fit` prints on stderr about a finished fit: the -v summary line, `c1mesh: note:`
lines for options that did nothing and the advice to smooth, and the report's warnings
(cli/README.md).
"""
from __future__ import annotations

import click
from click.core import ParameterSource

from c1mesh.cli.shell import stderr_is_terminal


def summary(report: dict) -> str:
    """The -v line about one fit: points kept of read, what was made, seconds, and the
    height axis and limiter counts where the report has them."""
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


def note(report: dict, quiet: bool) -> None:
    """`c1mesh: note:` lines on stderr (not with -q) for options given that did nothing: a
    --scheduler not used (the user asked for the cluster and should know the work stayed
    here), and a --max-slope given for heights whose slopes are no angles (the report's
    max_slope_not_applied; its default then goes unmentioned); and, only on a terminal, as
    progress (a pipe or a log stays quiet: the report keeps them), the report's advice to
    fit noisy heights with --smooth auto unless --smooth was given (the user chose), and
    the strength --smooth auto chose and how."""
    if quiet:
        return
    used = report.get("scheduler")
    if isinstance(used, str) and used.startswith("not used"):
        click.echo(f"c1mesh: note: {_input_name(report)}: --scheduler {used}", err=True)
    why = report.get("max_slope_not_applied")
    if why and _option_given("max_slope"):
        click.echo(f"c1mesh: note: {_input_name(report)}: --max-slope was not applied: {why}", err=True)
    classes = report.get("classes")
    if classes and classes.get("source") in ("file", "filter") and stderr_is_terminal():
        click.echo(f"c1mesh: note: {_input_name(report)}: {classes_note(classes)}", err=True)
    advice = report.get("suggestion")
    if advice and not _option_given("smooth") and stderr_is_terminal():
        click.echo(f"c1mesh: note: {_input_name(report)}: {advice}", err=True)
    smoothing = report.get("smoothing")
    if smoothing and smoothing.get("cv_curve") and stderr_is_terminal():
        chosen = "" if _option_given("smooth") else DEFAULT_NOTE
        click.echo(f"c1mesh: note: {_input_name(report)}: {chosen}{strength_note(smoothing)}", err=True)


DEFAULT_NOTE = "the normals are estimated, so the spline is fitted to the points by default (--smooth off: " \
               "through them); "
"""What the strength note says first when the smoothing fit is the default's (issue 38)."""


def strength_note(smoothing: dict) -> str:
    """The note about the strength a --smooth auto fit chose, and how (report "smoothing")."""
    windows = smoothing.get("search_windows") or {}
    count = len(windows.get("centres", []))
    where = (f"on {count} window{'s' if count > 1 else ''} of side {windows['side']:.4g}" if count
             else "on the whole mesh")
    limit = "; the lowest score lay at the search's limit" if smoothing.get("search_limit_reached") else ""
    return (f"--smooth auto chose strength {smoothing['strength']:.3g}: the lowest spatial-block "
            f"cross-validation score of {len(smoothing['cv_curve'])} tried, {where}{limit}")


def classes_note(classes: dict) -> str:
    """The note about the points a LAS/LAZ fit chose by default: the file's ground class,
    or the ground filter's ground (report "classes")."""
    kept = f"{classes.get('points_kept', '?')} of {classes.get('points_read', '?')} points"
    if classes["source"] == "file":
        return f"fitting the ground class 2 ({kept}); --classes all fits every point"
    return (f"fitting the ground the ground filter found ({kept}; {classes.get('reason')}); "
            "`c1mesh ground` writes its classes for checking, --classes all fits every point")


def _option_given(name: str) -> bool:
    """Whether option `name` of the running command was given on its command line."""
    ctx = click.get_current_context(silent=True)
    return ctx is not None and ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT)


def _input_name(report: dict) -> str:
    """The input(s) a report is about, for a message: one name, or the first and a count."""
    names = report.get("input")
    if isinstance(names, (list, tuple)):
        return names[0] if len(names) == 1 else f"{names[0]} and {len(names) - 1} more"
    return str(names)


def warn(report: dict, quiet: bool) -> None:
    """The report's warnings on stderr, one line each (not with -q)."""
    if quiet:
        return
    name = report.get("input")
    name = ", ".join(map(str, name)) if isinstance(name, (list, tuple)) else name
    for text in report.get("warnings", []):
        click.echo(f"c1mesh: warning: {name}: {text}", err=True)
