"""Point location in an arbitrary (not necessarily Delaunay) triangulation.

A uniform grid of buckets over the mesh's bounding box lists, for each cell, the triangles
whose bounding boxes overlap it. A query point is tested against the candidates of its cell
with exact barycentric coordinates; it belongs to the candidate whose smallest barycentric
coordinate is largest (so points on shared edges resolve deterministically). Works for any
set of non-overlapping triangles: no walking, no Delaunay property assumed.
"""
from __future__ import annotations

import numpy as np

_QUERY_CHUNK = 1 << 19


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
        self.origin = lo.min(axis=0)
        extent = np.maximum(hi.max(axis=0) - self.origin, 1e-300)
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
        """Triangle index (M,) of each query (−1 outside) and barycentrics (M, 3)."""
        tri = np.full(xy.shape[0], -1, dtype=np.int64)
        lam = np.full((xy.shape[0], 3), np.nan)
        for s in range(0, xy.shape[0], _QUERY_CHUNK):
            part = slice(s, s + _QUERY_CHUNK)
            tri[part], lam[part] = self._find_chunk(xy[part])
        return tri, lam

    def barycentric(self, xy: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """Barycentric coordinates (M, 3) of points xy (M, 2) in triangles tri (M,)."""
        lam = np.empty((xy.shape[0], 3))
        corners = self.triangles[tri]
        for k in range(2):
            # λ_k vanishes at vertex k+1, so λ_k(x) = G_k·(x − p_{k+1}) is exact near that edge.
            ref = self.points[corners[:, (k + 1) % 3]]
            lam[:, k] = np.einsum("md,md->m", self.G[tri, k], xy - ref)
        lam[:, 2] = 1.0 - lam[:, 0] - lam[:, 1]
        return lam

    def _find_chunk(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = xy.shape[0]
        tri = np.full(m, -1, dtype=np.int64)
        lam = np.full((m, 3), np.nan)
        finite = np.isfinite(xy).all(axis=1)
        inside_box = finite & np.all(xy >= self.origin - 0.5 * self.cell, axis=1)
        inside_box &= np.all(xy <= self.origin + self.shape * self.cell + 0.5 * self.cell, axis=1)
        query = np.flatnonzero(inside_box)
        ci, cj = self._cell_of(xy[query])
        cell_id = ci * self.shape[1] + cj
        n_cand = self.bucket_start[cell_id + 1] - self.bucket_start[cell_id]
        pair_query = np.repeat(query, n_cand)
        first = np.repeat(self.bucket_start[cell_id] - (np.cumsum(n_cand) - n_cand), n_cand)
        pair_tri = self.bucket_tris[first + np.arange(pair_query.size)]
        pair_lam = self.barycentric(xy[pair_query], pair_tri)
        score = pair_lam.min(axis=1)
        ok = score >= -self.tolerance
        pair_query, pair_tri, pair_lam, score = pair_query[ok], pair_tri[ok], pair_lam[ok], score[ok]
        # Best candidate per query: sort by (query, -score) and take the first of each query.
        order = np.lexsort((-score, pair_query))
        pair_query = pair_query[order]
        keep = np.ones(pair_query.size, dtype=bool)
        keep[1:] = pair_query[1:] != pair_query[:-1]
        best = order[keep]
        tri[pair_query[keep]] = pair_tri[best]
        lam[pair_query[keep]] = pair_lam[best]
        return tri, lam
