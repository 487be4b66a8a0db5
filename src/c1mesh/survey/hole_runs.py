"""A DEM's fill over the tiles: the survey's long triangles (c1mesh.stages.holes) found
from the tiles' short ones, and the reach of the halos across them.

The in-memory fill (pipeline.driver.filled_mesh) spans the trim's holes with the long
Delaunay triangles the tiles never certify. Here: every tile's rim points from its halo
of short triangles (holes.rim_points), one Del(rim points) in this process (a few
percent of the survey: a budget check refuses more), and each candidate's centroid asked
of the halo of the tile whose cell holds it (a short triangle holding a point of a cell
has its corners within one longest edge of it: that halo holds it).

A long triangle is as wide as its hole, so a halo of 4 longest short edges (halos) does
not hold the stars of its far corners. `far_centres` lists, per tile, the points whose
neighbourhood its halo must read besides its cell's: the corners of the long triangles
reached from the cell, up to four long hops (the limiter's rings, halos' docstring),
each with the radius the rings left need; halos.HaloCache reads the records within it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.lazy import LazyModule
from c1mesh.core.threads import map_in_threads
from c1mesh.stages.holes import rim_points, short_cover, spanning_triangles
from c1mesh.stages.trim import kept_triangles
from c1mesh.survey.halos import HALO_EDGES, HaloCache
from c1mesh.survey.tile_spill import save_array
from c1mesh.survey.trim_runs import trim_tiles

spatial = LazyModule("scipy.spatial")


@dataclass(frozen=True)
class TiledFill:
    """A DEM's fill over the tiles (module docstring), as pipeline.driver.filled_mesh makes
    it in memory: the union of the trimmed triangles and the whole triangulation (short
    and long triangles) trimmed without max_edge and without the view-ray curtain rules.
    files: per tile the whole triangulation's own triangles (.npy, or None), copied from
    the short ones before the trim; far: the halos' far reads (far_centres); triangles:
    (k, 3) global point indices of the long triangles (stages.holes.spanning_triangles of
    the rim points); rims: the rim points (RIM: survey index, x, y in the plane)."""

    files: list
    far: dict
    triangles: np.ndarray
    rims: np.ndarray

    @classmethod
    def prepare(cls, halos, max_edge: float | None, memory: int, name: str, temps) -> "TiledFill":
        """From the halos of the short triangles (halos.HaloCache, before the trim; its
        files are copied): the long triangles (none without a max_edge) added to their
        owners' copies, and the far reads."""
        triangles, rims = np.empty((0, 3), np.int64), np.empty(0, RIM)
        if max_edge is not None:
            triangles, rims = long_triangles(halos, max_edge, memory, name)
        return cls(add_long_triangles(halos.files, halos.grid, triangles, rims, temps, "whole"),
                   far_centres(triangles, rims, halos.grid, halos.reach / HALO_EDGES), triangles, rims)

    def filled(self, trimmed: list, heights, reach: float, temps, where) -> "Filled":
        """The filled triangulation (Filled) from the tiles' files after the trim (trimmed).
        The whole triangulation is trimmed here (trim_runs.trim_tiles, without the view
        rules); where: (runner, name)."""
        runner, name = where
        whole = HaloCache(heights, self.files, heights.grid, reach, temps, "whole", far=self.far)
        whole.prefetch(runner, name)
        trim_tiles(whole, whole.grid, temps, False, runner, name)
        files, counts, spanning = [], [], []
        for t, (kept, other) in enumerate(zip(trimmed, self.files)):
            kept = np.load(kept) if kept is not None else np.empty((0, 3), np.int64)
            other = np.load(other) if other is not None else np.empty((0, 3), np.int64)
            counts.append(len(kept))
            added = other[kept_triangles(other, kept)]
            spanning.append(added)
            union = np.concatenate([kept, added])
            if not len(union) and trimmed[t] is None:
                files.append(None)
                continue
            path = temps.new(f"filled-{t}.npy")
            save_array(path, union)
            files.append(path)
        added = np.concatenate(spanning) if spanning else np.empty((0, 3), np.int64)
        long = self.triangles[~kept_triangles(self.triangles, added)] if len(added) else self.triangles[:0]
        return Filled(files, tuple(counts), far_centres(long, self.rims, heights.grid, reach / HALO_EDGES),
                      np.unique(added))


@dataclass(frozen=True)
class Filled:
    """A DEM's filled triangulation over the tiles: files, per tile the .npy of its own
    triangles (or None), the trimmed ones first; trimmed, per tile how many those are;
    far, its halos' far reads (far_centres of the long triangles it kept); spanning, the
    survey numbers of the corners of the triangles that span holes, ascending."""

    files: list
    trimmed: tuple
    far: dict
    spanning: np.ndarray


RIM = np.dtype([("index", "<i8"), ("x", "<f8"), ("y", "<f8")])
"""A rim point: its survey number and position in the frame's plane."""

RIM_POINT_BYTES = 200
"""Memory per rim point of the Del(rim points) and its candidates' tests (bytes)."""


def rim_records(halos) -> np.ndarray:
    """The survey's rim points (RIM records, ascending survey numbers), each tile's owned
    ones from its halo of short triangles (before the trim), and the points of its cell in
    no short triangle (a halo keeps only the points its triangles use), in the thread
    knob's threads."""
    def of(t: int) -> np.ndarray:
        halo = halos.halo(t)
        cell = halos.heights.tile(t)
        records = np.concatenate([halo.records[rim_points(halo)],
                                  cell[~np.isin(cell["index"], halo.records["index"])]])
        rim = np.empty(len(records), RIM)
        for name in RIM.names:
            rim[name] = records[name]
        return rim
    parts = map_in_threads(of, [t for t in range(len(halos.grid))])
    rims = np.concatenate(parts) if parts else np.empty(0, RIM)
    return rims.take(np.argsort(rims["index"], kind="stable"))


def long_triangles(halos, max_edge: float, memory: int, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(the survey's long triangles (k, 3) in survey numbers, holes.spanning_triangles'
    form; the rim points, RIM records): from the halos of the short triangles (halos:
    halos.HaloCache before the trim). memory: the budget (bytes); InputError naming the
    survey (name) when the rim points need more."""
    rims = rim_records(halos)
    if len(rims) * RIM_POINT_BYTES > memory:
        raise InputError(f"{name}: the DEM's fill spans holes whose rims hold {len(rims)} points, more than "
                         "--memory holds at once: give --fill off, or raise --memory")
    xy = np.column_stack([rims["x"], rims["y"]])
    grid = halos.grid

    def covered(centroids: np.ndarray) -> np.ndarray:
        held = np.zeros(len(centroids), dtype=bool)
        owner = grid.tile_of(centroids)

        def ask(t: int) -> None:
            members = np.flatnonzero(owner == t)
            halo = halos.halo(t)
            points = halo.points               # a triangle holding a centroid has its corners within max_edge
            near = spatial.cKDTree(centroids[members]).query(points, distance_upper_bound=max_edge * (1 + 1e-9))[0]
            triangles = halo.triangles[np.isfinite(near)[halo.triangles[:, 0]]]
            held[members] = short_cover(points, triangles)(centroids[members])
        map_in_threads(ask, np.unique(owner).tolist())
        return held
    return spanning_triangles(xy, rims["index"], max_edge, covered), rims


def add_long_triangles(files, grid, triangles: np.ndarray, rims: np.ndarray, temps, label: str) -> list:
    """Copies of the tiles' triangle files (files: per tile a .npy or None) with the long
    triangles (k, 3) added to their owners' (the tile of the lowest-numbered corner, as
    buffered_delaunay owns a triangle), in new files named by label; rims: RIM records
    holding every corner."""
    lowest = np.searchsorted(rims["index"], triangles[:, 0])         # lowest first: holes' form
    owner = grid.tiles_of(rims["x"][lowest], rims["y"][lowest])
    copies = []
    for t, path in enumerate(files):
        own = triangles[owner == t]
        if path is None and not len(own):
            copies.append(None)
            continue
        copy = temps.new(f"{label}-{t}.npy")
        short = np.load(path) if path is not None else np.empty((0, 3), np.int64)
        save_array(copy, np.concatenate([short, own]))
        copies.append(copy)
    return copies


def far_centres(triangles: np.ndarray, rims: np.ndarray, grid, edge: float) -> dict:
    """{tile: (m, 3) x, y and radius of the far reads of its halo} (module docstring).

    A halo holds the points within HALO_EDGES (4) longest short edges (edge) of its cell,
    for the limiter: the stars of the points within 3 rings of its own, and their points
    (halos' docstring). A long triangle's corner within 3 edges of the cell may be at ring
    3, its other corners at ring 4: the k-th long hop of a path lands at ring k or more,
    whose points within 4 − k rings it needs, and no point lies beyond 4 edges of a
    path's last landing. So: the corners of the long triangles (k, 3) with a corner
    within 3 edges of the cell are read around within 3 edges; then, for k = 2, 3, 4,
    the corners of those with a corner within the last hop's radius of its corners are
    read around within 4 − k edges (the fourth's only the point). The max norm, as a
    halo's rectangle. rims: RIM records holding every corner."""
    if not len(triangles):
        return {}
    corners = np.unique(triangles)
    at = np.searchsorted(rims["index"], corners)
    xy = np.column_stack([rims["x"][at], rims["y"][at]])
    rows = np.searchsorted(corners, triangles)                        # (k, 3) rows of corners
    tree = spatial.cKDTree(xy)
    by_corner = _triangles_of_corners(rows, len(corners))
    slack = 1 + 1e-9
    centres = {}
    for t in range(len(grid)):
        x0, y0, x1, y1 = grid.grown(t, (HALO_EDGES - 1) * edge * slack)
        front = np.flatnonzero((xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1))
        radius = np.full(len(corners), -1.0)
        for hop in range(1, HALO_EDGES + 1):
            far = np.unique(rows[by_corner(front)])
            far = far[radius[far] < 0]
            if not far.size:
                break
            radius[far] = reach = (HALO_EDGES - hop) * edge * slack
            front = np.unique(np.concatenate(tree.query_ball_point(xy[far], reach, p=np.inf))).astype(np.int64)
        read = radius >= 0
        if read.any():
            centres[t] = np.column_stack([xy[read], radius[read]])
    return centres


def _triangles_of_corners(rows: np.ndarray, count: int):
    """by_corner(corners (c,)) -> the rows of the triangles (k, 3 corner rows) that have one
    of them (CSR lists of each corner's triangles)."""
    flat = rows.ravel()
    order = np.argsort(flat, kind="stable")
    start = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=count))])
    triangle = order // 3

    def by_corner(corners: np.ndarray) -> np.ndarray:
        if not corners.size:
            return np.empty(0, np.int64)
        return np.unique(np.concatenate([triangle[start[c]:start[c + 1]] for c in corners.tolist()]))
    return by_corner
