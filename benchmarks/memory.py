"""Memory: peak RSS of ``c1mesh fit`` (level 4) against the size of the mesh it produces.

The run is a child process measured alone (os.wait4 → ru_maxrss). The yardstick is the
output arrays a caller ends up holding: vertices float64 ×3 + normals float64 ×3 per vertex
and faces int32 ×3 per face (int32 suffices below 2**31 vertices; int64 faces would make
the yardstick larger and the ratio look better). A second child that only imports the
same modules gives the interpreter + imports baseline.

While ``c1mesh.pipeline`` cannot be imported, the child instead builds
``RSDInterpolator(...).refine(4)`` from the same terrain (``python -m benchmarks.memory
refine N LEVEL``) and the section says so.
"""
from __future__ import annotations

import json
import resource
import sys
import tempfile
from pathlib import Path

from benchmarks.common import (C1MESH, Config, Section, fmt_bytes, pipeline_status,
                               report_from_stderr, run_child,
                               terrain_cloud, verdict, write_cloud_ply)

LEVEL = 4


def output_bytes(vertices: int, faces: int) -> int:
    return vertices * (3 + 3) * 8 + faces * 3 * 4


def run(cfg: Config) -> Section:
    sec = Section("Memory: peak RSS of a fit")
    why = pipeline_status()
    n, exe = cfg.memory_size, sys.executable
    sec.add(__doc__.split("\n\n")[1].replace("\n", " "), "")
    with tempfile.TemporaryDirectory() as tmp:
        if not why:
            what = f"`c1mesh fit` of {n:,} points, level {LEVEL}"
            src = Path(tmp) / "in.ply"
            write_cloud_ply(src, *terrain_cloud(n))
            child = run_child([exe, *C1MESH, "fit", str(src), "-o", f"{tmp}/out.ply",
                               "--level", str(LEVEL), "--report", "-", "-q"])
            mesh = report_from_stderr(child.stderr)["output_mesh"] if child.returncode == 0 else None
            imports = "import c1mesh.cli, c1mesh.pipeline"
        else:
            what = (f"`RSDInterpolator(...).refine({LEVEL})` of {n:,} points "
                    f"(`c1mesh fit` not available: {why})")
            child = run_child([exe, "-m", "benchmarks.memory", "refine", str(n), str(LEVEL)])
            mesh = json.loads(child.stdout) if child.returncode == 0 else None
            imports = "import scipy.spatial, c1mesh"
        base = run_child([exe, "-c", imports])
    if mesh is None:
        sec.add(f"The run failed ({child.returncode}): `{child.stderr.strip()[-300:]}`", "")
        return sec
    size = output_bytes(mesh["vertices"], mesh["faces"])
    r = child.peak_rss / size
    sec.add(f"Measured: {what}.", "",
            "| output vertices | output faces | output arrays | peak RSS | interpreter + imports | "
            "**peak RSS / output** | (peak − imports) / output |",
            "|---:|---:|---:|---:|---:|---:|---:|",
            f"| {mesh['vertices']:,} | {mesh['faces']:,} | {fmt_bytes(size)} | "
            f"{fmt_bytes(child.peak_rss)} | {fmt_bytes(base.peak_rss)} | {r:.2f}× | "
            f"{(child.peak_rss - base.peak_rss) / size:.2f}× |", "")
    label = "c1mesh fit" if not why else "refine (pipeline n/a)"
    sec.headlines.append((f"memory: peak RSS / output arrays, {label}, N={n:,}, level {LEVEL}",
                          f"{r:.2f}×", "≤ 3×", verdict(r <= 3)))
    return sec


def _refine_child(n: int, level: int) -> dict:
    """The fallback child: terrain → Delaunay → RSDInterpolator → refine; output counts."""
    from scipy.spatial import Delaunay

    from c1mesh import RSDInterpolator

    pts, nrm = terrain_cloud(n)
    xy = pts[:, :2]
    interp = RSDInterpolator(xy, pts[:, 2], -nrm[:, :2] / nrm[:, 2:3],
                             triangles=Delaunay(xy - xy.mean(axis=0)).simplices)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    m = interp.refine(level)
    return {"vertices": len(m.values), "faces": len(m.triangles), "rss_before_refine": before}


if __name__ == "__main__":
    print(json.dumps(_refine_child(int(sys.argv[2]), int(sys.argv[3]))))
