"""Time against survey size for the memory-bounded fit (not a suite section: it takes an hour).

    python -m benchmarks.survey_size run FOLDER [MILLIONS ...]    # default 1 2 4 12 25 50
    python -m benchmarks.survey_size report FOLDER                # markdown + survey_size.png

`run` makes each synthetic LAZ once (benchmarks.tiled_delaunay.make: smooth terrain at about
4 points per m², 2 cm noise, all class 2), then times

    c1mesh fit FOLDER/N.laz --classes 2 --level 1 --memory 2G -o FOLDER/N.ply --report ...

in a child process, one size after another, and appends one JSON line per size to
FOLDER/survey_size.jsonl: wall seconds, CPU seconds of the process tree (user + system, from
wait4), the peak of the summed RSS of the process tree (sampled every 0.2 s, so a peak
shorter than that can be missed), the tile count from the report, and the machine's load
average before and after. The output mesh is deleted after each size (50M points at level 1
is about 3.7 GB of PLY). Under 2G a survey of up to about 1.1M points fits in memory, so the
1M row is the in-memory fit: the peer whose throughput the tiled fits are compared with.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

SIZES_M = (1, 2, 4, 12, 25, 50)
MEMORY = "2G"


def run(folder: Path, sizes_m: tuple[int, ...]) -> None:
    """Make and fit each size; append its measurements to folder/survey_size.jsonl."""
    from benchmarks.common import compile_sources
    from benchmarks.tiled_delaunay import make

    compile_sources()
    folder.mkdir(parents=True, exist_ok=True)
    for m in sizes_m:
        laz = folder / f"{m}M.laz"
        if not laz.exists():
            make(str(laz), m * 1_000_000)
        row = _fit(laz, folder)
        with open(folder / "survey_size.jsonl", "a") as log:
            log.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)


def _fit(laz: Path, folder: Path) -> dict:
    import psutil

    mesh, report = folder / f"{laz.stem}.ply", folder / f"{laz.stem}.json"
    exe = str(Path(sys.executable).with_name("c1mesh"))
    cmd = [exe, "fit", "--smooth", "off", str(laz), "--classes", "2", "--level", "1", "--memory", MEMORY,
           "-o", str(mesh), "--report", str(report), "-q"]
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    child = subprocess.Popen(cmd, stderr=subprocess.PIPE)
    tree_peak = _sample_tree_rss(psutil.Process(child.pid))
    _, status, usage = os.wait4(child.pid, 0)
    seconds = time.perf_counter() - start
    stderr = child.stderr.read().decode(errors="replace")
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {code}: {stderr.strip()}")
    facts = json.loads(report.read_text())
    points = facts["points"]["read"]
    mesh.unlink()
    return {"file": laz.name, "points": points, "tiles": _tile_count(facts), "seconds": seconds,
            "cpu_seconds": usage.ru_utime + usage.ru_stime, "tree_peak_rss": tree_peak,
            "load_before": load_before, "load_after": os.getloadavg()[0],
            "stage_seconds": facts.get("seconds"), "commit": _commit()}


def _sample_tree_rss(process) -> int:
    """The largest summed RSS of process and its descendants, sampled until it exits."""
    import psutil

    peak = 0
    while process.is_running() and process.status() != psutil.STATUS_ZOMBIE:
        try:
            members = [process, *process.children(recursive=True)]
            peak = max(peak, sum(p.memory_info().rss for p in members))
        except psutil.Error:
            pass
        time.sleep(0.2)
    return peak


def _tile_count(facts: dict) -> int:
    """The report's tile count (an int, or a list of per-tile entries); 0 for an in-memory fit."""
    tiles = facts.get("tiles") or 0
    return len(tiles) if isinstance(tiles, list) else int(tiles)


def _commit() -> str:
    done = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parent)
    return done.stdout.strip()


def report(folder: Path) -> None:
    """Print the markdown table and write benchmarks/survey_size.png from the log."""
    latest = {}                                   # a size run again replaces its earlier row
    for line in (folder / "survey_size.jsonl").read_text().splitlines():
        if line:
            row = json.loads(line)
            latest[row["file"]] = row
    rows = sorted(latest.values(), key=lambda r: r["points"])
    peer = rows[0]
    print("| points | tiles | wall | CPU (user + sys) | wall per M points | throughput / 1M in memory "
          "| peak RSS (tree) | RSS per input point | load before / after |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        per_m = r["seconds"] / (r["points"] / 1e6)
        relative = (r["points"] / r["seconds"]) / (peer["points"] / peer["seconds"])
        print(f"| {r['points']:,} | {r['tiles'] or 'in memory'} | {r['seconds']:.0f} s | {r['cpu_seconds']:.0f} s "
              f"| {per_m:.1f} s | {relative:.2f} | {r['tree_peak_rss'] / 2**30:.2f} GiB "
              f"| {r['tree_peak_rss'] / r['points']:.0f} B | {r['load_before']:.1f} / {r['load_after']:.1f} |")
    tiled = [r for r in rows if r["tiles"]]
    _stage_table(tiled)
    _linearity(tiled)
    _plot(rows, Path(__file__).resolve().parent / "survey_size.png")


def _stage_table(rows: list[dict]) -> None:
    """Wall seconds per million points of each stage of the tiled fits."""
    stages = list(dict.fromkeys(stage for r in rows for stage in r["stage_seconds"]))
    print("\n| points | " + " | ".join(stages) + " |")
    print("|---:|" + "---:|" * len(stages))
    for r in rows:
        per_m = [r["stage_seconds"].get(stage, 0.0) / (r["points"] / 1e6) for stage in stages]
        print(f"| {r['points']:,} | " + " | ".join(f"{v:.1f}" for v in per_m) + " |")


def linear_fit(rows: list[dict], key: str) -> tuple[float, float, float]:
    """Least squares key = a + b * (million points) over rows: (a seconds, b seconds per
    million points, the largest |residual| / key)."""
    import numpy as np

    millions = np.array([r["points"] / 1e6 for r in rows])
    seconds = np.array([r[key] for r in rows])
    b, a = np.polyfit(millions, seconds, 1)
    return float(a), float(b), float(np.max(np.abs(seconds - (a + b * millions)) / seconds))


def _linearity(rows: list[dict]) -> None:
    """How far the tiled fits' wall and CPU seconds are from a straight line in the size."""
    if len(rows) < 3:
        return
    print()
    for key, label in (("seconds", "wall"), ("cpu_seconds", "CPU")):
        a, b, worst = linear_fit(rows, key)
        per_m = [r[key] / (r["points"] / 1e6) for r in rows]
        print(f"- {label}: {a:.0f} s + {b:.1f} s per million points (least squares over "
              f"{rows[0]['points'] / 1e6:g}M-{rows[-1]['points'] / 1e6:g}M); largest residual "
              f"{100 * worst:.1f}% of the measured time; per million points "
              f"{min(per_m):.1f}-{max(per_m):.1f} s.")


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    millions = [r["points"] / 1e6 for r in rows]
    fig, (ax, per) = plt.subplots(1, 2, figsize=(11, 4))
    ax.plot(millions, [r["seconds"] for r in rows], "o-", label="wall")
    ax.plot(millions, [r["cpu_seconds"] for r in rows], "s--", label="CPU (user + sys)")
    tiled = [r for r in rows if r["tiles"]]
    if len(tiled) >= 3:
        a, b, _ = linear_fit(tiled, "seconds")
        span = [tiled[0]["points"] / 1e6, tiled[-1]["points"] / 1e6]
        ax.plot(span, [a + b * m for m in span], ":", color="grey",
                label=f"wall, least squares: {a:.0f} s + {b:.1f} s/M")
    ax.set_xlabel("survey size (million points)")
    ax.set_ylabel("seconds")
    ax.set_title(f"c1mesh fit --level 1 --memory {MEMORY} (LAZ, class 2)")
    ax.grid(alpha=0.3)
    ax.legend()
    per.plot(millions, [r["seconds"] / m for r, m in zip(rows, millions)], "o-", label="wall")
    per.plot(millions, [r["cpu_seconds"] / m for r, m in zip(rows, millions)], "s--", label="CPU (user + sys)")
    per.set_ylim(bottom=0)
    per.set_xlabel("survey size (million points)")
    per.set_ylabel("seconds per million points")
    per.set_title("flat = linear (the 1M fit is in memory)")
    per.grid(alpha=0.3)
    per.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str]) -> int:
    command, folder = argv[0], Path(argv[1])
    if command == "run":
        run(folder, tuple(int(m) for m in argv[2:]) or SIZES_M)
    elif command == "report":
        report(folder)
    else:
        raise SystemExit(__doc__)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
