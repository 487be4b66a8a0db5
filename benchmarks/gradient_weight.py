"""Should the normals' gradients enter the smoothing fit as data? Held-out error against μ.

    python -m benchmarks.gradient_weight [--seeds 3] [--n 20000]

The synthetic terrain of common.terrain_cloud (100 m square) with 2 cm Gaussian height noise
and normals tilted by 3° RMS (as estimated normals are, geo._noisy), or exact normals. For
each seed 10% of the points are held out; stages.smoothing.smooth_fit is fitted to the rest
with strength "auto" and the normals' gradients as data with gradient_weight μ (0: heights
alone, today's default), on the training points' Delaunay triangulation with the limiter's
edge directions. Scores: the RMS of (fit − true height) and of (fit gradient − true
gradient) at the held-out points, and the RMS against the held-out noisy heights.
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from benchmarks.common import terrain_cloud
from benchmarks.geo import _noisy

WEIGHTS = (0.0, 0.01, 0.1, 1.0, 10.0)
NOISE = 0.02


def _truth(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(z (n,), gradient (n, 2)) of common.terrain_cloud's analytic terrain."""
    x, y = xy[:, 0], xy[:, 1]
    z = 3 * np.sin(x / 10) * np.cos(y / 15) + 0.02 * x
    gx = 0.3 * np.cos(x / 10) * np.cos(y / 15) + 0.02
    gy = -0.2 * np.sin(x / 10) * np.sin(y / 15)
    return z, np.column_stack([gx, gy])


def run_seed(n: int, seed: int, normal_noise_deg: float) -> list[dict]:
    from c1mesh.engine.interpolator import RSDInterpolator
    from c1mesh.engine.topology import edge_table
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.pipeline.steps import compact_vertices
    from c1mesh.stages.limiter import edge_directions
    from c1mesh.stages.smoothing import GradientPrior, SmoothingControl, SmoothingData, smooth_fit
    from c1mesh.stages.trim import trim_mesh

    points, normals = terrain_cloud(n, seed=seed)
    if normal_noise_deg:
        normals = _noisy(normals, normal_noise_deg, seed=seed + 100)
    rng = np.random.default_rng(seed)
    z = points[:, 2] + rng.normal(0.0, NOISE, n)
    held = rng.random(n) < 0.1
    xy, zt = points[~held, :2], z[~held]
    grads = -normals[~held, :2] / normals[~held, 2:3]
    mesh, _ = trim_mesh(xy, delaunay(xy), max_edge="auto")
    used, triangles = compact_vertices(xy, mesh.triangles)
    xy, zt, grads = xy[used], zt[used], grads[used]
    table = edge_table(triangles, len(xy))
    directions, _ = edge_directions(xy, triangles, table)
    spacing = math.sqrt(100.0 * 100.0 / n)
    true_z, true_g = _truth(points[held, :2])
    rows = []
    for mu in WEIGHTS:
        fit = smooth_fit(xy, triangles, SmoothingData(zt, spacing=spacing), SmoothingControl(strength="auto", seed=seed),
                         directions=directions, prior=GradientPrior(grads, weight=mu))
        interp = RSDInterpolator(xy, fit.values, fit.gradients, triangles=triangles, directions=directions,
                                 edge_table=table)
        at = points[held, :2]
        value, gradient = interp(at), interp.gradient(at)
        ok = np.isfinite(value)
        rows.append({"mu": mu, "s": fit.strength,
                     "truth": float(np.sqrt(np.mean((value[ok] - true_z[ok]) ** 2))),
                     "gradient": float(np.sqrt(np.mean(np.sum((gradient[ok] - true_g[ok]) ** 2, axis=1)))),
                     "heldout": float(np.sqrt(np.mean((value[ok] - z[held][ok]) ** 2)))})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--n", type=int, default=20000)
    args = parser.parse_args()
    for degrees in (3.0, 0.0):
        table = [run_seed(args.n, seed, degrees) for seed in range(args.seeds)]
        print(f"\nnormals tilted {degrees:g}° RMS, N = {args.n:,}, {args.seeds} seeds, 2 cm height noise\n")
        print("| μ (gradient_weight) | s chosen (median) | RMS vs true height (m) | RMS gradient error | "
              "RMS vs held-out heights (m) |")
        print("|---:|---:|---:|---:|---:|")
        for i, mu in enumerate(WEIGHTS):
            rows = [seed_rows[i] for seed_rows in table]
            mean = {k: np.mean([r[k] for r in rows]) for k in ("truth", "gradient", "heldout")}
            print(f"| {mu:g} | {np.median([r['s'] for r in rows]):.3g} | {mean['truth']:.5f} | "
                  f"{mean['gradient']:.5f} | {mean['heldout']:.5f} |")


if __name__ == "__main__":
    main()
