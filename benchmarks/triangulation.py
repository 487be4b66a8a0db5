"""Triangulation at scale: plain ``scipy.spatial.Delaunay`` vs ``c1mesh.engine.triangulation.delaunay``.

The fit pipeline triangulates every cloud, and at 1M points Delaunay is one of its largest
stages. ``c1mesh.engine.triangulation.delaunay`` may add spatial presorting or tiling; while it
does not exist the row says "pending" and only scipy is measured.

    python -m benchmarks.triangulation peers [N] [REPS] [NAME ...]   # "Delaunay at 1M" (issue 23)

`peers` times Delaunay libraries back to back on N centred uniform random points (REPS
alternating rounds, medians), each next to scipy's triangles as sorted vertex triples. The
peers are optional installs, measured only (none is a c1mesh dependency): PyPI `triangle`
(Shewchuk's Triangle, non-commercial licence) and `cgal` (CGAL's SWIG bindings, GPL/LGPL).
"""
from __future__ import annotations

import importlib
import json
import statistics
import sys
import time

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


def _morton(xy: np.ndarray) -> np.ndarray:
    """Order of the points along a Morton (Z) curve on a 2^16 grid of their bounding box."""
    lo, span = xy.min(axis=0), np.ptp(xy, axis=0).max()
    q = np.minimum(((xy - lo) / span * 65536).astype(np.uint64), 65535)
    code = np.zeros(len(xy), dtype=np.uint64)
    for bit in range(16):
        for axis in range(2):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(2 * bit + axis)
    return np.argsort(code, kind="stable")


def _scipy(options=None):
    def run(xy):
        return Delaunay(xy, qhull_options=options).simplices
    return run


def _scipy_sorted(xy):
    order = _morton(xy)
    return order[Delaunay(xy[order]).simplices]


def _c1mesh(threads):
    def run(xy):
        from c1mesh.core.threads import limit
        from c1mesh.engine.triangulation import delaunay

        with limit(threads):
            return delaunay(xy)
    return run


def _triangle(options):
    def run(xy):
        import triangle

        return triangle.triangulate({"vertices": xy}, options)["triangles"]
    return run


def _cgal(xy):
    """CGAL Delaunay_triangulation_2 through its SWIG bindings: points built and inserted
    (CGAL spatially sorts a list insert), faces read back through Python iterators."""
    from CGAL.CGAL_Kernel import Point_2
    from CGAL.CGAL_Triangulation_2 import Delaunay_triangulation_2

    dt = Delaunay_triangulation_2()
    start = time.perf_counter()
    dt.insert([Point_2(float(x), float(y)) for x, y in xy])
    _cgal.insert_seconds = time.perf_counter() - start
    index = {(x, y): i for i, (x, y) in enumerate(xy.tolist())}
    faces = []
    for f in dt.finite_faces():
        corner = []
        for k in range(3):
            p = f.vertex(k).point()
            corner.append(index[(p.x(), p.y())])
        faces.append(corner)
    return np.array(faces, dtype=np.int64)


PEERS = {
    "scipy Delaunay (qhull, default Qbb Qc Qz Q12)": ("BSD-3 (scipy), qhull licence", _scipy()),
    "scipy Delaunay, Morton-presorted points": ("BSD-3, qhull licence", _scipy_sorted),
    "scipy Delaunay, qhull_options='Qbb Qz Q12' (no Qc)": ("BSD-3, qhull licence", _scipy("Qbb Qz Q12")),
    "scipy Delaunay, qhull_options='QJ' (joggled)": ("BSD-3, qhull licence", _scipy("QJ")),
    "c1mesh delaunay (tiled qhull), 1 thread": ("c1mesh", _c1mesh(1)),
    "c1mesh delaunay (tiled qhull), 2 threads": ("c1mesh", _c1mesh(2)),
    "triangle (Shewchuk), divide and conquer": ("non-commercial (Triangle's own)", _triangle("Q")),
    "triangle (Shewchuk), sweepline (-F)": ("non-commercial (Triangle's own)", _triangle("QF")),
    "cgal Delaunay_triangulation_2 (SWIG bindings)": ("GPL-3 / LGPL-3 (CGAL), bindings LGPL", _cgal),
}


def _triples(tri: np.ndarray) -> np.ndarray:
    t = np.sort(np.asarray(tri, dtype=np.int64), axis=1)
    return t[np.lexsort(t.T[::-1])]


def peers(n: int = 1_000_000, reps: int = 3, only: tuple[str, ...] = (), seed: int = 2) -> list[dict]:
    """Seconds (all rounds and median) of every available peer on n centred uniform points
    (only: the peers whose names contain one of these strings; () for all), and whether
    its triangles equal scipy's default (sorted vertex triples)."""
    xy = np.random.default_rng(seed).random((n, 2)) - 0.5
    reference = _triples(Delaunay(xy).simplices)
    chosen = {name: peer for name, peer in PEERS.items() if not only or any(o in name for o in only)}
    rows = {name: {"name": name, "licence": licence, "seconds": [], "same": None, "triangles": None}
            for name, (licence, _) in chosen.items()}
    for _ in range(reps):
        for name, (_, run) in chosen.items():
            row = rows[name]
            if row.get("error") or (name.startswith("cgal") and row["seconds"]):
                continue                   # CGAL's Python-side loops take a minute: one round
            try:
                start = time.perf_counter()
                tri = run(xy)
                row["seconds"].append(time.perf_counter() - start)
            except ImportError as exc:
                row["error"] = f"not installed ({exc.name})"
                continue
            if name.startswith("cgal"):
                row.setdefault("insert_seconds", []).append(_cgal.insert_seconds)
            if row["same"] is None:
                row["triangles"] = int(len(tri))
                row["same"] = bool(len(tri) == len(reference) and np.array_equal(_triples(tri), reference))
            del tri
            print(json.dumps({k: row[k] for k in ("name", "seconds", "same", "insert_seconds") if k in row}),
                  file=sys.stderr, flush=True)
    for row in rows.values():
        if row["seconds"]:
            row["median"] = statistics.median(row["seconds"])
        if row.get("insert_seconds"):
            row["insert_median"] = statistics.median(row["insert_seconds"])
    return list(rows.values())


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "peers":
        sizes = [int(a) for a in sys.argv[2:4]]
        print(json.dumps(peers(*sizes, only=tuple(sys.argv[4:])), indent=1))
    else:
        raise SystemExit(__doc__)
