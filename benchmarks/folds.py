"""Folded faces of the lattice route at steep steps, over sample families (issue 38).

    python -m benchmarks.folds [--seeds 6] [--write]

Issue 38 asks for 0 folded facets on samples with steps. Whether a fit on the lattice folds
beside a bank narrower than a cell depends on where the bank falls among the cells and on
the noise, so one sample says little: a rule can pass it and fail the next position
(docs/smoothing.md, "Folds at steps: local stiffness, measured"). This benchmark fits
families of c1mesh.testing.steps samples with `c1mesh fit --smooth auto --spacing 1.3`
(the samples' spacing) at the default level and counts, per fit, the faces whose geometric
normal is more than 90° from a corner's written normal (c1mesh.testing.quality.
folded_faces):
- "banks, shifted": steps.banks(seed, shift) for the 16 shifts (0, ¼, ½, ¾) × 1.3 m in x
  and y, the sampling unchanged (so the steps sit at 16 sub-cell positions of the lattice);
- "walls": steps.walls(seed): the banks plus three lines of points 0-6 m off the ground.
No peer: the count is the measure, and its target is 0. One thread, in this process.
"""
from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time

import numpy as np

from benchmarks.common import Section, show_section
from c1mesh.testing.steps import SPACING, banks, lattice_folds, walls

TITLE = "Folded faces at steep steps: the lattice route over sample families (issue 38)"
SHIFTS = (0.0, 0.25, 0.5, 0.75)


def families(seeds: int) -> dict[str, list[tuple[str, np.ndarray]]]:
    """Each family's (label, points) fits."""
    shifted = [(f"seed {seed}, shift ({fx:g}, {fy:g}) × {SPACING:g} m",
                banks(seed, shift=(fx * SPACING, fy * SPACING)))
               for fx, fy in itertools.product(SHIFTS, repeat=2) for seed in range(seeds)]
    return {"banks, shifted": shifted, "walls": [(f"seed {seed}", walls(seed)) for seed in range(seeds)]}


def run(seeds: int) -> Section:
    """The table: per family the fits, those with a folded face, the faces folded (most in
    one fit, all fits), the chosen strengths' median, and which fits folded."""
    sec = Section(TITLE)
    sec.body += ["`python -m benchmarks.folds --seeds %d`: `c1mesh fit --smooth auto --spacing %g` at the "
                 "default level, one thread." % (seeds, SPACING), "",
                 "| family | fits | fits with a folded face | most faces in one fit | faces in all "
                 "| median s | seconds |",
                 "|---|---|---|---|---|---|---|"]
    folded_fits = []
    for name, fits in families(seeds).items():
        start = time.perf_counter()
        counts, strengths = [], []
        for label, points in fits:
            count, strength = lattice_folds(points, workers=1)
            counts.append(count)
            strengths.append(strength)
            if count:
                folded_fits.append(f"{name}, {label}: {count} faces at s = {strength:.3g}")
        seconds = time.perf_counter() - start
        sec.body.append(f"| {name} | {len(fits)} | {sum(c > 0 for c in counts)} | {max(counts)} | {sum(counts)} | "
                        f"{statistics.median(strengths):.3g} | {seconds:.0f} |")
    sec.body += ["", "Fits that folded:" if folded_fits else "No fit folded a face."]
    sec.body += [f"- {line}" for line in folded_fits]
    return sec


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.folds", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=6, help="seeds per shift and of the walls (default 6)")
    parser.add_argument("--write", action="store_true", help=f"replace the '{TITLE}' section of RESULTS.md")
    args = parser.parse_args(argv)
    return show_section(run(args.seeds), args.write)


if __name__ == "__main__":
    sys.exit(main())
