"""PNG previews: a hillshade coloured by height, with a scale bar and a height colour bar.

Five sources, one picture: a fitted spline in a frame whose chart is a plane
(`render_spline`: heights and exact normals sampled at pixel centres), a surface mesh in
world coordinates, whatever frame made it (`render_surface`: the topmost face at each
pixel centre, heights and normals interpolated over it; the perspective fit's preview),
a mesh file with vertex normals (`render_mesh`: heights and normals of the vertices
averaged per pixel), and a DEM's cells (`render_dem`), both from the fit that writes the
DEM (`render_dem_fit`: shaded by the spline's gradient at the cell centres) and from the
GeoTIFF (`render_raster`: Horn's gradient of the cells, since the spline is not at hand;
one-sided at the edges of the data). The two DEM pictures draw the same cells: only the
shading differs. Pixels are in the scan frame's plane (x east, y north for terrain),
north up. matplotlib is imported only here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from c1mesh.core.cloud import PointCloud
from c1mesh.core.crs import describe
from c1mesh.core.errors import InputError
from c1mesh.formats import atomic_output, read_cloud
from c1mesh.formats.meshes import read_glb_vertices
from c1mesh.geo.raster import BLOCK_CELLS, hillshade, horn_gradient_at_edges, is_raster_path, rasterio_module
from c1mesh.geo.raster_grid import RasterGrid, SplineSampler
from c1mesh.stages.frame import choose_frame
from c1mesh.stages.surface import refined_vertex_count, surface_stream

PIXELS = 700
"""Cells along the longer side of a preview."""


def render_spline(interp, frame, path, crs: str | None = None, z_factor: float | None = 1.0) -> None:
    """Preview of a fitted spline: sampled on a grid over its triangulation in the scan
    frame (heights in world z when the frame's axes are the world's). z_factor: x, y units
    per height unit for the shading (raster.py); None (heights in units of their own, the
    factor unknown): coloured by height, unshaded, since any light would fake the slopes."""
    view = SplineView.of(interp.points.min(axis=0), interp.points.max(axis=0), frame)
    z, g = SplineSampler(interp, view.origin).window(view.grid, range(view.grid.height), range(view.grid.width))
    view.render(z, g, path, crs, z_factor)


@dataclass(frozen=True)
class SplineView:
    """Where render_spline samples the spline and where it draws it: grid, the pixels'
    cells in local x, y (PIXELS across the longer side of the vertices' box); origin, the
    sampler's (the frame's height origin when its axes are the world's, heights drawn in
    world z; else 0); offset, the world x, y of local (0, 0) (0 unless the axes are the
    world's). A survey fitted in tiles samples the same cells (pipeline.bounded_dem)."""

    grid: RasterGrid
    origin: tuple
    offset: np.ndarray

    @classmethod
    def of(cls, lo, hi, frame) -> "SplineView":
        """The view of a spline whose vertices span lo..hi (local x, y) in `frame`."""
        world = np.allclose(frame.axes, np.eye(3))
        return cls(RasterGrid.covering(lo, hi, _pixel_size(lo, hi)),
                   (0.0, 0.0, frame.origin[2] if world else 0.0),
                   np.asarray(frame.origin[:2], dtype=float) if world else np.zeros(2))

    def render(self, z: np.ndarray, g: np.ndarray, path, crs: str | None, z_factor: float | None) -> None:
        """Draw the heights z (h, w, world z) and spline gradients g (h, w, 2) sampled at
        the grid's centres (NaN outside the triangulation). z_factor: x, y units per
        height unit for the shading (None: unshaded, coloured by height)."""
        grid, offset = self.grid, self.offset
        extent = (grid.west + offset[0], grid.west + offset[0] + grid.width * grid.resolution,
                  grid.north + offset[1] - grid.height * grid.resolution, grid.north + offset[1])
        shade, title = _shading(g, z_factor)
        render_arrays(z, shade, extent, path, _units(crs), title)


def _shading(g: np.ndarray, z_factor: float | None) -> tuple[np.ndarray, str]:
    """(the gradients a fit's preview shades by, its title): the spline's gradients g
    (..., 2) times z_factor, x, y units per height unit; zero for z_factor None (unknown:
    coloured by height, unshaded, since any light would fake the slopes)."""
    if z_factor is None:
        return np.zeros_like(g), "C1 surface (unshaded: no --z-factor)"
    return (g if z_factor == 1.0 else g * z_factor), "C1 surface (spline normals)"


PREVIEW_VERTICES = 1_000_000
"""The most vertices of the refinement a perspective fit's preview is drawn from (the
output's level, or the highest level below it that stays under this): about three per
pixel of a PIXELS-wide picture, and bounded whatever --level the output has."""


def render_fit(interp, frame, path, crs: str | None = None, level: int | None = None,
               z_factor: float | None = 1.0, dem=None) -> None:
    """The preview of a fit (geo.finish calls this for every fit).

    dem: (RasterGrid, SplineSampler) of the DEM the fit wrote, or None. With one, the DEM's
    cells (render_dem_fit), so that `c1mesh preview` of the DEM draws the same cells.
    Else frame.ScanFrame (the spline is a height over a plane): render_spline. Otherwise
    (the perspective frame: the chart (u, v) of inverse depth is no map plane) the refined
    surface in world coordinates, at `level` or the highest lower level with at most
    PREVIEW_VERTICES vertices, drawn by render_surface. z_factor: render_spline's.
    """
    if dem is not None:
        render_dem_fit(*dem, path, crs=crs, z_factor=z_factor)
        return
    if not hasattr(frame, "normals_from_gradients"):
        render_spline(interp, frame, path, crs=crs, z_factor=z_factor)
        return

    level = max(1, int(level or 1))
    while level > 1 and refined_vertex_count(interp, level) > PREVIEW_VERTICES:
        level -= 1
    mesh = surface_stream(interp.refinement(level), frame, None).materialize()
    render_surface(mesh.vertices, mesh.faces, mesh.vertex_normals, path, crs=crs,
                   title="C1 surface (perspective fit)")


def render_surface(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, path,
                   crs: str | None = None, title: str = "C1 surface") -> None:
    """Preview of a surface mesh: vertices (N, 3) world coordinates, faces (F, 3) vertex
    indices, normals (N, 3) unit vertex normals (any sign).

    Seen along the axis where the surface is most nearly a height field (frame.choose_frame
    of the vertices and normals; world z for terrain within 10° of it), so the picture does
    not depend on the frame that made the mesh. Each pixel centre takes the topmost face
    over it (a z-buffer: nearer faces hide farther ones), its height and normal
    interpolated linearly (barycentric) over the face.
    """
    frame, world = _view_frame(vertices, normals)
    local = frame.to_local(vertices)
    up = frame.vectors_to_local(normals)
    up *= np.where(up[:, 2:] < 0, -1.0, 1.0)
    finite = np.isfinite(local).all(axis=1)          # faces with another corner draw nothing
    if not finite.any():
        raise InputError("nothing to preview: the surface has no finite vertex")
    lo, hi = local[finite, :2].min(axis=0), local[finite, :2].max(axis=0)
    grid = RasterGrid.covering(lo, hi, _pixel_size(lo, hi))
    with np.errstate(invalid="ignore"):
        z, g = _rasterize(local, up, np.asarray(faces), grid)
    z += frame.origin[2] if world else 0.0
    offset = frame.origin[:2] if world else np.zeros(2)
    size = grid.resolution
    extent = (grid.west + offset[0], grid.west + offset[0] + grid.width * size,
              grid.north + offset[1] - grid.height * size, grid.north + offset[1])
    render_arrays(z, g, extent, path, _units(crs), title)


_RASTER_CHUNK = 1 << 19
"""Candidate (face, pixel) pairs per step of _rasterize (bounds its temporaries)."""


@dataclass(frozen=True)
class _PixelVertices:
    """A mesh's vertices as _rasterize draws them: col, row (N,) their position in pixels
    of the grid (pixel centres at integers, row 0 at the north edge); height (N,) their z
    in the view frame; up (N, 3) their normals in that frame, z >= 0."""

    col: np.ndarray
    row: np.ndarray
    height: np.ndarray
    up: np.ndarray


@dataclass(frozen=True)
class _ZBuffer:
    """The picture _rasterize fills, pixels numbered row by row (width per row): best
    (h*w,) the height of the face drawn at each pixel (-inf: none yet); out (h*w, 3) its
    height and gradient x, y there (NaN: none). The arrays are written in place."""

    width: int
    best: np.ndarray
    out: np.ndarray


def _rasterize(local: np.ndarray, up: np.ndarray, faces: np.ndarray, grid: RasterGrid):
    """Heights (h, w) and gradients (h, w, 2) at the pixel centres of `grid` from the topmost
    face over each (NaN where none): local (N, 3) vertices in the view frame (x, y over the
    grid, z up), up (N, 3) their normals in that frame with z >= 0."""
    h, w = grid.height, grid.width
    col = (local[:, 0] - grid.west) / grid.resolution - 0.5       # pixel centres at integers
    row = (grid.north - local[:, 1]) / grid.resolution - 0.5
    first_col = np.ceil(col[faces].min(axis=1)).astype(np.int64).clip(0, w)
    last_col = np.floor(col[faces].max(axis=1)).astype(np.int64).clip(-1, w - 1)
    first_row = np.ceil(row[faces].min(axis=1)).astype(np.int64).clip(0, h)
    last_row = np.floor(row[faces].max(axis=1)).astype(np.int64).clip(-1, h - 1)
    finite = np.isfinite(col[faces]).all(axis=1) & np.isfinite(row[faces]).all(axis=1)
    cols = np.where(finite, np.maximum(last_col - first_col + 1, 0), 0)
    rows = np.where(finite, np.maximum(last_row - first_row + 1, 0), 0)
    candidates = cols * rows
    vertices = _PixelVertices(col, row, local[:, 2], up)
    buffer = _ZBuffer(w, np.full(h * w, -np.inf), np.full((h * w, 3), np.nan))
    ends = np.cumsum(candidates)
    start = 0
    while start < faces.shape[0]:
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + _RASTER_CHUNK, "right"))
        stop = max(stop, start + 1)
        part = slice(start, stop)
        face = np.repeat(np.arange(start, stop), candidates[part])
        step = np.arange(face.size) - np.repeat(np.cumsum(candidates[part]) - candidates[part],
                                                candidates[part])
        pc = first_col[face] + step % cols[face]
        pr = first_row[face] + step // np.maximum(cols[face], 1)
        _draw(vertices, faces[face], pc, pr, buffer)
        start = stop
    out = buffer.out
    return out[:, 0].reshape(h, w), out[:, 1:].reshape(h, w, 2)


def _draw(vertices: _PixelVertices, corners: np.ndarray, pc: np.ndarray, pr: np.ndarray,
          buffer: _ZBuffer) -> None:
    """Rasterise candidate pixels (pc, pr) (K,) of faces `corners` (K, 3) into the
    z-buffer: a pixel inside a face (barycentric weights >= 0, with a tolerance so shared
    edges leave no gap) takes it when it is higher than what the pixel holds."""
    col, row, height, up = vertices.col, vertices.row, vertices.height, vertices.up
    best, out = buffer.best, buffer.out
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    bx, by = col[b] - col[a], row[b] - row[a]
    cx, cy = col[c] - col[a], row[c] - row[a]
    px, py = pc - col[a], pr - row[a]
    area = bx * cy - by * cx
    with np.errstate(divide="ignore", invalid="ignore"):
        wb = (px * cy - py * cx) / area
        wc = (bx * py - by * px) / area
    wa = 1.0 - wb - wc
    inside = (area != 0) & (wa >= -1e-9) & (wb >= -1e-9) & (wc >= -1e-9)
    if not inside.any():
        return
    wa, wb, wc, a, b, c = wa[inside], wb[inside], wc[inside], a[inside], b[inside], c[inside]
    pixel = pr[inside] * buffer.width + pc[inside]
    z = wa * height[a] + wb * height[b] + wc * height[c]
    order = np.lexsort((z, pixel))                         # by pixel, highest last
    last = np.r_[pixel[order][1:] != pixel[order][:-1], True]
    top = order[last]
    pixel, z = pixel[top], z[top]
    higher = z > best[pixel]
    pixel, top = pixel[higher], top[higher]
    n = wa[top, None] * up[a[top]] + wb[top, None] * up[b[top]] + wc[top, None] * up[c[top]]
    nz = np.maximum(n[:, 2], 1e-3)                          # seen edge-on: steep, not undefined
    best[pixel] = z[higher]
    out[pixel, 0] = z[higher]
    out[pixel, 1] = -n[:, 0] / nz
    out[pixel, 2] = -n[:, 1] / nz


def _view_frame(points: np.ndarray, normals: np.ndarray):
    """The frame a surface is seen in (render_surface, render_mesh) and whether its axes
    are the world's: where it is a height field, world z for terrain within 10° of it."""
    frame = choose_frame(points, normals)
    if frame.axes[2, 2] > math.cos(math.radians(10)):   # terrain: show world x, y and z
        frame = choose_frame(points, normals, "z")
    return frame, bool(np.allclose(frame.axes, np.eye(3)))


def render_dem_fit(grid: RasterGrid, sampler: SplineSampler, path, crs: str | None = None,
                   z_factor: float | None = 1.0) -> None:
    """Preview of the DEM a fit writes: its cells (grid, and the sampler that gave their
    heights: raster.write_fit_rasters), shaded by the spline's gradient at their centres.
    The cells a fill spans across the trim's holes are drawn hatched (the support layer
    gives their distance to the data). z_factor: render_spline's (None: unshaded)."""
    stride = preview_stride(grid)
    z, g, filled = _dem_cells(grid, sampler, stride)
    render_dem_cells(DemCells(z, g, filled), grid, stride, path, crs, z_factor)


@dataclass(frozen=True)
class DemCells:
    """A DEM preview's cells (i·s, j·s) of its grid, s the stride: z (m, n) heights rounded
    to float32 as the DEM stores them (NaN: nodata), g (m, n, 2) the spline's gradient
    there, hatched (m, n) bool: spanning a hole the trim opened (or None: none)."""

    z: np.ndarray
    g: np.ndarray
    hatched: np.ndarray | None = None


def render_dem_cells(cells: DemCells, grid: RasterGrid, stride: int, path, crs: str | None = None,
                     z_factor: float | None = 1.0) -> None:
    """The picture of a fit's DEM from its cells (DemCells) shaded by the spline's
    gradient: the in-memory fit's (render_dem_fit) and the tiled DEM writer's
    (pipeline.bounded_dem), which gather the same cells each its own way. z_factor: x, y
    units per height unit (None: unknown, unshaded)."""
    shade, title = _shading(cells.g, z_factor)
    render_dem(cells.z, shade, grid, stride, path, _units(crs), title, hatched=cells.hatched)


def _dem_cells(grid: RasterGrid, sampler: SplineSampler, stride: int):
    """Heights (⌈h/s⌉, ⌈w/s⌉), the spline's gradients (⌈h/s⌉, ⌈w/s⌉, 2) and which cells the
    fill spans ((⌈h/s⌉, ⌈w/s⌉) bool: centre in a triangle the trim removed, raster_grid.FillRule)
    at the cells (i·s, j·s) of the grid, s = stride (NaN: nodata): the cells the DEM finds
    (sampler.cells) in blocks of rows (strided: each kept row alone), evaluated only at the
    kept columns. Heights rounded to float32, as the DEM stores them, so both pictures of
    a DEM colour the same numbers."""
    kept = range(0, grid.height, stride)
    cols = range(grid.width)
    z = np.full((len(kept), len(cols[::stride])), np.nan)
    g = np.full(z.shape + (2,), np.nan)
    filled = np.zeros(z.shape, dtype=bool)
    per_block = max(1, BLOCK_CELLS // grid.width) if stride == 1 else 1
    for first in range(0, len(kept), per_block):
        last = min(first + per_block, len(kept)) - 1
        cell, tri, l0, l1, shift = sampler.cells(grid, range(kept[first], kept[last] + 1), cols)
        row, col = np.divmod(cell, grid.width)          # row 0 of the block is kept row `first`
        mine = col % stride == 0
        values, grads = sampler.evaluate(tri[mine], l0[mine], l1[mine], True, shift[mine])
        at = (first + row[mine], col[mine] // stride)
        z[at] = values + sampler.origin[2]
        g[at] = grads
        if sampler.fill is not None:                    # the nearest-triangle cells are the trim's
            filled[at] = ~sampler.fill.trimmed[tri[mine]] & ~shift[mine].any(axis=1)
    return z.astype(np.float32).astype(np.float64), g, filled


def render_raster(source, path) -> None:
    """Preview of a GeoTIFF DEM (band 1, north up) with Horn's gradient of its cells,
    one-sided next to nodata and at the border (raster.horn_gradient_at_edges), so every
    cell with a height is drawn, as in the preview of the fit that wrote it."""
    rasterio = rasterio_module()
    try:
        with rasterio.open(source) as ds:
            z = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
            t = ds.transform
            crs = ds.crs.to_wkt() if ds.crs else None
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"cannot read the raster '{source}': {exc}") from exc
    grid = RasterGrid(t.c, t.f, abs(t.a), z.shape[1], z.shape[0])
    stride = preview_stride(grid)
    g = horn_gradient_at_edges(z, grid.resolution)
    render_dem(z[::stride, ::stride], g[::stride, ::stride], grid, stride, path, _units(crs),
               f"{Path(str(source)).name} (Horn gradient)")


def preview_stride(grid: RasterGrid) -> int:
    """Every how many cells a DEM's preview draws one: 1 up to PIXELS cells along the
    longer side, else the smallest stride that brings it to at most that (the picture's
    memory and time are bounded whatever the resolution)."""
    return max(1, math.ceil(max(grid.width, grid.height) / PIXELS))


def render_dem(z: np.ndarray, gradient: np.ndarray, grid: RasterGrid, stride: int, path,
               units: str, title: str, hatched: np.ndarray | None = None) -> None:
    """The picture of a DEM's cells: z (m, n) the heights of the cells (i·s, j·s) of grid,
    s = stride (NaN: nodata), gradient (m, n, 2) finite wherever z is. Each drawn cell
    stands for the s × s block of cells it starts; every cell with a height is drawn.
    hatched (m, n) bool: cells drawn hatched (render_arrays)."""
    size = grid.resolution * stride
    extent = (grid.west, grid.west + z.shape[1] * size, grid.north - z.shape[0] * size, grid.north)
    render_arrays(z, gradient, extent, path, units, title, hatched)


def render_mesh(source, path) -> None:
    """Preview of a mesh or point file with vertex normals: averages per pixel in the
    frame where it is a height field (c1mesh.stages.frame.choose_frame)."""
    if Path(str(source)).suffix.lower() == ".glb":
        points, normals, document_crs = read_glb_vertices(Path(source).read_bytes())
        cloud = PointCloud(points=points, normals=normals, crs=document_crs)
    else:
        cloud = read_cloud(source)
    if cloud.normals is None:
        raise InputError(f"'{source}' has no vertex normals to shade; fit it first (c1mesh fit)")
    frame, world = _view_frame(cloud.points, cloud.normals)
    local = frame.to_local(cloud.points)
    normals = frame.vectors_to_local(cloud.normals)
    normals *= np.where(normals[:, 2:] < 0, -1.0, 1.0)
    lo, hi = local[:, :2].min(axis=0), local[:, :2].max(axis=0)
    area = max(float(np.prod(hi - lo)), 1e-300)
    size = max(_pixel_size(lo, hi), 1.5 * math.sqrt(area / len(local)))
    grid = RasterGrid.covering(lo, hi, size)
    col = np.clip(((local[:, 0] - grid.west) / size).astype(np.int64), 0, grid.width - 1)
    row = np.clip(((grid.north - local[:, 1]) / size).astype(np.int64), 0, grid.height - 1)
    cell = row * grid.width + col
    count = np.bincount(cell, minlength=grid.width * grid.height).astype(float)
    mean = lambda v: np.bincount(cell, v, minlength=count.size) / np.where(count > 0, count, np.nan)  # noqa: E731
    z = mean(local[:, 2]) + (frame.origin[2] if world else 0.0)
    nz = mean(normals[:, 2])
    g = np.stack([-mean(normals[:, 0]) / nz, -mean(normals[:, 1]) / nz], axis=-1)
    shape = (grid.height, grid.width)
    z, g = _fill_gaps(z.reshape(shape), g.reshape(shape + (2,)))
    offset = frame.origin[:2] if world else np.zeros(2)
    extent = (grid.west + offset[0], grid.west + offset[0] + grid.width * size,
              grid.north + offset[1] - grid.height * size, grid.north + offset[1])
    render_arrays(z, g, extent, path, _units(cloud.crs), f"{Path(str(source)).name} (vertex normals)")


def _fill_gaps(z: np.ndarray, g: np.ndarray, passes: int = 2):
    """Fill empty pixels that have at least 4 of 8 filled neighbours with their mean
    (vertices of a refined mesh are not uniform, so some pixels inside it get none)."""
    for _ in range(passes):
        empty = ~np.isfinite(z)
        if not empty.any():
            break
        stack = np.concatenate([z[..., None], g], axis=-1)
        padded = np.pad(stack, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
        h, w = z.shape
        shifts = [padded[1 + di:1 + di + h, 1 + dj:1 + dj + w] for di in (-1, 0, 1) for dj in (-1, 0, 1)
                  if di or dj]
        neighbours = np.stack(shifts)                                   # (8, h, w, 3)
        have = np.isfinite(neighbours[..., 0])
        count = have.sum(axis=0)
        total = np.where(have[..., None], neighbours, 0.0).sum(axis=0)
        fill = empty & (count >= 4)
        z[fill] = total[fill, 0] / count[fill]
        g[fill] = total[fill, 1:] / count[fill, None]
    return z, g


def render_file(source, path) -> None:
    """Preview of an existing output: a GeoTIFF DEM or a mesh file."""
    if not Path(source).exists():
        raise InputError(f"Input file '{source}' does not exist.")
    (render_raster if is_raster_path(source) else render_mesh)(source, path)


def render_arrays(z: np.ndarray, gradient: np.ndarray, extent, path, units: str, title: str,
                  hatched: np.ndarray | None = None) -> None:
    """Draw heights z (h, w) shaded by gradients (h, w, 2) over extent (left, right, bottom,
    top) and write the PNG atomically. NaN heights are transparent. hatched (h, w) bool:
    cells drawn under diagonal hatching, with a note under the map (a DTM's cells filled
    across holes in the data, so a reader sees which heights no point is near)."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    valid = np.isfinite(z) & np.isfinite(gradient).all(axis=-1)
    if not valid.any():
        raise InputError("nothing to preview: the surface covers no pixel")
    lo, hi = np.percentile(z[valid], [1, 99])
    hi = hi if hi > lo else lo + 1.0
    rgba = matplotlib.colormaps["gist_earth"](np.clip((z - lo) / (hi - lo), 0, 1) * 0.85 + 0.1)
    shade = hillshade(np.where(valid[..., None], gradient, 0.0))
    rgba[..., :3] *= (0.25 + 0.75 * shade)[..., None]
    rgba[..., 3] = valid
    h, w = z.shape
    plot_w = 5.6                                   # inches of map; margins around it
    if hatched is not None and (hatched & valid).any():
        rgba = _hatched(rgba, hatched & valid, round(plot_w * 100))
    plot_h = plot_w * h / w
    fig = Figure(figsize=(plot_w + 2.3, plot_h + 0.9), dpi=100)
    FigureCanvasAgg(fig)
    W, H = plot_w + 2.3, plot_h + 0.9
    ax = fig.add_axes((1.1 / W, 0.4 / H, plot_w / W, plot_h / H))
    ax.imshow(rgba, extent=extent, origin="upper", interpolation="nearest")
    if hatched is not None and (hatched & valid).any():
        ax.annotate("hatched: filled across a hole in the data (see the support layer)", (1.0, 0.0),
                    xycoords="axes fraction", xytext=(0, -16), textcoords="offset points",
                    fontsize=7, ha="right", va="top")
    ax.set_title(title, fontsize=10)
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(labelsize=7)
    _scale_bar(ax, extent, units)
    cax = fig.add_axes(((1.3 + plot_w) / W, 0.2 + 0.4 / H, 0.15 / W, 0.6 * plot_h / H))
    norm = matplotlib.colors.Normalize(lo, hi)
    cmap = matplotlib.colors.ListedColormap(matplotlib.colormaps["gist_earth"](np.linspace(0.1, 0.95, 256)))
    fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap), cax=cax).set_label(
        f"height ({units})" if units else "height", fontsize=8)
    cax.tick_params(labelsize=7)
    with atomic_output(path, "wb") as handle:
        fig.savefig(handle, format="png")


def _hatched(rgba: np.ndarray, mask: np.ndarray, map_pixels: int) -> np.ndarray:
    """rgba (h, w, 4) with diagonal stripes darkened over the cells of mask (h, w) bool: the
    hatching of the cells a fill spans. The stripes are drawn into the cells, not over
    them, so they never fall outside the drawn cells. They are about 6 pixels apart on a
    map map_pixels wide whatever the grid: a grid coarser than that is first repeated k×k
    per cell (nearest, what imshow shows anyway), so even a hole of one cell shows stripes,
    not a dark speck that would read as a pit."""
    h, w = mask.shape
    k = max(1, math.ceil(map_pixels / (2 * w)))
    if k > 1:
        rgba = np.repeat(np.repeat(rgba, k, axis=0), k, axis=1)
        mask = np.repeat(np.repeat(mask, k, axis=0), k, axis=1)
    period = max(3, round(6 * w * k / map_pixels))
    i, j = np.ogrid[:h * k, :w * k]
    stripe = (i + j) % period < max(1, period // 3)
    rgba[mask & stripe, :3] *= 0.55
    return rgba


def _scale_bar(ax, extent, units: str) -> None:
    """A bar of a round length (1, 2 or 5 × 10^k) about a fifth of the width, bottom left."""
    width = extent[1] - extent[0]
    raw = width / 5
    power = 10 ** math.floor(math.log10(raw))
    length = max(m * power for m in (1, 2, 5) if m * power <= raw)
    x0 = extent[0] + 0.05 * width
    y0 = extent[2] + 0.05 * (extent[3] - extent[2])
    ax.plot([x0, x0 + length], [y0, y0], color="black", linewidth=4, solid_capstyle="butt")
    ax.plot([x0, x0 + length], [y0, y0], color="white", linewidth=1.5, solid_capstyle="butt")
    ax.text(x0 + length / 2, y0 + 0.035 * (extent[3] - extent[2]), f"{length:g} {units}".strip(),
            ha="center", va="bottom", fontsize=9,
            bbox={"facecolor": "white", "alpha": 0.7, "edgecolor": "none", "pad": 1})


def _pixel_size(lo, hi) -> float:
    span = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    return span / PIXELS if span > 0 else 1.0


_UNIT_NAMES = {"metre": "m", "meter": "m", "US survey foot": "ft (US)", "foot": "ft", "degree": "°"}


def _units(crs: str | None) -> str:
    """Short name of the horizontal unit of a CRS ('' when there is none)."""
    if not crs:
        return ""
    unit = describe(crs)["units"] or ""
    return _UNIT_NAMES.get(unit, unit)
