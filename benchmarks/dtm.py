"""The whole DTM job against GMT: a 1M-point LAZ to a 1 m DEM (issue 38).

    python -m benchmarks.dtm make FOLDER              # FOLDER/dtm.laz and FOLDER/dtm.bin
    python -m benchmarks.dtm run FOLDER [--reps 3] [--spacings 1 2] [--no-delaunay] [--write]

The survey is issue 38's (and the floor job's kind): 1,000,000 points uniform over a
1000 × 1000 m square, z = 100 + 30 sin(x/97) cos(y/131) + 2 cm Gaussian noise, all class
2, stored at millimetre scale. dtm.bin holds the same points, as the LAZ stores them, as
binary doubles x y z: the GMT side reads those.

Contenders, each a child process timed from start to exit with its own peak RSS (and its
children's: GMT is two commands under one shell); one round runs each once, back to back,
and the table shows medians over the rounds:
- `c1mesh fit dtm.laz -o DIR/default.tif --resolution 1`, the job as a user runs it: the
  default, here the lattice at `--spacing auto` (the points' mean spacing, 1 m);
- `c1mesh fit dtm.laz -o DIR/smooth.tif --resolution 1 --smooth auto`, the smoothing fit with
  a vertex at every point (not with run's --no-delaunay: 70-80 s a round);
- the same with `--smooth off`, the exact interpolant;
- with `--spacing D` (run's --spacings, none by default): `--smooth auto` on the nodes of a
  D × D lattice over the points, fitted to every point and solved by multigrid (the lattice
  route of issue 38, docs/smoothing.md);
- GMT: `gmt blockmedian -R0/1000/0/1000 -I1 -bi3d -bo3d dtm.bin > bm.bin` then
  `gmt surface bm.bin -bi3d -R0/1000/0/1000 -I1 -T0.25 -Gs.nc`, GMT's own recipe for a
  DEM from scattered points (blockmedian first, as its documentation asks). Skipped and
  said so when `gmt` is absent (benchmarks/install-peers.sh installs it).

Accuracy: the RMS of each DEM against the true (noise-free) heights at its own cells,
over the cells whose centre lies in [10, 990]² (GMT extrapolates to the border and c1mesh
stops at the hull, so the rim is left out of both). GMT's grid is read with
`gmt grd2xyz` after the clock stops. Thread counts: c1mesh at its default (every core,
shown in the table's header), GMT as installed (its `surface` is single-threaded).
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import C1MESH, Section, fmt_bytes, run_child, show_section

N = 1_000_000
SIDE = 1000.0
NOISE = 0.02
REGION = f"-R0/{SIDE:g}/0/{SIDE:g}"
MARGIN = 10.0
TITLE = "DTM job: a 1M-point LAZ to a 1 m DEM, c1mesh against GMT (issue 38)"


def true_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Issue 38's terrain (metres): 100 + 30 sin(x/97) cos(y/131)."""
    return 100.0 + 30.0 * np.sin(x / 97.0) * np.cos(y / 131.0)


def make(folder: Path, n: int = N, seed: int = 0) -> None:
    """FOLDER/dtm.laz (n points, class 2, mm scale) and FOLDER/dtm.bin (the LAZ's
    coordinates as stored, binary little-endian doubles x y z)."""
    import laspy

    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, SIDE, n), rng.uniform(0, SIDE, n)
    z = true_height(x, y) + rng.normal(0, NOISE, n)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [0, 0, 0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, z
    las.classification = np.full(n, 2, np.uint8)
    folder.mkdir(parents=True, exist_ok=True)
    las.write(folder / "dtm.laz")
    stored = laspy.read(folder / "dtm.laz")
    xyz = np.column_stack([stored.x, stored.y, stored.z]).astype("<f8")
    (folder / "dtm.bin").write_bytes(xyz.tobytes())


def gmt_status() -> str:
    """'' when the `gmt` binary is on PATH, else why the GMT rows are skipped."""
    return "" if shutil.which("gmt") else "gmt not found on PATH (benchmarks/install-peers.sh installs it)"


def c1mesh_run(folder: Path, smooth: str | None, spacing: float | None = None) -> tuple[float, int, Path]:
    """(seconds, peak RSS, DEM path) of one `c1mesh fit` to a 1 m DEM (with --smooth and
    --spacing when they are given; smooth None: the default)."""
    name = smooth or "default"
    dem = folder / (f"{name}.tif" if spacing is None else f"{name}-spacing{spacing:g}.tif")
    thin = [] if spacing is None else ["--spacing", f"{spacing:g}"]
    given = [] if smooth is None else ["--smooth", smooth]
    done = run_child([sys.executable, *C1MESH, "fit", str(folder / "dtm.laz"), "-o", str(dem),
                      "--resolution", "1", *given, *thin])
    if done.returncode:
        raise RuntimeError(f"c1mesh fit --smooth {smooth} {' '.join(thin)} failed: {done.stderr.strip()[-400:]}")
    return done.seconds, done.peak_rss, dem


def gmt_run(folder: Path) -> tuple[float, int, Path]:
    """(seconds, peak RSS, grid path) of blockmedian + surface, both under one shell."""
    grid = folder / "gmt.nc"
    script = (f"cd '{folder}' && "                  # GMT leaves a gmt.history where it runs
              f"gmt blockmedian {REGION} -I1 -bi3d -bo3d dtm.bin > bm.bin && "
              f"gmt surface bm.bin -bi3d {REGION} -I1 -T0.25 -G'{grid.name}'")
    done = run_child(["sh", "-c", script])
    if done.returncode:
        raise RuntimeError(f"GMT failed: {done.stderr.strip()[-400:]}")
    return done.seconds, done.peak_rss, grid


def dem_rms(path: Path) -> float:
    """RMS (m) of a c1mesh GeoTIFF DEM against true_height at its cell centres in the margin."""
    import rasterio

    with rasterio.open(path) as src:
        z = src.read(1, masked=True)
        cols, rows = np.meshgrid(np.arange(src.width), np.arange(src.height))
        t = src.transform
        x, y = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e      # north-up: b = d = 0
    return _rms(np.asarray(x), np.asarray(y), np.ma.filled(z.astype(float), np.nan))


def gmt_rms(path: Path) -> float:
    """RMS (m) of GMT's grid against true_height at its nodes in the margin."""
    with tempfile.TemporaryDirectory(prefix="c1mesh-dtm-") as tmp:
        out = Path(tmp) / "grid.bin"
        with out.open("wb") as handle:
            subprocess.run(["gmt", "grd2xyz", str(path), "-bo3d"], stdout=handle, check=True, cwd=tmp)
        xyz = np.fromfile(out, dtype="<f8").reshape(-1, 3)
    return _rms(xyz[:, 0], xyz[:, 1], xyz[:, 2])


def _rms(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> float:
    inside = (x >= MARGIN) & (x <= SIDE - MARGIN) & (y >= MARGIN) & (y <= SIDE - MARGIN) & np.isfinite(z)
    error = z[inside] - true_height(x[inside], y[inside])
    return float(np.sqrt(np.mean(error ** 2)))


def run(folder: Path, reps: int, spacings: tuple[float, ...] = (), delaunay: bool = True) -> Section:
    """The contenders, reps rounds; in a round every c1mesh run is followed by a GMT run,
    and its × GMT is its time over that run's (the machine may be shared: the pair ran
    under the same load); the table shows medians. The section for RESULTS.md."""
    jobs = [("the default (no --smooth)", lambda: c1mesh_run(folder, None))]
    if delaunay:
        jobs.append(("--smooth auto", lambda: c1mesh_run(folder, "auto")))
    jobs.append(("--smooth off", lambda: c1mesh_run(folder, "off")))
    jobs += [(f"--smooth auto --spacing {d:g}", lambda d=d: c1mesh_run(folder, "auto", d)) for d in spacings]
    runs: dict[str, list[tuple[float, int]]] = {name: [] for name, _ in jobs}
    runs["GMT"] = []
    ratios: dict[str, list[float]] = {name: [] for name, _ in jobs}
    outputs: dict[str, Path] = {}
    skipped = gmt_status()
    for _ in range(reps):
        for name, job in jobs:
            seconds, rss, outputs[name] = job()
            runs[name].append((seconds, rss))
            print(f"[dtm] {name}: {seconds:.2f} s, {fmt_bytes(rss)}", file=sys.stderr)
            if skipped:
                continue
            gmt_seconds, gmt_rss, outputs["GMT"] = gmt_run(folder)
            runs["GMT"].append((gmt_seconds, gmt_rss))
            ratios[name].append(seconds / gmt_seconds)
            print(f"[dtm] GMT: {gmt_seconds:.2f} s, {fmt_bytes(gmt_rss)} ({seconds / gmt_seconds:.1f}×)",
                  file=sys.stderr)
    rms = {name: (gmt_rms(path) if name == "GMT" else dem_rms(path)) for name, path in outputs.items()}
    command = f"python -m benchmarks.dtm run DIR --reps {reps}" + \
        (" --spacings " + " ".join(f"{d:g}" for d in spacings) if spacings else "") + \
        ("" if delaunay else " --no-delaunay")
    return _section(runs, ratios, rms, skipped, command, reps)


def _section(runs, ratios, rms, skipped: str, command: str, reps: int) -> Section:
    sec = Section(TITLE)
    sec.add(f"`{command}`: medians of {reps} rounds, one machine, "
            f"c1mesh at its default threads ({os.cpu_count()} cores), GMT `surface` single-threaded; "
            "every c1mesh run is followed by a GMT run, and × GMT is the median of the pairs' ratios. "
            "RMS against the noise-free heights over the cells in [10, 990]² m.", "",
            "| run | time | × GMT | peak memory | RMS against the true heights |",
            "|---|---|---|---|---|")
    for name, samples in runs.items():
        if not samples:
            continue
        seconds = statistics.median(s for s, _ in samples)
        peak = statistics.median(r for _, r in samples)
        times = "1.0×" if name == "GMT" else (f"{statistics.median(ratios[name]):.1f}×" if ratios[name] else "–")
        sec.add(f"| {name if name != 'GMT' else 'GMT blockmedian + surface -T0.25'} | {seconds:.2f} s | "
                f"{times} | {fmt_bytes(peak)} | {rms[name] * 1000:.1f} mm |")
    if skipped:
        sec.add("", f"GMT skipped: {skipped}.")
    sec.add("", "Issue 38's target: the default job within 5× GMT's time, at most 1.5 GB, and an RMS "
            "at or below GMT's.")
    return sec


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.dtm", description=__doc__.split("\n\n")[0])
    parser.add_argument("verb", choices=["make", "run"])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--points", type=int, default=N, help="make: how many points (default 1M)")
    parser.add_argument("--spacings", type=float, nargs="*", default=[],
                        help="run: also --smooth auto with each of these --spacing values")
    parser.add_argument("--no-delaunay", action="store_true",
                        help="run: leave out --smooth auto with a vertex at every point (70-80 s a round)")
    parser.add_argument("--write", action="store_true",
                        help=f"run: write the '{TITLE}' section of RESULTS.md, its runs so far kept below")
    args = parser.parse_args(argv)
    if args.verb == "make":
        make(args.folder, args.points)
        return 0
    return show_section(run(args.folder, args.reps, tuple(args.spacings), not args.no_delaunay), args.write,
                        keep_earlier=True)


if __name__ == "__main__":
    sys.exit(main())
