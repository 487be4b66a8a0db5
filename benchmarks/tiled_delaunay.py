"""The tiled triangulation stage of a LAZ survey with bounded memory (not a suite section).

    python -m benchmarks.tiled_delaunay make OUT.laz N        # synthetic terrain, class 2
    /usr/bin/time -v python -m benchmarks.tiled_delaunay run IN.laz [POINTS_PER_TILE]
    /usr/bin/time -v python -m benchmarks.tiled_delaunay whole IN.laz   # the in-memory peer

`run` streams the LAZ by laspy's chunk iterator: stages.frame.frame_of_chunks (no
normals), buffered_delaunay.streamed_hull, tile_spill.spill, then
buffered_delaunay.trimmed_delaunay with max_edge "auto", each tile's triangles saved to
a temporary .npy file; it prints the triangle count, max_edge and the seconds of each
stage. `whole` does the same stage in memory (choose_frame, delaunay, trim's long-edge
rule). Numbers: docs/tiles.md.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time

import numpy as np

CHUNK = 1_000_000


def make(path: str, n: int) -> None:
    """A LAZ of n points at ~4 per m^2 on smooth terrain with 2 cm noise, all class 2."""
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [500000, 4000000, 0]
    rng = np.random.default_rng(0)
    side = np.sqrt(n / 4.0)
    with laspy.open(path, mode="w", header=header) as writer:
        for start in range(0, n, CHUNK):
            m = min(CHUNK, n - start)
            x, y = rng.uniform(0, side, m), rng.uniform(0, side, m)
            z = 100 + 10 * np.sin(x / 150) * np.cos(y / 200) + 3 * np.sin(x / 37 + y / 53) + rng.normal(0, 0.02, m)
            record = laspy.ScaleAwarePointRecord.zeros(m, header=header)
            record.x, record.y, record.z = x + 500000, y + 4000000, z
            record.classification = np.full(m, 2, np.uint8)
            writer.write_points(record)


def _world_chunks(path: str):
    import laspy

    with laspy.open(path) as reader:
        for chunk in reader.chunk_iterator(CHUNK):
            keep = np.asarray(chunk.classification) == 2
            yield np.column_stack([np.asarray(chunk.x)[keep], np.asarray(chunk.y)[keep], np.asarray(chunk.z)[keep]])


def run(path: str, per_tile: int = 500_000) -> None:
    import c1mesh.survey.buffered_delaunay as bd
    from c1mesh.core.outputs import register_temp, unregister_temp
    from c1mesh.stages.frame import frame_of_chunks as streamed_frame
    from c1mesh.survey.tile_spill import spill

    t0 = time.perf_counter()
    frame = streamed_frame(lambda: ((p, None) for p in _world_chunks(path)))
    t1 = time.perf_counter()
    bounds = {"lo": np.full(2, np.inf), "hi": np.full(2, -np.inf), "n": 0}

    def plane_chunks():
        start = 0
        for points in _world_chunks(path):
            xy = frame.to_local(points)[:, :2]
            bounds["lo"], bounds["hi"] = np.minimum(bounds["lo"], xy.min(0)), np.maximum(bounds["hi"], xy.max(0))
            yield np.arange(start, start + len(xy)), xy
            start += len(xy)
        bounds["n"] = start
    hull = bd.streamed_hull(plane_chunks())
    n = bounds["n"]
    side = int(np.ceil(np.sqrt(n / per_tile)))
    grid = bd.TileGrid((*bounds["lo"], *bounds["hi"]), side, side)
    t2 = time.perf_counter()
    folder = tempfile.gettempdir()
    saved: list[tuple[str, str]] = []

    def keep(result):
        names = (os.path.join(folder, f".tiled-delaunay-{os.getpid()}-{result.tile}.npy"),
                 os.path.join(folder, f".tiled-delaunay-{os.getpid()}-{result.tile}-longest.npy"))
        for name in names:
            register_temp(name)
        saved.append(names)
        np.save(names[0], result.triangles)
        np.save(names[1], result.longest)
        return result.rounds, result.read
    try:
        with spill(_world_chunks(path), frame, grid, folder, "tiled-delaunay") as tiles:
            t3 = time.perf_counter()
            max_edge, kept = bd.trimmed_delaunay(tiles.read, grid, n, hull, keep=keep)
            t4 = time.perf_counter()
        count = sum(int((np.load(longest) <= max_edge).sum()) for _, longest in saved)
    finally:
        for names in saved:
            for name in names:
                if os.path.exists(name):
                    os.unlink(name)
                unregister_temp(name)
    print(f"points {n} tiles {len(grid)} triangles {count} max_edge {max_edge:.6f} "
          f"max_rounds {max(r for r, _ in kept)} max_read {max(m for _, m in kept)}")
    print(f"frame {t1 - t0:.1f} s, hull {t2 - t1:.1f} s, spill {t3 - t2:.1f} s, "
          f"triangulate {t4 - t3:.1f} s, total {t4 - t0:.1f} s")


def whole(path: str) -> None:
    from c1mesh.stages.frame import choose_frame
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.stages.trim import trim

    t0 = time.perf_counter()
    points = np.concatenate(list(_world_chunks(path)))
    xy = choose_frame(points).to_local(points)[:, :2]
    del points
    t1 = time.perf_counter()
    triangles = delaunay(xy)
    _, report = trim(xy, triangles, max_edge="auto", min_circle_ratio=0.0)
    t2 = time.perf_counter()
    print(f"points {len(xy)} triangles {len(triangles) - report.removed['long_edge']} "
          f"max_edge {report.max_edge:.6f}")
    print(f"read+frame {t1 - t0:.1f} s, triangulate+trim {t2 - t1:.1f} s")


if __name__ == "__main__":
    command, args = sys.argv[1], sys.argv[2:]
    if command == "make":
        make(args[0], int(args[1]))
    elif command == "run":
        run(args[0], *(int(a) for a in args[1:]))
    else:
        whole(args[0])
