"""One survey from many files: the seamless fit, its tiles and the ownership rule.

`c1mesh fit A.laz B.laz ... --seamless` treats the inputs as one point cloud: they are
concatenated in the order given and fitted by the same stages as a single file
(pipeline.build_surface), so the frame, the auto --max-edge, the normals near borders
and the Delaunay triangulation are those of the whole survey and cannot depend on how
the survey was cut into files.

Ownership rule: every base triangle belongs to exactly one input, the input that holds
the triangle's lowest-numbered corner point (points numbered in concatenation order).
Each input's output holds the refined triangles of the base triangles it owns.

Tiles: the refinement of one input's triangles is an independent task (`TileTask`,
`run_tile`): the RSD spline on a triangle depends only on its corner data (values,
gradients) and the direction shared by each of its edges, all of which the task carries.
Points on an edge shared by two tiles are evaluated, as in the whole-survey refinement,
by the edge's owner triangle (topology.EdgeTable: lowest slot, then lowest triangle), so
each task also carries the "halo" — the other tiles' triangles across its border edges —
and keeps the triangles in survey order: both tiles then evaluate a border point from the
same triangle with the same arithmetic, and the border vertices of the two outputs are
bit-identical. Merging exactly equal vertices of all outputs gives the whole-survey mesh.
"""
from __future__ import annotations

import contextlib
import os
import socket
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from c1mesh.core.cloud import PointCloud, SurfaceMesh
from c1mesh.core.crs import esri_wkt, prj_path, same_crs
from c1mesh.core.errors import InputError
from c1mesh.core.outputs import mesh_format, plan_outputs, register_temp, unregister_temp
from c1mesh.core.plan import PointSelection
from c1mesh.core.platform_memory import peak_rss_mb
from c1mesh.core.threads import blas_threads
from c1mesh.core.tile import row_min
from c1mesh.engine.refine import Refinement
from c1mesh.engine.rsd import VertexData
from c1mesh.engine.schemes import NAMED_TUPLES, get_scheme
from c1mesh.engine.topology import edge_table, triangle_neighbours
from c1mesh.formats import PRJ_SIDECAR, read_cloud, write_mesh
from c1mesh.formats.las import no_class_error
from c1mesh.stages.ground import choose_points
from c1mesh.stages.surface import surface_stream


@dataclass
class Survey:
    """Inputs concatenated into one cloud.

    cloud: all points, in input order; names: (n_inputs,) input names; offsets:
    (n_inputs + 1,) int64, input i holds cloud points [offsets[i], offsets[i + 1]).
    """

    cloud: PointCloud
    names: list[str]
    offsets: np.ndarray

    def input_of(self, point_index: np.ndarray) -> np.ndarray:
        """The input (0-based) holding each cloud point index."""
        return np.searchsorted(self.offsets[1:], point_index, side="right")


def _choose_survey_points(clouds: list, choice) -> tuple[list, dict | None]:
    """(the clouds restricted to the survey's chosen points, the report's "classes"):
    c1mesh.stages.ground.choose_points over the whole survey at once, so that "auto" takes
    class 2 from every file when any file has it, and the ground filter otherwise, run
    over all files together (it sees across their edges, as in one file)."""
    if any(c.classification is None for c in clouds) or not clouds:
        return clouds, None
    classification = np.concatenate([c.classification for c in clouds])
    points = np.concatenate([c.points for c in clouds])
    keep, selection = choose_points(classification, points, clouds[0].crs, choice)
    if keep is None:
        return clouds, selection
    ends = np.cumsum([len(c) for c in clouds])[:-1]
    return [c.subset(part) for c, part in zip(clouds, np.split(keep, ends))], selection


def load_survey(sources: Sequence[str], select: PointSelection, normals: str = "auto") -> Survey:
    """Read every input (keeping the points select.classes chooses: codes, or "auto",
    "all", "filter" as stages.ground.choose_points reads them; within select.bounds) and
    concatenate them in order.

    An input without points of the wanted classes contributes none (a survey may have
    tiles of water); the survey as a whole must have points. Normals are kept only when
    every input has them (else they are estimated survey-wide; normals "file" asks for
    them: InputError naming an input without); colours only when every input has them
    with the same channel count.
    """
    clouds, found = [], set()
    for source in sources:
        cloud = read_cloud(source, select.input_format, bounds=select.bounds)
        if isinstance(select.classes, tuple):
            if cloud.classification is None:
                raise InputError(f"{source}: --classes needs a classification field (LAS/LAZ)")
            found.update(np.unique(cloud.classification).tolist())
            cloud = cloud.subset(np.isin(cloud.classification, np.asarray(select.classes)))
        clouds.append(cloud)
    clouds, selection = _choose_survey_points(clouds, select.classes)
    counts = np.array([len(c) for c in clouds], dtype=np.int64)
    if counts.sum() == 0 and found:                  # the words of the one-file reader
        raise no_class_error(list(select.classes), found, select.bounds is not None)
    if counts.sum() == 0:
        raise InputError(("the input has no points" if len(sources) == 1 else "the inputs have no points")
                         + (" inside --bounds" if select.bounds else ""))
    if normals == "file" and any(c.normals is None for c in clouds):
        missing = next(s for s, c in zip(sources, clouds) if c.normals is None)
        raise InputError(f"{missing}: the input has no normals; use --normals estimate (or auto)")
    normals = _concatenate([c.normals for c in clouds])
    colors = _concatenate([c.colors for c in clouds])
    classification = _concatenate([c.classification for c in clouds])
    cloud = PointCloud(np.concatenate([c.points for c in clouds]), normals, colors, classification,
                       crs=survey_crs(sources, [c.crs for c in clouds]),
                       height_column=survey_height_column(sources, clouds), selection=selection)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    return Survey(cloud, [str(s) for s in sources], offsets)


def survey_height_column(sources: Sequence[str], clouds: Sequence[PointCloud]) -> str | None:
    """The header height column the inputs name (PointCloud.height_column), one for the
    survey, so a survey of such tables is fitted in plan units like one of them; None when
    none names one; InputError when only some do, since then the heights of some inputs would
    be fitted in a common metric with x and y, and others not."""
    named = [c.height_column for c in clouds]
    if any(named) and not all(named):
        with_column = next(s for s, name in zip(sources, named) if name)
        without = next(s for s, name in zip(sources, named) if not name)
        raise InputError(f"'{with_column}' names a height column and '{without}' does not: the heights "
                         "would be fitted in different units; give every input the same header")
    return named[0]


def survey_crs(sources: Sequence[str], crs_list: Sequence[str | None]) -> str | None:
    """The CRS (WKT) the inputs declare, one for the survey: inputs without one take it;
    InputError naming two inputs that declare different ones (c1mesh does not reproject)."""
    declared = [(source, crs) for source, crs in zip(sources, crs_list) if crs]
    for source, crs in declared[1:]:
        if not same_crs(crs, declared[0][1]):
            raise InputError(f"'{source}' and '{declared[0][0]}' declare different CRSs; c1mesh "
                             "does not reproject: reproject the tiles to one CRS first (e.g. pdal translate)")
    return declared[0][1] if declared else None


def _concatenate(arrays: list) -> np.ndarray | None:
    """The arrays stacked, or None unless every input has one of the same width."""
    if any(a is None for a in arrays) or len({a.shape[1:] for a in arrays}) != 1:
        return None
    return np.concatenate(arrays)


def triangle_owners(model, survey: Survey) -> np.ndarray:
    """(T,) the input owning each base triangle: the one holding its lowest-numbered corner.

    model.used and model.hf.source_index are ascending, so the lowest triangle index is
    also the lowest cloud index.
    """
    triangles = model.interp.triangles
    cloud_index = model.hf.source_index[model.used]
    return survey.input_of(cloud_index[row_min(triangles)])


@dataclass
class TileTask:
    """Everything one tile's refinement needs (picklable: it travels to Dask workers).

    vertices: the rsd.VertexData (local frame) of the tile's n corner points (owned and
    halo triangles), in survey order; colors (n, c) uint8 or None;
    triangles (t, 3) into those points, in survey order; coefficients (t, 21) and
    G (t, 3, 2): the survey interpolator's rows for them; owned (t,) bool: the triangles
    whose refinement this tile outputs (the rest is the halo); frame: the survey's
    ScanFrame; scheme: a scheme name or ShapeTuple; input_points: the input's point count;
    ascii: write ASCII PLY; crs: the survey's CRS (WKT) for the PLY header, or None.
    """

    index: int
    name: str
    output: str
    vertices: VertexData
    colors: np.ndarray | None
    triangles: np.ndarray
    coefficients: np.ndarray
    G: np.ndarray
    owned: np.ndarray
    frame: Any
    scheme: Any
    level: int
    input_points: int
    ascii: bool = False
    crs: str | None = None


class TilePlan:
    """The tiles of a survey's base surface (model: pipeline.SurfaceModel), one per input,
    each TileTask built only when asked for.

    plan[i] is input i's task: its owned triangles plus the halo across its border edges.
    Tasks are built on demand so that a run holds the survey's base surface and only the
    tasks in flight, not a second copy of the data in tasks. len(plan) is the input count;
    names and outputs are per input.
    """

    def __init__(self, model, survey: Survey, outputs: Sequence[str], level: int, ascii: bool = False,
                 crs: str | None = None):
        interp = model.interp
        self.interp, self.frame, self.level, self.ascii = interp, model.frame, level, ascii   # not the cloud
        self.crs = crs
        self.names, self.outputs = list(survey.names), [str(o) for o in outputs]
        self.counts = np.diff(survey.offsets)
        self.owners = triangle_owners(model, survey)
        self.across = triangle_neighbours(interp.triangles, interp.points.shape[0])
        colors = survey.cloud.colors
        self.colors = None if colors is None else colors[model.hf.source_index[model.used]]
        self.scheme = _scheme_for_task(interp.scheme)

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> TileTask:
        if not 0 <= i < len(self):
            raise IndexError(i)
        interp = self.interp
        owned = self.owners == i
        halo = np.zeros_like(owned)
        across = self.across[owned]
        halo[across[across >= 0]] = True
        keep = np.flatnonzero(owned | halo)                    # survey order
        corners = interp.triangles[keep]
        points = np.unique(corners)
        return TileTask(
            i, self.names[i], self.outputs[i],
            VertexData(interp.points[points], interp.values[points], interp.gradients[points]),
            None if self.colors is None else self.colors[points],
            np.searchsorted(points, corners), interp.coefficients[keep], interp.lambda_gradients[keep],
            owned[keep], self.frame, self.scheme, self.level, int(self.counts[i]), self.ascii,
            self.crs)


def _scheme_for_task(scheme):
    """A named scheme travels by name (its shape functions hold lambdas, which plain
    pickle refuses); a custom ShapeTuple travels as itself (Dask's cloudpickle takes it)."""
    return scheme.name if NAMED_TUPLES.get(scheme.name) is scheme else scheme


@dataclass
class TileResult:
    """A refined tile: its mesh (world coordinates; None once written) and a report row."""

    index: int
    mesh: SurfaceMesh
    report: dict


def run_tile(task: TileTask, target=None) -> TileResult:
    """Refine one tile and keep the refined triangles of its owned base triangles.

    target: a path to stream the tile's mesh to (then the result's mesh is None: memory
    stays block-sized, as in `c1mesh fit`); None returns the mesh in memory (to send it
    back from a worker). Output vertices are those the kept faces use, in the tile
    refinement's order.
    """
    start = time.perf_counter()
    stream = tile_stream(task)
    mesh = None
    if target is None:
        mesh = stream.materialize()
    else:
        with blas_threads(1):        # as the in-memory fit: an idle BLAS pool spins on the writer's core
            write_mesh(stream, target, ascii=task.ascii, crs=task.crs, sidecar=False)
    owned = int(task.owned.sum())
    report = {"tile": task.name, "output": task.output, "worker": worker_address(),
              "input_points": task.input_points, "base_triangles": owned,
              "halo_triangles": int(task.owned.size - owned),
              "vertices": int(stream.vertex_count), "triangles": int(stream.face_count),
              "seconds": round(time.perf_counter() - start, 6)}
    return TileResult(task.index, mesh, report)


def tile_stream(task: TileTask):
    """The owned part of a tile's refinement as a MeshStream (pipeline.surface_stream).

    One integer pass over the faces marks the output points the owned faces use; the
    vertex pass then evaluates the tile block by block and keeps the marked points, the
    face pass keeps the owned faces, renumbered. Halo triangles are evaluated but few.
    """
    L2 = task.level * task.level
    table = edge_table(task.triangles, task.vertices.points.shape[0])
    refinement = Refinement(task.vertices, task.triangles,
                            task.coefficients, task.G, table, get_scheme(task.scheme), task.level)
    whole = surface_stream(refinement, task.frame, task.colors)
    owned_faces = np.repeat(task.owned, L2)
    used = np.zeros(refinement.vertex_count, dtype=bool)
    for first, faces in refinement.face_blocks():
        keep = owned_faces[first:first + len(faces)]
        used[(faces if keep.all() else faces[keep]).ravel()] = True      # most blocks are all owned
    renumber = np.cumsum(used, dtype=refinement.index_dtype)
    renumber -= 1

    def vertex_blocks():
        position = 0
        for vertices, normals, colors in whole.vertex_blocks():
            keep = used[position:position + len(vertices)]
            position += len(vertices)
            if keep.all():
                yield vertices, normals, colors
            else:
                yield (vertices[keep], None if normals is None else normals[keep],
                       None if colors is None else colors[keep])

    def face_blocks():
        first = 0
        for faces in whole.face_blocks():
            keep = owned_faces[first:first + len(faces)]
            first += len(faces)
            yield renumber.take(faces if keep.all() else faces[keep])
    return replace(whole, vertex_count=int(used.sum()), face_count=int(owned_faces.sum()),
                   vertex_blocks=vertex_blocks, face_blocks=face_blocks)


def temp_path(output: str):
    """The hidden file beside `output` a tile is written to before the run succeeds.

    The path is registered with c1mesh.core.outputs (register_temp) before anything is written
    there, so an interrupted run (SIGINT, SIGTERM, SIGHUP) removes it; write_tiles
    unregisters it once renamed into place or removed.
    """
    target = Path(output)
    temp = target.with_name(f".{target.name}.tile-{os.getpid()}{target.suffix}")
    register_temp(temp)
    return temp


def worker_address() -> str:
    """The Dask worker running this code, or host:pid outside Dask."""
    if "distributed" in sys.modules:            # a Dask worker has imported it; importing costs ~1 s
        try:
            return sys.modules["distributed"].get_worker().address
        except ValueError:                       # imported, but not running in a worker
            pass
    return f"{socket.gethostname()}:{os.getpid()}"


def task_row(points: int, start: float) -> dict:
    """A task's report row: its points, seconds since start, the worker that ran it and
    that worker's peak RSS so far (MB; the largest of the tasks it has run, with the
    interpreter's own)."""
    return {"points": int(points), "seconds": round(time.perf_counter() - start, 3), "worker": worker_address(),
            "worker_peak_mb": peak_rss_mb()}


def write_tiles(results: Iterable[TileResult], outputs: Sequence[str], ascii: bool = False,
                on_tile: Callable[[dict], None] | None = None, crs: str | None = None) -> list[dict]:
    """Write each tile's mesh to its output, all or nothing.

    Meshes (and, with a crs, their .prj sidecars for the formats that have one) go to
    hidden temporary files beside their outputs and are renamed into place only after
    every tile has succeeded; a failure (re-raised as InputError naming the tile) removes
    them, so no output of the run appears. Returns the report rows in input order.
    """
    rows: dict[int, dict] = {}
    with staged_outputs(crs) as stage:
        for result in results:
            temp = stage(outputs[result.index])
            if result.mesh is not None:                  # else run_tile wrote it there
                write_mesh(result.mesh, temp, ascii=ascii, crs=crs, sidecar=False)
            rows[result.index] = result.report
            if on_tile:
                on_tile(result.report)
    return [rows[i] for i in sorted(rows)]


@contextlib.contextmanager
def staged_outputs(crs: str | None = None):
    """All or nothing for several outputs: yields stage(output), which gives the hidden
    file beside `output` to write (`temp_path`; with a crs, the .prj sidecar of formats
    that have one is staged too). When the block ends, every staged file is renamed into
    place; when it raises, every one is removed, so no output of the run appears."""
    temps: dict[Path, Path] = {}                         # temporary file -> final path

    def stage(output) -> Path:
        temp = temp_path(output)
        temps[temp] = Path(output)
        if crs and mesh_format(output) in PRJ_SIDECAR:      # the format carries its CRS in a .prj
            temps.update(_temp_prj(output, crs))
        return temp
    try:
        yield stage
        for temp, final in temps.items():
            os.replace(temp, final)
            unregister_temp(temp)
    except BaseException:
        for temp in temps:
            temp.unlink(missing_ok=True)
            unregister_temp(temp)
        raise


def _temp_prj(output: str, crs: str) -> dict:
    """{temporary file: final .prj path} of `output`'s CRS sidecar (ESRI WKT), written."""
    final = prj_path(output)
    plan_outputs([("CRS sidecar", final)])          # not a device, FIFO or directory
    temp = temp_path(str(final))
    temp.write_text(esri_wkt(crs) + "\n", encoding="utf-8")
    return {temp: final}


class TileError(InputError):
    """A tile failed; the message names it."""


def tile_failure(name: str, exc: BaseException) -> TileError:
    """The error to report for the tile `name` whose task raised exc."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return TileError(f"tile {name}: {text}")


