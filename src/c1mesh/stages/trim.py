"""Trimming of what should not be meshed: the fit's trim stage after the Delaunay triangulation.

`trim` removes triangles that bridge gaps (any edge longer than `max_edge`) and then peels
thin triangles ("slivers") off the boundary, because the spline divides by quantities that
vanish as triangles flatten; fans that touch the rest at one vertex ("bowties") go too.

The sliver and bow-tie rules are written once, as functions of a tile (`TrimTile`: the
triangles a tile holds, its vertices' survey numbers and which lie in its cell), and run
over the tiles of a `TrimRun`: the in-memory fit's one tile (`OneTile`, every vertex its
own) or a survey's (c1mesh.survey.trim_runs), so both remove the same triangles.

- which triangles are thin: per tile, `thin_triangles`, its own thin triangles (lowest
  corner in its cell) with whether each lies on the boundary: the summary;
- the peel: it removes every connected set of live thin triangles (joined through shared
  edges) that holds a triangle on the boundary (at first) or beside one removed since
  (later). Such a set may cross any number of tiles, so it is decided over the joined
  summaries (`peeled`, the reduce). Thin triangles are rare in a Delaunay triangulation
  (219 of 1M on synthetic terrain, 28 of 50k on Autzen ground), so their list fits in
  memory (`Thin`);
- bow-ties: per tile, `bowtie_cuts` at the vertices in its cell, whose whole star the
  tile holds; the fan kept is chosen by point numbers alone, so a tile decides as the
  whole triangulation does;
- the loop, `settle`: peel, cut the bow-ties, peel again from the cut fans' neighbours,
  until no bow-tie is left. A bow-tie can only appear at a corner of a triangle removed
  since the last look, so later rounds look there only, in the tiles holding them.
  `trim_run` starts it from the boundary, `retrim_run` from the holes a later rule cut
  (the curtains: curtains.remove_curtain_run).

Long edges are per tile too, in the triangulation (buffered_delaunay.tile_pass); the
"auto" max_edge is survey-wide (buffered_delaunay.trimmed_delaunay).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, partial
from typing import Any, Callable, Protocol

import numpy as np
from numpy.typing import ArrayLike

from c1mesh.core.errors import InputError
from c1mesh.core.threads import compress_rows, overlap, parallel_blocks
from c1mesh.core.tile import row_any, row_min, tile_rows
from c1mesh.engine.topology import EdgeTable, edge_table_sides, live_edges, sub_table
from c1mesh.engine.topology import triangle_neighbours as topology_neighbours
from c1mesh.engine.triangulation import as_xy
from c1mesh.stages import _trim as kernel

AUTO_EDGE_FACTOR = 4.0
"""max_edge="auto" is this times the median edge length. In the Delaunay triangulation of
uniform random points (the most irregular gap-free sampling) the longest edge of a triangle
stays below ~4x the median edge: 0-2 of 650,000 interior triangles exceed it. Real LiDAR
ground (4_6_crop.las, class 2) loses 4% of its area at 4x, mostly under trees and buildings
(81% of that area holds non-ground returns); at 2.5x it would also cut the many holes left
by one or two missing points."""


@dataclass
class TrimReport:
    """What `trim` did.

    triangles_before / triangles_after: counts in and out.
    removed: triangles removed by reason: "long_edge" (an edge longer than max_edge),
             "sliver" (thin boundary triangles), "bowtie" (fans that touched the rest of
             the mesh at a single vertex).
    max_edge: the edge-length limit used (local units), or None when disabled.
    unreferenced_points: points of xy that no remaining triangle uses.
    """

    triangles_before: int
    triangles_after: int
    removed: dict[str, int] = field(default_factory=dict)
    max_edge: float | None = None
    unreferenced_points: int = 0


KERNEL_BLOCK = 1 << 14
"""Triangles per block of the edge-length kernel, run in the thread knob's threads
(core.threads.parallel_blocks; Python threads, not OpenMP, whose thread pool does not
survive a fork: a forked --jobs worker would hang in it)."""

MIN_CIRCLE_RATIO = 0.01
"""trim's default: a boundary triangle whose inscribed/circumscribed radius ratio is below
this is a sliver (the in-memory and the tiled trim use the same value)."""


def check_triangles_left(count: int) -> None:
    """InputError when the trim left no triangle (`count` 0): nothing to fit or refine. Every
    path says it right after its trim, before the smoothing fit or the refinement."""
    if count == 0:
        raise InputError("no triangles are left after trimming; try --max-edge none")


def trim(xy: ArrayLike, triangles: ArrayLike, max_edge: str | float | None = "auto",
         min_circle_ratio: float = MIN_CIRCLE_RATIO) -> tuple[np.ndarray, TrimReport]:
    """Remove gap-bridging and thin boundary triangles; return (triangles (T', 3), report).

    xy:        (n, 2) plane points; triangles: (T, 3) indices into xy, e.g. from `delaunay`.
    max_edge:  triangles with an edge longer than this are removed (bridges over gaps,
               long hull triangles; holes stay holes). "auto" = AUTO_EDGE_FACTOR x the
               median edge length of the input triangulation; None (or "none") disables.
    min_circle_ratio: boundary triangles whose inradius/circumradius ratio, scaled so an
               equilateral triangle has 1 (matplotlib's TriAnalyzer ratio x 2), is below
               this are removed, repeatedly while newly exposed boundary triangles
               qualify. Interior triangles are never removed by this rule. 0 disables.
    Guarantees: the result is a subset of the input in input order and orientation; if
    the input is edge-manifold (every edge in at most 2 triangles, as any triangulation
    is) so is the result, and no vertex is a bowtie: the triangles around every vertex
    form one fan (where two fans met at a vertex, the smaller ones are removed).
    Raises InputError for bad shapes, indices, options, or a non-edge-manifold input.
    `trim_mesh` is the same trim for a fit that goes on with the kept triangles' edges.
    """
    pts = as_xy(xy)
    tri = _as_triangles(triangles, pts.shape[0])
    topology = overlap(lambda: triangle_neighbours(tri, pts.shape[0]),     # independent
                       lambda: edge_lengths(pts, tri))
    tile = TrimTile(tri, np.ones(tri.shape[0], dtype=bool), pts.shape[0], topology=topology)
    report = _trim(tile, max_edge, min_circle_ratio)
    return tri[tile.alive], report


class TrimmedMesh:
    """The triangles a trim kept, with the topology of the triangulation they were cut from,
    so the stages after the trim reuse its one edge sort: curtains.remove_curtains (the
    noise floor's edges, the re-trim around its holes) and the interpolator (`edge_table`).

    source (T, 3) int64: the triangulation trimmed; alive (T,) bool: the kept triangles;
    triangles (T', 3): source[alive], in input order and orientation; table, other,
    neighbours: topology.edge_table_sides(source, n_points); lengths (T, 3): edge_lengths
    of source. `retrim(mesh, drop)` removes more triangles (sharing the rest).
    """

    def __init__(self, source: np.ndarray, alive: np.ndarray, table: EdgeTable, other: np.ndarray,
                 neighbours: np.ndarray, lengths: np.ndarray, n_points: int):
        self.source, self.alive, self.table, self.other = source, alive, table, other
        self.neighbours, self.lengths, self.n_points = neighbours, lengths, n_points

    @cached_property
    def triangles(self) -> np.ndarray:
        """source[alive] (T', 3), made when first asked: a trim, its curtains and their
        re-trim each make a TrimmedMesh, and only the last one's triangles are needed."""
        return compress_rows(self.alive, self.source)      # np.compress: 3x faster than a 2-d mask

    @classmethod
    def of(cls, xy: np.ndarray, triangles: ArrayLike) -> "TrimmedMesh":
        """All of ``triangles`` (T, 3) over the points xy (n, 2), nothing removed."""
        pts = as_xy(xy)
        tri = _as_triangles(triangles, pts.shape[0])
        lengths, (table, other, neighbours) = overlap(lambda: edge_lengths(pts, tri),
                                                      lambda: edge_table_sides(tri, pts.shape[0]))
        return cls(tri, np.ones(tri.shape[0], dtype=bool), table, other, neighbours, lengths, pts.shape[0])

    def with_alive(self, alive: np.ndarray) -> "TrimmedMesh":
        """The same source with the triangles ``alive`` (T,) bool kept."""
        return TrimmedMesh(self.source, alive, self.table, self.other, self.neighbours,
                           self.lengths, self.n_points)

    def tile(self, points: np.ndarray | None = None) -> "TrimTile":
        """The in-memory fit's one TrimTile of this mesh: its source, a copy of its alive
        mask (the rules clear it), its topology; points as TrimTile takes them."""
        return TrimTile(self.source, self.alive.copy(), self.n_points, points,
                        topology=(self.neighbours, self.lengths))

    def live_edge_mask(self) -> np.ndarray:
        """(E,) bool over table.edges: the edges of the kept triangles."""
        return live_edges(self.table, self.alive, self.other)[1] > 0

    def edge_table(self, used: np.ndarray | None = None) -> EdgeTable:
        """topology.edge_table of the kept triangles (self.triangles), with the vertices
        renumbered by ``used`` as pipeline.steps.compact_vertices does (None: not)."""
        return sub_table(self.table, self.alive, self.other, used)


def trim_mesh(xy: ArrayLike, triangles: ArrayLike, max_edge: str | float | None = "auto",
              min_circle_ratio: float = MIN_CIRCLE_RATIO) -> tuple[TrimmedMesh, TrimReport]:
    """`trim`, with the kept triangles as a TrimmedMesh (mesh.triangles: `trim`'s result).

    Its edge table comes from the same sort as its neighbours, so a fit numbers the edges
    once (a non-manifold input raises InputError from topology.edge_table instead)."""
    mesh = TrimmedMesh.of(xy, triangles)
    tile = mesh.tile()
    report = _trim(tile, max_edge, min_circle_ratio)
    return mesh.with_alive(tile.alive), report


def trim_again(mesh: TrimmedMesh, max_edge: str | float | None,
               min_circle_ratio: float = MIN_CIRCLE_RATIO) -> tuple[TrimmedMesh, TrimReport]:
    """trim_mesh of the triangulation `mesh` was cut from (mesh.source) with another
    max_edge, reusing its edge lengths and neighbours (no second edge sort): a DEM's fill
    (c1mesh.pipeline.driver.filled_mesh) trims it again without max_edge."""
    tile = mesh.with_alive(np.ones(mesh.source.shape[0], dtype=bool)).tile()
    report = _trim(tile, max_edge, min_circle_ratio)
    return mesh.with_alive(tile.alive), report


def retrim(mesh: TrimmedMesh, drop: np.ndarray, min_circle_ratio: float = MIN_CIRCLE_RATIO
           ) -> tuple[TrimmedMesh, dict[str, int]]:
    """The mesh without the live triangles ``drop`` (indices into mesh.source), and without
    the slivers and bowties their holes expose (`retrim_run` on its one tile); and
    {"long_edge": 0, "sliver", "bowtie"}.

    The same as trim(xy, mesh.triangles minus drop, max_edge=None) for a mesh that trim
    left (no thin triangle on its boundary, no bowtie vertex).
    """
    run = OneTile(mesh.tile())
    counts = retrim_run(run, run.tile.cuts(np.asarray(drop, dtype=np.int64)), min_circle_ratio)
    return mesh.with_alive(run.tile.alive), {"long_edge": 0, **counts}


def _trim(tile: "TrimTile", max_edge, min_circle_ratio: float) -> TrimReport:
    """`trim` of the in-memory fit's one tile, all of whose triangles are alive: the long
    edges cleared from tile.alive, then `trim_run`; the report."""
    limit = _edge_limit(tile.lengths, tile.neighbours, max_edge)
    if not 0.0 <= min_circle_ratio <= 1.0:
        raise InputError(f"min_circle_ratio must be between 0 and 1, got {min_circle_ratio}")
    alive = tile.alive
    if limit is not None:                      # NaN lengths are not above it: kept, as before
        parallel_blocks(lambda part: np.logical_and(alive[part], ~row_any(tile.lengths[part] > limit),
                                                    out=alive[part]), alive.shape[0], KERNEL_BLOCK << 2)
    long_edge = int((~alive).sum())
    _, counts = trim_run(OneTile(tile), min_circle_ratio)
    return TrimReport(triangles_before=int(alive.shape[0]), triangles_after=int(np.count_nonzero(alive)),
                      removed={"long_edge": long_edge, **counts}, max_edge=limit,
                      unreferenced_points=tile.size - used_points(tile.source, alive, tile.size))


# ---- the rules as functions of a tile, and their loop over a run's tiles -----------------

@dataclass
class Cuts:
    """Triangles the trim's tiles found (to remove, or thin): corners (k, 3) int64 survey
    numbers; tiles (k, 3) int64 the tile whose cell holds each corner; rows (k,) int64 each
    one's row in the TrimTile that found it (what OneTile removes by: its tile persists;
    a survey's halos are read again without the removed triangles, so its runs go by
    corners)."""

    corners: np.ndarray
    tiles: np.ndarray
    rows: np.ndarray

    def __len__(self) -> int:
        return self.rows.shape[0]

    @classmethod
    def join(cls, parts: list["Cuts"]) -> "Cuts":
        """The parts, one after the other."""
        none = np.empty((0, 3), dtype=np.int64)
        return cls(np.concatenate([none] + [p.corners for p in parts]),
                   np.concatenate([none] + [p.tiles for p in parts]),
                   np.concatenate([none[:, 0]] + [p.rows for p in parts]))

    def take(self, index: np.ndarray) -> "Cuts":
        """The triangles index (k',) of these."""
        return Cuts(self.corners[index], self.tiles[index], self.rows[index])

    def distinct(self) -> "Cuts":
        """These without repeats (two tiles may cut one triangle, at two of its corners),
        in the order of their first rows."""
        if len(self) < 2:
            return self
        _, first = np.unique(np.sort(self.corners, axis=1), axis=0, return_index=True)
        return self.take(np.sort(first))

    def tile_set(self) -> set[int]:
        """The tiles holding a corner of these triangles."""
        return set(np.unique(self.tiles).tolist())


@dataclass(frozen=True)
class Place:
    """Where a survey's tile lies: numbers (m,) int64 its vertices' survey numbers,
    ascending; home (m,) int64 the tile whose cell holds each vertex; number: the tile's."""

    numbers: np.ndarray
    home: np.ndarray
    number: int


class TrimTile:
    """One tile as the trim's rules see it.

    source (T, 3) int64: the triangles the tile holds, rows into its `size` vertices (a
    survey's tile: its halo's final triangles, core.tile.Tile.triangles, which hold the
    whole star of every vertex in its cell); alive (T,) bool: those still in the mesh (a
    run whose tile persists removes by clearing it, OneTile; a survey's tiles are read
    without the removed ones). points: (size, 2) x, y, or (size, 5) the rows of
    curtains.point_rows (x, y, z, gx, gy), which the curtain rule needs; None where
    neither is needed. place: the tile's Place in a survey (None: the in-memory fit's one
    tile, tile 0, the rows are the survey numbers and every vertex is its own).
    topology: (neighbours (T, 3), lengths (T, 3)) as triangle_neighbours and
    edge_lengths give them, when known (a TrimmedMesh's); else made when first asked.
    """

    points: np.ndarray | None = None        # a subclass may make them when first read

    def __init__(self, source: np.ndarray, alive: np.ndarray, size: int, points: np.ndarray | None = None,
                 place: Place | None = None, topology: tuple[np.ndarray, np.ndarray] | None = None):
        self.source, self.alive, self.size, self.place = source, alive, size, place
        if points is not None:
            self.points = points
        if topology is not None:            # instance attributes: the cached properties are not run
            self.neighbours, self.lengths = topology

    @cached_property
    def neighbours(self) -> np.ndarray:
        """(T, 3) the triangle across the edge opposite corner k, or -1."""
        return triangle_neighbours(self.source, self.size)

    @cached_property
    def lengths(self) -> np.ndarray:
        """(T, 3) edge_lengths of source."""
        return edge_lengths(self.points[:, :2], self.source)

    @property
    def number(self) -> int:
        """The tile's number (0: the in-memory fit's one tile)."""
        return 0 if self.place is None else self.place.number

    def own_live(self) -> np.ndarray:
        """(T,) bool the live triangles the tile decides: those whose lowest corner lies in
        its cell (its rows ascend with the survey numbers), each triangle in one tile."""
        if self.place is None:
            return self.alive
        return self.alive & (self.place.home[row_min(self.source)] == self.place.number)

    def at(self, near: Cuts | None) -> np.ndarray | None:
        """(size,) bool the vertices in the tile's cell that are corners of `near`; near
        None: every vertex in its cell (None back where that is every vertex)."""
        if self.place is None:
            if near is None:
                return None
            at = np.zeros(self.size, dtype=bool)
            at[near.corners.ravel()] = True
            return at
        own = self.place.home == self.place.number
        if near is None:
            return own
        rows = tile_rows(self.place.numbers, near.corners)      # a search of the few corners, no sort of the tile
        at = np.zeros(self.size, dtype=bool)
        at[rows[rows >= 0]] = True
        return own & at

    def cuts(self, rows: np.ndarray) -> Cuts:
        """The triangles rows (k,) of source as Cuts."""
        corners = self.source[rows]
        if self.place is None:
            return Cuts(corners, np.zeros_like(corners), rows)
        return Cuts(self.place.numbers[corners], self.place.home[corners], rows)


class TrimRun(Protocol):
    """The tiles the trim's loop runs over: OneTile in memory; a survey's
    (c1mesh.survey.trim_runs.TrimRuns)."""

    def map(self, step: Callable[[TrimTile], Any], tiles: set[int] | None = None) -> list:
        """[step(tile)] for the tiles (numbers; None: all), in tile order."""

    def remove(self, cuts: Cuts) -> None:
        """The triangles cuts leave the mesh: later steps do not see them."""


class OneTile:
    """The in-memory fit's TrimRun: one tile, which persists; removing clears its alive."""

    def __init__(self, tile: TrimTile):
        self.tile = tile

    def map(self, step: Callable[[TrimTile], Any], tiles: set[int] | None = None) -> list:
        return [step(self.tile)] if tiles is None or self.tile.number in tiles else []

    def remove(self, cuts: Cuts) -> None:
        self.tile.alive[cuts.rows] = False


def thin_triangles(tile: TrimTile, min_ratio: float) -> tuple[Cuts, np.ndarray]:
    """The summary: the tile's own live thin triangles (circle_ratio below min_ratio) as
    Cuts, and (k,) bool whether each lies on the boundary (an edge without a live triangle
    across)."""
    if "lengths" in tile.__dict__ or tile.points is None:        # measured already (in memory)
        rows = _thin_rows(tile.lengths, tile.alive, min_ratio)
        rows = rows[tile.own_live()[rows]]
    else:                                                          # a survey's halo: its own rows only
        rows = _thin_rows_at(tile.points[:, :2], tile.source, tile.own_live(), min_ratio)
    across = tile.neighbours[rows]
    boundary = ((across < 0) | ~tile.alive[across]).any(axis=1)
    return tile.cuts(rows), boundary


def peeled(triangles: np.ndarray, front: np.ndarray) -> np.ndarray:
    """The reduce: (k,) bool which of the thin triangles (k, 3) (survey numbers) the peel
    removes, front (k,) bool those it starts from: the connected sets of them, through
    shared edges, that hold a front triangle. Over the thin triangles alone, as a thin
    triangle's other neighbours are never peeled."""
    k = len(triangles)
    if not k or not front.any():
        return np.zeros(k, dtype=bool)
    corners, local = np.unique(triangles, return_inverse=True)
    across = triangle_neighbours(local.reshape(-1, 3), len(corners))
    t, side = np.nonzero(across >= 0)
    component = connected_sets(k, t, across[t, side])
    reached = np.zeros(component.max() + 1, dtype=bool)
    reached[component[front]] = True
    return reached[component]


def bowtie_cuts(tile: TrimTile, near: Cuts | None = None) -> Cuts:
    """What remove_bowties cuts at the tile's own vertices that are corners of `near`
    (None: at all of them), without removing it: every fan but the kept one.

    With near, over the stars of those vertices alone (the live triangles with a corner
    there, and their neighbours among themselves): a fan at a vertex and the open edges
    at it are all in its star, so the cuts are the whole tile's, without the tile's
    neighbours (an edge sort of the whole halo for a few thousand vertices)."""
    at = tile.at(near)
    if near is None:
        return tile.cuts(remove_bowties(tile.source, tile.alive.copy(), tile.neighbours, at))
    rows = _live_rows(tile.source, tile.alive, at)
    star = tile.source[rows]
    cut = remove_bowties(star, np.ones(len(rows), dtype=bool), triangle_neighbours(star, tile.size), at)
    return tile.cuts(rows[cut])


class Thin:
    """The thin triangles of a run's tiles, thin_triangles of each joined in tile order
    (the peel only ever removes those): triangles (Cuts), boundary (k,) bool, and alive
    (k,) bool those still in the mesh."""

    def __init__(self, triangles: Cuts, boundary: np.ndarray):
        self.triangles, self.boundary = triangles, boundary
        self.alive = np.ones(len(triangles), dtype=bool)

    @classmethod
    def of(cls, run: TrimRun, min_ratio: float) -> "Thin":
        parts = run.map(partial(thin_triangles, min_ratio=min_ratio))
        return cls(Cuts.join([part for part, _ in parts]),
                   np.concatenate([np.zeros(0, dtype=bool)] + [boundary for _, boundary in parts]))

    def peel(self, front: np.ndarray) -> Cuts:
        """Mark dead and return the live ones `peeled` removes from front (k,) bool."""
        live = np.flatnonzero(self.alive)
        gone = live[peeled(self.triangles.corners[live], front[live])]
        self.alive[gone] = False
        return self.triangles.take(gone)

    def remove(self, cuts: Cuts) -> None:
        """Another rule removed cuts: a thin one among them can no longer be peeled."""
        self.alive &= kept_triangles(self.triangles.corners, cuts.corners)

    def next_to(self, cuts: Cuts) -> np.ndarray:
        """(k,) bool the thin triangles sharing an edge with one of cuts."""
        return touching(self.triangles.corners, cuts.corners)


def settle(run: TrimRun, thin: Thin, front: np.ndarray, near: Cuts | None,
           early: Cuts | None = None) -> tuple[int, int]:
    """trim's loop over the run's tiles: peel the live thin components that hold a `front`
    (k,) bool triangle, cut the bow-ties, peel again from the cut fans' neighbours, until
    no bow-tie is left; returns (slivers, bow-tie triangles) removed. near: the triangles
    removed since the tiles were last looked at for bow-ties, whose corners are the only
    places one can appear (None: look everywhere). early: the first round's bow-tie cuts
    (at those places) if the tiles found them before the first peel, in the pass that
    read them for another rule (None: the round looks after the peel).

    Why early serves: a vertex's bow-tie decision depends on its star alone, and the
    peel changes only the stars of its triangles' corners. So the early cuts with no
    corner among the peeled triangles' stand; those with one are looked at again, with
    the peeled triangles' corners, after the peel."""
    sliver = bowtie = 0
    while True:
        gone = thin.peel(front)
        sliver += len(gone)
        run.remove(gone)
        if near is not None:
            near = Cuts.join([near, gone])
        if early is None:
            cut = Cuts.join(run.map(partial(bowtie_cuts, near=near),
                                    None if near is None else near.tile_set())).distinct()
        else:
            stale = np.isin(early.corners, gone.corners).any(axis=1)
            again = Cuts.join([gone, early.take(stale)])
            cut = Cuts.join([early.take(~stale)] + run.map(partial(bowtie_cuts, near=again),
                                                           again.tile_set())).distinct()
            early = None
        if not len(cut):
            return sliver, bowtie
        bowtie += len(cut)
        run.remove(cut)
        thin.remove(cut)
        front, near = thin.next_to(cut), cut


def trim_run(run: TrimRun, min_ratio: float) -> tuple[Thin, dict[str, int]]:
    """The sliver peel and bow-tie removal over the run's tiles, after the long-edge rule:
    (the run's Thin, {"sliver", "bowtie"} removed). One pass over the tiles finds their
    thin triangles and, before the peel, their bow-ties (settle's early)."""
    parts = run.map(partial(thin_and_bowties, min_ratio=min_ratio))
    thin = Thin(Cuts.join([part for part, _, _ in parts]),
                np.concatenate([np.zeros(0, dtype=bool)] + [boundary for _, boundary, _ in parts]))
    sliver, bowtie = settle(run, thin, thin.boundary, None, Cuts.join([cuts for _, _, cuts in parts]))
    return thin, {"sliver": sliver, "bowtie": bowtie}


def thin_and_bowties(tile: TrimTile, min_ratio: float) -> tuple[Cuts, np.ndarray, Cuts]:
    """trim_run's first pass over a tile: its thin_triangles (the Cuts, the boundary flags)
    and its bowtie_cuts at every vertex in its cell, from one read of the tile."""
    thin, boundary = thin_triangles(tile, min_ratio)
    return thin, boundary, bowtie_cuts(tile)


def retrim_run(run: TrimRun, cuts: Cuts, min_ratio: float, thin: Thin | None = None,
               early: Cuts | None = None) -> dict[str, int]:
    """Remove the live triangles cuts (another rule's, found by the run's tiles) and the
    slivers and bow-ties their holes expose: only the thin triangles beside the holes can
    be newly on the boundary, and only the holes' corners can become bow-ties. thin: the
    run's Thin from trim_run (None: taken now); early: the bow-ties at the holes' corners
    once the holes are cut, if the tiles found them as they found the cuts (settle's
    early; None: looked for after the peel). Returns {"sliver", "bowtie"} removed."""
    run.remove(cuts)
    if not len(cuts):
        return {"sliver": 0, "bowtie": 0}
    if thin is None:
        thin = Thin.of(run, min_ratio)
    else:
        thin.remove(cuts)
    sliver, bowtie = settle(run, thin, thin.next_to(cuts), cuts, early)
    return {"sliver": sliver, "bowtie": bowtie}


def touching(triangles: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(k,) bool: which of triangles (k, 3) share an edge with one of others (m, 3)
    (survey numbers)."""
    if not len(triangles) or not len(others):
        return np.zeros(len(triangles), dtype=bool)
    n = int(max(triangles.max(), others.max())) + 1

    def keys(t):
        return [np.minimum(t[:, a], t[:, b]) * n + np.maximum(t[:, a], t[:, b]) for a, b in ((0, 1), (1, 2), (2, 0))]
    theirs = np.concatenate(keys(others))
    return np.logical_or.reduce([np.isin(k, theirs) for k in keys(triangles)])


def drop_triangles(triangles: np.ndarray, removed: np.ndarray) -> np.ndarray:
    """The rows of triangles (T, 3) that are not, as a set of corners, a row of removed
    (R, 3) (survey numbers): triangles[kept_triangles(triangles, removed)], copied row by
    row (np.compress: 3.7 ms against the boolean index's 9.3 ms at 500k rows)."""
    return np.compress(kept_triangles(triangles, removed), triangles, axis=0)


def kept_triangles(triangles: np.ndarray, removed: np.ndarray, numbers: np.ndarray | None = None) -> np.ndarray:
    """(T,) bool which triangles (T, 3) are not, as a set of corners, a row of removed
    (R, 3) (survey numbers); numbers: (m,) the survey numbers of the rows the triangles
    hold instead (a halo's), None: the triangles are survey numbers. A hash of the
    removed rows and one pass over the triangles (kernel: stages/_trim.pyx), so a halo's
    load costs one pass whatever the survey has removed. With ascending numbers (a
    halo's) the rows that are removed corners are marked first (`_removed_corners`): a
    triangle without one as its first corner is kept at the cost of one byte read, where
    looking up its three numbers and hashing them cost a halo load 20 ms."""
    keep = np.ones(len(triangles), dtype=bool)
    if not len(removed) or not len(triangles):
        return keep
    table = np.full(_table_size(len(removed)), -1, dtype=np.int64)
    mapped = numbers is not None
    numbers = np.ascontiguousarray(numbers if mapped else np.empty(0), dtype=np.int64)
    removed = np.ascontiguousarray(removed, dtype=np.int64)
    kernel.kept_triangles(np.ascontiguousarray(triangles, dtype=np.int64), numbers, mapped, removed, table,
                          keep.view(np.uint8), _removed_corners(numbers, removed) if mapped else _NO_ROWS)
    return keep


_NO_ROWS = np.empty(0, dtype=np.uint8)


def _removed_corners(numbers: np.ndarray, removed: np.ndarray) -> np.ndarray:
    """(m,) uint8: 1 at the rows whose survey number numbers (m,) is a corner of removed
    (R, 3), found by binary search; empty (not known) unless numbers ascend strictly."""
    if numbers.size > 1 and not (numbers[1:] > numbers[:-1]).all():
        return _NO_ROWS
    corners = removed.ravel()
    rows = np.minimum(np.searchsorted(numbers, corners), numbers.size - 1)
    marks = np.zeros(numbers.size, dtype=np.uint8)
    marks[rows[numbers[rows] == corners]] = 1
    return marks


def triangles_among(index: np.ndarray, triangles) -> np.ndarray:
    """The triangles (k, 3) (survey numbers) whose three corners are among `index` (a
    halo's survey numbers, distinct), as rows of index, in their order; triangles: one
    (T, 3) array or an iterable of them (a halo's tiles' files, loaded one at a time),
    whose results follow one another. A hash of index, built once, and one pass over the
    triangles (kernel: stages/_trim.pyx; no sort of them, which cost a halo read most of
    its time when it sifted nine tiles' triangles). Beside the table, a filter of 8 bits
    a number (one set per number, in the cache where the table is not) turns away most
    numbers not in index with one read: most triangles a halo reads are a neighbour's,
    far from its cell, and a look-up in the table cost one of memory per corner."""
    out, count = np.empty((0, 3), dtype=np.int64), 0
    if not len(index):
        return out
    index = np.ascontiguousarray(index, dtype=np.int64)
    table = np.full((_table_size(len(index)), 2), -1, dtype=np.int64)
    bits = np.zeros(max(1, _table_size(4 * len(index)) // 64), dtype=np.uint64)
    kernel.number_table(index, table, bits)
    for part in [triangles] if isinstance(triangles, np.ndarray) else triangles:
        part = np.ascontiguousarray(part, dtype=np.int64).reshape(-1, 3)
        if count + len(part) > len(out):                  # room for every row of the part
            out = _grown(out, count, max(2 * len(out), count + len(part)))
        count += kernel.triangles_among(table, bits, part, out[count:])
    return out[:count]


def _grown(rows: np.ndarray, count: int, size: int) -> np.ndarray:
    """A (size, 3) int64 array whose first count rows are those of rows; the rest are
    not written (np.empty: their pages cost no memory until they are)."""
    grown = np.empty((size, 3), dtype=np.int64)
    grown[:count] = rows[:count]
    return grown


def connected_sets(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) int64 the connected set of each of n items that the pairs (a[i], b[i]) join,
    numbered in the order of each set's lowest item, as scipy's connected_components
    numbers an undirected graph (kernel: stages/_trim.pyx, a union-find; no sparse graph
    is built, and the plain fit does not import scipy for it)."""
    labels = np.empty(n, dtype=np.int64)
    kernel.component_labels(np.ascontiguousarray(a, dtype=np.int64), np.ascontiguousarray(b, dtype=np.int64), labels)
    return labels


def _table_size(keys: int) -> int:
    """A kernel hash table's slots for `keys` keys: the power of two at least twice as many."""
    return 1 << max(1, int(2 * keys - 1).bit_length())


def circle_ratio(lengths: np.ndarray) -> np.ndarray:
    """2 r_in / R_circ of triangles with edge lengths (T, 3): 1 for equilateral, 0 if flat.

    From Heron: 16 A^2 = P (P-2a)(P-2b)(P-2c) with r = 2A/P, R = abc/4A, so
    2r/R = (P-2a)(P-2b)(P-2c) / (abc), clipped to [0, 1] (a point-like triangle, 0/0, is
    0). The kernel (stages/_trim.pyx) over blocks of KERNEL_BLOCK triangles in the thread
    knob's threads; `thin_triangles` compares the same arithmetic with min_ratio.
    """
    lengths = np.ascontiguousarray(lengths, dtype=np.float64)
    if lengths.ndim != 2 or lengths.shape[1] != 3:
        raise InputError(f"edge lengths must have shape (T, 3), got {lengths.shape}")
    out = np.empty(lengths.shape[0])
    parallel_blocks(lambda part: kernel.circle_ratios(lengths, out, part.start, part.stop),
                    lengths.shape[0], KERNEL_BLOCK)
    return out


def _thin_rows(lengths: np.ndarray, alive: np.ndarray, min_ratio: float) -> np.ndarray:
    """Ascending indices of the live triangles (alive (T,) bool) whose circle_ratio of
    edge lengths (T, 3) is below min_ratio (kernel: stages/_trim.pyx; no (T,) ratios)."""
    rows = np.empty(lengths.shape[0], dtype=np.int64)
    count = kernel.thin_rows(np.ascontiguousarray(lengths, dtype=np.float64),
                             np.ascontiguousarray(alive).view(np.uint8), float(min_ratio), rows)
    return rows[:count].copy()


def _thin_rows_at(xy: np.ndarray, tri: np.ndarray, alive: np.ndarray, min_ratio: float) -> np.ndarray:
    """`_thin_rows` of the triangles tri (T, 3) from their corners' plane coordinates xy
    (n, 2), without their (T, 3) lengths (stages/_trim.pyx, thin_rows_at: sqrt lengths
    screen, hypot's decide, so the rows are _thin_rows' of edge_lengths). A survey's trim
    measured every halo triangle's lengths to find the few thin ones among its own."""
    rows = np.empty(tri.shape[0], dtype=np.int64)
    screen = 2.0 * min_ratio if min_ratio >= 1e-6 else np.inf
    count = kernel.thin_rows_at(np.ascontiguousarray(xy, dtype=np.float64), np.ascontiguousarray(tri, dtype=np.int64),
                                np.ascontiguousarray(alive).view(np.uint8), float(min_ratio), float(screen), rows)
    return rows[:count].copy()


def _as_triangles(triangles: ArrayLike, n: int) -> np.ndarray:
    tri = np.asarray(triangles)
    if tri.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer):
        raise InputError(f"triangles must be an integer array of shape (T, 3), got {tri.dtype} "
                         f"with shape {tri.shape}")
    if tri.min() < 0 or tri.max() >= n:
        raise InputError(f"triangle indices must lie in [0, {n}), got {tri.min()}..{tri.max()}")
    return tri.astype(np.int64, copy=False)


def edge_lengths(xy: np.ndarray, tri: np.ndarray, workers: int | None = None) -> np.ndarray:
    """(T, 3) length of the edge opposite vertex k of the triangles tri (T, 3), indices into
    xy (n, 2); lengths in xy's unit. The kernel (stages/_trim.pyx) runs over fixed blocks of
    KERNEL_BLOCK triangles in the thread knob's threads (workers: that many instead); each
    length is one hypot, the same at any count."""
    tri = np.ascontiguousarray(tri, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise InputError(f"triangles must have shape (T, 3), got {tri.shape}")
    if tri.size and (tri.min() < 0 or tri.max() >= len(xy)):
        raise InputError(f"triangle indices must lie in [0, {len(xy)}), got {tri.min()}..{tri.max()}")
    rows = np.ascontiguousarray(xy, dtype=np.float64)
    lengths = np.empty(tri.shape)
    parallel_blocks(lambda part: kernel.edge_lengths(rows, tri, lengths, part.start, part.stop),
                    tri.shape[0], KERNEL_BLOCK, threads=workers)
    return lengths


def triangle_neighbours(tri: np.ndarray, n: int) -> np.ndarray:
    """(T, 3) triangle across the edge opposite vertex k, or -1; InputError if an edge has 3+
    (topology.triangle_neighbours, the edge table's kernel without the table)."""
    return topology_neighbours(tri, n)


def _edge_limit(lengths: np.ndarray, neighbours: np.ndarray, max_edge) -> float | None:
    """The max_edge option resolved to a length, or None."""
    if max_edge is None or (isinstance(max_edge, str) and max_edge.strip().lower() == "none"):
        return None
    if isinstance(max_edge, str) and max_edge.strip().lower() == "auto":
        once = _each_edge_once(lengths, neighbours)
        return float(AUTO_EDGE_FACTOR * np.median(once, overwrite_input=True)) if once.size else None  # a temporary
    try:
        limit = float(max_edge)
    except (TypeError, ValueError):
        limit = float("nan")
    if not np.isfinite(limit) or limit <= 0:
        raise InputError(f"max_edge must be 'auto', None or a positive length, got {max_edge!r}")
    return limit


def _each_edge_once(lengths: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """The lengths (T, 3) of every edge once, from the triangle whose neighbour across it
    (neighbours (T, 3)) is none or later, in row order: the edges of the triangulation,
    each once (kernel: stages/_trim.pyx, no (T, 3) masks: each block of triangles counts
    its edges, then writes them after the blocks before it, both passes in the thread
    knob's threads)."""
    lengths = np.ascontiguousarray(lengths, dtype=np.float64)
    neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
    T = lengths.shape[0]
    first = np.zeros(-(-T // KERNEL_BLOCK) + 1, dtype=np.int64)

    def count(part: slice) -> None:
        first[part.start // KERNEL_BLOCK + 1] = kernel.once_count(neighbours, part.start, part.stop)
    parallel_blocks(count, T, KERNEL_BLOCK)
    np.cumsum(first, out=first)
    once = np.empty(int(first[-1]))
    parallel_blocks(lambda part: kernel.once_lengths(lengths, neighbours, once[first[part.start // KERNEL_BLOCK]:],
                                                     part.start, part.stop), T, KERNEL_BLOCK)
    return once


def used_points(tri: np.ndarray, alive: np.ndarray, n_points: int) -> int:
    """How many of n_points points the triangles tri (T, 3) that are alive (T,) bool use
    (kernel: stages/_trim.pyx; no copy of the live triangles)."""
    used = np.zeros(n_points, dtype=np.uint8)
    kernel.mark_used(np.ascontiguousarray(tri, dtype=np.int64), np.ascontiguousarray(alive).view(np.uint8),
                     used)
    return int(np.count_nonzero(used))


def _live_rows(tri: np.ndarray, alive: np.ndarray, at: np.ndarray | None) -> np.ndarray:
    """Ascending indices of the live triangles of tri (T, 3) (alive (T,) bool) with a
    corner in at (n,) bool (None: every live one); kernel: stages/_trim.pyx."""
    rows = np.empty(tri.shape[0], dtype=np.int64)
    everywhere = at is None
    marks = np.zeros(1, dtype=np.uint8) if everywhere else np.ascontiguousarray(at).view(np.uint8)
    return rows[:kernel.live_rows(tri, alive.view(np.uint8), marks, everywhere, rows)]


def _corner_slots(tri: np.ndarray, rows: np.ndarray, marked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t, slot): the corners at marked (n,) bool vertices of the triangles rows (R,) of
    tri (T, 3), by row then slot: np.nonzero(marked[tri[rows]]) with t = rows[r], without
    the (R, 3) gathers (kernel: stages/_trim.pyx)."""
    t, slot = np.empty(3 * rows.size, dtype=np.int64), np.empty(3 * rows.size, dtype=np.int64)
    count = kernel.corner_slots(tri, rows, np.ascontiguousarray(marked).view(np.uint8), t, slot)
    return t[:count], slot[:count]


def remove_bowties(tri: np.ndarray, alive: np.ndarray, neighbours: np.ndarray,
                    at: np.ndarray | None = None) -> np.ndarray:
    """Remove all but the largest fan at every bowtie vertex; return the removed triangles.

    A vertex is a bowtie when more than 2 boundary edges meet there (each fan brings 2).
    A fan is a set of live triangles around the vertex joined through edges at it. Among
    fans of equal size the one whose smallest triangle (corners sorted, then compared
    lexicographically) comes first is kept: a rule of point numbers alone, so a tile that
    holds the vertex's star decides as the whole triangulation does (bowtie_cuts).
    at: (n,) bool, the vertices to look at (None: all); a tile passes the vertices whose
    whole star it holds.
    """
    tri = np.ascontiguousarray(tri, dtype=np.int64)
    if not len(tri):
        return np.zeros(0, dtype=np.int64)
    neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
    n = tri.max() + 1
    live = _live_rows(tri, alive, None if at is None else at[:n])
    ends = np.zeros(n, dtype=np.int64)
    kernel.open_ends(tri, alive.view(np.uint8), neighbours, live, ends)
    bow = ends > 2
    if at is not None:
        bow &= at[:n]
    if not bow.any():
        return np.zeros(0, dtype=np.int64)
    t, j = _corner_slots(tri, live, bow)                      # incidences (triangle, slot)
    v = tri[t, j]
    key = v * len(tri) + t
    order = np.argsort(key)
    # neighbours through the two edges at v (opposite the other two slots)
    links = []
    for step in (1, 2):
        other = neighbours[t, (j + step) % 3]
        ok = (other >= 0) & alive[np.maximum(other, 0)]
        pos = order[np.searchsorted(key[order], v[ok] * len(tri) + other[ok])]
        links.append(np.stack([np.flatnonzero(ok), pos]))
    links = np.concatenate(links, axis=1)
    fan = connected_sets(t.size, links[0], links[1])
    size = np.bincount(fan)
    # per vertex keep the fan with most triangles; ties: the fan holding the smallest
    # triangle as a sorted corner triple (order-free: the same in any triangle order)
    corners = np.sort(tri[t], axis=1)
    rank = np.empty(t.size, dtype=np.int64)
    rank[np.lexsort(corners.T[::-1])] = np.arange(t.size)
    smallest = np.full(size.size, t.size, dtype=np.int64)
    np.minimum.at(smallest, fan, rank)
    best = np.lexsort((smallest[fan], -size[fan], v))          # sorted by v, then best fan first
    first = np.ones(best.size, dtype=bool)
    first[1:] = v[best[1:]] != v[best[:-1]]
    keep_fan = np.zeros(size.size, dtype=bool)
    keep_fan[fan[best[first]]] = True
    cut = np.unique(t[~keep_fan[fan]])
    alive[cut] = False
    return cut
