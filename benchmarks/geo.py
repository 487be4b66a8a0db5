"""Terrain outputs: slope from the spline's gradient vs Horn / `gdaldem slope`, DEM speed,
GLB precision on a LiDAR tile.

Slope table: an analytic terrain (common.terrain_cloud, 100 m square, exact normals, or
normals tilted by random 3° errors as estimated normals are) is fitted to GeoTIFF DEMs at
resolutions of ¼ to 8 point spacings (spacing = √(area / N)); each slope raster is compared
with the analytic slope at the cell centres (RMS degrees, cells at least 5 m inside the
square). Contenders: the spline's analytic gradient (`--slope-method spline`), Horn's 3x3
differences of the same DEM computed by c1mesh (`--slope-method horn`), and `gdaldem slope`
(GDAL, Horn's method by default) on the same DEM file when gdal-bin is installed.

Speed: `c1mesh fit` of a 1M-point terrain to a DEM whose cell count equals the vertex count
of the level-2 mesh, against the level-2 mesh fit itself (both child processes, PLY out).

GLB: the autzen LiDAR ground (class 2) fitted to PLY and to GLB at level 2; the largest
distance between corresponding world positions.
"""
from __future__ import annotations

import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import (C1MESH, ROOT, Config, Section, fmt_s, fmt_x, median, report_from_stderr,
                               run_child, terrain_cloud, verdict, write_cloud_ply)
from c1mesh.geo.raster import AUTO_SPLINE_FROM_SMOOTHED

NOTE = ("Where both have values c1mesh's Horn equals `gdaldem slope` (same DEM file); at coarse resolutions their RMS differ because gdaldem leaves the cells next to nodata empty (not in its RMS), while c1mesh fills them with the spline's gradient. Bold: the better of spline and Horn. `--slope-method auto` takes Horn below 8 spacings and the spline from 8 on.")
SIDE = 100.0
"""Side of the analytic terrain square (m)."""
FACTORS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
MARGIN = 5.0


def analytic_slope(x, y):
    """Slope (degrees) of common.terrain_cloud's z = 3 sin(x/10) cos(y/15) + 0.02 x."""
    gx = 0.3 * np.cos(x / 10) * np.cos(y / 15) + 0.02
    gy = -0.2 * np.sin(x / 10) * np.sin(y / 15)
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def _noisy(normals: np.ndarray, degrees: float, seed: int = 5) -> np.ndarray:
    """Normals tilted by independent Gaussian angles of `degrees` RMS per component."""
    rng = np.random.default_rng(seed)
    tilted = normals + rng.normal(0.0, math.radians(degrees) / math.sqrt(2), normals.shape) * [1, 1, 0]
    return tilted / np.linalg.norm(tilted, axis=1)[:, None]


def _fit(src: Path, dem: Path, resolution: float, method: str, slope: Path) -> None:
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit
    fit(str(src), str(dem), FitOptions(smooth="off", axis="z", normals="file", resolution=resolution,
                                       slope=str(slope), slope_method=method), keep_mesh=False)


def _rms_error(path: Path) -> float:
    """RMS of (raster − analytic slope) over valid cells at least MARGIN inside the square."""
    import rasterio
    with rasterio.open(path) as ds:
        band = ds.read(1, masked=True)
        rows, cols = np.indices(band.shape)
        x, y = ds.transform @ (cols + 0.5, rows + 0.5)
    keep = ~np.ma.getmaskarray(band) & (x > MARGIN) & (x < SIDE - MARGIN) & (y > MARGIN) & (y < SIDE - MARGIN)
    err = band.data[keep].astype(float) - analytic_slope(x[keep], y[keep])
    return float(np.sqrt(np.mean(err * err)))


def slope_table(n: int, tmp: Path) -> list[dict]:
    """Rows {normals, factor, resolution, spline, horn, gdaldem} of RMS slope errors (deg)."""
    points, normals = terrain_cloud(n)
    spacing = SIDE / math.sqrt(n)
    gdaldem = shutil.which("gdaldem")
    rows = []
    for label, nrm in (("exact", normals), ("3° noise", _noisy(normals, 3.0))):
        src = tmp / f"terrain_{label[:5]}.ply"
        write_cloud_ply(src, points, nrm)
        for factor in FACTORS:
            res = factor * spacing
            row = {"normals": label, "factor": factor, "resolution": res}
            for method in ("spline", "horn"):
                dem, slope = tmp / f"dem_{method}.tif", tmp / f"slope_{method}.tif"
                _fit(src, dem, res, method, slope)
                row[method] = _rms_error(slope)
            row["gdaldem"] = None
            if gdaldem:
                out = tmp / "gdaldem_slope.tif"
                subprocess.run([gdaldem, "slope", "-q", str(tmp / "dem_spline.tif"), str(out)], check=True)
                row["gdaldem"] = _rms_error(out)
            rows.append(row)
    return rows


NOISE = 0.02
"""Height noise of the noisy-heights slope table (m RMS): LiDAR ground's."""


def noisy_heights_slope_table(n: int, tmp: Path, factors=(1.0, 2.0, 3.0, 4.0, 8.0)) -> list[dict]:
    """Rows {smooth, factor, resolution, spline, horn} of RMS slope errors (deg) of
    common.terrain_cloud's heights with NOISE Gaussian noise and no normals (an XYZ file:
    gradients fitted to the heights), fitted exactly, with --smooth auto (a vertex at every
    point) and at the default (no --smooth: issue 38's lattice at --spacing auto, so D is
    the resolution from 1 spacing on), each to a DEM and its slope by the spline's gradient
    and by Horn's differences of that DEM."""
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    points, _ = terrain_cloud(n)
    points = points + np.random.default_rng(11).normal(0.0, NOISE, points.shape) * [0, 0, 1]
    src = tmp / "terrain_noisy.xyz"
    np.savetxt(src, points, fmt="%.6f")
    spacing = SIDE / math.sqrt(n)
    rows = []
    for smooth in ("off", "auto", "default"):
        for factor in factors:
            row = {"smooth": smooth, "factor": factor, "resolution": factor * spacing}
            for method in ("spline", "horn"):
                dem, slope = tmp / f"dem_{method}.tif", tmp / f"slope_{method}.tif"
                fit(str(src), str(dem), FitOptions(axis="z", resolution=factor * spacing, slope=str(slope),
                                                   slope_method=method, smooth=smooth), keep_mesh=False)
                row[method] = _rms_error(slope)
            rows.append(row)
    return rows


def noisy_heights_lines(rows: list[dict], n: int) -> list[str]:
    """The markdown table of noisy_heights_slope_table's rows."""
    lines = [f"### Slope RMS error (degrees) from noisy heights: N = {n:,}, {NOISE * 100:g} cm noise, "
             "no normals", "",
             "| --smooth | resolution / spacing | resolution (m) | spline gradient | Horn (c1mesh) |",
             "|---|---:|---:|---:|---:|"]
    for r in rows:
        best = "spline" if r["spline"] <= r["horn"] else "horn"
        mark = {k: f"**{r[k]:.3f}**" if k == best else f"{r[k]:.3f}" for k in ("spline", "horn")}
        lines.append(f"| {r['smooth']} | {r['factor']:g} | {r['resolution']:.3f} | {mark['spline']} | "
                     f"{mark['horn']} |")
    return lines


def _speed(cfg: Config, tmp: Path, n: int) -> dict:
    """Child-run seconds of a level-2 mesh fit and of a DEM with as many cells as its vertices."""
    src = tmp / f"terrain_{n}.ply"
    write_cloud_ply(src, *terrain_cloud(n))
    exe = sys.executable
    mesh_cmd = [exe, *C1MESH, "fit", "--smooth", "off", str(src), "-o", str(tmp / "l2.ply"), "--level", "2",
                "--axis", "z", "--report", "-", "-q"]
    first = run_child(mesh_cmd)
    if first.returncode:
        raise RuntimeError(first.stderr[-600:])
    vertices = report_from_stderr(first.stderr)["output_mesh"]["vertices"]
    # cells over the square = vertices; the grid is aligned, so the count is close, not equal
    res = SIDE / math.sqrt(vertices)
    dem_cmd = [exe, *C1MESH, "fit", "--smooth", "off", str(src), "-o", str(tmp / "dem.tif"), "--resolution", repr(res),
               "--report", "-", "-q"]
    times = {"mesh": [], "dem": []}
    cells = 0
    for _ in range(cfg.reps):
        for name, cmd in (("mesh", mesh_cmd), ("dem", dem_cmd)):
            child = run_child(cmd)
            if child.returncode:
                raise RuntimeError(child.stderr[-600:])
            times[name].append(child.seconds)
            if name == "dem":
                cells = report_from_stderr(child.stderr)["raster"]["cells"]
    return {"vertices": vertices, "cells": cells, "resolution": res, **times}


def glb_vs_ply(tmp: Path, source: Path, level: int = 2) -> float:
    """Largest |world position difference| between the GLB and the PLY of one fit."""
    from c1mesh.formats import read_cloud
    from c1mesh.formats.meshes import read_glb_vertices
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit
    options = FitOptions(smooth="off", classes=(2,), level=level)
    fit(str(source), str(tmp / "tile.ply"), options, keep_mesh=False)
    fit(str(source), str(tmp / "tile.glb"), options, keep_mesh=False)
    ply = read_cloud(str(tmp / "tile.ply")).points
    glb = read_glb_vertices((tmp / "tile.glb").read_bytes())[0]
    return float(np.abs(glb - ply).max())


def lidar_rasters(tmp: Path, source: Path, resolution: float) -> dict:
    """Ground of a LiDAR tile to DEM + slope + hillshade; what rasterio and gdalinfo see."""
    import rasterio

    from c1mesh.formats import read_cloud
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit
    files = {k: tmp / f"lidar_{k}.tif" for k in ("dem", "slope", "hillshade")}
    report = fit(str(source), str(files["dem"]), FitOptions(smooth="off", classes=(2,), resolution=resolution,
                                                            slope=str(files["slope"]),
                                                            hillshade=str(files["hillshade"]))).report
    import pyproj
    same = all(pyproj.CRS(rasterio.open(f).crs.to_wkt()).equals(pyproj.CRS(read_cloud(str(source)).crs))
               for f in files.values())
    gdalinfo = shutil.which("gdalinfo")
    opened = None
    if gdalinfo:
        opened = all(subprocess.run([gdalinfo, str(f)], capture_output=True).returncode == 0
                     for f in files.values())
    return {"cells": report["raster"]["cells"], "with_data": report["raster"]["cells_with_data"],
            "method": report["raster"]["slope_method"], "same_crs": same, "gdalinfo": opened,
            "seconds": report["seconds"].get("raster", 0.0)}


def run(cfg: Config) -> Section:
    sec = Section("Geo: slope honesty, DEM speed, GLB precision")
    sec.add(__doc__.split("\n\n", 1)[1].strip().replace("\n", " "), "")
    n_slope = 1_000 if cfg.quick else 10_000
    n_speed = 20_000 if cfg.quick else 1_000_000
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        rows = slope_table(n_slope, tmp)
        sec.add(f"### Slope RMS error vs the analytic slope (degrees), N = {n_slope:,}, "
                f"spacing {SIDE / math.sqrt(n_slope):.2f} m", "",
                "| normals | resolution / spacing | resolution (m) | spline gradient | "
                "Horn (c1mesh) | gdaldem slope |", "|---|---:|---:|---:|---:|---:|")
        for r in rows:
            gd = "not installed" if r["gdaldem"] is None else f"{r['gdaldem']:.4f}"
            best = "spline" if r["spline"] <= r["horn"] else "horn"
            mark = {k: f"**{r[k]:.4f}**" if k == best else f"{r[k]:.4f}" for k in ("spline", "horn")}
            sec.add(f"| {r['normals']} | {r['factor']:g} | {r['resolution']:.3f} | {mark['spline']} | "
                    f"{mark['horn']} | {gd} |")
        sec.add("", NOTE)
        noisy = noisy_heights_slope_table(n_slope, tmp)
        sec.add("", *noisy_heights_lines(noisy, n_slope))
        for smooth in ("auto", "default"):
            coarse = [r for r in noisy if r["smooth"] == smooth and r["factor"] >= AUTO_SPLINE_FROM_SMOOTHED]
            wins = sum(r["spline"] < r["horn"] for r in coarse)
            sec.headlines.append((f"geo: noisy heights, --smooth {smooth}, spline slope better than Horn's from "
                                  f"{AUTO_SPLINE_FROM_SMOOTHED:g} spacings", f"{wins} of {len(coarse)} resolutions",
                                  "all (issue 38)", verdict(wins == len(coarse))))
        exact_fine = [r for r in rows if r["normals"] == "exact" and r["factor"] < 1]
        worst = max(r["spline"] for r in exact_fine)
        sec.headlines.append(("geo: slope RMS error, spline gradient, exact normals, res < spacing",
                              f"{worst:.3f}°", "≤ 1°", verdict(worst <= 1.0)))
        speed = _speed(cfg, tmp, n_speed)
        r = median(speed["dem"]) / median(speed["mesh"])
        sec.add("", f"### DEM speed, N = {n_speed:,}", "",
                f"Level-2 mesh: {speed['vertices']:,} vertices, {fmt_s(median(speed['mesh']))}; "
                f"DEM at {speed['resolution']:.4f} m: {speed['cells']:,} cells, "
                f"{fmt_s(median(speed['dem']))} (median of {cfg.reps} child runs each, interleaved). "
                f"DEM / mesh = {fmt_x(r)}.")
        sec.headlines.append((f"geo: DEM time / level-2 mesh time, N={n_speed:,}", fmt_x(r), "≤ 1.5×",
                              verdict(r <= 1.5)))
        tile = ROOT / "data_samples" / "4_6_crop.las"
        lidar = lidar_rasters(tmp, tile, 3.0)
        gd = {None: "gdalinfo not installed", True: "gdalinfo opens all three", False: "**gdalinfo fails**"}
        sec.add("", f"### {tile.name} ground (class 2) to a 3 ft DEM + slope + hillshade", "",
                f"{lidar['with_data']:,} of {lidar['cells']:,} cells with data, slope method "
                f"{lidar['method']}, rasters in {lidar['seconds']:.2f} s; CRS equal to the input's: "
                f"{'yes' if lidar['same_crs'] else '**no**'}; {gd[lidar['gdalinfo']]}.")
        tile = ROOT / "data_samples" / "autzen_trim.laz"
        diff = glb_vs_ply(tmp, tile)
        sec.add("", f"### GLB vs PLY, {tile.name} ground, level 2", "",
                f"Largest world-position difference: {diff:.2e} ft.")
        sec.headlines.append(("geo: GLB vs PLY world positions, autzen ground", f"{diff:.1e}",
                              "≤ 1e-4", verdict(diff <= 1e-4)))
    sec.add("")
    return sec


if __name__ == "__main__" and sys.argv[1:2] == ["noisy-slope"]:   # the noisy-heights table alone
    with tempfile.TemporaryDirectory() as name:
        print("\n".join(noisy_heights_lines(noisy_heights_slope_table(10_000, Path(name)), 10_000)))
elif __name__ == "__main__":   # python -m benchmarks.geo [--quick]: this section alone
    from benchmarks import report
    from benchmarks.common import Config as _Config
    out = Path(sys.argv[sys.argv.index("--out") + 1]) if "--out" in sys.argv else Path(tempfile.mkdtemp())
    section = run(_Config.make("--quick" in sys.argv, out))
    print("\n".join([f"## {section.title}", *section.body]))
    for h in section.headlines:
        print(" | ".join(h))
