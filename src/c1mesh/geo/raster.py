"""GeoTIFF rasters from the C1 surface: DEM, slope, aspect and hillshade on one grid.

The grid is aligned to multiples of the resolution R in world coordinates (x to the east,
y to the north, z up: the surface must be a height field over the world XY plane, so the
fit uses --axis z). Each cell holds the spline at the cell centre. A cell whose centre lies
outside the trimmed triangulation but which holds input points (the trim removed the
triangle under its centre, or the centre lies just past the mesh's rim) holds the spline
of the nearest kept triangle, when that triangle lies within `reach` of the centre (the
fit passes its max_edge): the spline's value and gradient at the triangle's point closest
to the centre, continued linearly to the centre (slope rasters take that gradient).
Nodata is therefore only where there is no data: cells without points outside the
trimmed triangulation, and cells whose points lie more than `reach` from every kept
triangle (in a gap wider than --max-edge). A fill (--fill, FillRule; default: the whole
hull, DEFAULT_FILL) adds the cells of the holes the trim opened: the fit's spline spans
them (pipeline.driver.filled_mesh), and a cell there holds it when its centre is within
the fill distance of a point the fit used. The support raster holds each cell's distance
to that nearest point (SplineSampler.distances), nodata where the DEM is. Slope, aspect and hillshade come from a
gradient at each cell centre: the spline's own analytic gradient ("spline"), or Horn's
3x3 differences of the DEM ("horn", what `gdaldem slope` computes), chosen per resolution
by "auto" (see AUTO_SPLINE_FROM). The rasters are computed and written in blocks of rows, so
memory holds a few blocks, not the grid, and each becomes a Cloud-Optimised GeoTIFF
(COG_FORMAT, cog_copy).

Units: slope in degrees from horizontal (0-90); aspect in degrees clockwise from north of
the downhill direction (0-360, GDAL's convention; 0 where the surface is exactly flat);
hillshade 1-255 (uint8, 0 = nodata) for a light from azimuth 315°, altitude 45°, like
`gdaldem hillshade`. Slope and hillshade take the gradient times the z-factor, the x, y
units per height unit (ArcGIS's z-factor, the inverse of gdaldem's -s scale; 1 when x, y
and z share one unit): slope = atan(|∇z| · z_factor). Aspect needs none (a direction in
the plan does not depend on the height unit).

The grid and the sampling of the spline at its cell centres (the nearest-triangle rule
above) are c1mesh.geo.raster_grid; this module makes and writes the rasters from them.
"""
from __future__ import annotations

import contextlib
import math
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator
from xml.sax.saxutils import escape

import numpy as np

from c1mesh.core.crs import describe
from c1mesh.core.errors import DependencyError, InputError
from c1mesh.core.outputs import DEM_AXES, RASTER_FORMATS, register_temp, unregister_temp
from c1mesh.core.tile import bounds
from c1mesh.formats import atomic_output
from c1mesh.geo.raster_grid import FillRule, RasterGrid, SplineSampler

RASTER_SUFFIXES = tuple(f".{fmt}" for fmt in RASTER_FORMATS)
DEM_NODATA = -9999.0
HILLSHADE_NODATA = 0
BLOCK_ROWS = 256
"""GeoTIFF tile size, and the most rows computed and written at a time."""
BLOCK_CELLS = 1 << 17
"""Cells computed at a time (fewer rows per block on wide grids): bounds the memory."""
SLOPE_METHODS = ("auto", "spline", "horn")
AUTO_SPLINE_FROM = 8.0
"""`auto` uses the spline's gradient at resolutions of at least this many point spacings
(√(area / points)) and Horn's differences of the DEM below. From the slope table in
benchmarks/RESULTS.md (section geo): the sextic's gradient follows every error of the
input normals (it interpolates them) and is only O(h) between points, so Horn's 3x3
average of the spline's heights is closer to the true slope up to about 4 spacings with
exact normals and 8 spacings with 3° normal noise; beyond that Horn's own truncation
error (O(R²)) dominates and the spline gradient wins."""
AUTO_SPLINE_FROM_SMOOTHED = 4.0
"""The same crossover for a smoothing fit (--smooth): its spline is fitted to the heights,
not through their noise, and its analytic slope is the better one from 4 point spacings
on. Measured with `python -m benchmarks.geo noisy-slope` (benchmarks/RESULTS.md, geo: 2 cm
height noise, no normals, --smooth auto): slope RMS error spline / Horn 0.366° / 0.254° at
3 spacings, 0.360° / 0.447° at 4, 0.361° / 1.701° at 8."""
LIGHT_AZIMUTH, LIGHT_ALTITUDE = 315.0, 45.0
FILL_WORDS = ("hull", "off")
DEFAULT_FILL = "hull"
"""The DEM's default fill (--fill): every cell inside the hull of the points, as a DTM
user expects (lidR's rasterize_terrain and LAStools' blast2dem interpolate the whole hull);
the support layer (--support) then tells each cell's distance to the data."""


def is_raster_path(path) -> bool:
    """True when `path` names a GeoTIFF output (.tif/.tiff)."""
    return isinstance(path, (str, Path)) and Path(path).suffix.lower() in RASTER_SUFFIXES


def rasterio_module():
    """The rasterio module, imported on first use; DependencyError naming the install
    command when it is missing (GeoTIFF reading and writing need it)."""
    try:
        import rasterio
    except ImportError as exc:
        raise DependencyError('Writing GeoTIFF needs rasterio: pip install "rasterio>=1.3".') from exc
    return rasterio


# ------------------------------------------------------------------------------ gradients
def horn_gradient(dem: np.ndarray, resolution: float) -> np.ndarray:
    """Horn's (1981) 3x3 gradient of a north-up DEM with a one-cell halo.

    dem (h + 2, w + 2) → (h, w, 2) = (dz/dx east, dz/dy north); NaN where any of the nine
    cells is NaN. This is `gdaldem slope`'s default method.
    """
    a, b, c = dem[:-2, :-2], dem[:-2, 1:-1], dem[:-2, 2:]
    d, f = dem[1:-1, :-2], dem[1:-1, 2:]
    g, h, i = dem[2:, :-2], dem[2:, 1:-1], dem[2:, 2:]
    out = np.empty(a.shape + (2,))
    out[..., 0] = ((c + 2 * f + i) - (a + 2 * d + g)) / (8 * resolution)
    out[..., 1] = ((a + 2 * b + c) - (g + 2 * h + i)) / (8 * resolution)
    return out


HORN_WEIGHTS = (1.0, 2.0, 1.0)
"""Horn's weights of the three rows (for dz/dx) or columns (for dz/dy) of the 3x3 window."""


def horn_gradient_at_edges(dem: np.ndarray, resolution: float) -> np.ndarray:
    """Horn's gradient of a whole north-up DEM, also at cells next to nodata or the border.

    dem (h, w), NaN = nodata → (h, w, 2) = (dz/dx east, dz/dy north), NaN exactly where the
    DEM is. Horn's dz/dx is the 1-2-1 weighted mean of the central differences of the
    window's three rows (dz/dy: of its three columns). A row missing a cell gives the
    one-sided difference of the two it has (a row with one cell or none is left out, the
    weights of the others renormalised); a cell with no row giving a difference (a strip
    one cell wide) has 0 there. With all nine cells this is horn_gradient; a plane gives
    its exact gradient at every cell. gdaldem -compute_edges does the same at the raster's
    border (it extrapolates a missing row or column linearly), but repeats the centre cell
    for a nodata neighbour, which flattens the slope at the rim of every gap; the
    one-sided difference keeps it.
    """
    z = np.pad(np.asarray(dem, dtype=np.float64), 1, constant_values=np.nan)
    h, w = z.shape[0] - 2, z.shape[1] - 2
    cell = lambda di, dj: z[1 + di:1 + di + h, 1 + dj:1 + dj + w]   # noqa: E731  di > 0 south, dj > 0 east
    out = np.empty((h, w, 2))
    out[..., 0] = _weighted_differences([(cell(di, -1), cell(di, 0), cell(di, 1)) for di in (-1, 0, 1)],
                                        resolution)
    out[..., 1] = _weighted_differences([(cell(1, dj), cell(0, dj), cell(-1, dj)) for dj in (-1, 0, 1)],
                                        resolution)
    out[~np.isfinite(dem)] = np.nan
    return out


def _weighted_differences(lines, resolution: float) -> np.ndarray:
    """Horn's weighted mean of the differences along three lines (low, middle, high) (h, w)
    each: central where both ends are data, else one-sided with the middle, else left out;
    0 where no line has one."""
    total, weight = 0.0, 0.0
    for w, (low, middle, high) in zip(HORN_WEIGHTS, lines):
        d = (high - low) / (2 * resolution)
        d = np.where(np.isfinite(d), d, (high - middle) / resolution)
        d = np.where(np.isfinite(d), d, (middle - low) / resolution)
        have = np.isfinite(d)
        total = total + np.where(have, w * d, 0.0)
        weight = weight + np.where(have, w, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(weight > 0, total / weight, 0.0)


def slope_degrees(gradient: np.ndarray) -> np.ndarray:
    """Slope from horizontal in degrees, from gradients (..., 2)."""
    return np.degrees(np.arctan(np.hypot(gradient[..., 0], gradient[..., 1])))


def aspect_degrees(gradient: np.ndarray) -> np.ndarray:
    """Azimuth of the downhill direction, degrees clockwise from north in [0, 360); 0 where
    the gradient is exactly zero."""
    gx, gy = gradient[..., 0], gradient[..., 1]
    azimuth = np.mod(np.degrees(np.arctan2(-gx, -gy)), 360.0)
    return np.where((gx == 0) & (gy == 0), 0.0, azimuth)


def hillshade(gradient: np.ndarray, azimuth: float = LIGHT_AZIMUTH,
              altitude: float = LIGHT_ALTITUDE) -> np.ndarray:
    """Lambertian shade in [0, 1] of the unit normal (−gx, −gy, 1)/‖·‖ for a light from
    `azimuth` (degrees clockwise from north) and `altitude` (degrees above the horizon)."""
    az, alt = math.radians(azimuth), math.radians(altitude)
    light = (math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt))
    gx, gy = gradient[..., 0], gradient[..., 1]
    shade = (-gx * light[0] - gy * light[1] + light[2]) / np.sqrt(gx * gx + gy * gy + 1.0)
    return np.clip(shade, 0.0, 1.0)


def choose_slope_method(method: str, resolution: float, spacing: float, smoothed: bool = False) -> str:
    """'spline' or 'horn' for a requested method at a resolution and point spacing, for an
    exact or (smoothed) a smoothing fit: AUTO_SPLINE_FROM and AUTO_SPLINE_FROM_SMOOTHED."""
    if method not in SLOPE_METHODS:
        raise InputError(f"slope method must be one of {', '.join(SLOPE_METHODS)}, got {method!r}")
    if method != "auto":
        return method
    crossover = AUTO_SPLINE_FROM_SMOOTHED if smoothed else AUTO_SPLINE_FROM
    return "spline" if resolution >= crossover * spacing else "horn"


# ------------------------------------------------------------------------------- writing
@dataclass
class RasterTargets:
    """Where each raster goes (None = not written)."""

    dem: str | None = None
    slope: str | None = None
    aspect: str | None = None
    hillshade: str | None = None
    support: str | None = None

    def items(self):
        return [(k, v) for k, v in vars(self).items() if v is not None]


def grid_blocks(grid: RasterGrid, sampler: SplineSampler, method: str | None,
                block_rows: int | None = None) -> Iterator[tuple[range, np.ndarray, np.ndarray | None]]:
    """(rows, heights (n, w), gradients (n, w, 2)) for consecutive blocks of grid rows.

    method "spline": the spline's gradient at each centre; "horn": Horn's differences of
    the sampled heights (one extra cell around the block), the spline's gradient where a
    neighbour is nodata (at the edges of the mesh); None: heights only.
    """
    block_rows = block_rows or max(1, min(BLOCK_ROWS, BLOCK_CELLS // grid.width))
    for start in range(0, grid.height, block_rows):
        rows = range(start, min(start + block_rows, grid.height))
        if method != "horn":
            z, g = sampler.window(grid, rows, range(grid.width), gradients=method == "spline")
            yield rows, z, g
            continue
        halo = (range(rows.start - 1, rows.stop + 1), range(-1, grid.width + 1))
        cell, tri, l0, l1, shift = sampler.cells(grid, *halo)
        zh = np.full((len(halo[0]), len(halo[1])), np.nan)
        zh.ravel()[cell] = sampler.evaluate(tri, l0, l1, False, shift)[0] + sampler.origin[2]
        z = zh[1:-1, 1:-1]
        g = horn_gradient(zh, grid.resolution)
        edge = np.isfinite(z) & ~np.isfinite(g).all(axis=2)
        if edge.any():      # cells next to nodata: the spline's own gradient there
            wanted = np.zeros(zh.shape, bool)
            wanted[1:-1, 1:-1] = edge
            some = wanted.ravel()[cell]
            spline = np.full(zh.shape + (2,), np.nan)
            spline.reshape(-1, 2)[cell[some]] = sampler.evaluate(tri[some], l0[some], l1[some], True)[1]
            g[edge] = spline[1:-1, 1:-1][edge]
        yield rows, z, g


def _profile(grid: RasterGrid, dtype: str, nodata, crs: str | None) -> dict:
    """The staging GeoTIFF's profile (write_rasters): tiled as the COG will be, deflated
    fast (it is read once, by cog_copy)."""
    profile = {"driver": "GTiff", "width": grid.width, "height": grid.height, "count": 1,
               "dtype": dtype, "nodata": nodata, "transform": grid.transform,
               "compress": "deflate", "zlevel": 1, "tiled": True, "blockxsize": BLOCK_ROWS,
               "blockysize": BLOCK_ROWS, "BIGTIFF": "IF_SAFER"}
    if dtype.startswith("float"):
        profile["predictor"] = 3   # floating-point predictor: deflate packs DEMs much better
    if crs:
        profile["crs"] = crs
    return profile


_KINDS = {"dem": ("float32", DEM_NODATA), "slope": ("float32", DEM_NODATA),
          "aspect": ("float32", DEM_NODATA), "hillshade": ("uint8", HILLSHADE_NODATA),
          "support": ("float32", DEM_NODATA)}


def _layer(kind: str, z: np.ndarray, g: np.ndarray, z_factor: float = 1.0) -> np.ndarray:
    """The values of raster `kind` for one block, nodata filled in; z_factor: x, y units
    per height unit, scaling the gradient (height per x, y unit) of slope and hillshade."""
    outside = ~np.isfinite(z)
    if kind == "dem":
        return np.where(outside, DEM_NODATA, z)
    elif kind == "slope":
        out = slope_degrees(g if z_factor == 1.0 else g * z_factor)
    elif kind == "aspect":
        out = aspect_degrees(g)
    else:
        shade = np.rint(1.0 + 254.0 * hillshade(np.nan_to_num(g if z_factor == 1.0 else g * z_factor)))
        return np.where(outside, HILLSHADE_NODATA, shade).astype(np.uint8)
    return np.where(outside, DEM_NODATA, out).astype(np.float32)


def write_rasters(targets: RasterTargets, grid: RasterGrid, sampler: SplineSampler,
                  method: str = "spline", crs: str | None = None,
                  block_rows: int | None = None, dem_dtype: str = "float32",
                  z_factor: float = 1.0) -> dict:
    """Write the requested rasters of the spline `sampler` samples in one pass over the
    grid (grid_blocks, with the support layer's distances where asked); returns a report
    dict (write_blocks).

    z_factor: x, y units per height unit, for slope and hillshade (module docstring).

    dem_dtype "float64" keeps every digit of the spline's heights (GIS tools expect
    float32, the default, which rounds heights of 1e4 to ~1e-3).
    """
    shaded = any(kind not in ("dem", "support") for kind, _ in targets.items())

    def blocks():
        for rows, z, g in grid_blocks(grid, sampler, method if shaded else None, block_rows):
            support = sampler.centre_distances(grid, rows, np.isfinite(z)) if targets.support else None
            yield rows, z, g, support
    return write_blocks(targets, grid, blocks(), RasterStyle(method, crs, dem_dtype, z_factor))


@dataclass(frozen=True)
class RasterStyle:
    """How write_blocks writes: method, the slope method the gradients came from (the
    report's); crs (WKT or None); dem_dtype "float32" or "float64"; z_factor (x, y units
    per height unit, for slope and hillshade)."""

    method: str | None = "spline"
    crs: str | None = None
    dem_dtype: str = "float32"
    z_factor: float = 1.0


def write_blocks(targets: RasterTargets, grid: RasterGrid, blocks, style: RasterStyle = RasterStyle()) -> dict:
    """Write the requested rasters from blocks of grid rows; returns a report dict.

    blocks: (rows (range of grid rows, in order, covering the grid), heights (n, w) world z,
    NaN = nodata, gradients (n, w, 2) or None when no slope, aspect or hillshade is asked,
    support (n, w) distances, NaN where the DEM is nodata, or None without --support):
    from a sampled spline (write_rasters) or from grids the tiles filled
    (pipeline.bounded_dem).

    Every file is a Cloud-Optimised GeoTIFF (cog_copy): the blocks are written to a
    staging GeoTIFF beside the output (GDAL's COG driver writes only by copying a whole
    dataset), which GDAL then copies into the output's temporary file; the outputs are
    renamed into place only when all of them are complete (formats.atomic_output), and
    the staging files are removed on success, error and interrupt.
    """
    rasterio = rasterio_module()

    items = targets.items()
    if not items:
        return {}
    cells_inside = 0
    with contextlib.ExitStack() as stack:
        temps = {kind: stack.enter_context(atomic_output(path, "path")) for kind, path in items}
        staged = {kind: stack.enter_context(staging_path(temps[kind])) for kind, _ in items}
        kinds = dict(_KINDS, dem=(style.dem_dtype, DEM_NODATA))
        datasets = {kind: stack.enter_context(rasterio.open(staged[kind], "w", **_profile(
            grid, *kinds[kind], style.crs))) for kind, _ in items}
        farthest = 0.0
        for rows, z, g, support in blocks:
            cells_inside += int(np.isfinite(z).sum())
            window = rasterio.windows.Window(0, rows.start, grid.width, len(rows))
            for kind, ds in datasets.items():
                if kind == "support":
                    # each cell centre's distance to the nearest point the fit used; nodata: no DEM value
                    layer = np.where(np.isfinite(support), support, DEM_NODATA).astype(np.float32)
                    farthest = max(farthest, float(layer.max(initial=0.0)))
                else:
                    layer = _layer(kind, z, g, style.z_factor)
                ds.write(layer.astype(kinds[kind][0], copy=False), 1, window=window)
        for kind, ds in datasets.items():
            ds.close()
            cog_copy(staged[kind], temps[kind], kind)
    return {"grid": grid_facts(grid),
            "cells": grid.width * grid.height, "cells_with_data": cells_inside,
            "slope_method": style.method, "z_factor": style.z_factor, "files": dict(items),
            **({"support_max": farthest} if targets.support else {}),
            "format": {key: str(value) for key, value in COG_FORMAT.items()}}


def grid_facts(grid: RasterGrid) -> dict:
    """The report's raster.grid: west, north (CRS units), resolution, width, height (cells)."""
    return {"west": grid.west, "north": grid.north, "resolution": grid.resolution,
            "width": grid.width, "height": grid.height}


COG_FORMAT = {"driver": "COG", "compress": "DEFLATE", "predictor": "YES", "blocksize": BLOCK_ROWS,
              "overviews": "AUTO"}
"""How every raster is written (the report's raster.format): GDAL's COG driver, deflate
with its predictor (YES: floating-point for float rasters, horizontal differencing for
the uint8 hillshade), 256 x 256 tiles, and internal overviews halving the grid until it
fits one tile (averaged; nearest for the hillshade, whose shades are not heights)."""


@contextlib.contextmanager
def staging_path(target: Path):
    """A path beside `target` for the staging GeoTIFF, listed as a temporary file of the
    process (removed by the CLI's signal handler on Ctrl-C) and removed when the block
    ends, whatever happens."""
    path = Path(target).with_name(f".{Path(target).name}.{secrets.token_hex(4)}.stage.tif")
    register_temp(path)
    try:
        yield path
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        unregister_temp(path)


def cog_copy(source: Path, target: Path, kind: str) -> None:
    """Copy the GeoTIFF `source` into a Cloud-Optimised GeoTIFF at `target` with GDAL's
    COG driver (COG_FORMAT); overviews averaged, nearest for the hillshade."""
    import rasterio.shutil

    options = {key.upper(): value for key, value in COG_FORMAT.items() if key != "driver"}
    rasterio.shutil.copy(str(source), str(target), driver="COG", BIGTIFF="IF_SAFER",
                         OVERVIEW_RESAMPLING="NEAREST" if kind == "hillshade" else "AVERAGE", **options)


# --------------------------------------------------------------------------- mosaics
VRT_TYPES = {"float32": "Float32", "float64": "Float64", "uint8": "Byte"}


def write_vrt(path, grid: RasterGrid, tiles, kind: str = "dem", crs: str | None = None) -> None:
    """Write a GDAL VRT mosaic at `path` of the rasters `tiles` [(file path, window grid)],
    each a window (RasterGrid.window) of `grid`, of one raster kind (_KINDS: its type and
    nodata). The mosaic is `grid` itself; each tile is a ComplexSource placed at its
    window's row0, col0, its nodata cells transparent; the files are named relative to the
    VRT (GDAL's VRT format, gdal.org/drivers/raster/vrt.html; written by hand, as GDAL's
    BuildVRT has no rasterio binding). Atomic, as every output."""
    dtype, nodata = _KINDS[kind]
    t = grid.transform
    lines = [f'<VRTDataset rasterXSize="{grid.width}" rasterYSize="{grid.height}">']
    if crs:
        lines.append(f'  <SRS dataAxisToSRSAxisMapping="1,2">{escape(crs)}</SRS>')
    lines.append(f"  <GeoTransform>{t.c!r}, {t.a!r}, 0.0, {t.f!r}, 0.0, {t.e!r}</GeoTransform>")
    lines.append(f'  <VRTRasterBand dataType="{VRT_TYPES[dtype]}" band="1">')
    lines.append(f"    <NoDataValue>{nodata!r}</NoDataValue>")
    for file, window in tiles:
        name = os.path.relpath(Path(file).resolve(), Path(path).resolve().parent)
        size = f'xSize="{window.width}" ySize="{window.height}"'
        lines += ["    <ComplexSource>",
                  f'      <SourceFilename relativeToVRT="1">{escape(name)}</SourceFilename>',
                  "      <SourceBand>1</SourceBand>",
                  f'      <SrcRect xOff="0" yOff="0" {size}/>',
                  f'      <DstRect xOff="{window.col0 - grid.col0}" yOff="{window.row0 - grid.row0}" {size}/>',
                  f"      <NODATA>{nodata!r}</NODATA>",
                  "    </ComplexSource>"]
    lines += ["  </VRTRasterBand>", "</VRTDataset>"]
    with atomic_output(path, "w") as handle:
        handle.write("\n".join(lines) + "\n")


MOSAIC_NAME = "mosaic.vrt"
"""The VRT mosaic of --seamless -O's per-tile DEMs, in the output folder."""

SIDE_KINDS = ("slope", "aspect", "hillshade", "support")
"""The rasters on a DEM's grid besides it."""


def tile_targets(output, sides: dict) -> RasterTargets:
    """The rasters of one input's tile under --seamless -O: its DEM `output` (DIR/NAME.tif)
    and, for each side raster asked (sides: {kind: the option's path or None}),
    DIR/NAME.KIND.tif."""
    stem = Path(output).with_suffix("")
    return RasterTargets(dem=str(output), **{kind: f"{stem}.{kind}.tif" for kind, path in sides.items() if path})


def write_input_rasters(outputs, targets, windows, write, grid: RasterGrid, mosaics: dict,
                        crs: str | None) -> list[dict]:
    """--seamless -O's rasters, in memory and in tiles alike: for each input's DEM path in
    outputs, its RasterTargets (tile_targets) and its window of `grid` (None: no cell, no
    file), write(targets, window) -> that window's facts (write_blocks' or
    write_fit_rasters'); then the VRT mosaics (mosaics: {kind: path}, mosaic_paths).
    Returns the report's raster.tiles rows. On failure every file already written is
    removed."""
    written, tiles, created = [], [], []
    try:
        for output, target, window in zip(outputs, targets, windows):
            if window is None:
                tiles.append({"output": output, "written": False})
                continue
            facts = write(target, window)
            created += [path for _, path in target.items()]
            written.append((target, window))
            tiles.append({"output": output, "written": True, "files": facts["files"], "row0": window.row0,
                          "col0": window.col0, "width": window.width, "height": window.height,
                          "cells_with_data": facts["cells_with_data"]})
        for kind, path in mosaics.items():
            write_vrt(path, grid, [(getattr(t, kind), w) for t, w in written], kind, crs)
            created.append(path)
    except BaseException:
        for path in created:
            Path(path).unlink(missing_ok=True)
        raise
    return tiles


def mosaic_paths(outputs, sides: dict) -> dict:
    """The VRT mosaic of each raster kind under --seamless -O: the DEMs' DIR/MOSAIC_NAME, and
    for each side raster asked the .vrt path its option names (--slope out/slope.vrt)."""
    paths = {"dem": str(Path(outputs[0]).parent / MOSAIC_NAME)}
    paths.update({kind: str(path) for kind, path in sides.items() if path})
    return paths


# ------------------------------------------------------------------------ the fit's side
def targets_for(output, options) -> RasterTargets:
    """The rasters a fit writes: the DEM when `output` is a .tif, plus --slope/--aspect/
    --hillshade. InputError when they are asked for without a --resolution."""
    targets = RasterTargets(dem=str(output) if is_raster_path(output) else None,
                            slope=options.slope, aspect=options.aspect, hillshade=options.hillshade,
                            support=options.support)
    if targets.items() and options.resolution is None:
        raise InputError("GeoTIFF outputs (-o *.tif, --slope, --aspect, --hillshade, --support) need --resolution")
    if any(path for kind, path in targets.items() if kind != "dem") and targets.dem is None:
        raise InputError("--slope, --aspect, --hillshade and --support come with a DEM: give -o DEM.tif")
    for kind, path in targets.items():
        if not is_raster_path(path):
            raise InputError(f"the {kind} raster '{path}' must be a GeoTIFF (.tif or .tiff)")
    return targets


def raster_axis(axis):
    """The height axis for raster outputs: world z (a DEM is z over x, y)."""
    if isinstance(axis, str) and axis.strip().lower() in DEM_AXES:
        return "z"
    raise InputError(f"a DEM is heights over the world XY plane; --axis {axis} cannot be used "
                     "with GeoTIFF outputs (use --axis z or auto)")


SPACING_BLOCK = 1 << 16
"""Triangles per block of mean_spacing's twice-areas."""


def mean_spacing(points: np.ndarray, triangles: np.ndarray) -> float:
    """√(area of the triangulation / number of points): the mean point spacing. Each
    triangle's twice-area |u × v| (u, v its edges from its first corner) is formed in
    blocks of SPACING_BLOCK triangles into one (T,) array, then summed whole (numpy's
    pairwise sum): the bits of the one-pass expression, without its (T, 2) corner and
    edge copies (0.2 GB at 2M triangles, the DTM job's peak)."""
    twice = np.empty(triangles.shape[0])
    for start in range(0, triangles.shape[0], SPACING_BLOCK):
        a, b, c = (points[triangles[start:start + SPACING_BLOCK, k]] for k in range(3))
        u, v = b - a, c - a
        twice[start:start + SPACING_BLOCK] = np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
    area = 0.5 * twice.sum()
    return float(math.sqrt(area / points.shape[0]))


def fill_distance(value) -> float | None:
    """The DEM's fill distance D from --fill (FitOptions.fill): None for "off" or 0 (the
    trim's holes stay nodata), inf for "hull" (every cell inside the hull of the points),
    else a length D > 0 in the CRS's (the scan's) units. InputError for anything else."""
    if isinstance(value, str) and value.strip().lower() in FILL_WORDS:
        return math.inf if value.strip().lower() == "hull" else None
    try:
        distance = float(value)
    except (TypeError, ValueError):
        distance = math.nan
    if not (distance >= 0 and not math.isnan(distance)):
        raise InputError(f"--fill must be hull, off or a distance >= 0, got {value!r}")
    return None if distance == 0 else distance


def dem_sampling(interp, frame, resolution: float, data_xy=None, reach: float | None = None,
                 fill: FillRule | None = None, fit_xy=None) -> tuple[RasterGrid, SplineSampler]:
    """The grid of a fit's DEM (aligned at `resolution`, covering the triangulation in
    world x, y) and the sampler of the spline at its cell centres. data_xy (m, 2): the
    fitted points in the frame's plane (their cells always get a value within `reach`,
    the trim's max_edge: SplineSampler); None: the triangulation alone decides. The
    rasters (write_fit_rasters) and the fit's preview (preview.render_dem_fit) both take
    their cells from these, so they cover the same cells. fill: the FillRule of a DEM that
    spans the trim's holes (None: none); fit_xy (k, 2): the points the fit used, in the
    frame's plane (None: the interpolator's vertices), for the fill and the support layer."""
    if not np.allclose(frame.axes, np.eye(3)):
        raise InputError("raster outputs need the world z axis as height axis (--axis z)")
    lo, hi = bounds(interp.points)
    lo, hi = lo + frame.origin[:2], hi + frame.origin[:2]
    grid = RasterGrid.covering(lo, hi, resolution)
    return grid, SplineSampler(interp, frame.origin, data_xy, reach, fill, fit_xy, grid)


def write_fit_rasters(targets: RasterTargets, grid: RasterGrid, sampler: SplineSampler, options,
                      crs: str | None, smoothed: bool = False) -> dict:
    """Write the requested rasters of a fitted spline on its DEM grid (dem_sampling);
    returns the report's "raster" section. options.z_factor (None: 1) scales slope and
    hillshade; heights in units of their own without one are refused before
    (pipeline.check_angles). smoothed: the spline is a smoothing fit's (the slope
    method's crossover, choose_slope_method)."""
    check_angle_crs(crs, options)
    spacing = mean_spacing(sampler.interp.points, sampler.interp.triangles)
    method = choose_slope_method(options.slope_method, grid.resolution, spacing, smoothed)
    z_factor = 1.0 if options.z_factor is None else float(options.z_factor)
    report = write_rasters(targets, grid, sampler, method, crs, z_factor=z_factor)
    report["point_spacing"] = float(spacing)
    return report


def check_angle_crs(crs: str | None, options) -> None:
    """InputError for slope, aspect or hillshade rasters (options.slope, .aspect,
    .hillshade) of a geographic CRS: x, y in degrees are not in the units of z. The support
    is a distance, and needs no check."""
    if crs and (options.slope or options.aspect or options.hillshade):
        if describe(crs)["geographic"]:
            raise InputError("slope, aspect and hillshade need x, y in the units of z; the CRS is "
                             "geographic (degrees): reproject to a projected CRS first")
