"""Engine: `RSDInterpolator.refine` against matplotlib's reduced HCT and against a floor.

Same inputs on both sides (points, values, exact gradients, the same Delaunay triangles);
our level L = 2**k has exactly the output points of matplotlib's ``subdiv=k`` (asserted).
``refine`` returns values AND gradients; matplotlib's public ``refine_field`` returns values
only, so at level 4 we also time matplotlib computing values and gradients through the
same private path ``refine_field`` uses (``_interpolate_multikeys`` with the refiner's
triangle index, no point location).

The floor is what no implementation can avoid: the coefficient (T×21) × basis (21×P)
product for the values (P = lattice points per triangle, preallocated ``out``), plus a
fresh copy of arrays the size of refine's output (values, gradients, int32 triangles,
int32 parents; refine also writes the points, which the floor leaves out).
"""
from __future__ import annotations

import cProfile
import io
import pstats

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.tri as mtri  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import Delaunay  # noqa: E402

from benchmarks.common import (Config, Section, fmt_s, fmt_x, franke, median, paired,  # noqa: E402
                               random_points, ratio, verdict)
from c1mesh import RSDInterpolator  # noqa: E402
from c1mesh.core import threads  # noqa: E402
from c1mesh.engine import rsd  # noqa: E402
from c1mesh.engine.refine import MAX_WORKERS, lattice_pattern  # noqa: E402
from c1mesh.core.threads import available_cpus  # noqa: E402

ALL = min(available_cpus(), MAX_WORKERS)
"""Threads refine uses by default (all cores, at most MAX_WORKERS)."""


def floor_job(I: RSDInterpolator, level: int, M: int, K: int):
    """A callable doing the floor's work, with its inputs allocated (and touched) up front."""
    pat = lattice_pattern(level)
    B = np.ascontiguousarray(rsd.basis(I.scheme, pat.lattice / level))
    C = I.coefficients
    out = np.empty((C.shape[0], B.shape[1]))
    sources = [np.ones(M), np.ones((M, 2)), np.ones((K, 3), np.int32), np.ones(K, np.int32)]
    np.matmul(C, B, out=out)                       # warm-up

    def job():
        np.matmul(C, B, out=out)
        return [a.copy() for a in sources]
    return job


def run(cfg: Config) -> Section:
    sec = Section("Engine: refine vs matplotlib rHCT vs floor")
    sec.add("Franke's function on N uniform random points in the unit square, exact gradients, "
            "scipy Delaunay triangles given to both sides (triangulation is timed separately). "
            f"{cfg.reps} repetitions, contenders interleaved, then "
            f"{cfg.fast_reps - cfg.reps} more of refine and floor alone ({cfg.fast_reps} in all: "
            "a single cold or disturbed run of these short jobs would otherwise move the "
            "median); every timed call starts after a short idle pause (common.SETTLE). "
            "Ratios are medians of per-repetition ratios, refine vs matplotlib over the "
            "interleaved repetitions only. matplotlib runs are abandoned after "
            f"{cfg.peer_limit:.0f} s (then nothing is extrapolated).", "")
    build_rows, rows, plot = [], [], []
    for n in cfg.engine_sizes:
        pts = random_points(n, seed=1)
        z, g = franke(pts)
        tri = Delaunay(pts).simplices
        built = {}

        def ours_build():
            built["ours"] = RSDInterpolator(pts, z, g, triangles=tri)
            return built["ours"]

        def mpl_build():
            t = mtri.Triangulation(pts[:, 0], pts[:, 1], triangles=tri)
            built["mpl"] = mtri.CubicTriInterpolator(t, z, kind="user", dz=(g[:, 0], g[:, 1]))
            return built["mpl"]
        bt = paired({"ours": ours_build, "mpl": mpl_build}, cfg.reps, {"mpl": cfg.peer_limit})
        mpl_build = (fmt_s(median(bt["mpl"])) if np.isfinite(median(bt["mpl"]))
                     else f"> {cfg.peer_limit:.0f} s, abandoned")
        build_rows.append(f"| {n:,} | {len(tri):,} | {fmt_s(median(bt['ours']))} | "
                          f"{mpl_build} | {fmt_x(ratio(bt['mpl'], bt['ours']))} |")
        I, mpl_ok = built["ours"], "mpl" in built and np.isfinite(median(bt["mpl"]))
        for level in cfg.levels:
            mpl_ok = _level(cfg, sec, rows, plot, n, I, built.get("mpl"), level, mpl_ok)
        if n == cfg.profile_size:
            sec.add(*_profile(I, max(cfg.levels)))
        del built, I
    sec.add("### Build (interpolator construction from points, values, gradients, triangles)", "",
            "| N | triangles | c1mesh build | matplotlib build | matplotlib / c1mesh |",
            "|---:|---:|---:|---:|---:|", *build_rows, "")
    sec.add("### Refine", "",
            f"Threads: matplotlib runs in one thread (its numpy code starts none). c1mesh "
            f"refine is timed twice: with one thread (c1mesh.core.threads.limit(1), BLAS limited "
            f"to 1 too) and with all cores ({ALL} threads here: the {available_cpus()} CPUs "
            f"this process may use, at most refine.MAX_WORKERS = {MAX_WORKERS}; fewer when "
            "the mesh has fewer blocks, the count used is in brackets). Both ratios are "
            "shown.", "",
            "| N | level (subdiv) | output points | c1mesh refine (values+grads), 1 thread | "
            f"c1mesh refine, all cores (threads) | floor | "
            "matplotlib refine_field (values, 1 thread) | matplotlib values+grads | "
            "**c1mesh vs matplotlib, 1 thread each** | "
            "**c1mesh (all cores) vs matplotlib (1 thread)** | **c1mesh / floor** |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|", *rows, "",
            "c1mesh vs matplotlib = matplotlib `refine_field` time / c1mesh `refine` time "
            "(c1mesh also computes gradients, matplotlib does not). "
            "'values+grads' is matplotlib doing what refine does, timed once at the smallest N, "
            "level 4 (it costs several times refine_field). "
            "c1mesh / floor = refine time (all cores) / floor time. Cores: refine splits "
            "its blocks over its worker threads; the floor's product uses the cores through "
            "BLAS, its copies one. The build (above) also uses all cores.", "")
    sec.add("`refine` builds `parent` on first use; the timed refine reads it, so both sides "
            "produce a parent array, as the floor specifies.", "")
    _plot(plot, cfg.out / "engine.png")
    sec.add("![engine timings](engine.png)", "")
    return sec


def _level(cfg, sec, rows, plot, n, I, mpl_interp, level, mpl_ok) -> bool:
    """Time one (N, level) cell; returns whether matplotlib should be tried at the next level."""
    k = int(np.log2(level))
    counts = {}

    def ours():
        m = I.refine(level)
        m.parent                                   # computed on first use; the floor copies one
        counts["ours"] = m.points.shape[0]
        return m

    def ours_1():
        with threads.limit(1):                     # one thread for refine and for BLAS
            m = I.refine(level)
            m.parent
        return m
    M = n + len(I.edges) * (level - 1) + len(I.triangles) * (level - 1) * (level - 2) // 2
    K = len(I.triangles) * level * level
    jobs = {"ours": ours, "ours_1": ours_1, "floor": floor_job(I, level, M, K)}
    if mpl_ok:
        refiner = mtri.UniformTriRefiner(mpl_interp._triangulation)

        def mpl():
            t, zz = refiner.refine_field(I.values, triinterpolator=mpl_interp, subdiv=k)
            counts["mpl"] = t.x.shape[0]
            return zz

        def mpl_vg():
            t, idx = refiner.refine_triangulation(subdiv=k, return_tri_index=True)
            return mpl_interp._interpolate_multikeys(t.x, t.y, tri_index=idx,
                                                     return_keys=("z", "dzdx", "dzdy"))
        jobs["mpl"] = mpl
        if level == 4 and n == cfg.engine_sizes[0]:
            jobs["mpl_vg"] = mpl_vg
    times = paired(jobs, cfg.reps, {"mpl": cfg.peer_limit, "mpl_vg": cfg.peer_limit}, once=("mpl_vg",))
    # refine vs floor: more repetitions (cheap), so one cold or disturbed run cannot move
    # the median; the matplotlib ratio pairs only the first cfg.reps, run beside matplotlib
    more = paired({"ours": ours, "floor": jobs["floor"]}, cfg.fast_reps - cfg.reps)
    times["ours"] += more["ours"]
    times["floor"] += more["floor"]
    assert counts["ours"] == M, (counts["ours"], M)
    if "mpl" in counts:
        assert counts["mpl"] == counts["ours"], f"point counts differ: {counts}"
    t_ours, t_floor = times["ours"], times["floor"]
    r_floor = ratio(t_ours, t_floor)
    t_mpl = times.get("mpl", [float("nan")])
    mpl_done = np.isfinite(median(t_mpl))
    r_mpl = ratio(t_mpl, t_ours) if mpl_done else float("nan")
    r_mpl_1 = ratio(t_mpl, times["ours_1"]) if mpl_done else float("nan")
    if "mpl" not in times:
        mpl_cell = "not run (build abandoned or a smaller level timed out)"
    elif mpl_done:
        mpl_cell = fmt_s(median(t_mpl))
    else:
        mpl_cell = f"> {cfg.peer_limit:.0f} s, abandoned"
    vg = times.get("mpl_vg")
    vg_cell = "—" if not vg else (f"{fmt_s(median(vg))} (1 run)" if np.isfinite(median(vg))
                                  else f"> {cfg.peer_limit:.0f} s")
    blocks = -(-len(I.triangles) // I.refinement(level).rows)
    used = min(ALL, blocks)                        # Refinement.mesh's own count
    rows.append(f"| {n:,} | {level} ({k}) | {M:,} | {fmt_s(median(times['ours_1']))} | "
                f"{fmt_s(median(t_ours))} ({used}) | {fmt_s(median(t_floor))} | {mpl_cell} | {vg_cell} | "
                f"{fmt_x(r_mpl_1)} | {fmt_x(r_mpl)} | {fmt_x(r_floor)} |")
    plot.append((f"{n // 1000}k L{level}", median(t_ours), median(t_floor),
                 median(t_mpl) if mpl_done else np.nan))
    if mpl_done:
        sec.headlines.append((f"engine: c1mesh refine vs matplotlib refine_field, N={n:,}, "
                              f"level {level}, both 1 thread", fmt_x(r_mpl_1), "(none set)", "—"))
        sec.headlines.append((f"engine: c1mesh refine vs matplotlib refine_field, N={n:,}, "
                              f"level {level}, c1mesh {used} threads, matplotlib 1",
                              fmt_x(r_mpl), "≥ 30×", verdict(r_mpl >= 30)))
    elif "mpl" in times:
        sec.headlines.append((f"engine: c1mesh vs matplotlib, N={n:,}, level {level}",
                              f"matplotlib > {cfg.peer_limit:.0f} s, not measured", "≥ 30×",
                              "see the 100k row"))
    sec.headlines.append((f"engine: c1mesh refine / floor, N={n:,}, level {level}",
                          fmt_x(r_floor), "≤ 5×", verdict(r_floor <= 5)))
    return mpl_done


def _profile(I: RSDInterpolator, level: int) -> list[str]:
    """cProfile of one refine: where the time goes (top functions by own time)."""
    prof = cProfile.Profile()
    prof.enable()
    m = I.refine(level)
    prof.disable()
    del m
    buf = io.StringIO()
    stats = pstats.Stats(prof, stream=buf).strip_dirs().sort_stats("tottime")
    stats.print_stats(12)
    lines = [ln for ln in buf.getvalue().splitlines() if ln.strip()]
    start = next(i for i, ln in enumerate(lines) if "ncalls" in ln)
    total = next((ln for ln in lines if "function calls" in ln), "").strip()
    return [f"### Where refine spends its time (cProfile, N={len(I.points):,}, level {level})", "",
            f"{total}; top functions by own time (tottime). cProfile sees the calling thread "
            "only: that is the first of refine's workers, the others run the same code on "
            "their own blocks.", "", "```",
            *lines[start:start + 13], "```", ""]


def _plot(plot, path) -> None:
    labels = [p[0] for p in plot]
    x = np.arange(len(plot))
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=80)
    bars = (("c1mesh refine", 1), ("floor", 2), ("matplotlib refine_field", 3))
    for i, (name, col) in enumerate(bars):
        ax.bar(x + (i - 1) * 0.27, [p[col] for p in plot], 0.27, label=name)
    ax.set_xticks(x, labels)
    ax.set_yscale("log")
    ax.set_ylabel("median seconds (log)")
    ax.set_title("refine: c1mesh vs floor vs matplotlib (missing bar = not run)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
