"""GeoTIFF rasters from the C1 surface: DEM, slope, aspect and hillshade on one grid.

The grid is aligned to multiples of the resolution R in world coordinates (x to the east,
y to the north, z up: the surface must be a height field over the world XY plane, so the
fit uses --axis z). Each cell holds the spline at the cell centre; cells whose centre lies
outside the trimmed triangulation are nodata. Slope, aspect and hillshade come from a
gradient at each cell centre: the spline's own analytic gradient ("spline"), or Horn's
3x3 differences of the DEM ("horn", what `gdaldem slope` computes), chosen per resolution
by "auto" (see AUTO_SPLINE_FROM). The rasters are computed and written in blocks of rows, so
memory holds a few blocks, not the grid.

Units: slope in degrees from horizontal (0-90); aspect in degrees clockwise from north of
the downhill direction (0-360, GDAL's convention; 0 where the surface is exactly flat);
hillshade 1-255 (uint8, 0 = nodata) for a light from azimuth 315°, altitude 45°, like
`gdaldem hillshade`. Slope and aspect assume that x, y and z share one length unit.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from c1mesh import rsd
from c1mesh.errors import DependencyError, InputError

RASTER_SUFFIXES = (".tif", ".tiff")
DEM_NODATA = -9999.0
HILLSHADE_NODATA = 0
BLOCK_ROWS = 256
"""Rows computed and written at a time (also the GeoTIFF tile size)."""
SLOPE_METHODS = ("auto", "spline", "horn")
AUTO_SPLINE_FROM = 8.0
"""`auto` uses the spline's gradient at resolutions of at least this many point spacings
(√(area / points)) and Horn's differences of the DEM below. From the slope table in
benchmarks/RESULTS.md (section geo): the sextic's gradient follows every error of the
input normals (it interpolates them) and is only O(h) between points, so Horn's 3x3
average of the spline's heights is closer to the true slope up to about 4 spacings with
exact normals and 8 spacings with 3° normal noise; beyond that Horn's own truncation
error (O(R²)) dominates and the spline gradient wins."""
LIGHT_AZIMUTH, LIGHT_ALTITUDE = 315.0, 45.0


def is_raster_path(path) -> bool:
    """True when `path` names a GeoTIFF output (.tif/.tiff)."""
    return isinstance(path, (str, Path)) and Path(path).suffix.lower() in RASTER_SUFFIXES


def _rasterio():
    try:
        import rasterio
    except ImportError as exc:
        raise DependencyError('Writing GeoTIFF needs rasterio: pip install "rasterio>=1.3".') from exc
    return rasterio


# ---------------------------------------------------------------------------------- grid
@dataclass(frozen=True)
class RasterGrid:
    """A north-up grid: column j, row i has its centre at (west + (j + ½)R, north − (i + ½)R).

    west and north are multiples of the resolution R (world units), so grids of different
    tiles at the same R line up cell for cell.
    """

    west: float
    north: float
    resolution: float
    width: int
    height: int

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
        return Affine(self.resolution, 0.0, self.west, 0.0, -self.resolution, self.north)

    def centres(self, rows: range, origin=(0.0, 0.0), halo: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates minus `origin` for `rows` (and `halo` extra cells on every
        side): x (ncols,), y (nrows,), computed from the grid's corner so large world
        coordinates cancel exactly against the origin before the offsets are added."""
        r = self.resolution
        cols = np.arange(-halo, self.width + halo) + 0.5
        lines = np.arange(rows.start - halo, rows.stop + halo) + 0.5
        return (self.west - origin[0]) + cols * r, (self.north - origin[1]) - lines * r


# ------------------------------------------------------------------------------- sampling
class SplineSampler:
    """Values and analytic gradients of a fitted spline at world points of a height field.

    interp: the RSDInterpolator in the scan frame; origin: (3,) the frame's origin. The
    frame's axes must be the world axes (--axis z), so that local = world − origin and
    the local gradient is the world gradient dz/dx, dz/dy.
    """

    def __init__(self, interp, origin):
        self.interp = interp
        self.origin = np.asarray(origin, dtype=np.float64)

    def sample(self, x: np.ndarray, y: np.ndarray, gradients: bool = True):
        """Spline at the grid x (ncols,) × y (nrows,) given in local (origin-subtracted)
        coordinates: heights (nrows, ncols) in world z and gradients (nrows, ncols, 2),
        NaN outside the mesh. Each point is located once for both."""
        xx, yy = np.meshgrid(x, y)
        xy = np.column_stack([xx.ravel(), yy.ravel()])
        _, tri, lam, _ = self.interp._locate(xy)
        inside = np.flatnonzero(tri >= 0)
        z = np.full(xy.shape[0], np.nan)
        g = np.full((xy.shape[0], 2), np.nan) if gradients else None
        if inside.size:
            t = tri[inside]
            C = self.interp.coefficients[t]
            z[inside] = rsd.values_at(self.interp.scheme, C, lam[inside]) + self.origin[2]
            if gradients:
                g[inside] = rsd.gradients_at(self.interp.scheme, C, self.interp._G[t], lam[inside])
        shape = (y.size, x.size)
        return z.reshape(shape), (None if g is None else g.reshape(shape + (2,)))


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


def slope_degrees(gradient: np.ndarray) -> np.ndarray:
    """Slope from horizontal in degrees, from gradients (..., 2)."""
    return np.degrees(np.arctan(np.hypot(gradient[..., 0], gradient[..., 1])))


def aspect_degrees(gradient: np.ndarray) -> np.ndarray:
    """Azimuth of the downhill direction, degrees clockwise from north in [0, 360)."""
    return np.mod(np.degrees(np.arctan2(-gradient[..., 0], -gradient[..., 1])), 360.0)


def hillshade(gradient: np.ndarray, azimuth: float = LIGHT_AZIMUTH,
              altitude: float = LIGHT_ALTITUDE) -> np.ndarray:
    """Lambertian shade in [0, 1] of the unit normal (−gx, −gy, 1)/‖·‖ for a light from
    `azimuth` (degrees clockwise from north) and `altitude` (degrees above the horizon)."""
    az, alt = math.radians(azimuth), math.radians(altitude)
    light = (math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt))
    gx, gy = gradient[..., 0], gradient[..., 1]
    shade = (-gx * light[0] - gy * light[1] + light[2]) / np.sqrt(gx * gx + gy * gy + 1.0)
    return np.clip(shade, 0.0, 1.0)


def choose_slope_method(method: str, resolution: float, spacing: float) -> str:
    """'spline' or 'horn' for a requested method at a resolution and point spacing."""
    if method not in SLOPE_METHODS:
        raise InputError(f"slope method must be one of {', '.join(SLOPE_METHODS)}, got {method!r}")
    if method != "auto":
        return method
    return "spline" if resolution >= AUTO_SPLINE_FROM * spacing else "horn"


# ------------------------------------------------------------------------------- writing
@dataclass
class RasterTargets:
    """Where each raster goes (None = not written)."""

    dem: str | None = None
    slope: str | None = None
    aspect: str | None = None
    hillshade: str | None = None

    def items(self):
        return [(k, v) for k, v in vars(self).items() if v is not None]


def grid_blocks(grid: RasterGrid, sampler: SplineSampler, method: str,
                block_rows: int = BLOCK_ROWS) -> Iterator[tuple[range, np.ndarray, np.ndarray]]:
    """(rows, heights (n, w), gradients (n, w, 2)) for consecutive blocks of grid rows.

    method "spline": the spline's gradient at each centre; "horn": Horn's differences of
    the sampled heights (one extra cell around the block), the spline's gradient where a
    neighbour is nodata (at the edges of the mesh).
    """
    for start in range(0, grid.height, block_rows):
        rows = range(start, min(start + block_rows, grid.height))
        if method == "spline":
            x, y = grid.centres(rows, sampler.origin)
            z, g = sampler.sample(x, y)
        else:
            x, y = grid.centres(rows, sampler.origin, halo=1)
            zh, gh = sampler.sample(x, y)
            z, g = zh[1:-1, 1:-1], gh[1:-1, 1:-1]
            horn = horn_gradient(zh, grid.resolution)
            ok = np.isfinite(horn).all(axis=2)
            g = np.where(ok[..., None], horn, g)
        yield rows, z, g


def _profile(grid: RasterGrid, dtype: str, nodata, crs: str | None) -> dict:
    profile = {"driver": "GTiff", "width": grid.width, "height": grid.height, "count": 1,
               "dtype": dtype, "nodata": nodata, "transform": grid.transform,
               "compress": "deflate", "tiled": True, "blockxsize": BLOCK_ROWS,
               "blockysize": BLOCK_ROWS, "BIGTIFF": "IF_SAFER"}
    if dtype.startswith("float"):
        profile["predictor"] = 3   # floating-point predictor: deflate packs DEMs much better
    if crs:
        profile["crs"] = crs
    return profile


_KINDS = {"dem": ("float32", DEM_NODATA), "slope": ("float32", DEM_NODATA),
          "aspect": ("float32", DEM_NODATA), "hillshade": ("uint8", HILLSHADE_NODATA)}


def _layer(kind: str, z: np.ndarray, g: np.ndarray) -> np.ndarray:
    """The values of raster `kind` for one block, nodata filled in."""
    outside = ~np.isfinite(z)
    if kind == "dem":
        return np.where(outside, DEM_NODATA, z)
    elif kind == "slope":
        out = slope_degrees(g)
    elif kind == "aspect":
        out = aspect_degrees(g)
    else:
        shade = np.rint(1.0 + 254.0 * hillshade(np.nan_to_num(g)))
        return np.where(outside, HILLSHADE_NODATA, shade).astype(np.uint8)
    return np.where(outside, DEM_NODATA, out).astype(np.float32)


def write_rasters(targets: RasterTargets, grid: RasterGrid, sampler: SplineSampler,
                  method: str = "spline", crs: str | None = None,
                  block_rows: int = BLOCK_ROWS, dem_dtype: str = "float32") -> dict:
    """Write the requested rasters in one pass over the grid; returns a report dict.

    dem_dtype "float64" keeps every digit of the spline's heights (GIS tools expect
    float32, the default, which rounds heights of 1e4 to ~1e-3).

    Every file is written to a temporary file and renamed into place only when all of them
    are complete (formats.atomic_output), with overviews (2x, 4x, ... averaged) added.
    """
    rasterio = _rasterio()
    from c1mesh.formats import atomic_output

    items = targets.items()
    if not items:
        return {}
    cells_inside = 0
    with contextlib.ExitStack() as stack:
        temps = {kind: stack.enter_context(atomic_output(path, "path")) for kind, path in items}
        kinds = dict(_KINDS, dem=(dem_dtype, DEM_NODATA))
        datasets = {kind: stack.enter_context(rasterio.open(temps[kind], "w", **_profile(
            grid, *kinds[kind], crs))) for kind, _ in items}
        for rows, z, g in grid_blocks(grid, sampler, method, block_rows):
            cells_inside += int(np.isfinite(z).sum())
            window = rasterio.windows.Window(0, rows.start, grid.width, len(rows))
            for kind, ds in datasets.items():
                ds.write(_layer(kind, z, g).astype(kinds[kind][0], copy=False), 1, window=window)
        for kind, ds in datasets.items():
            _build_overviews(ds, grid, kind)
            ds.close()
    return {"grid": {"west": grid.west, "north": grid.north, "resolution": grid.resolution,
                     "width": grid.width, "height": grid.height},
            "cells": grid.width * grid.height, "cells_with_data": cells_inside,
            "slope_method": method, "files": dict(items)}


def _build_overviews(ds, grid: RasterGrid, kind: str) -> None:
    """2x, 4x, ... overviews down to about one tile (averaged; nearest for hillshade)."""
    from rasterio.enums import Resampling

    factors, factor = [], 2
    while max(grid.width, grid.height) / factor >= BLOCK_ROWS / 2 and factor <= 1024:
        factors.append(factor)
        factor *= 2
    if factors:
        ds.build_overviews(factors, Resampling.nearest if kind == "hillshade" else Resampling.average)


# ------------------------------------------------------------------------ the fit's side
def targets_for(output, options) -> RasterTargets:
    """The rasters a fit writes: the DEM when `output` is a .tif, plus --slope/--aspect/
    --hillshade. InputError when they are asked for without a --resolution."""
    targets = RasterTargets(dem=str(output) if is_raster_path(output) else None,
                            slope=options.slope, aspect=options.aspect, hillshade=options.hillshade)
    if targets.items() and options.resolution is None:
        raise InputError("GeoTIFF outputs (-o *.tif, --slope, --aspect, --hillshade) need --resolution")
    if (options.slope or options.aspect or options.hillshade) and targets.dem is None:
        raise InputError("--slope, --aspect and --hillshade come with a DEM: give -o DEM.tif")
    for kind, path in targets.items():
        if not is_raster_path(path):
            raise InputError(f"the {kind} raster '{path}' must be a GeoTIFF (.tif or .tiff)")
    return targets


def raster_axis(axis):
    """The height axis for raster outputs: world z (a DEM is z over x, y)."""
    if isinstance(axis, str) and axis.strip().lower() in ("auto", "z", "+z"):
        return "z"
    raise InputError(f"a DEM is heights over the world XY plane; --axis {axis} cannot be used "
                     "with GeoTIFF outputs (use --axis z or auto)")


def mean_spacing(points: np.ndarray, triangles: np.ndarray) -> float:
    """√(area of the triangulation / number of points): the mean point spacing."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    u, v = b - a, c - a
    area = 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).sum()
    return float(math.sqrt(area / points.shape[0]))


def write_fit_rasters(targets: RasterTargets, interp, frame, options, crs: str | None) -> dict:
    """Sample a fitted spline onto the aligned grid covering its triangulation and write
    the requested rasters; returns the report's "raster" section."""
    if not np.allclose(frame.axes, np.eye(3)):
        raise InputError("raster outputs need the world z axis as height axis (--axis z)")
    if crs and (options.slope or options.aspect or options.hillshade):
        from c1mesh.crs import describe
        if describe(crs)["geographic"]:
            raise InputError("slope, aspect and hillshade need x, y in the units of z; the CRS is "
                             "geographic (degrees): reproject to a projected CRS first")
    lo = interp.points.min(axis=0) + frame.origin[:2]
    hi = interp.points.max(axis=0) + frame.origin[:2]
    grid = RasterGrid.covering(lo, hi, options.resolution)
    spacing = mean_spacing(interp.points, interp.triangles)
    method = choose_slope_method(options.slope_method, grid.resolution, spacing)
    report = write_rasters(targets, grid, SplineSampler(interp, frame.origin), method, crs)
    report["point_spacing"] = float(spacing)
    return report
