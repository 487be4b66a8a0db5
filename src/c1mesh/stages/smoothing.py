"""The C1 smoothing fit of the RSD spline: vertex values and gradients from noisy data (issue 24).

The unknowns are u = (f_v, ∇f_v) at every vertex; the spline they define (the same one
RSDInterpolator builds from them, with the same edge directions and scheme) minimises

    Σ_i w_i (F(x_i) − z_i)²  +  λ ∫ F_xx² + 2 F_xy² + F_yy² dx  [ + μ Σ_v |∇f_v − n_v|² ]

over the data points x_i (by default the vertices themselves). λ comes from a
dimensionless strength s, λ = s · h² · Σw / M (h the mean point spacing, M data points),
which makes the fit's shape independent of the units of x, y, z and of the weights'
scale; `strength="auto"` picks s by cross-validation over spatial blocks. Derivations,
quadrature, solver measurements: docs/smoothing.md.

    fit = smooth_fit(points, triangles, SmoothingData(z, spacing=h), SmoothingControl(strength="auto"))
    interp = RSDInterpolator(points, fit.values, fit.gradients, triangles)

What the fit matches is a SmoothingData (values, where and how much they weigh, their
spacing), how it runs a SmoothingControl (strength, scheme, folds, seed, threads), and
gradients it may be pulled toward a GradientPrior.

The energy blocks live in smoothing_energy, the sparse system and solvers in
smoothing_system; this module normalises units, validates input, and chooses s.

The stage on a tile (core.tile.Tile; the bottom of this module). `smooth_tile` is its run:
the fit of a tile's vertices and final triangles, returning what its own vertices and
triangles need (their fitted heights and gradients, their edges' directions) and the
facts of its solve (TileSolve). `smoothing_reach` is how far it reads beyond its cell.
What must be the same across the survey is the strength s (given, or with "auto" the
cross-validation search on one tile, `search_strength`) and the report's totals, a
reduce over the tiles' solves (`solve_totals`, `combined_fit`). The in-memory fit is one
tile, every vertex owned (Tile.whole), run by `smooth_tile` itself; a survey fitted in
tiles runs it on every tile's cell grown by its halo (c1mesh.survey.smoothing_runs): one
sweep of restricted overlapping Schwarz, each tile keeping the vertex data of the
vertices in its own cell, every edge one direction, whichever tile refines its triangles.
That union is the C1 spline of those vertex data; it differs from the one-tile fit only
through the halo's cut: the fit's influence decays over a few smoothing lengths
ℓ = s^(1/4) h (the length at which the energy λ ∫|D²F|² and the data term per area h⁻²
balance), and the halo reaches HALO_LENGTHS of them (docs/smoothing.md, "In tiles").
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from c1mesh.core.threads import limit, parallel_blocks
from c1mesh.core.tile import Tile, plane_bounds
from c1mesh.engine import rsd
from c1mesh.engine.locate import TriangleLocator
from c1mesh.engine.schemes import DEFAULT_SCHEME, ShapeTuple, get_scheme
from c1mesh.engine.topology import edge_table, edge_table_sides
from c1mesh.stages import _smoothing as kernel
from c1mesh.stages.folds import ROUNDS as FOLD_ROUNDS, CellStiffness, folded_triangles
from c1mesh.stages.lattice_solver import Lattice, LatticeFactor, LatticeSolver, colour_order, stencil_neighbours
from c1mesh.stages.lattice_system import LatticeSystem
from c1mesh.stages.limiter import edge_directions, own_triangles_in
from c1mesh.stages.smoothing_energy import (SchemeNotPolynomialError, SmoothingError,
                                            energy_blocks, energy_blocks_of, energy_tensor,
                                            triangle_directions)
from c1mesh.stages.smoothing_system import (Factor, System, TriangleShapes, assemble_energy,
                                            available_solvers, data_rows, hat_trace, solve, timed,
                                            vertex_order)
from c1mesh.stages.trim import connected_sets

CV_BLOCK = 4.0
"""Side of a cross-validation block, in mean point spacings h (shrunk on small inputs so
that there are at least 4 blocks per fold). Larger blocks guard against spatially
correlated errors but turn held-out blocks into holes the fit must bridge, which biases
the choice toward less smoothing (docs/smoothing.md: 8 h chose s 3x too small on white
noise, 1 h and 4 h within 30 % of the best)."""
SEARCH_VERTICES = 5_000
"""Above this many points the search for s runs on square windows of the mesh (SearchWindows,
`search_windows`) holding about this many vertices together, then one full solve follows.
Held-out RMS, benchmarks.heldout's splits, seeds 0-4, against the search on the whole mesh
(autzen_trim ground / 4_6_crop ground / synthetic 100 m terrain), in WINDOW_ANCHORS' 9
windows: the lattice (the default) 0, +0.39 %, 0; a vertex at every point +0.13 %, +0.09 %,
-0.14 %. In 4 windows at the quarter points (until the nineteenth stop) the lattice missed
by +1.4 % on 4_6_crop (its windows chose twice the whole's s), the vertices at the points
-0.10 %, -0.10 %, -0.22 %; 10,000 points in 4 windows gave +0.33 %, 0 (whole mesh), -0.18 %
at twice the search's time, 2,500 +1.5 % on autzen. Pieces a window cuts off are not
scored (MIN_PIECE_DATA; docs/smoothing.md, "Speed")."""
WINDOW_ANCHORS = tuple((x, y) for y in (1 / 6, 1 / 2, 5 / 6) for x in (1 / 6, 1 / 2, 5 / 6))
"""Where the search windows go, as fractions of the points' bounding box: each window is
centred on the point nearest one of these anchors (`search_windows`), the centres of a 3 × 3
grid of the box. Nine small windows sample a survey whose terrain varies more places than
four larger ones at the quarter points did, at no more cost (a window's factor grows faster
than its size)."""
CHART_SEARCH_SHARE = 0.1
"""The share of a perspective chart's vertices its search windows hold (at least
SEARCH_VERTICES; `chart_search_vertices`). A depth frame is a scene, not a terrain: a table,
a mug, a wall, their edges, each wanting its own smoothing, and the nine windows of 5,000
pixels sample 2.4 % of the mug stereo frame's 209,029 on flat patches. Measured there
(windows at the nine anchors, the strength s each size chooses; the whole chart's own
search, 267 s, chooses 0.058): 5,000 vertices 0.17 (the whole chart's CV score 1.5 % above
its best), 10,000 0.17, 20,903 (this share) 0.088 (+0.19 %), 40,000 0.091; the fit 11.7 s
against 8.4-9.2 s at 5,000. On noisy quantised synthetic frames, whose content is one
surface, both sizes are within 1 % (docs/perspective.md, "Smoothing in the chart")."""
CHART_SEARCH_MOST = 25_000
"""The most vertices a chart's search windows hold, whatever its share: the search's cost
grows faster than its windows (its factors), and on a frame four times the mug's (the mug
tiled 2 × 2 in its chart, 835,609 pixels) a tenth of it (83,560) took 31 s of search, 2.5×
the final factor, to choose the same s as 5,000 pixels (0.058, the single mug's best); at
25,000, 5.9 s and s = 0.088 (on the single mug 1.0019× its best CV). The mug itself
(20,903) is below it."""
CV_RIDGE = 1e-9
"""Relative ridge of the cross-validation solves (smoothing_system.solve: a held-out
block may cover a whole island of the mesh)."""
GRID = tuple(float(e) for e in range(-3, 5))
"""log10 s of the coarse search (stopped two steps past the lowest score); where the
lowest score is at an end of it, the grid goes on past that end in the same steps
(SEARCH_LIMITS); REFINE_STEPS of golden-section search in log s follow in the two steps
around the best."""
SEARCH_LIMITS = (-6.0, 7.0)
"""log10 s past which the coarse grid is not extended: beyond them the fit no longer
changes with s for anything the data can show, so the CV curve is flat and could not
turn. A feature of wavelength ℓ spacings keeps about 1 / (1 + s (2π/ℓ)⁴) of its height
(docs/smoothing.md). At s = 1e-6 the shortest wavelength the points resolve (ℓ = 2) keeps
all but 1e-4 of it: the fit is the interpolant. At s = 1e7 a feature keeps half its
height only if it is 2π s^¼ ≈ 350 spacings long, over 3 times the side of the largest
region the search fits (SEARCH_VERTICES, ~100 spacings): the fit is the plane."""
REFINE_STEPS = 4
EDF_PROBES = 4
LATTICE_EDF_PROBES = 1
"""Hutchinson probes of the edf on the lattice, where each probe is a multigrid CG solve over
the whole survey (about 1 s at 1M nodes) rather than a back substitution: one probe's
standard deviation is below √(2 edf) (hat_trace), 0.7 % at edf 40,000. Measured on the DTM
job (1M nodes, edf 40,048): eight probes gave 39,745-40,281, standard deviation 209 (0.5 %).
The edf is only reported, so a 0.5 % spread is worth the 3 s that three more probes cost."""
LATTICE_STEP = 3e-6
"""With `smooth_fit(..., lattice=)`, the final solve's CG stops once a step moves no vertex
height by more than this many Z (the RMS of the data about their weighted plane, the
normalised height unit; stages.lattice_solver: the last step bounds the error). Z is not
the noise: it holds the relief too, so a constant relative to it is one relative to the
relief. The grid-solver study stopped at 0.05 mm on a survey of Z ≈ 15 m with 2 cm noise
(3.3e-6 Z), and every run then lay within 0.074 mm of CHOLMOD (0.4 % of the noise); this
constant keeps that, and where Z is near the noise (flat ground) it asks more than needed,
which costs a few CG iterations (each contracts the error by 0.3-0.6), not accuracy.
Where the relief is 100 m, 3e-6 Z is 0.3 mm, 1.5 % of a 2 cm noise."""
LATTICE_EDF_STEP = 3e-2
"""The lattice's step rule for the Hutchinson probes of the edf (in the probes' own unit:
they are ±1 data, as large as Z is to the heights): an error of 3e-2 per fitted value moves
vᵀF by at most about 3e-2 √M (30 at 1M data), well below the estimate's own spread
√(2 tr H / probes) (181 at edf 65,500 and 4 probes; LATTICE_EDF_PROBES is 1). Measured at 1M nodes and data (4 probes solved
side by side; their estimate against the same probes solved to 1e-4, 8 iterations): 1e-2
took 4 iterations and was 5.8 off, 3e-2 took 2 and was 5.0 off, 0.3 took 1 and was 78 off.
At 360k nodes 1e-3 gave edf 23,702 and 1e-2 gave 23,699."""
FILE_NORMALS_WEIGHT = 1.0
"""gradient_weight the pipeline gives the gradients of normals read from the file
(HEIGHT_GRADIENTS_WEIGHT for gradients fitted to the heights). Held-out, synthetic
terrain with 2 cm height noise (python -m benchmarks.gradient_weight), RMS against the true
heights at weights 0 → 1: 0.0103 → 0.0090 m (20k points, 3 seeds) and 0.0121 → 0.0117
(5k, 1 seed) with normals tilted 3° RMS; 0.0103 → 0.0075 and 0.0121 → 0.0100 with exact
normals. Weight 1 was better than 0 in all four; 0.1 was worse in one, 10 worse with
tilted normals."""
HEIGHT_GRADIENTS_WEIGHT = 0.5
"""gradient_weight the pipeline gives the heights' own least-squares gradients
(c1mesh.stages.height_gradients: a LAZ's or a bare xyz's, whose normals are estimated).
They measure nothing new, but they pull the vertex gradients toward the local quadratic
slope of the data, which the spline's own energy does not: its energy-optimal gradients
are biased (the RSD basis has zero second derivatives at the vertices; docs/smoothing.md,
"Known properties"). Held-out RMS over the thin-plate RBF's, 5 seeds (python -m
benchmarks.smoothing_limits gradient-data all 0.3 0.5), heights only → 0.5: Autzen 1.024 →
1.009, 4_6_crop 1.016 → 1.012, synthetic 2 cm terrains 1.18 → 1.09-1.10. Weight 1
undersmoothed where the CV chooses strong smoothing (docs/smoothing.md)."""
_DEGENERACY = 1e-12
CHECK_BLOCK = 1 << 16
"""Edges or triangles per block of the input checks (_directions)."""


def gradient_data_weight(normal_source: str, gradient_source: str) -> float:
    """The gradient_weight a fit gives its vertex gradients as smoothing data, by where they
    come from (c1mesh.pipeline.driver's sources): HEIGHT_GRADIENTS_WEIGHT for gradients
    fitted to the heights (gradient_source "heights"), FILE_NORMALS_WEIGHT for normals read
    from the file, 0 for normals estimated by PCA (not measured as data)."""
    if gradient_source == "heights":
        return HEIGHT_GRADIENTS_WEIGHT
    return FILE_NORMALS_WEIGHT if normal_source == "file" else 0.0


@dataclass(frozen=True)
class SmoothingData:
    """The data a smoothing fit matches, in the caller's units.

    values (M,): the measured heights z. spacing: the mean spacing h of the data points,
    in the length units of the vertices (the strength's length unit, module doc). xy
    (M, 2): where the values were measured, in the vertices' coordinates; None: at the
    vertices themselves (then M = N, values[i] at vertex i). weights (M,) >= 0: each
    value's weight, any scale (None: all 1). own (M,) bool: the points a tile of a survey
    answers for (its cell's), the only ones SmoothFit.outside counts (None: all)."""

    values: np.ndarray
    spacing: float
    xy: np.ndarray | None = None
    weights: np.ndarray | None = None
    own: np.ndarray | None = None


@dataclass(frozen=True)
class GradientPrior:
    """Gradients the fit's vertex gradients are pulled toward: the μ term of the module doc.

    gradients (N, 2): one (∂z/∂x, ∂z/∂y) per vertex, in height units per length unit
    (from normals, or fitted to the heights); NaN rows: no datum at that vertex. weight
    >= 0: dimensionless, one vertex's gradient weighs like `weight` data points' values
    over one spacing (μ = weight · h² · Σw / M; docs/smoothing.md); 0: ignored."""

    gradients: np.ndarray
    weight: float


@dataclass(frozen=True)
class SearchWindows:
    """Where the search for s runs: the mesh's triangles with all three corners in squares
    of side `side` centred at `centres` ((x, y) pairs, the vertices' coordinates); no
    centres: the whole mesh.

    Why squares at fixed places of the survey: the strength is one number for the whole
    survey, and a fit in memory, in tiles or on Dask must find the same one. So the
    windows depend only on the survey's points (their count, their bounding box, the
    points nearest its anchors), which every path can find (`search_windows` in memory; a
    reduce of `nearest_to_anchors` over the tiles), never on a vertex numbering or on
    the tile a search runs in."""

    centres: tuple = ()
    side: float = 0.0

    @property
    def whole(self) -> bool:
        return not self.centres

    def rects(self, grow: float = 0.0) -> list:
        """The windows as closed rectangles (x0, y0, x1, y1), each grown by `grow`."""
        half = self.side / 2 + grow
        return [(x - half, y - half, x + half, y + half) for x, y in self.centres]

    def as_dict(self) -> dict:
        """The report's form: side and centres (frame units); no centres: the whole mesh."""
        return {"side": float(self.side), "centres": [[float(x), float(y)] for x, y in self.centres]}

    def holding(self, xy: np.ndarray) -> np.ndarray:
        """(n,) bool: the points xy (n, 2) in some window (all of them when whole)."""
        if self.whole:
            return np.ones(xy.shape[0], dtype=bool)
        inside = np.zeros(xy.shape[0], dtype=bool)
        for x0, y0, x1, y1 in self.rects():
            inside |= (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
        return inside


def window_anchors(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """(k, 2) the WINDOW_ANCHORS of the bounding box lower (2,) .. upper (2,)."""
    fractions = np.array(WINDOW_ANCHORS, dtype=float)
    return np.asarray(lower, float) + fractions * (np.asarray(upper, float) - np.asarray(lower, float))


def nearest_to_anchors(xy: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """A part's summary for the windows' centres: (k, 3) rows (squared distance, x, y) of
    the point of xy (n, 2) nearest each anchor (k, 2) (ties: the lower x, then y; rows of
    inf where xy is empty). `reduce_nearest` of the parts' summaries is the whole's."""
    rows = np.full((anchors.shape[0], 3), np.inf)
    if xy.shape[0]:
        for a, anchor in enumerate(anchors):
            d2 = (xy[:, 0] - anchor[0]) ** 2 + (xy[:, 1] - anchor[1]) ** 2
            tied = np.flatnonzero(d2 == d2.min())        # one pass; the tie rule sorts only the ties
            best = tied[np.lexsort((xy[tied, 1], xy[tied, 0]))[0]]
            rows[a] = d2[best], xy[best, 0], xy[best, 1]
    return rows


def reduce_nearest(summaries: list) -> np.ndarray:
    """(k, 3): per anchor the least (squared distance, x, y) of the parts' summaries
    (`nearest_to_anchors`), which is the whole's, in any order of the parts."""
    stacked = np.stack(summaries)                          # (parts, k, 3)
    out = np.empty(stacked.shape[1:])
    for a in range(stacked.shape[1]):
        rows = stacked[:, a]
        out[a] = rows[np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0]))[0]]
    return out


def window_side(lower: np.ndarray, upper: np.ndarray, count: int, budget: int) -> float:
    """The side of the search windows of a survey of `count` points in the bounding box
    lower (2,) .. upper (2,): the square that would hold budget / len(WINDOW_ANCHORS) of them
    if they filled the box evenly (`windows_of_parts`' budget). Where they fill it
    unevenly (holes, a ragged border) a window holds fewer; a pixel grid holds that many.
    Rounded to 2 significant digits: the in-memory and the tiled fit find the same box but
    for the last bits of the frames' local coordinates, and may count a few points apart
    (the in-memory height field merges near-duplicate positions, the tiled spill exact ones)."""
    per_window = budget // len(WINDOW_ANCHORS)
    extent = np.asarray(upper, float) - np.asarray(lower, float)
    return float(f"{math.sqrt(per_window * float(extent[0] * extent[1]) / count):.2g}")


def windows_at(nearest: np.ndarray, side: float) -> SearchWindows:
    """The SearchWindows of that side centred at the points `nearest` (k, 3) of
    reduce_nearest (rows of inf: no point, no window; the same centre twice: one window)."""
    centres = []
    for d2, x, y in nearest:
        if np.isfinite(d2) and (float(x), float(y)) not in centres:
            centres.append((float(x), float(y)))
    return SearchWindows(tuple(centres), side)


def search_windows(xy: np.ndarray, budget: int | None = None) -> SearchWindows:
    """The survey's SearchWindows from all its points xy (n, 2) (those of the height field,
    fitted or not): `windows_of_parts` with one part."""
    xy = np.asarray(xy, dtype=float)
    return windows_of_parts(lambda: iter((xy,)), xy.shape[0], budget)


def windows_of_parts(parts, count: int, budget: int | None = None) -> SearchWindows:
    """The SearchWindows of a survey of `count` points given in parts: parts() a fresh
    iterator of (m, 2) xy arrays (the in-memory fit's one, or a tiled survey's tiles).
    The whole mesh for at most `budget` points (None: SEARCH_VERTICES); else two reduces
    over the parts, the bounding box and then each part's `nearest_to_anchors`, give
    squares of `window_side` centred on the points nearest the box's anchors, holding about
    `budget` points together. Any split of the same points gives the same windows."""
    budget = SEARCH_VERTICES if budget is None else int(budget)
    if count <= budget:
        return SearchWindows()
    lower, upper = plane_bounds(parts())
    anchors = window_anchors(lower, upper)
    nearest = reduce_nearest([nearest_to_anchors(xy, anchors) for xy in parts()])
    return windows_at(nearest, window_side(lower, upper, count, budget))


def chart_search_vertices(count: int) -> int:
    """The search windows' budget of a perspective chart of `count` vertices:
    CHART_SEARCH_SHARE of them, at most CHART_SEARCH_MOST and at least SEARCH_VERTICES."""
    return max(SEARCH_VERTICES, min(int(CHART_SEARCH_SHARE * count), CHART_SEARCH_MOST))


@dataclass(frozen=True)
class SmoothingControl:
    """How a smoothing fit runs.

    strength: the dimensionless s > 0, or "auto" (chosen by spatial-block
    cross-validation). scheme: the shape-function tuple, a name or a ShapeTuple
    (engine.schemes; it must be polynomial). folds: cross-validation folds of "auto"
    (a whole number >= 2). seed: the folds' block assignment and the trace probes.
    threads: c1mesh.core.threads.limit of the solve (None: the process's setting).
    windows: where "auto" searches (SearchWindows: the survey's, which a survey fitted in
    tiles and the in-memory fit choose alike, `search_windows`); None: chosen from the
    fit's own vertices by the same rule. least_strength: the least s "auto" may choose
    (0: SEARCH_LIMITS' lower end); the lattice route's is lattice_mesh.least_strength,
    the least smoothing its cells can carry without ringing. edf: estimate the effective
    degrees of freedom (SmoothFit.edf, a reported diagnostic that nothing else reads);
    False skips it (edf None): on the lattice it is one more multigrid solve, 1.0 s of the
    DTM job's 11.6 s at 1M nodes, which the CLI spends only when it writes a report."""

    strength: "float | str" = "auto"
    scheme: "str | ShapeTuple" = DEFAULT_SCHEME
    folds: int = 5
    seed: int = 0
    threads: int | None = None
    windows: "SearchWindows | None" = None
    least_strength: float = 0.0
    edf: bool = True
    fold_net: bool = False
    """The triangles are a lattice's (stages.lattice_mesh): stiffen the cells where the fit
    folds a face and solve again at the same s (stages.folds); the lattice route sets it."""


@dataclass
class SmoothFit:
    """Result of `smooth_fit`, in the caller's units.

    values (N,), gradients (N, 2): vertex data of the fitted spline. strength: s used;
    lam: λ actually used (length² × weight units, module doc). cv_curve: (s, held-out RMS
    in height units) pairs in the order tried ([] when s was given). search_limit_reached:
    the lowest score lay at SEARCH_LIMITS, so s may be better still beyond it (None when s
    was given; False: s is an interior minimum of the curve). edf: effective degrees of freedom
    tr(H) (Hutchinson estimate; None when SmoothingControl.edf was False). residual_rms,
    residual_max: of z − F at the data points with weight > 0. solver: the linear solver's
    name. seconds: wall time per phase.
    outside: data points outside the triangulation (ignored). gradient_weight: the
    weight the gradient data had (0: none). own_residuals: with data at points marked own
    (SmoothingData.own), (count, sum of squares, largest) of those points' residuals, for
    a tile's TileSolve; else None.
    """

    values: np.ndarray
    gradients: np.ndarray
    strength: float
    lam: float
    cv_curve: list = field(default_factory=list)
    search_limit_reached: bool | None = None
    edf: float | None = None
    residual_rms: float = 0.0
    residual_max: float = 0.0
    solver: str = ""
    seconds: dict = field(default_factory=dict)
    outside: int = 0
    gradient_weight: float = 0.0
    own_residuals: tuple | None = None
    search_windows: dict | None = None
    """Where "auto" searched (SearchWindows.as_dict); None when s was given."""
    fold_rounds: int = 0
    """Solves the fold net added (SmoothingControl.fold_net; 0: no face folded)."""
    fold_cells: tuple = ()
    """The lattice cells (i, j) whose neighbourhood the fold net stiffened (stages.folds.
    CellStiffness), sorted; the report gives their number (stiffened_cells)."""

    def as_dict(self) -> dict:
        """JSON-ready summary for the fit report (no per-vertex arrays)."""
        out = asdict(self)
        del out["values"], out["gradients"], out["own_residuals"], out["fold_cells"]
        out["stiffened_cells"] = len(self.fold_cells)
        out["cv_curve"] = [[float(s), float(r)] for s, r in self.cv_curve]
        out["seconds"] = {k: round(float(v), 4) for k, v in self.seconds.items()}
        for key in ("strength", "lam", "residual_rms", "residual_max"):
            out[key] = float(out[key])
        out["edf"] = None if self.edf is None else float(self.edf)
        return out


def parse_strength(text: str) -> "float | str | None":
    """'off' → None, 'auto' → 'auto', a positive number → float; SmoothingError else."""
    word = str(text).strip().lower()
    if word == "off":
        return None
    if word == "auto":
        return "auto"
    try:
        value = float(word)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise SmoothingError(f"the smoothing strength must be 'auto', 'off' or a positive "
                             f"number, got {text!r}")
    return value


# ------------------------------------------------------------------------- the problem
@dataclass
class _Problem:
    """A smoothing problem in normalised units (lengths / h, heights / Z, weights / mean).

    data_tri/data_lam: each data point's triangle and barycentrics, None when the data
    are the vertices. grad (N, 2) with NaN rows where there is no gradient datum.
    """

    points: np.ndarray
    triangles: np.ndarray
    dirs: np.ndarray
    scheme: object
    z: np.ndarray
    w: np.ndarray
    data_xy: np.ndarray
    data_tri: np.ndarray | None
    data_lam: np.ndarray | None
    grad: np.ndarray | None
    shapes: TriangleShapes | None = None
    """The triangles are translates of a few (a lattice's): smoothing_system.TriangleShapes."""

    def system(self) -> System:
        """The System: the energy K as CSR (assemble_energy), the data rows, the gradient data."""
        K = assemble_energy(self.points, self.triangles, self.dirs, self.scheme, self.shapes)
        return System(K, self._rows(), self.z, *self._gradient_data())

    def lattice_system(self, nbr: np.ndarray) -> LatticeSystem:
        """The LatticeSystem (S in stencil form, no CSR) of a problem on a lattice whose
        vertices have the stencil neighbours nbr (N, 7): each triangle shape's energy block
        once (shapes None: one per triangle), the data rows, the gradient data."""
        if self.shapes is None:
            shape_of, reps = np.arange(self.triangles.shape[0], dtype=np.int64), slice(None)
        else:
            shape_of, reps = self.shapes.key, self.shapes.reps
        elements = energy_blocks_of(self.points, self.triangles[reps], self.dirs[reps], self.scheme)
        return LatticeSystem(self.triangles, shape_of, elements, nbr, self._rows(), self.z, *self._gradient_data())

    def _rows(self):
        """The data rows (smoothing_system.data_rows), None when the data are the vertices."""
        if self.data_tri is None:
            return None
        return data_rows(self.points, self.triangles, self.dirs, self.scheme, self.data_tri, self.data_lam,
                         self.shapes)

    def _gradient_data(self) -> tuple:
        """(mask (N,) 1.0 where a vertex has a gradient datum, values (N, 2), 0 elsewhere), or
        (None, None) without gradient data."""
        if self.grad is None:
            return None, None
        mask = np.isfinite(self.grad).all(axis=1).astype(float)
        return mask, np.where(mask[:, None] > 0, self.grad, 0.0)

    def renumbered(self, order: np.ndarray) -> "_Problem":
        """The same problem with vertex order[i] as vertex i (order (N,) a permutation);
        the triangles keep their order and their corners' order."""
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        at_vertices = self.data_tri is None
        z, w, xy = ((self.z[order], self.w[order], self.data_xy[order]) if at_vertices
                    else (self.z, self.w, self.data_xy))
        return _Problem(self.points[order], rank[self.triangles], self.dirs, self.scheme, z, w, xy,
                        self.data_tri, self.data_lam, None if self.grad is None else self.grad[order],
                        self.shapes)

    def subset(self, keep_vertex: np.ndarray) -> "_Problem":
        """The problem on the triangles with all three vertices kept (no re-triangulation)."""
        tri_keep = keep_vertex[self.triangles].all(axis=1)
        tris = self.triangles[tri_keep]
        used = np.zeros(self.points.shape[0], dtype=bool)
        used[tris.ravel()] = True
        new = np.cumsum(used) - 1
        if self.data_tri is None:
            data = np.flatnonzero(used)
            tri_map, lam = None, None
        else:
            tri_new = np.cumsum(tri_keep) - 1
            data = np.flatnonzero(tri_keep[self.data_tri])
            tri_map, lam = tri_new[self.data_tri[data]], self.data_lam[data]
        return _Problem(self.points[used], new[tris], self.dirs[tri_keep], self.scheme,
                        self.z[data], self.w[data], self.data_xy[data], tri_map, lam,
                        None if self.grad is None else self.grad[used],
                        None if self.shapes is None else self.shapes.subset(tri_keep))


def _check_inputs(points, triangles, data: SmoothingData):
    try:                       # no copies: smooth_fit never writes into its inputs (47 MB at 1M points)
        pts = np.asarray(points, dtype=float)
        z = np.asarray(data.values, dtype=float)
        tri = np.asarray(triangles)
    except (TypeError, ValueError):
        raise SmoothingError("points, triangles and values must be numeric arrays") from None
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 3:
        raise SmoothingError(f"points must have shape (N, 2) with N >= 3, got {pts.shape}")
    if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0 or not np.issubdtype(tri.dtype, np.integer):
        raise SmoothingError(f"triangles must be integer vertex indices of shape (T, 3), got {tri.shape}")
    if tri.min() < 0 or tri.max() >= pts.shape[0]:
        raise SmoothingError(f"triangle vertex indices must lie in [0, {pts.shape[0] - 1}]")
    xy = pts if data.xy is None else np.asarray(data.xy, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise SmoothingError(f"the data's xy must have shape (M, 2), got {xy.shape}")
    if z.shape != (xy.shape[0],):
        raise SmoothingError(f"values must have shape ({xy.shape[0]},) (one per data point), got {z.shape}")
    w = np.ones_like(z) if data.weights is None else np.asarray(data.weights, dtype=float)
    if w.shape != z.shape:
        raise SmoothingError(f"weights must have shape {z.shape}, got {w.shape}")
    if data.own is not None and np.shape(data.own) != z.shape:
        raise SmoothingError(f"the data's own mask must have shape {z.shape}, got {np.shape(data.own)}")
    if not (np.isfinite(pts).all() and np.isfinite(z).all() and np.isfinite(xy).all()):
        raise SmoothingError("points, the data's xy and values must be finite")
    if not (np.isfinite(w).all() and (w >= 0).all() and w.sum() > 0):
        raise SmoothingError("weights must be finite, non-negative and not all zero")
    try:
        spacing = float(data.spacing)
    except (TypeError, ValueError):
        spacing = float("nan")
    if not (np.isfinite(spacing) and spacing > 0):
        raise SmoothingError(f"the data's spacing must be a positive length, got {data.spacing!r}")
    return pts, np.ascontiguousarray(tri, dtype=np.int64), z, xy, w, spacing     # no copy of int64 triangles


def _directions(points, triangles, directions):
    table = edge_table(triangles, points.shape[0])
    u = None
    if directions is not None:
        u = np.array(directions, dtype=float)
        if u.shape != table.edges.shape or not np.isfinite(u).all():
            raise SmoothingError(f"directions must be a finite ({table.edges.shape[0]}, 2) "
                                 f"array, got shape {u.shape}")
        if not _all_blocks(kernel.directions_cross, points, table.edges, u):
            raise SmoothingError("a direction is zero or parallel to its edge; it must cross the edge")
    dirs = triangle_directions(points, triangles, table.tri_edge, u, table.edges)
    if not _nondegenerate(points, triangles):
        raise SmoothingError("the mesh has degenerate (zero-area) triangles")
    return dirs


def _nondegenerate(points: np.ndarray, triangles: np.ndarray) -> bool:
    """Whether every triangle's |sin| at its vertex 0 exceeds _DEGENERACY: |det| (twice
    the area, rsd.barycentric_gradients' formula) against the product of the two edge
    lengths there (kernel: _smoothing.nondegenerate)."""
    return _all_blocks(kernel.nondegenerate, points, triangles)


def _all_blocks(check, points: np.ndarray, rows: np.ndarray, *arrays: np.ndarray) -> bool:
    """Whether check(points (N, 2), rows (R, k) int64, *arrays, _DEGENERACY, first, stop)
    holds on every block of CHECK_BLOCK rows, the blocks in the thread knob's threads."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    arrays = tuple(np.ascontiguousarray(a, dtype=np.float64) for a in arrays)
    passed = np.zeros(-(-rows.shape[0] // CHECK_BLOCK), dtype=bool)

    def block(part: slice) -> None:
        passed[part.start // CHECK_BLOCK] = check(points, rows, *arrays, _DEGENERACY,
                                                  part.start, part.stop)
    parallel_blocks(block, rows.shape[0], CHECK_BLOCK)
    return bool(passed.all())


# ------------------------------------------------------------------------ the fit
def weighted_plane(xy: np.ndarray, z: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(a, b, c) of the weighted least-squares plane z ≈ a + b x + c y.

    smooth_fit fits the deviations from it: the energy of a plane is zero and the sextic
    reproduces planes, so the fit of plane + d is plane + the fit of d in exact arithmetic.
    In floating point a plane's energy is zero only to rounding times the largest energy
    block, which a thin triangle makes large; fitting d instead returns a plane exactly
    (to the rounding of the plane itself) and scales that error by the deviations only.
    """
    A = np.column_stack([np.ones_like(z), xy]) * np.sqrt(w)[:, None]
    if A.shape[0] < 3 or np.linalg.matrix_rank(A) < 3:
        return np.array([float(np.average(z, weights=w)), 0.0, 0.0])
    return np.linalg.lstsq(A, z * np.sqrt(w), rcond=None)[0]


def smooth_fit(points, triangles, data: SmoothingData, control: SmoothingControl = SmoothingControl(), *,
               directions=None, prior: GradientPrior | None = None,
               lattice: Lattice | None = None, search_only: bool = False) -> SmoothFit:
    """Fit vertex values and gradients of the RSD spline to data (module doc).

    points (N, 2) vertices, triangles (T, 3). data: the SmoothingData (values, where,
    their weights and spacing); control: the SmoothingControl (strength, scheme, folds,
    seed, threads). directions: (E, 2) edge directions in RSDInterpolator's edge order or
    None (unit normals). prior: a GradientPrior the vertex gradients are pulled toward, or
    None.

    lattice: where the vertices sit on a regular grid (stages.lattice_solver.Lattice, in
    the points' units; vertex k at lattice.positions()[k], checked), the triangles splitting
    its cells by the diagonal (i, j)-(i+1, j+1). The final solve is then
    lattice_solver's multigrid-preconditioned CG, stopped at LATTICE_STEP, instead of
    the direct factorisation, and the vertices are not renumbered for one (no METIS
    order). The strength search keeps its direct solves on small windows. edf is then
    Hutchinson's estimate with the probes solved by the same CG (LATTICE_EDF_STEP).
    The final system is assembled in the solver's stencil form (stages.lattice_system),
    never as CSR. solver: "lattice-pcg"; seconds: "lattice_setup" (the hierarchy) apart
    from "solve", the stencil's assembly in "assemble".

    search_only (with strength "auto"): return once the search has chosen s, with no values,
    gradients or edf (a survey's search tile: its fit at s is thrown away, and its ring of
    lattice nodes beyond the windows may hold pieces too poor in data to solve).
    """
    pts, tri, z, xy, w, h = _check_inputs(points, triangles, data)
    vertex_data = data.xy is None
    if vertex_data and z.shape[0] != pts.shape[0]:
        raise SmoothingError("without the data's xy the values are the vertices' (M must equal N)")
    strength, folds, seed, threads = control.strength, control.folds, control.seed, control.threads
    if not (strength == "auto" or (isinstance(strength, (int, float)) and np.isfinite(strength)
                                   and strength > 0)):
        raise SmoothingError(f"strength must be 'auto' or a positive number, got {strength!r}")
    if int(folds) != folds or folds < 2:
        raise SmoothingError(f"folds must be a whole number >= 2, got {folds!r}")
    if not (np.isfinite(control.least_strength) and control.least_strength >= 0):
        raise SmoothingError(f"the least strength must be >= 0, got {control.least_strength!r}")
    gradient_weight = 0.0 if prior is None else prior.weight
    if not (np.isfinite(gradient_weight) and gradient_weight >= 0):
        raise SmoothingError(f"the gradient prior's weight must be >= 0, got {gradient_weight!r}")
    shape = get_scheme(control.scheme)
    energy_tensor(shape)                 # SchemeNotPolynomialError before any work
    seconds: dict = {}
    with limit(threads), timed(seconds, "assemble"):
        centre = pts.mean(axis=0)
        plane = weighted_plane((xy - centre) / h, z, w)
        trend = plane[0] + ((xy - centre) / h) @ plane[1:]
        Z = float(np.sqrt(np.average((z - trend) ** 2, weights=w))) or 1.0
        w_mean = float(w.sum() / w.shape[0])
        npts = (pts - centre) / h
        grad = None
        if prior is not None and gradient_weight > 0:
            grad = np.array(prior.gradients, dtype=float)
            if grad.shape != pts.shape:
                raise SmoothingError(f"the gradient prior must have shape {pts.shape}, got {grad.shape}")
            grad = (grad - plane[1:] / h) * (h / Z)     # the deviations from the plane, as z
        grid = None if lattice is None else _lattice_of(lattice, pts, npts, centre, h)
        shapes = None if grid is None or directions is not None else lattice_shapes(grid, tri)
        dirs = _directions(npts, tri, directions) if shapes is None else shared_directions(npts, tri, shapes)
        nxy = (xy - centre) / h
        data_tri = data_lam = own_inside = None
        outside = 0
        if not vertex_data:
            if shapes is None:
                G, _ = rsd.barycentric_gradients(npts[tri])
                data_tri, data_lam = TriangleLocator(npts, tri, G).find(nxy)
            else:
                data_tri, data_lam = lattice_locate(grid, npts, tri, nxy)
            inside = data_tri >= 0
            outside = int((~inside).sum() if data.own is None else (~inside[data.own]).sum())
            own_inside = None if data.own is None else np.asarray(data.own, dtype=bool)[inside]
            data_tri, data_lam = data_tri[inside], data_lam[inside]
            nxy, z, w, trend = nxy[inside], z[inside], w[inside], trend[inside]
        zn, wn = (z - trend) / Z, w / w_mean
        if not (wn > 0).any():
            raise SmoothingError("no weighted data point lies inside the triangulation")
        problem = _Problem(npts, tri, dirs, shape, zn, wn, nxy, data_tri, data_lam, grad, shapes)
    method = available_solvers()[0]
    solved, order, system = _assembled(problem, method, seconds, threads, grid)
    solved_w = solved.w                          # the weights in the system's numbering (its z: system.z)
    solved_mesh = (solved.points, solved.triangles) if control.fold_net and grid is None else None
    del solved
    mu = float(gradient_weight)
    curve: list = []
    at_limit = windows = None
    ahead = grid is not None and not search_only       # the final system's data term, summed during the search
    with limit(threads), (system.data_term_ahead(solved_w, mu) if ahead else contextlib.nullcontext()) as data_term:
        if strength == "auto":
            with timed(seconds, "search"):
                windows = search_windows(pts) if control.windows is None else control.windows
                s, curve, at_limit = _search(problem, int(folds), mu, method, seed,
                                             None if windows.whole else windows.holding(pts),
                                             _lowest_exponent(control.least_strength))
        else:
            s = float(strength)
        chosen = dict(strength=s, lam=s * h * h * w_mean, search_limit_reached=at_limit, seconds=seconds,
                      cv_curve=[(tried, score * Z) for tried, score in curve],       # in height units
                      outside=outside, gradient_weight=mu if grad is not None else 0.0,
                      search_windows=None if windows is None else windows.as_dict())
        if search_only:
            return SmoothFit(values=np.empty(0), gradients=np.empty((0, 2)), solver=method, **chosen)
        # the search's: the final solve needs none of them (dirs: 93 MB at 2M triangles; the
        # data's located copies about 70 MB at 1M points; the system holds its own)
        net = None
        if control.fold_net:                          # the caller's triangles are a lattice's
            net = _FoldNet(pts, tri, shape, order, _Units(Z, h, plane, npts),
                           (*solved_mesh, dirs) if grid is None else None)
        del problem, dirs, nxy, z, w, trend, zn, wn, data_tri, data_lam
        if grid is None:
            with timed(seconds, "solve"):                 # the last matrix unless the net may add one
                u, factor = solve(system, s, solved_w, mu, method, keep_energy=net is not None)
        else:
            with timed(seconds, "assemble"):
                term = data_term()
                S, rhs = system.with_strength(s, term)
            with timed(seconds, "lattice_setup"):
                solver = LatticeSolver(S, replace(grid, nodes=grid.nodes[order]))
            del S                                      # the solver's fine level holds it
            with timed(seconds, "solve"):
                u = solver.pcg(rhs, LATTICE_STEP)[0]
        if net is not None:
            with timed(seconds, "folds"):
                while (extra := net.extra(u)) is not None:
                    if grid is None:
                        system.K.data += net.direct_energy(system.K, extra)
                        u, factor = solve(system, s, solved_w, mu, method, keep_energy=True)
                    else:
                        fine = solver.levels[0].op
                        system.stiffen(fine, s, term, extra)
                        solver = LatticeSolver(fine, replace(grid, nodes=grid.nodes[order]))
                        u = solver.pcg(rhs, LATTICE_STEP, x0=u)[0]
            chosen.update(fold_rounds=net.rounds, fold_cells=net.folded_cells)
        if grid is not None:
            factor = LatticeFactor(solver, LATTICE_EDF_STEP)
        edf = None
        if control.edf:
            with timed(seconds, "edf"):
                edf = hat_trace(system, factor, solved_w, EDF_PROBES if grid is None else LATTICE_EDF_PROBES, seed)
    residual = (system.z - system.fitted(u)) * Z     # in the system's numbering (data points: theirs)
    own_residuals = None
    if not vertex_data and own_inside is not None:
        mine = residual[own_inside & (solved_w > 0)]
        own_residuals = (int(mine.size), float(np.sum(mine ** 2)), float(np.abs(mine).max()) if mine.size else 0.0)
    residual = residual[solved_w > 0]
    if net is not None and net.checked is not None and net.checked[0] is u:
        values, gradients = net.checked[1]              # the net's last check: this solve's
    else:
        values, gradients = _Units(Z, h, plane, npts).vertex_data(u if order is None else _in_input_order(u, order))
    return SmoothFit(values=values, gradients=gradients, edf=edf,
                     residual_rms=float(np.sqrt(np.mean(residual**2))) if residual.size else 0.0,
                     residual_max=float(np.abs(residual).max()) if residual.size else 0.0,
                     solver=method if grid is None else "lattice-pcg", own_residuals=own_residuals, **chosen)


@dataclass(frozen=True)
class _Units:
    """smooth_fit's normalisation: Z the height unit, h the length unit, plane the data's
    weighted plane (a, b, c) in normalised x, y, npts (N, 2) the vertices normalised."""

    Z: float
    h: float
    plane: np.ndarray
    npts: np.ndarray

    def vertex_data(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values (N,), gradients (N, 2)) in the caller's units of unknowns u (3N,) in input order."""
        values = u[0::3] * self.Z + (self.plane[0] + self.npts @ self.plane[1:])
        gradients = np.stack([u[1::3], u[2::3]], 1) * (self.Z / self.h) + self.plane[1:] / self.h
        return values, gradients


class _FoldNet:
    """smooth_fit's fold net on a lattice (stages.folds): after each solve, the triangles
    folding a face at folds.FOLD_LEVEL; their cells stiffened (folds.CellStiffness), at
    most folds.ROUNDS times. pts (N, 2), tri (T, 3): the vertices in the caller's units and
    the triangles; scheme: the ShapeTuple; order: the system's vertex numbering (None: the
    input's); units: the _Units of the unknowns. direct: (points, triangles, dirs) of the
    problem in the system's numbering, for the energy of a direct solve's CSR (None: the
    multigrid's stencil). checked: (u, (values, gradients)) of the last solve checked, which
    smooth_fit returns when it is the final one."""

    def __init__(self, pts: np.ndarray, tri: np.ndarray, scheme, order, units: _Units, direct: tuple | None):
        self.pts, self.tri, self.scheme, self.order, self.units = pts, tri, scheme, order, units
        self.direct = direct
        self.cells: CellStiffness | None = None            # made at the first fold
        self.factors: np.ndarray | None = None
        self.rounds = 0
        self.checked: tuple | None = None

    @property
    def folded_cells(self) -> tuple:
        """The cells stiffened, sorted (SmoothFit.fold_cells)."""
        return () if self.cells is None else tuple(sorted(self.cells.levels))

    def extra(self, u: np.ndarray) -> np.ndarray | None:
        """(T,) each triangle's energy to add, in units of its own, for the next solve; None
        when the solve u (3N,) folds no face or the rounds are spent."""
        if self.rounds == FOLD_ROUNDS:
            return None
        values, gradients = self.units.vertex_data(u if self.order is None else _in_input_order(u, self.order))
        self.checked = (u, (values, gradients))
        folded = folded_triangles(self.pts, values, gradients, self.tri, self.scheme)
        if not folded.size:
            return None
        if self.cells is None:
            legs = np.linalg.norm(self.pts[self.tri[0]] - self.pts[self.tri[0, [1, 2, 0]]], axis=1)
            self.cells = CellStiffness(self.pts, self.tri, float(legs.min()))
            self.factors = np.ones(self.tri.shape[0])
        self.cells.fold(folded)
        factors = self.cells.multipliers()
        extra, self.factors = factors - self.factors, factors
        self.rounds += 1
        return extra

    def direct_energy(self, K, extra: np.ndarray) -> np.ndarray:
        """Σ_t extra[t] K_t (the triangles' energy blocks, assemble_energy) on the pattern of
        K (CSR, sorted indices), as values aligned with K.data."""
        points, triangles, dirs = self.direct
        n = K.shape[0]
        key = np.repeat(np.arange(n, dtype=np.int64), np.diff(K.indptr)) * n + K.indices
        out = np.zeros_like(K.data)
        for factor in np.unique(extra[extra > 0]):
            chosen = extra == factor
            part = assemble_energy(points, triangles[chosen], dirs[chosen], self.scheme, None).tocsr()
            part.sort_indices()
            where = np.searchsorted(key, np.repeat(np.arange(n, dtype=np.int64), np.diff(part.indptr)) * n
                                    + part.indices)
            np.add.at(out, where, factor * part.data)
        return out


def _lattice_of(lattice: Lattice, pts: np.ndarray, npts: np.ndarray, centre: np.ndarray, h: float) -> Lattice:
    """The lattice in the normalised units of npts = (pts − centre) / h, after checking that
    vertex k sits at its node (to 1e-6 of the smaller spacing); SmoothingError else."""
    if not isinstance(lattice, Lattice):
        raise SmoothingError(f"lattice must be a stages.lattice_solver.Lattice, got {type(lattice).__name__}")
    if lattice.nodes.shape != (pts.shape[0],):
        raise SmoothingError(f"the lattice's nodes must be ({pts.shape[0]},), one per vertex, "
                             f"got {lattice.nodes.shape}")
    grid = lattice.scaled(centre, h)
    off = float(np.abs(grid.positions() - npts).max()) if pts.shape[0] else 0.0
    if not off <= 1e-6 * min(grid.spacing):
        raise SmoothingError(f"the vertices are not the lattice's nodes (up to {off * h:g} away)")
    return grid


def lattice_shapes(grid: Lattice, triangles: np.ndarray) -> TriangleShapes:
    """The TriangleShapes of a lattice mesh's triangles (T, 3): two triangles have one shape
    when their corners, in their order, lie at the same node offsets from their first.
    A half cell's offsets are −1, 0 or 1, so a triangle's 4 of them are one base-3 key
    (SHAPE_KEYS of them) whose order is theirs: the shapes are numbered as np.unique of the
    keys would number them, from a count of each key and each present key's first
    triangle, without sorting the T keys (the sort took 0.4 s of the 0.6 s at 2M
    triangles); SmoothingError for a triangle whose corners are not one cell's."""
    j, i = np.divmod(grid.nodes, grid.shape[1])                       # (N,) each
    key = np.zeros(triangles.shape[0], dtype=np.int64)
    for along in (i, j):
        first = along[triangles[:, 0]]
        for corner in (1, 2):
            offset = along[triangles[:, corner]] - first              # (T,): −1, 0 or 1 in a cell
            if offset.size and np.abs(offset).max() > 1:
                raise SmoothingError("the triangles are not the lattice's cells split in two: a triangle's "
                                     "corners are not one cell's nodes")
            key *= 3
            key += offset + 1
    present = np.flatnonzero(np.bincount(key, minlength=SHAPE_KEYS))
    number = np.zeros(SHAPE_KEYS, dtype=np.int64)
    number[present] = np.arange(present.size)
    reps = np.array([np.argmax(key == k) for k in present], dtype=np.int64)
    return TriangleShapes(number[key], reps)


SHAPE_KEYS = 3 ** 4
"""The base-3 keys of a lattice triangle's 4 corner offsets (lattice_shapes)."""


def shared_directions(npts: np.ndarray, triangles: np.ndarray, shapes: TriangleShapes) -> np.ndarray:
    """(T, 3, 2) the unit normal directions of lattice triangles: each shape's, from its
    representative (the spline does not see a direction's sign, which the edge's numbering
    sets)."""
    reps = triangles[shapes.reps]
    used, local = np.unique(reps, return_inverse=True)
    shared = _directions(npts[used], local.reshape(-1, 3), None)          # (k, 3, 2)
    return shared[shapes.key]


LOCATE_BLOCK = 1 << 16
"""Points per block of lattice_locate's barycentrics (in the thread knob's threads)."""


def lattice_locate(grid: Lattice, npts: np.ndarray, triangles: np.ndarray,
                   xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(triangle (M,) of each point xy (M, 2), −1 outside; barycentrics (M, 3) in its
    corners' order, NaN outside) on a lattice mesh (grid in the units of npts and xy): the
    cell by arithmetic, then the half of it below or above its (i, j)-(i+1, j+1) diagonal
    (each triangle's cell and half by the kernel lattice_slots); the barycentrics by the
    kernel lattice_barycentrics in rsd.barycentric_gradients' arithmetic, point by point in
    fixed blocks in the thread knob's threads (the same bits at any count)."""
    ny, nx = grid.shape
    hx, hy = grid.spacing
    u = (xy[:, 0] - grid.origin[0]) / hx
    v = (xy[:, 1] - grid.origin[1]) / hy
    i = np.clip(np.floor(u), 0, nx - 2).astype(np.int64)
    j = np.clip(np.floor(v), 0, ny - 2).astype(np.int64)
    upper = (v - j) > (u - i)
    slot = 2 * (j * (nx - 1) + i) + upper
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    where = np.full(2 * max(nx - 1, 1) * max(ny - 1, 1), -1, dtype=np.int64)
    kernel.lattice_slots(np.ascontiguousarray(grid.nodes, dtype=np.int64), triangles, nx, where)
    box = (u >= 0) & (v >= 0) & (u <= nx - 1) & (v <= ny - 1)
    tri = np.where(box, where[slot], -1)
    lam = np.full((xy.shape[0], 3), np.nan)
    npts, xy = np.ascontiguousarray(npts, dtype=np.float64), np.ascontiguousarray(xy, dtype=np.float64)
    parallel_blocks(lambda part: kernel.lattice_barycentrics(npts, triangles, tri, xy, lam, part.start, part.stop),
                    xy.shape[0], LOCATE_BLOCK)
    return tri, lam


def _assembled(problem: _Problem, method: str, seconds: dict, threads, grid: Lattice | None = None):
    """(solved, order, system): the problem with its vertices renumbered by
    smoothing_system.vertex_order when CHOLMOD factors it and that gives an order (from
    METIS_FROM unknowns), else the problem itself and order None; and its System. With
    grid (the Lattice of the problem's vertices, normalised units) the vertices are
    renumbered by lattice_solver.colour_order instead (the lattice solver needs no
    fill-reducing order, and takes its vertices colour by colour), and the system is a
    LatticeSystem: S is assembled in the solver's stencil form once s is known, never as
    CSR. The search for s keeps the input's numbering and its own CSR systems: its
    windows are small, and their vertices are chosen by number."""
    order = None if grid is None else colour_order(grid)
    if method == "cholmod" and grid is None:
        with limit(threads), timed(seconds, "order"):
            order = vertex_order(problem.triangles, problem.points.shape[0])
        if order is None:                       # below METIS_FROM: no phase to report
            del seconds["order"]
    solved = problem if order is None else problem.renumbered(order)
    with limit(threads), timed(seconds, "assemble"):
        if grid is None:
            system = solved.system()
            system.vertices_ordered = order is not None          # a fill-reducing order
        else:
            ny, nx = grid.shape
            system = solved.lattice_system(stencil_neighbours(grid.nodes[order], nx, ny))
    return solved, order, system


def _in_input_order(u: np.ndarray, order: np.ndarray) -> np.ndarray:
    """The unknowns (3N,) of a problem renumbered by order, in the input's vertex order."""
    out = np.empty_like(u)
    out.reshape(-1, 3)[order] = u.reshape(-1, 3)
    return out


# ------------------------------------------------------------------- choosing s
def _search_problem(problem: _Problem, keep: np.ndarray | None) -> _Problem:
    """The problem on the triangles with every corner kept (keep (N,) bool: the vertices
    in the search windows), or the whole problem (keep None)."""
    return problem if keep is None else problem.subset(keep)


def fold_of(xy: np.ndarray, folds: int, block: float, seed: int) -> np.ndarray:
    """(M,) fold of each point: its block × block cell of the plane, cells dealt to folds
    at random (seeded) and evenly."""
    cell = np.floor((xy - xy.min(axis=0)) / block).astype(np.int64)
    _, key = np.unique(cell[:, 0] * (cell[:, 1].max() + 1) + cell[:, 1], return_inverse=True)
    n_blocks = int(key.max()) + 1
    deal = np.random.default_rng(seed).permutation(n_blocks) % folds
    return deal[key.ravel()]


def cv_score(problem: _Problem, system: System, s: float, fold: np.ndarray, folds: int,
             mu: float, method: str, cache: dict | None = None) -> float:
    """Held-out RMS of F − z over all folds (each weighted point held out once), scoring
    only the held-out points whose connected piece of the mesh keeps at least
    MIN_PIECE_DATA weighted points of its own (`scored`). cache keeps what does not change
    with s between calls: the symbolic factorisation (the pattern never changes), each
    fold's scored points and, for data off the vertices, its data term
    (System.normal_values)."""
    cache = {} if cache is None else cache
    sq, count = 0.0, 0
    for k in range(folds):
        out = (fold == k) & (problem.w > 0)
        if not out.any():
            continue
        w = np.where(out, 0.0, problem.w)
        scored = cache.get(("scored", k))
        if scored is None:
            scored = cache[("scored", k)] = out & _supported(problem, w, cache)
        normal = None
        if system.data is not None:
            normal = cache.get(("normal", k))
            if normal is None:
                normal = cache[("normal", k)] = system.normal_values(w)
        S, rhs = system.matrix(s * w.sum() / problem.w.sum(), w, mu,
                               held_out=out if system.data is None else None, ridge=CV_RIDGE, normal=normal)
        factor = Factor(S, method, cache.get("analysis"), system.vertices_ordered)
        cache["analysis"] = factor.analysis
        r = (system.fitted(factor.solve(rhs)) - problem.z)[scored]
        sq += float(r @ r)
        count += int(scored.sum())
    return float(np.sqrt(sq / max(count, 1)))


MIN_PIECE_DATA = 10
"""Weighted data points a connected piece of the mesh must keep in a fold for its held-out
points to be scored. A piece with fewer (a fragment a search window cut off, or a small
island, nearly all inside one held-out block) has no fit of its own: its heights are the
ridge's and the energy's null space (a plane through a few, often nearly collinear,
points), and their error, which jumps with s, measures no smoothing. On the mug frame's
5,000-point windows a 7-vertex fragment with 3 points left took one fold's RMS from 0.0048
to 0.21 as s went from 1.7e-4 to 1e-2 (the other folds: 0.004 throughout) and the search
chose s = 0.00017 (1,422 folded faces); with 10,000-point windows such points held the
whole curve at 0.0356, 9× the 0.0040 of the points it can predict."""


def _supported(problem: _Problem, w: np.ndarray, cache: dict) -> np.ndarray:
    """(M,) bool: the data points whose connected piece of the mesh holds at least
    MIN_PIECE_DATA points of weight w > 0."""
    piece = cache.get("piece")
    if piece is None:
        tri = problem.triangles
        vertex_piece = connected_sets(problem.points.shape[0], np.concatenate([tri[:, 0], tri[:, 1]]),
                                      np.concatenate([tri[:, 1], tri[:, 2]]))
        piece = cache["piece"] = vertex_piece if problem.data_tri is None else vertex_piece[tri[problem.data_tri, 0]]
    kept = np.bincount(piece[w > 0], minlength=int(piece.max(initial=-1)) + 1)
    return kept[piece] >= MIN_PIECE_DATA


def _lowest_exponent(least_strength: float) -> float:
    """log10 of the least s the search tries: SEARCH_LIMITS' lower end, or least_strength
    (SmoothingControl) when that is larger."""
    return max(SEARCH_LIMITS[0], math.log10(least_strength)) if least_strength > 0 else SEARCH_LIMITS[0]


def _search(problem: _Problem, folds: int, mu: float, method: str, seed: int, keep: np.ndarray | None,
            lowest: float = SEARCH_LIMITS[0]):
    """(s, curve, limit reached): log-grid (`_coarse`, from log10 s = lowest up) then
    golden-section search of the spatial-block CV score. The limit is reached when s is
    the lowest or highest s tried, not an interior minimum of the curve, which happens
    only at `lowest` or at SEARCH_LIMITS' upper end."""
    sub = _search_problem(problem, keep)
    if not (sub.w > 0).any():              # no fitted triangle in the windows: search on the whole
        sub = problem
    system = sub.system()
    extent = np.ptp(sub.data_xy, axis=0)
    block = min(CV_BLOCK, max(float(np.sqrt(extent[0] * extent[1] / (4 * folds))), 1.0))
    fold = fold_of(sub.data_xy, folds, block, seed)
    curve: list = []
    scores: dict = {}
    cache: dict = {}

    def score(log_s: float) -> float:
        if log_s not in scores:
            scores[log_s] = cv_score(sub, system, 10.0**log_s, fold, folds, mu, method, cache)
            curve.append((10.0**log_s, scores[log_s]))
        return scores[log_s]

    grid, best = _coarse(score, lowest)
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    ratio = (np.sqrt(5) - 1) / 2
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    for _ in range(REFINE_STEPS):
        if score(a) < score(b):
            hi, b = b, a
            a = hi - ratio * (hi - lo)
        else:
            lo, a = a, b
            b = lo + ratio * (hi - lo)
    log_best = min(scores, key=scores.get)
    return 10.0**log_best, curve, log_best in (grid[0], grid[-1])


def _coarse(score, lowest: float = SEARCH_LIMITS[0]) -> tuple[list, int]:
    """(log10 s tried, ascending; index of the lowest score) of the coarse search: GRID
    (its steps below `lowest` replaced by `lowest` itself), stopped two steps past the
    lowest score (the curve is unimodal), then, while the lowest score is at an end, one
    more step past that end, down to `lowest` (log10 s, at least SEARCH_LIMITS[0]) and up
    to SEARCH_LIMITS[1]. So the lowest is an interior point of the curve, with a higher
    score on each side, unless it lies at a limit."""
    grid, values = [], []
    for e in sorted({max(e, lowest) for e in GRID}):
        grid.append(e)
        values.append(score(e))
        if len(values) - 1 - int(np.argmin(values)) >= 2:
            break
    step = GRID[1] - GRID[0]
    best = int(np.argmin(values))
    while best == 0 and grid[0] > lowest:
        grid.insert(0, max(grid[0] - step, lowest))
        values.insert(0, score(grid[0]))
        best = int(np.argmin(values))
    while best == len(grid) - 1 and grid[-1] + step <= SEARCH_LIMITS[1]:
        grid.append(grid[-1] + step)
        values.append(score(grid[-1]))
        best = int(np.argmin(values))
    return grid, best


# -------------------------------------------------------------------- the stage on a tile
HALO_LENGTHS = 28.0
"""A tile's smoothing halo, in smoothing lengths s^(1/4) h beyond its cell (module doc).
On a 12,000-point terrain with 2 cm noise in 9 tiles, the largest height difference from
the one-tile fit, relative to the residual RMS, was 1.6e-2 at 20 lengths and 5.7e-3 at 24
for s = 10, 7.3e-4 at 24 for s = 100, and below 1.4e-4 at 32 for both (docs/smoothing.md,
"In tiles")."""
LATTICE_HALO_LENGTHS = 112.0
LATTICE_HALO_SPACINGS = 96.0
"""The halo with the vertices on a lattice (--spacing, stages.lattice_mesh): the larger of
LATTICE_HALO_LENGTHS smoothing lengths and LATTICE_HALO_SPACINGS point spacings h. Its
nodes carry no data, and where the data are sparse a node's value reaches further than
HALO_LENGTHS, the more so the smaller s. autzen_trim ground in 4 tiles, the largest height
difference from the in-memory fit (residual RMS in brackets):
- --spacing 3 --smooth 0.01 (0.034 ft): 0.64 ft at 28 lengths (17 ft), 0.012 at 56, 4.2e-4
  at 84, 1.4e-5 at 112 (69 ft = 35 h) and 1.2e-5 at 140 (the in-memory multigrid's own
  tolerance: 1.3e-5 from CHOLMOD);
- --spacing 2 --smooth auto, s = 0.0022 (0.0136 ft): 6.7e-3 ft at 112 lengths (47 ft =
  24 h), 4.5e-5 at 52 h, 5.5e-6 at 64 h (125 ft), 3.0e-7 at 104 h.
With the solve's cells grown to whole blocks (lattice_mesh.KEPT_BLOCK: data-free margins
of up to 7 more cells), --spacing 2 --smooth 0.01 (0.034 ft): 7.9e-4 ft at 64 h, 1.0e-5
at 96 h (187 ft), 8.1e-7 at 128 h."""




def smoothing_reach(strength: float, spacing: float, lengths: float | None = None) -> float:
    """How far beyond its cell a tile's smoothing run reads (frame units): `lengths`
    smoothing lengths s^(1/4) h (None: HALO_LENGTHS, read when called), for strength s
    and spacing h. The scheduler gives a tile no less than the limiter's halo besides:
    near holes and borders, where the edges are long, the gradients reach further."""
    lengths = HALO_LENGTHS if lengths is None else lengths
    return lengths * float(strength) ** 0.25 * spacing


@dataclass(frozen=True)
class SmoothingRun:
    """What every tile's smoothing run shares, the same across the survey: control (its
    strength: s > 0, or "auto" to search on the tile run, `smooth_tile`; its scheme),
    spacing h (frame units, the strength's length unit: the survey's), overshoot ("off":
    unit normals; else the edge directions of limiter.edge_directions, chosen from the
    tile's geometry before the fit, which is then the spline of those directions; the
    fit's gradients agree with its heights by construction, so no other overshoot remedy
    applies), gradient_weight (of the tile's vertex gradients as data:
    gradient_data_weight; 0: none)."""

    control: SmoothingControl
    spacing: float
    overshoot: str = "limit"
    gradient_weight: float = 0.0


@dataclass
class TileSolve:
    """What one tile's solve reports: its own vertices, the sum of squares and the largest
    of their residuals (height units), its vertex count with its halo and their effective
    degrees of freedom (Hutchinson), its own edges (lower end own) whose direction is not
    the unit normal, and its own data points outside the triangles (with lattice
    vertices: SmoothingData.own; else 0)."""

    own: int
    squares: float
    largest: float
    halo_vertices: int
    edf: float | None
    turned: int
    outside: int = 0
    residuals: int | None = None
    """How many residuals squares and largest are over: the own data points inside the
    triangles with --spacing (the vertices are lattice nodes), else None (the own vertices)."""
    fold_rounds: int = 0
    fold_cells: tuple = ()
    """The fold net's rounds and stiffened cells in the tile's halo (SmoothFit's)."""

    @property
    def residual_count(self) -> int:
        return self.own if self.residuals is None else self.residuals


@dataclass
class SmoothedTile:
    """`smooth_tile`'s result: values (o,), gradients (o, 2), the fitted heights and
    gradients of the tile's own vertices (tile.own, in its records' order); directions
    (E, 2) of its own triangles' edges (smooth_tile says in which order), None with
    overshoot "off"; solve, the TileSolve; fit, the SmoothFit of every vertex the tile
    read (None: the tile has no triangles)."""

    values: np.ndarray
    gradients: np.ndarray
    directions: np.ndarray | None
    solve: TileSolve
    fit: SmoothFit | None


@dataclass(frozen=True)
class StrengthSearch:
    """What the search for s found on the tile it ran on (`search_strength`): strength, and
    SmoothFit's cv_curve, search_limit_reached, solver and seconds."""

    strength: float
    cv_curve: list
    search_limit_reached: bool | None
    solver: str
    seconds: dict
    windows: dict | None = None


def smooth_tile(tile: Tile, run: SmoothingRun, owned: np.ndarray | None = None, table=None,
                data: SmoothingData | None = None, lattice: Lattice | None = None) -> SmoothedTile:
    """The smoothing stage's run on one tile: smooth_fit of its vertices and final
    triangles with run's strength, spacing and scheme, its vertex gradients as data with
    run.gradient_weight, and the edge directions run.overshoot asks for.

    owned (k, 3): the survey numbers of the tile's own triangles, whose edges' directions
    it returns, in the order of topology.edge_table of those triangles numbered by
    ascending corner (as survey.refine_runs numbers them); None: the tile owns all of
    its triangles and every record is a corner of one (the in-memory fit's one tile,
    after pipeline.steps.compact_vertices), the directions then in the order of
    edge_table(tile.triangles), which is that order. A tile without triangles fits
    nothing: its own vertices, which no triangle uses, keep their data. table:
    edge_table(tile.triangles) when built already (the trim's, in memory; not with owned);
    None: built here when run.overshoot asks for edge directions (nothing else needs it).

    With strength "auto" the run searches s on the tile (`search_strength`) and solves at
    the s it found, in one smooth_fit: the in-memory fit's one tile is both the tile the
    search runs on and the only tile run.

    data: None, the tile's heights at its vertices with run.spacing. With --spacing
    (stages.lattice_mesh: the vertices on a lattice) every point's height at its position: the
    whole survey's in memory, a tile's those of the heights in its halo
    (survey.smoothing_runs); points outside the triangles are then ignored and counted in
    SmoothFit.outside, and the tile's heights serve only its TileSolve's residuals.
    lattice: where the tile's vertices are lattice nodes (--spacing, stages.lattice_mesh),
    their Lattice, for smooth_fit's multigrid solve; None: any mesh."""
    if not len(tile.triangles):              # nothing to fit: no triangle uses its vertices
        return SmoothedTile(tile.values[tile.own], tile.gradients[tile.own],
                            None if run.overshoot == "off" else np.empty((0, 2)),
                            TileSolve(0, 0.0, 0.0, 0, None, 0), None)
    other = None
    if table is not None and owned is not None:
        raise ValueError("smooth_tile numbers the edges itself when given the own triangles")
    if table is None and run.overshoot != "off":     # only the edge directions need the edges
        table, other = edge_table_sides(tile.triangles, len(tile.records))[:2]      # not its neighbours: memory
    fit, directions, changed = _fit_tile(tile, run, table, data, lattice)
    own = tile.own
    every = bool(own.all())
    values, gradients = (fit.values, fit.gradients) if every else (fit.values[own], fit.gradients[own])
    turned = 0
    if directions is not None:
        if owned is not None:
            directions = directions[own_triangles_in(tile, table, other, owned)[2]]
        turned = int(changed[own[table.edges[:, 0]]].sum())
    if fit.own_residuals is None:
        residual = tile.records["z"][own] - values
        count, squares = None, float(np.sum(residual ** 2))
        largest = float(np.abs(residual).max()) if residual.size else 0.0
    else:                                   # the data's own points: the nodes have no heights
        count, squares, largest = fit.own_residuals
    solve = TileSolve(own=int(own.sum()), squares=squares, largest=largest, halo_vertices=len(tile.records),
                      edf=fit.edf, turned=turned, outside=fit.outside, residuals=count,
                      fold_rounds=fit.fold_rounds, fold_cells=fit.fold_cells)
    return SmoothedTile(values, gradients, directions, solve, fit)


def search_strength(tile: Tile, run: SmoothingRun, data: SmoothingData | None = None) -> StrengthSearch:
    """The survey's strength s for strength "auto": smooth_fit's block cross-validation on
    the tile of the survey's search windows (run.control.windows; survey.smoothing_runs
    reads the vertices in them and the final triangles among those), then used by every
    tile. The in-memory fit's one tile runs it inside `smooth_tile`, on the same windows.
    data: as smooth_tile's (None: the tile's heights at its vertices)."""
    auto = replace(run, control=replace(run.control, strength="auto"))
    fit = _fit_tile(tile, auto, edge_table(tile.triangles, len(tile.records)), data, search_only=True)[0]
    return StrengthSearch(fit.strength, fit.cv_curve, fit.search_limit_reached, fit.solver, fit.seconds,
                          fit.search_windows)


def _fit_tile(tile: Tile, run: SmoothingRun, table, data: SmoothingData | None, lattice: Lattice | None = None,
              search_only: bool = False):
    """(SmoothFit of every vertex of tile, directions (E, 2) in table's order or None,
    changed (E,) bool or None): smooth_tile's fit."""
    points = tile.points
    directions, changed = (None, None) if run.overshoot == "off" else edge_directions(points, tile.triangles, table)
    prior = GradientPrior(tile.gradients, run.gradient_weight) if run.gradient_weight else None
    data = SmoothingData(tile.values, run.spacing) if data is None else data
    fit = smooth_fit(points, tile.triangles, data, run.control, directions=directions, prior=prior, lattice=lattice,
                     search_only=search_only)
    return fit, directions, changed


def solve_totals(solves: list[TileSolve]) -> tuple[int, float, float | None]:
    """(own vertices, sum of their squared residuals, edf) over the tiles' solves, the same
    in any order of the list: the float sums are math.fsum's, exactly rounded. edf sums each
    halo's estimate scaled by its share of own vertices (None: no solve had one)."""
    edfs = [s.edf * s.own / s.halo_vertices for s in solves if s.edf is not None and s.halo_vertices]
    return (sum(s.residual_count for s in solves), math.fsum(s.squares for s in solves),
            math.fsum(edfs) if edfs else None)


def combined_fit(solves: list[TileSolve], run: SmoothingRun, search: StrengthSearch | None,
                 seconds: dict) -> SmoothFit:
    """The survey's SmoothFit, the reduce of its tiles' solves (in any order: solve_totals),
    for its report (SmoothFit.as_dict); values and gradients are empty, each tile keeps
    its own. run: with the strength every tile used; search: what found it (None: given);
    seconds: the wall time of each phase. Its residuals are over every own vertex; the
    one-tile SmoothFit's come from the normalised solve and may differ in a last bit."""
    own, squares, edf = solve_totals(solves)
    strength = float(run.control.strength)
    return SmoothFit(values=np.empty(0), gradients=np.empty((0, 2)), strength=strength,
                     lam=strength * run.spacing ** 2, cv_curve=[] if search is None else list(search.cv_curve),
                     search_limit_reached=None if search is None else search.search_limit_reached, edf=edf,
                     residual_rms=math.sqrt(squares / own) if own else 0.0,
                     residual_max=max((s.largest for s in solves), default=0.0),
                     solver=available_solvers()[0] if search is None else search.solver, seconds=seconds,
                     outside=sum(s.outside for s in solves), gradient_weight=float(run.gradient_weight),
                     search_windows=None if search is None else search.windows,
                     fold_rounds=max((s.fold_rounds for s in solves), default=0),
                     fold_cells=tuple(sorted(set().union(*(s.fold_cells for s in solves)))))


__all__ = ["SmoothingError", "SchemeNotPolynomialError", "SmoothingData", "SmoothingControl",
           "GradientPrior", "SmoothFit", "smooth_fit", "SmoothingRun", "SmoothedTile", "TileSolve",
           "StrengthSearch", "smooth_tile", "search_strength", "smoothing_reach", "solve_totals",
           "combined_fit", "lattice_shapes", "shared_directions", "HALO_LENGTHS", "LATTICE_HALO_LENGTHS", "LATTICE_HALO_SPACINGS",
           "energy_blocks", "parse_strength", "fold_of", "cv_score", "CV_BLOCK",
           "SEARCH_VERTICES", "SEARCH_LIMITS", "SearchWindows", "search_windows", "window_anchors", "chart_search_vertices",
           "nearest_to_anchors", "reduce_nearest", "window_side", "windows_at", "windows_of_parts"]
