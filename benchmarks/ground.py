"""Ground filters scored as the ISPRS filter test does (issue 39).

    python -m benchmarks.ground [--write]

Each filter classifies every point of a tile whose classes are stripped; the scores are
those of Sithole & Vosselman (2004): Type I (ground rejected, % of the true ground),
Type II (objects accepted as ground, % of the true objects), total error (% of all
points) and Cohen's kappa (%), against the truth:

- real tiles: the provider's class 2 in the classified LAS/LAZ files of
  /work/shared/data/real/ and data_samples/ (byte copies are scored once), converted to
  metres by the CRS's linear unit (c1mesh.core.crs.metres_per_unit: 4_6_crop is in US
  survey feet, autzen_trim in international feet). autzen_trim's class 2 is incomplete:
  66% of its class-1 points lie within 0.3 m (vertically) of the TIN of its class-2
  points, so those points are left out of its scores (issue 39);
- synthetic stand-ins for the tiles kept back for acceptance (c1mesh.testing.ground_scenes,
  seeded): steep wooded terrain of 26° median slope (seeds 0-2, and one with 15 cm of
  ground noise), and a crop that one flat 50 × 60 m roof fills with the ground in a 10 m
  strip beside it (roofs 7, 4 and 3 m high, with returns on the wall).

Filters, each with one parameter set for every tile:
  c1mesh ground        c1mesh.stages.ground.classify_ground at its defaults (what
                       `c1mesh ground` and the fit of an unclassified tile run);
  SMRF (PDAL defaults) the same module as plain SMRF (Pingel et al. 2013) at filters.smrf's
                       defaults: cell 1 m, slope 0.15, window 18 m, threshold 0.5 m,
                       scalar 1.25;
  CSF                  the authors' PyPI package cloth-simulation-filter (import CSF) at its
                       defaults (cloth resolution 1 m, rigidness 3, class threshold 0.5 m,
                       time step 0.65, 500 iterations, slope smoothing on), on the points
                       in metres; skipped when not installed.
Bars (issue 39): total error ≤ 3% on 4_6_crop, ≤ 8% on autzen_trim (scored as above),
≤ 5% with kappa ≥ 65% on the steep tile, ≤ 2% on the roof tile.

Reading the table: each peer fails one kind of tile, as issue 39 measured on the tiles it
keeps back. Plain SMRF keeps a roof that fills the crop (its 18 m window never fits
past the roof's edge, and beyond the crop there is no ground to see), and its slope of
0.15 cuts ridges on steep ground; CSF's rigid cloth cannot follow 26° slopes and rejects
much of the ground there (it holds the 7 m roof, not the 4 m and 3 m ones). c1mesh's
filter takes its roof handling from the raised segments and its steep-ground handling
from the slope-adaptive pass, with one parameter set. On autzen_trim most of its
remaining error is Type II: points 0.3-0.75 m above the provider's tight class-2 surface.
The kept-back PDAL tiles (steep, roof) are not in this table; the synthetic stand-ins are.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from benchmarks.common import ROOT, Section, write_section
from c1mesh.stages.ground import PDAL_SMRF, GroundParameters, classify_ground
from c1mesh.testing.ground_scenes import filter_scores, roof_scene, steep_scene

TITLE = "Ground filters: ISPRS scores against the provider's class 2 (issue 39)"
REAL = Path("/work/shared/data/real")
SAMPLES = ROOT / "data_samples"
BARS = {"4_6_crop.las": (3.0, None), "autzen_trim.laz": (8.0, None), "synthetic steep": (5.0, 65.0),
        "synthetic roof": (2.0, None)}
"""Issue 39's bars by tile (total error %, least kappa %); the synthetic ones apply to
every seed of their kind."""
MIN_DENSITY = 0.5
"""points per m²: sparser files (simple.copc.laz: 1,065 points over 15 km²) are listed, not scored."""
NEAR_GROUND = 0.3
"""metres: autzen_trim's class-1 points this close to its class-2 TIN are left out."""


@dataclass
class Tile:
    """points (n, 3) metres; ground (n,) bool truth; scored (n,) bool: the points scored."""

    name: str
    points: np.ndarray
    ground: np.ndarray
    scored: np.ndarray
    note: str = ""
    skipped: bool = False


def classified_files() -> list[Path]:
    """The classified LAS/LAZ files of REAL and data_samples, each content once."""
    import hashlib

    seen, files = set(), []
    for folder in (REAL, SAMPLES):
        for path in sorted(folder.glob("*.la[sz]")):
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
            if digest not in seen:
                seen.add(digest)
                files.append(path)
    return files


def real_tile(path: Path) -> Tile | None:
    """The tile of a LAS/LAZ file in metres with its class 2 as truth; None when it has no
    class 2 or nothing else."""
    import laspy

    from c1mesh.core.crs import las_crs, metres_per_unit

    las = laspy.read(str(path))
    xy_unit, z_unit, unit = metres_per_unit(las_crs(las.header))
    points = np.column_stack([np.asarray(las.x) * xy_unit, np.asarray(las.y) * xy_unit, np.asarray(las.z) * z_unit])
    ground = np.asarray(las.classification) == 2
    if ground.all() or not ground.any():
        return None
    scored, note = np.ones(len(points), bool), f"{unit}, {len(points):,} points"
    area = np.ptp(points[:, 0]) * np.ptp(points[:, 1])
    if len(points) < MIN_DENSITY * area:
        return Tile(path.name, points, ground, scored, f"{len(points):,} points over {area / 1e6:.3g} km²: "
                    f"under {MIN_DENSITY} points per m², not a ground-filter tile", skipped=True)
    if path.name.startswith("autzen_trim"):
        near = ~ground & (np.abs(points[:, 2] - _class2_surface(points, ground)) <= NEAR_GROUND)
        scored = ~near
        note += (f"; {near.sum():,} class-1 points ({100 * near.sum() / (~ground).sum():.0f}% of class 1) "
                 f"within {NEAR_GROUND} m of the class-2 TIN left out")
    return Tile(path.name, points, ground, scored, note)


def _class2_surface(points: np.ndarray, ground: np.ndarray) -> np.ndarray:
    """(n,) the height of the TIN of the class-2 points at every point (NaN outside its hull)."""
    from scipy.interpolate import LinearNDInterpolator

    return LinearNDInterpolator(points[ground, :2], points[ground, 2])(points[:, :2])


def synthetic_tiles() -> list[Tile]:
    scenes = [steep_scene(seed=seed) for seed in (0, 1, 2)] + [steep_scene(seed=3, noise=0.15)]
    notes = ["seed 0", "seed 1", "seed 2", "seed 3, 15 cm ground noise"]
    scenes += [roof_scene(seed=0), roof_scene(seed=1, roof_height=4.0), roof_scene(seed=2, roof_height=3.0)]
    notes += ["roof 7 m high", "roof 4 m high", "roof 3 m high"]
    return [Tile(scene.name, scene.points, scene.ground, np.ones(len(scene.points), bool),
                 f"{note}, {len(scene.points):,} points") for scene, note in zip(scenes, notes)]


def csf_ground(points: np.ndarray) -> np.ndarray:
    """(n,) bool: CSF's ground at the package's defaults, run in a temporary directory with
    the cloth export off and its progress lines (C++ stdout) silenced."""
    import CSF

    csf = CSF.CSF()
    csf.setPointCloud(np.ascontiguousarray(points, dtype=np.float64))
    ground, rest = CSF.VecInt(), CSF.VecInt()
    with tempfile.TemporaryDirectory() as folder, _silenced(), _cwd(folder):
        csf.do_filtering(ground, rest, exportCloth=False)
    found = np.zeros(len(points), bool)
    found[np.asarray(list(ground), dtype=np.int64)] = True
    return found


@contextlib.contextmanager
def _cwd(folder: str):
    previous = os.getcwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(previous)


@contextlib.contextmanager
def _silenced():
    """File descriptor 1 to /dev/null (a C++ library's progress lines)."""
    sys.stdout.flush()
    saved = os.dup(1)
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


def filters() -> dict[str, Callable[[np.ndarray], np.ndarray] | str]:
    """Name → classifier of (n, 3) metres, or the reason it is skipped."""
    table: dict = {"c1mesh ground": lambda p: classify_ground(p),
                   "SMRF (PDAL defaults)": lambda p: classify_ground(p, params=GroundParameters(**PDAL_SMRF))}
    try:
        import CSF  # noqa: F401
        table["CSF (package defaults)"] = csf_ground
    except ImportError:
        table["CSF (package defaults)"] = "not installed: pip install cloth-simulation-filter"
    return table


def verdict(tile: Tile, total: float, kappa: float) -> str:
    bar = BARS.get(tile.name)
    if bar is None:
        return ""
    ok = total <= bar[0] and (bar[1] is None or kappa >= bar[1])
    return ("pass" if ok else "FAIL") + f" (≤ {bar[0]:g}%" + (f", κ ≥ {bar[1]:g}%)" if bar[1] else ")")


def rows(tiles: list[Tile], log=print) -> list[str]:
    """The markdown table: one row per tile and filter."""
    lines = ["| tile | filter | Type I % | Type II % | total % | kappa % | scored points | s | bar |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|"]
    for tile in tiles:
        if tile.skipped:
            lines.append(f"| {tile.name} | — | — | — | — | — | — | — | not scored: {tile.note} |")
            continue
        for name, classify in filters().items():
            if isinstance(classify, str):
                lines.append(f"| {tile.name} | {name} | — | — | — | — | — | — | {classify} |")
                continue
            start = time.perf_counter()
            found = classify(tile.points)
            seconds = time.perf_counter() - start
            s = filter_scores(tile.ground[tile.scored], found[tile.scored])
            mine = verdict(tile, s.total, s.kappa) if name == "c1mesh ground" else ""
            lines.append(f"| {tile.name} ({tile.note.split(',')[0]}) | {name} | {s.type_1:.2f} | {s.type_2:.2f} | "
                         f"{s.total:.2f} | {s.kappa:.1f} | {s.points:,} | {seconds:.2f} | {mine} |")
            log(lines[-1])
    return lines


def dtm_rows(tiles: list[Tile], log=print) -> list[str]:
    """The DTM comparison: a 1 m DEM (c1mesh fit, in memory) of the filter's ground against
    the DEM of the true ground (class 2, or the synthetic truth), |difference| over the
    cells both have, in metres."""
    lines = ["| tile | cells compared | mean abs. Δ (m) | 95th percentile (m) | max (m) |", "|---|---:|---:|---:|---:|"]
    for tile in tiles:
        if tile.skipped or tile.name == "synthetic roof":
            continue
        found = classify_ground(tile.points)
        with tempfile.TemporaryDirectory() as folder:
            gap = _dem_gaps(_dem(tile.points[found], Path(folder) / "filter.tif"),
                            _dem(tile.points[tile.ground], Path(folder) / "truth.tif"))
        lines.append(f"| {tile.name} ({tile.note.split(',')[0]}) | {gap.size:,} | {gap.mean():.3f} | "
                     f"{np.percentile(gap, 95):.3f} | {gap.max():.2f} |")
        log(lines[-1])
    return lines


def _dem(points: np.ndarray, path: Path) -> tuple[np.ma.MaskedArray, int, int]:
    """(heights, west, north) of the 1 m DEM that `c1mesh fit ... -o DEM.tif --resolution 1`
    makes of points in metres (a PointCloud, every other option at its default): its
    west and north edges are whole metres, so two DEMs of one tile share their grid."""
    import rasterio

    from c1mesh.core.cloud import PointCloud
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    fit(PointCloud(points=points), path, FitOptions(smooth="off", resolution=1.0, axis="z"))
    with rasterio.open(path) as raster:
        return raster.read(1, masked=True), int(round(raster.transform.c)), int(round(raster.transform.f))


def _dem_gaps(first, second) -> np.ndarray:
    """|first − second| over the cells both DEMs ((heights, west, north)) have data."""
    (a, west_a, north_a), (b, west_b, north_b) = first, second
    west, north = max(west_a, west_b), min(north_a, north_b)
    east = min(west_a + a.shape[1], west_b + b.shape[1])
    south = max(north_a - a.shape[0], north_b - b.shape[0])
    if east <= west or north <= south:
        return np.zeros(0)
    cut = lambda d, w, n: d[n - north:n - south, west - w:east - w]  # noqa: E731
    gap = np.abs(cut(a, west_a, north_a) - cut(b, west_b, north_b))
    return gap.compressed()


def section(command: str, log=print) -> Section:
    from benchmarks.report import machine

    tiles = [tile for path in classified_files() if (tile := real_tile(path)) is not None] + synthetic_tiles()
    sec = Section(TITLE)
    sec.add(f"Reproduce: `{command}`.", "", *machine(), "", __doc__.split("\n\n", 2)[2].strip(), "",
            "Tiles: " + "; ".join(f"{t.name}: {t.note}" for t in tiles if not t.name.startswith("synthetic")) + ".",
            "", *rows(tiles, log), "",
            "The DTM check of issue 39 (its steep tile's DTM from the stripped classes within 0.2 m, 95th "
            "percentile, of the DTM from the provider's class 2): 1 m DEMs made by c1mesh's fit (in memory, "
            "defaults) of the filter's ground and of the true ground, compared where both have data:", "",
            *dtm_rows(tiles, log), "")
    return sec


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.ground", description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", action="store_true", help=f"replace the '{TITLE}' section of benchmarks/RESULTS.md")
    args = parser.parse_args(argv)
    command = " ".join(["python -m benchmarks.ground", *(sys.argv[1:] if argv is None else argv)])
    sec = section(command)
    if args.write:
        write_section(ROOT / "benchmarks" / "RESULTS.md", sec)
        print(f"[ground] wrote the '{TITLE}' section of benchmarks/RESULTS.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
