"""Running `fit` once its command line is checked: one input, a batch of inputs (each
failure reported, exit 3), or a --seamless survey; the mesh, its .prj sidecar and the
JSON report are committed together or not at all (c1mesh.core.outputs.Outputs).
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import click

from c1mesh.cli.messages import note, summary, warn
from c1mesh.cli.options import plan
from c1mesh.cli.progress import caption, stage_bar, survey_progress
from c1mesh.cli.shell import EXIT_PARTIAL, fail, message, naming, stderr_is_terminal, worker_start
from c1mesh.core.errors import C1MeshError
from c1mesh.core.outputs import STDIO, Outputs, mesh_format, plan_outputs
from c1mesh.core.plan import TiledRun


def _fit(source, output, options, on_stage=None, keep_mesh: bool = False, *, outputs=None,
        tiles: TiledRun | None = None):
    """c1mesh.pipeline.run.fit, the one driver, imported when a fit runs (not for --help);
    the CLI streams the mesh to its output (keep_mesh False)."""
    from c1mesh.pipeline.run import fit as run_fit
    return run_fit(source, output, options, on_stage, keep_mesh, outputs=outputs, tiles=tiles)


def threads_per_process(threads: int | None, jobs: int) -> int:
    """--threads shared by the --jobs processes, so together they do not oversubscribe
    (Open3D's OpenMP threads included)."""
    from c1mesh.core.threads import openmp_at_start, per_process
    count = per_process(threads, jobs)
    openmp_at_start(count)
    return count


@dataclass(frozen=True)
class Console:
    """What `fit` says and where: report (the JSON report's path, - for stderr, None:
    none), quiet (no warnings, notes or progress), verbose (a summary per input), debug
    (tracebacks)."""

    report: str | None = None
    quiet: bool = False
    verbose: bool = False
    debug: bool = False


@dataclass(frozen=True)
class Workers:
    """Where `fit` runs: jobs (--jobs: processes; None: the tiled fit's choice), threads
    (--threads, the one knob; None: every CPU), scheduler (a Dask scheduler's address)."""

    jobs: int | None = 1
    threads: int | None = None
    scheduler: str | None = None


@dataclass(frozen=True)
class Destination:
    """Where `fit --seamless` writes: output (-o, one mesh or DEM of the survey), or
    output_dir (-O) with each input's name and suffix."""

    output: str | None
    output_dir: str | None
    suffix: str | None


def fit_survey(inputs, destination: Destination, options, console: Console, workers: Workers) -> None:
    """`fit --seamless`: the inputs as one survey (c1mesh.survey.tiles), one line on any failure."""
    output, output_dir, suffix = destination.output, destination.output_dir, destination.suffix
    report, quiet, debug = console.report, console.quiet, console.debug
    jobs, threads, scheduler = workers.jobs, workers.threads, workers.scheduler
    pairs = plan(inputs, None, output_dir, suffix) if output_dir else [(inputs[0], output)]
    try:
        if options.crs:
            from c1mesh.core.crs import parse_crs
            options = replace(options, crs=parse_crs(options.crs))
        if output_dir and not Path(output_dir).exists():
            Path(output_dir).mkdir(parents=True)
        named = [("output", dst) for _, dst in pairs] + (_tile_rasters(pairs, options) if output_dir else [])
        named += [("report", None if report in (None, STDIO) else report)]
        targets = plan_outputs(named, list(inputs))
        from c1mesh.geo.raster import is_raster_path
        for (_, dst), target in zip(pairs, targets):
            if not is_raster_path(dst):
                mesh_format(dst, target=target)
    except (C1MeshError, OSError) as exc:
        fail(message(exc), debug)
    options.workers = threads_per_process(threads, 1)
    mesh = sys.stdout.buffer if output == STDIO else output
    outputs = [d for _, d in pairs] if output_dir else None
    tiles = TiledRun(scheduler=scheduler, jobs=jobs)
    try:
        if stderr_is_terminal() and not quiet:
            progress, callbacks = survey_progress(list(inputs), options, len(pairs) if output_dir else 0, mesh)
            with progress:
                result = _fit(list(inputs), mesh, options, outputs=outputs, tiles=replace(tiles, **callbacks)).report
        else:
            result = _fit(list(inputs), mesh, options, outputs=outputs, tiles=tiles).report
    except Exception as exc:  # noqa: BLE001 — a failed tile names itself; no output is left
        fail(_survey_naming(inputs, message(exc)), debug)
    warn(result, quiet)
    _write_report(report, targets[-1], result, debug)
    note(result, quiet)


def _tile_rasters(pairs, options) -> list[tuple[str, str]]:
    """The side rasters and mosaics of per-tile DEMs (--seamless -O DIR --suffix .tif), named
    as c1mesh.pipeline.driver names them, for the check of every output before any input
    is read; none for meshes."""
    from c1mesh.geo.raster import is_raster_path, mosaic_paths, tile_targets

    if not pairs or not is_raster_path(pairs[0][1]):
        return []
    from c1mesh.pipeline.driver import side_rasters

    sides = side_rasters(options)
    named = [(f"{kind} raster", path) for _, dst in pairs for kind, path in tile_targets(dst, sides).items()
             if kind != "dem"]
    return named + [(f"{kind} mosaic", path) for kind, path in mosaic_paths([dst for _, dst in pairs],
                                                                            sides).items()]


def _survey_naming(inputs, text: str) -> str:
    """A survey's error led by its input when it has one, as a single input's fit says it
    (shell.naming); a survey of several inputs leaves the naming to the error, which
    names the file it is about."""
    return naming(inputs[0], text) if len(inputs) == 1 else text


def fit_one(src, dst, targets, options, console: Console, workers: Workers) -> None:
    """Fit one input; the mesh and the report are committed together, or neither is."""
    report, quiet, verbose, debug = console.report, console.quiet, console.verbose, console.debug
    jobs, scheduler = workers.jobs, workers.scheduler
    from c1mesh.geo.raster import is_raster_path
    from c1mesh.pipeline.driver import STAGES

    mesh_target, report_target = targets
    raster = is_raster_path(dst)
    options = replace(options, output_format=None if raster else mesh_format(dst, target=mesh_target))
    show = stderr_is_terminal() and not quiet

    def run(target):
        tiles = TiledRun(scheduler=scheduler, jobs=jobs)
        source = sys.stdin.buffer if src == STDIO else src
        if not show:
            return _fit(source, target, options, tiles=tiles).report
        with stage_bar(len(STAGES), f"fitting {src}") as bar:
            tiles = replace(tiles, on_tile=lambda name, done, count: caption(bar, f"{name}: tile {done} of {count}"))
            return _fit(source, target, options, lambda name: bar.update(1, name), tiles=tiles).report
    try:
        with Outputs() as outputs:
            if raster:      # c1mesh.geo.raster writes the GeoTIFFs, each atomically
                result = run(dst)
            else:
                with outputs.open(mesh_target) as mesh_file:
                    result = run(mesh_file)
                _write_prj(outputs, dst, mesh_target, options.output_format, result)
            result["output"] = dst
            _stage_report(outputs, report_target, result)
            outputs.commit()
    except Exception as exc:  # noqa: BLE001 — any failure is one line
        fail(naming(src, message(exc)), debug)
    if report == STDIO:
        click.echo(json.dumps(result, indent=2), err=True)
    note(result, quiet)
    warn(result, quiet)
    if verbose and not quiet:
        click.echo(summary(result), err=True)


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


def _stage_report(outputs: Outputs, target, payload: dict) -> None:
    """The JSON report into the transaction `outputs`, at its checked target (None: no file)."""
    if target is not None:
        with outputs.open(target, "w") as handle:
            handle.write(json.dumps(payload, indent=2) + "\n")


def _write_report(report, target, payload, debug) -> None:
    """The batch's JSON report to its checked target (or stderr for -)."""
    if not report:
        return
    if report == STDIO:
        click.echo(json.dumps(payload, indent=2), err=True)
        return
    try:
        with Outputs() as outputs:
            _stage_report(outputs, target, payload)
            outputs.commit()
    except (C1MeshError, OSError) as exc:
        fail(f"cannot write report '{report}': {message(exc)}", debug)


def _batch_worker(args):
    src, dst, options, scheduler = args
    try:
        return src, _fit(src, dst, options, tiles=TiledRun(scheduler=scheduler)).report, None
    except Exception as exc:  # noqa: BLE001 — reported per file, the batch goes on
        return src, None, message(exc)


def fit_batch(pairs, report_target, options, console: Console, workers: Workers) -> None:
    """Fit several inputs, each on its own (in `jobs` processes): a failing input is
    listed on stderr and the others are still written; exit 3 when some failed."""
    report, quiet, verbose, debug = console.report, console.quiet, console.verbose, console.debug
    jobs, scheduler = workers.jobs or 1, workers.scheduler
    work = [(src, dst, options, scheduler) for src, dst in pairs]
    show = stderr_is_terminal() and not quiet
    if jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=jobs, initializer=worker_start) as pool:
            results = _collect(pool.map(_batch_worker, work), len(work), show, verbose and not quiet)
    else:
        results = _collect(map(_batch_worker, work), len(work), show, verbose and not quiet)
    for _, rep, _ in results:
        if rep:
            note(rep, quiet)
            warn(rep, quiet)
    failures = [(src, err) for src, _, err in results if err]
    _write_report(report, report_target,
                  {"inputs": [{"input": src, "report": rep, "error": err} for src, rep, err in results]}, debug)
    if failures:
        for src, err in failures:
            click.echo(f"c1mesh: failed: {src}: {err}", err=True)
        click.echo(f"c1mesh: {len(failures)} of {len(results)} inputs failed", err=True)
        sys.exit(EXIT_PARTIAL)


def _collect(iterator, total, show, verbose):
    if show:
        with click.progressbar(iterator, length=total, label="fitting", file=sys.stderr) as bar:
            return list(bar)
    results = []
    for item in iterator:
        results.append(item)
        if verbose and item[1]:
            click.echo(summary(item[1]), err=True)
    return results


def classify_ground_file(src: str, dst: str, report, quiet: bool, debug: bool) -> None:
    """`c1mesh ground`: the output and the report checked against the input and each other
    before anything is read, then written together (atomically) or not at all."""
    from c1mesh.pipeline.ground_file import classify_file

    try:
        targets = plan_outputs([("output", dst), ("report", None if report in (None, STDIO) else report)], [src])
        with Outputs() as outputs:
            with outputs.open(targets[0]) as handle:
                result = classify_file(src, handle, dst)
            _stage_report(outputs, targets[1] if len(targets) > 1 else None, result)
            outputs.commit()
    except Exception as exc:  # noqa: BLE001 — any failure is one line
        fail(naming(src, message(exc)), debug)
    if report == STDIO:
        click.echo(json.dumps(result, indent=2), err=True)
    if not quiet and stderr_is_terminal():
        click.echo(f"c1mesh: {src}: {result['ground']} of {result['points']} points are ground -> {dst}", err=True)
