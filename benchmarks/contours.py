"""Contours (issue 40): how close c1mesh's contours are to the true level sets, against
the linear contours of the same DEM, and the README's picture.

Not a section of `python -m benchmarks`: the measurements behind RESULTS.md *Contours*.

    python -m benchmarks.contours franke [SEED]      # the table: Franke's function, 10k points
    python -m benchmarks.contours figure OUT.png     # autzen_trim's contours over its hillshade

franke: Franke's function sampled at 10,000 uniform random points on the unit square (mean
spacing h = 0.01) is fitted (`fit -o dem.tif --resolution R --contours c.gpkg --interval
0.1`, in process) at R = 0.5 to 10 spacings. For each R: the largest and RMS |f(v) − level|
over the vertices v of c1mesh's contours, and over those of contourpy's linear contours of
the DEM file (float32, cell centres: what `gdal_contour` draws), on the cells whose centre
is in the triangulation (the cells c1mesh traces on); and the seconds of the contour stage.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESOLUTIONS = (0.005, 0.01, 0.02, 0.03, 0.05, 0.1)
INTERVAL = 0.1


def franke(x, y):
    """Franke's (1979) test function on the unit square."""
    return (0.75 * np.exp(-((9 * x - 2) ** 2 + (9 * y - 2) ** 2) / 4)
            + 0.75 * np.exp(-(9 * x + 1) ** 2 / 49 - (9 * y + 1) / 10)
            + 0.5 * np.exp(-((9 * x - 7) ** 2 + (9 * y - 3) ** 2) / 4)
            - 0.2 * np.exp(-(9 * x - 4) ** 2 - (9 * y - 7) ** 2))


def _vertex_errors(lines, levels) -> np.ndarray:
    return np.concatenate([np.abs(franke(line[:, 0], line[:, 1]) - level) for line, level in zip(lines, levels)])


def _read(path):
    from pyogrio.raw import read

    _, _, geometry, fields = read(str(path))
    lines = [np.frombuffer(w[9:9 + 16 * int.from_bytes(w[5:9], "little")], "<f8").reshape(-1, 2) for w in geometry]
    return lines, fields[0]


def _linear(dem_path, interp, origin, levels):
    """(lines, levels) of contourpy's linear contours of the DEM on the cells inside the triangulation."""
    import contourpy
    import rasterio

    with rasterio.open(dem_path) as ds:
        dem, t = ds.read(1).astype(np.float64), ds.transform
        dem[dem == ds.nodata] = np.nan
    rows, cols = np.mgrid[0:dem.shape[0], 0:dem.shape[1]]
    x, y = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e
    inside = interp.find_simplex(np.column_stack([x.ravel(), y.ravel()]) - origin[:2]) >= 0
    dem[~inside.reshape(dem.shape)] = np.nan
    generator = contourpy.contour_generator(x, y, np.ma.masked_invalid(dem), name="serial", corner_mask=False)
    lines, line_levels = [], []
    for level in np.unique(levels):
        found = generator.lines(level)
        lines += found
        line_levels += [level] * len(found)
    return lines, line_levels


def franke_table(seed: int = 40) -> str:
    """The markdown table of the franke command."""
    from c1mesh.core.cloud import PointCloud
    from c1mesh.pipeline.driver import FitOptions, build_surface
    from c1mesh.pipeline.run import fit
    from c1mesh.pipeline.steps import StageTimer

    xy = np.random.default_rng(seed).random((10_000, 2))
    cloud = PointCloud(np.column_stack([xy, franke(xy[:, 0], xy[:, 1])]))
    rows = ["| R (spacings) | c1mesh max | linear max | c1mesh RMS | linear RMS | c1mesh vertices | contour seconds |",
            "|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as folder:
        for resolution in RESOLUTIONS:
            dem, gpkg = Path(folder) / f"dem-{resolution}.tif", Path(folder) / f"c-{resolution}.gpkg"
            options = FitOptions(smooth="off", axis="z", resolution=resolution, contours=str(gpkg), interval=INTERVAL)
            report = fit(cloud, str(dem), options).report
            lines, levels = _read(gpkg)
            ours = _vertex_errors(lines, levels)
            model = build_surface(cloud, options, StageTimer(None))
            linear = _vertex_errors(*_linear(dem, model.interp, model.frame.origin, levels))
            rows.append(f"| {resolution} ({resolution / 0.01:g}) | {ours.max():.2e} | {linear.max():.2e} | "
                        f"{np.sqrt(np.mean(ours ** 2)):.2e} | {np.sqrt(np.mean(linear ** 2)):.2e} | "
                        f"{ours.size} | {report['contours']['seconds']:.2f} |")
    return "\n".join(rows)


def figure(out: Path) -> None:
    """autzen_trim's ground fitted at 2 ft with contours every 2 ft, drawn over its
    hillshade (the README's command), with a zoom on the mound south of the road."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rasterio

    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    with tempfile.TemporaryDirectory() as folder:
        dem, shade, gpkg = (Path(folder) / name for name in ("dem.tif", "hillshade.tif", "contours.gpkg"))
        start = time.perf_counter()
        fit(str(ROOT / "data_samples" / "autzen_trim.laz"), str(dem),
            FitOptions(smooth="off", classes=(2,), resolution=2.0, hillshade=str(shade), contours=str(gpkg), interval=2.0))
        print(f"fit: {time.perf_counter() - start:.1f} s", file=sys.stderr)
        with rasterio.open(shade) as ds:
            image, box = ds.read(1, masked=True), ds.bounds
        lines, levels = _read(gpkg)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2), dpi=100, gridspec_kw={"width_ratios": [2.1, 1]},
                             layout="constrained")
    norm = plt.Normalize(float(levels.min()), float(levels.max()))
    for ax in axes:
        ax.imshow(image, cmap="gray", extent=(box.left, box.right, box.bottom, box.top), interpolation="nearest")
        for line, level in zip(lines, levels):
            ax.plot(line[:, 0], line[:, 1], color=plt.cm.viridis(norm(level)), lw=0.9)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        ax.xaxis.set_major_locator(plt.MaxNLocator(4))
        ax.yaxis.set_major_locator(plt.MaxNLocator(4))
        ax.ticklabel_format(useOffset=False, style="plain")
    zoom = (636360, 636500, 849060, 849200)
    axes[0].add_patch(plt.Rectangle((zoom[0], zoom[2]), zoom[1] - zoom[0], zoom[3] - zoom[2], fill=False, lw=1.2,
                                    edgecolor="tab:red"))
    axes[1].set_xlim(*zoom[:2])
    axes[1].set_ylim(*zoom[2:])
    axes[0].set_title("autzen_trim ground: contours every 2 ft over the hillshade (2 ft grid, EPSG:2994 ft)",
                      fontsize=9)
    axes[1].set_title("the red box", fontsize=9)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap="viridis"), ax=axes, label="level (ft)", shrink=0.7)
    fig.savefig(out, bbox_inches="tight")


def main(argv: list[str]) -> int:
    if argv[:1] == ["franke"]:
        print(franke_table(int(argv[1]) if len(argv) > 1 else 40))
        return 0
    if argv[:1] == ["figure"] and len(argv) == 2:
        figure(Path(argv[1]))
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
