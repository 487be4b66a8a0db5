"""The lattice's spacing against held-out ground (issue 38, `--spacing auto`).

    python -m benchmarks.lattice_spacing [SAMPLE ...]      (default: autzen_trim.laz)

For each of benchmarks.heldout's splits (seeds 0-2) of a LiDAR sample's ground: the lattice
fit (`--smooth auto`) at the training points' hull spacing Dm, and at Dm / 1.6 and Dm / 2.5
with their own search and with Dm's strength; held-out RMS (heights along the frame's axis,
the points the mesh covers) and seconds. docs/smoothing.md, "The lattice's spacing".
"""
from __future__ import annotations

import sys
import time

import numpy as np

from benchmarks.heldout import SAMPLES, c1mesh_model, held_out, lidar_ground, mean_spacing

FINER = (1.6, 2.5)
"""How much finer than Dm the other lattices are."""


def score(train: np.ndarray, test: np.ndarray, spacing: float, strength) -> tuple[float, float, float]:
    """(held-out RMS, the strength used, seconds) of the lattice fit of train at `spacing`."""
    start = time.perf_counter()
    model = c1mesh_model(train, smooth=strength, spacing=spacing)
    seconds = time.perf_counter() - start
    local = model.frame.to_local(test)
    heights = model.interp(local[:, :2])
    covered = np.isfinite(heights)
    rms = float(np.sqrt(np.mean((heights[covered] - local[covered, 2]) ** 2)))
    return rms, float(model.smoothing.strength), seconds


def run(name: str, seeds=(0, 1, 2)) -> None:
    data = lidar_ground(SAMPLES / name, name)
    print(f"{data.name}: {len(data.points):,} points")
    for seed in seeds:
        test = held_out(len(data.points), seed)
        train, held = data.points[~test], data.points[test]
        coarse = float(f"{mean_spacing(train[:, :2]):.3g}")
        base = score(train, held, coarse, "auto")
        print(f"seed {seed}, Dm = {coarse:g}: RMS {base[0]:.5f}, s {base[1]:.4g}, {base[2]:.1f} s", flush=True)
        for k in FINER:
            spacing = float(f"{coarse / k:.3g}")
            own, moved = score(train, held, spacing, "auto"), score(train, held, spacing, base[1])
            print(f"  D = {spacing:g}: own search RMS {own[0]:.5f} ({own[0] / base[0]:.3f} x Dm's), s {own[1]:.4g}, "
                  f"{own[2]:.1f} s | Dm's s: RMS {moved[0]:.5f} ({moved[0] / own[0]:.4f} x own), {moved[2]:.1f} s",
                  flush=True)


def main(argv: list[str] | None = None) -> int:
    for name in (argv if argv else ["autzen_trim.laz"]):
        run(name)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
