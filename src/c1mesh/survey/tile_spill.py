"""Points binned to tiles on disk: the first pass of a survey larger than memory.

The survey's points arrive in chunks, in survey order (LAS/LAZ by laspy's chunk iterator).
Each chunk is projected to the frame's plane and its rows are appended to one spill file
per tile of a buffered_delaunay.TileGrid; a tile then reads its cell and buffer from the
few spill files those rectangles touch, never the survey. A row is (survey number int64,
x, y, height float64) in the frame; files are raw arrays of that record (np.fromfile).

Spill files are hidden files `.NAME.spill-PID-T.bin` beside the output (or in $TMPDIR),
registered with c1mesh.core.outputs, so they are removed when the spill is closed, when the
block that made it fails, and when the process is interrupted (SIGINT, SIGTERM, SIGHUP).
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from c1mesh.core.lazy import LazyModule
from c1mesh.core.outputs import register_temp, unregister_temp
from c1mesh.survey import _tile_spill as kernel
from c1mesh.survey.buffered_delaunay import TileGrid

spatial = LazyModule("scipy.spatial")

RECORD = np.dtype([("index", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
"""One spilled point: survey number and frame coordinates (x, y in the plane, z height)."""


def save_array(path, array: np.ndarray) -> None:
    """np.save to exactly path (np.save given a name would append .npy)."""
    with open(path, "wb") as file:
        np.save(file, array)


class TileSpill:
    """Per-tile spill files of a survey; use as a context manager (files removed on exit).

    grid: the tiles; directory: where the files go; stem: names them (`.STEM.spill-...`).
    """

    def __init__(self, grid: TileGrid, directory: str | os.PathLike | None = None, stem: str = "c1mesh",
                 record: np.dtype = RECORD):
        self.grid, self.record = grid, record
        self.directory = Path(directory if directory is not None else tempfile.gettempdir())
        self.paths = [self.directory / f".{stem}.spill-{os.getpid()}-{t}.bin" for t in range(len(grid))]
        self.counts = np.zeros(len(grid), dtype=np.int64)
        self._created = False

    def __enter__(self) -> "TileSpill":
        """Create the (empty) spill files, once."""
        if not self._created:
            self._created = True
            for path in self.paths:
                register_temp(path)              # before the file exists: a signal finds nothing or it
                path.write_bytes(b"")
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Remove every spill file."""
        for path in self.paths:
            with contextlib.suppress(OSError):
                path.unlink()
            unregister_temp(path)

    def add(self, index: np.ndarray, local: np.ndarray) -> None:
        """Append points: index (m,) survey numbers, local (m, 3) frame coordinates."""
        tiles = self.grid.tile_of(local[:, :2])
        order = np.argsort(_sort_keys(tiles, len(self.grid)), kind="stable")   # survey order within a tile
        bounds = np.searchsorted(tiles[order], np.arange(len(self.grid) + 1))
        for tile in np.flatnonzero(np.diff(bounds)):
            rows = order[bounds[tile]:bounds[tile + 1]]
            record = np.empty(len(rows), RECORD)
            record["index"] = index[rows]
            record["x"], record["y"], record["z"] = local[rows, 0], local[rows, 1], local[rows, 2]
            with open(self.paths[tile], "ab") as file:
                record.tofile(file)
            self.counts[tile] += len(rows)

    def append(self, t: int, records: np.ndarray) -> None:
        """Append records (of this spill's record dtype, with fields index, x, y) to tile t."""
        with open(self.paths[t], "ab") as file:
            records.astype(self.record, copy=False).tofile(file)
        self.counts[t] += len(records)

    def tile(self, t: int) -> np.ndarray:
        """The records of tile t, in survey order."""
        return np.fromfile(self.paths[t], dtype=self.record)

    def read(self, rect) -> tuple[np.ndarray, np.ndarray]:
        """buffered_delaunay.Reader: (index ascending, xy (m, 2)) of the points in the closed
        rectangle (x0, y0, x1, y1), from the tiles whose cells it touches."""
        records = self.records(rect)
        return records["index"], np.column_stack([records["x"], records["y"]])

    def records(self, rect) -> np.ndarray:
        """The records in the closed rectangle, ascending survey numbers. (np.compress and
        take: numpy's boolean and integer indexing of a structured array take a generic
        per-row path, measured 8-13x slower on 250k of these 32-byte records; the copies
        are the same.)"""
        parts = [_in_rect(self.tile(t), rect) for t in self.touching(rect)]
        records = np.concatenate(parts) if parts else np.empty(0, self.record)
        return records.take(np.argsort(records["index"], kind="stable"))

    def records_near(self, rect, far: np.ndarray | None) -> tuple[np.ndarray, list[int]]:
        """(the records in the closed rectangle or within a far read's radius of its point,
        in the max norm, ascending survey numbers; the tiles read): `records` with a
        halo's far reads (far (m, 3): x, y, radius; survey.hole_runs.far_centres; None:
        none)."""
        tiles = self.reading(rect, far)
        if far is None or not len(far):
            return self.records(rect), tiles
        parts = []
        for t in tiles:
            r = self.tile(t)
            keep = _rect_mask(r, rect)
            meeting = _meeting(far, self.grid.cell(t))
            for radius in np.unique(far[meeting, 2]).tolist():
                mine = far[(far[:, 2] == radius) & meeting][:, :2]
                lo, hi = mine.min(axis=0) - radius, mine.max(axis=0) + radius    # only the records in their box
                ask = np.flatnonzero(~keep & (r["x"] >= lo[0]) & (r["x"] <= hi[0])
                                     & (r["y"] >= lo[1]) & (r["y"] <= hi[1]))
                if ask.size:
                    distance = spatial.cKDTree(mine).query(np.column_stack([r["x"][ask], r["y"][ask]]), p=np.inf,
                                                   distance_upper_bound=radius * (1 + 1e-12) + 1e-300)[0]
                    keep[ask[distance <= radius]] = True
            parts.append(np.compress(keep, r))
        records = np.concatenate(parts) if parts else np.empty(0, self.record)
        return records.take(np.argsort(records["index"], kind="stable")), tiles

    def reading(self, rect, far: np.ndarray | None) -> list[int]:
        """The tiles records_near reads: those meeting the rectangle or a far read's square."""
        tiles = set(self.touching(rect))
        if far is not None and len(far):
            meets = [bool(_meeting(far, self.grid.cell(t)).any()) and self.counts[t] > 0
                     for t in range(len(self.grid))]
            tiles.update(t for t, met in enumerate(meets) if met)
        return sorted(tiles)

    def touching(self, rect) -> Iterator[int]:
        """The tiles whose cells meet the closed rectangle."""
        x0, y0, x1, y1 = rect
        for t in range(len(self.grid)):
            cx0, cy0, cx1, cy1 = self.grid.cell(t)
            if cx0 <= x1 and x0 <= cx1 and cy0 <= y1 and y0 <= cy1 and self.counts[t]:
                yield t


def _sort_keys(tiles: np.ndarray, count: int) -> np.ndarray:
    """tiles (m,) int64 numbers below count, as uint16 when they fit: numpy's stable sort
    is a radix sort on 16-bit keys and a merge sort on 64-bit ones, so the same order
    (a stable sort of equal keys is one permutation) costs a pass per byte instead of
    m log m (the spill's argsort took 0.96 s of its 1.6 s at 12M points)."""
    return tiles.astype(np.uint16) if count <= 1 << 16 else tiles


def _rect_mask(records: np.ndarray, rect) -> np.ndarray:
    """(m,) bool: which records (with fields x, y) lie in the closed rectangle (x0, y0, x1,
    y1); the kernel's one pass over the rows (survey/_tile_spill.pyx: 1.4 ms against 0.3 ms
    for a tile of 245k rows)."""
    mask = np.empty(len(records), dtype=np.uint8)
    kernel.in_rect(records["x"], records["y"], *map(float, rect), mask)
    return mask.view(bool)


def _in_rect(records: np.ndarray, rect) -> np.ndarray:
    """The records in the closed rectangle, in their order (np.compress: see TileSpill.records)."""
    return np.compress(_rect_mask(records, rect), records)


def _meeting(far: np.ndarray, cell) -> np.ndarray:
    """(m,) bool: the far reads (m, 3: x, y, radius) whose squares meet the closed cell."""
    x0, y0, x1, y1 = cell
    return ((far[:, 0] + far[:, 2] >= x0) & (far[:, 0] - far[:, 2] <= x1)
            & (far[:, 1] + far[:, 2] >= y0) & (far[:, 1] - far[:, 2] <= y1))


def spill(chunks: Iterable[np.ndarray], frame, grid: TileGrid, directory=None, stem: str = "c1mesh") -> TileSpill:
    """A TileSpill (entered: close it, or use it in a with block) of world points (m, 3)
    given in chunks in survey order, numbered 0, 1, ... in that order, in `frame`'s local
    coordinates. A failure while spilling removes the files."""
    result = TileSpill(grid, directory, stem).__enter__()
    try:
        start = 0
        for points in chunks:
            local = frame.to_local(np.asarray(points, dtype=np.float64))
            result.add(np.arange(start, start + len(local), dtype=np.int64), local)
            start += len(local)
    except BaseException:
        result.close()
        raise
    return result


def file_blocks(file, dtype, rows: int) -> Iterator[np.ndarray]:
    """Arrays of up to `rows` records of dtype read from an open binary file to its end,
    each allocated at the size it is read. np.fromfile(count=rows) allocates all `rows`
    and shrinks the array when fewer remain; glibc then keeps the shrunken blocks' tails
    apart (measured: the noise floors' median over 289 tile residual files grew the
    parent from 171 to 434 MB at 12M points)."""
    dtype = np.dtype(dtype)
    remaining = (os.fstat(file.fileno()).st_size - file.tell()) // dtype.itemsize
    while remaining > 0:
        part = np.fromfile(file, dtype, count=min(rows, remaining))
        if not len(part):
            return
        remaining -= len(part)
        yield part
