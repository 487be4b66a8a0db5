"""Pipeline: ``c1mesh fit`` end to end vs Open3D's Poisson reconstruction on the same file.

Both sides get the same binary PLY (an analytic terrain with exact unit normals, see
common.terrain_cloud) and run as child processes doing read → reconstruct → write, so the
wall times include the same kind of work (interpreter start, imports, file I/O). Per-stage
seconds come from ``c1mesh fit --report -`` and from the Poisson child's own timers
(``c1mesh fit`` streams its output: one thread evaluates the spline block by block, the
main thread packs rows, a third writes the file; "refine" is the time spent waiting for
evaluated blocks, "write" the rest of the writing, fsync included).
The outputs differ in size: c1mesh's level 4 has ~16 vertices per input point, Poisson's
vertex count is set by its octree depth; both counts are shown.

Run as ``python -m benchmarks.pipeline poisson IN.ply OUT.ply DEPTH`` for the Poisson child,
or ``... stages IN.ply OUT.ply LEVEL`` for the library stages (used only while
``c1mesh.pipeline.driver`` cannot be imported).
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import (C1MESH, MEASURED, Config, Section, fmt_bytes, fmt_s, fmt_x,
                               median, pipeline_status, ratio, report_from_stderr, run_child,
                               terrain_cloud, verdict, write_cloud_ply)

LEVEL = 4


def run(cfg: Config) -> Section:
    sec = Section("Pipeline: c1mesh fit vs Open3D Poisson")
    why = pipeline_status()
    ours = "c1mesh fit" if not why else "library stages"
    if why:
        sec.add(f"**`c1mesh fit` not available** ({why}). The c1mesh row below is the library "
                "stages chained by this benchmark (read_cloud, normals → gradients with z up, "
                "scipy Delaunay, RSDInterpolator, refine, write_mesh), not the pipeline.", "")
    sec.add(__doc__.split("\n\n")[1].replace("\n", " "), "",
            f"{cfg.reps} repetitions, contenders interleaved; level {LEVEL}; "
            f"Poisson depths {', '.join(map(str, cfg.poisson_depths))}.", "",
            "| N | contender | wall (median) | output vertices | output faces | peak RSS | "
            f"contender / {ours} |", "|---:|---|---:|---:|---:|---:|---:|")
    stage_rows, plot = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for n in cfg.pipeline_sizes:
            src = Path(tmp) / f"terrain_{n}.ply"
            write_cloud_ply(src, *terrain_cloud(n))
            runs = _measure(cfg, tmp, src, why)
            MEASURED.update({(name, n): r for name, r in runs.items()})
            t_ours = runs[ours]["seconds"]
            for name, r in runs.items():
                rel = "1×" if name == ours else fmt_x(ratio(r["seconds"], t_ours))
                sec.add(f"| {n:,} | {name} | {fmt_s(median(r['seconds']))} | {r['vertices']:,} | "
                        f"{r['faces']:,} | {fmt_bytes(median(r['rss']))} | {rel} |")
                stages = {k: median(v) for k, v in r["stages"].items()}
                stages["process start, imports, other"] = median(r["seconds"]) - sum(stages.values())
                stage_rows[n, name] = stages
                plot.append((f"{n // 1000}k\n{name.replace('Poisson ', 'P')}", stages))
            for d in cfg.poisson_depths:
                r = ratio(runs[f"Poisson depth {d}"]["seconds"], t_ours)
                target = d == 10 and n >= 1_000_000
                sec.headlines.append((f"pipeline: Poisson depth {d} / {ours}, N={n:,}, level {LEVEL}",
                                      fmt_x(r), "≥ 3×" if target else "(none set)",
                                      verdict(r >= 3) if target else "—"))
    sec.add("", f"contender / {ours} > 1 means c1mesh is faster.", "",
            "### Stage breakdown (median seconds)", "")
    for (n, name), stages in stage_rows.items():
        total = sum(stages.values())
        parts = ", ".join(f"{k} {v:.2f} s ({100 * v / total:.0f}%)" for k, v in stages.items())
        sec.add(f"- N={n:,}, {name}: {parts}")
    _plot(plot, cfg.out / "pipeline.png")
    sec.add("", "![pipeline stages](pipeline.png)", "")
    return sec


def _measure(cfg: Config, tmp: str, src: Path, why: str) -> dict:
    """Interleaved child runs; per contender: seconds, rss, stages (lists), vertices, faces."""
    exe = sys.executable
    if not why:
        jobs = {"c1mesh fit": [exe, *C1MESH, "fit", "--smooth", "off", str(src), "-o", f"{tmp}/c1.ply",
                               "--level", str(LEVEL), "--report", "-", "-q"]}
    else:
        jobs = {"library stages": [exe, "-m", "benchmarks.pipeline", "stages", str(src),
                                   f"{tmp}/c1.ply", str(LEVEL)]}
    for d in cfg.poisson_depths:
        jobs[f"Poisson depth {d}"] = [exe, "-m", "benchmarks.pipeline", "poisson", str(src),
                                      f"{tmp}/poisson.ply", str(d)]
    runs = {name: {"seconds": [], "rss": [], "stages": {}} for name in jobs}
    for _ in range(cfg.reps):
        for name, cmd in jobs.items():
            child = run_child(cmd)
            if child.returncode != 0:
                raise RuntimeError(f"{name} failed ({child.returncode}): {child.stderr[-600:]}")
            info = (report_from_stderr(child.stderr) if name == "c1mesh fit"
                    else json.loads(child.stdout))
            r = runs[name]
            r["seconds"].append(child.seconds)
            r["rss"].append(child.peak_rss)
            for stage, s in info["seconds"].items():
                r["stages"].setdefault(stage, []).append(s)
            mesh = info.get("output_mesh", info)
            r["vertices"], r["faces"] = mesh["vertices"], mesh["faces"]
    return runs


def _plot(plot, path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.8), dpi=80)
    names = list(dict.fromkeys(k for _, st in plot for k in st))
    bottom = np.zeros(len(plot))
    for i, stage in enumerate(names):
        h = np.array([st.get(stage, 0.0) for _, st in plot])
        ax.bar(range(len(plot)), h, 0.6, bottom=bottom, label=stage, color=f"C{i % 10}")
        bottom += h
    ax.set_xticks(range(len(plot)), [label for label, _ in plot], fontsize=7)
    ax.set_ylabel("median seconds")
    ax.set_title("end to end, by stage")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ----------------------------------------------------------------------------- children
def _poisson(src: str, dst: str, depth: int) -> dict:
    import open3d as o3d

    seconds, t = {}, time.perf_counter()
    pcd = o3d.io.read_point_cloud(src)
    seconds["read"], t = time.perf_counter() - t, time.perf_counter()
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    seconds["poisson"], t = time.perf_counter() - t, time.perf_counter()
    o3d.io.write_triangle_mesh(dst, mesh)
    seconds["write"] = time.perf_counter() - t
    return {"seconds": seconds, "vertices": len(mesh.vertices), "faces": len(mesh.triangles)}


def _stages(src: str, dst: str, level: int) -> dict:
    from scipy.spatial import Delaunay

    from c1mesh import RSDInterpolator
    from c1mesh.core.cloud import SurfaceMesh
    from c1mesh.formats import read_cloud, write_mesh

    seconds, t = {}, time.perf_counter()

    def lap(name):
        nonlocal t
        seconds[name], t = time.perf_counter() - t, time.perf_counter()
    cloud = read_cloud(src)
    lap("read")
    xy, z = cloud.points[:, :2], cloud.points[:, 2]
    g = -cloud.normals[:, :2] / cloud.normals[:, 2:3]
    lap("normals")
    tri = Delaunay(xy - xy.mean(axis=0)).simplices
    lap("triangulate")
    interp = RSDInterpolator(xy, z, g, triangles=tri)
    lap("interpolate")
    m = interp.refine(level)
    nrm = np.column_stack([-m.gradients, np.ones(len(m.values))])
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    mesh = SurfaceMesh(np.column_stack([m.points, m.values]), m.triangles, nrm)
    lap("refine")
    write_mesh(mesh, dst)
    lap("write")
    return {"seconds": seconds, "vertices": len(mesh.vertices), "faces": len(mesh.faces)}


if __name__ == "__main__":
    mode, src, dst, arg = sys.argv[1:5]
    job = {"poisson": _poisson, "stages": _stages}[mode]
    print(json.dumps(job(src, dst, int(arg))))
