"""Overshoot control for noisy scans that keeps the spline C1 (docs/overshoot.md).

The remedies, plain functions over arrays, applied by the fit pipeline between the height
field and the RSDInterpolator:

* `reconcile_heights` moves the two heights of a short edge, by at most `HEIGHT_CLIP`
  noise floors, where their difference disagrees with their gradients so much that the
  spline would crease across the edge's triangles more sharply than their sub-faces can
  show (near-coincident points with independent noise). Heights stay one per vertex.
* `reconcile_gradients` blends a vertex gradient that disagrees with the heights of its
  neighbours with their secant slopes (least squares), one gradient per vertex.
* `limit_gradients` then scales a vertex gradient down where it disagrees with the heights of
  its neighbours (a Fritsch–Carlson-like limiter on the secants of the vertex's edges).
  A vertex has one gradient, shared by all its triangles, so the spline stays C1.
* `edge_directions` picks, for every edge, the direction u the RSD spline uses across it
  (Thm 3.4: any vector not parallel to the edge, one per edge, shared by both triangles).
  The unit normal makes the ratios r_ln = G_l·u_n / G_n·u_n blow up on obtuse thin
  triangles; a direction through the opposite vertices keeps them within [-1, 0].

Both change nothing on well-behaved data: the limiter only acts on edges whose data fail
the trapezoid test (below), which exact data of any quadratic passes and smooth data
passes up to O(h³); the directions change only edges whose unit-normal ratio exceeds
`RATIO_LIMIT`.

As a stage of tiles (core.tile.Tile): the noise floors are survey-wide, a summary per tile
(`floor_summary`: the |trapezoid residuals| of the edges the tile owns) and one reduce
(`reduce_floor`: their exact median), once with the input data and once with the data
reconciled with the first floor (`NoiseFloors`); the run on a tile is `tile_limits`. The
in-memory fit is one tile (`control_overshoot`), whose floors are the same summary over
every edge, reduced; c1mesh.survey schedules the tiles.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.threads import overlap, parallel_blocks
from c1mesh.core.threads import workers as thread_count
from c1mesh.core.tile import Tile, compact
from c1mesh.engine.topology import (EdgeTable, edge_slots, edge_table, edge_table_sides, live_edges, sub_table,
                                    table_from_slots, unique_edges)
from c1mesh.stages import _limiter as kernel
from c1mesh.stages.streamed_median import Chunks, streamed_median
from c1mesh.stages.trim import kept_triangles

OVERSHOOT_MODES = ("limit", "off")

SECANT_FACTOR = 2.0
"""A gradient may predict at most this multiple of an inconsistent edge's height change
(Fritsch–Carlson allow 3 for cubic Hermite; the RSD edge curve uses Φ(t) = t³(10 − 15t +
6t²) for the derivative term too, whose bump is about twice the cubic one)."""
CONSISTENCY = 0.25
"""An edge is inconsistent when its trapezoid residual exceeds this fraction of its scale."""
NOISE_FACTOR = 1.0
"""Residuals within this multiple of the median |trapezoid residual| (the noise floor of
the data; O(h³) for exact smooth data) are tolerated, and so is a prediction that far
outside the secant band."""
NORMAL_WEIGHT = 1.0
"""Weight of a vertex's normal against its edges' secant slopes in `reconcile_gradients`."""
RATIO_LIMIT = 2.0
"""Edges whose unit-normal RSD ratio max(|s|, |1 − s|) exceeds this get another direction."""
CREASE_LEVEL = 4
"""The refinement level (sub-faces per triangle edge) whose sampling `reconcile_heights`
protects: the default level. A fixed constant, so --level changes the sampling only."""
KERNEL_BLOCK = 1 << 16
"""Edges or triangles per block of the per-edge and per-triangle kernels (stages/_limiter.pyx),
run in the thread knob's threads (core.threads.parallel_blocks; fixed blocks, so the bits
do not depend on the count)."""
HEIGHT_CLIP = 2.0
"""`reconcile_heights` moves a height by at most this multiple of the noise floor: half of
an edge's residual up to twice the floor, what noise alone explains; larger misfits are
features (a kerb, a wall foot) and keep the rest."""


def check_mode(mode: str) -> None:
    """InputError unless `mode` is one of OVERSHOOT_MODES (checked before a fit's work)."""
    if mode not in OVERSHOOT_MODES:
        raise InputError(f"overshoot must be one of {', '.join(OVERSHOOT_MODES)}, got {mode!r}")


@dataclass
class LimiterReport:
    """What the remedies changed: vertices whose height moved (`reconcile_heights`) or whose
    gradient changed, and edges whose direction is not the unit normal."""

    gradients_limited: int = 0
    directions_changed: int = 0
    heights_reconciled: int = 0

    def as_dict(self) -> dict:
        return {"gradients_limited": self.gradients_limited,
                "directions_changed": self.directions_changed,
                "heights_reconciled": self.heights_reconciled}


@dataclass(frozen=True)
class NoiseFloors:
    """The survey's median |trapezoid residual| (height units) over every edge of its final
    triangles, with the input heights and gradients (first: reconcile_heights,
    reconcile_gradients) and with both reconciled with the first (second: limit_gradients)."""

    first: float
    second: float


@dataclass
class TileLimits:
    """The limiter's result for the corners of one tile's triangles: records (c,) the
    corners (ascending survey numbers; their z reconciled), triangles (k, 3) into them,
    gradients (c, 2) limited (None: the records' own), directions (E, 2) (None: the unit
    normals) in the order of
    topology.edge_table(triangles, c).edges; limited: own vertices whose gradient changed,
    turned: own edges whose direction is not the unit normal, lifted: own vertices whose
    height moved (own: in the tile's cell; lower end, for an edge); table: that
    topology.EdgeTable when known (the RSDInterpolator then numbers no edges), else None."""

    records: np.ndarray
    triangles: np.ndarray
    gradients: np.ndarray
    directions: np.ndarray
    limited: int
    turned: int
    lifted: int = 0
    table: EdgeTable | None = None


@dataclass(frozen=True)
class Reconciliation:
    """A tile's data reconciled with the survey's first noise floor, as the second floor's
    summary found it (`reconciled_summary`): values (n,), gradients (n, 2), and the (n,)
    bool vertices whose height moved (lifted) and whose gradient was reconciled (moved);
    edges: the tile's edge table as topology.edge_slots (E, 2), None when not kept.
    Given back to `tile_limits` on the same tile, it spares the refinement a second
    reconciliation of the same data (the reconciliations took 11.8 s of the 12M-point
    survey's tile processes, half of it in the refinement) and a second sort of its edges
    (5.4 s of the 12M survey's refinement, against 8 bytes an edge kept between them)."""

    values: np.ndarray
    gradients: np.ndarray
    lifted: np.ndarray
    moved: np.ndarray
    edges: np.ndarray | None = None


def floor_summary(tile: Tile, first: float | None = None) -> np.ndarray:
    """The noise floors' summary of one tile: (e,) |trapezoid residual| (height units) of
    the tile's own edges, those of its triangles whose lower-numbered end it owns (each
    edge of a survey in exactly one tile; every edge, for the in-memory fit's one tile).
    With the tile's heights and gradients (first None: the first floor, and the curtains'
    floor, c1mesh.stages.curtains), or with both reconciled with the survey's first floor
    (the second floor). The halo must hold the star of every vertex within 3 longest
    edges of the cell, so that the reconciled data of the own edges' ends are the whole
    survey's (c1mesh.survey.halos). `reduce_floor` of every tile's summary is the
    floor."""
    if first is None:            # the own edges alone: their residuals are the first floor's values
        edges = unique_edges(tile.triangles, len(tile.records), tile.own)
        return residual_sizes(trapezoid_residuals(tile.points, tile.values, tile.gradients, edges))
    return reconciled_summary(tile, first)[0]


def floor_summary_after(tile: Tile, earlier: np.ndarray, removed: np.ndarray) -> np.ndarray:
    """The first floor's summary of a tile (floor_summary(tile)) from `earlier`, its
    summary when its triangles were tile.triangles and `removed` (r, 3) rows of its
    records (triangles dropped since, with a corner among its records): earlier without
    the sizes of the own edges that only removed triangles held.

    Why: a survey's first floor is its curtains' floor, taken again after the curtains
    removed a few triangles a tile. Numbering every edge again cost a tile as much as the
    first summary; this costs a pass over the triangles' corners. The data did not
    change, so an edge's residual has the same bits in both summaries (the kernels'
    arithmetic is per edge), and the result holds floor_summary(tile)'s values, each as
    often: the same floor (a median). Equal values may stand in another order."""
    edges = _removed_own_edges(tile, removed)
    if not len(edges):
        return earlier
    gone = edges[~_held_edges(tile.triangles, edges, len(tile.records))]
    return _without(earlier, residual_sizes(trapezoid_residuals(tile.points, tile.values, tile.gradients, gone)))


def _removed_own_edges(tile: Tile, removed: np.ndarray) -> np.ndarray:
    """(e, 2) the distinct edges of the triangles removed (r, 3) (rows of tile.records)
    whose lower end the tile owns, lower end first, ascending (as unique_edges orders them)."""
    removed = np.asarray(removed, dtype=np.int64).reshape(-1, 3)
    sides = np.sort(np.concatenate([removed[:, [0, 1]], removed[:, [1, 2]], removed[:, [0, 2]]]), axis=1)
    sides = sides[tile.own[sides[:, 0]]]
    n = len(tile.records)
    keys = np.unique(sides[:, 0] * n + sides[:, 1])
    return np.column_stack([keys // n, keys % n])


def _held_edges(triangles: np.ndarray, edges: np.ndarray, n: int) -> np.ndarray:
    """(e,) bool: which edges (e, 2) (lower end first) a triangle of triangles (k, 3) over n
    vertices holds. Only the triangles with two ends of such edges among their corners
    are numbered: one gather of flags over the corners."""
    marked = np.zeros(n, dtype=np.uint8)
    marked[edges.ravel()] = 1
    near = np.compress(marked[triangles[:, 0]] + marked[triangles[:, 1]] + marked[triangles[:, 2]] >= 2,
                       triangles, axis=0)
    sides = np.sort(np.concatenate([near[:, [0, 1]], near[:, [1, 2]], near[:, [0, 2]]]), axis=1)
    return np.isin(edges[:, 0] * n + edges[:, 1], sides[:, 0] * n + sides[:, 1])


def _without(values: np.ndarray, taken: np.ndarray) -> np.ndarray:
    """values (m,) float64 without one occurrence of each of taken (t,) (bit for bit), a
    new array in values' order; RuntimeError if values hold one of them fewer times.
    The values whose lowest 16 bits are some taken value's are found by one look-up in a
    table of 2**16 flags, and only those are compared (a search per value cost a tile's
    summary 0.1 s)."""
    if not taken.size:
        return values
    keys = np.ascontiguousarray(values, dtype=np.float64).view(np.uint64)
    gone, count = np.unique(np.ascontiguousarray(taken, dtype=np.float64).view(np.uint64), return_counts=True)
    table = np.zeros(1 << 16, dtype=bool)
    table[gone.astype(np.uint16)] = True
    maybe = np.flatnonzero(table[keys.astype(np.uint16)])
    hits = maybe[np.isin(keys[maybe], gone)]
    order = np.argsort(keys[hits], kind="stable")             # each value's hits, in values' order
    runs = keys[hits][order]
    rank = np.arange(runs.size) - np.searchsorted(runs, runs)
    drop = hits[order[rank < count[np.searchsorted(gone, runs)]]]
    if drop.size != taken.size:
        raise RuntimeError(f"a summary held {drop.size} of the {taken.size} values to remove")
    return np.delete(values, drop)


def reconciled_summary(tile: Tile, first: float) -> tuple[np.ndarray, Reconciliation]:
    """The second noise floor's summary of one tile (`floor_summary` with the first floor
    `first`), and the tile's data reconciled with it, which `tile_limits` takes back."""
    table, other = edge_table_sides(tile.triangles, len(tile.records))[:2]
    counted = tile.own[table.edges[:, 0]]
    geometry = EdgeGeometry.of(tile.points, tile.values, table.edges)
    reconciled, _ = _reconciled(tile.values, tile.gradients, geometry, table, True, first)
    return (residual_sizes(reconciled.residuals(), counted),
            Reconciliation(reconciled.values, reconciled.gradients, reconciled.lifted, reconciled.moved,
                           edge_slots(table, other)))


def residual_sizes(residuals: np.ndarray, counted: np.ndarray | None = None) -> np.ndarray:
    """(e,) |residuals| of the edges counted (E,) bool marks (None: all), a new array: the
    values a noise floor is the median of (`floor_summary`)."""
    return np.abs(residuals if counted is None else np.compress(counted, residuals))


def reduce_floor(summaries: Chunks) -> float:
    """The noise floor: the exact median of the summaries' values (`floor_summary` or
    `residual_sizes` arrays; summaries() a fresh iterator of them, as
    c1mesh.stages.streamed_median takes them). One summary (the in-memory fit's one tile)
    is selected in place by np.median (it is consumed; 0 when empty); several by
    streamed_median, which gives np.median's bits. So a survey cut into any tiles has the
    one tile's floor."""
    parts = iter(summaries())
    first = next(parts, None)
    if first is not None and next(parts, None) is None:
        return float(np.median(first, overwrite_input=True)) if first.size else 0.0
    return streamed_median(summaries)


def _measured_floor(residuals: np.ndarray) -> float:
    """The noise floor of residuals (E,) over every edge: the one tile's summary, reduced."""
    return reduce_floor(lambda: (residual_sizes(residuals),))


def control_overshoot(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                      triangles: np.ndarray, mode: str = "limit", table: EdgeTable | None = None,
                      heights: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, LimiterReport]:
    """Heights, gradients and edge directions for an RSDInterpolator on a (noisy) height field.

    points (n, 2), values (n,), gradients (n, 2), triangles (T, 3). mode "limit" applies
    `reconcile_heights`, `reconcile_gradients`, then `limit_gradients`, and
    `edge_directions`; "off" returns the values and gradients unchanged and None (the
    interpolator's unit normals). table: the c1mesh.engine.topology.edge_table of the triangles if
    already built (pass the same table to the RSDInterpolator so the edges are numbered
    once). heights=False skips `reconcile_heights`: its crease test compares a slope
    error with 1 (45°), which needs the plane's and the height's units to agree, as in a
    height field and not in a depth chart (u, v, w). The in-memory fit's one tile: its
    noise floors are `floor_summary`'s values over every edge, reduced (`reduce_floor`),
    taken from the remedies' own residuals; `tile_limits` is the same on a tile of a
    survey with the survey's floors. Returns (values, gradients, directions in the order
    of table.edges or None, report).
    """
    if mode == "off":
        return values, gradients, None, LimiterReport()
    table = edge_table(triangles, points.shape[0]) if table is None else table
    limits = _limits(points, values, gradients, triangles, table, heights, None)
    return limits.values, limits.gradients, limits.directions, limits.report(table)


def tile_limits(tile: Tile, owned: np.ndarray, floors: NoiseFloors,
                reconciled: Reconciliation | None = None) -> TileLimits:
    """The limiter's run on one tile of a survey: the reconciled heights, limited gradients
    and edge directions of the tile's own triangles `owned` (k, 3) survey numbers, all
    inside the tile, with the survey's noise floors; changes counted over the vertices
    (and edges by their lower end) the tile owns, so the tiles' counts add up to the
    survey's. The halo must hold the star of every vertex within 3 longest edges of the
    cell (c1mesh.survey.halos): then the corners' results are the whole survey's.
    reconciled: this tile's data reconciled with floors.first (`reconciled_summary`), or
    None to reconcile it here; the same bits either way (its edges, when kept, are the
    edge table's, given back without a sort)."""
    if reconciled is not None and reconciled.edges is not None:
        table, other = table_from_slots(tile.triangles, len(tile.records), reconciled.edges)
    else:
        table, other = edge_table_sides(tile.triangles, len(tile.records))[:2]      # not its neighbours: memory
    limits = _limits(tile.points, tile.values, tile.gradients, tile.triangles, table, True, floors, reconciled)
    report = limits.report(table, tile.own)
    corners, triangles, at, own_table = own_triangles_in(tile, table, other, owned)
    records = tile.records.take(corners)                 # structured rows: take, not [corners]
    records["z"] = limits.values[corners]
    return TileLimits(records, triangles, limits.gradients[corners], limits.directions[at],
                      report.gradients_limited, report.directions_changed, report.heights_reconciled, own_table)


def own_triangles_in(tile: Tile, table: EdgeTable, other: np.ndarray,
                     owned: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, EdgeTable]:
    """A tile's own triangles `owned` (k, 3) survey numbers, some of its halo's triangles in
    their order there (c1mesh.survey.halos reads the tile's file in order), whose edges are
    table, and other its second slots (topology.edge_table_sides of tile.triangles):
    (corners (c,) ascending halo rows, triangles (k, 3) into corners, at (E',) the halo
    edge of each edge of those triangles, and their EdgeTable (E' edges), equal to
    edge_table(triangles, c)).

    The halo reads each tile's file in turn, so the owned triangles are one run of its
    rows (`_owned_run`, checked row for row), else they are found by trim.kept_triangles'
    hash, one pass; their table is the halo table's sub_table, which keeps the halo
    edges' order (`at`), without another sort. RuntimeError when they are not, in order,
    the rows of `owned`."""
    tri = tile.triangles
    owned = np.asarray(owned, dtype=np.int64)
    start = _owned_run(tile, owned)
    if start is None:
        keep = ~kept_triangles(tri, owned, tile.records["index"])
        mine = tri[keep]
        if mine.shape != owned.shape or not np.array_equal(tile.records["index"][mine], owned):
            raise RuntimeError("a tile's own triangles are not, in order, some of its halo's triangles")
    else:                                 # _owned_run compared the run with owned, row for row
        keep = np.zeros(len(tri), dtype=bool)
        keep[start:start + len(owned)] = True
        mine = tri[start:start + len(owned)]
    corners, triangles = compact(mine, len(tile.records))
    at = np.flatnonzero(live_edges(table, keep, other)[1])
    return corners, triangles, at, sub_table(table, keep, other, corners)


def _owned_run(tile: Tile, owned: np.ndarray) -> int | None:
    """The first row of the run of tile.triangles whose survey numbers are owned (k, 3) row
    for row, or None when no run starting at a row that begins as owned[0] is."""
    tri, numbers = tile.triangles, tile.records["index"]
    if not len(owned) or len(owned) > len(tri):
        return None
    for start in np.flatnonzero(numbers[tri[: len(tri) - len(owned) + 1, 0]] == owned[0, 0]).tolist():
        if np.array_equal(numbers[tri[start:start + len(owned)]], owned):
            return start
    return None


@dataclass(frozen=True)
class _Limits:
    """The remedies over one tile: values (n,), gradients (n, 2), directions (E, 2); which
    vertices' heights moved (lifted), gradients were reconciled (moved) or limited
    (changed), (n,) bool each, and which edges turned (E,) bool."""

    values: np.ndarray
    gradients: np.ndarray
    directions: np.ndarray
    lifted: np.ndarray
    moved: np.ndarray
    changed: np.ndarray
    turned: np.ndarray

    def report(self, table: EdgeTable, counted: np.ndarray | None = None) -> LimiterReport:
        """The changes of the vertices counted (n,) bool marks and of the edges whose lower
        end it marks (None: all)."""
        changed, moved, lifted, turned = self.changed, self.moved, self.lifted, self.turned
        if counted is not None:
            changed, moved, lifted, turned = (changed & counted, moved & counted, lifted & counted,
                                              turned & counted[table.edges[:, 0]])
        return LimiterReport(int((changed | moved).sum()), int(turned.sum()), int(lifted.sum()))


def _limits(points: np.ndarray, values: np.ndarray, gradients: np.ndarray, triangles: np.ndarray,
            table: EdgeTable, heights: bool, floors: NoiseFloors | None,
            reconciled: Reconciliation | None = None) -> _Limits:
    """`control_overshoot`'s remedies on a tile's arrays with its edge table; floors: the
    survey's (None: the one tile's own, measured); reconciled: as tile_limits takes it."""
    geometry = EdgeGeometry.of(points, values if reconciled is None else reconciled.values, table.edges)
    # The directions need only the positions: they run in one thread beside the heights'
    # and gradients' remedies (core.threads.overlap; one after the other with one worker).
    (directions, turned), (values, limited, lifted, moved, changed) = overlap(
        lambda: _directions(points, triangles, table, (geometry.dx, geometry.dy), RATIO_LIMIT, threads=1),
        lambda: _remedies(values, gradients, geometry, table, floors, heights, reconciled))
    return _Limits(values, limited, directions, lifted, moved, changed, turned)


def _remedies(values: np.ndarray, gradients: np.ndarray, geometry: "EdgeGeometry", table: EdgeTable,
              floors: NoiseFloors | None, heights: bool,
              known: Reconciliation | None = None) -> tuple[np.ndarray, ...]:
    """`control_overshoot`'s heights and gradients: (values (n,), gradients (n, 2), and the
    (n,) bool vertices whose height moved, gradient was reconciled, gradient was limited).
    known: the data reconciled already (geometry then over its values), whose predictions
    over every edge are those `_reconciled` updates edge by edge."""
    if known is None:
        reconciled, _ = _reconciled(values, gradients, geometry, table, heights,
                                    None if floors is None else floors.first)
    else:
        reconciled = _Reconciled(known.values, known.gradients, geometry, geometry.predictions(known.gradients),
                                 known.lifted, known.moved)
    second = _measured_floor(reconciled.residuals()) if floors is None else floors.second
    limited, changed = _limit(reconciled.gradients, reconciled.geometry, reconciled.predicted, SECANT_FACTOR,
                              CONSISTENCY, NOISE_FACTOR, second)
    return reconciled.values, limited, reconciled.lifted, reconciled.moved, changed


@dataclass(frozen=True)
class _Reconciled:
    """A tile's data after `reconcile_heights` (when asked) and `reconcile_gradients`:
    values (n,), gradients (n, 2), their geometry and predictions over the table's edges,
    and which vertices' heights (lifted) and gradients (moved) changed, (n,) bool."""

    values: np.ndarray
    gradients: np.ndarray
    geometry: "EdgeGeometry"
    predicted: tuple[np.ndarray, np.ndarray]
    lifted: np.ndarray
    moved: np.ndarray

    def residuals(self) -> np.ndarray:
        """(E,) the trapezoid residuals of the reconciled data."""
        return self.geometry.residuals(self.predicted)


def _reconciled(values: np.ndarray, gradients: np.ndarray, geometry: "EdgeGeometry", table: EdgeTable,
                heights: bool, first: float | None) -> tuple[_Reconciled, float]:
    """values (n,) and gradients (n, 2) over geometry (the table's edges) reconciled with
    the first noise floor (None: measured over these edges, the one tile's); returns them
    and that floor."""
    predicted = geometry.predictions(gradients)             # heights do not change these
    residual = geometry.residuals(predicted)
    if first is None:
        first = _measured_floor(residual)
    lifted = np.zeros(values.shape[0], dtype=bool)
    if heights:
        values, lifted = _reconcile_heights(values, geometry, residual, table, first)
    if lifted.any():
        geometry = geometry.with_values(values)
    reconciled, moved, near = _reconcile(gradients, geometry, predicted, first)
    # Reconciliation changes the gradients of touched vertices only, so only the edges
    # that reach one ("near") predict anything new.
    predicted = geometry.predictions(reconciled, near, into=predicted)
    return _Reconciled(values, reconciled, geometry, predicted, lifted, moved), first


def reconcile_heights(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                      triangles: np.ndarray, table: EdgeTable | None = None,
                      noise_floor: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Heights (n,) of short edges moved toward what their gradients say, within the noise.

    Why: two points d apart whose heights differ by noise make the spline rise by the
    edge's trapezoid residual e = Δ − (δ_a + δ_b)/2 across d, while their gradients say it
    does not. The spline then creases along the edge's triangles with a curvature of about
    6|e|/d² (a cubic's, rising e over d with zero end slopes), and a sub-face of length
    D/L (D the longest edge of the edge's triangles, L = `CREASE_LEVEL`) samples that
    crease with a slope error of about (D/L)·6|e|/d². Above 1 (45°) sub-faces fold
    against the spline's normals and show as needles, though the spline itself is C1 and
    does not fold (docs/overshoot.md, "Remedy 3").

    What: every edge with 6|e|·D > L·d² moves each end by half its residual, toward each
    other's prediction (a residual of zero for the pair), clipped to HEIGHT_CLIP ×
    noise_floor (the median |e| over all edges; measured here when None); a vertex on
    several such edges moves by the mean of their moves. One height per vertex, so the
    spline stays C1. Exact data of any quadratic have e = 0 and move nothing; smooth data
    have e = O(d³), so only an edge far shorter than its triangles can qualify, and it
    moves by at most half its O(d³) residual. Returns (values, changed (n,) bool).
    """
    table = edge_table(triangles, points.shape[0]) if table is None else table
    geometry = EdgeGeometry.of(points, values, table.edges)
    residual = geometry.residuals(geometry.predictions(gradients))
    if noise_floor is None:
        noise_floor = _measured_floor(residual)
    return _reconcile_heights(values, geometry, residual, table, noise_floor)


def _reconcile_heights(values: np.ndarray, geometry: "EdgeGeometry", residual: np.ndarray,
                       table: EdgeTable, noise_floor: float) -> tuple[np.ndarray, np.ndarray]:
    """`reconcile_heights` on gathered edge data and residuals (E,): the squared lengths and
    their triangles' longest (`_longest_adjacent_edge2`), then the kernel's moves
    (stages/_limiter.pyx crease_moves), one thread."""
    f = np.asarray(values, dtype=float)
    n = f.shape[0]
    if noise_floor <= 0:
        return f, np.zeros(n, dtype=bool)
    length2 = geometry.dx * geometry.dx
    length2 += geometry.dy * geometry.dy
    reach2 = _longest_adjacent_edge2(length2, table)
    out, count = np.empty(n), np.zeros(n, dtype=np.int64)
    moved = kernel.crease_moves(np.ascontiguousarray(f), geometry.a, geometry.b,
                                np.ascontiguousarray(residual, dtype=np.float64), length2, reach2,
                                float(CREASE_LEVEL), HEIGHT_CLIP * noise_floor, np.zeros(n), count,
                                np.empty(length2.size, dtype=np.int64), out)
    if moved == 0:
        return f, np.zeros(n, dtype=bool)
    return out, count > 0


def _longest_adjacent_edge2(length2: np.ndarray, table: EdgeTable) -> np.ndarray:
    """(E,) the squared longest edge of the triangles that contain each edge, from the edges'
    squared lengths length2 (E,) >= 0 (plane units squared); NaN where a NaN takes part, as
    np.maximum.at from zeros gives it. The kernel (stages/_limiter.pyx), one thread."""
    if length2.shape != table.count.shape:
        raise ValueError(f"length2 has shape {length2.shape}, the table {table.count.shape[0]} edges")
    out = np.empty(length2.shape[0])
    kernel.longest_adjacent(np.ascontiguousarray(length2, dtype=np.float64),
                            np.ascontiguousarray(table.tri_edge, dtype=np.int64), out)
    return out


def _edge_blocks(work, count: int, threads: int | None = None) -> None:
    """work(start, stop) over the fixed blocks of KERNEL_BLOCK of range(count), in the
    thread knob's threads or ``threads`` (each block writes its own rows: the same bits
    at any count)."""
    parallel_blocks(lambda part: work(part.start, part.stop), count, KERNEL_BLOCK, threads)


def _rows(array: np.ndarray) -> np.ndarray:
    """An (m, 2) float array as the kernels take it, C-ordered float64 (a copy only when it
    is not): a point's or a gradient's two components in one row, one cache line."""
    array = np.ascontiguousarray(array, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise InputError(f"expected an (m, 2) array, got shape {array.shape}")
    return array


def _edge_ends(edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a, b) (E,) each: the two ends of edges (E, 2), contiguous int64, for the kernels;
    copied over blocks of edges in the thread knob's threads (numpy's copies release the
    GIL), so the new arrays' pages fault in on both cores."""
    edges = np.asarray(edges, dtype=np.int64)
    a, b = np.empty(edges.shape[0], dtype=np.int64), np.empty(edges.shape[0], dtype=np.int64)

    def copy(part: slice) -> None:
        a[part], b[part] = edges[part, 0], edges[part, 1]
    parallel_blocks(copy, edges.shape[0], KERNEL_BLOCK)
    return a, b


@dataclass(frozen=True)
class EdgeGeometry:
    """What the consistency test needs of each edge a→b that no gradient changes.

    a, b (E,) int64 vertex indices; dx, dy (E,) = p_b − p_a (plane units); delta (E,) =
    f_b − f_a; size (E,) = |f_a| + |f_b| (for the rounding allowance), all contiguous.
    Gathered once and shared by the reconciliation, the limiter and the edge directions.
    """

    a: np.ndarray
    b: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    delta: np.ndarray
    size: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray, values: np.ndarray, edges: np.ndarray) -> "EdgeGeometry":
        """The geometry of edges (E, 2) over points (n, 2) and heights values (n,); the
        kernels (edge_vectors, edge_values) in blocks of edges."""
        a, b = _edge_ends(edges)
        return cls(a, b, *_edge_vectors(points, a, b), *_edge_values(values, a, b))

    def with_values(self, values: np.ndarray) -> "EdgeGeometry":
        """The same edges over new heights (the positions' differences are kept)."""
        return EdgeGeometry(self.a, self.b, self.dx, self.dy, *_edge_values(values, self.a, self.b))

    def predictions(self, gradients: np.ndarray, rows: np.ndarray | None = None,
                    into: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(A_a·d, A_b·d) (E,) each: the height changes the end gradients (n, 2) predict.
        rows (E,) bool: only those edges are computed, written into ``into`` (pred_a,
        pred_b), which keeps the others; None: every edge, into ``into`` or new arrays."""
        g = _rows(gradients)
        if rows is not None and into is None:
            raise ValueError("predictions of some rows need the arrays to write them into")
        pred_a, pred_b = (np.empty(self.a.size), np.empty(self.a.size)) if into is None else into
        mask = np.empty(0, dtype=np.uint8) if rows is None else np.ascontiguousarray(rows, dtype=bool).view(np.uint8)
        _edge_blocks(lambda start, stop: kernel.predict(g, self.a, self.b, self.dx, self.dy, mask,
                                                        pred_a, pred_b, start, stop), self.a.size)
        return pred_a, pred_b

    def residuals(self, predicted: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """e = Δ − (δ_a + δ_b)/2 (E,), height units, from the predictions (pred_a, pred_b)."""
        out = np.empty(self.a.size)
        _edge_blocks(lambda start, stop: kernel.residuals(self.delta, *predicted, out, start, stop), out.size)
        return out


def _edge_vectors(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) (E,): p_b − p_a of the edges a→b (E,) over the points (n, 2); InputError for
    an index outside the points."""
    xy = _rows(points)
    n = xy.shape[0]
    if a.size and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= n):
        raise InputError(f"edge indices must lie in [0, {n}), got "
                         f"{min(a.min(), b.min())}..{max(a.max(), b.max())}")
    dx, dy = np.empty(a.size), np.empty(a.size)
    _edge_blocks(lambda start, stop: kernel.edge_vectors(xy, a, b, dx, dy, start, stop), a.size)
    return dx, dy


def _edge_values(values: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(delta, size) (E,) of the edges a→b over the heights values (n,)."""
    f = np.ascontiguousarray(values, dtype=np.float64)
    delta, size = np.empty(a.size), np.empty(a.size)
    _edge_blocks(lambda start, stop: kernel.edge_values(f, a, b, delta, size, start, stop), a.size)
    return delta, size


def trapezoid_residuals(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                        edges: np.ndarray) -> np.ndarray:
    """e = Δ − (δ_a + δ_b)/2 per edge (E,): zero for every quadratic, O(|d|³) for smooth
    data. The median of |e| over a survey's edges is its noise floor (`inconsistent_edges`)."""
    geometry = EdgeGeometry.of(points, values, edges)
    return geometry.residuals(geometry.predictions(gradients))


def inconsistent_edges(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                       edges: np.ndarray, consistency: float = CONSISTENCY,
                       noise_factor: float = NOISE_FACTOR, noise_floor: float | None = None
                       ) -> tuple[np.ndarray, dict]:
    """Edges (E,) bool whose end gradients say something their heights do not.

    For an edge k→j with d = p_j − p_k, Δ = f_j − f_k, δ_k = A_k·d, δ_j = A_j·d, the
    trapezoid residual e = Δ − (δ_k + δ_j)/2 vanishes for every quadratic and is O(|d|³)
    for smooth data. An edge is inconsistent when |e| > consistency · max(|Δ|, |δ_k|/2,
    |δ_j|/2) + noise_factor · median |e| (the noise floor of the data set; ``noise_floor``
    gives it when these edges are part of a larger survey) + rounding.
    Also returns the per-edge quantities {"delta", "pred_a", "pred_b", "noise"}.
    """
    geometry = EdgeGeometry.of(points, values, edges)
    return _inconsistent(geometry, geometry.predictions(gradients), consistency,
                         noise_factor, noise_floor)


def _inconsistent(geometry: EdgeGeometry, predicted: tuple[np.ndarray, np.ndarray],
                  consistency: float, noise_factor: float, noise_floor: float | None
                  ) -> tuple[np.ndarray, dict]:
    """`inconsistent_edges` on gathered edge data and predictions (pred_a, pred_b): the
    kernel's test (stages/_limiter.pyx inconsistent) in blocks of edges."""
    pred_a, pred_b = predicted
    if noise_floor is None:
        noise_floor = _measured_floor(geometry.residuals(predicted))
    noise = noise_factor * noise_floor
    bad = np.empty(geometry.a.size, dtype=bool)
    rounding = 64 * np.finfo(float).eps
    _edge_blocks(lambda start, stop: kernel.inconsistent(geometry.delta, pred_a, pred_b, geometry.size,
                                                         consistency, noise, rounding, bad.view(np.uint8),
                                                         start, stop), bad.size)
    return bad, {"delta": geometry.delta, "pred_a": pred_a, "pred_b": pred_b, "noise": noise}


def reconcile_gradients(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                        edges: np.ndarray, normal_weight: float = NORMAL_WEIGHT,
                        noise_floor: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gradients (n, 2) blended with the 1-ring heights where they disagree with them.

    At every vertex k touching an inconsistent edge (`inconsistent_edges`), the gradient
    becomes the least-squares solution of the secant slopes of all its edges and the
    normal's own gradient A_k:

        min_G  Σ_e (G·û_e − Δ_e/|d_e|)² + normal_weight · deg_k · |G − A_k|²,

    û_e the unit edge direction, deg_k the vertex's edge count: the heights and the normal
    weigh the same at normal_weight = 1. Other vertices keep A_k, so exact smooth data
    (no inconsistent edge) are unchanged. One gradient per vertex: the spline stays C1.
    noise_floor as in `inconsistent_edges`. Returns (gradients, changed (n,) bool).
    """
    geometry = EdgeGeometry.of(points, values, edges)
    out, touched, _ = _reconcile(gradients, geometry, geometry.predictions(gradients),
                                 noise_floor, normal_weight)
    return out, touched


def _reconcile(gradients: np.ndarray, geometry: EdgeGeometry, predicted: tuple[np.ndarray, np.ndarray],
               noise_floor: float | None, normal_weight: float = NORMAL_WEIGHT
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`reconcile_gradients` on gathered edge data; also returns the (E,) bool edges that
    reach a changed vertex. The kernels mark the touched vertices (touch, one thread) and
    build their 2×2 systems (normal_equations, a range of vertices per thread, the sums
    in numpy's bincount order); numpy's solve (LAPACK) solves them."""
    A = np.asarray(gradients, dtype=float)
    n = A.shape[0]
    bad, _ = _inconsistent(geometry, predicted, CONSISTENCY, NOISE_FACTOR, noise_floor)
    touched, near = np.zeros(n, dtype=bool), np.empty(bad.size, dtype=bool)
    kernel.touch(geometry.a, geometry.b, bad.view(np.uint8), touched.view(np.uint8), near.view(np.uint8))
    vertices = np.flatnonzero(touched)
    position = np.full(n, -1, dtype=np.int64)
    position[vertices] = np.arange(vertices.size)
    M_t, r_t, degree = np.zeros((vertices.size, 2, 2)), np.zeros((vertices.size, 2)), np.zeros(vertices.size)
    g = _rows(A)
    # One range of vertices per thread: a vertex's sums are the same in any range (the
    # kernel's docstring says why), so the ranges need not be fixed blocks.
    parallel_blocks(lambda part: kernel.normal_equations(geometry.a, geometry.b, geometry.dx, geometry.dy,
                                                         geometry.delta, near.view(np.uint8), position,
                                                         vertices, g, float(normal_weight), degree,
                                                         M_t, r_t, part.start, part.stop),
                    vertices.size, max(1, -(-vertices.size // thread_count())))
    out = A.copy()
    out[touched] = _solve_2x2(M_t, r_t)
    return out, touched, near


def _solve_2x2(M: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The solutions (m, 2) of the systems M (m, 2, 2) x = r (m, 2) by numpy's solve
    (LAPACK's gesv), in fixed blocks of systems, in one thread whatever the knob says:
    OpenBLAS's gesv called from two threads at once ran 3x slower than from one (0.23-0.31 s
    against 0.08 s for the 1M-point LAZ fit's systems, with the limiter's directions on the
    other core), so threads cost here. Each system is solved alone: the same bits."""
    x = np.empty_like(r)

    def block(part: slice) -> None:
        x[part] = np.linalg.solve(M[part], r[part, :, None])[:, :, 0]
    parallel_blocks(block, r.shape[0], KERNEL_BLOCK, threads=1)
    return x


def limit_gradients(points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                    edges: np.ndarray, secant_factor: float = SECANT_FACTOR,
                    consistency: float = CONSISTENCY,
                    noise_factor: float = NOISE_FACTOR, noise_floor: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Gradients (n, 2) scaled down where they disagree with the neighbouring heights.

    points (n, 2), values (n,), gradients (n, 2) in the height-field frame; edges (E, 2)
    vertex pairs of the triangulation. Returns (new gradients, changed (n,) bool).

    For an edge k→j with d = p_j − p_k, the height change Δ = f_j − f_k and the changes
    the end gradients predict, δ_k = A_k·d and δ_j = A_j·d, the trapezoid residual
    e = Δ − (δ_k + δ_j)/2 vanishes for every quadratic and is O(|d|³) for smooth data.
    An edge is inconsistent when |e| > consistency · max(|Δ|, |δ_k|/2, |δ_j|/2) +
    noise_factor · median |e| (the noise floor of the whole data set) + rounding: the
    gradients then say something the heights do not. On inconsistent edges each end's
    prediction must lie between 0 and secant_factor · Δ (so it has the secant's sign and
    at most that multiple of its size, as in Fritsch–Carlson); a vertex gradient is
    multiplied by the largest t in [0, 1] that meets this on all its inconsistent edges.
    Scaling keeps the direction, and 0 always qualifies (a flat vertex cannot overshoot
    along an edge by itself). noise_floor as in `inconsistent_edges`.
    """
    geometry = EdgeGeometry.of(points, values, edges)
    return _limit(gradients, geometry, geometry.predictions(gradients), secant_factor,
                  consistency, noise_factor, noise_floor)


def _limit(gradients: np.ndarray, geometry: EdgeGeometry,
           predicted: tuple[np.ndarray, np.ndarray], secant_factor: float,
           consistency: float, noise_factor: float, noise_floor: float | None
           ) -> tuple[np.ndarray, np.ndarray]:
    """`limit_gradients` on gathered edge data and the gradients' predictions: each vertex's
    factor by the kernel (stages/_limiter.pyx limit_factors, one thread)."""
    A = np.asarray(gradients, dtype=float)
    bad, parts = _inconsistent(geometry, predicted, consistency, noise_factor, noise_floor)
    factor = np.ones(A.shape[0])
    kernel.limit_factors(geometry.a, geometry.b, geometry.delta, *predicted, bad.view(np.uint8),
                         float(secant_factor), parts["noise"], factor)
    changed = factor < 1.0
    limited = A.copy()
    limited[changed] *= factor[changed, None]
    return limited, changed


def edge_directions(points: np.ndarray, triangles: np.ndarray, table: EdgeTable,
                    ratio_limit: float = RATIO_LIMIT) -> tuple[np.ndarray, np.ndarray]:
    """One direction per edge of ``table`` (E, 2) that keeps the RSD ratios small.

    In a triangle with the edge [p_l, p_m] opposite p_n, a direction u through p_n meets
    the edge's line at q = p_l + s (p_m − p_l), and then G_l·u / G_n·u = −(1 − s) and
    G_m·u / G_n·u = −s: the ratios are bounded by 1 when q lies on the edge, and grow
    without bound for the unit normal on obtuse thin triangles (its foot q falls far
    outside the edge). Candidates: the unit normal, the line joining the two opposite
    vertices (interior edges; q on the edge when the quadrilateral is convex), and the
    lines from each opposite vertex to the edge's midpoint. The unit normal is kept
    unless its worst ratio over the edge's triangles exceeds ``ratio_limit``; otherwise
    the candidate with the smallest worst ratio wins. Returns (directions (E, 2),
    changed (E,) bool). Every direction is used by both triangles of its edge, so the
    spline stays C1 (Thm 3.4).
    """
    p = np.asarray(points, dtype=float)
    return _directions(p, triangles, table, _edge_vectors(p, *_edge_ends(table.edges)), ratio_limit)


def _directions(p: np.ndarray, triangles: np.ndarray, table: EdgeTable,
                edge: tuple[np.ndarray, np.ndarray], ratio_limit: float,
                threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`edge_directions` given the edge vectors (dx, dy) (E,) each = p_b − p_a, in the
    thread knob's threads or ``threads``."""
    p = np.asarray(p, dtype=float)
    tri = _checked_triangles(triangles, table, p.shape[0])
    dx, dy = edge
    out = np.empty((dx.size, 2))
    _edge_blocks(lambda start, stop: kernel.unit_normals(dx, dy, out, start, stop), dx.size, threads)
    # The unit normal's foot is the projection of the opposite vertex onto the edge's line,
    # so its worst ratio needs no cross products. Only the edges the screen flags (a few
    # percent on real scans) weigh the other candidates, and the kernel decides there
    # (choose_directions, in blocks of flagged edges).
    change = _normal_ratio_screen(p, tri, table, threads) > ratio_limit * (1 - 1e-9)
    if not change.any():
        return out, change
    idx = np.flatnonzero(change)
    first, second = _opposite_vertices(tri, table, idx)
    xy = _rows(p)
    a, b = _edge_ends(table.edges)
    parallel_blocks(lambda part: kernel.choose_directions(xy, a, b, dx, dy, idx, first, second,
                                                          float(ratio_limit), out, change.view(np.uint8),
                                                          part.start, part.stop), idx.size, KERNEL_BLOCK >> 4,
                    threads)
    return out, change


def _checked_triangles(triangles: np.ndarray, table: EdgeTable, n: int) -> np.ndarray:
    """triangles (T, 3) as the kernels take them (C-ordered int64), after checking that
    they are the table's and index the n points."""
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    if tri.shape != table.tri_edge.shape:
        raise InputError(f"triangles have shape {tri.shape}, the edge table {table.tri_edge.shape}")
    if tri.size and (tri.min() < 0 or tri.max() >= n):
        raise InputError(f"triangle indices must lie in [0, {n}), got {tri.min()}..{tri.max()}")
    return tri


def _normal_ratio_screen(p: np.ndarray, tri: np.ndarray, table: EdgeTable,
                         threads: int | None = None) -> np.ndarray:
    """Worst max(|s|, |1 − s|) of the unit normal over each edge's one or two triangles,
    s = (p_n − p_l)·e / |e|² the foot of the opposite vertex p_n on the edge's line (the
    ratio does not depend on which end is p_l). The kernels (stages/_limiter.pyx) in
    blocks of triangles: each corner's ratio (corner_ratios), then per edge the value of
    its owner's corner where larger than its other corner's, else the other's (NaN
    included, as a scatter of every slot in slot-major order followed by the larger ones
    left it; edge_screen). A screen: choose_directions decides."""
    xy = _rows(p)
    ratio = np.empty(tri.shape)
    screen = np.empty(table.edges.shape[0])
    _edge_blocks(lambda start, stop: kernel.corner_ratios(xy, tri, ratio, start, stop), tri.shape[0], threads)
    _edge_blocks(lambda start, stop: kernel.edge_screen(table.tri_edge, table.owner, table.owner_slot,
                                                        table.count, ratio, screen, start, stop),
                 tri.shape[0], threads)
    return screen


def _opposite_vertices(tri: np.ndarray, table: EdgeTable, idx: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """For the edges ``idx`` the vertex opposite each in its owner triangle, and in the
    other triangle (-1 on the boundary); the kernel (opposite_vertices), one thread."""
    first = tri[table.owner[idx], table.owner_slot[idx]]
    position = np.full(table.edges.shape[0], -1, dtype=np.int64)
    position[idx] = np.arange(idx.size)
    second = np.full(idx.size, -1, dtype=np.int64)
    kernel.opposite_vertices(tri, table.tri_edge, position, first, second)
    return first, second
