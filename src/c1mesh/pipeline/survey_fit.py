"""`--seamless`: several inputs fitted as one survey, on the same stages as one input.

-o writes the fit of the concatenated cloud (pipeline.driver.fit); -O fits the survey once
and writes each input's own triangles as tile tasks (survey.tiles, survey.distributed); a
LAS/LAZ survey larger than --memory goes to the memory-bounded fit (survey.bounded_fit).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable, Sequence

from c1mesh.core.crs import parse_crs
from c1mesh.core.errors import InputError
from c1mesh.core.plan import TiledRun
from c1mesh.core.threads import workers as thread_count
from c1mesh.geo.products import geo_plan, resolve_crs
from c1mesh.geo.raster import is_raster_path
from c1mesh.pipeline.driver import (
    angle_z_factor,
    build_surface,
    fit,
    fit_dem_tiles,
    frame_facts,
    smoothing_facts,
    surface_facts,
    trim_facts,
)
from c1mesh.pipeline.plan import fit_plan, resolve_options_axis
from c1mesh.pipeline.report import ReportCore, crs_facts, scheme_facts
from c1mesh.pipeline.steps import StageTimer
from c1mesh.stages.ground import resolved_classes
from c1mesh.stages.surface import PLANE_LEVEL
from c1mesh.stages.warnings import smoothing_suggestion
from c1mesh.survey.distributed import run_tiles
from c1mesh.pipeline.bounded_fit import fit_tiled
from c1mesh.survey.sizing import needs_tiles
from c1mesh.survey.tiles import load_survey, plan_tiles, write_tiles

OWNERSHIP = "lowest-numbered corner point"
"""The report's ownership of --seamless -O: the rule that gives each triangle to one output."""


@dataclass(frozen=True)
class SurveyProgress:
    """Whom a --seamless fit tells how far it is: on_stage(stage) after each stage
    (in-memory -o: pipeline.STAGES; in tiles: bounded_fit.TILED_STAGES); on_tile(row) with
    each output's report row as it is written (in-memory -O); on_tile_pass(pass, tiles
    done, tiles) as each tile task of the memory-bounded fit finishes."""

    on_stage: Callable[[str], None] | None = None
    on_tile: Callable[[dict], None] | None = None
    on_tile_pass: Callable[[str, int, int], None] | None = None


def fit_seamless(sources: Sequence[str], options, output=None, outputs: Sequence[str] | None = None,
                 scheduler: str | None = None, jobs: int | None = 1,
                 progress: SurveyProgress = SurveyProgress()) -> dict:
    """Fit the inputs as one survey; returns the report.

    output: one path for the whole survey's mesh (the fit of the concatenated cloud,
    written as `c1mesh fit` writes one input); or outputs: one path per input, each
    holding the triangles its input owns (module docstring), tiles run by
    distributed.run_tiles (scheduler, jobs; None: 1); progress: SurveyProgress. A LAS/LAZ
    survey larger than options.memory allows in one piece (in_tiles) goes to the
    memory-bounded fit (c1mesh.pipeline.bounded_fit), which writes the one mesh, or splits it
    into the outputs by the same ownership rule (c1mesh.survey.split_outputs).
    """

    options, _ = resolve_options_axis(sources[0], options)     # LAS/LAZ surveys: z, as for one file
    if outputs is not None and options.contours:
        raise InputError("--contours makes one survey-wide file: use it with --seamless -o, not -O")
    user_crs = parse_crs(options.crs) if options.crs else None
    if in_tiles(list(sources), options, output):
        report = fit_in_tiles(list(sources), output, options,
                              TiledRun(scheduler=scheduler, jobs=jobs, outputs=outputs, on_stage=progress.on_stage,
                                       on_tile=progress.on_tile_pass))
        if outputs is not None:
            report["ownership"] = OWNERSHIP
        return report
    if scheduler is not None and output is not None:
        raise InputError(f"--scheduler runs the tiles of --seamless -O, or of a fit larger than --memory "
                         f"allows; {sources[0]} is fitted in memory in one piece: drop --scheduler, "
                         "or use -O DIR")
    timer = StageTimer(None)
    with timer.stage("read"):
        survey = load_survey(sources, fit_plan(options).select, options.normals)
    if output is not None:
        report = fit(survey.cloud, output, options, on_stage=progress.on_stage, keep_mesh=False).report
        report["input"] = list(survey.names)
        report["seconds"] = {"read": timer.seconds["read"], **report["seconds"]}
        return report
    if is_raster_path(outputs[0]):             # per-tile DEMs and their VRT mosaic
        report = fit_dem_tiles(survey, outputs, options, timer)
        report["ownership"] = OWNERSHIP
        return report
    level_from = "default" if options.level is None else "option"
    if options.level is None:                   # a height field: PLANE_LEVEL unless --level is given
        options = replace(options, level=PLANE_LEVEL)
    if not isinstance(options.classes, tuple):  # the stages see codes: the filter's ground as 2
        options = replace(options, classes=resolved_classes(survey.cloud.selection))

    crs, crs_source = resolve_crs(survey.cloud.crs, user_crs, survey.names[0])
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
    jobs = jobs or 1
    report.update({"overshoot": model.overshoot.as_dict(), "ownership": OWNERSHIP,
                   "scheduler": scheduler or (f"{jobs} local processes" if jobs > 1 else "in process")})
    tasks = plan_tiles(model, survey, outputs, options.level, options.ascii, crs)
    del model, survey               # the cloud and height field: the plan keeps what tiles need
    start = time.perf_counter()
    report["tiles"] = write_tiles(run_tiles(tasks, scheduler, jobs), tasks.outputs, ascii=options.ascii,
                                  on_tile=progress.on_tile, crs=crs)
    timer.seconds["tiles"] = round(time.perf_counter() - start, 6)
    return report


def in_tiles(source, options, output=None) -> bool:
    """Whether `source` (one LAS/LAZ path, or a list of them: one survey) is fitted by the
    memory-bounded fit (survey.sizing.needs_tiles) into output (a mesh, or a DEM .tif):
    larger than options.memory allows in one piece. Reads the inputs' headers only."""
    return needs_tiles(source, fit_plan(options, output))


def fit_in_tiles(source, output, options, run: TiledRun = TiledRun()) -> dict:
    """The memory-bounded fit (c1mesh.pipeline.bounded_fit.fit_tiled: source one LAS/LAZ path or
    a list, output a mesh path, run where its tiles run) with its facts made the report of
    c1mesh.pipeline.report's schema."""
    plan = fit_plan(options, output)                  # InputError for a bad --smooth, before any work
    if plan.dem is not None:
        geo_plan(output, options)                     # the rasters' paths and options, before any work
    if plan.surface.spacing is not None:
        raise InputError("--spacing is not yet available for a fit larger than --memory (fitted in tiles, "
                         "whose vertices are the points): raise --memory, or fit without --spacing")
    return tiles_report(fit_tiled(source, output, plan, run), options)


def tiles_report(facts: dict, options) -> dict:
    """The report of a memory-bounded fit from the facts fit_tiled returns (consumed). No
    one interpolator is held, so c1_certificate and pieces are null; its normals are
    always estimated (it refuses --normals file)."""
    level = facts.pop("level")
    report = ReportCore(
        input=facts.pop("input"), output=facts.pop("output"), points=facts.pop("points"),
        normals="estimated", gradients=facts.pop("gradients"), frame={"kind": "axis", **facts.pop("frame")},
        triangles=facts.pop("triangles"), level=level,
        level_from=None if level is None else "default" if options.level is None else "option",
        output_mesh=facts.pop("output_mesh"),
        scheme=scheme_facts(options.scheme), c1_certificate=None, pieces=None, warnings=facts.pop("warnings"),
        crs=facts.pop("crs"), seconds=facts.pop("seconds"), threads=thread_count(),
        z_factor=1.0 if options.z_factor is None else float(options.z_factor)).as_dict()
    report.update(facts)
    if "raster" in report:        # a DEM (pipeline.tiled_dem): --fill off, the one fill done in tiles
        report["raster"]["fill"] = {"option": options.fill, "distance": None, "triangles_spanning_holes": 0}
    overshoot = report.get("overshoot")
    if "smoothing" not in report and overshoot:     # the advice of an exact fit, as in memory
        text = smoothing_suggestion(overshoot["gradients_limited"], int(report["points"]["kept"]))
        if text is not None:
            report["suggestion"] = text
    return report
