"""`fit --seamless -O` for a survey larger than --memory: the tiled fit's joined mesh split
into one mesh per input (c1mesh.pipeline.bounded_fit).

The ownership rule is c1mesh.survey.tiles': a base triangle, and every face refined from it,
belongs to the input that holds its lowest-numbered corner point (survey numbers run over
the inputs in order, as the concatenated cloud numbers them). The tiled join has already
given every output point one global number and one record (position, normal, colour), so a
vertex on a border between two inputs is the same record, to the bit, in both outputs:
merging the outputs' exactly equal vertices gives the `-o` mesh.

Memory: the split streams the joined faces once into one face file per output; writing an
output holds the sorted global numbers of its vertices (8 bytes each) and blocks of the
rest, so the largest input's vertex count bounds it, not the survey's.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from c1mesh.core.cloud import MeshStream
from c1mesh.core.plan import MeshTarget
from c1mesh.core.threads import blas_threads
from c1mesh.core.tile import row_min
from c1mesh.formats import write_mesh
from c1mesh.survey.tile_spill import file_blocks
from c1mesh.survey.tiles import staged_outputs

BLOCK = 1 << 16
"""Faces (vertices) per block read, remapped and written."""


class InputOwners:
    """Which input holds each survey number: counts (N,) the points each input contributes
    to the survey, in order (after class and bounds filters). Picklable."""

    def __init__(self, counts: Sequence[int]):
        self.ends = np.cumsum(np.asarray(counts, dtype=np.int64))

    def of(self, numbers: np.ndarray) -> np.ndarray:
        """(…) int32 input index of each survey number."""
        return np.searchsorted(self.ends, numbers, side="right").astype(np.int32)


def face_owners(owners: InputOwners, triangles: np.ndarray, level: int) -> np.ndarray:
    """(k·level²,) int32 owner input of each refined face of the base triangles (k, 3)
    (survey numbers), in the refinement's order: level² faces per triangle, triangle by
    triangle."""
    return np.repeat(owners.of(row_min(triangles)), level * level)


def split_faces(face_path: Path, owner_path: Path, outputs: int, temps) -> list[Path]:
    """Stream the joined faces (int64 triples, global numbers) and their owners (int32) into
    one face file per output; returns their paths."""

    paths = [temps.new(f"output-{i}.faces") for i in range(outputs)]
    with open(face_path, "rb") as faces, open(owner_path, "rb") as owner_file:
        for block in file_blocks(faces, "<i8", 3 * BLOCK):
            block = block.reshape(-1, 3)
            owner = np.fromfile(owner_file, "<i4", count=len(block))
            if len(owner) != len(block):
                raise RuntimeError("the joined faces and their owners differ in length")
            for i in np.unique(owner):
                mine = block[owner == i]
                with open(paths[i], "ab") as file:
                    mine.tofile(file)
    return paths


@dataclass(frozen=True)
class OutputMeshes:
    """How -O's meshes are written: mesh, the core.plan.MeshTarget (format, ascii); crs,
    the survey's WKT or None; names, one input name per output (the report's rows)."""

    mesh: MeshTarget
    crs: str | None
    names: Sequence[str]


def write_outputs(vertex_path: Path, dtype: np.dtype, face_paths: list[Path], outputs: Sequence[str],
                  how: OutputMeshes) -> list[dict]:
    """Write each output's mesh from the joined vertex records (`dtype`, global numbers) and
    its face file, all or nothing (c1mesh.survey.tiles.staged_outputs, as write_tiles). Returns
    one report row per input: input, output, vertices, faces."""
    records = np.memmap(vertex_path, dtype=dtype, mode="r") if os.path.getsize(vertex_path) else \
        np.empty(0, dtype=dtype)
    rows = []
    with staged_outputs(how.crs) as stage:
        for name, output, faces in zip(how.names, outputs, face_paths):
            rows.append({"input": name, "output": str(output),
                         **_write_one(records, faces, stage(output), how)})
    return rows


def _write_one(records: np.ndarray, face_path: Path, target: Path, how: OutputMeshes) -> dict:
    """One output's mesh: its faces renumbered over the sorted global numbers they use."""
    used = _used_vertices(face_path)
    coloured = records.dtype.names is not None and "c" in records.dtype.names
    face_count = os.path.getsize(face_path) // 24 if face_path.exists() else 0

    def vertex_blocks():
        for start in range(0, len(used), BLOCK):
            part = np.asarray(records[used[start:start + BLOCK]])
            yield part["v"], part["n"], part["c"] if coloured else None

    def face_blocks():
        if not face_count:
            return
        with open(face_path, "rb") as file:
            for block in file_blocks(file, "<i8", 3 * BLOCK):
                yield np.searchsorted(used, block).reshape(-1, 3)
    with blas_threads(1):
        write_mesh(MeshStream(len(used), face_count, True, 3 if coloured else 0, vertex_blocks, face_blocks),
                   target, how.mesh.format, ascii=how.mesh.ascii, crs=how.crs, sidecar=False)
    return {"vertices": int(len(used)), "faces": int(face_count)}


MERGE = 1 << 22
"""Block-unique numbers gathered before they are merged into the sorted set."""


def _used_vertices(face_path: Path) -> np.ndarray:
    """Sorted unique global numbers of the faces in face_path, merged a batch of blocks at
    a time (a merge per block would sort the growing set once per block)."""

    used, pending, size = np.empty(0, dtype=np.int64), [], 0
    if not face_path.exists():
        return used
    with open(face_path, "rb") as file:
        for block in file_blocks(file, "<i8", 3 * BLOCK):
            pending.append(np.unique(block))
            size += len(pending[-1])
            if size >= MERGE:
                used = np.unique(np.concatenate([used, *pending]))
                pending, size = [], 0
    return np.unique(np.concatenate([used, *pending])) if pending else used
