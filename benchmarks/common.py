"""Shared pieces of the benchmark: run configuration, paired timing, test data, sections.

Why paired timing: this machine is noisy (2 shared cores), so an absolute time means
little. Each repetition runs every contender once, back to back, and the figure we report
is the median over repetitions of the per-repetition ratio; the median times are shown
beside it only for orientation.
"""
from __future__ import annotations

import gc
import json
import re
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parent.parent   # the directory holding the benchmarks package


@dataclass
class Config:
    """Sizes and repetitions of one run; ``quick`` shrinks everything to finish in < ~60 s."""

    quick: bool
    out: Path
    reps: int
    engine_sizes: tuple[int, ...]
    levels: tuple[int, ...]
    pipeline_sizes: tuple[int, ...]
    poisson_depths: tuple[int, ...]
    delaunay_sizes: tuple[int, ...]
    accuracy_sizes: tuple[int, ...]
    memory_size: int
    profile_size: int
    fast_reps: int             # repetitions of refine vs floor (matplotlib runs only `reps`)
    accuracy_grid: int = 200   # evaluation grid of the convergence study: accuracy_grid² points
    terrain_crop: int | None = None   # DEM rows and columns used (None: the whole grid)
    memory_levels: tuple[int, ...] = (2, 4, 8)
    peer_limit: float = 60.0   # seconds: a matplotlib run longer than this is abandoned

    @classmethod
    def make(cls, quick: bool, out: Path) -> "Config":
        if quick:
            # every section and code path once, at sizes that run in seconds (the smoke
            # test); the numbers mean nothing
            return cls(True, out, reps=1, engine_sizes=(5_000,), levels=(4,),
                       pipeline_sizes=(5_000,), poisson_depths=(6,),
                       delaunay_sizes=(55_000,), accuracy_sizes=(100, 400, 1600),
                       memory_size=5_000, profile_size=5_000, fast_reps=1,
                       accuracy_grid=40, terrain_crop=80, memory_levels=(2, 4, 8))
        return cls(False, out, reps=3, engine_sizes=(100_000, 1_000_000), levels=(4, 8),
                   pipeline_sizes=(100_000, 1_000_000), poisson_depths=(8, 10),
                   delaunay_sizes=(100_000, 1_000_000),
                   accuracy_sizes=(100, 400, 1600, 6400, 25_600),
                   memory_size=1_000_000, profile_size=1_000_000, fast_reps=9)


@dataclass
class Section:
    """One part of RESULTS.md: a heading, markdown body, and headline ratios for the summary.

    headlines: rows (what, measured, target, verdict) for the summary table at the top.
    """

    title: str
    body: list[str] = field(default_factory=list)
    headlines: list[tuple[str, str, str, str]] = field(default_factory=list)

    def add(self, *lines: str) -> None:
        self.body.extend(lines)


class PeerTimeout(Exception):
    """A peer's run exceeded the configured limit and was abandoned."""


SETTLE = 0.1
"""Seconds of idle time before each timed call (see `timed`)."""


def timed(fn: Callable[[], object], limit: float | None = None) -> float:
    """Wall time of one call; the result is dropped only after the clock stops.

    Every call starts from idle cores: after a garbage collection, SETTLE seconds pass
    before the clock starts. A multi-threaded BLAS keeps its threads spinning for a while
    after a matrix product (OpenBLAS: measured here, a refine right after the floor's
    2-thread product took 68 ms instead of 47 ms; 0.05 s later, 47 ms again), and that
    would charge one contender's leftovers to the next.

    With ``limit`` (seconds) a SIGALRM interrupts the call (between numpy operations) and
    PeerTimeout is raised: used for matplotlib, which can take minutes at 1M points.
    """
    gc.collect()
    time.sleep(SETTLE)
    if limit:
        def _alarm(signum, frame):
            raise PeerTimeout
        old = signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, limit)
    try:
        start = time.perf_counter()
        result = fn()
        elapsed = time.perf_counter() - start
    finally:
        if limit:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
    del result
    return elapsed


def paired(contenders: dict[str, Callable[[], object]], reps: int,
           limits: dict[str, float] | None = None, once: tuple[str, ...] = ()) -> dict[str, list[float]]:
    """Run all contenders once per repetition, interleaved; returns their times.

    A contender that times out (``limits``) gets ``inf`` for that repetition and is not
    run again. Contenders named in ``once`` run in the first repetition only.
    """
    limits = limits or {}
    times: dict[str, list[float]] = {name: [] for name in contenders}
    dropped: set[str] = set()
    for rep in range(reps):
        for name, fn in contenders.items():
            if name in dropped or (rep and name in once):
                continue
            try:
                times[name].append(timed(fn, limits.get(name)))
            except PeerTimeout:
                times[name].append(float("inf"))
                dropped.add(name)
    return times


def median(xs) -> float:
    return float(np.median(np.asarray(xs, dtype=float)))


def ratio(slow: list[float], fast: list[float]) -> float:
    """Median over repetitions of slow/fast (pairs from the same repetition)."""
    n = min(len(slow), len(fast))
    return median([s / f for s, f in zip(slow[:n], fast[:n])])


def fmt_s(t: float) -> str:
    if not np.isfinite(t):
        return "—"
    return f"{t * 1000:.0f} ms" if t < 1 else f"{t:.2f} s"


def fmt_x(r: float) -> str:
    return "—" if not np.isfinite(r) else (f"{r:.1f}×" if r >= 1 else f"{r:.2f}×")


def verdict(ok: bool) -> str:
    return "met" if ok else "**missed**"


# ----------------------------------------------------------------------------- test data
def franke(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Franke's test function on the unit square and its exact gradient."""
    X, Y = 9 * xy[:, 0], 9 * xy[:, 1]
    terms = [(0.75, np.exp(-((X - 2) ** 2 + (Y - 2) ** 2) / 4), -(X - 2) / 2, -(Y - 2) / 2),
             (0.75, np.exp(-(X + 1) ** 2 / 49 - (Y + 1) / 10), -2 * (X + 1) / 49, -0.1 + 0 * Y),
             (0.5, np.exp(-((X - 7) ** 2 + (Y - 3) ** 2) / 4), -(X - 7) / 2, -(Y - 3) / 2),
             (-0.2, np.exp(-(X - 4) ** 2 - (Y - 7) ** 2), -2 * (X - 4), -2 * (Y - 7))]
    f = sum(c * e for c, e, _, _ in terms)
    gx = 9 * sum(c * e * dx for c, e, dx, _ in terms)
    gy = 9 * sum(c * e * dy for c, e, _, dy in terms)
    return f, np.stack([gx, gy], axis=1)


def exp_sin(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """exp(x)·sin(2y) and its gradient."""
    e, s, c = np.exp(xy[:, 0]), np.sin(2 * xy[:, 1]), np.cos(2 * xy[:, 1])
    return e * s, np.stack([e * s, 2 * e * c], axis=1)


def paraboloid(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A tilted, anisotropic paraboloid (a general quadratic) and its gradient."""
    x, y = xy[:, 0] - 0.3, xy[:, 1] - 0.6
    f = x * x + 2 * y * y + 0.5 * x * y + 0.7 * x - 0.4 * y
    return f, np.stack([2 * x + 0.5 * y + 0.7, 4 * y + 0.5 * x - 0.4], axis=1)


FUNCTIONS = {"Franke": franke, "exp(x)·sin(2y)": exp_sin, "paraboloid": paraboloid}


def random_points(n: int, seed: int = 0) -> np.ndarray:
    """n uniform random points in the unit square."""
    return np.random.default_rng(seed).random((n, 2))


# ----------------------------------------------------------------------------- subprocesses
@dataclass
class ChildRun:
    """One child process: wall seconds, its own peak RSS in bytes, exit code, output."""

    seconds: float
    peak_rss: int
    returncode: int
    stdout: str
    stderr: str


# Linux carries ru_maxrss across fork+exec: a child forked from this (large) process would
# report at least our RSS. A tiny launcher process forks the real command instead, times
# it and reads its rusage with wait4.
_LAUNCHER = ("import json, os, subprocess, sys, time\n"
             "t = time.perf_counter(); p = subprocess.Popen(sys.argv[2:])\n"
             "_, status, use = os.wait4(p.pid, 0)\n"
             "with open(sys.argv[1], 'w') as f:\n"
             "    json.dump([time.perf_counter() - t, use.ru_maxrss * 1024,"
             " os.waitstatus_to_exitcode(status)], f)\n")


def compile_sources() -> None:
    """Bring src/c1mesh's bytecode up to date, once per benchmark process, before anything
    is timed. An installed package carries its bytecode; the editable one gets it from
    setup.sh, and where PYTHONDONTWRITEBYTECODE is set (container images) a module edited
    after that is compiled again by every command that imports it: 36 edited modules cost
    each c1mesh process 0.12 s (2026-12-06), a cost no user pays."""
    global _COMPILED
    if not _COMPILED:
        import compileall
        compileall.compile_dir(str(ROOT / "src" / "c1mesh"), quiet=1)
        _COMPILED = True


_COMPILED = False


def run_child(cmd: list[str], discard_stdout: bool = False) -> ChildRun:
    """Run ``cmd`` (through the launcher) and return its wall time and peak RSS, with the
    package's bytecode current (`compile_sources`).

    discard_stdout: send the child's stdout to /dev/null instead of collecting it (for a
    mesh written to stdout)."""
    import os
    import subprocess
    import tempfile

    compile_sources()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        filter(None, [str(ROOT), os.environ.get("PYTHONPATH", "")])))
    with tempfile.TemporaryDirectory() as tmp:
        stats = Path(tmp) / "stats.json"
        gc.collect()
        done = subprocess.run([sys.executable, "-c", _LAUNCHER, str(stats), *cmd], env=env,
                              stdout=subprocess.DEVNULL if discard_stdout else subprocess.PIPE,
                              stderr=subprocess.PIPE)
        seconds, rss, code = json.loads(stats.read_text()) if stats.exists() else (0, 0, done.returncode)
        return ChildRun(seconds, rss, code, (done.stdout or b"").decode(errors="replace"),
                        done.stderr.decode(errors="replace"))


def fmt_bytes(n: float) -> str:
    return f"{n / 2**30:.2f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def terrain_cloud(n: int, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """n points of a smooth analytic terrain over a 100 m square, with exact unit normals.

    z = 3 sin(x/10) cos(y/15) + 0.02 x: hills plus a tilt, normals (−∇z, 1)/|…| pointing up.
    """
    xy = np.random.default_rng(seed).random((n, 2)) * 100.0
    x, y = xy[:, 0], xy[:, 1]
    z = 3 * np.sin(x / 10) * np.cos(y / 15) + 0.02 * x
    gx = 0.3 * np.cos(x / 10) * np.cos(y / 15) + 0.02
    gy = -0.2 * np.sin(x / 10) * np.sin(y / 15)
    normals = np.stack([-gx, -gy, np.ones(n)], axis=1)
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    return np.column_stack([xy, z]), normals


def write_cloud_ply(path, points: np.ndarray, normals: np.ndarray) -> None:
    """Binary little-endian PLY with double x y z nx ny nz (what both c1mesh and Open3D read)."""
    n = len(points)
    names = ("x", "y", "z", "nx", "ny", "nz")
    rows = np.empty(n, dtype=[(c, "<f8") for c in names])
    for i, c in enumerate(names):
        rows[c] = (points if i < 3 else normals)[:, i % 3]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\n" + "".join(f"property double {c}\n" for c in names)
              + "end_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rows.tobytes())


def pipeline_status() -> str:
    """'' when ``c1mesh fit`` can run, else why not (the pipeline is written concurrently)."""
    try:
        import c1mesh.cli  # noqa: F401
        import c1mesh.pipeline.driver  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any failure means "not available yet"
        return f"{type(exc).__name__}: {exc}"
    return ""


def report_from_stderr(stderr: str) -> dict:
    """The JSON report ``c1mesh fit --report -`` prints on stderr (other lines may surround it)."""
    start = stderr.find("{")
    if start < 0:
        raise ValueError(f"no JSON report on stderr: {stderr[-300:]}")
    return json.JSONDecoder().raw_decode(stderr[start:])[0]


#: Child runs shared between sections: (contender, N) -> {"rss": [...], "vertices", "faces"}.
#: The memory section reuses the pipeline section's peak RSS of `c1mesh fit` at 1M points.
MEASURED: dict[tuple[str, int], dict] = {}

#: The `c1mesh` command run through this interpreter (no dependence on an installed script).
C1MESH = ["-c", "from c1mesh.cli import run; run()"]


def show_section(sec: Section, write: bool, keep_earlier: bool = False) -> int:
    """A benchmark command's end: print the section's body and, with `write`, replace its
    section of benchmarks/RESULTS.md (write_section; keep_earlier: the section's runs so
    far move under its `### Earlier runs`); returns the exit status, 0."""
    print("\n".join(sec.body))
    if write:
        write_section(ROOT / "benchmarks" / "RESULTS.md", sec, keep_earlier)
    return 0


EARLIER = "### Earlier runs"
"""The heading under which a section written with keep_earlier keeps its former runs."""


def write_section(path: Path, sec: Section, keep_earlier: bool = False) -> None:
    """Replace the `## TITLE` section of RESULTS.md (up to the next `## `), or append it.
    keep_earlier: the replaced section's head (up to its EARLIER heading) becomes the first
    of its earlier runs, above the ones it kept, so a new measurement never erases an old one."""
    text = path.read_text() if path.exists() else ""
    block = "\n".join([f"## {sec.title}", "", *sec.body]).rstrip() + "\n"
    pattern = re.compile(rf"^## {re.escape(sec.title)}\n.*?(?=^## |\Z)", re.M | re.S)
    found = pattern.search(text)
    if found and keep_earlier:
        old = found.group(0)[len(f"## {sec.title}\n"):]
        head, _, earlier = old.partition(EARLIER)
        block = block + "\n" + EARLIER + "\n\nThe run before:\n\n" + head.strip() + "\n\n" + earlier.strip() + "\n"
    if found:
        text = pattern.sub(lambda _: block + "\n", text, count=1).rstrip() + "\n"
    else:
        text = text.rstrip() + "\n\n" + block
    path.write_text(text)
