"""Tiles: `c1mesh fit --seamless -O` over a grid of files against one fit of the whole cloud.

The survey is the smooth terrain of benchmarks.common at 100 points per m², with exact
normals, cut into a grid of PLY files of about TILE_POINTS points each; the peer is
`c1mesh fit` of the same points as one file (what --seamless -o writes). Each size runs
both as child processes, alternately, `reps` times; the ratio is the median over
repetitions of seamless / whole. One tile task (c1mesh.survey.tiles.run_tile) of the largest
survey is also run alone in a child to give the peak memory of one task, the figure that
matters when tiles run on Dask workers. `-j 2` (a pool of two worker processes) is
timed once at the smallest size against `-j 1` (tiles in the process);
--quick runs one repetition of two small sizes and leaves `-j 2` out.
"""
from __future__ import annotations

import json
import pickle
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import (C1MESH, Config, Section, fmt_bytes, fmt_s, fmt_x, median, run_child,
                               terrain_cloud, verdict, write_cloud_ply)

LEVEL = 4
TILE_POINTS = 250_000


def sizes(cfg: Config) -> tuple[int, ...]:
    """Survey sizes: 1M, 2M, 4M points in a full run (the lead may raise them)."""
    return (10_000, 20_000) if cfg.quick else (1_000_000, 2_000_000, 4_000_000)


def make_survey(n: int, folder: Path, per_tile: int) -> tuple[list[str], str]:
    """Write n terrain points as a grid of tile files and as one file; returns their paths."""
    points, normals = terrain_cloud(n)
    points[:, :2] *= np.sqrt(n / 1e6)                       # 100 points per m² at every size
    side = max(1, int(round(np.sqrt(n / per_tile))))
    span = points[:, :2].max(axis=0) + 1e-9
    ij = np.minimum((points[:, :2] / span * side).astype(int), side - 1)
    cell = ij[:, 0] + side * ij[:, 1]
    order = np.argsort(cell, kind="stable")
    write_cloud_ply(folder / "whole.ply", points[order], normals[order])
    paths = []
    for c in range(side * side):
        pick = cell == c
        paths.append(str(folder / f"tile_{c:03d}.ply"))
        write_cloud_ply(paths[-1], points[pick], normals[pick])
    return paths, str(folder / "whole.ply")


def run(cfg: Config) -> Section:
    sec = Section("Tiles: seamless survey vs one whole fit")
    sec.add(__doc__.split("\n\n")[1].replace("\n", " "), "")
    exe, rows, per_tile = sys.executable, [], (5_000 if cfg.quick else TILE_POINTS)
    tile_peak = None
    for n in sizes(cfg):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            paths, whole = make_survey(n, folder, per_tile)
            common = ["--level", str(LEVEL), "-q"]
            seamless, single = [], []
            for _ in range(1 if cfg.quick else cfg.reps):
                child = run_child([exe, *C1MESH, "fit", "--smooth", "off", *paths, "--seamless", "-O", f"{tmp}/out", *common])
                _check(child, "seamless")
                seamless.append(child)
                child = run_child([exe, *C1MESH, "fit", "--smooth", "off", whole, "-o", f"{tmp}/whole.c1.ply", *common])
                _check(child, "whole")
                single.append(child)
            row = {"n": n, "tiles": len(paths),
                   "seamless": [c.seconds for c in seamless], "whole": [c.seconds for c in single],
                   "seamless_rss": max(c.peak_rss for c in seamless),
                   "whole_rss": max(c.peak_rss for c in single)}
            if n == sizes(cfg)[0] and not cfg.quick:       # parallel runs say little at toy sizes
                child = run_child([exe, *C1MESH, "fit", "--smooth", "off", *paths, "--seamless", "-O", f"{tmp}/dask",
                                   "-j", "2", *common])
                _check(child, "-j 2")
                row["dask2"] = child.seconds
            if n == sizes(cfg)[-1]:
                tile_peak = _tile_task_peak(paths, folder)
            rows.append(row)
    _table(sec, rows, tile_peak)
    _plot(rows, cfg.out / "tiles.png")
    sec.add("", "![time against survey size](tiles.png)", "")
    return sec


def _check(child, what: str) -> None:
    if child.returncode != 0:
        raise RuntimeError(f"{what} failed: {child.stderr.strip()[-400:]}")


def _tile_task_peak(paths: list[str], folder: Path) -> dict:
    """Peak RSS of a child that runs the middle tile's task alone, and of one that only imports."""
    exe = sys.executable
    task_file = folder / "task.pickle"
    done = run_child([exe, "-m", "benchmarks.tiles", "plan", str(task_file), *paths])
    _check(done, "planning")
    info = json.loads(done.stdout)
    alone = run_child([exe, "-m", "benchmarks.tiles", "task", str(task_file)])
    _check(alone, "tile task")
    base = run_child([exe, "-c", "import c1mesh.survey.tiles, c1mesh.engine.refine, c1mesh.pipeline.driver"]).peak_rss
    return {"peak": alone.peak_rss, "imports": base, "points": info["points"],
            "report": json.loads(alone.stdout)}


def _table(sec: Section, rows: list[dict], tile_peak: dict | None) -> None:
    sec.add(f"Level {LEVEL}; times are medians of the child processes' wall time.", "",
            "| points | tiles | seamless -O | whole fit | **seamless / whole** | seamless per M points | "
            "peak RSS seamless | peak RSS whole |", "|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        ratio = median([s / w for s, w in zip(r["seamless"], r["whole"])])
        t = median(r["seamless"])
        sec.add(f"| {r['n']:,} | {r['tiles']} | {fmt_s(t)} | {fmt_s(median(r['whole']))} | {fmt_x(ratio)} | "
                f"{fmt_s(t / r['n'] * 1e6)} | {fmt_bytes(r['seamless_rss'])} | {fmt_bytes(r['whole_rss'])} |")
    first, last = rows[0], rows[-1]
    per_m = [median(r["seamless"]) / r["n"] * 1e6 for r in rows]
    growth = per_m[-1] / per_m[0]
    sec.add("", f"Time per million points grows {fmt_x(growth)} from {first['n']:,} to {last['n']:,} points "
            "(1.0× is linear).")
    if "dask2" in first:
        sec.add("", f"`-j 2` (two worker processes) at "
                f"{first['n']:,} points: {fmt_s(first['dask2'])} against {fmt_s(median(first['seamless']))} "
                "with the tiles run in the process.")
    ratio = median([s / w for s, w in zip(last["seamless"], last["whole"])])
    sec.headlines.append((f"tiles: seamless -O / whole fit time, N={last['n']:,}, level {LEVEL}",
                          fmt_x(ratio), "≤ 1.5×", verdict(ratio <= 1.5)))
    if tile_peak:
        task = tile_peak["report"]
        sec.add("", f"One tile task alone ({task['base_triangles']:,} base triangles + {task['halo_triangles']:,} "
                f"halo, {task['vertices']:,} output vertices): peak RSS {fmt_bytes(tile_peak['peak'])}, of which "
                f"{fmt_bytes(tile_peak['imports'])} is the interpreter and imports; "
                f"{(tile_peak['peak'] - tile_peak['imports']) / task['vertices']:.0f} bytes per output vertex, "
                f"{task['seconds']:.2f} s.")


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = np.array([r["n"] for r in rows]) / 1e6
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(n, [median(r["seamless"]) for r in rows], "o-", label="--seamless -O (tiles)")
    ax.plot(n, [median(r["whole"]) for r in rows], "s--", label="one whole fit")
    ax.set_xlabel("survey size (million points)")
    ax.set_ylabel("wall time (s)")
    ax.set_title(f"c1mesh fit, level {LEVEL}")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _plan_child(task_file: str, paths: list[str]) -> dict:
    """Build the survey model and pickle the middle input's tile task to task_file."""
    from c1mesh.pipeline.driver import FitOptions, build_surface
    from c1mesh.survey.tiles import TilePlan, load_survey

    options = FitOptions(smooth="off", level=LEVEL)
    survey = load_survey(paths, options)
    tasks = TilePlan(build_surface(survey.cloud, options), survey, [p + ".out" for p in paths], LEVEL)
    task = tasks[len(tasks) // 2]
    Path(task_file).write_bytes(pickle.dumps(task))
    return {"points": int(task.vertices.points.shape[0])}


def _task_child(task_file: str) -> dict:
    from c1mesh.survey.tiles import run_tile

    return run_tile(pickle.loads(Path(task_file).read_bytes())).report


if __name__ == "__main__":
    if sys.argv[1] == "plan":
        print(json.dumps(_plan_child(sys.argv[2], sys.argv[3:])))
    else:
        print(json.dumps(_task_child(sys.argv[2])))
