"""How the memory-bounded fit sizes itself: when a survey needs tiles, how many points a
tile holds, how many tiles run at once and with how many threads (c1mesh.pipeline.bounded_fit).

All of it follows from the --memory budget and the inputs' headers alone, so the grid,
and with it the output bytes, never depend on where or how many tasks run."""
from __future__ import annotations

import math

from c1mesh.core.errors import InputError
from c1mesh.core.outputs import LAS_FORMATS
from c1mesh.core.plan import DEFAULT_SMOOTH, FitPlan, SurfaceSettings
from c1mesh.core.threads import per_process
from c1mesh.formats.copc import points_to_read
from c1mesh.survey.inputs import survey_name, survey_paths

BYTES_PER_POINT = 1_800
"""Peak memory of the in-memory fit per input point (bytes). Measured: about 1.1 GB per
million points at level 4 with file normals, 1.36–1.78 GB at level 1 with estimated
normals (benchmarks; 1.78 GB: `c1mesh fit` of a 1M-point synthetic LAZ, --overshoot off);
the rule takes the upper end."""
SMOOTHING_BYTES_PER_POINT = 7_000
"""Peak memory per point of a smoothing fit whose vertices are the points (bytes): the
exact fit's BYTES_PER_POINT plus the sparse Cholesky factor and system, measured at
4.9 KB a vertex for smooth_fit at 100k and 300k vertices (peak RSS over the triangulated
input; the factor's fill grows like N log N) and 7 GB for the in-memory fit of 1M points."""


def point_bytes(surface: SurfaceSettings) -> int:
    """Peak bytes per input point of the fit `surface` asks for: SMOOTHING_BYTES_PER_POINT
    for a smoothing fit with a vertex at every point, else BYTES_PER_POINT (a --spacing
    fit's solve follows its lattice's nodes, not its points)."""
    if surface.strength not in (None, DEFAULT_SMOOTH) and surface.spacing is None:   # default: the lattice's
        return SMOOTHING_BYTES_PER_POINT
    return BYTES_PER_POINT


TILE_SHARE = 4
"""A tile's points may use at most 1 / TILE_SHARE of the budget at BYTES_PER_POINT: a tile
reads its buffer too (about twice its points for the normals and the triangulation) and
the parent's state (the interpreter, the join's band of border keys, the trim's removed
triangles) shares the rest."""
TILE_POINTS_CAP = 1_000_000
"""Largest tile (points): past this the halo's share of a tile's work is already small, and
a larger budget is better spent on more tiles in flight (`tiles_at_once`)."""


def fits_in_memory(point_count: int, memory: int | None, per_point: int = BYTES_PER_POINT) -> bool:
    """True when the in-memory fit of point_count points at per_point bytes each
    (point_bytes) stays within memory bytes (None: no budget given, always in memory)."""
    return memory is None or point_count * per_point <= memory


def points_per_tile(memory: int, per_point: int = BYTES_PER_POINT) -> int:
    """The points a tile may hold under a budget of memory bytes: 1 / TILE_SHARE of it at
    per_point bytes (point_bytes), at least 10,000 and at most TILE_POINTS_CAP. The share
    also covers a smoothing tile's halo (docs/smoothing.md: 1.1-1.3x its points)."""
    return max(10_000, min(TILE_POINTS_CAP, int(memory // (per_point * TILE_SHARE))))


def grid_side(count: int, memory: int, per_tile: int | None = None, per_point: int = BYTES_PER_POINT) -> int:
    """Tiles along each side of the square grid for count points, each holding at most
    points_per_tile(memory) points (per_tile overrides that, for tests). The grid, and so
    the output bytes, depend on the budget only, never on how many workers run the tiles."""
    return max(1, math.ceil(math.sqrt(count / (per_tile or points_per_tile(memory, per_point)))))


def tiles_at_once(memory: int, jobs: int, per_point: int = BYTES_PER_POINT) -> int:
    """How many of `jobs` local processes may each hold a tile at once within memory bytes.

    A tile task's peak is about its tile's points at BYTES_PER_POINT (the in-memory fit's
    rule; measured: a worker peaked at 207 MB on tiles of 69,444 points, 125 MB by the
    rule, its interpreter 100 MB of it), so half the budget goes to tasks in flight and
    the rest to the parent's survey-wide state: two at the default TILE_SHARE, more once
    a larger budget meets TILE_POINTS_CAP. Asking for more jobs than this runs this many."""
    task_bytes = points_per_tile(memory, per_point) * per_point
    return max(1, min(int(jobs), int(memory // (2 * task_bytes))))


def needs_tiles(source, plan: FitPlan) -> bool:
    """True when `source` (a LAS/LAZ/COPC path, by --input-format or else by its extension,
    as c1mesh.formats.read_cloud decides; or a list of them: one survey) holds more points,
    by the headers, than the in-memory fit can take within plan.memory bytes
    (point_bytes per point); then it is fitted by `fit_tiled`. Streams, other formats
    and fits without a budget are never tiled. Raises InputError when the input needs
    tiles but the plan asks for something the tiled fit does not do."""
    paths = survey_paths(source)
    if plan.memory is None or paths is None:
        return False
    fmt = plan.select.input_format          # as read_cloud: the given format, else the extension
    if any((fmt or path.suffix).lower().lstrip(".") not in LAS_FORMATS for path in paths):
        return False
    count = sum(points_to_read(path, plan.select.bounds) for path in paths)
    per_point = point_bytes(plan.surface)
    if fits_in_memory(count, plan.memory, per_point):
        return False
    need = f"{survey_name(paths)}: {count} points need about {count * per_point / 1e6:.0f} MB in " \
           f"one piece, more than --memory {plan.memory / 1e6:.0f} MB, so they are fitted in tiles"
    if plan.heights.normals == "file":
        raise InputError(f"{need}; the tiled fit estimates normals: drop --normals file, or raise --memory")
    return True


def task_threads(threads: int | None, runner) -> int | None:
    """Threads each tile task may use: the fit's (`threads`, the knob; None: the process's
    setting) in this process, shared by the local workers, one on a Dask worker."""
    if runner.scheduler is not None:
        return 1
    if runner.jobs == 1:
        return threads
    return per_process(threads, runner.jobs)
