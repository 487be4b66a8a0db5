"""Point location in an arbitrary (not necessarily Delaunay) triangulation.

A uniform grid of buckets over the mesh's bounding box lists, for each cell, the triangles
whose bounding boxes overlap it. A query point is tested against the candidates of its cell
with exact barycentric coordinates; it belongs to the candidate whose smallest barycentric
coordinate is largest, the first of the cell's list on a tie (so points on shared edges
resolve deterministically). The search is a kernel (_locate.pyx), query by query. Works for any
set of non-overlapping triangles: no walking, no Delaunay property assumed.
"""
from __future__ import annotations

import numpy as np

from c1mesh.core.threads import parallel_blocks
from c1mesh.core.tile import bounds
from c1mesh.engine import _locate as kernel

_QUERY_BLOCK = 1 << 16
"""Queries per block of the kernel (the blocks run in the thread knob's threads)."""


class TriangleLocator:
    """Find the triangle containing each query point.

    points (N, 2), triangles (T, 3), G (T, 3, 2) barycentric gradients (rsd.barycentric_gradients).
    ``tolerance`` is how far below 0 a barycentric coordinate may be and still count as
    inside (round-off on edges and at vertices).
    """

    def __init__(self, points: np.ndarray, triangles: np.ndarray, G: np.ndarray,
                 tolerance: float = 1e-10):
        self.points, self.triangles, self.G = points, triangles, G
        self.tolerance = tolerance
        corners = points[triangles]                      # (T, 3, 2)
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        self.origin, highest = bounds(lo)[0], bounds(hi)[1]
        extent = np.maximum(highest - self.origin, 1e-300)
        cells_wanted = max(1, triangles.shape[0])
        cell = np.sqrt(extent[0] * extent[1] / cells_wanted) if extent.min() > 0 else extent.max() / cells_wanted
        cell = max(cell, extent.max() / 4096.0)
        self.cell = cell
        self.shape = np.minimum((extent / cell).astype(np.int64) + 1, 4096)
        self._build_buckets(lo, hi)

    def _cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ij = np.floor((xy - self.origin) / self.cell).astype(np.int64)
        return np.clip(ij[:, 0], 0, self.shape[0] - 1), np.clip(ij[:, 1], 0, self.shape[1] - 1)

    def _build_buckets(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """CSR lists: triangles overlapping each grid cell (by bounding box)."""
        i0, j0 = self._cell_of(lo)
        i1, j1 = self._cell_of(hi)
        ni, nj = i1 - i0 + 1, j1 - j0 + 1
        per_tri = ni * nj
        tri = np.repeat(np.arange(len(per_tri)), per_tri)
        start = np.repeat(np.cumsum(per_tri) - per_tri, per_tri)
        local = np.arange(tri.size) - start
        ci = i0[tri] + local % ni[tri]
        cj = j0[tri] + local // ni[tri]
        cell_id = ci * self.shape[1] + cj
        order = np.argsort(cell_id, kind="stable")
        self.bucket_tris = tri[order]
        counts = np.bincount(cell_id, minlength=int(self.shape[0] * self.shape[1]))
        self.bucket_start = np.concatenate([[0], np.cumsum(counts)])

    def find(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Triangle index (M,) of each query (−1 outside) and barycentrics (M, 3) (NaN
        outside). The kernel (_locate.find) takes the queries in blocks of _QUERY_BLOCK in
        the thread knob's threads, each query on its own."""
        xy = np.ascontiguousarray(xy, dtype=np.float64)
        tri = np.full(xy.shape[0], -1, dtype=np.int64)
        lam = np.full((xy.shape[0], 3), np.nan)
        points = np.ascontiguousarray(self.points, dtype=np.float64)
        triangles = np.ascontiguousarray(self.triangles, dtype=np.int64)
        G = np.ascontiguousarray(self.G, dtype=np.float64)
        origin = self.origin.astype(np.float64)

        def block(part: slice) -> None:
            kernel.find(points, triangles, G, self.bucket_start, self.bucket_tris, float(origin[0]),
                        float(origin[1]), float(self.cell), int(self.shape[0]), int(self.shape[1]),
                        float(self.tolerance), xy, part.start, part.stop, tri, lam)
        parallel_blocks(block, xy.shape[0], _QUERY_BLOCK)
        return tri, lam
