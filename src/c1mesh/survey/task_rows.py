"""The memory-bounded fit's report pieces (c1mesh.pipeline.bounded_fit): the per-tile rows of
what each pass's task did (`TileRows`) and the CRS facts; c1mesh.pipeline.run
makes the report of c1mesh.pipeline.report's schema from them."""
from __future__ import annotations

import numpy as np

from c1mesh.core.crs import describe


class TileRows:
    """The per-tile report rows of a tiled fit: for each tile, what each pass's task did
    (seconds, worker), its height-field points and its final triangles; threads: the
    threads each task may use (None: the process's setting)."""

    def __init__(self, grid, threads, on_tile=None):
        self.grid, self.threads, self.on_tile = grid, threads, on_tile
        self.passes: dict[int, dict] = {}

    def name(self, t: int) -> str:
        """How a message names tile t: its number and cell (frame units)."""
        x0, y0, x1, y1 = self.grid.cell(t)
        return f"{t} (cell {x0:.2f}..{x1:.2f} x {y0:.2f}..{y1:.2f})"

    def add(self, t: int, stage: str, row: dict) -> None:
        self.passes.setdefault(t, {})[stage] = row
        if self.on_tile:
            done = sum(stage in passes for passes in self.passes.values())
            self.on_tile(stage, done, len(self.grid))

    def table(self, points: np.ndarray, triangles: dict) -> list[dict]:
        """One row per tile: tile, cell, points (height field), triangles (owned final
        base triangles), seconds (all its tasks), worker (of its last task), and per pass
        the seconds, worker and its peak RSS so far (MB)."""
        out = []
        for t in range(len(self.grid)):
            passes = self.passes.get(t, {})
            last = list(passes.values())[-1] if passes else {}
            out.append({"tile": t, "cell": [round(c, 6) for c in self.grid.cell(t)],
                        "points": int(points[t]), "triangles": int(triangles.get(t, 0)),
                        "seconds": round(sum(p["seconds"] for p in passes.values()), 3),
                        "worker": last.get("worker"),
                        "passes": {k: {key: p[key] for key in ("seconds", "worker", "worker_peak_mb")}
                                   for k, p in passes.items()}})
        return out


def describe_crs(crs, crs_source) -> dict | None:
    facts = describe(crs)
    if facts is not None:
        facts["source"] = crs_source
    return facts
