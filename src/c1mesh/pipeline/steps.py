"""The steps every whole-input fit shares once its frame is chosen, the axis (height-field)
and the perspective (depth-frame) fit alike: compact the vertices, interpolate with the
overshoot limiter, refine and write the surface, count its pieces, and the stage timer and
names the reports use. pipeline.driver and pipeline.depth_fit both import them from here.
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from c1mesh.core.plan import MeshTarget
from c1mesh.core.cloud import MeshStream, SurfaceMesh
from c1mesh.core.threads import blas_threads, parallel_blocks
from c1mesh.core.tile import Tile
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.engine.topology import edge_table
from c1mesh.formats import check_mesh_size, write_mesh
from c1mesh.pipeline import _steps as kernel
from c1mesh.stages.limiter import LimiterReport, control_overshoot
from c1mesh.stages.smoothing import SmoothingData, SmoothingRun, smooth_tile
from c1mesh.stages.surface import surface_stream


@dataclass
class FitResult:
    mesh: SurfaceMesh
    report: dict = field(default_factory=dict)


@dataclass(frozen=True)
class FitRun:
    """What a fit's report says of the run itself, whatever the path: source and output
    (paths or streams, shown by display_name), the options, the cloud read, the stage
    timer, z_factor (x, y units per height unit for angles; None: unknown) and the crs
    facts (pipeline.report.crs_facts; None: no CRS)."""

    source: object
    output: object
    options: object
    cloud: object
    timer: "StageTimer"
    z_factor: float | None
    crs: dict | None


class StageTimer:
    """Per-stage wall-clock timings, plus an optional progress callback per finished stage."""

    def __init__(self, on_stage: Callable[[str], None] | None):
        self.seconds: dict[str, float] = {}
        self.on_stage = on_stage

    def move(self, source: str, target: str, seconds: float) -> None:
        """Book `seconds` measured inside stage `source` to stage `target` instead."""
        self.seconds[source] = round(self.seconds[source] - seconds, 6)
        self.seconds[target] = round(self.seconds[target] + seconds, 6)

    @contextmanager
    def stage(self, name: str):
        start = time.perf_counter()
        yield
        self.seconds[name] = round(time.perf_counter() - start, 6)
        if self.on_stage:
            self.on_stage(name)


def compact_vertices(xy, triangles):
    """Drop points no triangle uses; returns (used point indices (n',) ascending, as
    np.unique gives them, and the triangles (T, 3) re-indexed into them). The kernel
    (pipeline/_steps.pyx) marks and numbers in one thread, then re-indexes blocks of
    triangles in the thread knob's threads."""
    tri = np.ascontiguousarray(triangles, dtype=np.int64).reshape(-1, 3)
    if tri.size and (tri.min() < 0 or tri.max() >= xy.shape[0]):
        raise ValueError(f"triangle indices must lie in [0, {xy.shape[0]}), got {tri.min()}..{tri.max()}")
    remap = np.full(xy.shape[0], -1, dtype=np.int64)
    local = np.empty(tri.shape, dtype=np.int64)
    kernel.number_used(tri, remap)
    parallel_blocks(lambda part: kernel.renumber_rows(tri, remap, local, part.start, part.stop), tri.shape[0])
    return np.flatnonzero(remap >= 0), local.reshape(np.shape(triangles))


def limited_interpolator(points, values, gradients, triangles, scheme, overshoot: str,
                         heights: bool = True, table=None) -> tuple[RSDInterpolator, Any]:
    """The RSDInterpolator of a (noisy) height field with its overshoot controlled
    (c1mesh.stages.limiter.control_overshoot in mode `overshoot`: its values are the reconciled
    heights), the edges numbered once for both; and the limiter's report. Shared by the
    plane and the perspective fits (these pass heights=False; control_overshoot says why, and
    so do plane fits of heights in units of their own, `_plan_heights`). table: the
    topology.EdgeTable of the triangles when already built (trim.TrimmedMesh.edge_table)."""
    if table is None and overshoot != "off":
        table = edge_table(triangles, points.shape[0])
    values, limited, directions, report = control_overshoot(points, values, gradients, triangles,
                                                            overshoot, table, heights=heights)
    interp = RSDInterpolator(points, values, limited, triangles=triangles, scheme=scheme,
                             directions=directions, edge_table=table)
    return interp, report


def smoothed_interpolator(tile: Tile, run: SmoothingRun, data: SmoothingData | None = None,
                          table=None, lattice=None) -> tuple[RSDInterpolator, Any, Any]:
    """The RSDInterpolator of the smoothing fit of a height field, its limiter report and
    the SmoothFit: the smoothing stage's run (c1mesh.stages.smoothing.smooth_tile) on the
    in-memory fit's one tile, as a survey fitted in tiles runs it on each of its tiles.

    tile: core.tile.Tile.whole of the vertices (n, 2), their heights and gradients and
    the triangles (T, 3) over them, every vertex a corner; run: the stage's SmoothingRun
    (strength, scheme, spacing, overshoot: of its remedies only the edge directions apply,
    and the weight of the vertices' gradients as data, smoothing.gradient_data_weight);
    data: None, the vertices' heights, else what the in-memory fit alone may fit
    (--spacing: every point's height at its position). table: the triangles'
    topology.edge_table when built already (the trim's), else built here. lattice: where the
    vertices are lattice nodes (stages.lattice_solver.Lattice: solved by multigrid), else None.
    """
    table = edge_table(tile.triangles, len(tile.records)) if table is None else table
    smoothed = smooth_tile(tile, run, table=table, data=data, lattice=lattice)
    interp = RSDInterpolator(tile.points, smoothed.values, smoothed.gradients, triangles=tile.triangles,
                             scheme=run.control.scheme, directions=smoothed.directions, edge_table=table)
    return interp, LimiterReport(directions_changed=smoothed.solve.turned), smoothed.fit


@dataclass(frozen=True)
class WorldSurface:
    """A spline ready to refine into world coordinates: interp (the RSDInterpolator),
    frame (stages.frame.ScanFrame or stages.perspective.PerspectiveFrame: surface_stream),
    colors ((n, 3) uint8 of interp's vertices, or None)."""

    interp: RSDInterpolator
    frame: Any
    colors: np.ndarray | None = None


def write_surface(surface: WorldSurface, output, target: MeshTarget, level: int, timer: StageTimer,
                  keep_mesh: bool, faces_facing: Callable[[MeshStream], MeshStream] | None = None):
    """The refine and write stages of a whole-input fit, the same for every frame.

    Refines the surface at `level` into world coordinates through its frame, optionally
    passes the stream through faces_facing (the perspective fit turns its faces to the
    viewpoint), and writes it to output (path, stream or None) as target says (format,
    ascii, crs: None for none); InputError, before anything is evaluated, when the
    output's format cannot hold the refined mesh (formats.check_mesh_size). keep_mesh=False
    with an output streams block by block (the mesh is then None; the time the writer
    waited for evaluated blocks is booked to "refine"). Returns (mesh or None, the MeshStream).
    """
    streaming = output is not None and not keep_mesh
    with timer.stage("refine"):
        stream = surface_stream(surface.interp.refinement(level), surface.frame, surface.colors)
        if output is not None:      # the counts are known now: refuse before evaluating (formats' limits)
            check_mesh_size(output, target.format, stream)
        if faces_facing is not None:
            stream = faces_facing(stream)
        mesh = None if streaming else stream.materialize()
    with timer.stage("write"):
        if output is not None:
            evaluating = _StopWatch()
            with blas_threads(1 if streaming else None):    # its idle pool spins on the writer's core
                write_mesh(evaluating.wrap(stream) if streaming else mesh, output, target.format,
                           ascii=target.ascii, crs=target.crs)
    if streaming:
        timer.move("write", "refine", evaluating.seconds)
    return mesh, stream


def mesh_pieces(xy: np.ndarray, triangles: np.ndarray, table=None) -> dict:
    """Connected pieces (through shared edges) of a triangulation, and area kept.

    xy (n, 2) plane points, every one used by some triangle (as after compact_vertices);
    triangles (T, 3); table: their topology.EdgeTable when already built (the
    interpolator has one). Returns {"count", "largest_fraction" (of the triangles),
    "area_fraction" (triangulated area / convex hull area of the points)}. Each slot's
    edge names its owner triangle, so a union-find joins every triangle to the owners of
    its edges without a sort (kernel: pipeline/_steps.pyx); the hull is taken over the
    boundary vertices, which hold its corners.
    """
    table = edge_table(triangles, xy.shape[0]) if table is None else table
    count_t = triangles.shape[0]
    scratch = np.empty((2, count_t), dtype=np.int64)
    count, largest = kernel.pieces(np.ascontiguousarray(table.tri_edge, dtype=np.int64),
                                   np.ascontiguousarray(table.owner, dtype=np.int64), *scratch)
    area = _triangulated_area(xy, triangles)
    rim = np.unique(table.edges[table.count == 1])            # the hull's corners are among these
    hull = hull_area(xy[rim])
    return {"count": int(count),
            "largest_fraction": float(largest / count_t),
            "area_fraction": float(area / hull) if hull > 0 else 1.0}


def hull_area(xy: np.ndarray) -> float:
    """The area of the convex hull of points xy (n, 2) (kernel: pipeline/_steps.pyx,
    Andrew's monotone chain over the points sorted by x, then y; 0 for fewer than 3
    points or points on one line). Our own so that a plain fit imports no scipy."""
    order = np.lexsort((xy[:, 1], xy[:, 0]))
    x, y = np.ascontiguousarray(xy[order, 0], dtype=np.float64), np.ascontiguousarray(xy[order, 1], dtype=np.float64)
    return float(kernel.hull_area(x, y, np.empty(2 * len(order) + 1, dtype=np.int64)))


AREA_BLOCK = 1 << 16
"""Triangles per block of the area kernel, run in the thread knob's threads."""


def _triangulated_area(xy: np.ndarray, triangles: np.ndarray) -> float:
    """Sum of the triangles' areas (xy's unit squared): twice each area by the kernel
    (pipeline/_steps.pyx) over fixed blocks in the thread knob's threads, summed by numpy
    (its pairwise sum, the same at any thread count), halved."""
    x, y = (np.ascontiguousarray(xy[:, k], dtype=np.float64) for k in range(2))
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    doubled = np.empty(tri.shape[0])
    parallel_blocks(lambda part: kernel.doubled_areas(x, y, tri, doubled, part.start, part.stop),
                    tri.shape[0], AREA_BLOCK)
    return 0.5 * float(doubled.sum())


class _StopWatch:
    """Accumulates the time a MeshStream spends producing blocks (not the writer's time)."""

    def __init__(self):
        self.seconds = 0.0

    def wrap(self, stream: MeshStream) -> MeshStream:
        return replace(stream, vertex_blocks=self._timed(stream.vertex_blocks),
                       face_blocks=self._timed(stream.face_blocks))

    def _timed(self, blocks: Callable[[], Iterator]) -> Callable[[], Iterator]:
        def timed():
            iterator = blocks()
            while True:
                start = time.perf_counter()
                item = next(iterator, None)
                self.seconds += time.perf_counter() - start
                if item is None:
                    return
                yield item
        return timed


def display_name(obj) -> str | None:
    """How the report names an input or output: its path, a stream's name, or None."""
    if obj is None:
        return None
    if isinstance(obj, (str, Path)):
        return str(obj)
    return getattr(obj, "name", "<stream>")
