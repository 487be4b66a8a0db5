"""Triangulation at scale: plain ``scipy.spatial.Delaunay`` vs ``c1mesh.engine.triangulation.delaunay``.

The fit pipeline triangulates every cloud, and at 1M points Delaunay is one of its largest
stages. ``c1mesh.engine.triangulation.delaunay`` may add spatial presorting or tiling; while it
does not exist the row says "pending" and only scipy is measured.
"""
from __future__ import annotations

import importlib

import numpy as np
from scipy.spatial import Delaunay

from benchmarks.common import Config, Section, fmt_s, fmt_x, median, paired, random_points, ratio


def _ours():
    """c1mesh.engine.triangulation.delaunay, or None with the reason it is unavailable."""
    try:
        mod = importlib.import_module("c1mesh.engine.triangulation")
    except Exception as exc:  # noqa: BLE001 - any import failure means "not there yet"
        return None, f"c1mesh.engine.triangulation not importable ({type(exc).__name__})"
    fn = getattr(mod, "delaunay", None)
    return (fn, "") if callable(fn) else (None, "c1mesh.engine.triangulation has no delaunay()")


def _triangles(result) -> np.ndarray:
    tri = getattr(result, "simplices", result)
    return np.asarray(tri[0] if isinstance(tri, tuple) else tri)


def same_triangles(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two triangulations hold the same vertex triples (orientation and order ignored)."""
    if a.shape != b.shape:
        return False
    key = lambda t: np.unique(np.sort(t.astype(np.int64), axis=1), axis=0)  # noqa: E731
    return bool(np.array_equal(key(a), key(b)))


def run(cfg: Config) -> Section:
    sec = Section("Triangulation: scipy Delaunay vs c1mesh.engine.triangulation.delaunay")
    fn, why = _ours()
    sec.add(f"Uniform random points in the unit square, {cfg.reps} repetitions interleaved. "
            "Ratio = scipy time / c1mesh time (> 1 means c1mesh is faster). 'same triangles': "
            "the two return the same set of vertex triples.", "",
            "| N | scipy Delaunay | triangles | c1mesh delaunay | triangles | same triangles | "
            "scipy / c1mesh |", "|---:|---:|---:|---:|---:|---|---:|")
    for n in cfg.delaunay_sizes:
        pts = random_points(n, seed=2)
        last = {}

        def scipy_job():
            d = Delaunay(pts)
            last["scipy"] = d.simplices
            return d
        jobs = {"scipy": scipy_job}
        if fn is not None:
            def ours_job():
                r = fn(pts)
                last["ours"] = _triangles(r)
                return r
            jobs["ours"] = ours_job
        try:
            times = paired(jobs, cfg.reps)
        except Exception as exc:  # noqa: BLE001 - a half-written function must not stop the run
            times = paired({"scipy": scipy_job}, cfg.reps)
            why = f"c1mesh delaunay failed: {type(exc).__name__}: {str(exc)[:120]}"
        if "ours" in times and len(times["ours"]) == len(times["scipy"]):
            r = ratio(times["scipy"], times["ours"])
            same = "yes" if same_triangles(last["scipy"], last["ours"]) else "**no**"
            sec.add(f"| {n:,} | {fmt_s(median(times['scipy']))} | {len(last['scipy']):,} | "
                    f"{fmt_s(median(times['ours']))} | {len(last['ours']):,} | {same} | {fmt_x(r)} |")
            sec.headlines.append((f"triangulation: scipy / c1mesh delaunay, N={n:,}", fmt_x(r),
                                  "(none set)", "—"))
        else:
            sec.add(f"| {n:,} | {fmt_s(median(times['scipy']))} | {len(last['scipy']):,} | "
                    "pending | — | — | pending |")
    if why:
        sec.add("", f"c1mesh column pending: {why}.")
    sec.add("")
    return sec
