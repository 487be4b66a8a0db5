"""The cells of a north-up raster grid and the fitted spline sampled at their centres.

RasterGrid is the grid, aligned to multiples of the resolution R in world coordinates (x
to the east, y to the north), so grids of different tiles at one R line up cell for cell.
SplineSampler gives the spline's value and analytic gradient at the centre of each cell
inside the trimmed triangulation, and at a cell outside it that holds input points, the
spline of the nearest kept triangle within a reach (NearestTriangles), continued linearly
from that triangle's point closest to the centre. c1mesh.geo.raster turns these samples
into the DEM, slope, aspect and hillshade GeoTIFFs; c1mesh.geo.preview into a PNG.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.core.lazy import LazyModule
from c1mesh.core.threads import background
from c1mesh.core.tile import finite_rows
from c1mesh.engine import rsd
from c1mesh.engine.properties import scheme_properties

spatial = LazyModule("scipy.spatial")


# ---------------------------------------------------------------------------------- grid
@dataclass(frozen=True)
class RasterGrid:
    """A north-up grid: column j, row i has its centre at (west + (j + ½)R, north − (i + ½)R).

    west and north are multiples of the resolution R (world units), so grids of different
    tiles at the same R line up cell for cell. A window of a grid (`window`) keeps the
    grid's west and north and counts its cells from row0, col0: its cell (i, j) is the
    grid's cell (row0 + i, col0 + j), sampled by the same arithmetic, so a window's cells
    are bit for bit the grid's (per-tile DEMs of one survey).
    """

    west: float
    north: float
    resolution: float
    width: int
    height: int
    row0: int = 0
    col0: int = 0

    def window(self, rows: range, cols: range) -> "RasterGrid":
        """The window of this grid's cells rows × cols (indices of this grid)."""
        return RasterGrid(self.west, self.north, self.resolution, len(cols), len(rows),
                          self.row0 + rows.start, self.col0 + cols.start)

    def window_over(self, lo, hi) -> "RasterGrid | None":
        """The window of this grid's cells that meet the box lo..hi (world x, y): the
        cells holding its corners and those between, clipped to the grid (None: no cell)."""
        r = self.resolution
        cols = range(max(int(np.floor((lo[0] - self.west) / r)), 0),
                     min(int(np.floor((hi[0] - self.west) / r)) + 1, self.width))
        rows = range(max(int(np.floor((self.north - hi[1]) / r)), 0),
                     min(int(np.floor((self.north - lo[1]) / r)) + 1, self.height))
        return self.window(rows, cols) if len(rows) and len(cols) else None

    @classmethod
    def covering(cls, lo, hi, resolution: float) -> "RasterGrid":
        """The aligned grid that covers the box lo..hi (world x, y)."""
        r = float(resolution)
        if not (r > 0 and math.isfinite(r)):
            raise InputError(f"--resolution must be a positive length, got {resolution!r}")
        west, east = math.floor(lo[0] / r) * r, math.ceil(hi[0] / r) * r
        south, north = math.floor(lo[1] / r) * r, math.ceil(hi[1] / r) * r
        width, height = max(1, round((east - west) / r)), max(1, round((north - south) / r))
        if width * height > 4e9:
            raise InputError(f"a {width} x {height} grid at resolution {r:g} is too large; "
                             "use a coarser --resolution")
        return cls(west, north, r, int(width), int(height))

    @property
    def transform(self):
        """The rasterio/GDAL affine transform of the grid."""
        from affine import Affine
        return Affine(self.resolution, 0.0, self.west + self.col0 * self.resolution, 0.0, -self.resolution,
                      self.north - self.row0 * self.resolution)


# ----------------------------------------------------------------------------------- fill
@dataclass(frozen=True)
class FillRule:
    """Which cells of a DEM that spans the trim's holes hold the spline.

    trimmed (T,) bool over the interpolator's triangles: those the trim kept (a cell whose
    centre lies in one always holds the spline); the others span the holes the trim opened
    (pipeline.driver.filled_mesh), and a cell whose centre lies in one holds the spline
    when the centre is within `distance` (local units, inf: any) of the nearest point the
    fit used (SplineSampler's fit points)."""

    trimmed: np.ndarray
    distance: float = math.inf


# ------------------------------------------------------------------------------- sampling
def polynomial_form(scheme) -> tuple[np.ndarray, np.ndarray, float]:
    """(K (21, P), exponents (P, 2), max error) of the spline on one triangle as a
    polynomial in (λ0, λ1): coefficients C (T, 21) @ K are the monomial coefficients of
    λ0^i λ1^j, (i, j) = exponents, i + j ≤ d, the scheme's degree.

    Built by interpolating the basis on the degree-d lattice (unisolvent for degree d);
    the returned error is the largest difference from rsd.basis at random barycentrics,
    so a scheme that is not a polynomial of its stated degree is caught, not trusted.
    """
    degree = scheme.degree
    if degree is None:
        degree = scheme_properties(scheme).degree
    exponents = np.array([(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)])
    lattice = exponents / degree
    lam = np.column_stack([lattice, 1.0 - lattice.sum(axis=1)])
    vandermonde = lattice[:, :1] ** exponents[:, 0] * lattice[:, 1:] ** exponents[:, 1]
    K = np.linalg.solve(vandermonde, rsd.basis(scheme, lam).T).T          # (21, P)
    probe = np.random.default_rng(0).dirichlet((1, 1, 1), 200)
    mono = probe[:, :1] ** exponents[:, 0] * probe[:, 1:2] ** exponents[:, 1]
    error = float(np.abs(mono @ K.T - rsd.basis(scheme, probe).T).max())
    return K, exponents, error


class NodeCells:
    """The cells of a DEM grid whose centres are the spline's vertices: a fit on a lattice of
    the DEM's resolution with its nodes at the cell centres (stages.lattice_mesh), whose
    heights and gradients there are its vertex data, read off instead of evaluated (the
    same numbers: the RSD spline interpolates its vertex data). Made only when every vertex
    sits at a centre (to 1e-6 cells) and every triangle's corners are in neighbouring cells,
    so that no other centre lies in a triangle (`of`); the cells holding data points but no
    vertex (`bare`) are SplineSampler's nearest-triangle cells.

    grid: the whole grid (its windows share west, north and resolution); row, col (n,) the
    cell of each vertex that holds one, vertex (n,) those vertices (None: every vertex);
    by_row: their order by (row, col); bare_cells: the grid's flat cell numbers (row ×
    width + col) holding data points and no vertex's cell, ascending."""

    def __init__(self, grid: "RasterGrid", row: np.ndarray, col: np.ndarray, bare_cells: np.ndarray,
                 origin: np.ndarray, vertex: np.ndarray | None = None):
        self.grid, self.row, self.col, self.bare_cells, self.origin = grid, row, col, bare_cells, origin
        self.vertex = np.arange(row.size) if vertex is None else vertex
        self.by_row = np.argsort(row, kind="stable")
        self.sorted_rows = row[self.by_row]

    @classmethod
    def of(cls, interp, origin: np.ndarray, grid: "RasterGrid", data_xy, fill: "FillRule | None" = None,
           distances=None) -> "NodeCells | None":
        """The NodeCells of interp's vertices (local plane, origin (3,)) on grid, or None when
        they are not the grid's centres (module rule above). With a fill of finite distance
        D, a vertex of the holes' triangles only (on no triangle the trim kept) farther than
        D from the fit's points (distances: SplineSampler.distances) holds no cell, as the
        evaluated fill drops its centre (SplineSampler.cells)."""
        if grid.row0 or grid.col0:
            return None
        cells = vertex_cells(interp, origin, grid)
        if cells is None:
            return None
        ri, ci = cells
        if ri.min() < 0 or ci.min() < 0 or ri.max() >= grid.height or ci.max() >= grid.width:
            return None
        vertex = np.arange(ri.size)
        if fill is not None and math.isfinite(fill.distance):
            kept = np.zeros(ri.size, dtype=bool)
            kept[interp.triangles[fill.trimmed].ravel()] = True
            spans = np.flatnonzero(~kept)
            kept[spans] = distances(interp.points[spans, :2]) <= fill.distance
            vertex = np.flatnonzero(kept)
        ri, ci = ri[vertex], ci[vertex]
        r = grid.resolution
        held = np.zeros(grid.height * grid.width, dtype=bool)
        if data_xy is not None:
            xy = _finite_xy(data_xy)
            ii, jj = _cells_of(xy[:, 0], xy[:, 1], grid.west - origin[0], grid.north - origin[1], r)
            inside = (ii >= 0) & (ii < grid.height) & (jj >= 0) & (jj < grid.width)
            held[ii[inside] * grid.width + jj[inside]] = True
        held[ri * grid.width + ci] = False
        return cls(grid, ri, ci, np.flatnonzero(held), np.asarray(origin, dtype=np.float64), vertex)

    def serves(self, grid: "RasterGrid") -> bool:
        """Whether grid is this grid or one of its windows."""
        base = self.grid
        return (grid.west, grid.north, grid.resolution) == (base.west, base.north, base.resolution)

    def window(self, rows: range, cols: range) -> tuple[np.ndarray, np.ndarray]:
        """(vertex (k,), cell (k,)): the vertices whose cells lie in rows × cols (whole-grid
        indices) and their flat cell numbers in that window."""
        lo, hi = np.searchsorted(self.sorted_rows, [rows.start, rows.stop])
        held = self.by_row[lo:hi]
        col = self.col[held]
        held = held[(col >= cols.start) & (col < cols.stop)]
        return self.vertex[held], (self.row[held] - rows.start) * len(cols) + (self.col[held] - cols.start)

    def bare(self, rows: range, cols: range) -> tuple[np.ndarray, np.ndarray]:
        """(cell (k,), centre (k, 2)): the cells of rows × cols holding data and no vertex, as
        flat numbers in that window, and their centres in local plane units (the arithmetic
        of SplineSampler._uncovered)."""
        width, r = self.grid.width, self.grid.resolution
        lo, hi = np.searchsorted(self.bare_cells, [rows.start * width, rows.stop * width])
        i, j = np.divmod(self.bare_cells[lo:hi], width)
        keep = (j >= cols.start) & (j < cols.stop)
        i, j = i[keep], j[keep]
        centre = _cell_centres(self.grid.west - self.origin[0], self.grid.north - self.origin[1], r, i, j)
        return (i - rows.start) * len(cols) + (j - cols.start), centre


class SplineSampler:
    """Values and analytic gradients of a fitted spline at the cell centres of a grid.

    interp: the RSDInterpolator in the scan frame; origin: (3,) the frame's origin. The
    frame's axes must be the world axes (--axis z), so that local = world − origin and
    the local gradient is the world gradient dz/dx, dz/dy.

    Cells are found triangle by triangle (scan conversion: the cell centres inside each
    triangle's bounding box, kept when their barycentric coordinates are ≥ −1e-10, the
    tolerance of c1mesh.engine.locate), and the spline is evaluated as its per-triangle
    polynomial in (λ0, λ1) (polynomial_form): values and gradients are then sums of
    monomials instead of 21 shape functions per point, the same numbers to ~1e-12.

    Cells whose centre lies in no triangle but which hold a point of data_xy (m, 2) (local
    plane coordinates, the fitted points) get the nearest triangle within `reach` (local
    units; None: any distance; NearestTriangles), evaluated at its point closest to the
    centre and continued linearly from there (`evaluate`); with a fill, the nearest of
    the triangles the trim kept.

    fill: a FillRule (None: every triangle's cells hold the spline). fit_xy (k, 2): the
    points the fit used, local plane coordinates (None: the interpolator's vertices), from
    which `distances` measures each centre's distance (the support layer, the fill rule).
    """

    TOLERANCE = 1e-10

    def __init__(self, interp, origin, data_xy=None, reach: float | None = None,
                 fill: FillRule | None = None, fit_xy=None, grid: "RasterGrid | None" = None):
        self.interp = interp
        self.origin = np.asarray(origin, dtype=np.float64)
        self.fill = fill
        self._fit_xy = interp.points[:, :2] if fit_xy is None else np.asarray(fit_xy, dtype=np.float64)
        self._tree = None                                  # cKDTree of _fit_xy, built when first needed
        self._reach, self._nearest = reach, None          # NearestTriangles, built when first needed,
        self._rim = np.zeros(0, dtype=np.int64)          # over these triangles (rim_triangles)
        self._ready = False
        self._nodes = None if grid is None else NodeCells.of(interp, self.origin, grid, data_xy, fill,
                                                              self.distances)
        if self._nodes is not None:         # the grid's centres are the vertices: `window` reads them
            self._data = None
            return
        # the data's sort by y (0.17 s at 1M points) in a second thread, beside the triangles' boxes
        with background(lambda: None if data_xy is None else _RowSorted(data_xy)) as rows:
            self._triangles()
            self._data = rows()

    def _triangles(self) -> None:
        """The set-up that needs no data points: the triangles' boxes, their order by north
        edge, the polynomial form of the scheme, the barycentric maps (once; a sampler
        reading its values off the vertices (NodeCells) makes it only if a cell needs the
        nearest-triangle rule)."""
        if self._ready:
            return
        interp, fill = self.interp, self.fill
        # the triangles the nearest-triangle rule searches: the trim's (a fill's triangles
        # span holes and the hull, and their long edges would widen every search)
        self._searched = np.arange(len(interp.triangles)) if fill is None else np.flatnonzero(fill.trimmed)
        K, self.exponents, error = polynomial_form(interp.scheme)
        self.K = K if error < 1e-9 else None        # else: rsd's shape functions per point
        tri, pts = interp.triangles, interp.points
        xs = [pts[tri[:, k], 0] for k in range(3)]
        ys = [pts[tri[:, k], 1] for k in range(3)]
        self._lo = np.column_stack([np.minimum(np.minimum(xs[0], xs[1]), xs[2]),
                                    np.minimum(np.minimum(ys[0], ys[1]), ys[2])])
        self._hi = np.column_stack([np.maximum(np.maximum(xs[0], xs[1]), xs[2]),
                                    np.maximum(np.maximum(ys[0], ys[1]), ys[2])])
        self.degree = int(self.exponents.max())
        self._index = {(int(i), int(j)): k for k, (i, j) in enumerate(self.exponents)}
        self._index = np.array([[self._index.get((i, j), -1) for j in range(self.degree + 1)]
                                for i in range(self.degree + 1)])
        # per triangle, one contiguous array each (gathered per cell): for k = 0, 1 the
        # gradient of λ_k and the vertex k+1 it is measured from
        G = interp.lambda_gradients
        self._bary = [(G[:, k, 0].copy(), G[:, k, 1].copy(), xs[k + 1], ys[k + 1]) for k in range(2)]
        self._order = np.argsort(self._hi[:, 1])                         # by north edge
        self._north = self._hi[self._order, 1]
        self._span = float((self._hi[:, 1] - self._lo[:, 1]).max()) if len(tri) else 0.0
        self._ready = True

    def window(self, grid: RasterGrid, rows: range, cols: range, gradients: bool = True):
        """Heights (nrows, ncols) in world z and gradients (nrows, ncols, 2) at the centres
        of grid cells rows × cols (indices may lie outside the grid: a halo); NaN outside
        the triangulation. gradients=False skips them (returns None): a DEM alone, or
        Horn's differences, need heights only."""
        nr, nc = len(rows), len(cols)
        z = np.full(nr * nc, np.nan)
        g = np.full((nr * nc, 2), np.nan) if gradients else None
        if self._nodes is not None and self._nodes.serves(grid):
            whole = _lattice(grid, rows, cols)
            vertex, cell = self._nodes.window(*whole)
            z[cell] = self.interp.values[vertex] + self.origin[2]
            if gradients:
                g[cell] = self.interp.gradients[vertex]
            cell, centres = self._nodes.bare(*whole)
            if not cell.size:
                return z.reshape(nr, nc), None if g is None else g.reshape(nr, nc, 2)
            has, tri, l0, l1, shift = self.continued(centres)
            cell = cell[has]
        else:
            cell, tri, l0, l1, shift = self.cells(grid, rows, cols)
        values, grads = self.evaluate(tri, l0, l1, gradients, shift)
        z[cell] = values + self.origin[2]
        if not gradients:
            return z.reshape(nr, nc), None
        g[cell] = grads
        return z.reshape(nr, nc), g.reshape(nr, nc, 2)

    def cells(self, grid: RasterGrid, rows: range, cols: range):
        """(flat cell index, triangle, λ0, λ1), each (m,), and shift (m, 2), of every cell
        centre of rows × cols inside a triangle (shift 0; a cell on a shared edge may appear
        twice: either triangle gives the same C1 surface; the later one is kept by the
        callers' assignment), then of the cells holding data points whose centre is in no
        triangle: the point q of the nearest triangle closest to the centre (λ0, λ1 of q)
        and shift = centre − q (local units), for `evaluate`'s linear continuation."""
        self._triangles()
        rows, cols = _lattice(grid, rows, cols)
        r = grid.resolution
        x0 = grid.west - self.origin[0]          # local x of the grid's west edge
        y0 = grid.north - self.origin[1]
        nc = len(cols)
        top, bottom = y0 - (rows.start + 0.5) * r, y0 - (rows.stop - 0.5) * r
        # triangles whose y-range meets the rows: north edge in [bottom, top + tallest]
        slack = r * 1e-9
        first = np.searchsorted(self._north, bottom - slack, side="left")
        last = np.searchsorted(self._north, top + self._span + slack, side="right")
        cand = self._order[first:last]
        cand = cand[self._lo[cand, 1] <= top + slack]
        cand = cand[(self._hi[cand, 0] >= x0 + (cols.start + 0.5) * r - slack)
                    & (self._lo[cand, 0] <= x0 + (cols.stop - 0.5) * r + slack)]
        eps = 1e-9
        j0 = np.maximum(np.ceil((self._lo[cand, 0] - x0) / r - 0.5 - eps).astype(np.int64), cols.start)
        j1 = np.minimum(np.floor((self._hi[cand, 0] - x0) / r - 0.5 + eps).astype(np.int64), cols.stop - 1)
        i0 = np.maximum(np.ceil((y0 - self._hi[cand, 1]) / r - 0.5 - eps).astype(np.int64), rows.start)
        i1 = np.minimum(np.floor((y0 - self._lo[cand, 1]) / r - 0.5 + eps).astype(np.int64), rows.stop - 1)
        nj = np.maximum(j1 - j0 + 1, 0)
        count = np.maximum(i1 - i0 + 1, 0) * nj
        tri = np.repeat(cand, count)
        local = np.arange(tri.size) - np.repeat(np.cumsum(count) - count, count)
        di, dj = np.divmod(local, np.repeat(nj, count))
        ii = np.repeat(i0, count) + di
        jj = np.repeat(j0, count) + dj
        cx, cy = x0 + (jj + 0.5) * r, y0 - (ii + 0.5) * r
        l0, l1 = self.barycentric(tri, cx, cy)
        tol = -self.TOLERANCE
        keep = (l0 >= tol) & (l1 >= tol) & (1.0 - l0 - l1 >= tol)
        if self.fill is not None and math.isfinite(self.fill.distance):
            spans = np.flatnonzero(keep & ~self.fill.trimmed[tri])       # cells in the holes' triangles
            far = self.distances(np.column_stack([cx[spans], cy[spans]])) > self.fill.distance
            keep[spans[far]] = False
        cell = (ii[keep] - rows.start) * nc + (jj[keep] - cols.start)
        found = (cell, tri[keep], l0[keep], l1[keep], np.zeros((cell.size, 2)))
        if self._nodes is not None and self._nodes.serves(grid):     # the data's cells: NodeCells'
            bare, centres = self._nodes.bare(rows, cols)
            has, *continued = self.continued(centres)
            return tuple(np.concatenate(pair) for pair in zip(found, (bare[has], *continued)))
        if self._data is None:
            return found
        return tuple(np.concatenate(pair) for pair in zip(found, self._uncovered(grid, rows, cols, cell)))

    def distances(self, xy: np.ndarray) -> np.ndarray:
        """(m,) the distance from each local plane point xy (m, 2) to the nearest point the
        fit used (fit_xy), by a k-d tree."""
        if self._tree is None:
            self._tree = spatial.cKDTree(self._fit_xy)
        return self._tree.query(xy)[0] if len(xy) else np.zeros(0)

    def centre_distances(self, grid: RasterGrid, rows: range, where: np.ndarray) -> np.ndarray:
        """(len(rows), width) the distance from each cell centre of the grid's rows where
        `where` (len(rows), width) bool holds to the nearest point the fit used
        (`distances`), in the grid's units; NaN elsewhere."""
        i, j = np.nonzero(where)
        x = grid.west - self.origin[0] + (grid.col0 + j + 0.5) * grid.resolution
        y = grid.north - self.origin[1] - (grid.row0 + rows.start + i + 0.5) * grid.resolution
        out = np.full(where.shape, np.nan)
        out[i, j] = self.distances(np.column_stack([x, y]))
        return out

    def _uncovered(self, grid: RasterGrid, rows: range, cols: range, covered: np.ndarray):
        """(cell, triangle, λ0, λ1, shift) of the cells of rows × cols that hold data points
        but whose centre lies in no triangle (`covered`: the flat cells that do), from
        their nearest triangle within reach (at its point closest to the centre); cells
        with none are left out (nodata)."""
        r, nc = grid.resolution, len(cols)
        x0, y0 = grid.west - self.origin[0], grid.north - self.origin[1]
        ii, jj = self._data.cells(x0, y0, r, rows, cols)
        # the cells with data and no covering triangle, ascending: marks over the window's
        # cells instead of a sort of its points (np.unique and np.isin: 0.11 s a 1M-cell DEM)
        marked = np.zeros(len(rows) * nc, dtype=bool)
        marked[(ii - rows.start) * nc + (jj - cols.start)] = True
        marked[covered] = False
        cell = np.flatnonzero(marked)
        i, j = np.divmod(cell, nc)
        has, tri, l0, l1, shift = self.continued(_cell_centres(x0, y0, r, rows.start + i, cols.start + j))
        return cell[has], tri, l0, l1, shift

    def continued(self, centre: np.ndarray):
        """(has (m,) bool, then for the centres that have one: triangle, λ0, λ1, shift) of
        the nearest searched triangle within the reach to each local plane point centre
        (m, 2), at its point q closest to the centre, shift = centre − q: the nearest-
        triangle rule of the cells outside the triangles (`_uncovered`; a tiled DEM asks
        each tile's own triangles and keeps the nearest: |shift| is the distance)."""
        self._triangles()
        if self._nearest is None and len(centre):
            self._rim = rim_triangles(self.interp.edge_table, self._searched)
            self._nearest = NearestTriangles(self.interp.points, self.interp.triangles[self._rim], self._reach)
        tri = self._nearest.of(centre) if len(centre) else np.zeros(0, np.int64)
        has = tri >= 0
        tri = np.where(has, self._rim[np.maximum(tri, 0)], -1)
        centre = centre[has]
        tri = tri[has]
        q = closest_points(centre, self.interp.points[self.interp.triangles[tri]])
        l0, l1 = self.barycentric(tri, q[:, 0], q[:, 1])
        return has, tri, l0, l1, centre - q

    def barycentric(self, tri, px, py) -> tuple[np.ndarray, np.ndarray]:
        """λ0, λ1 (m,) of points in triangles: λ_k = G_k·(p − vertex k+1), as
        c1mesh.engine.locate computes them (exact near the edge opposite vertex k)."""
        self._triangles()
        out = []
        for gx, gy, rx, ry in self._bary:
            lam = gx[tri] * (px - rx[tri])
            lam += gy[tri] * (py - ry[tri])
            out.append(lam)
        return out[0], out[1]

    def evaluate(self, tri, l0, l1, gradients: bool = True, shift=None):
        """Values (m,) and gradients (m, 2) (None unless `gradients`) of the spline at
        barycentrics (l0, l1, 1 − l0 − l1) in triangles tri (m,), continued linearly by
        shift (m, 2) (None: 0): value + gradient · shift, the gradient unchanged. The
        triangle's polynomial itself is not continued past the triangle: past a thin one
        it grows as the power of its degree (a sextic continued past rim triangles gave
        slopes off by up to 76° on an analytic terrain)."""
        self._triangles()
        values, grads = self._polynomial(tri, l0, l1, gradients)
        moved = np.zeros(0, np.int64) if shift is None else np.flatnonzero(shift.any(axis=1))
        if moved.size:
            slope = grads[moved] if grads is not None else \
                self._polynomial(tri[moved], l0[moved], l1[moved], True)[1]
            values[moved] += slope[:, 0] * shift[moved, 0] + slope[:, 1] * shift[moved, 1]
        return values, grads

    def _polynomial(self, tri, l0, l1, gradients: bool = True):
        """Values (m,) and gradients (m, 2) (None unless `gradients`) of the spline at
        barycentrics (l0, l1, 1 − l0 − l1) in triangles tri (m,)."""
        it = self.interp
        if self.K is None:
            C, G = it.coefficients[tri], it.lambda_gradients[tri]
            lam = np.column_stack([l0, l1, 1.0 - l0 - l1])
            return (rsd.values_at(it.scheme, C, lam),
                    rsd.gradients_at(it.scheme, C, G, lam) if gradients else None)
        A = self.K.T @ it.coefficients[tri].T                            # (P, m), rows contiguous
        m, d = tri.size, self.degree
        power0 = [np.ones(m), l0]
        power1 = [np.ones(m), l1]
        for _ in range(2, d + 1):
            power0.append(power0[-1] * l0)
            power1.append(power1[-1] * l1)
        values, d0, d1 = np.zeros(m), np.zeros(m), np.zeros(m)
        q, r, tmp = np.empty(m), np.empty(m), np.empty(m)
        for i in range(d + 1):
            # q = Σ_j a_ij λ1^j, r = ∂q/∂λ1; then F += λ0^i q, ∂F/∂λ0 += i λ0^(i−1) q, ∂F/∂λ1 += λ0^i r
            q.fill(0.0)
            r.fill(0.0)
            for j in range(d + 1 - i):
                row = A[self._index[i, j]]
                np.multiply(row, power1[j], out=tmp)
                q += tmp
                if j and gradients:
                    np.multiply(row, power1[j - 1], out=tmp)
                    tmp *= j
                    r += tmp
            np.multiply(q, power0[i], out=tmp)
            values += tmp
            if not gradients:
                continue
            np.multiply(r, power0[i], out=tmp)
            d1 += tmp
            if i:
                np.multiply(q, power0[i - 1], out=tmp)
                tmp *= i
                d0 += tmp
        if not gradients:
            return values, None
        (g0x, g0y, _, _), (g1x, g1y, _, _) = self._bary
        out = np.empty((m, 2))
        out[:, 0] = d0 * g0x[tri] + d1 * g1x[tri]
        out[:, 1] = d0 * g0y[tri] + d1 * g1y[tri]
        return values, out


def _lattice(grid: RasterGrid, rows: range, cols: range) -> tuple[range, range]:
    """rows and cols of a window (RasterGrid.window) as indices of its whole grid."""
    return (range(rows.start + grid.row0, rows.stop + grid.row0),
            range(cols.start + grid.col0, cols.stop + grid.col0))


def vertex_cells(interp, origin: np.ndarray, grid: RasterGrid) -> tuple[np.ndarray, np.ndarray] | None:
    """(row, col) int64 (n,): the cell of grid (its indices, which may lie outside it) whose
    centre each vertex of interp (local plane, origin (3,)) sits at, when every vertex sits
    at a centre (to 1e-6 cells) and every triangle's corners lie in neighbouring cells, so
    that no other centre lies in a triangle: the DEM's cells are then the vertices' (a
    lattice fit at the DEM's resolution, NodeCells). None else."""
    if not len(interp.points) or not _at_centres(interp.points[:64], origin, grid)[0]:
        return None                                  # a Delaunay fit's vertices: told at once
    at, ri, ci = _at_centres(interp.points, origin, grid)
    if not at:
        return None
    corners = interp.triangles[:, [0, 1, 2, 0]]
    if np.abs(np.diff(ci[corners], axis=1)).max(initial=0) > 1 or \
            np.abs(np.diff(ri[corners], axis=1)).max(initial=0) > 1:
        return None
    return ri, ci

def _at_centres(points: np.ndarray, origin: np.ndarray, grid: RasterGrid) -> tuple[bool, np.ndarray, np.ndarray]:
    """(whether every local plane point (n, 2) sits at a cell centre of grid, to 1e-6
    cells; their rows and columns (n,) int64 there)."""
    r = grid.resolution
    col = (points[:, 0] + origin[0] - grid.west) / r - 0.5
    row = (grid.north - (points[:, 1] + origin[1])) / r - 0.5
    ci, ri = np.rint(col), np.rint(row)
    at = bool(np.abs(col - ci).max() < 1e-6 and np.abs(row - ri).max() < 1e-6)
    return at, ri.astype(np.int64), ci.astype(np.int64)


def _finite_xy(xy) -> np.ndarray:
    """The rows of plane points xy (any shape of 2-rows) whose coordinates are finite, (m, 2) float64."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return xy[finite_rows(xy)]


def _cells_of(x: np.ndarray, y: np.ndarray, x0: float, y0: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) int64 (m,) of the cells holding the plane points x, y (m,) each, in the
    grid whose west edge is local x0 and north edge local y0, cell size r (a point on a
    cell's west or north edge belongs to that cell): _RowSorted's and NodeCells' one rule."""
    return np.floor((y0 - y) / r).astype(np.int64), np.floor((x - x0) / r).astype(np.int64)


def _cell_centres(x0: float, y0: float, r: float, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """(k, 2) the local plane centres of the cells (row, col) (k,) each of that grid: the
    nearest-triangle rule's points (SplineSampler._uncovered and NodeCells.bare alike)."""
    return np.column_stack([x0 + (col + 0.5) * r, y0 - (row + 0.5) * r])


class _RowSorted:
    """Plane points (m, 2) sorted by y, to list the grid cells that hold points row band
    by row band (a block of rows reads only its band)."""

    def __init__(self, xy):
        xy = _finite_xy(xy)
        order = np.argsort(xy[:, 1], kind="stable")
        self.x, self.y = xy[order, 0], xy[order, 1]

    def cells(self, x0: float, y0: float, r: float, rows: range, cols: range):
        """Row and column indices (k,) of the points inside the cells rows × cols of the
        grid whose west edge is local x0 and north edge local y0, cell size r (a point on
        a cell's west or north edge belongs to that cell)."""
        low, high = y0 - rows.stop * r, y0 - rows.start * r
        band = slice(np.searchsorted(self.y, low, side="right"), np.searchsorted(self.y, high, side="right"))
        ii, jj = _cells_of(self.x[band], self.y[band], x0, y0, r)
        inside = (ii >= rows.start) & (ii < rows.stop) & (jj >= cols.start) & (jj < cols.stop)
        return ii[inside], jj[inside]


def rim_triangles(table, searched: np.ndarray) -> np.ndarray:
    """The triangles of `searched` (ascending triangle numbers) with a corner on the
    boundary of the region they cover (an end of an edge that only one of them has), in
    ascending order: the only ones that can be nearest to a point outside the region.

    Why: the nearest point q of a nearest triangle to an outside point p lies on the
    region's boundary (were q inside, the segment pq would cross the boundary closer to
    p, on another triangle), so every triangle at the least distance has q on a boundary
    edge or at a boundary corner: it has a boundary corner. Searching these alone gives the
    same triangle, ties (the lowest number) included, and skips building the search over
    a million interior triangles for the few cells on the rim (2.7 s at 1M points).
    table: the topology.EdgeTable of all the interpolator's triangles."""
    count = np.bincount(table.tri_edge[searched].ravel(), minlength=len(table.edges))
    corner = np.zeros(int(table.edges.max()) + 1 if len(table.edges) else 0, dtype=bool)
    corner[table.edges[count == 1].ravel()] = True
    tri = table.edges[table.tri_edge[searched]]                   # (S, 3, 2): each triangle's edges' ends
    return searched[corner[tri.reshape(len(searched), -1)].any(axis=1)]


class NearestTriangles:
    """The nearest triangle to plane points, within a reach.

    points (n, 2), triangles (T, 3): a triangulation in the plane (local units); reach:
    the largest distance searched (None: any); points no triangle uses are not searched. A
    triangle at distance d from p has all three corners within d + L of p, L its longest
    edge, and the nearest corner's triangles bound d from above: so the triangles of the corners within d_corner + L_max
    of p are the candidates, and their exact point-triangle distances decide. Ties go to
    the lowest triangle number, so the answer does not depend on the search order.
    """

    def __init__(self, points: np.ndarray, triangles: np.ndarray, reach: float | None = None):
        self.points, self.triangles = np.asarray(points, dtype=np.float64), np.asarray(triangles)
        self.reach = np.inf if reach is None else float(reach)
        corners = self.points[self.triangles]                                   # (T, 3, 2)
        edges = corners[:, [1, 2, 0]] - corners
        self.longest = float(np.sqrt((edges ** 2).sum(axis=2)).max()) if len(self.triangles) else 0.0
        order = np.argsort(self.triangles.ravel(), kind="stable")
        self._of_vertex = order // 3                                            # triangles by vertex
        self._start = np.searchsorted(self.triangles.ravel()[order], np.arange(len(self.points) + 1))
        self._corners = np.unique(self.triangles)                               # points some triangle uses
        self._tree = spatial.cKDTree(self.points[self._corners])

    def of(self, query: np.ndarray) -> np.ndarray:
        """(q,) the nearest triangle to each query point (q, 2) within the reach, -1 if none."""
        out = np.full(len(query), -1, dtype=np.int64)
        if not len(self.triangles) or not len(query):
            return out
        first, _ = self._tree.query(query)
        for q, (p, d) in enumerate(zip(query, first)):
            if d - self.longest > self.reach:                # every triangle is farther than reach
                continue
            near = self._corners[self._tree.query_ball_point(p, d + self.longest)]
            cand = np.unique(np.concatenate([self._of_vertex[self._start[v]:self._start[v + 1]]
                                             for v in near]))
            dist = point_triangle_distance(p, self.points[self.triangles[cand]])
            best = np.flatnonzero(dist == dist.min())
            if dist[best[0]] <= self.reach:
                out[q] = cand[best].min()
        return out


def closest_points(p: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(m, 2) the point of each triangle corners (m, 3, 2) closest to the plane point p
    (m, 2): p itself inside, else the nearest point of its three edges."""
    a, b = corners, corners[:, [1, 2, 0]]
    ab = b - a
    rel = p[:, None, :] - a
    t = np.clip((rel * ab).sum(axis=2) / np.maximum((ab * ab).sum(axis=2), 1e-300), 0.0, 1.0)
    foot = a + t[..., None] * ab                                              # (m, 3, 2)
    nearest = np.argmin(((foot - p[:, None, :]) ** 2).sum(axis=2), axis=1)
    q = foot[np.arange(len(p)), nearest]
    cross = ab[..., 0] * rel[..., 1] - ab[..., 1] * rel[..., 0]               # (m, 3)
    inside = (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)
    return np.where(inside[:, None], p, q)


def point_triangle_distance(p: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(k,) Euclidean distance from the plane point p (2,) to the triangles corners (k, 3, 2):
    0 inside, else the distance to the nearest of the three edges."""
    a, b = corners, corners[:, [1, 2, 0]]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(axis=2) / np.maximum((ab * ab).sum(axis=2), 1e-300), 0.0, 1.0)
    edge = np.sqrt((((a + t[..., None] * ab) - p) ** 2).sum(axis=2)).min(axis=1)
    cross = ab[..., 0] * (p[1] - a[..., 1]) - ab[..., 1] * (p[0] - a[..., 0])   # (k, 3)
    inside = (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)
    return np.where(inside, 0.0, edge)
