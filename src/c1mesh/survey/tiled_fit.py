"""The fit of a LAS/LAZ survey larger than memory: tile by tile, streamed to one PLY.

    survey stats (frame, box) → spill to tiles → per tile: normals → height field
    → buffered Delaunay + long-edge trim (one pass over all tiles: the auto max_edge is
    survey-wide) → sliver peel, bow-ties, curtains (c1mesh.survey.tiled_trim) → the limiter's two noise floors
    (two passes: c1mesh.survey.tiled_limiter)
    → per tile: limited gradients and edge directions from its halo, RSD interpolator on
    its owned triangles → refine → a part file → the parts joined in tile order into one
    vertex file and one face file → one mesh file

The "per tile" passes, the first read of every tile's halo and the noise floors'
residuals are tasks (distributed.TaskRunner: this process, -j local processes or a Dask
cluster) that read the spill files and write their results to files; the rest (frame,
spill, hull, the trim's peel and bow-tie rounds, the medians, the join) runs here.
Nothing of the output depends on where the tasks ran.

Every stage is the tile-local form of a whole-survey stage (c1mesh.survey.survey_stats,
tile_spill, tile_normals, buffered_delaunay, tiled_limiter), so the surface equals the
in-memory fit of the same points with the same reduced options (below), to rounding;
nothing depends on the grid.

What the tiled path does differently from `pipeline.build_surface` (docs/tiles.md):

- normals are always estimated (the spill keeps no file normals): by default fitted to
  the heights as in memory (c1mesh.stages.height_gradients, tile by tile:
  tile_normals.tile_height_normals), with --gradients normals by PCA (tile_normals);
  colours and the CRS are carried;
- the height field drops points with unusable or too steep normals and exact duplicate
  positions (keeping the lowest-numbered point); the near-duplicate merge and the
  stacking test of frame.height_field are not applied;
- the trim is the in-memory default (long edges, sliver peel, bow-ties, then curtains
  and what their holes expose), run over the tiles (`_trim`, c1mesh.survey.tiled_trim), so it
  is the same, not a reduction;
- the overshoot limiter (default; --overshoot off skips it) is the in-memory one, run
  tile by tile with the survey's noise floors (c1mesh.survey.tiled_limiter).

The rule for the one output: a base triangle belongs to the tile holding its
lowest-numbered corner point (buffered_delaunay); each tile refines only its own
triangles. A refined vertex that can lie in two tiles' outputs lies on the boundary of
both tiles' owned regions: a corner point, or a point on a base edge that only one owned
triangle of the tile has. Such vertices are numbered globally by a key that does not
depend on the tile — the survey number of a corner, (lower end, higher end, position from
the lower end) of an edge point — and written once, by the first tile that reaches them;
later tiles refer to that number (c1mesh.survey.tiled_join, which forgets a key once no later
tile can meet it). All other vertices are written by their only tile.
Edge points on a tile border are thus evaluated from the first tile's triangle, where
the whole-survey refinement uses the edge's owner triangle: the two agree to rounding
(the spline is continuous), which is the only difference.
"""
from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.survey.tiles import task_row

BYTES_PER_POINT = 1_800
"""Peak memory of the in-memory fit per input point (bytes). Measured: about 1.1 GB per
million points at level 4 with file normals, 1.36–1.78 GB at level 1 with estimated
normals (benchmarks; 1.78 GB: `c1mesh fit` of a 1M-point synthetic LAZ, --overshoot off);
the rule takes the upper end."""
TILE_SHARE = 4
"""A tile's points may use at most 1 / TILE_SHARE of the budget at BYTES_PER_POINT: a tile
reads its buffer too (about twice its points for the normals and the triangulation) and
the parent's state (the interpreter, the join's band of border keys, the trim's removed
triangles) shares the rest."""
TILE_POINTS_CAP = 1_000_000
"""Largest tile (points): past this the halo's share of a tile's work is already small, and
a larger budget is better spent on more tiles in flight (`tiles_at_once`)."""
CHUNK = 1_000_000
"""Points per chunk read from a LAS/LAZ file."""
TILED_STAGES = ("frame", "spill", "normals", "triangulate", "trim", "noise floors", "refine+write")
"""The stages fit_tiled reports (on_stage, the report's seconds), in order; "noise floors"
only with the overshoot limiter (the default)."""
WRITE_BLOCK = 1 << 16
"""Vertices (faces) per block streamed from the joined files to the mesh writer, as the
PLY writer packs them: the writer holds a few blocks in flight (the block read, its
packed rows and up to four in its background queue, about 6 × 3.3 MB of coloured
vertices at this size), so with 1M-vertex (48 MB) blocks the write alone held well over
100 MB whatever the budget, and still about 40 MB at 256k."""

HEIGHT = np.dtype([("index", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                   ("gx", "<f8"), ("gy", "<f8")])
"""One height-field point in a spill: survey number, frame position, height, gradient."""
VERTEX = np.dtype([("v", "<f8", 3), ("n", "<f8", 3)])
VERTEX_RGB = np.dtype([("v", "<f8", 3), ("n", "<f8", 3), ("c", "u1", 3)])
"""One output vertex in the temporary vertex file: position, normal (world), colour."""


def fits_in_memory(point_count: int, memory: int | None) -> bool:
    """True when the in-memory fit of point_count points stays within memory bytes
    (None: no budget given, always in memory)."""
    return memory is None or point_count * BYTES_PER_POINT <= memory


def points_per_tile(memory: int) -> int:
    """The points a tile may hold under a budget of memory bytes: 1 / TILE_SHARE of it at
    BYTES_PER_POINT, at least 10,000 and at most TILE_POINTS_CAP."""
    return max(10_000, min(TILE_POINTS_CAP, int(memory // (BYTES_PER_POINT * TILE_SHARE))))


def grid_side(count: int, memory: int, per_tile: int | None = None) -> int:
    """Tiles along each side of the square grid for count points, each holding at most
    points_per_tile(memory) points (per_tile overrides that, for tests). The grid, and so
    the output bytes, depend on the budget only, never on how many workers run the tiles."""
    return max(1, math.ceil(math.sqrt(count / (per_tile or points_per_tile(memory)))))


def tiles_at_once(memory: int, jobs: int) -> int:
    """How many of `jobs` local processes may each hold a tile at once within memory bytes.

    A tile task's peak is about its tile's points at BYTES_PER_POINT (the in-memory fit's
    rule; measured: a worker peaked at 207 MB on tiles of 69,444 points, 125 MB by the
    rule, its interpreter 100 MB of it), so half the budget goes to tasks in flight and
    the rest to the parent's survey-wide state: two at the default TILE_SHARE, more once
    a larger budget meets TILE_POINTS_CAP. Asking for more jobs than this runs this many."""
    task_bytes = points_per_tile(memory) * BYTES_PER_POINT
    return max(1, min(int(jobs), int(memory // (2 * task_bytes))))


def needs_tiles(source, options) -> bool:
    """True when `source` (a LAS/LAZ path, or a list of them: one survey) holds more points,
    by the headers, than the in-memory fit can take within options.memory bytes
    (BYTES_PER_POINT per point); then it is fitted by `fit_tiled`. Streams, other formats
    and fits without a budget are never tiled. Raises InputError when the input needs
    tiles but the options ask for something the tiled fit does not do."""
    from c1mesh.formats.copc import points_to_read

    paths = survey_paths(source)
    if options.memory is None or paths is None:
        return False
    if any(path.suffix.lower() not in (".las", ".laz") for path in paths):
        return False
    count = sum(points_to_read(path, getattr(options, "bounds", None)) for path in paths)
    if fits_in_memory(count, options.memory):
        return False
    need = f"{survey_name(paths)}: {count} points need about {count * BYTES_PER_POINT / 1e6:.0f} MB in " \
           f"one piece, more than --memory {options.memory / 1e6:.0f} MB, so they are fitted in tiles"
    if options.resolution is not None or options.slope or options.aspect or options.hillshade or options.preview:
        raise InputError(f"{need}; rasters, --resolution and --preview need the in-memory fit "
                         "(raise --memory)")
    if options.normals == "file":
        raise InputError(f"{need}; the tiled fit estimates normals: drop --normals file, or raise --memory")
    return True


def survey_needs_tiles(sources: Sequence[str], options) -> bool:
    """Whether fit_seamless fits the survey in tiles (c1mesh.survey.tiled_fit): a LAS/LAZ survey
    larger than options.memory allows in one piece. Reads the inputs' headers only."""
    from c1mesh.stages.frame import resolve_axis

    options, _ = resolve_axis(sources[0], options)     # LAS/LAZ surveys: z, as for one file
    return needs_tiles(list(sources), options)


def survey_paths(source) -> list[Path] | None:
    """The files of a tiled fit's input: one path, or a list of paths read as one survey
    (`fit --seamless`); None for a stream or anything else."""
    if isinstance(source, (str, Path)):
        return [Path(source)]
    if isinstance(source, (list, tuple)) and source and all(isinstance(s, (str, Path)) for s in source):
        return [Path(s) for s in source]
    return None


def survey_name(paths: list[Path]) -> str:
    """How messages name a survey: its file, or its first file and the count."""
    return str(paths[0]) if len(paths) == 1 else f"{paths[0]} and {len(paths) - 1} more files"


class CachedChunks:
    """survey_stats.Chunks that decompress a source once: the first pass copies the world
    points (float64 x, y, z) to a hidden temporary file, later passes read that file (a
    LAZ decompression costs more than reading 24 bytes a point). Call close() to remove it."""

    def __init__(self, chunks: Callable, temps: "_Temps", chunk: int = CHUNK):
        self.source, self.chunk, self.path, self.complete = chunks, chunk, temps.new("points.bin"), False

    def __call__(self):
        if self.complete:
            return self._cached()
        return self._first()

    def _first(self):
        with open(self.path, "wb") as file:
            for points, normals in self.source():
                np.ascontiguousarray(points, dtype="<f8").tofile(file)
                yield points, normals
        self.complete = True

    def _cached(self):
        from c1mesh.survey.tile_spill import file_blocks

        with open(self.path, "rb") as file:
            for part in file_blocks(file, "<f8", 3 * self.chunk):
                yield part.reshape(-1, 3), None


def las_chunks(source, classes=None, chunk: int = CHUNK, colours: "Colours | None" = None,
               bounds=None, file_counts: list | None = None) -> Callable:
    """survey_stats.Chunks over a LAS/LAZ file, or over several read one after another as
    one survey: a callable giving a fresh iterator of (world points (m, 3), None) in file
    order, keeping only `classes` (None: all). colours: where each pass also sends the
    kept points' RGB, when every file has it (a survey has colours only if all its files
    do, as in c1mesh.survey.tiles.load_survey). bounds: only the points in this closed x/y box
    (formats.copc.Box), in file order: a COPC file decodes only the nodes meeting it.
    file_counts: a list each pass refills with the points it kept from each file."""
    import laspy

    from c1mesh.formats.copc import region_chunks

    paths = survey_paths(source)

    def dimensions(path):
        with laspy.open(str(path)) as reader:
            return set(reader.header.point_format.dimension_names)
    rgb_everywhere = colours is not None and all({"red", "green", "blue"} <= dimensions(p) for p in paths)

    def chunks():
        if file_counts is not None:
            file_counts.clear()
        for path in paths:
            kept = 0
            for part in region_chunks(path, bounds, chunk):
                keep = np.isin(np.asarray(part.classification), np.asarray(classes)) if classes else None
                xyz = _kept_columns(part, ("x", "y", "z"), keep, np.float64)
                if rgb_everywhere:
                    colours.add(_kept_columns(part, ("red", "green", "blue"), keep, np.uint16))
                del part                    # not held while the next chunk decodes
                kept += len(xyz)
                yield xyz, None
            if file_counts is not None:
                file_counts.append(kept)
    return chunks


def _kept_columns(part, names, keep, dtype) -> np.ndarray:
    """(m, len(names)) the named dimensions of a laspy record's rows `keep` (bool, or None:
    all), filled a column at a time: a whole-chunk (n, 3) copy and its filtered copy
    would be held at once, beside the decoded chunk and the one the reader still holds."""
    count = len(part) if keep is None else int(np.count_nonzero(keep))
    out = np.empty((count, len(names)), dtype=dtype)
    for i, name in enumerate(names):
        column = np.asarray(getattr(part, name) if name in ("x", "y", "z") else part[name])
        out[:, i] = column if keep is None else column[keep]
    return out


class Colours:
    """The survey's RGB by survey number, in a temporary file of uint16 (as LAS stores
    it), written on the first pass over the file; `of` gives uint8 colours by the
    in-memory reader's rule (formats._common.colors_to_uint8: 16-bit when any channel
    of the survey exceeds 255; no colours when all are zero)."""

    def __init__(self, temps: "_Temps"):
        self.path, self.count, self.largest, self._file = temps.new("colours.bin"), 0, 0, None
        self._done = False

    def add(self, rgb: np.ndarray) -> None:
        if self._done:
            return
        if self._file is None:
            self._file = open(self.path, "wb")
        np.ascontiguousarray(rgb, dtype="<u2").tofile(self._file)
        self.count += len(rgb)
        self.largest = max(self.largest, int(rgb.max(initial=0)))

    def finish(self) -> None:
        """Close the file after the first pass (later passes add nothing)."""
        if self._file is not None:
            self._file.close()
            self._file = None                   # picklable: tasks read the colours file
        self._done = True

    @property
    def present(self) -> bool:
        return self.count > 0 and self.largest > 0

    def of(self, survey: np.ndarray) -> np.ndarray | None:
        """(k, 3) uint8 colours of the points with these survey numbers, or None."""
        if not self.present:
            return None
        table = np.memmap(self.path, dtype="<u2", mode="r", shape=(self.count, 3))
        rgb = np.asarray(table[survey]).astype(np.int64)
        return (rgb >> 8 if self.largest > 255 else rgb).astype(np.uint8)


class _Temps:
    """Hidden temporary files registered for removal (c1mesh.core.outputs), removed on close."""

    def __init__(self, directory, stem: str):
        self.directory, self.stem, self.paths = Path(directory), stem, []

    def new(self, name: str) -> Path:
        from c1mesh.core.outputs import register_temp

        path = self.directory / f".{self.stem}.{name}-{os.getpid()}"
        register_temp(path)
        self.paths.append(path)
        return path

    def close(self) -> None:
        from c1mesh.core.outputs import unregister_temp

        for path in self.paths:
            if path.exists():
                path.unlink()
            unregister_temp(path)


def fit_tiled(source, output, options, memory: int, per_tile: int | None = None,
              on_stage: Callable[[str], None] | None = None, directory=None,
              scheduler: str | None = None, jobs: int = 1,
              on_tile: Callable[[str, int, int], None] | None = None,
              outputs: Sequence[str] | None = None) -> dict:
    """Fit a LAS/LAZ file tile by tile (module docstring) and write one mesh to output, or,
    with outputs (one path per input file, output None), each input's owned part of it
    (c1mesh.survey.tiled_outputs: `fit --seamless -O` beyond --memory).

    options: pipeline.FitOptions (classes, axis, k, max_slope, max_edge, scheme, level,
    overshoot, output_format, ascii; normals not "file"); memory: the
    budget in bytes, which sizes the tiles; per_tile: points per tile (overrides the
    budget, for tests); directory: where the temporary spill files go (default: beside a
    path output, else $TMPDIR). Returns the fit's facts (input, output, points, frame,
    triangles, gradients, level, output_mesh, warnings, crs, seconds, and the tiles' own:
    tiles, tile_tasks, scheduler, ...), which c1mesh.pipeline.survey_fit.tiled_report makes
    the report of c1mesh.pipeline.report's schema.

    The per-tile passes (normals, triangulation, refinement) run as tasks
    (distributed.TaskRunner): here (jobs 1), on up to `jobs` local processes (as many
    as the budget lets hold a tile at once, `tiles_at_once`), or on the Dask cluster at
    `scheduler` (a tile at a time per worker thread), whose workers must see `directory`.
    The tiles are sized by the budget alone, so the output bytes do not depend on where
    the tasks ran or on how many ran at once. on_tile(pass,
    tiles done, tiles) is called as each tile's task of a pass finishes (progress).
    """
    from c1mesh.survey.distributed import TaskRunner
    from c1mesh.survey.buffered_delaunay import TileGrid
    from c1mesh.survey.tiled_outputs import InputOwners
    from c1mesh.core.platform_memory import release_free_heap
    from c1mesh.survey.survey_stats import streamed_frame
    from c1mesh.survey.tile_spill import spill

    from c1mesh.stages.surface import with_plane_level

    options = with_plane_level(options)
    _check_options(options)
    paths = survey_paths(source)
    name = survey_name(paths)
    crs, crs_source = survey_crs(paths, options.crs)
    seconds, start = {}, time.perf_counter()

    def done(stage):
        nonlocal start
        release_free_heap()                 # a stage's freed heap would sit under the next one's peak
        seconds[stage] = round(time.perf_counter() - start, 3)
        start = time.perf_counter()
        if on_stage:
            on_stage(stage)

    if outputs is not None and len(outputs) != len(paths):
        raise ValueError("outputs must name one path per input file")
    target = outputs[0] if outputs is not None else output
    if directory is None:
        directory = Path(target).parent if isinstance(target, (str, Path)) else Path(tempfile.gettempdir())
    temps = _Temps(directory, Path(str(target)).name if isinstance(target, (str, Path)) else "c1mesh")
    file_counts: list[int] = []
    stack = contextlib.ExitStack()
    try:
        colours = Colours(temps)
        chunks = CachedChunks(las_chunks(source, options.classes, colours=colours,
                                         bounds=getattr(options, "bounds", None), file_counts=file_counts), temps)
        axis = "z" if isinstance(options.axis, str) and options.axis.strip().lower() == "auto" else options.axis
        frame = streamed_frame(chunks, axis)
        colours.finish()
        count, box = _plane_box(chunks, frame)
        if count < 3:
            raise InputError(f"{name}: only {count} points" + (f" of class {list(options.classes)}"
                                                                 if options.classes else ""))
        side = grid_side(count, memory, per_tile)
        grid = TileGrid(box, side, side)
        done("frame")
        runner = stack.enter_context(TaskRunner(scheduler, jobs if scheduler else tiles_at_once(memory, jobs)))
        rows = _TileRows(grid, _task_threads(options, runner), on_tile)
        with spill((p for p, _ in chunks()), frame, grid, directory, temps.stem + ".raw") as raw:
            done("spill")
            heights = _height_spill(raw, grid, count, options, directory, temps.stem, runner, rows)
        try:
            done("normals")
            max_edge, triangle_files, buffers, delaunay_count = _triangulate(heights, grid, options.max_edge,
                                                                             temps, runner, rows)
            long_edge = delaunay_count - sum(len(np.load(f, mmap_mode="r")) for f in triangle_files)
            done("triangulate")
            from c1mesh.survey.tiled_limiter import HaloCache, halo_reach, longest_final_edge

            longest = max_edge if max_edge is not None else longest_final_edge(heights, triangle_files,
                                                                                grid, buffers)
            halos = HaloCache(heights, triangle_files, grid, halo_reach(longest), temps)
            halos.prefetch(runner, rows.name, lambda t, row: rows.add(t, "halo", row))
            from c1mesh.stages.curtains import view_rules_apply
            removed = _trim(halos, grid, temps, view_rules_apply(options.classes, frame.axes))
            done("trim")
            limiter = None
            if options.overshoot == "limit":
                limiter = _Limiter(halos, temps, runner, rows.name)
                done("noise floors")
            split = None if outputs is None else _Split(InputOwners(file_counts), outputs,
                                                         [str(p) for p in paths])
            report = _write_tiles(heights, grid, triangle_files, buffers, max_edge, frame, options,
                                  output, temps, limiter, crs, colours, runner, rows, split)
            done("refine+write")
        finally:
            heights.close()
    finally:
        stack.close()
        temps.close()
    from c1mesh.stages.height_gradients import use_height_gradients
    from c1mesh.stages.warnings import auto_limit, fit_warnings
    kept = report.pop("kept")
    report.update({"input": str(paths[0]) if len(paths) == 1 else [str(p) for p in paths],
                   "output": str(output) if outputs is None else [str(o) for o in outputs],
                   "tiles": len(grid),
                   # a note, not a warning: the result is the in-memory fit's (docs/tiles.md)
                   "note": f"fitted in {len(grid)} tiles to stay within the memory budget (docs/tiles.md)",
                   "warnings": fit_warnings(count, kept, delaunay_count, long_edge, max_edge,
                                            auto_limit(options.max_edge)),
                   "points": {"read": count, "kept": kept}, "max_edge": max_edge,
                   "triangles": {"before_trim": delaunay_count,
                                 "after_trim": sum(report["triangles_per_tile"].values()),
                                 "removed": removed, "max_edge": max_edge},
                   "gradients": "heights" if use_height_gradients(getattr(options, "gradients", "auto"),
                                                                  "estimated") else "normals",
                   "level": options.level, "scheduler": runner.kind,
                   "tile_tasks": rows.table(heights.counts, report.pop("triangles_per_tile")),
                   "seconds": seconds, "frame": {"origin": frame.origin.tolist(),
                                                 "axes": frame.axes.tolist()}})
    report["crs"] = _describe_crs(crs, crs_source)
    return report


def survey_crs(source, user_crs) -> tuple[str | None, str | None]:
    """(CRS WKT, "file" | "option" | None) of a LAS/LAZ survey (one path or a list): the
    CRS its headers declare (c1mesh.survey.tiles.survey_crs: one for all files, InputError when
    two differ) and the user's --crs (WKT or any c1mesh.core.crs.parse_crs input) resolved as
    the in-memory fit does (InputError when they differ)."""
    import laspy

    from c1mesh.core.crs import las_crs, parse_crs, resolve
    from c1mesh.survey.tiles import survey_crs as common_crs

    paths = survey_paths(source)
    declared = []
    for path in paths:
        with laspy.open(str(path)) as reader:
            declared.append(las_crs(reader.header))
    file_crs = common_crs([str(p) for p in paths], declared)
    return resolve(file_crs, parse_crs(user_crs) if user_crs else None, survey_name(paths))


def _describe_crs(crs, crs_source) -> dict | None:
    from c1mesh.core.crs import describe

    facts = describe(crs)
    if facts is not None:
        facts["source"] = crs_source
    return facts


def _check_options(options) -> None:
    from c1mesh.stages.limiter import check_mode

    check_mode(options.overshoot)
    if options.normals == "file":
        raise InputError("the tiled fit estimates normals; --normals file needs the in-memory fit")


def _plane_box(chunks, frame) -> tuple[int, tuple[float, float, float, float]]:
    """(point count, (x0, y0, x1, y1) box of the points in the frame's plane)."""
    count, low, high = 0, np.full(2, np.inf), np.full(2, -np.inf)
    for points, _ in chunks():
        if len(points):
            xy = frame.to_local(points)[:, :2]
            low, high = np.minimum(low, xy.min(axis=0)), np.maximum(high, xy.max(axis=0))
            count += len(points)
    return count, (float(low[0]), float(low[1]), float(high[0]), float(high[1]))


def _height_spill(raw, grid, count: int, options, directory, stem: str, runner, rows: "_TileRows"):
    """Per tile: normals of its own points (tile_normals), then its height-field points
    (usable, not too steep, exact duplicate positions dropped), spilled to a new TileSpill
    of HEIGHT records (entered; the caller closes it). Each tile is a task (`_tile_heights`)
    that reads the raw spill and writes its own height file, run by runner
    (distributed.TaskRunner)."""
    from c1mesh.survey.buffered_delaunay import INITIAL_SPACINGS, mean_spacing
    from c1mesh.stages.height_gradients import height_neighbours, use_height_gradients
    from c1mesh.survey.tile_spill import TileSpill

    heights = TileSpill(grid, directory, stem + ".height", record=HEIGHT).__enter__()
    try:
        job = _HeightJob(raw, grid, options.k, height_neighbours(options.k), math.cos(math.radians(options.max_slope)),
                         INITIAL_SPACINGS * mean_spacing(grid.box, count),
                         use_height_gradients(getattr(options, "gradients", "auto"), "estimated"),
                         rows.threads)
        tiles = [t for t in range(len(grid)) if raw.counts[t]]
        for i, row in runner.map(_tile_heights, len(tiles), lambda i: (job, tiles[i], heights.paths[tiles[i]]),
                                 lambda i: rows.name(tiles[i])):
            heights.counts[tiles[i]] = row.pop("points")
            rows.add(tiles[i], "normals", row)
    except BaseException:
        heights.close()
        raise
    return heights


class _HeightJob:
    """What every tile's normals task shares (picklable): raw the raw TileSpill, the grid,
    k (PCA neighbours), height_k (height-fit neighbours), cos_max (steepest normal
    allowed), buffer (first read buffer, frame units), from_heights (normals fitted to the
    heights, else PCA), threads per task (None: the process's setting)."""

    def __init__(self, raw, grid, k, height_k, cos_max, buffer, from_heights, threads):
        self.raw, self.grid, self.k, self.height_k, self.cos_max = raw, grid, k, height_k, cos_max
        self.buffer, self.from_heights, self.threads = buffer, from_heights, threads

    def read3(self, rect):
        records = self.raw.records(rect)
        return records["index"], np.column_stack([records["x"], records["y"], records["z"]])


def _tile_heights(job: _HeightJob, t: int, path) -> dict:
    """One tile's height-field records (HEIGHT) written to path; returns its report row
    (points written, seconds, worker)."""
    from c1mesh.stages.frame import normal_gradients
    from c1mesh.core.threads import limit
    from c1mesh.survey.tile_normals import tile_height_normals, tile_normals

    start = time.perf_counter()
    with limit(job.threads):
        if job.from_heights:
            result = tile_height_normals(job.read3, job.grid, t, job.height_k, job.buffer)
        else:
            result = tile_normals(job.read3, job.grid, t, job.k, job.buffer, towards=(0.0, 0.0, 1.0))
        own = job.raw.tile(t)                                     # survey order, as result.index
        normals = result.normals
        length = np.linalg.norm(normals, axis=1)
        usable = np.isfinite(length) & (length > 0)
        usable[usable] &= np.abs(normals[usable, 2] / length[usable]) >= job.cos_max
        own, normals = own[usable], normals[usable]
        first = _first_of_positions(own["x"], own["y"])
        own, normals = own[first], normals[first]
        gradients, _ = normal_gradients(normals)
        records = np.empty(len(own), HEIGHT)
        for name in ("index", "x", "y", "z"):
            records[name] = own[name]
        records["gx"], records["gy"] = gradients[:, 0], gradients[:, 1]
        with open(path, "wb") as file:
            records.tofile(file)
    return task_row(len(records), start)


class _TileRows:
    """The per-tile report rows of a tiled fit: for each tile, what each pass's task did
    (seconds, worker), its height-field points and its final triangles; threads: the
    threads each task may use (None: the process's setting)."""

    def __init__(self, grid, threads, on_tile=None):
        self.grid, self.threads, self.on_tile = grid, threads, on_tile
        self.passes: dict[int, dict] = {}

    def name(self, t: int) -> str:
        """How a message names tile t: its number and cell (frame units)."""
        x0, y0, x1, y1 = self.grid.cell(t)
        return f"{t} (cell {x0:.2f}..{x1:.2f} x {y0:.2f}..{y1:.2f})"

    def add(self, t: int, stage: str, row: dict) -> None:
        self.passes.setdefault(t, {})[stage] = row
        if self.on_tile:
            done = sum(stage in passes for passes in self.passes.values())
            self.on_tile(stage, done, len(self.grid))

    def table(self, points: np.ndarray, triangles: dict) -> list[dict]:
        """One row per tile: tile, cell, points (height field), triangles (owned final
        base triangles), seconds (all its tasks), worker (of its last task), and per pass
        the seconds, worker and its peak RSS so far (MB)."""
        out = []
        for t in range(len(self.grid)):
            passes = self.passes.get(t, {})
            last = list(passes.values())[-1] if passes else {}
            out.append({"tile": t, "cell": [round(c, 6) for c in self.grid.cell(t)],
                        "points": int(points[t]), "triangles": int(triangles.get(t, 0)),
                        "seconds": round(sum(p["seconds"] for p in passes.values()), 3),
                        "worker": last.get("worker"),
                        "passes": {k: {key: p[key] for key in ("seconds", "worker", "worker_peak_mb")}
                                   for k, p in passes.items()}})
        return out


def _task_threads(options, runner) -> int | None:
    """Threads each tile task may use: the fit's (options.workers; None: the process's
    setting) in this process, shared by the local workers, one on a Dask worker."""
    from c1mesh.core.threads import per_process

    if runner.scheduler is not None:
        return 1
    if runner.jobs == 1:
        return options.workers
    return per_process(options.workers, runner.jobs)


def _first_of_positions(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Ascending indices of the first point (lowest index) at each distinct (x, y)."""
    order = np.lexsort((np.arange(len(x)), y, x))
    new = np.ones(len(x), dtype=bool)
    new[1:] = (x[order][1:] != x[order][:-1]) | (y[order][1:] != y[order][:-1])
    return np.sort(order[new])


def _triangulate(heights, grid, max_edge, temps, runner, rows: _TileRows):
    """The survey's Delaunay triangulation with the long-edge trim, each tile a task
    (`_tile_delaunay`, `_tile_trimmed`) that reads the height spill and writes its owned
    triangles to a file: (max_edge or None, per tile a .npy file of its owned triangles
    (survey numbers), per tile the buffer its corners lie within, the triangle count of
    the whole Delaunay triangulation: 2n - 2 - h by Euler's formula, n points and h hull
    corners, exact unless points lie on the hull between its corners)."""
    from c1mesh.survey.buffered_delaunay import INITIAL_SPACINGS, mean_spacing, streamed_hull, trimmed_delaunay

    count = int(heights.counts.sum())
    if count < 3:
        raise InputError(f"only {count} points are left for the height field; need at least 3")
    hull = streamed_hull((r["index"], np.column_stack([r["x"], r["y"]]))
                         for r in (heights.tile(t) for t in range(len(grid))))
    files = [temps.new(f"triangles-{t}.npy") for t in range(len(grid))]
    buffers = np.zeros(len(grid))
    if max_edge is None:
        first = INITIAL_SPACINGS * mean_spacing(grid.box, count)
        for t, (buffer, row) in runner.map(_tile_delaunay, len(grid),
                                           lambda t: (heights, grid, t, first, hull, files[t], rows.threads),
                                           rows.name):
            buffers[t] = buffer
            rows.add(t, "triangulate", row)
        return None, files, buffers, 2 * count - 2 - len(hull.index)
    longest = [temps.new(f"longest-{t}.npy") for t in range(len(grid))]
    shorts = [temps.new(f"short-{t}.npy") for t in range(len(grid))]

    def passes(bound):
        for t, (buffer, row) in runner.map(
                _tile_trimmed, len(grid),
                lambda t: (heights, grid, t, bound, hull, files[t], longest[t], shorts[t], rows.threads),
                rows.name):
            buffers[t] = buffer
            rows.add(t, "triangulate", row)
            yield shorts[t], t
    limit, _ = trimmed_delaunay(heights.read, grid, count, hull, max_edge, passes=passes)
    for t in range(len(grid)):
        triangles = np.load(files[t])
        short = np.load(longest[t]) <= limit
        if not short.all():
            _save(files[t], triangles[short])
    return limit, files, buffers, 2 * count - 2 - len(hull.index)


def _save(path, array: np.ndarray) -> None:
    with open(path, "wb") as file:
        np.save(file, array)


def _tile_delaunay(heights, grid, t: int, buffer: float, hull, path, threads) -> tuple[float, dict]:
    """Tile t's final triangles (buffered_delaunay.tile_triangles) saved to path (.npy);
    returns (its buffer, its report row)."""
    from c1mesh.survey.buffered_delaunay import tile_triangles
    from c1mesh.core.threads import limit

    start = time.perf_counter()
    with limit(threads):
        result = tile_triangles(heights.read, grid, t, buffer, hull)
    _save(path, result.triangles)
    return result.buffer, task_row(result.read, start)


def _tile_trimmed(heights, grid, t: int, bound: float, hull, path, longest_path, short_path, threads):
    """Tile t's triangles with edges up to bound (buffered_delaunay.tile_pass) saved to
    path, their longest edges to longest_path, its certified short edge lengths to
    short_path (the survey's would grow the parent by 24 bytes a point:
    buffered_delaunay.short_median reads them back a tile at a time); returns (its
    buffer, its report row)."""
    from c1mesh.survey.buffered_delaunay import tile_pass
    from c1mesh.core.threads import limit

    start = time.perf_counter()
    with limit(threads):
        result = tile_pass(heights.read, grid, t, bound, hull)
    _save(path, result.triangles)
    _save(longest_path, result.longest)
    _save(short_path, result.short)
    return result.buffer, task_row(result.read, start)


def _trim(halos, grid, temps, view_rules: bool = True) -> dict[str, int]:
    """The in-memory default trim after the long-edge rule, over the tiles
    (c1mesh.survey.tiled_trim): trim's sliver peel and bow-tie removal, then curtains
    (c1mesh.stages.curtains) with the survey's noise floor, then the peel and bow-tie removal
    of the holes they left, as pipeline.build_surface runs them. halos: the
    tiled_limiter.HaloCache, whose `removed` grows as triangles go (each halo drops them
    as it loads); the removed triangles also leave their tiles' files. Returns the
    removed counts by reason (as TrimReport.removed). view_rules: curtains.view_rules_apply."""
    
    from c1mesh.stages.curtains import REASONS
    from c1mesh.survey.tiled_limiter import edge_floor
    from c1mesh.survey.tiled_trim import curtain_cuts, thin_triangles
    from c1mesh.stages.trim import MIN_CIRCLE_RATIO as min_ratio
    thin, boundary, tiles = [np.empty((0, 3), np.int64)], [np.empty(0, bool)], [np.empty((0, 3), np.int64)]
    for t in halos.tiles():
        triangles, on_boundary, corners = thin_triangles(halos.halo(t), min_ratio, grid)
        thin.append(triangles)
        boundary.append(on_boundary)
        tiles.append(corners)
    state = _TrimState(halos, grid, np.concatenate(thin), np.concatenate(tiles))
    state.settle(np.concatenate(boundary), set(halos.tiles()))
    floor = edge_floor(halos.halos, temps, "curtains")
    cut, corners, counts = [np.empty((0, 3), np.int64)], [np.empty((0, 3), np.int64)], {r: 0 for r in REASONS}
    for t in halos.tiles():
        triangles, where, reasons = curtain_cuts(halos.halo(t), floor, grid, view_rules)
        cut.append(triangles)
        corners.append(where)
        for reason, count in reasons.items():
            counts[reason] += count
    cut, corners = np.concatenate(cut), np.concatenate(corners)
    state.remove(cut, corners)
    state.settle(state.next_to(cut), set(np.unique(corners).tolist()))
    state.write_files()
    return {"sliver": state.sliver, "bowtie": state.bowtie, **counts}


class _TrimState:
    """What the tiled trim has removed so far. thin (k, 3): every thin triangle of the
    survey after the long-edge rule (survey numbers; peeling only ever removes those),
    tiles (k, 3) the tile of each corner; `alive` marks those still in the mesh."""

    def __init__(self, halos, grid, thin: np.ndarray, tiles: np.ndarray):
        self.halos, self.grid, self.thin, self.tiles = halos, grid, thin, tiles
        self.alive = np.ones(len(thin), dtype=bool)
        self.sliver = self.bowtie = 0

    def remove(self, triangles: np.ndarray, tiles: np.ndarray) -> None:
        """Remove triangles (k, 3) whose corners lie in tiles (k, 3); a thin one (a
        bow-tie fan's or a curtain) can then no longer be peeled. The halo cache keeps
        them by owner tile (HaloCache.removed)."""
        from c1mesh.survey.tiled_trim import drop_triangles, owner_tiles

        if len(triangles):                  # compares only rows sharing a lowest corner with a thin one
            kept = drop_triangles(np.column_stack([self.thin, np.arange(len(self.thin))]), triangles)
            still = np.zeros(len(self.thin), dtype=bool)
            still[kept[:, 3]] = True
            self.alive &= still
        owners = owner_tiles(triangles, tiles)
        order = np.argsort(owners, kind="stable")
        tile_numbers, starts = np.unique(owners[order], return_index=True)
        for t, group in zip(tile_numbers.tolist(), np.split(triangles[order], starts[1:])):
            earlier = self.halos.removed.get(t)
            self.halos.removed[t] = group if earlier is None else np.concatenate([earlier, group])

    def next_to(self, triangles: np.ndarray) -> np.ndarray:
        """(k,) bool: the thin triangles sharing an edge with one of triangles."""
        from c1mesh.survey.tiled_trim import touching

        return touching(self.thin, triangles)

    def settle(self, front: np.ndarray, pending: set) -> None:
        """trim's loop: peel the live thin components that hold a live `front` triangle
        (k,) bool, then cut bow-ties, peel from the cuts' neighbours, until no bow-tie is
        left (trim.trim). A bow-tie can only appear at a corner of a removed
        triangle, so a round looks only at the tiles holding such corners: `pending`
        (tile numbers) for the first, those of the triangles removed since, later."""
        from c1mesh.survey.tiled_trim import bowtie_cuts, peeled

        while True:
            live = np.flatnonzero(self.alive)
            gone = live[peeled(self.thin[live], front[live])]
            self.alive[gone] = False
            self.sliver += len(gone)
            self.remove(self.thin[gone], self.tiles[gone])
            pending |= set(np.unique(self.tiles[gone]).tolist())
            cut, corners = [np.empty((0, 3), np.int64)], [np.empty((0, 3), np.int64)]
            for t in sorted(pending & set(self.halos.tiles())):
                triangles, where = bowtie_cuts(self.halos.halo(t), self.grid)
                cut.append(triangles)
                corners.append(where)
            cut, corners = np.concatenate(cut), np.concatenate(corners)
            if not len(cut):
                return
            self.bowtie += len(cut)
            self.remove(cut, corners)
            front, pending = self.next_to(cut), set(np.unique(corners).tolist())

    def write_files(self) -> None:
        """Drop the removed triangles from their owners' triangle files and the cached halos."""
        from c1mesh.survey.tiled_trim import drop_triangles

        for t, removed in self.halos.removed.items():
            triangles = np.load(self.halos.files[t])
            with open(self.halos.files[t], "wb") as file:
                np.save(file, drop_triangles(triangles, removed))
        self.halos.prune()


class _Limiter:
    """The overshoot limiter over the tiles (c1mesh.survey.tiled_limiter): the survey's noise
    floors, found on construction; a refinement task (`_refine_tile`) limits its tile's
    data from the cached halo (halos, picklable) and these floors."""

    def __init__(self, halos, temps, runner=None, name=str):
        from c1mesh.survey.distributed import TaskRunner
        from c1mesh.survey.tiled_limiter import noise_floors_on

        self.halos = halos
        self.floors = noise_floors_on(halos, temps, runner or TaskRunner(), name)
        self.limited = self.turned = self.lifted = 0

    def tile(self, tile: int, triangles: np.ndarray):
        """tiled_limiter.TileLimits of the tile's own triangles (survey numbers)."""
        from c1mesh.survey.tiled_limiter import tile_limits

        return tile_limits(self.halos.halo(tile), triangles, self.floors)

    def report(self) -> dict:
        return {"gradients_limited": self.limited, "directions_changed": self.turned,
                "heights_reconciled": self.lifted,
                "noise_floors": [self.floors.first, self.floors.second]}


class _RefineJob:
    """What every tile's refinement task shares (picklable; the files it names are read
    by the task): the height spill, grid, per tile its triangle file and buffer, max_edge,
    frame, options, limiter (None: --overshoot off), colours, threads per task, owners
    (tiled_outputs.InputOwners, with -O: each part then records its faces' owner inputs)."""

    def __init__(self, heights, grid, triangle_files, buffers, max_edge, frame, options, limiter, colours, threads,
                 owners=None):
        from c1mesh.survey.tiled_join import KeyExpiry

        self.heights, self.grid, self.files, self.buffers = heights, grid, triangle_files, buffers
        self.max_edge, self.frame, self.scheme, self.level = max_edge, frame, options.scheme, options.level
        self.limiter, self.colours, self.threads, self.owners = limiter, colours, threads, owners
        self.expiry = KeyExpiry(grid, [self.reach(t) for t in range(len(grid))])

    def reach(self, t: int) -> float:
        """How far beyond its cell the corners of tile t's own triangles lie (frame units):
        the trim's max_edge, else its Delaunay buffer, with a relative margin for rounding."""
        return (self.max_edge if self.max_edge is not None else self.buffers[t]) * (1 + 1e-9)

    def tile_data(self, t: int, triangles: np.ndarray):
        """(records (c,) of the corners, triangles (k, 3) into them, gradients or None,
        directions or None, limited, turned, lifted) of tile t's own triangles (survey numbers)."""
        if self.limiter is not None:
            limits = self.limiter.tile(t, triangles)
            return (limits.records, limits.triangles, limits.gradients, limits.directions,
                    limits.limited, limits.turned, limits.lifted)
        from c1mesh.survey.tiled_limiter import halo_rows

        records = self.heights.records(self.grid.grown(t, self.reach(t)))
        corners, local = np.unique(triangles, return_inverse=True)
        rows = halo_rows(records["index"], corners)
        if np.any(rows < 0):
            raise RuntimeError(f"tile {t}: a corner point lies outside the rectangle it read")
        return records[rows], local.reshape(triangles.shape), None, None, 0, 0, 0


class _Part:
    """The temporary files of one tile's refinement: vertices (all of its refinement's
    output points, VERTEX or VERTEX_RGB), faces (int64 triples, tile-local numbers), keys
    (.npz: the border keys of `tiled_join.border_keys`, their points and last tiles),
    owners (int32 per face, with -O: tiled_outputs.face_owners)."""

    def __init__(self, temps, t: int):
        self.vertices, self.faces = temps.new(f"part-{t}.vertices"), temps.new(f"part-{t}.faces")
        self.keys, self.owners = temps.new(f"part-{t}.keys"), temps.new(f"part-{t}.owners")

    def remove(self) -> None:
        for path in (self.vertices, self.faces, self.keys, self.owners):
            path.unlink(missing_ok=True)


def _refine_tile(job: _RefineJob, t: int, part: _Part) -> dict | None:
    """Refine tile t's own triangles into its part files; returns its report row with
    vertices, corners (input points among them, first), faces, triangles, limited,
    turned, lifted, or None for a tile without triangles."""
    from c1mesh.core.threads import limit

    start = time.perf_counter()
    triangles = np.load(job.files[t])
    if not len(triangles):
        return None
    with limit(job.threads):
        records, local, gradients, directions, limited, turned, lifted = job.tile_data(t, triangles)
        colors = None if job.colours is None else job.colours.of(records["index"])
        counts = _write_part(records, local, job.frame, job.scheme, job.level, part, gradients, directions, colors,
                             job.expiry)
        if job.owners is not None:
            from c1mesh.survey.tiled_outputs import face_owners

            owner = face_owners(job.owners, triangles, job.level)
            if len(owner) != counts["faces"]:
                raise RuntimeError(f"tile {t}: {counts['faces']} faces, {len(owner)} owners")
            owner.astype("<i4").tofile(part.owners)
    return {**counts, "triangles": len(triangles), "limited": limited, "turned": turned, "lifted": lifted,
            **task_row(len(records), start)}


def _write_tiles(heights, grid, triangle_files, buffers, max_edge, frame, options, output, temps,
                 limiter: "_Limiter | None" = None, crs: str | None = None,
                 colours: Colours | None = None, runner=None, rows: "_TileRows | None" = None,
                 split: "_Split | None" = None) -> dict:
    """Refine each tile's owned triangles (a task per tile, `_refine_tile`, writing part
    files), then join the parts in tile order, numbering shared vertices globally (module
    docstring), into one vertex and one face file; then write the mesh from them, or with
    split (-O), each input's part of it (c1mesh.survey.tiled_outputs)."""
    from c1mesh.core.cloud import MeshStream
    from c1mesh.survey.distributed import TaskRunner
    from c1mesh.formats import write_mesh
    from c1mesh.core.threads import blas_threads
    from c1mesh.survey.tile_spill import file_blocks
    from c1mesh.survey.tiled_join import PartJoin

    runner = runner or TaskRunner()
    rows = rows or _TileRows(grid, options.workers)
    coloured = colours is not None and colours.present
    job = _RefineJob(heights, grid, triangle_files, buffers, max_edge, frame, options, limiter,
                     colours if coloured else None, rows.threads, None if split is None else split.owners)
    tiles = [t for t in range(len(grid)) if triangle_files[t] is not None]
    parts = {t: _Part(temps, t) for t in tiles}
    vertex_path, face_path, owner_path = temps.new("vertices.bin"), temps.new("faces.bin"), temps.new("owners.bin")
    join = PartJoin(VERTEX_RGB if coloured else VERTEX)
    triangles_per_tile, ready, next_tile = {}, {}, 0
    with open(vertex_path, "wb") as vertex_file, open(face_path, "wb") as face_file, \
            open(owner_path, "wb") as owner_file:
        for i, row in runner.map(_refine_tile, len(tiles), lambda i: (job, tiles[i], parts[tiles[i]]),
                                 lambda i: rows.name(tiles[i])):
            ready[i] = row
            while next_tile in ready:                       # join in tile order, as soon as possible
                t, row = tiles[next_tile], ready.pop(next_tile)
                if row is not None:
                    join.add(t, parts[t], row, vertex_file, face_file)
                    if split is not None:
                        with open(parts[t].owners, "rb") as owners:
                            shutil.copyfileobj(owners, owner_file)
                    triangles_per_tile[t] = row["triangles"]
                    if limiter is not None:
                        limiter.limited += row["limited"]
                        limiter.turned += row["turned"]
                        limiter.lifted += row["lifted"]
                    rows.add(t, "refine", {k: row[k] for k in ("seconds", "worker", "worker_peak_mb")})
                parts[t].remove()
                join.passed(t)
                next_tile += 1
    written, faces = join.written, join.faces
    if faces == 0:
        raise InputError("no triangles are left after trimming; try --max-edge none")
    report = {"kept": join.kept, "output_mesh": {"vertices": written, "faces": faces},
              "shared_vertex_keys": join.keys,
              "shared_vertex_keys_held": join.shared.peak, "triangles_per_tile": triangles_per_tile}
    if limiter is not None:
        report["overshoot"] = limiter.report()
    if split is not None:
        report["output_meshes"] = split.write(vertex_path, VERTEX_RGB if coloured else VERTEX, face_path, owner_path,
                                        temps, options, crs)
        return report
    block = WRITE_BLOCK

    def vertex_blocks():
        with open(vertex_path, "rb") as file:
            for part in file_blocks(file, VERTEX_RGB if coloured else VERTEX, block):
                yield part["v"], part["n"], part["c"] if coloured else None

    def face_blocks():
        with open(face_path, "rb") as file:
            for part in file_blocks(file, "<i8", 3 * block):
                yield part.reshape(-1, 3)
    with blas_threads(1):
        write_mesh(MeshStream(written, faces, True, 3 if coloured else 0, vertex_blocks, face_blocks), output,
                   options.output_format, ascii=options.ascii, crs=crs)
    return report


@dataclass
class _Split:
    """-O: the survey's owner inputs (tiled_outputs.InputOwners), one output path and one
    name per input."""

    owners: object
    outputs: Sequence[str]
    names: Sequence[str]

    def write(self, vertex_path, dtype, face_path, owner_path, temps, options, crs) -> list[dict]:
        """Split the joined faces by owner and write every input's mesh (all or nothing)."""
        from c1mesh.survey.tiled_outputs import split_faces, write_outputs

        paths = split_faces(face_path, owner_path, len(self.outputs), temps)
        return write_outputs(vertex_path, dtype, paths, self.outputs, options, crs, self.names)


def _write_part(records, triangles, frame, scheme, level, part: _Part, gradients=None, directions=None,
                colors=None, expiry=None) -> dict:
    """Refine one tile's owned triangles (triangles (T, 3) into records, survey order) and
    write all its output points (world position, normal, colour), its faces (tile-local
    numbers) and its border keys to its part files; returns {vertices, corners, faces}.
    gradients (n, 2) and directions (E, 2): the limiter's (None: the records' gradients,
    unit-normal directions); colors (n, 3) uint8 of the records, or None; expiry: the
    tiled_join.KeyExpiry that gives each border key its last tile."""
    from c1mesh.engine.interpolator import RSDInterpolator
    from c1mesh.stages.surface import surface_stream
    from c1mesh.survey.tiled_join import border_keys

    xy = np.column_stack([records["x"], records["y"]])
    if gradients is None:
        gradients = np.column_stack([records["gx"], records["gy"]])
    interp = RSDInterpolator(xy, records["z"], gradients, triangles=triangles, scheme=scheme,
                             directions=directions)
    refinement = interp.refinement(level)
    with open(part.keys, "wb") as file:
        np.savez(file, **border_keys(refinement, records["index"], xy, expiry))
    stream = surface_stream(refinement, frame, colors)
    with open(part.vertices, "wb") as file:
        for vertices, normals, blended in stream.vertex_blocks():
            out = np.empty(len(vertices), VERTEX if colors is None else VERTEX_RGB)
            out["v"], out["n"] = vertices, normals
            if colors is not None:
                out["c"] = blended
            out.tofile(file)
    with open(part.faces, "wb") as file:
        for faces in stream.face_blocks():
            np.asarray(faces, dtype="<i8").tofile(file)
    return {"vertices": int(refinement.vertex_count), "corners": len(records), "faces": int(stream.face_count)}
