"""The fit of a LAS/LAZ survey larger than memory: tile by tile, streamed to one PLY.

    frame (stages.frame.frame_of_chunks), box → spill to tiles → per tile: normals → height field
    → buffered Delaunay + long-edge trim (one pass over all tiles: the auto max_edge is
    survey-wide) → sliver peel, bow-ties, curtains (c1mesh.survey.trim_runs) → the limiter's two noise floors
    (two passes: c1mesh.survey.halos.noise_floors)
    → per tile: limited gradients and edge directions from its halo, RSD interpolator on
    its owned triangles → refine → a part file → the parts joined in tile order into one
    vertex file and one face file → one mesh file

The "per tile" passes, the first read of every tile's halo and the noise floors'
residuals are tasks (distributed.TaskRunner: this process, -j local processes or a Dask
cluster) that read the spill files and write their results to files; the rest (frame,
spill, hull, the trim's peel and bow-tie rounds, the medians, the join) runs here.
Nothing of the output depends on where the tasks ran.

Every stage is the tile-local form of a whole-survey stage (c1mesh.stages.frame.frame_of_chunks,
tile_spill, tile_normals, buffered_delaunay, trim_runs, halos), so the surface
equals the in-memory fit of the same points with the same reduced options (below), to
rounding; nothing depends on the grid. The trim and the limiter run the stage functions
of c1mesh.stages.trim, .curtains and .limiter on each tile's halo; their module
docstrings say which function each step runs and which steps are survey-wide.

What the tiled path does differently from `pipeline.build_surface` (docs/tiles.md):

- normals are always estimated (the spill keeps no file normals): by default fitted to
  the heights as in memory (c1mesh.stages.height_gradients, tile by tile:
  tile_normals.tile_height_normals), with --gradients normals by PCA (tile_normals);
  colours and the CRS are carried;
- the height field drops points with unusable or too steep normals and exact duplicate
  positions (keeping the lowest-numbered point), and runs the stacking test of
  height_field.height_field survey-wide (height_runs.survey_stacking); the near-duplicate
  merge is not applied;
- the trim is the in-memory default (long edges, sliver peel, bow-ties, then curtains
  and what their holes expose), run over the tiles (`trim_tiles`, c1mesh.survey.trim_runs), so it
  is the same, not a reduction;
- the overshoot limiter (default; --overshoot off skips it) is the in-memory one, run
  tile by tile with the survey's noise floors (limiter.tile_limits; halos.TiledLimiter);
- a DEM's default fill spans the trim's holes as the in-memory fill does, with the long
  triangles found from the tiles' short ones (c1mesh.survey.hole_runs), its halos
  reading across them.

The rule for the one output: a base triangle belongs to the tile holding its
lowest-numbered corner point (buffered_delaunay); each tile refines only its own
triangles. A refined vertex that can lie in two tiles' outputs lies on the boundary of
both tiles' owned regions: a corner point, or a point on a base edge that only one owned
triangle of the tile has. Such vertices are numbered globally by a key that does not
depend on the tile — the survey number of a corner, (lower end, higher end, position from
the lower end) of an edge point — and written once, by the first tile that reaches them;
later tiles refer to that number (c1mesh.survey.join, which forgets a key once no later
tile can meet it). All other vertices are written by their only tile.
Edge points on a tile border are thus evaluated from the first tile's triangle, where
the whole-survey refinement uses the edge's owner triangle: the two agree to rounding
(the spline is continuous), which is the only difference.
"""
from __future__ import annotations

import contextlib
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.plan import DEFAULT_SMOOTH, DemPlan, FitPlan, TiledRun
from c1mesh.core.platform_memory import release_free_heap
from c1mesh.core.threads import workers as thread_count
from c1mesh.core.tile import bounds, corner_rows
from c1mesh.engine.refine import fewest_refined_vertices
from c1mesh.geo.contours import BYTES_PER_NODE
from c1mesh.geo.products import ContourRequest, add_contour_facts, level_for_mean_edge, side_length_sum
from c1mesh.geo.raster import check_angle_crs, fill_distance, mosaic_paths, tile_targets
from c1mesh.geo.preview import SplineView
from c1mesh.pipeline.bounded_dem import (DemGrid, DemJob, DemSupport, InputWindows, TiledDem, dem_grid,
                                         input_windows, vertex_box)
from c1mesh.pipeline.plan import default_smoothing
from c1mesh.pipeline.report import ReportCore, scheme_facts
from c1mesh.stages.curtains import view_rules_apply
from c1mesh.stages.frame import frame_of_chunks
from c1mesh.stages.height_gradients import check_positions, distinct_rows, use_height_gradients
from c1mesh.stages.lattice_mesh import (auto_spacing, check_cells_left, check_lattice_spacing, is_auto, lattice_offset,
                                        support_least_strength)
from c1mesh.stages.limiter import check_mode
from c1mesh.stages.smoothing import SmoothingControl, SmoothingRun, gradient_data_weight
from c1mesh.stages.surface import with_plane_level
from c1mesh.stages.trim import check_triangles_left
from c1mesh.stages.warnings import auto_limit, fit_warnings, smoothing_suggestion
from c1mesh.survey.buffered_delaunay import TileGrid
from c1mesh.survey.distributed import TaskRunner
from c1mesh.survey.ground_pass import GroundPass, ground_mask
from c1mesh.survey.height_runs import height_spill, survey_stacking
from c1mesh.survey.smoothing_runs import SmoothedFill, TiledSmoother, TiledSmoothing, WrappedSmoother
from c1mesh.survey.tile_spill import spill
from c1mesh.survey.halos import HaloCache, TiledLimiter, halo_reach, longest_final_edge
from c1mesh.survey.hole_runs import TiledFill
from c1mesh.survey.inputs import (
    CachedChunks,
    Colours,
    Temps,
    las_chunks,
    survey_crs,
    survey_name,
    survey_paths,
    tiled_classes,
)
from c1mesh.survey.split_outputs import InputOwners
from c1mesh.survey.sizing import TILE_SHARE, grid_side, point_bytes, points_per_tile, task_threads, tiles_at_once
from c1mesh.survey.refine_runs import MeshWriting, RefineJob, Split, TiledMesh, check_output_size, write_tiles
from c1mesh.survey.task_rows import TileRows, describe_crs
from c1mesh.survey.delaunay_runs import triangulate_tiles
from c1mesh.survey.lattice_runs import LATTICE_MARGIN, LatticeFill, lattice_halo, lattice_tiles
from c1mesh.survey.trim_runs import trim_tiles

TILED_STAGES = ("ground", "frame", "spill", "normals", "triangulate", "trim", "noise floors", "smoothing",
                "refine+write")
"""The stages fit_tiled reports (on_stage, the report's seconds), in order; "ground" only when the
ground filter chooses the points (survey.ground_pass), "noise floors"
only with the overshoot limiter (the default) of an exact fit, "smoothing" only with a
smoothing strength (c1mesh.survey.smoothing_runs); a DEM output (-o DEM.tif) has "raster"
(c1mesh.pipeline.bounded_dem) in place of "refine+write"."""


def fit_tiled(source, output, plan: FitPlan, run: TiledRun = TiledRun()) -> dict:
    """Fit a LAS/LAZ file tile by tile (module docstring) and write one mesh to output, or,
    with run.outputs (one path per input file, output None), each input's owned part of
    it (c1mesh.survey.split_outputs: `fit --seamless -O` beyond --memory).

    plan: the fit's core.plan.FitPlan (its memory, the budget in bytes, sizes the tiles;
    its axis resolved, normals not "file"); run: where the tiles run and whom they tell
    (core.plan.TiledRun). Returns the fit's facts (input, output, points, frame,
    triangles, gradients, level, output_mesh, warnings, crs, seconds, and the tiles' own:
    tiles, tile_tasks, scheduler, ...), which `tiles_report` makes
    the report of c1mesh.pipeline.report's schema.

    The per-tile passes (normals, triangulation, refinement) run as tasks
    (distributed.TaskRunner): here (jobs 1), on up to `jobs` local processes (as many
    as the budget lets hold a tile at once, `tiles_at_once`), or on the Dask cluster at
    `scheduler` (a tile at a time per worker thread), whose workers must see `directory`.
    jobs None: one local process per thread of the knob (plan.threads), one thread
    each; `c1mesh fit`'s default. Tiles in two processes beat one process with two
    threads at every size measured (docs/tiles.md), because most of a tile's
    stages run in one thread.
    The tiles are sized by the budget alone, so the output bytes do not depend on where
    the tasks ran or on how many ran at once. run.on_tile(pass,
    tiles done, tiles) is called as each tile's task of a pass finishes (progress).
    A smoothing strength runs the smoothing fit (c1mesh.survey.smoothing_runs,
    which then replaces the limiter but for edge directions; with --spacing its vertices
    on a lattice, c1mesh.survey.lattice_runs, and every height fitted).
    """
    level_from = "default" if plan.surface.level is None else "option"
    plan = with_plane_level(plan)
    _check_plan(plan)
    surface = plan.surface
    if surface.strength == DEFAULT_SMOOTH:          # the tiles' normals are estimated: the lattice fit
        strength, spacing = default_smoothing(surface.spacing, estimated=True)
        plan = replace(plan, surface=replace(surface, strength=strength, spacing=spacing))
        surface = plan.surface
    strength, memory = surface.strength, plan.memory
    select, selection, filtered = tiled_classes(source, plan.select)     # class 2 by default, else the filter
    # the tiles estimate their normals; their gradients come from the heights by default
    gradient_source = "heights" if use_height_gradients(plan.heights.gradients, "estimated") else "normals"
    paths = survey_paths(source)
    name = survey_name(paths)
    crs, crs_source = survey_crs(paths, plan.mesh.crs)
    if plan.dem is not None:
        check_angle_crs(crs, plan.dem)
    contours = _contour_request(plan, crs)    # GeoJSON needs an EPSG code: refused now, not after the fit
    outputs, jobs, scheduler = run.outputs, run.jobs, run.scheduler
    seconds, start = {}, time.perf_counter()

    def done(stage):
        nonlocal start
        release_free_heap()                 # a stage's freed heap would sit under the next one's peak
        seconds[stage] = round(time.perf_counter() - start, 3)
        start = time.perf_counter()
        if run.on_stage:
            run.on_stage(stage)

    if outputs is not None and len(outputs) != len(paths):
        raise ValueError("outputs must name one path per input file")
    target = outputs[0] if outputs is not None else output
    directory = run.directory
    if directory is None:
        directory = Path(target).parent if isinstance(target, (str, Path)) else Path(tempfile.gettempdir())
    temps = Temps(directory, Path(str(target)).name if isinstance(target, (str, Path)) else "c1mesh")
    file_counts: list[int] = []
    stack = contextlib.ExitStack()
    try:
        keep = None
        if filtered:                               # the filter's ground, tile by tile (survey.ground_pass)
            keep, facts = ground_mask(source, select.bounds, crs if crs_source == "file" else None,
                                      GroundPass(memory, run.per_tile, directory, temps.stem))
            selection.update({"points_read": int(len(keep)), "points_kept": int(keep.sum()), "filter": facts})
            done("ground")
        colours = Colours(temps)
        chunks = CachedChunks(las_chunks(source, select.classes, colours=colours,
                                         bounds=select.bounds, file_counts=file_counts, keep=keep), temps)
        axis = plan.heights.axis
        axis = "z" if isinstance(axis, str) and axis.strip().lower() == "auto" else axis
        frame = frame_of_chunks(chunks, axis)
        colours.finish()
        count, box, positions = _plane_box(chunks, frame)
        if is_auto(surface.spacing):               # the in-memory rule: the chosen points' box and count
            plan = replace(plan, surface=replace(surface, spacing=auto_spacing(box[:2], box[2:], count)))
            surface = plan.surface
        if surface.spacing is not None:            # every lattice node inside the tiles' box
            box = _grown_box(box, LATTICE_MARGIN * surface.spacing)
        _check_contour_grid(plan, box, name)
        if gradient_source == "heights":          # as the in-memory fit's height gradients say it
            check_positions(count, positions)
        elif count < 3:
            raise InputError(f"{name}: only {count} points" + (f" of class {list(select.classes)}"
                                                                 if select.classes else ""))
        per_point = point_bytes(surface)
        side = grid_side(count, memory, run.per_tile, per_point)
        grid = TileGrid(box, side, side)
        done("frame")
        if jobs is None:
            jobs = thread_count(plan.threads) if len(grid) > 1 else 1
        runner = stack.enter_context(TaskRunner(scheduler, jobs if scheduler else tiles_at_once(memory, jobs, per_point)))
        rows = TileRows(grid, task_threads(plan.threads, runner), run.on_tile)
        with spill((p for p, _ in chunks()), frame, grid, directory, temps.stem + ".raw") as raw:
            done("spill")
            height_pass = height_spill(raw, grid, count, plan.heights, directory, temps.stem, runner, rows)
        heights = height_pass.heights
        merged = height_pass.usable - int(heights.counts.sum())      # exact duplicates, one record kept
        try:
            spacing, stacked = survey_stacking(height_pass, grid, frame.axes[2], runner, rows.name, temps)
            data = lattice = lattice_facts = None
            if surface.spacing is not None:    # --spacing: the smoothing's vertices on a lattice, every height fitted
                check_lattice_spacing(surface.spacing, spacing)
                lattice = lattice_tiles(heights, surface.spacing, spacing, temps, temps.stem,
                                        lattice_offset(frame.origin, surface.spacing),
                                        fill=plan.dem is not None and plan.dem.fill is not None)
                data, heights = heights, stack.enter_context(contextlib.closing(lattice.nodes))
                lattice_facts = lattice.facts()
            done("normals")
            if lattice is None:
                max_edge, triangle_files, buffers, delaunay_count = triangulate_tiles(
                    heights, grid, surface.max_edge, temps, runner, rows, most=TILE_SHARE * points_per_tile(memory))
            else:                              # the lattice's cells: no Delaunay, no trim
                max_edge, triangle_files, buffers = None, lattice.shown_files, lattice.buffers
                delaunay_count = lattice.triangles
            long_edge = delaunay_count - _kept_count(triangle_files, lattice)
            done("triangulate")
            longest = max_edge if max_edge is not None else (
                math.sqrt(2.0) * surface.spacing if lattice is not None
                else longest_final_edge(heights, triangle_files, grid, buffers))
            halos = HaloCache(heights, triangle_files, grid, halo_reach(longest), temps)
            halos.prefetch(runner, rows.name, lambda t, row: rows.add(t, "halo", row))
            fitted = (2,) if filtered else select.classes        # the filter's ground counts as class 2
            fill = None                    # a DEM's fill: the whole triangulation, copied before the trim
            if plan.dem is not None and plan.dem.fill is not None and lattice is None:
                fill = TiledFill.prepare(halos, max_edge, memory, name, temps)
            removed, kept = ({}, None) if lattice is not None else \
                trim_tiles(halos, grid, temps, view_rules_apply(fitted, frame.axes), runner, rows.name)
            kept_triangles = _kept_count(triangle_files, lattice)
            if lattice is None:
                check_triangles_left(kept_triangles)
            else:
                check_cells_left(kept_triangles, lattice.grid)
            trimmed_mesh = TiledMesh(heights, grid, triangle_files, buffers, max_edge, frame)
            filled = None
            if fill is not None:           # the filled triangulation's halos in place of the trim's
                filled = fill.filled(triangle_files, heights, halos.reach, temps, (runner, rows.name))
                halos = HaloCache(heights, filled.files, grid, halos.reach, temps, "filled", far=filled.far)
                halos.prefetch(runner, rows.name)
                kept = None
            if plan.dem is None and plan.mesh.resolution is not None:     # --resolution of a mesh: its level
                level = level_for_mean_edge(_mean_edge(halos, triangle_files), plan.mesh.resolution)
                plan = replace(plan, surface=replace(surface, level=level))
                surface, level_from = plan.surface, "resolution"
            if outputs is None and output is not None and plan.dem is None:
                _check_size(kept_triangles, plan, output, colours.present)
            done("trim")
            mesh = trimmed_mesh if filled is None else replace(trimmed_mesh, files=filled.files, far=filled.far)
            limiter = None
            if strength is not None:       # fitted over the trimmed triangles; a fill spans the holes
                run_ = SmoothingRun(SmoothingControl(strength, surface.scheme, edf=surface.edf), spacing,
                                    surface.overshoot, gradient_data_weight("estimated", gradient_source))
                if lattice is not None:        # unit normal directions, no gradient data: as in memory
                    least = support_least_strength(surface.spacing, spacing, lattice.triangles,
                                                   int(data.counts.sum()))
                    run_ = replace(run_, control=replace(run_.control, least_strength=least, fold_net=True),
                                   overshoot="off", gradient_weight=0.0)
                fit = TiledSmoothing(run_, longest, data, 0.0 if lattice is None else lattice_halo(lattice.grid),
                                     None if lattice is None else lattice.grid)
                solved = trimmed_mesh if lattice is None else replace(trimmed_mesh, files=lattice.files)
                limiter = TiledSmoother(solved, fit, temps, runner, rows.name,
                                        on_done=lambda t, row: rows.add(t, "smoothing", row))
                if filled is not None:
                    limiter = SmoothedFill(limiter, halos, filled.spanning, temps, runner, rows.name)
                if lattice is not None and lattice.holes is not None and not lattice.holes.empty:   # hole_fill
                    limiter = LatticeFill(limiter, lattice, surface.scheme)
                done("smoothing")
            elif surface.overshoot == "limit":
                limiter = TiledLimiter(halos, temps, runner, rows.name, kept)
                done("noise floors")
            if plan.dem is not None:
                support = DemSupport(max_edge,
                                     filled.trimmed if filled is not None else None if lattice is None else lattice.kept,
                                     None if lattice is None else data)
                job = DemJob(RefineJob(mesh, surface, MeshWriting(temps, limiter), None, rows.threads), halos,
                             dem_grid(mesh, plan.dem.resolution), longest, _shaded(plan.dem), rows.threads, support)
                windows = None if outputs is None else _windows(job, chunks, file_counts, outputs, plan.dem)
                report = _write_dem(job, (temps, runner, rows, windows), plan.dem, (chunks, crs, contours), limiter)
                done("raster")
            else:
                split = None if outputs is None else Split(InputOwners(file_counts), outputs,
                                                           [str(p) for p in paths])
                drawn = _MeshDrawings.sample(plan, (mesh, halos, longest, limiter), contours,
                                             (temps, runner, rows))
                try:
                    report = write_tiles(mesh, plan, output, MeshWriting(temps, limiter, crs, colours, runner,
                                                                         rows, split))
                except BaseException:
                    drawn.discard()
                    raise
                done("refine+write")
                drawn.finish(report, crs, seconds)
        finally:
            height_pass.close()
    finally:
        stack.close()
        temps.close()
    kept = report.pop("kept")
    contour_facts = report.pop("contours", None)
    report.update({"input": str(paths[0]) if len(paths) == 1 else [str(p) for p in paths],
                   "output": str(output) if outputs is None else [str(o) for o in outputs],
                   "tiles": len(grid),
                   # a note, not a warning: the result is the in-memory fit's (docs/tiles.md)
                   "note": f"fitted in {len(grid)} tiles to stay within the memory budget (docs/tiles.md)",
                   "warnings": fit_warnings(count, _on_surface(kept, data, limiter), delaunay_count, long_edge,
                                            max_edge, auto_limit(surface.max_edge), merged=merged),
                   "points": {"read": count, "kept": kept, "stacked": stacked, "spacing": spacing},
                   "max_edge": max_edge,
                   "triangles": {"before_trim": delaunay_count,     # a fill's spanning triangles are no trim's
                                 "after_trim": sum(filled.trimmed) if filled is not None
                                 else kept_triangles if lattice is not None
                                 else sum(report["triangles_per_tile"].values()),
                                 "removed": {"long_edge": long_edge, **removed}, "max_edge": max_edge},
                   "gradients": gradient_source,
                   "level": None if plan.dem is not None else surface.level,
                   "level_from": None if plan.dem is not None else level_from, "scheduler": runner.kind,
                   "tile_tasks": rows.table(heights.counts, report.pop("triangles_per_tile")),
                   "seconds": seconds, "frame": {"origin": frame.origin.tolist(),
                                                 "axes": frame.axes.tolist()}})
    add_contour_facts(report, contour_facts)
    report["crs"] = describe_crs(crs, crs_source)
    report["classes"] = selection
    if strength is not None:
        report["smoothing"] = {**limiter.smoothing(), "lattice": lattice_facts}
    return report


def _shaded(dem: DemPlan) -> bool:
    """Whether the DEM's outputs need the spline's gradients (slope, aspect, hillshade, and
    the preview, which shades the cells by it as the in-memory fit's does)."""
    return bool(dem.slope or dem.aspect or dem.hillshade or dem.preview)


def _windows(job: DemJob, chunks, counts, outputs, dem: DemPlan) -> InputWindows:
    """--seamless -O DIR --suffix .tif: each input's DEM (outputs, one per input; counts:
    the points each holds) and side rasters DIR/NAME.KIND.tif on its window of the
    survey's grid, and the mosaics (the DEMs' DIR/mosaic.vrt; a side raster's its
    option's .vrt path), as pipeline.driver.fit_dem_tiles names them."""
    sides = {"slope": dem.slope, "aspect": dem.aspect, "hillshade": dem.hillshade, "support": dem.support}
    return InputWindows(list(outputs), [tile_targets(output, sides) for output in outputs],
                        input_windows(job, chunks, InputOwners(counts), len(outputs)), mosaic_paths(outputs, sides))


def _write_dem(job: DemJob, where, dem: DemPlan, inputs, limiter) -> dict:
    """The tiled DEM (c1mesh.pipeline.bounded_dem) of the trimmed survey, in place of the
    mesh's refinement: the facts write_tiles gives a mesh (kept, output_mesh null,
    triangles_per_tile, overshoot), the raster section and the contours' (None: none).
    where: (temps, runner, rows, the per-input DEMs' InputWindows or None); inputs: (the
    points' chunks, the CRS, the geo.products.ContourRequest or None)."""
    chunks, crs, contours = inputs
    temps, runner, rows, windows = where
    facts = TiledDem(job, temps, runner, rows, windows=windows).write(dem, chunks, crs,
                                                                     isinstance(limiter, (TiledSmoother, WrappedSmoother)),
                                                                     contours)
    report = {"kept": facts["kept"], "output_mesh": None, "triangles_per_tile": facts["triangles_per_tile"],
              "raster": facts["raster"], "contours": facts["contours"]}
    if limiter is not None:
        limiter.limited += facts["limited"]
        limiter.turned += facts["turned"]
        limiter.lifted += facts["lifted"]
        report["overshoot"] = limiter.report()
    return report


def _contour_request(plan: FitPlan, crs: str | None) -> ContourRequest | None:
    """The contours the plan asks for (a DEM's, or a mesh's), writing the fit's CRS
    (ContourRequest.with_crs: InputError for a GeoJSON whose CRS has no EPSG code)."""
    asked = plan.dem if plan.dem is not None else plan.products
    if asked is None or asked.contours is None:
        return None
    return ContourRequest(asked.contours, asked.interval).with_crs(crs, plan.mesh.crs)


class _MeshDrawings:
    """A mesh output's preview and contours in tiles (core.plan.MeshProducts): the tiles
    sample each one's grid before the mesh is written (pipeline.bounded_dem.TiledDem, as a
    DEM's cells), the contours are staged then and committed after the mesh, and the
    preview is drawn after it, as the in-memory fit orders them.

    The contours' grid is the in-memory one (geo.products.contour_grid): the aligned grid
    over the spline's vertices at --resolution, else at the mean output edge (the mean
    side of the kept triangles over the level: _mean_edge, whose last bit may differ from
    the in-memory sum's). The preview's is geo.preview.SplineView's."""

    def __init__(self, products, staged, facts: dict | None, preview):
        self.products, self.staged, self.facts, self.preview = products, staged, facts, preview

    @classmethod
    def sample(cls, plan: FitPlan, fitted, contours: ContourRequest | None, where) -> "_MeshDrawings":
        """Sample the grids: fitted (the TiledMesh, its HaloCache, the longest final edge,
        the limiter or smoother), where (temps, runner, rows)."""
        products = plan.products
        if products is None:
            return cls(None, None, None, None)
        mesh, halos, longest, limiter = fitted
        surfaces = RefineJob(mesh, plan.surface, MeshWriting(where[0], limiter), None, where[2].threads)

        def tiles(dem: DemGrid, gradients: bool, stage: str) -> TiledDem:
            return TiledDem(DemJob(surfaces, halos, dem, longest, gradients, where[2].threads), *where,
                            stage=stage)
        staged, facts, preview = None, None, None
        if contours is not None:
            step = plan.mesh.resolution or _mean_edge(halos, mesh.files) / plan.surface.level
            grid = dem_grid(mesh, step)
            _check_contour_grid(plan, (0.0, 0.0, grid.grid.width * step, grid.grid.height * step),
                                str(contours.path), step)
            staged, facts = tiles(grid, False, "contours").contours(contours)
        if products.preview is not None:
            try:
                view = SplineView.of(*vertex_box(mesh), mesh.frame)
                grid = DemGrid(view.grid, np.asarray(view.origin, dtype=np.float64))
                preview = (view, *tiles(grid, True, "preview").cells())
            except BaseException:
                if staged is not None:
                    staged.discard()
                raise
        return cls(products, staged, facts, preview)

    def discard(self) -> None:
        """Remove the staged contours (the mesh failed)."""
        if self.staged is not None:
            self.staged.discard()

    def finish(self, report: dict, crs: str | None, seconds: dict) -> None:
        """Commit the contours (their facts into report["contours"]) and draw the preview
        (its seconds into `seconds`)."""
        if self.staged is not None:
            self.staged.commit()
            report["contours"] = self.facts
        if self.preview is not None:
            start = time.perf_counter()
            view, z, g = self.preview
            view.render(z, g, self.products.preview, crs, 1.0 if self.products.z_factor is None
                        else self.products.z_factor)
            seconds["preview"] = round(time.perf_counter() - start, 6)


def _check_contour_grid(plan: FitPlan, box, name: str, step: float | None = None) -> None:
    """InputError when the contours' grid, on the box (x0, y0, x1, y1) of the points (frame
    units, the grid covers at most that and a cell around it) at its resolution (the DEM's
    or the mesh's --resolution; step: the mesh's grid step once known), needs more than
    the --memory budget for its tracing in one piece (geo.contours.BYTES_PER_NODE). No
    check while the step is not known yet."""
    asked = plan.dem if plan.dem is not None else plan.products
    if asked is None or asked.contours is None:
        return
    step = plan.dem.resolution if plan.dem is not None else plan.mesh.resolution if step is None else step
    if step is None:
        return
    x0, y0, x1, y1 = box
    nodes = ((x1 - x0) / step + 2) * ((y1 - y0) / step + 2)
    if nodes * BYTES_PER_NODE > plan.memory:
        raise InputError(f"{name}: contours traced on a grid of about {nodes / 1e6:.3g}M nodes at {step:g} need "
                         f"about {nodes * BYTES_PER_NODE / 1e6:.0f} MB, more than --memory "
                         f"{plan.memory / 1e6:.0f} MB; give a coarser --resolution, or raise --memory")


def _on_surface(kept: int, data, smoother) -> int:
    """The points the surface uses, for the unused-points warning: its vertices, or with
    --spacing (data: the height spill) the heights its triangles cover, as
    pipeline.driver.points_on_surface counts them in memory."""
    return kept if data is None else int(data.counts.sum()) - smoother.outside()


def _mean_edge(halos: HaloCache, triangle_files) -> float:
    """The mean side length of the survey's kept triangles (geo.products.mean_edge_length):
    each tile's own triangles' sum (side_length_sum, from its halo, which holds their
    corners), added exactly (math.fsum), over three sides a triangle. The in-memory sum
    rounds in another order, so the two means may differ in a last bit, and the level
    they round to only when the mean lies within that of a half-integer multiple of
    --resolution."""
    totals, sides = [], 0
    for t in halos.tiles():
        own = np.load(triangle_files[t]) if triangle_files[t] is not None else np.empty((0, 3), np.int64)
        if not len(own):
            continue
        halo = halos.halo(t)
        rows, local = corner_rows(halo.records["index"], own)
        totals.append(side_length_sum(np.column_stack([halo.records["x"][rows], halo.records["y"][rows]]), local))
        sides += 3 * len(own)
    return math.fsum(totals) / sides


def _check_size(triangles: int, plan: FitPlan, output, coloured: bool) -> None:
    """InputError, before the smoothing, the limiter and the refinement, when the output's
    format cannot hold the refined mesh of the survey's `triangles` kept triangles: its
    faces are exactly L² per triangle, its vertices at least refine.fewest_refined_vertices
    (the survey's edges are not counted here); write_tiles checks the exact counts as the
    tiles are joined."""
    level = plan.surface.level
    check_output_size(output, plan.mesh, fewest_refined_vertices(triangles, level), triangles * level ** 2,
                      coloured)


def _check_plan(plan: FitPlan) -> None:
    check_mode(plan.surface.overshoot)
    if plan.heights.normals == "file":
        raise InputError("the tiled fit estimates normals; --normals file needs the in-memory fit")


def _kept_count(triangle_files: list, lattice) -> int:
    """The triangles the tiles' files hold that are the surface's own: all of them, or on a
    lattice with a DEM's fill the support's (LatticeTiles.kept; the rest span its holes)."""
    if lattice is not None and lattice.kept is not None:
        return sum(lattice.kept)
    return sum(len(np.load(f, mmap_mode="r")) for f in triangle_files if f is not None)


def _grown_box(box: tuple, by: float) -> tuple[float, float, float, float]:
    """box (x0, y0, x1, y1) grown by `by` on every side."""
    return (box[0] - by, box[1] - by, box[2] + by, box[3] + by)


def _plane_box(chunks, frame) -> tuple[int, tuple[float, float, float, float], int]:
    """(point count, (x0, y0, x1, y1) box of the points in the frame's plane, distinct
    plane positions counted up to 3)."""
    count, low, high, seen = 0, np.full(2, np.inf), np.full(2, -np.inf), []
    for points, _ in chunks():
        if len(points):
            xy = frame.to_local(points)[:, :2]
            least, most = bounds(xy)         # column by column: numpy's row reduction is ~10x slower
            low, high = np.minimum(low, least), np.maximum(high, most)
            count += len(points)
            if len(seen) < 3:
                seen = distinct_rows(xy, 3, seen)
    return count, (float(low[0]), float(low[1]), float(high[0]), float(high[1])), len(seen)


def tiles_report(facts: dict, options) -> dict:
    """The report of a memory-bounded fit from the facts fit_tiled returns (consumed), in
    c1mesh.pipeline.report's schema. No one interpolator is held, so c1_certificate and
    pieces are null; its normals are always estimated (it refuses --normals file)."""
    level, level_from = facts.pop("level"), facts.pop("level_from")
    report = ReportCore(
        input=facts.pop("input"), output=facts.pop("output"), points=facts.pop("points"),
        normals="estimated", gradients=facts.pop("gradients"), frame={"kind": "axis", **facts.pop("frame")},
        triangles=facts.pop("triangles"), level=level,
        level_from=level_from,
        output_mesh=facts.pop("output_mesh"),
        scheme=scheme_facts(options.scheme), c1_certificate=None, pieces=None, warnings=facts.pop("warnings"),
        crs=facts.pop("crs"), seconds=facts.pop("seconds"), threads=thread_count(),
        z_factor=1.0 if options.z_factor is None else float(options.z_factor)).as_dict()
    report.update(facts)
    if options.resolution is not None:         # as geo.products.finish says it in memory
        report["resolution"] = options.resolution
    if "raster" in report:        # a DEM (pipeline.bounded_dem), as pipeline.driver.fill_facts says it
        distance = fill_distance(options.fill)
        spans = report["raster"].pop("fill", {}).get("triangles_spanning_holes", 0)
        report["raster"]["fill"] = {"option": options.fill, "triangles_spanning_holes": spans,
                                    "distance": None if distance is None else "inf" if math.isinf(distance) else distance}
    overshoot = report.get("overshoot")
    if "smoothing" not in report and overshoot:     # the advice of an exact fit, as in memory
        text = smoothing_suggestion(overshoot["gradients_limited"], int(report["points"]["kept"]))
        if text is not None:
            report["suggestion"] = text
    return report
