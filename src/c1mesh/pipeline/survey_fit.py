"""`--seamless`: several inputs fitted as one survey, on the same stages as one input.

-o writes the fit of the concatenated cloud (pipeline.driver.fit); -O fits the survey once
and writes each input's own triangles as tile tasks (survey.tiles, survey.distributed); a
LAS/LAZ survey larger than --memory goes to the memory-bounded fit (survey.tiled_fit).
"""
from __future__ import annotations

import time
from typing import Callable, Sequence

from c1mesh.core.errors import InputError
from c1mesh.stages.frame import resolve_axis
from c1mesh.stages.surface import with_plane_level
from c1mesh.stages.warnings import auto_limit, fit_warnings
from c1mesh.core.crs import describe, parse_crs
from c1mesh.geo.products import resolve_crs
from c1mesh.pipeline.driver import _Timer, build_surface, fit
from c1mesh.survey.distributed import run_tiles
from c1mesh.survey.tiled_fit import fit_tiled
from c1mesh.survey.tiles import load_survey, plan_tiles, survey_needs_tiles, write_tiles


def fit_seamless(sources: Sequence[str], options, output=None, outputs: Sequence[str] | None = None,
                 scheduler: str | None = None, jobs: int = 1,
                 on_tile: Callable[[dict], None] | None = None,
                 on_stage: Callable[[str], None] | None = None,
                 on_tile_pass: Callable[[str, int, int], None] | None = None) -> dict:
    """Fit the inputs as one survey; returns the report.

    output: one path for the whole survey's mesh (the fit of the concatenated cloud,
    written as `c1mesh fit` writes one input); or outputs: one path per input, each
    holding the triangles its input owns (module docstring), tiles run by
    distributed.run_tiles (scheduler, jobs). Progress: on_tile is called with each
    tile's report row as it is written (in-memory -O); on_stage after each stage
    (in-memory -o: pipeline.STAGES; in tiles: tiled_fit.TILED_STAGES). A LAS/LAZ survey
    larger than options.memory allows in one piece (survey_needs_tiles) goes to the
    memory-bounded fit (c1mesh.survey.tiled_fit; on_tile_pass(pass, tiles done, tiles) as each
    tile task finishes), which writes the one mesh, or splits it into the outputs by the
    same ownership rule (c1mesh.survey.tiled_outputs).
    """

    options, _ = resolve_axis(sources[0], options)     # LAS/LAZ surveys: z, as for one file
    user_crs = parse_crs(options.crs) if options.crs else None
    if survey_needs_tiles(sources, options):
        report = fit_tiled(list(sources), output, options, options.memory, on_stage=on_stage,
                           scheduler=scheduler, jobs=jobs, outputs=outputs, on_tile=on_tile_pass)
        if outputs is not None:
            report["ownership"] = "lowest-numbered corner point"
        return report
    if scheduler is not None and output is not None:
        raise InputError(f"--scheduler runs the tiles of --seamless -O, or of a fit larger than --memory "
                         f"allows; {sources[0]} is fitted in memory in one piece: drop --scheduler, "
                         "or use -O DIR")
    timer = _Timer(None)
    with timer.stage("read"):
        survey = load_survey(sources, options)
    if output is not None:
        report = fit(survey.cloud, output, options, on_stage=on_stage, keep_mesh=False).report
        report["input"] = list(survey.names)
        report["seconds"] = {"read": timer.seconds["read"], **report["seconds"]}
        return report
    options = with_plane_level(options)         # a height field: PLANE_LEVEL unless --level is given

    crs, crs_source = resolve_crs(survey.cloud.crs, user_crs, survey.names[0])
    model = build_surface(survey.cloud, options, timer)
    report = {"inputs": list(survey.names), "outputs": list(outputs),
              "points": {"read": len(survey.cloud), "kept": int(model.used.size)},
              "normals": model.normal_source,
              "frame": {"origin": model.frame.origin.tolist(), "axes": model.frame.axes.tolist()},
              "triangles": {"after_trim": model.trim_report.triangles_after,
                            "max_edge": model.trim_report.max_edge},
              "level": options.level, "ownership": "lowest-numbered corner point",
              "scheduler": scheduler or (f"{jobs} local processes" if jobs > 1 else "in process"),
              "crs": None if crs is None else {**describe(crs), "source": crs_source},
              "warnings": fit_warnings(len(survey.cloud), int(model.used.size),
                                       model.trim_report.triangles_before,
                                       model.trim_report.removed.get("long_edge", 0),
                                       model.trim_report.max_edge, auto_limit(options.max_edge))}
    tasks = plan_tiles(model, survey, outputs, options.level, options.ascii, crs)
    del model, survey               # the cloud and height field: the plan keeps what tiles need
    start = time.perf_counter()
    report["tiles"] = write_tiles(run_tiles(tasks, scheduler, jobs), tasks.outputs, ascii=options.ascii,
                                  on_tile=on_tile, crs=crs)
    timer.seconds["tiles"] = round(time.perf_counter() - start, 6)
    report["seconds"] = timer.seconds
    return report
