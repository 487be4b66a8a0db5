"""Memory: peak RSS of ``c1mesh fit`` per input point and per output vertex, levels 2, 4, 8.

Runs are child processes measured alone (ru_maxrss via wait4), each ``c1mesh fit`` of the
same N-point terrain (common.terrain_cloud, a binary PLY with normals) at one level,
writing a binary PLY to stdout, which goes to /dev/null (so no file of gigabytes is
written; the mesh is streamed block by block either way, ``fit(..., keep_mesh=False)``,
so the process never holds the output arrays). A child that only imports the same
modules gives the interpreter + imports baseline; "above baseline" subtracts it. One more
child running ``c1mesh.pipeline.run.fit`` at level 4 records the peak reached by the end of
each stage.

While ``c1mesh.pipeline.driver`` cannot be imported, the child instead builds
``RSDInterpolator(...).refine(L)`` from the same terrain and the section says so.
"""
from __future__ import annotations

import json
import resource
import sys
import tempfile
from pathlib import Path

from benchmarks.common import (C1MESH, Config, Section, fmt_bytes, pipeline_status,
                               report_from_stderr, run_child, terrain_cloud, write_cloud_ply)

STAGE_LEVEL = 4


def run(cfg: Config) -> Section:
    sec = Section("Memory: peak RSS of a fit")
    why = pipeline_status()
    n, exe = cfg.memory_size, sys.executable
    sec.add(__doc__.split("\n\n")[1].replace("\n", " "), "")
    rows, stages = [], None
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "in.ply"
        write_cloud_ply(src, *terrain_cloud(n))
        if not why:
            imports = "import c1mesh.cli, c1mesh.pipeline.driver"
            what = f"`c1mesh fit` of {n:,} points ({fmt_bytes(src.stat().st_size)} binary PLY)"
        else:
            imports = "import scipy.spatial, c1mesh"
            what = (f"`RSDInterpolator(...).refine(L)` of {n:,} points "
                    f"(`c1mesh fit` not available: {why})")
        base = run_child([exe, "-c", imports]).peak_rss
        for level in cfg.memory_levels:
            peak, vertices = _one_level(exe, src, n, level, why)
            rows.append((level, vertices, peak))
        if not why:
            staged = run_child([exe, "-m", "benchmarks.memory", "stages", str(src),
                                f"{tmp}/out2.ply", str(STAGE_LEVEL)])
            stages = json.loads(staged.stdout)["stages"] if staged.returncode == 0 else None
    sec.add(f"Measured: {what}; interpreter + imports: {fmt_bytes(base)}.", "",
            "| level | output vertices | peak RSS | above baseline | **bytes per input point** "
            "| bytes per output vertex | above baseline: per input point | per output vertex |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|")
    for level, vertices, peak in rows:
        sec.add(f"| {level} | {vertices:,} | {fmt_bytes(peak)} | {fmt_bytes(peak - base)} | "
                f"{peak / n:,.0f} | {peak / vertices:,.0f} | {(peak - base) / n:,.0f} | "
                f"{(peak - base) / vertices:,.1f} |")
        sec.headlines.append((f"memory: peak RSS per input point, N={n:,}, level {level}",
                              f"{peak / n:,.0f} B ({(peak - base) / n:,.0f} B above imports)",
                              "(none set)", "—"))
    sec.add("")
    if stages:
        sec.add(f"Peak RSS reached by the end of each stage (one `c1mesh.pipeline.run.fit` run at "
                f"level {STAGE_LEVEL} in a child, writing a file):", "",
                "| stage | peak so far | per input point |", "|---|---:|---:|",
                *[f"| {name} | {fmt_bytes(rss)} | {rss / n:,.0f} B |" for name, rss in stages], "")
    return sec


def _one_level(exe: str, src: Path, n: int, level: int, why: str) -> tuple[int, int]:
    """(peak RSS, output vertices) of one child fitting `src` at `level`."""
    if not why:
        child = run_child([exe, *C1MESH, "fit", "--smooth", "off", str(src), "-o", "-", "--level", str(level),
                           "--report", "-", "-q"], discard_stdout=True)
        if child.returncode != 0:
            raise RuntimeError(f"c1mesh fit --level {level} failed: {child.stderr.strip()[-400:]}")
        return child.peak_rss, report_from_stderr(child.stderr)["output_mesh"]["vertices"]
    child = run_child([exe, "-m", "benchmarks.memory", "refine", str(n), str(level)])
    if child.returncode != 0:
        raise RuntimeError(f"refine child failed: {child.stderr.strip()[-400:]}")
    return child.peak_rss, json.loads(child.stdout)["vertices"]


def _peak() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _stages_child(src: str, dst: str, level: int) -> dict:
    """c1mesh.pipeline.run.fit as the CLI runs it (streaming), recording the peak RSS per stage."""
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    stages = [("interpreter + imports", _peak())]
    fit(src, dst, FitOptions(smooth="off", level=level), on_stage=lambda name: stages.append((name, _peak())),
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
