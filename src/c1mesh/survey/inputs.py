"""What the memory-bounded fit reads and keeps on disk (c1mesh.pipeline.bounded_fit): the survey's
files and how messages name them, its LAS/LAZ points a chunk at a time (decompressed
once, `CachedChunks`), its colours by survey number (`Colours`), its CRS, and the
hidden temporary files every pass registers for removal (`Temps`)."""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from c1mesh.core.crs import las_crs, parse_crs, resolve
from c1mesh.core.outputs import register_temp, unregister_temp
from c1mesh.core.plan import PointSelection
from c1mesh.formats.copc import laspy_module, region_chunks
from c1mesh.formats.las import no_class_error
from c1mesh.survey.tile_spill import file_blocks
from c1mesh.survey.tiles import survey_crs as common_crs

CHUNK = 1_000_000
"""Points per chunk read from a LAS/LAZ file."""


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
    """stages.frame.FrameChunks that decompress a source once: the first pass copies the world
    points (float64 x, y, z) to a hidden temporary file, later passes read that file (a
    LAZ decompression costs more than reading 24 bytes a point). Call close() to remove it."""

    def __init__(self, chunks: Callable, temps: "Temps", chunk: int = CHUNK):
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
        with open(self.path, "rb") as file:
            for part in file_blocks(file, "<f8", 3 * self.chunk):
                yield part.reshape(-1, 3), None


def las_chunks(source, classes=None, chunk: int = CHUNK, colours: "Colours | None" = None,
               bounds=None, file_counts: list | None = None, keep: np.ndarray | None = None) -> Callable:
    """stages.frame.FrameChunks over a LAS/LAZ file, or over several read one after another as
    one survey: a callable giving a fresh iterator of (world points (m, 3), None) in file
    order, keeping only `classes` (None: all). colours: where each pass also sends the
    kept points' RGB, when every file has it (a survey has colours only if all its files
    do, as in c1mesh.survey.tiles.load_survey). bounds: only the points in this closed x/y box
    (formats.copc.Box), in file order: a COPC file decodes only the nodes meeting it.
    file_counts: a list each pass refills with the points it kept from each file. keep:
    (N,) bool over the survey's points inside bounds, in this order, before `classes`
    (the ground filter's ground, survey.ground_pass): only those are kept."""
    laspy = laspy_module()
    paths = survey_paths(source)

    def dimensions(path):
        with laspy.open(str(path)) as reader:
            return set(reader.header.point_format.dimension_names)
    rgb_everywhere = colours is not None and all({"red", "green", "blue"} <= dimensions(p) for p in paths)

    def chunks():
        if file_counts is not None:
            file_counts.clear()
        found, total, read = set(), 0, 0
        for path in paths:
            kept = 0
            for part in region_chunks(path, bounds, chunk):
                if classes:
                    found.update(np.unique(np.asarray(part.classification)).tolist())
                rows = np.isin(np.asarray(part.classification), np.asarray(classes)) if classes else None
                if keep is not None:
                    mine = keep[read:read + len(part)]
                    rows = mine if rows is None else rows & mine
                read += len(part)
                xyz = _kept_columns(part, ("x", "y", "z"), rows, np.float64)
                if rgb_everywhere:
                    colours.add(_kept_columns(part, ("red", "green", "blue"), rows, np.uint16))
                del part                    # not held while the next chunk decodes
                kept += len(xyz)
                yield xyz, None
            if file_counts is not None:
                file_counts.append(kept)
            total += kept
        if classes and found and not total:          # as the in-memory reader says it
            raise no_class_error(list(classes), found, bounds is not None)
    return chunks


def has_ground_class(source, bounds=None) -> bool:
    """Whether the survey has a point of the ground class 2, over a LAS/LAZ file or a list
    read as one survey (inside `bounds`, as las_chunks reads it), stopping at the first
    chunk with one: how the tiled fit resolves its default class choice (the ground class
    when there is one) before its passes."""
    for path in survey_paths(source):
        for part in region_chunks(path, bounds, CHUNK):
            if (np.asarray(part.classification) == 2).any():
                return True
    return False


def tiled_classes(source, select: PointSelection) -> tuple[PointSelection, dict, bool]:
    """(select with classes resolved to codes or None, the report's "classes", whether the
    ground filter chooses the points) for the tiled fit, as stages.ground.choose_points
    chooses in memory: the given codes; every point for "all" (or None); the ground class
    2 for "auto" when the survey has any (a scan of its classes first); else, and for
    "filter", the filter's ground (survey.ground_pass: the caller runs it and completes
    the facts with its counts)."""
    choice = select.classes
    if isinstance(choice, tuple):
        return select, {"selected": list(choice), "source": "option"}, False
    if choice in ("all", None):
        return replace(select, classes=None), {"selected": "all", "source": "option"}, False
    if choice == "auto":
        if has_ground_class(source, select.bounds):
            return replace(select, classes=(2,)), {"selected": [2], "source": "file"}, False
    why = "asked (--classes filter)" if choice == "filter" else "the file has no ground class 2"
    return replace(select, classes=None), {"selected": [2], "source": "filter", "reason": why}, True


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

    def __init__(self, temps: "Temps"):
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

class Temps:
    """Hidden temporary files registered for removal (c1mesh.core.outputs), removed on close."""

    def __init__(self, directory, stem: str):
        self.directory, self.stem, self.paths = Path(directory), stem, []
        self.copy = False

    def __setstate__(self, state: dict) -> None:
        """A Temps unpickled (a task's argument in a worker process, or a Dask worker's
        thread) is a copy: its close is never called, so it must not make files."""
        self.__dict__.update(state, copy=True)

    def owned_here(self) -> bool:
        """Whether this is the Temps that made the files and removes them on close, not a
        copy sent with a task."""
        return not self.copy

    def new(self, name: str) -> Path:
        """A new hidden path in the directory, registered for removal. Only the driver's
        Temps may make one: a copy sent with a task (to a worker process or a Dask worker)
        would list the file in the copy alone, and nobody would remove it."""
        if not self.owned_here():
            raise RuntimeError(f"temporary file '{name}' requested from a copy of the survey's Temps in a "
                               "task; only the driver's Temps, which removes them, may make them")
        path = self.directory / f".{self.stem}.{name}-{os.getpid()}"
        register_temp(path)
        self.paths.append(path)
        return path

    def close(self) -> None:
        for path in self.paths:
            if path.exists():
                path.unlink()
            unregister_temp(path)

def survey_crs(source, user_crs) -> tuple[str | None, str | None]:
    """(CRS WKT, "file" | "option" | None) of a LAS/LAZ survey (one path or a list): the
    CRS its headers declare (c1mesh.survey.tiles.survey_crs: one for all files, InputError when
    two differ) and the user's --crs (WKT or any c1mesh.core.crs.parse_crs input) resolved as
    the in-memory fit does (InputError when they differ)."""
    laspy = laspy_module()
    paths = survey_paths(source)
    declared = []
    for path in paths:
        with laspy.open(str(path)) as reader:
            declared.append(las_crs(reader.header))
    file_crs = common_crs([str(p) for p in paths], declared)
    return resolve(file_crs, parse_crs(user_crs) if user_crs else None, survey_name(paths))
