"""The one driver: every fit runs through `fit`, the library's verb and the CLI's.

    fit(one input, or a list of inputs: one survey; one output, or one per input)
      → the execution, from the options and the inputs' headers, before any point is read:
          in memory, as one tile              (c1mesh.pipeline.driver.fit_in_memory)
          in tiles, beyond --memory           (c1mesh.pipeline.bounded_fit.fit_tiled: the
                                               same stages on spilled tiles, run here, on
                                               local processes or on a Dask cluster)
      → a survey fitted in memory with one output per input (-O): the survey's one model,
        each input's own triangles refined as tile tasks (c1mesh.survey.tiles) or each
        input's window of the survey's DEM (driver.fit_dem_tiles)

Which execution ran never changes the answer: the tiled stages are the in-memory ones
run on a tile with its halo (docs/tiles.md says what differs, and to what digit). A
Dask scheduler given for a fit that runs in memory in one piece has nothing to run; the
report's `scheduler` then says so. Nothing here prints or exits.
"""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable

from c1mesh.core.crs import parse_crs
from c1mesh.core.crs import resolve as resolve_crs
from c1mesh.core.errors import InputError
from c1mesh.core.plan import TiledRun
from c1mesh.core.threads import limit as thread_limit
from c1mesh.core.threads import workers as thread_count
from c1mesh.formats import check_output
from c1mesh.geo.products import geo_plan
from c1mesh.geo.raster import SIDE_KINDS, is_raster_path
from c1mesh.pipeline.bounded_fit import fit_tiled, tiles_report
from c1mesh.pipeline.driver import (
    FitOptions,
    angle_z_factor,
    build_surface,
    fit_dem_tiles,
    fit_in_memory,
    frame_facts,
    smoothing_facts,
    surface_facts,
    trim_facts,
)
from c1mesh.pipeline.plan import fit_plan, resolve_options_axis
from c1mesh.pipeline.report import ReportCore, crs_facts
from c1mesh.pipeline.steps import FitResult, StageTimer
from c1mesh.stages.ground import resolved_classes
from c1mesh.stages.surface import PLANE_LEVEL
from c1mesh.survey.distributed import run_tiles
from c1mesh.survey.sizing import needs_tiles
from c1mesh.survey.tiles import TilePlan, load_survey, write_tiles

OWNERSHIP = "lowest-numbered corner point"
"""The report's ownership of per-input outputs: the rule that gives each triangle to one output."""

SCHEDULER_UNUSED = ("not used: {what} fits in --memory, so it was fitted in one piece in this process "
                    "(the scheduler runs the tiles of a larger fit, or of --seamless -O)")
"""The report's `scheduler` when a scheduler had no tiles to run (also the CLI's note)."""


def fit(source, output=None, options: FitOptions | None = None, on_stage: Callable[[str], None] | None = None,
        keep_mesh: bool = True, *, outputs=None, tiles: TiledRun | None = None) -> FitResult:
    """Fit a refined C1 surface mesh, or a DEM, to a scan or a survey.

    source: a path, a binary stream (then options.input_format is required) or a
    PointCloud; or a list of paths, fitted as one survey (`c1mesh fit --seamless`).
    output: one path or binary stream for the whole result (None: only return the mesh);
    or outputs (a survey only): one path per input, each holding the triangles its input
    owns (OWNERSHIP), or its window of the survey's DEM. options: FitOptions (None: the
    defaults); on_stage(name) after each stage; keep_mesh=False streams the mesh to the
    output instead of returning it (the CLI does this). tiles: where tiles run and whom
    they tell (core.plan.TiledRun: a Dask scheduler, local jobs, on_tile, and per_tile,
    which forces tiles of that size: tests). Returns the FitResult: the mesh (None when
    streamed, tiled or split) and the report (c1mesh.pipeline.report's schema, the same
    on every path). Every stage uses at most options.workers threads. on_stage, when
    given, replaces tiles.on_stage.
    """
    options = options or FitOptions()
    tiles = tiles or TiledRun()
    tiles = tiles if on_stage is None else replace(tiles, on_stage=on_stage)
    survey = isinstance(source, (list, tuple))
    if survey and not source:
        raise InputError("a survey needs at least one input file")
    if outputs is not None and (not survey or output is not None):
        raise ValueError("outputs (one per input) go with a list of inputs and no single output")
    if output is not None and not is_raster_path(output):   # fails now, not after the work
        check_output(output, options.output_format, inputs=tuple(source) if survey else (source,))
    with thread_limit(options.workers):
        if survey:          # LAS/LAZ surveys: z, as fit_in_memory resolves (and reports) one file's axis
            options, _ = resolve_options_axis(source[0], options)
        if outputs is not None and options.contours:
            raise InputError("--contours makes one survey-wide file: use it with --seamless -o, not -O")
        plan = fit_plan(options, output if outputs is None else outputs[0])   # a bad --smooth fails before any work
        if tiles.per_tile is not None or needs_tiles(list(source) if survey else source, plan):
            return FitResult(None, _fit_in_tiles(source, output, plan, replace(tiles, outputs=outputs), options))
        if outputs is not None:
            return FitResult(None, _fit_survey_outputs(source, outputs, options, tiles))
        result = _fit_whole(source, output, options, tiles, keep_mesh)
    if tiles.scheduler is not None:
        result.report["scheduler"] = SCHEDULER_UNUSED.format(what="the survey" if survey else "the input")
    return result


def _fit_in_tiles(source, output, plan, tiles: TiledRun, options: FitOptions) -> dict:
    """The memory-bounded fit (bounded_fit.fit_tiled: a mesh, or a DEM when output is a
    GeoTIFF, pipeline.bounded_dem) and its report; plan: the options' core.plan.FitPlan for
    that output, resolved once by `fit`."""
    if plan.dem is not None and tiles.outputs is None:
        geo_plan(output, options)                     # the rasters' paths and options, before any work
    elif plan.dem is not None:                        # -O's DEMs: the side rasters' options name mosaics
        geo_plan(tiles.outputs[0], replace(options, **{kind: None for kind in SIDE_KINDS}))
    report = tiles_report(fit_tiled(source, output, plan, tiles), options)
    if tiles.outputs is not None:
        report["ownership"] = OWNERSHIP
    return report


def _fit_whole(source, output, options: FitOptions, tiles: TiledRun, keep_mesh: bool) -> FitResult:
    """One input, or a survey's inputs as one cloud, fitted in memory to one output."""
    if not isinstance(source, (list, tuple)):
        return fit_in_memory(source, output, options, tiles.on_stage, keep_mesh)
    timer = StageTimer(None)
    with timer.stage("read"):
        survey = load_survey(source, fit_plan(options).select, options.normals)
    result = fit_in_memory(survey.cloud, output, options, tiles.on_stage, keep_mesh)
    result.report["input"] = list(survey.names)
    result.report["seconds"] = {"read": timer.seconds["read"], **result.report["seconds"]}
    return result


def _fit_survey_outputs(sources, outputs, options: FitOptions, tiles: TiledRun) -> dict:
    """`--seamless -O` in memory: the survey fitted once, each input's own triangles
    refined as tile tasks (survey.tiles, run by survey.distributed.run_tiles on tiles'
    scheduler or jobs) into its output, or each input's window of the survey's DEM."""
    timer = StageTimer(None)
    with timer.stage("read"):
        survey = load_survey(sources, fit_plan(options).select, options.normals)
    if is_raster_path(outputs[0]):             # per-tile DEMs and their VRT mosaic
        report = fit_dem_tiles(survey, outputs, options, timer)
        report["ownership"] = OWNERSHIP
        return report
    level_from = "default" if options.level is None else "option"
    if options.level is None:                   # a height field: PLANE_LEVEL unless --level is given
        options = replace(options, level=PLANE_LEVEL)
    if not isinstance(options.classes, tuple):  # the stages see codes: the filter's ground as 2
        options = replace(options, classes=resolved_classes(survey.cloud.selection))
    crs, crs_source = resolve_crs(survey.cloud.crs, parse_crs(options.crs) if options.crs else None,
                                  survey.names[0])
    model = build_surface(survey.cloud, options, timer)
    report = ReportCore(
        input=list(survey.names), output=list(outputs),
        points={"read": len(survey.cloud), "kept": int(model.used.size)},
        normals=model.normal_source, gradients=model.gradient_source, frame=frame_facts(model.frame),
        triangles=trim_facts(model.trim_report), level=options.level, level_from=level_from,
        output_mesh=None, **surface_facts(survey.cloud, model, options, pieces_in_warnings=False),
        crs=crs_facts(crs, crs_source),
        seconds=timer.seconds, threads=thread_count(), z_factor=angle_z_factor(survey.cloud, options)).as_dict()
    report.update(smoothing_facts(model))
    report.update({} if survey.cloud.selection is None else {"classes": survey.cloud.selection})
    jobs = tiles.jobs or 1
    report.update({"overshoot": model.overshoot.as_dict(), "ownership": OWNERSHIP,
                   "scheduler": tiles.scheduler or (f"{jobs} local processes" if jobs > 1 else "in process")})
    tasks = TilePlan(model, survey, outputs, options.level, options.ascii, crs)
    del model, survey               # the cloud and height field: the plan keeps what tiles need
    start = time.perf_counter()
    report["tiles"] = write_tiles(run_tiles(tasks, tiles.scheduler, jobs), tasks.outputs, ascii=options.ascii,
                                  on_tile=tiles.on_output, crs=crs)
    timer.seconds["tiles"] = round(time.perf_counter() - start, 6)
    return report


def in_tiles(source, options: FitOptions, output=None) -> bool:
    """Whether `fit` runs `source` (one LAS/LAZ path, or a list of them: one survey) in
    tiles into output (a mesh, or a DEM .tif): larger than options.memory allows in one
    piece (survey.sizing.needs_tiles). Reads the inputs' headers only (the CLI's progress
    asks, to show the tiles' stages)."""
    return needs_tiles(source, fit_plan(options, output))
