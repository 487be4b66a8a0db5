"""Memory: peak RSS of ``c1mesh fit`` (level 4) against the size of the mesh it produces.

Runs are child processes measured alone (ru_maxrss via wait4). The yardstick is the output
arrays a caller ends up holding: vertices float64 ×3 + normals float64 ×3 per vertex and
faces int32 ×3 per face (int32 suffices below 2**31 vertices; int64 faces would make the
yardstick larger and the ratio look better). The headline peak is the median of the
pipeline section's `c1mesh fit` runs at this N when it made them, else one run here. A
child that only imports the same modules gives the interpreter + imports baseline, and one
child running ``c1mesh.pipeline.fit`` records the peak reached by the end of each stage.
``c1mesh fit`` streams the refined mesh to its output file block by block
(``fit(..., keep_mesh=False)``), so it never holds those arrays; the yardstick stays what
the issue asked for, the size of the mesh produced.

While ``c1mesh.pipeline`` cannot be imported, the child instead builds
``RSDInterpolator(...).refine(4)`` from the same terrain and the section says so.
"""
from __future__ import annotations

import json
import resource
import sys
import tempfile
from pathlib import Path

from benchmarks.common import (C1MESH, MEASURED, Config, Section, fmt_bytes, median,
                               pipeline_status, report_from_stderr, run_child, terrain_cloud,
                               verdict, write_cloud_ply)

LEVEL = 4


def output_bytes(vertices: int, faces: int) -> int:
    return vertices * (3 + 3) * 8 + faces * 3 * 4


def run(cfg: Config) -> Section:
    sec = Section("Memory: peak RSS of a fit")
    why = pipeline_status()
    n, exe = cfg.memory_size, sys.executable
    sec.add(__doc__.split("\n\n")[1].replace("\n", " "), "")
    stages = None
    with tempfile.TemporaryDirectory() as tmp:
        if not why:
            src = Path(tmp) / "in.ply"
            write_cloud_ply(src, *terrain_cloud(n))
            shared = MEASURED.get(("c1mesh fit", n))
            if shared:
                peak, runs = median(shared["rss"]), len(shared["rss"])
                mesh = {"vertices": shared["vertices"], "faces": shared["faces"]}
            else:
                child = run_child([exe, *C1MESH, "fit", str(src), "-o", f"{tmp}/out.ply",
                                   "--level", str(LEVEL), "--report", "-", "-q"])
                if child.returncode != 0:
                    raise RuntimeError(f"c1mesh fit failed: {child.stderr.strip()[-400:]}")
                peak, runs, mesh = child.peak_rss, 1, report_from_stderr(child.stderr)["output_mesh"]
            what = f"`c1mesh fit` of {n:,} points, level {LEVEL} (median of {runs} run(s))"
            staged = run_child([exe, "-m", "benchmarks.memory", "stages", str(src),
                                f"{tmp}/out2.ply", str(LEVEL)])
            stages = json.loads(staged.stdout)["stages"] if staged.returncode == 0 else None
            imports = "import c1mesh.cli, c1mesh.pipeline"
        else:
            what = (f"`RSDInterpolator(...).refine({LEVEL})` of {n:,} points "
                    f"(`c1mesh fit` not available: {why})")
            child = run_child([exe, "-m", "benchmarks.memory", "refine", str(n), str(LEVEL)])
            if child.returncode != 0:
                raise RuntimeError(f"refine child failed: {child.stderr.strip()[-400:]}")
            peak, mesh = child.peak_rss, json.loads(child.stdout)
            imports = "import scipy.spatial, c1mesh"
        base = run_child([exe, "-c", imports]).peak_rss
    size = output_bytes(mesh["vertices"], mesh["faces"])
    r = peak / size
    sec.add(f"Measured: {what}.", "",
            "| output vertices | output faces | output arrays | peak RSS | interpreter + imports | "
            "**peak RSS / output** | (peak − imports) / output |",
            "|---:|---:|---:|---:|---:|---:|---:|",
            f"| {mesh['vertices']:,} | {mesh['faces']:,} | {fmt_bytes(size)} | {fmt_bytes(peak)} | "
            f"{fmt_bytes(base)} | {r:.2f}× | {(peak - base) / size:.2f}× |", "")
    if stages:
        sec.add("Peak RSS reached by the end of each stage (one `c1mesh.pipeline.fit` run in a child):",
                "", "| stage | peak so far | × output |", "|---|---:|---:|",
                *[f"| {name} | {fmt_bytes(rss)} | {rss / size:.2f}× |" for name, rss in stages], "")
    label = "c1mesh fit" if not why else "refine (pipeline n/a)"
    sec.headlines.append((f"memory: peak RSS / output arrays, {label}, N={n:,}, level {LEVEL}",
                          f"{r:.2f}×", "≤ 3×", verdict(r <= 3)))
    return sec


def _peak() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _stages_child(src: str, dst: str, level: int) -> dict:
    """c1mesh.pipeline.fit as the CLI runs it (streaming), recording the peak RSS per stage."""
    from c1mesh.pipeline import FitOptions, fit

    stages = [("interpreter + imports", _peak())]
    fit(src, dst, FitOptions(level=level), on_stage=lambda name: stages.append((name, _peak())),
        keep_mesh=False)
    return {"stages": stages}


def _refine_child(n: int, level: int) -> dict:
    """The fallback child: terrain → Delaunay → RSDInterpolator → refine; output counts."""
    from scipy.spatial import Delaunay

    from c1mesh import RSDInterpolator

    pts, nrm = terrain_cloud(n)
    xy = pts[:, :2]
    interp = RSDInterpolator(xy, pts[:, 2], -nrm[:, :2] / nrm[:, 2:3],
                             triangles=Delaunay(xy - xy.mean(axis=0)).simplices)
    m = interp.refine(level)
    return {"vertices": len(m.values), "faces": len(m.triangles)}


if __name__ == "__main__":
    if sys.argv[1] == "stages":
        print(json.dumps(_stages_child(sys.argv[2], sys.argv[3], int(sys.argv[4]))))
    else:
        print(json.dumps(_refine_child(int(sys.argv[2]), int(sys.argv[3]))))
