"""Points binned to tiles on disk: the first pass of a survey larger than memory.

The survey's points arrive in chunks, in survey order (LAS/LAZ by laspy's chunk iterator).
Each chunk is projected to the frame's plane and its rows are appended to one spill file
per tile of a buffered_delaunay.TileGrid; a tile then reads its cell and buffer from the
few spill files those rectangles touch, never the survey. A row is (survey number int64,
x, y, height float64) in the frame; files are raw arrays of that record (np.fromfile).

Spill files are hidden files `.NAME.spill-PID-T.bin` beside the output (or in $TMPDIR),
registered with c1mesh.core.outputs, so they are removed when the spill is closed, when the
block that made it fails, and when the process is interrupted (SIGINT, SIGTERM, SIGHUP).

Rims. A tile's buffer or halo reaches a few metres into its eight neighbours, and reading
each of them whole to keep a strip of it was most of a read's time (18 ms for a 4 m
buffer over 245k-point tiles, 8 of the 9 tiles' records thrown away). A spill made with a
rim width W keeps, beside each tile file written whole (`write_tile`), a rim file: the
tile's records within W of its cell's sides, in eight parts (four sides, four corners),
each in survey order. A read whose rectangle meets only rim parts of a tile reads just
those parts; the records it keeps, and their order after the read's sort, are the same.
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
                 record: np.dtype = RECORD, rim: float | None = None):
        self.grid, self.record = grid, record
        self.directory = Path(directory if directory is not None else tempfile.gettempdir())
        self.paths = [self.directory / f".{stem}.spill-{os.getpid()}-{t}.bin" for t in range(len(grid))]
        self.counts = np.zeros(len(grid), dtype=np.int64)
        self.rim = None if rim is None else _rim_width(grid, rim)
        self.rim_paths = [] if self.rim is None else [path.with_suffix(".rim") for path in self.paths]
        # per tile the rows of its rim file's parts (cy * 3 + cx, the middle part 4 not
        # kept), set by set_tile; -1: no rim file (read the tile whole)
        self.rim_counts = np.full((len(grid), 9), -1, dtype=np.int64)
        self._created = False

    def __enter__(self) -> "TileSpill":
        """Create the (empty) spill files, once."""
        if not self._created:
            self._created = True
            for path in self.paths:
                register_temp(path)              # before the file exists: a signal finds nothing or it
                path.write_bytes(b"")
            for path in self.rim_paths:
                register_temp(path)              # written by write_tile
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Remove every spill file."""
        for path in self.paths + self.rim_paths:
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

    def write_tile(self, t: int, records: np.ndarray) -> np.ndarray:
        """Write tile t's records (its whole file, survey order), and with a rim width its
        rim file; returns the rim parts' row counts (9,) for set_tile (-1s without a rim).
        A task in another process writes, the parent then calls set_tile."""
        records = records.astype(self.record, copy=False)
        with open(self.paths[t], "wb") as file:
            records.tofile(file)
        if self.rim is None:
            return np.full(9, -1, dtype=np.int64)
        part = _rim_parts(records, self.grid.cell(t), self.rim)
        order = np.argsort(part, kind="stable")            # int8 keys: numpy's radix sort
        counts = np.bincount(part, minlength=9).astype(np.int64)
        middle = int(counts[:4].sum())                     # the middle part's rows, not kept
        order = np.concatenate([order[:middle], order[middle + int(counts[4]):]])
        counts[4] = 0
        with open(self.rim_paths[t], "wb") as file:
            records.take(order).tofile(file)
        return counts

    def set_tile(self, t: int, count: int, rim_counts: np.ndarray) -> None:
        """Record what write_tile wrote for tile t (in the process that reads the spill)."""
        self.counts[t] = count
        self.rim_counts[t] = rim_counts

    def tile(self, t: int) -> np.ndarray:
        """The records of tile t, in survey order."""
        return np.fromfile(self.paths[t], dtype=self.record)

    def _near_rect(self, t: int, rect) -> list[np.ndarray]:
        """Tile t's records that may lie in the closed rectangle, as arrays each in survey
        order: the parts of its rim that the rectangle meets, when it meets no others;
        else the whole tile."""
        parts = self._rim_parts_meeting(t, rect)
        if parts is None:
            return [self.tile(t)]
        starts = np.concatenate([[0], np.cumsum(self.rim_counts[t])])
        with open(self.rim_paths[t], "rb") as file:
            chunks = []
            for p in parts:
                file.seek(int(starts[p]) * self.record.itemsize)
                chunks.append(np.fromfile(file, dtype=self.record, count=int(self.rim_counts[t, p])))
        return chunks

    def _rim_parts_meeting(self, t: int, rect) -> list[int] | None:
        """The rim parts (cy * 3 + cx) of tile t that the closed rectangle meets, or None
        when it meets the middle (or the tile has no rim file)."""
        if self.rim is None or self.rim_counts[t, 0] < 0:
            return None
        xs, ys = _bands(self.grid.cell(t), self.rim)
        x_meets = _band_meets(xs, rect[0], rect[2])
        y_meets = _band_meets(ys, rect[1], rect[3])
        if x_meets[1] and y_meets[1]:
            return None
        return [cy * 3 + cx for cy in range(3) for cx in range(3)
                if x_meets[cx] and y_meets[cy] and self.rim_counts[t, cy * 3 + cx]]

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
        return _merged([_in_rect(part, rect) for t in self.touching(rect) for part in self._near_rect(t, rect)],
                       self.record)

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
            meeting = _meeting(far, self.grid.cell(t))
            if not meeting.any():
                parts.extend(_in_rect(part, rect) for part in self._near_rect(t, rect))
                continue
            r = self.tile(t)
            keep = _rect_mask(r, rect)
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
        return _merged(parts, self.record), tiles

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


RIM_SPACINGS = 40.0
"""A spill's rim width (`TileSpill(rim=...)`) in mean point spacings, as the height spill
sets it: the first buffers and halos reach 17-37 spacings (4 and 8.6 m at the 12M
survey's 0.24 m) into a neighbour; a doubled buffer beyond it reads the tile whole. A
4 m read around a 245k-point tile took 9 ms against 22 ms reading its neighbours whole;
the 12M survey used 4-5 % less CPU (two alternating pairs)."""


def _rim_width(grid: TileGrid, width: float) -> float:
    """The rim width: width, at most a quarter of the narrowest cell side (so a cell's
    middle band is never empty and the parts are ordered: x < lo <= hi < x)."""
    x0, y0, x1, y1 = grid.box
    return float(min(width, (x1 - x0) / grid.nx / 4, (y1 - y0) / grid.ny / 4))


def _bands(cell, width: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """((lo, hi) in x, (lo, hi) in y): a cell's three bands along each axis, coordinate
    below lo (0), from lo to hi (1), above hi (2); records outside the cell (a border
    tile's) fall in the outer bands."""
    x0, y0, x1, y1 = cell
    return (x0 + width, x1 - width), (y0 + width, y1 - width)


def _band_meets(band: tuple[float, float], a: float, b: float) -> tuple[bool, bool, bool]:
    """Whether the closed interval [a, b] meets each of the three bands (`_bands`)."""
    lo, hi = band
    return a < lo, a <= hi and b >= lo, b > hi


def _rim_parts(records: np.ndarray, cell, width: float) -> np.ndarray:
    """(m,) int8 each record's part cy * 3 + cx of the cell's bands (4: the middle)."""
    (xlo, xhi), (ylo, yhi) = _bands(cell, width)
    x, y = records["x"], records["y"]
    cx = (x >= xlo).astype(np.int8) + (x > xhi)
    cy = (y >= ylo).astype(np.int8) + (y > yhi)
    return (cy * 3 + cx).astype(np.int8)


def _merged(parts: list[np.ndarray], record: np.dtype) -> np.ndarray:
    """The records of parts (each ascending by survey number, the spill's record dtype)
    in one array, ascending by it, as a stable sort of their concatenation would give
    them: the parts but the longest sorted together, then merged with the longest by the
    kernel (one comparison and one record copy a row), so a tile's whole file beside its
    neighbours' strips is copied once (a 4 m read around a 245k-point tile: the
    concatenation, argsort and take took 5 ms of its 9). One output array and the short
    parts' sort: merging the parts two at a time left each read's intermediate arrays in
    the workers' held heap (their peak at the refinement 310 -> 380 MB). A repeated or
    descending number: the stable sort of the whole concatenation instead."""
    if not parts:
        return np.empty(0, record)
    if len(parts) == 1:
        numbers = parts[0]["index"]
        return parts[0] if bool(np.all(numbers[1:] > numbers[:-1])) else _sorted_concatenation(parts, record)
    if record.itemsize % 8 or record.fields["index"][:2] != (np.dtype("<i8"), 0):
        return _sorted_concatenation(parts, record)        # not the kernel's layout
    longest = max(range(len(parts)), key=lambda n: len(parts[n]))
    rest = _sorted_concatenation([p for n, p in enumerate(parts) if n != longest], record)
    out = np.empty(len(parts[longest]) + len(rest), record)
    if kernel.merge_two(_rows(parts[longest], record), _rows(rest, record), _rows(out, record)):
        return out
    return _sorted_concatenation(parts, record)


def _sorted_concatenation(parts: list[np.ndarray], record: np.dtype) -> np.ndarray:
    """The parts' records in one array, stably sorted by survey number."""
    records = np.concatenate(parts) if parts else np.empty(0, record)
    return records.take(np.argsort(records["index"], kind="stable"))


def _rows(records: np.ndarray, record: np.dtype) -> np.ndarray:
    """records (contiguous, of dtype record) as (m, itemsize) bytes, for the merge kernel."""
    return np.ascontiguousarray(records).view(np.uint8).reshape(len(records), record.itemsize)


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
