"""Delaunay triangulation of a survey cut into rectangular tiles, with buffers sized by the data.

The survey's points lie in the frame's plane (2-D, the height field's xy) inside the
survey's bounding box B. The box is cut into an nx × ny grid of tiles; tile t holds the
points that fall in its cell (half-open cells, the last row and column closed). A tile
reads its cell grown by a buffer b, the closed rectangle E, and triangulates what it read
(Q = the points in E) on its own.

The buffer rule (why a tile's triangles are final). A triangle of Del(Q) whose open
circumdisk holds no point of the survey is a triangle of the survey's Delaunay
triangulation Del(P). Every point the tile has not read lies in B \\ E, so a triangle is
*safe* when its circumdisk does not reach B \\ E. A hull edge of Q is safe when the open
half-plane beyond it does not reach B \\ E (then it is a hull edge of P too). The tests
are conservative: a disk or half-plane that only touches B \\ E counts as reaching it.

The ownership rule (who writes a triangle). A triangle belongs to the tile holding its
lowest-numbered corner point (points numbered as the survey gives them), the rule
c1mesh.survey.tiles uses for inputs. A tile's result is final when every triangle of Del(Q) at
one of its own points is safe, and so is every hull edge of Q at one of its own points:
then the star of each own point p in Del(Q) is its star in Del(P). (The safe triangles
around p are triangles of Del(P) and cover a whole neighbourhood of p, or, with p on Q's
hull, the whole angle between its two safe hull edges, beyond which P has no points;
Del(P)'s triangles at p cannot overlap them, so they are the same.) Otherwise the buffer
is doubled and the tile triangulated again; at worst E covers B, Q = P and every triangle
is safe, so the loop ends. The union over tiles of the triangles each tile owns is
therefore Del(P), every triangle exactly once, whatever the grid; cocircular points too,
as engine.triangulation is exact on the survey's coordinates (a tile triangulates them
unshifted) and cuts ties by them and the point numbers alone: dense tiles end with the
first buffer, sparse ones
(ground under trees, water) grow theirs.

A tile needs its points only through `read(rectangle)`, so points may come from memory
(`ArrayReader`) or from files binned on a first pass; a tile holds only what it read.
The plane geometry of the safety tests (unread strips, the hull clipped to them,
circumcircles, clear disks and half-planes) is c1mesh.survey.strip_geometry.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.lazy import LazyModule
from c1mesh.core.threads import map_in_threads
from c1mesh.survey import _buffered_delaunay as kernel
from c1mesh.engine.triangulation import delaunay_with_neighbours
from c1mesh.formats.copc import inside
from c1mesh.stages.trim import AUTO_EDGE_FACTOR
from c1mesh.stages.streamed_median import order_statistic
from c1mesh.survey.strip_geometry import (
    centres_clear,
    circumcircles,
    clip_to_hull,
    disks_clear,
    flags_and_edges,
    hull_edges_final,
    smallest_empty_circle,
    triangle_flags,
    unread_strips,
)

spatial = LazyModule("scipy.spatial")

Reader = Callable[[tuple[float, float, float, float]], tuple[np.ndarray, np.ndarray]]
"""read((x0, y0, x1, y1)) -> (index (m,) int64 ascending survey point numbers, xy (m, 2)
float64) of the points in the closed rectangle."""

INITIAL_SPACINGS = 4.0
"""The first buffer, in mean point spacings (sqrt(area of B / point count))."""


@dataclass(frozen=True)
class TileGrid:
    """An nx × ny grid of equal cells over the box (x0, y0, x1, y1) (frame units)."""

    box: tuple[float, float, float, float]
    nx: int
    ny: int

    def cell(self, t: int) -> tuple[float, float, float, float]:
        """The rectangle of tile t (t = i + nx·j)."""
        x0, y0, x1, y1 = self.box
        i, j = t % self.nx, t // self.nx
        w, h = (x1 - x0) / self.nx, (y1 - y0) / self.ny
        return (x0 + i * w, y0 + j * h, x1 if i == self.nx - 1 else x0 + (i + 1) * w,
                y1 if j == self.ny - 1 else y0 + (j + 1) * h)

    def grown(self, t: int, by: float) -> tuple[float, float, float, float]:
        """The closed rectangle of tile t's cell grown by `by` on every side (what a tile
        reads for its buffer or halo)."""
        cell = self.cell(t)
        return (cell[0] - by, cell[1] - by, cell[2] + by, cell[3] + by)

    def tile_of(self, xy: np.ndarray) -> np.ndarray:
        """(m,) int64 the tile of each point (m, 2) (finite): half-open cells, points on the
        box's far sides in the last row or column, points outside in the nearest."""
        xy = np.asarray(xy, dtype=np.float64)
        return self.tiles_of(xy[:, 0], xy[:, 1])

    def tiles_of(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """`tile_of` of the points with coordinates x, y (m,) each, which may be a record
        array's fields (no stacked copy). The kernel (survey/_buffered_delaunay.pyx), one
        pass: a halo load called it for every point it read."""
        out = np.empty(len(x), dtype=np.int64)
        kernel.tiles_of(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64),
                        *map(float, self.box), self.nx, self.ny, out)
        return out

    def __len__(self) -> int:
        return self.nx * self.ny


class ArrayReader:
    """A Reader over points held in memory, (n, 2) in survey order."""

    def __init__(self, xy: np.ndarray):
        self.xy = np.asarray(xy, dtype=np.float64)

    def __call__(self, rect):
        index = np.flatnonzero(inside(self.xy[:, 0], self.xy[:, 1], rect))
        return index, self.xy[index]


@dataclass
class TileTriangles:
    """One tile's final triangles: triangles (k, 3) int64 survey point numbers, in the
    orientation Qhull gave; buffer: the buffer (frame units) it ended with; read: points
    read in the last round; rounds: triangulations it took."""

    tile: int
    triangles: np.ndarray
    buffer: float
    read: int
    rounds: int


def mean_spacing(box, count: int) -> float:
    """sqrt(area / count): the mean distance between neighbouring points, frame units."""
    x0, y0, x1, y1 = box
    return float(np.sqrt(max((x1 - x0) * (y1 - y0), 1e-300) / max(count, 1)))


@dataclass(frozen=True)
class Hull:
    """The survey's convex hull: index (h,) survey numbers of its corner points and xy
    (h, 2) their coordinates, counter-clockwise. Found on the first pass (`streamed_hull`)."""

    index: np.ndarray
    xy: np.ndarray

    def edges(self) -> set[tuple[int, int]]:
        """The hull's edges as (lower, higher) survey numbers."""
        a, b = self.index, np.roll(self.index, -1)
        return set(zip(np.minimum(a, b).tolist(), np.maximum(a, b).tolist()))


def streamed_hull(chunks) -> Hull:
    """The convex hull of points given in chunks of (index (m,), xy (m, 2)), holding only
    one chunk and the hull so far: the hull of the union is the hull of the chunks' hulls."""
    index, xy = np.empty(0, np.int64), np.empty((0, 2))
    for chunk_index, chunk_xy in chunks:
        index = np.concatenate([index, np.asarray(chunk_index, np.int64)])
        xy = np.concatenate([xy, np.asarray(chunk_xy, np.float64)])
        if len(index) >= 3:
            corners = spatial.ConvexHull(xy).vertices                 # counter-clockwise in 2-D
            index, xy = index[corners], xy[corners]
    return Hull(index, xy)


def hull_of_parts(parts: list[Callable[[], tuple[np.ndarray, np.ndarray]]]) -> Hull:
    """`streamed_hull` of the parts that the callables read, each (index (m,), xy (m, 2)):
    each part is read and reduced to its own hull in the thread knob's threads (qhull
    releases the GIL), then those hulls are merged in order. A corner of the whole hull
    is a corner of its part's hull, so this is streamed_hull's hull, found in parallel
    (the 12M-point survey's 49 tiles: 2.2 s one by one in the parent)."""
    return streamed_hull(map_in_threads(lambda read: _part_hull(*read()), parts))


def _part_hull(index: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index, xy) of the corners of points xy (m, 2)'s convex hull; every point when there
    are fewer than 3 or qhull finds no 2-D hull (all on one line)."""
    index, xy = np.asarray(index, np.int64), np.asarray(xy, np.float64)
    if len(index) < 3:
        return index, xy
    try:
        corners = spatial.ConvexHull(xy).vertices
    except spatial.QhullError:
        return index, xy
    return index[corners], xy[corners]


def tile_triangles(read: Reader, grid: TileGrid, tile: int, buffer: float,
                   hull: Hull | None = None, max_edge: float | None = None,
                   most: int | None = None) -> TileTriangles:
    """Triangulate one tile, growing its buffer until its own triangles are final (module
    docstring); buffer: the first one, frame units (> 0). hull: the survey's convex hull
    from a first pass, or None. With it, points not read are known to lie in the hull as
    well as outside the read rectangle, and a hull edge of what was read is final when it
    is an edge of the survey's hull, so tiles along the survey's border keep small buffers
    (without it, their hull triangles' wide circles make them read most of the survey).
    max_edge: keep only the triangles whose edges are all at most this long (the long-edge
    trim), which needs only those to be safe once the buffer exceeds max_edge (module
    docstring); None keeps every triangle. most: the most points a read may hold (the
    memory budget's share; None: no limit). Without max_edge a border tile's hull
    slivers can need most of the survey's border read; past `most` that is an
    InputError instead of a read the budget cannot hold."""
    box, cell = grid.box, grid.cell(tile)
    if max_edge is not None:
        buffer = max(buffer, max_edge * (1 + 1e-9))
    hull_edges = None if hull is None else hull.edges()
    for reading in growing_reads(read, grid, tile, buffer):
        read_box, index, xy, own, covers = reading.box, reading.index, reading.points, reading.own, reading.covers
        buffer, rounds = reading.buffer, reading.round
        if not own.any() or (index.size < 3 and covers):
            return TileTriangles(tile, np.empty((0, 3), np.int64), buffer, len(index), rounds)
        if index.size < 3:
            continue
        if most is not None and index.size > most:
            raise InputError(f"without a --max-edge the triangles along the survey's border reach so "
                             f"far that this tile must read {index.size:,} points, more than --memory "
                             f"allows a tile ({most:,}); keep --max-edge auto (the default) or raise --memory")
        centre = np.array([(cell[0] + cell[2]) / 2, (cell[1] + cell[3]) / 2])
        local = xy - centre                          # small coordinates: circumcentres round less
        simplices, neighbours = delaunay_with_neighbours(xy)
        # survey coordinates for the lengths: trim's bits
        _, at_own, mine = triangle_flags(xy, simplices, own, index, np.inf if max_edge is None else max_edge)
        if covers:
            safe = True
        else:
            strips = unread_strips(read_box, box, centre)
            regions = None if hull is None else clip_to_hull(strips, hull.xy - centre)
            safe = (disks_clear(local, simplices[at_own], strips, regions).all()
                    and (max_edge is not None
                         or hull_edges_final(local, index, simplices, neighbours,
                                             own, strips, hull_edges)))
        if safe:
            keep = simplices[mine]
            return TileTriangles(tile, index[keep], buffer, len(index), rounds)


@dataclass
class Reading:
    """One read of a tile with a buffer: round (1, 2, ...), buffer (frame units), box (x0,
    y0, x1, y1) read, index (m,) survey numbers and points (m, 2 or 3) read, own (m,) bool
    the points in the tile's cell, covers: the box holds the whole survey."""

    round: int
    buffer: float
    box: tuple
    index: np.ndarray
    points: np.ndarray
    own: np.ndarray
    covers: bool


def growing_reads(read: Callable, grid: "TileGrid", tile: int, buffer: float) -> Iterator[Reading]:
    """Reads of a tile's cell widened by `buffer`, the buffer doubled for each next one: a
    caller takes readings until what it needs lies inside what was read (or it covers the
    survey), so buffers are sized by the data."""
    rounds = 0
    while True:
        rounds += 1
        box = grid.grown(tile, buffer)
        index, points = read(box)
        yield Reading(rounds, buffer, box, index, points, grid.tile_of(points[:, :2]) == tile,
                      _covers(box, grid.box))
        buffer *= 2.0


def _covers(read_box, box) -> bool:
    return read_box[0] <= box[0] and read_box[1] <= box[1] and read_box[2] >= box[2] and read_box[3] >= box[3]


def buffered_delaunay(read: Reader, grid: TileGrid, count: int, buffer: float | None = None,
                      hull: Hull | None = None, max_edge: float | None = None) -> Iterator[TileTriangles]:
    """Each tile's final triangles, tile by tile (module docstring). count: the survey's
    point count (sizes the first buffer: INITIAL_SPACINGS mean spacings unless given);
    hull: the survey's convex hull (streamed_hull), which keeps border tiles' buffers small;
    max_edge: keep only triangles with every edge at most this long (None: all)."""
    first = buffer if buffer is not None else INITIAL_SPACINGS * mean_spacing(grid.box, count)
    for tile in range(len(grid)):
        yield tile_triangles(read, grid, tile, first, hull, max_edge)


# ------------------------------------------------- one pass: the trimmed triangulation
@dataclass
class TilePass:
    """What one triangulation of a tile certifies for a bound B: short (e,) lengths of the
    survey's Delaunay edges of length <= B at its own points (an edge belongs to the tile
    of its lower-numbered end; trimmed_delaunay's median);
    triangles (k, 3) survey numbers of the survey's Delaunay triangles it owns whose edges
    are all <= B, longest (k,) their longest edge; buffer, read, rounds as TileTriangles."""

    tile: int
    short: np.ndarray
    triangles: np.ndarray
    longest: np.ndarray
    buffer: float
    read: int
    rounds: int


def tile_pass(read: Reader, grid: TileGrid, tile: int, bound: float, hull: Hull) -> TilePass:
    """Triangulate one tile once for both the edge statistic and the trimmed triangles up
    to `bound` (frame units), growing its buffer (from bound) until both are certified.

    A triangle is certified by its circumdisk (the module docstring's buffer rule); an
    edge of the tile's triangulation is an edge of the survey's when one of its triangles
    is certified, or else when one circle through its two ends is empty of what was read
    and clear of what was not: the smallest circle of the pencil between the
    circumcircles of its two triangles (for a short edge usually its diametral circle,
    which a buffer above `bound` always holds)."""
    box, cell = grid.box, grid.cell(tile)
    for reading in growing_reads(read, grid, tile, bound * (1 + 1e-9)):
        read_box, index, xy, own, covers = reading.box, reading.index, reading.points, reading.own, reading.covers
        buffer, rounds = reading.buffer, reading.round
        if not own.any() or index.size < 3:
            if not own.any() or covers:
                empty = np.empty(0)
                return TilePass(tile, empty, np.empty((0, 3), np.int64), empty, buffer, len(index), rounds)
            continue
        centre = np.array([(cell[0] + cell[2]) / 2, (cell[1] + cell[3]) / 2])
        local = xy - centre
        simplices, neighbors = delaunay_with_neighbours(xy)
        longest, at_own, triangle_mine, edges, lengths = flags_and_edges(xy, simplices, neighbors, own, index,
                                                                          bound)
        if not covers:
            strips = unread_strips(read_box, box, centre)
            regions = clip_to_hull(strips, hull.xy - centre)
            centres, radius = circumcircles(local, simplices)
            scale = np.abs(local).max()
            beyond = _UnreadCheck(read, read_box, grid.grown(tile, 2 * buffer), centre, strips, scale)
            if not beyond.clear(centres[at_own], radius[at_own], regions):
                continue
            # an edge of a triangle certified above is an edge of the survey's triangulation;
            # the others (both triangles longer than the bound, or a hull edge beside one)
            # are certified by their own smallest empty circle
            alone = _edges_without(at_own, neighbors, edges)
            circle, circle_radius = smallest_empty_circle(local, simplices, neighbors, *edges[alone].T, centres)
            if not beyond.clear(circle, circle_radius, regions):
                continue
        return TilePass(tile, lengths, index[simplices[triangle_mine]], longest[triangle_mine],
                        buffer, len(index), rounds)


UNREAD_DISKS = 64
"""The most disks that reach the unread strips a tile pass checks against the points
there (`_UnreadCheck`) before it doubles its buffer instead."""


@dataclass(frozen=True)
class _UnreadCheck:
    """A pass's disks against what it did not read. The buffer rule needs a disk that
    reaches an unread strip B \\ E to hold no survey point there; the strips' rectangles
    only bound where such points may lie, so a disk reaching one (a hull sliver's or a
    sliver's beside a building's hole, whose circle spans the empty hole: 7 of the 12M
    survey's 49 tiles, each by one or two triangles) made the whole tile be read and
    triangulated again with its buffer doubled. Reading the points in those disks' part
    of the strips instead settles them at the cost of a small read: a disk none of whose
    unread points lies in it (grown as centres_clear grows it) is clear, as certain as the
    strip test, as the points read are the survey's.

    read: the pass's Reader; read_box: what it read; next_box: the next round's read (a
    check that would read more than it holds doubles the buffer instead); offset: the
    tile's centre (disks and strips are relative to it); scale: centres_clear's."""

    read: Callable
    read_box: tuple
    next_box: tuple
    offset: np.ndarray
    strips: np.ndarray
    scale: float

    def clear(self, centre: np.ndarray, radius: np.ndarray, regions) -> bool:
        """Whether every disk (centre (k, 2), radius (k,)) is clear of unread points:
        centres_clear's test, then the points of the few disks it does not clear."""
        ok = centres_clear(centre, radius, self.strips, regions, self.scale)
        if ok.all():
            return True
        return self._holds_no_unread_point(centre[~ok], radius[~ok])

    def _holds_no_unread_point(self, centre: np.ndarray, radius: np.ndarray) -> bool:
        if len(centre) > UNREAD_DISKS or not (np.isfinite(centre).all() and np.isfinite(radius).all()):
            return False                             # a collinear triangle's disk: never clear
        reach = radius * (1 + 1e-9) + 1e-12 * self.scale
        low = (centre - reach[:, None]).min(axis=0)
        high = (centre + reach[:, None]).max(axis=0)
        rects = [r for r in (_meet((*low, *high), strip) for strip in self.strips) if r is not None]
        if sum((r[2] - r[0]) * (r[3] - r[1]) for r in rects) > _area(self.next_box):
            return False
        pad = 1e-9 * float(np.abs(self.next_box).max())      # the shift back to survey coordinates rounds
        for rect in rects:
            _, xy = self.read(tuple((np.add(rect, np.tile(self.offset, 2)) + [-pad, -pad, pad, pad]).tolist()))
            unread = ~inside(xy[:, 0], xy[:, 1], self.read_box)
            points = xy[unread] - self.offset
            for (cx, cy), r in zip(centre.tolist(), reach.tolist()):
                if np.any((points[:, 0] - cx) ** 2 + (points[:, 1] - cy) ** 2 <= r * r):
                    return False
        return True


def _meet(a, b):
    """The closed rectangles a and b's intersection (x0, y0, x1, y1), or None."""
    rect = (max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3]))
    return rect if rect[0] <= rect[2] and rect[1] <= rect[3] else None


def _area(rect) -> float:
    return (rect[2] - rect[0]) * (rect[3] - rect[1])


def _edges_without(certified: np.ndarray, neighbors: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(e,) bool: the edges (e, 4) rows (t, k, a, b) of which neither triangle (t, and its
    neighbour across corner k's opposite edge, neighbors (T, 3), -1 on the hull) is
    certified (T,) bool."""
    t, k = edges[:, 0], edges[:, 1]
    other = neighbors[t, k]
    return ~certified[t] & ~(certified[np.maximum(other, 0)] & (other >= 0))


def trimmed_delaunay(read: Reader, grid: TileGrid, count: int, hull: Hull, max_edge="auto",
                     keep: Callable[[TilePass], object] = lambda p: p,
                     passes: Callable[[float], Iterable[tuple[np.ndarray, object]]] | None = None
                     ) -> tuple[float, list]:
    """The survey's Delaunay triangulation after the long-edge trim, tile by tile, with one
    triangulation per tile: (max_edge, [keep(pass) per tile]).

    max_edge: a length, or "auto" (trim's rule: AUTO_EDGE_FACTOR x the median edge of the
    whole triangulation, equal to trim's to the bit: n points in general position with h
    hull corners have E = 3n - 3 - h edges, so the median's ranks are known from the
    first pass, and it is selected among the short edges the tiles certify, `short_median`,
    once more than half of the E edges are that short). Each tile certifies up to a bound B (max_edge, or for
    "auto" 2 x AUTO_EDGE_FACTOR mean spacings, raised and the pass repeated in the rare
    case the median comes out above it); its TilePass holds triangles up to B, of which
    those with longest <= max_edge are the result. keep(pass) is what is kept per tile
    (the default keeps the pass; a caller short of memory writes it to disk and keeps a path).
    passes(bound): instead of the tile loop here, the (short lengths, kept) of every tile's
    tile_pass up to bound, in any order (the median does not depend on it), the kept list
    in that order (c1mesh.survey.delaunay_runs runs the tiles as tasks this way); a tile's short
    lengths may be an array or the path of a .npy file holding it (`short_median`).
    """
    edges = 3 * count - 3 - len(hull.index)
    auto = isinstance(max_edge, str)
    bound = 2.0 * AUTO_EDGE_FACTOR * mean_spacing(grid.box, count) if auto else float(max_edge)

    def one_by_one(bound):
        for tile in range(len(grid)):
            result = tile_pass(read, grid, tile, bound, hull)
            short, result.short = result.short, None
            yield short, keep(result)

    while True:
        shorts, kept = [], []
        for short, result in (passes or one_by_one)(bound):
            shorts.append(short)
            kept.append(result)
        if not auto:
            return bound, kept
        median = short_median(shorts, edges)
        if median is not None:
            limit = float(AUTO_EDGE_FACTOR * median)
            if limit <= bound:
                return limit, kept
            bound = limit
        else:
            bound *= 2.0


SHORT_GATHER = 1 << 20
"""short_median collects at most this many lengths (8 MB) to partition them."""


def short_median(shorts: list, edges: int) -> float | None:
    """The median of the survey's `edges` Delaunay edge lengths from the certified short
    ones (per tile an array, or the path of a .npy file of it; each at most the bound,
    so every longer edge ranks above them): the value np.partition of their
    concatenation gives, to the bit, or None when at most half of the edges are short.

    The lengths are never concatenated (about 3 per survey point): the ranks are found
    by streamed_median.order_statistic, holding one tile's lengths and at most
    SHORT_GATHER candidates, so the parent's memory does not grow with the survey."""
    def chunks():
        for short in shorts:
            yield np.load(short) if isinstance(short, (str, os.PathLike)) else short
    if sum(_length(short) for short in shorts) <= edges // 2:
        return None
    upper = edges // 2
    if edges % 2:
        return order_statistic(chunks, upper, SHORT_GATHER)
    middle = [order_statistic(chunks, rank, SHORT_GATHER) for rank in (upper - 1, upper)]
    return float(np.mean(np.array(middle)))


def _length(short) -> int:
    """Values in a 1-D array, or in the .npy file at a path (read from its header)."""
    if not isinstance(short, (str, os.PathLike)):
        return len(short)
    with open(short, "rb") as file:
        version = np.lib.format.read_magic(file)
        header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                  else np.lib.format.read_array_header_2_0)
        shape, _, _ = header(file)
    return int(np.prod(shape))
