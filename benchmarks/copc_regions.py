"""What a COPC region read saves: ``python -m benchmarks.copc_regions [--grid N] FILE...``.

For each COPC file, the header's x/y extent is cut into an N x N grid of tiles (default
4, as a tiled fit would cut it) and each tile is read twice: by bounds
(read_cloud(..., bounds=tile): only the octree nodes meeting the tile are fetched and
decoded) and as a whole read filtered by numpy (what a reader without the octree does).
Prints, per file, the mean over tiles of the nodes, compressed bytes and points a region
read decodes, the points it keeps, and both read times; checks that both reads give the
same points.

``python -m benchmarks.copc_regions make OUT.copc.laz POINTS`` writes a synthetic terrain
COPC for this (4 points per m², a smooth surface plus 2 cm noise, class 2). It needs
copclib (``pip install copclib``; not a c1mesh dependency), which writes the LAZ chunks,
the hierarchy and the header; the octree is filled here: each point gets a level
(three quarters at the deepest, a quarter of the rest one level up, ...), and every cube
that holds deeper points is given one point of its own level so that the hierarchy
reaches every node.
"""
from __future__ import annotations

import sys
import time

import numpy as np


def measure(path: str, grid: int = 4) -> dict:
    """Mean per-tile cost of region reads against whole reads of the COPC file at path."""
    import laspy

    from c1mesh.formats import read_cloud
    from c1mesh.formats.copc import inside, region_cost

    with laspy.open(path) as reader:
        lo, hi = reader.header.mins[:2], reader.header.maxs[:2]
    start = time.perf_counter()
    whole = read_cloud(path)
    whole_seconds = time.perf_counter() - start
    everything = region_cost(path, None)
    rows = []
    for i in range(grid):
        for j in range(grid):
            a = lo + (hi - lo) * np.array([i, j]) / grid
            b = lo + (hi - lo) * np.array([i + 1, j + 1]) / grid
            box = (float(a[0]), float(a[1]), float(b[0]), float(b[1]))
            start = time.perf_counter()
            part = read_cloud(path, bounds=box)
            seconds = time.perf_counter() - start
            keep = inside(whole.points[:, 0], whole.points[:, 1], box)
            if not np.array_equal(part.points, whole.points[keep]):
                raise AssertionError(f"tile {i},{j}: the region read differs from the filtered whole read")
            cost = region_cost(path, box)
            rows.append((len(cost.nodes), cost.bytes, cost.points, len(part), seconds))
    r = np.array(rows, dtype=float).mean(axis=0)
    return {"file": path, "points": len(whole), "nodes": len(everything.nodes), "bytes": everything.bytes,
            "whole_read_s": whole_seconds, "tile_nodes": r[0], "tile_bytes": r[1], "tile_decoded": r[2],
            "tile_kept": r[3], "tile_read_s": r[4]}


def make(path: str, count: int, levels: int = 5, seed: int = 1) -> None:
    """A synthetic terrain COPC of `count` points at `path` (module docstring)."""
    import copclib as copc

    rng = np.random.default_rng(seed)
    side = np.sqrt(count / 4.0)
    x, y = rng.uniform(0, side, count), rng.uniform(0, side, count)
    z = 20 * np.sin(x / 37) * np.cos(y / 53) + 0.02 * rng.standard_normal(count) + 100
    half = side / 2
    finest = side / 2 ** levels
    cells = [np.minimum((v / finest).astype(np.int64), 2 ** levels - 1) for v in (x, y, z - (100 - half))]

    def key(k, rows):
        return (cells[0][rows] >> (levels - k) << 40) | (cells[1][rows] >> (levels - k) << 20) \
            | (cells[2][rows] >> (levels - k))
    level = levels - np.minimum(levels, np.floor(-np.log(rng.uniform(size=count)) / np.log(4)).astype(int))
    every = np.arange(count)
    for k in range(levels):          # every cube holding deeper points gets a point of its own
        deeper = every[level > k]
        orphan = ~np.isin(key(k, deeper), np.unique(key(k, every[level == k])))
        _, first = np.unique(key(k, deeper[orphan]), return_index=True)
        level[deeper[orphan][first]] = k
    config = copc.CopcConfigWriter(6, copc.Vector3(0.01, 0.01, 0.01), copc.Vector3(0, 0, 0))
    config.copc_info.center_x, config.copc_info.center_y, config.copc_info.center_z = half, half, 100.0
    config.copc_info.halfsize, config.copc_info.spacing = half, side / 64
    config.las_header.min = copc.Vector3(0, 0, float(z.min()))
    config.las_header.max = copc.Vector3(side, side, float(z.max()))
    writer = copc.FileWriter(path, config)
    for k in range(levels + 1):
        rows = every[level == k]
        keys = key(k, rows)
        order = np.argsort(keys, kind="stable")
        rows, keys = rows[order], keys[order]
        starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        for s, e in zip(starts, np.r_[starts[1:], len(rows)]):
            node = rows[s:e]
            points = copc.Points(writer.copc_config.las_header)
            for _ in node:
                points.AddPoint(points.CreatePoint())
            points.x, points.y, points.z = x[node].tolist(), y[node].tolist(), z[node].tolist()
            points.classification = [2] * len(node)
            k_x, k_y, k_z = (int(c[node[0]] >> (levels - k)) for c in cells)
            writer.AddNode(copc.VoxelKey(k, k_x, k_y, k_z), points)
    writer.Close()


def main(argv: list[str]) -> int:
    if argv[:1] == ["make"]:
        make(argv[1], int(argv[2]))
        return 0
    grid = 4
    if argv[:1] == ["--grid"]:
        grid, argv = int(argv[1]), argv[2:]
    print("| file | points | nodes | MB | tiles | per tile: nodes | MB fetched | points decoded | points kept "
          "| region read s | whole read s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for path in argv:
        m = measure(path, grid)
        print(f"| {m['file']} | {m['points']:,} | {m['nodes']} | {m['bytes'] / 1e6:.2f} | {grid}x{grid} "
              f"| {m['tile_nodes']:.1f} | {m['tile_bytes'] / 1e6:.3f} ({m['tile_bytes'] / m['bytes']:.2f}) "
              f"| {m['tile_decoded']:,.0f} ({m['tile_decoded'] / m['points']:.2f}) | {m['tile_kept']:,.0f} "
              f"| {m['tile_read_s']:.3f} | {m['whole_read_s']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
