"""RESULTS.md: the command, the machine, a summary of headline ratios, then every section.

Everything written comes from the run that writes it; the machine block records what the
numbers depend on (CPU, cores, RAM, library versions, the c1mesh commit and whether its
source had uncommitted edits at the time).
"""
from __future__ import annotations

import datetime
import os
import platform
import subprocess
from pathlib import Path

from benchmarks.common import ROOT, Section


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _ram() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                return f"{int(line.split()[1]) / 2**20:.1f} GiB"
    except OSError:
        pass
    return "unknown"


def _git() -> str:
    def git(*args):
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = git("status", "--porcelain", "--", "src")
    n = len(dirty.splitlines())
    return commit + (f" + {n} uncommitted file(s) under src/ (measured as on disk)" if n else "")


def machine() -> list[str]:
    import matplotlib
    import numpy
    import open3d
    import scipy

    return [f"- CPU: {_cpu_model()}; cores: {os.cpu_count()}; RAM: {_ram()}",
            f"- Python {platform.python_version()}, numpy {numpy.__version__}, "
            f"scipy {scipy.__version__}, matplotlib {matplotlib.__version__}, "
            f"open3d {open3d.__version__}",
            f"- c1mesh commit: {_git()}",
            f"- date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}"]


def write(path: Path, command: str, quick: bool, sections: list[Section], seconds: float) -> None:
    lines = ["# c1mesh benchmarks", "",
             f"Reproduce: `{command}` (from the repository root, with the project's venv). "
             f"{'QUICK run: small sizes, for smoke testing only. ' if quick else ''}"
             f"This run took {seconds / 60:.1f} min.", "", *machine(), "",
             "Every figure is a ratio to a peer measured in the same run (median over repetitions); "
             "absolute times are for orientation only.", "",
             "## Summary", "", "| what | measured | target | verdict |", "|---|---:|---|---|"]
    for sec in sections:
        lines += [f"| {w} | {m} | {t} | {v} |" for w, m, t, v in sec.headlines]
    lines.append("")
    for sec in sections:
        lines += [f"## {sec.title}", "", *sec.body, ""]
    path.write_text("\n".join(lines).rstrip() + "\n")
