"""The memory-bounded fit's last pass (c1mesh.pipeline.bounded_fit): each tile refines its own
triangles into part files (a task per tile, `_refine_tile`), the parts are joined in tile
order with one global vertex numbering (c1mesh.survey.join), and the mesh is
written from the joined files, or with -O one mesh per input (c1mesh.survey.split_outputs)."""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from c1mesh.core.cloud import MeshStream
from c1mesh.core.plan import FitPlan, MeshTarget, SurfaceSettings
from c1mesh.core.threads import blas_threads, limit
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.formats import MeshSize, check_mesh_size, write_mesh
from c1mesh.stages.limiter import TileLimits
from c1mesh.stages.surface import surface_stream
from c1mesh.stages.trim import check_triangles_left
from c1mesh.survey.distributed import TaskRunner
from c1mesh.survey.tile_spill import file_blocks
from c1mesh.core.tile import corner_rows, row_min, tile_rows
from c1mesh.survey.inputs import Colours
from c1mesh.survey.join import KeyExpiry, PartJoin, border_keys
from c1mesh.survey.split_outputs import OutputMeshes, face_owners, split_faces, write_outputs
from c1mesh.survey.task_rows import TileRows
from c1mesh.survey.tiles import task_row

WRITE_BLOCK = 1 << 16
"""Vertices (faces) per block streamed from the joined files to the mesh writer, as the
PLY writer packs them: the writer holds a few blocks in flight (the block read, its
packed rows and up to four in its background queue, about 6 × 3.3 MB of coloured
vertices at this size), so with 1M-vertex (48 MB) blocks the write alone held well over
100 MB whatever the budget, and still about 40 MB at 256k."""


VERTEX = np.dtype([("v", "<f8", 3), ("n", "<f8", 3)])
VERTEX_RGB = np.dtype([("v", "<f8", 3), ("n", "<f8", 3), ("c", "u1", 3)])
"""One output vertex in the temporary vertex file: position, normal (world), colour."""


@dataclass(frozen=True)
class TiledMesh:
    """The survey's trimmed triangulation, tile by tile (bounded_fit): heights, the
    TileSpill of HEIGHT records; grid, the buffered_delaunay.TileGrid; files, per tile
    the .npy of its own triangles (survey numbers; None: none); buffers, per tile its
    Delaunay buffer (frame units); max_edge, the trim's limit (None: none); frame, the
    survey's stages.frame.ScanFrame; far, a DEM's fill: {tile: (m, 2) the far corners of
    its long triangles and beyond} (survey.hole_runs.far_centres; empty: none)."""

    heights: object
    grid: object
    files: Sequence
    buffers: Sequence
    max_edge: float | None
    frame: object
    far: dict = field(default_factory=dict)


@dataclass(frozen=True)
class MeshWriting:
    """What write_tiles refines and writes with: temps (inputs.Temps), limiter (the
    halos.TiledLimiter or smoothing_runs.TiledSmoother; None: --overshoot off),
    crs (WKT or None), colours (inputs.Colours or None), runner
    (distributed.TaskRunner), rows (task_rows.TileRows), split (Split with -O, else None)."""

    temps: object
    limiter: object = None
    crs: str | None = None
    colours: Colours | None = None
    runner: object = None
    rows: TileRows | None = None
    split: "Split | None" = None


class RefineJob:
    """What every tile's refinement task shares (picklable; the files it names are read
    by the task): the TiledMesh's heights, grid, files, buffers, max_edge and frame; the
    scheme and level; limiter (None: --overshoot off), colours, threads per task, owners
    (split_outputs.InputOwners, with -O: each part then records its faces' owner inputs)."""

    def __init__(self, mesh: TiledMesh, surface: SurfaceSettings, writing: MeshWriting, colours, threads):
        self.heights, self.grid, self.files, self.buffers = mesh.heights, mesh.grid, mesh.files, mesh.buffers
        self.max_edge, self.frame, self.scheme, self.level = mesh.max_edge, mesh.frame, surface.scheme, surface.level
        self.far = mesh.far
        self.limiter, self.colours, self.threads = writing.limiter, colours, threads
        self.owners = None if writing.split is None else writing.split.owners
        self.expiry = KeyExpiry(mesh.grid, [self.reach(t) for t in range(len(mesh.grid))])

    def reach(self, t: int) -> float:
        """How far beyond its cell the corners of tile t's own triangles lie (frame units):
        the trim's max_edge, else its Delaunay buffer, with a relative margin for rounding."""
        return (self.max_edge if self.max_edge is not None else self.buffers[t]) * (1 + 1e-9)

    def spline(self, t: int, triangles: np.ndarray):
        """(RSDInterpolator over tile t's own triangles (survey numbers; its points the
        corners' local x, y), the corners' records (c,), (limited, turned, lifted)): the
        spline the tile refines (with the limiter's or the smoothing's data; the records'
        own without), as the tiled DEM samples it too (pipeline.bounded_dem)."""
        data = self.tile_data(t, triangles)
        records = data.records
        xy = np.column_stack([records["x"], records["y"]])
        gradients = data.gradients
        if gradients is None:
            gradients = np.column_stack([records["gx"], records["gy"]])
        interp = RSDInterpolator(xy, records["z"], gradients, triangles=data.triangles, scheme=self.scheme,
                                 directions=data.directions, edge_table=data.table)
        return interp, records, (data.limited, data.turned, data.lifted)

    def tile_data(self, t: int, triangles: np.ndarray) -> TileLimits:
        """The limiter.TileLimits of tile t's own triangles (survey numbers): the limiter's
        (or the smoothing's), or without one the corners' own records (gradients,
        directions and table None, no changes)."""
        if self.limiter is not None:
            return self.limiter.tile(t, triangles)
        records, _ = self.heights.records_near(self.grid.grown(t, self.reach(t)), self.far.get(t))
        rows, local = corner_rows(records["index"], triangles)
        if np.any(rows < 0):
            raise RuntimeError(f"tile {t}: a corner point lies outside the rectangle it read")
        return TileLimits(records.take(rows), local, None, None, 0, 0, 0)


def point_numbers(records: np.ndarray) -> np.ndarray:
    """(m,) the survey number of the point each vertex record stands for: its own, or a
    lattice node's nearest point (survey.lattice_runs.NODE's source)."""
    return records["source"] if "source" in records.dtype.names else records["index"]


def lowest_points(records: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(k, 1) the point (point_numbers) of each triangle's lowest-numbered corner, the
    corner whose input owns it with -O; triangles (k, 3) in the records' numbers."""
    lowest = row_min(triangles)
    if "source" not in records.dtype.names:
        return lowest[:, None]
    return records["source"][tile_rows(records["index"], lowest)][:, None]


class _Part:
    """The temporary files of one tile's refinement: vertices (all of its refinement's
    output points, VERTEX or VERTEX_RGB), faces (int64 triples, tile-local numbers), keys
    (.npz: the border keys of `join.border_keys`, their points and last tiles),
    owners (int32 per face, with -O: split_outputs.face_owners)."""

    def __init__(self, temps, t: int):
        self.vertices, self.faces = temps.new(f"part-{t}.vertices"), temps.new(f"part-{t}.faces")
        self.keys, self.owners = temps.new(f"part-{t}.keys"), temps.new(f"part-{t}.owners")

    def remove(self) -> None:
        for path in (self.vertices, self.faces, self.keys, self.owners):
            path.unlink(missing_ok=True)


def _refine_tile(job: RefineJob, t: int, part: _Part) -> dict | None:
    """Refine tile t's own triangles into its part files; returns its report row with
    vertices, corners (input points among them, first), faces, triangles, limited,
    turned, lifted, or None for a tile without triangles."""
    start = time.perf_counter()
    triangles = np.load(job.files[t])
    if not len(triangles):
        return None
    with limit(job.threads):
        interp, records, (limited, turned, lifted) = job.spline(t, triangles)
        colors = None if job.colours is None else job.colours.of(point_numbers(records))
        counts = _write_part(job, interp, records, part, colors)
        if job.owners is not None:
            owner = face_owners(job.owners, lowest_points(records, triangles), job.level)
            if len(owner) != counts["faces"]:
                raise RuntimeError(f"tile {t}: {counts['faces']} faces, {len(owner)} owners")
            owner.astype("<i4").tofile(part.owners)
    return {**counts, "triangles": len(triangles), "limited": limited, "turned": turned, "lifted": lifted,
            **task_row(len(records), start)}


def check_output_size(output, mesh: MeshTarget, vertices: int, faces: int, coloured: bool) -> None:
    """InputError when a mesh of this many vertices and faces (normals, and RGB if
    coloured) is beyond the limits of the output's format (formats.check_mesh_size); the
    tiled fit asks with the fewest vertices its triangles can refine to before any tile is
    refined (bounded_fit), and with the joined counts so far as tiles are joined."""
    check_mesh_size(output, mesh.format, MeshSize(vertices, faces, True, 3 if coloured else 0))


def write_tiles(mesh: TiledMesh, plan: FitPlan, output, writing: MeshWriting) -> dict:
    """Refine each tile's owned triangles (a task per tile, `_refine_tile`, writing part
    files), then join the parts in tile order, numbering shared vertices globally
    (bounded_fit's docstring), into one vertex and one face file; then write the mesh from
    them, or with writing.split (-O), each input's part of it (c1mesh.survey.split_outputs).
    Without split, InputError as soon as the joined counts pass the output format's
    limits (`check_output_size`), before the remaining tiles are refined."""
    grid, temps, limiter, split = mesh.grid, writing.temps, writing.limiter, writing.split
    runner = writing.runner or TaskRunner()
    rows = writing.rows or TileRows(grid, plan.threads)
    coloured = writing.colours is not None and writing.colours.present
    job = RefineJob(mesh, plan.surface, writing, writing.colours if coloured else None, rows.threads)
    tiles = [t for t in range(len(grid)) if mesh.files[t] is not None]
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
                    if split is None:      # the counts only grow: stop at the first tile past the format's limit
                        check_output_size(output, plan.mesh, join.written, join.faces, coloured)
                    else:
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
    check_triangles_left(faces)
    report = {"kept": join.kept, "output_mesh": {"vertices": written, "faces": faces},
              "shared_vertex_keys": join.keys,
              "shared_vertex_keys_held": join.shared.peak, "triangles_per_tile": triangles_per_tile}
    if limiter is not None:
        report["overshoot"] = limiter.report()
    if split is not None:
        report["output_meshes"] = split.write(vertex_path, VERTEX_RGB if coloured else VERTEX, face_path, owner_path,
                                        temps, plan.mesh, writing.crs)
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
                   plan.mesh.format, ascii=plan.mesh.ascii, crs=writing.crs)
    return report


@dataclass
class Split:
    """-O: the survey's owner inputs (split_outputs.InputOwners), one output path and one
    name per input."""

    owners: object
    outputs: Sequence[str]
    names: Sequence[str]

    def write(self, vertex_path, dtype, face_path, owner_path, temps, mesh: MeshTarget, crs) -> list[dict]:
        """Split the joined faces by owner and write every input's mesh (all or nothing)."""
        paths = split_faces(face_path, owner_path, len(self.outputs), temps)
        return write_outputs(vertex_path, dtype, paths, self.outputs, OutputMeshes(mesh, crs, self.names))


def _write_part(job: RefineJob, interp: RSDInterpolator, records, part: _Part, colors=None) -> dict:
    """Refine one tile's spline (RefineJob.spline: interp over its owned triangles, whose
    points are the records', survey order) at the job's level, and write all its output
    points (world position through the job's frame, normal, colour), its faces
    (tile-local numbers) and its border keys (with the job's join.KeyExpiry) to its part
    files; returns {vertices, corners, faces}. colors (n, 3) uint8 of the records, or None."""
    frame, level, expiry = job.frame, job.level, job.expiry
    xy = interp.points
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
