"""The refined surface in world coordinates, as a stream of blocks for the writers, and the
level a height field is refined at unless asked otherwise.

Every path (the in-memory fit, -O tiles, the memory-bounded survey fit, previews) turns a
refinement into world vertices, normals and colours through `surface_stream`.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from c1mesh.core.cloud import MeshStream
from c1mesh.core.plan import FitPlan
from c1mesh.core.threads import prefetch_dealt, ring
from c1mesh.engine.refine import Refinement, refined_counts
from c1mesh.stages import _surface as kernel

PLANE_LEVEL = 4
"""The refinement level of a height-field (axis-frame) fit when neither --level nor
--resolution is given: each triangle is split into 16."""


_PREFETCH = 2
"""Blocks a streamed surface is computed ahead of its writer."""


def surface_stream(refinement: Refinement, frame, colors: np.ndarray | None) -> MeshStream:
    """The refined surface in world coordinates as a MeshStream (heights = spline values).

    Each pass evaluates the spline block by block (refine.Refinement) and turns every
    block into world vertices, unit normals on the axis side and, when the input has
    colours (N, c) uint8, colours blended linearly; nothing of the size of the output is
    held, so the writers (all of them stream) need only block-sized memory. Blocks are
    dealt to one thread per worker, each a few blocks ahead of the writer, and handed
    over in order (c1mesh.core.threads.prefetch_dealt): the same blocks at any count.
    """
    fields = [] if colors is None else [colors.astype(float)]

    def world_blocks(w: int, count: int):
        size = refinement.largest_block
        local = np.empty((size, 3)) if hasattr(frame, "normals_from_gradients") else None
        slots = [np.empty((size, 6)) for _ in range(ring(_PREFETCH))]   # a row: vertex, normal
        for i, block in enumerate(refinement.vertex_blocks(fields=fields, deal=(w, count))):
            n = block.stop - block.start
            rows = slots[i % len(slots)][:n]
            if hasattr(frame, "normals_from_gradients"):      # perspective.PerspectiveFrame
                local[:n, :2] = block.points
                local[:n, 2] = block.values
                rows[:, :3] = frame.to_world(local[:n])
                rows[:, 3:] = frame.normals_from_gradients(local[:n], block.gradients)
            else:
                world_rows(frame, block.points, block.values, block.gradients, rows)
            blended = None
            if fields:
                blended = np.clip(np.rint(block.fields[0]), 0, 255).astype(np.uint8)
            yield rows[:, :3], rows[:, 3:], blended

    def dealt_faces(w: int, count: int):
        return (faces for _, faces in refinement.face_blocks(ring=ring(_PREFETCH), deal=(w, count)))

    def vertex_blocks():
        return prefetch_dealt(world_blocks, _PREFETCH)

    def face_blocks():
        return prefetch_dealt(dealt_faces, _PREFETCH)
    return MeshStream(refinement.vertex_count, refinement.face_count, True,
                      0 if colors is None else colors.shape[1], vertex_blocks, face_blocks)


def world_rows(frame, points: np.ndarray, values: np.ndarray, gradients: np.ndarray, out: np.ndarray) -> None:
    """Fill out (n, 6) with rows (vertex, normal): out[:, :3] the world points
    frame.to_world((x, y, z)) of a height field's plane points (n, 2) and values z (n,),
    out[:, 3:] the world unit normals frame.vectors_to_world(gradients_to_normals(gradients))
    of its gradients (n, 2), bit for bit; frame a ScanFrame, world units. One kernel pass
    (stages/_surface.pyx), 4x faster than numpy's four, without the GIL; the rows are a
    PLY's vertex rows (formats.ply packs them with one copy)."""
    n = len(points)
    if (np.shape(points) != (n, 2) or np.shape(values) != (n,) or np.shape(gradients) != (n, 2)
            or np.shape(out) != (n, 6)):
        raise ValueError(f"world_rows needs points (n, 2), values (n,), gradients (n, 2) and out (n, 6), got "
                         f"{np.shape(points)}, {np.shape(values)}, {np.shape(gradients)}, {np.shape(out)}")
    contiguous = lambda a: np.ascontiguousarray(a, dtype=np.float64)   # noqa: E731
    kernel.world_rows(contiguous(points), contiguous(values), contiguous(gradients), contiguous(frame.axes),
                      contiguous(frame.origin), out)


def with_plane_level(plan: FitPlan) -> FitPlan:
    """The plan with level PLANE_LEVEL when none is given: the tiled fits are height
    fields, whose level does not depend on the data."""
    if plan.surface.level is not None:
        return plan
    return replace(plan, surface=replace(plan.surface, level=PLANE_LEVEL))


def refined_vertex_count(interp, level: int) -> int:
    """Vertices of the level-`level` refinement of interp's triangulation, without building
    it (refine.refined_counts)."""
    return refined_counts(interp.points.shape[0], interp.edge_table.edges.shape[0], interp.triangles.shape[0],
                          level)[0]
