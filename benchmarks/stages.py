"""Each stage of a 1M-point `c1mesh fit` next to its floor (issue 23).

    python -m benchmarks.stages make FOLDER          # FOLDER/terrain.laz and FOLDER/normals.ply, 1M points
    python -m benchmarks.stages run FOLDER [REPS] [THREADS]  # the fits and the floors, REPS alternating
                                                     # rounds (3), at THREADS threads (2)
    python -m benchmarks.stages read FOLDER [REPS]   # LAZ read seconds at --threads 1 and 2
    python -m benchmarks.stages table RUN.json       # the markdown table of a run's output
    python -m benchmarks.stages job FOLDER [REPS]    # the LAZ fit against issue 23's floor job (3),
                                                     # and at --threads 1 against 2

The cases are the two of issue 23: the LAZ without normals at level 1 (`--classes 2`) and the
PLY with exact normals at level 4. The fits run as child processes (`c1mesh fit ... --report`),
their stage seconds from the report, their peak RSS from the process. Each round runs every
fit and every floor once, back to back; the table shows medians over the rounds.

The floors (a child process too, the same thread count):
* read: laspy's decode of the LAZ (lazrs), or numpy reading the PLY's bytes;
* normals / gradients: one `cKDTree.query(xy, k, workers=)` of every point (k = 25, the
  height fit's 24 neighbours and the point itself), points in the KD tree's leaf order as
  the height fit has them (about twice as fast as file order), the tree built before the
  clock starts;
* triangulate: Shewchuk's Triangle of the centred x, y (the floor job's; scipy's Delaunay
  where PyPI `triangle` is not installed);
* interpolate: one sort of the 3T edge keys of that triangulation (the limiter's and the
  interpolator's work is a few vectorised passes over the edge table this sort builds);
* write: the output file's bytes written to a file beside it.

The floor job (`job`, issue 23's target: the LAZ fit within 3x of it) is one child process
that reads the LAZ with laspy, triangulates the centred x, y with Shewchuk's Triangle (PyPI
`triangle`, the fastest 2-D Delaunay installable here; its licence forbids commercial use,
so it is a benchmark peer only, installed by benchmarks/install-peers.sh) and writes the
vertices and faces as a binary PLY. Its rounds alternate with the fit's; without `triangle`
the job is skipped and says so. Each round of `job` also fits the LAZ at --threads 1, after
the job, for issue 37's two-thread speed-up (median at 1 thread / median at 2), and says
whether the two outputs were the same bytes.
"""
from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import C1MESH, run_child, terrain_cloud, write_cloud_ply

N = 1_000_000
CASES = {
    "laz": ("terrain.laz", ["--classes", "2", "--level", "1"]),
    "ply": ("normals.ply", ["--level", "4"]),
}


def make(folder: Path) -> None:
    """The two 1M-point inputs: a LAZ terrain of class 2 (benchmarks.tiled_delaunay's) and a
    PLY of common.terrain_cloud with exact normals (the Pipeline section's)."""
    from benchmarks.tiled_delaunay import make as make_laz

    folder.mkdir(parents=True, exist_ok=True)
    make_laz(str(folder / "terrain.laz"), N)
    write_cloud_ply(folder / "normals.ply", *terrain_cloud(N))


def _floor_delaunay(xy: np.ndarray) -> np.ndarray:
    """The triangulate floor's triangles (T, 3) of xy (n, 2): Shewchuk's Triangle (PyPI
    `triangle`, the floor job's, the fastest 2-D Delaunay installable here, one thread),
    or scipy's Delaunay where it is not installed (FLOOR_OF says which was run)."""
    try:
        import triangle
    except ImportError:
        from scipy.spatial import Delaunay
        return Delaunay(xy).simplices.astype(np.int64)
    return triangle.triangulate({"vertices": xy}, "Q")["triangles"].astype(np.int64)


def _floor_child(source: str, output_bytes: int, threads: int) -> None:
    """Print the floors' seconds (JSON) for the input `source` (run in a child process)."""
    from scipy.spatial import cKDTree

    seconds = {}
    start = time.perf_counter()
    if source.endswith(".laz"):
        import laspy

        backend = laspy.LazBackend.Lazrs if threads == 1 else laspy.LazBackend.LazrsParallel
        with laspy.open(source, laz_backend=backend) as reader:
            points = reader.read_points(reader.header.point_count)
        xy = np.column_stack([np.asarray(points.x), np.asarray(points.y)])
    else:
        body = Path(source).read_bytes()
        rows = np.frombuffer(body[body.index(b"end_header\n") + 11:], dtype="<f8").reshape(-1, 6)
        xy = rows[:, :2].copy()
    seconds["read"] = time.perf_counter() - start
    xy -= xy.mean(axis=0)
    leaf_order = xy[cKDTree(xy, balanced_tree=False, compact_nodes=False).indices]
    tree = cKDTree(leaf_order, balanced_tree=False, compact_nodes=False)
    start = time.perf_counter()
    tree.query(leaf_order, k=25, workers=threads)
    seconds["knn"] = time.perf_counter() - start
    del tree, leaf_order
    start = time.perf_counter()
    tri = _floor_delaunay(xy)
    seconds["delaunay"] = time.perf_counter() - start
    start = time.perf_counter()
    n = np.int64(len(xy))
    keys = np.concatenate([np.minimum(tri[:, a], tri[:, b]) * n + np.maximum(tri[:, a], tri[:, b])
                           for a, b in ((0, 1), (1, 2), (2, 0))])
    keys.sort()
    seconds["edge_sort"] = time.perf_counter() - start
    blob = np.zeros(output_bytes, dtype=np.uint8)
    with tempfile.NamedTemporaryFile(dir=Path(source).parent) as out:
        start = time.perf_counter()
        out.write(blob.data)
        out.flush()
        os.fsync(out.fileno())
        seconds["write"] = time.perf_counter() - start
    print(json.dumps(seconds))


def _floor_job_child(source: str, output: str) -> None:
    """Issue 23's floor job (run in a child process): laspy read, Triangle, binary PLY."""
    import laspy
    import triangle

    with laspy.open(source, laz_backend=laspy.LazBackend.LazrsParallel) as reader:
        points = reader.read_points(reader.header.point_count)
    xyz = np.column_stack([np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)])
    faces = triangle.triangulate({"vertices": xyz[:, :2] - xyz[:, :2].mean(axis=0)}, "Q")["triangles"]
    rows = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", 3)])
    rows["n"], rows["v"] = 3, faces
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\nproperty double x\nproperty double y\nproperty double z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(output, "wb") as out:
        out.write(header.encode())
        out.write(xyz.astype("<f8").tobytes())
        out.write(rows.tobytes())


def floor_job(folder: Path, reps: int = 3, threads: int = 2) -> dict:
    """Alternating rounds of the LAZ case's `c1mesh fit`, the floor job and the fit at one
    thread, all child processes: {"fit": [wall s], "job": [wall s], "fit_1": [wall s],
    "ratio": median fit / median job, "threads_ratio": median fit_1 / median fit,
    "same_bytes": the two fits' outputs equal in every round}, or {"skipped": why}
    without PyPI `triangle`."""
    import importlib.util

    if importlib.util.find_spec("triangle") is None:
        return {"skipped": "PyPI triangle is not installed (benchmarks/install-peers.sh installs it)"}
    code = "import sys; from benchmarks.stages import _floor_job_child; _floor_job_child(*sys.argv[1:3])"
    walls, same = {"fit": [], "job": [], "fit_1": []}, True
    out = folder / "laz.out.ply"
    for _ in range(reps):
        walls["fit"].append(_fit(folder, "laz", threads)["wall"])
        written = out.read_bytes()
        child = run_child([sys.executable, "-c", code, str(folder / CASES["laz"][0]),
                           str(folder / "laz.floor.ply")])
        if child.returncode:
            raise RuntimeError(f"the floor job failed: {child.stderr[-500:]}")
        walls["job"].append(child.seconds)
        walls["fit_1"].append(_fit(folder, "laz", 1)["wall"])
        same = same and out.read_bytes() == written
        print(json.dumps({name: runs[-1] for name, runs in walls.items()}), file=sys.stderr)
    median = {name: statistics.median(runs) for name, runs in walls.items()}
    return {**walls, "ratio": median["fit"] / median["job"], "threads_ratio": median["fit_1"] / median["fit"],
            "same_bytes": same}


def _fit(folder: Path, case: str, threads: int) -> dict:
    """One `c1mesh fit` child of a case: its report's stage seconds, wall, peak RSS, output size."""
    name, options = CASES[case]
    out, report = folder / f"{case}.out.ply", folder / f"{case}.report.json"
    child = run_child([sys.executable, *C1MESH, "fit", "--smooth", "off", str(folder / name), *options, "-o", str(out),
                       "--report", str(report), "--threads", str(threads), "-q"])
    if child.returncode:
        raise RuntimeError(f"c1mesh fit {case} failed: {child.stderr[-500:]}")
    facts = json.loads(report.read_text())
    return {"seconds": facts["seconds"], "wall": child.seconds, "rss": child.peak_rss,
            "points": facts.get("points"), "output_bytes": out.stat().st_size}


def _floors(folder: Path, case: str, output_bytes: int, threads: int) -> dict:
    """The floors of a case, measured in a child process."""
    code = ("import sys; from benchmarks.stages import _floor_child; "
            "_floor_child(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))")
    child = run_child([sys.executable, "-c", code, str(folder / CASES[case][0]), str(output_bytes), str(threads)])
    if child.returncode:
        raise RuntimeError(f"floors of {case} failed: {child.stderr[-500:]}")
    return json.loads(child.stdout)


def run(folder: Path, reps: int = 3, threads: int = 2) -> dict:
    """Medians over `reps` alternating rounds of both fits and both floors."""
    rounds = []
    for _ in range(reps):
        one = {}
        for case in CASES:
            fit = _fit(folder, case, threads)
            one[case] = {"fit": fit, "floors": _floors(folder, case, fit["output_bytes"], threads)}
        rounds.append(one)
        print(json.dumps(one), file=sys.stderr)
    return rounds


def read_seconds(folder: Path, reps: int = 3) -> dict:
    """c1mesh.formats.las.read_las seconds of the LAZ under 1 and 2 threads, alternating."""
    from c1mesh.core.threads import limit
    from c1mesh.formats.las import read_las

    data = (folder / "terrain.laz").read_bytes()
    seconds = {1: [], 2: []}
    for _ in range(reps):
        for threads in seconds:
            with limit(threads):
                start = time.perf_counter()
                read_las(data, "terrain.laz")
                seconds[threads].append(time.perf_counter() - start)
    return {threads: {"runs": runs, "median": statistics.median(runs)} for threads, runs in seconds.items()}


FLOOR_OF = {"read": ("read", "laspy/lazrs decode (PLY: numpy reads the bytes)"),
            "normals": ("knn", "one cKDTree.query, k = 25"),
            "gradients": ("knn", "one cKDTree.query, k = 25"),
            "triangulate": ("delaunay", "Triangle, one thread"),
            "interpolate": ("edge_sort", "one sort of the 3T edge keys"),
            "write": ("write", "the output's bytes to disk, fsync")}


def table(rounds: list[dict]) -> str:
    """Markdown: per case, each stage's median seconds next to its floor's, and the wall,
    peak RSS and RSS per input point (medians over the rounds)."""
    med = statistics.median
    lines = ["| case | stage | c1mesh fit (s) | floor | floor (s) | stage / floor |",
             "|---|---|---:|---|---:|---:|"]
    for case in CASES:
        stages = rounds[0][case]["fit"]["seconds"]
        for stage in stages:
            took = med(r[case]["fit"]["seconds"][stage] for r in rounds)
            key, what = FLOOR_OF.get(stage, (None, "—"))
            no_search = stage in ("normals", "gradients") and (case == "ply" or stage == "gradients")
            if key is None or no_search:      # the PLY's gradients come from its normals; a LAZ's in "normals"
                lines.append(f"| {case} | {stage} | {took:.2f} | — | | |")
                continue
            floor = med(r[case]["floors"][key] for r in rounds)
            lines.append(f"| {case} | {stage} | {took:.2f} | {what} | {floor:.2f} | {took / floor:.1f}× |")
        wall = med(r[case]["fit"]["wall"] for r in rounds)
        rss = med(r[case]["fit"]["rss"] for r in rounds)
        points = rounds[0][case]["fit"]["points"]["read"]
        lines.append(f"| {case} | **wall** (child process) | {wall:.2f} | peak RSS {rss / 2**30:.2f} GiB, "
                     f"{rss / points:.0f} bytes per input point | | |")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    command, folder = argv[0], Path(argv[1])
    reps = int(argv[2]) if len(argv) > 2 else 3
    if command == "make":
        make(folder)
    elif command == "run":
        print(json.dumps(run(folder, reps, int(argv[3]) if len(argv) > 3 else 2), indent=1))
    elif command == "table":
        print(table(json.loads(folder.read_text())))
    elif command == "job":
        print(json.dumps(floor_job(folder, reps), indent=1))
    elif command == "read":
        print(json.dumps(read_seconds(folder, reps), indent=1))
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
