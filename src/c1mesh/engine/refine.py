"""Uniform refinement of an RSD spline: every triangle split into level² sub-triangles.

Output point numbering (input vertex i is output point i, and every point on a shared
edge or vertex exists once, so the mesh is conforming and crack-free):

  [0, N)     the N input points (values and gradients exactly the data)
  then, triangle by triangle: for k = 0, 1, 2, the L−1 points inside the triangle's
             edge k (opposite vertex k) if the triangle owns that edge, ordered from
             its vertex k+1 towards its vertex k+2; then its (L−1)(L−2)/2 interior points.

Each edge has one owner triangle (EdgeTable.owner), which evaluates the points on it; the
other triangle only refers to them. Blocks of consecutive triangles (CHUNK_ENTRIES
lattice points per block) are the unit of work: a block reads its own contiguous rows of
the coefficients, so nothing is gathered at random except vertex coordinates, and its
output points form one contiguous range. That range is handed to the caller as a
`VertexBlock`, which is what lets `c1mesh fit` stream a refined mesh straight to a file
without holding it (`Refinement.vertex_blocks`, `Refinement.face_blocks`), while
`Refinement.mesh` copies the blocks into full arrays.

Values and gradients are matrix products: coefficients (c × 21) @ basis (21 × P) over all
P non-vertex lattice points of every triangle of a block, with basis matrices built once
per level and tuple (rsd.basis); point coordinates are corner coordinates (c × 6) @ a
fixed blending matrix (6 × 2P). The points each triangle owns (owned edges, interior)
are then gathered straight into the output by one index list per block. Every product
runs over the full block height, a short last block padded, so that a point's bits do not
depend on the block it falls in (_BlockBuffers; `--seamless -O` tiles rely on it). Evaluating the
points of non-owned edges too wastes some arithmetic, but one longer product per block
beats selecting the inputs of each edge slot and three short products (measured at 1M
points, level 4, one thread: vertices 0.56 → 0.48 s; np.take of the kept indices rather
than np.compress per array: level 4 0.60 → 0.53 s, level 8 1.52 → 1.25 s, two threads).

`mesh` splits the blocks into contiguous ranges, one per worker thread (numpy releases
the GIL in its kernels); each worker pre-faults and fills its own slices of the outputs.

Memory: `Refinement` itself holds O(E + T) numbering arrays; a pass over the blocks adds
buffers for CHUNK_ENTRIES lattice points (≈ 12 MiB per thread, independent of T); `mesh()` adds
the outputs (M values, 2M gradients, 2M coordinates, 3·L²·T indices).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np

from c1mesh.engine import rsd
from c1mesh.core.platform_memory import madvise as _madvise
from c1mesh.engine.schemes import ShapeTuple
from c1mesh.core.threads import blas_threads, run_parallel
from c1mesh.core.threads import workers as thread_count
from c1mesh.engine.topology import EdgeTable

MAX_WORKERS = 4
"""Most threads Refinement.mesh uses, whatever c1mesh.core.threads.workers() allows: each
holds its own block temporaries (a basis block alone is 21 x CHUNK_ENTRIES doubles, 22 MB),
and it was only measured up to 2 cores."""

CHUNK_ENTRIES = 1 << 17
"""Lattice points (all (L+1)(L+2)/2 of each triangle) per block.

Smaller blocks keep temporaries in cache but cost more numpy calls per point, and two
worker threads then contend for the GIL between calls. Measured, 1M points, level 4,
two workers: 2**13 1.01 s, 2**15 0.62 s, 2**17 0.49 s, 2**18 0.47 s, 2**19 0.53 s
(level 8: 2**15 1.84 s, 2**17 1.53 s)."""


@dataclass
class RefinedMesh:
    """A refined triangle mesh with spline values and gradients at its points.

    points (M, 2), triangles (K, 3) counter-clockwise when the input triangles are,
    values (M,), gradients (M, 2), parent (K,) the input triangle of each sub-triangle
    (sub-triangles are stored parent by parent, level² each; filled by a second thread
    while refine computes, or on first use).
    Index arrays are int32 when M < 2**31 (halves memory), else int64.
    """

    points: np.ndarray
    triangles: np.ndarray
    values: np.ndarray
    gradients: np.ndarray
    level: int
    refinement: "Refinement" = field(repr=False, default=None)

    @property
    def parent(self) -> np.ndarray:
        if getattr(self, "_parent", None) is None:
            count = self.triangles.shape[0] // (self.level * self.level)
            self._parent = np.repeat(np.arange(count, dtype=self.triangles.dtype), self.level * self.level)
        return self._parent

    def linear(self, field_values: np.ndarray) -> np.ndarray:
        """Piecewise-linear interpolation of per-input-vertex data onto the refined points.

        field_values: (N,) or (N, d) array over the input points (e.g. colours). Returns
        (M,) or (M, d) float64: input points keep their data exactly, edge and interior
        points get the barycentric blend of their parent's corners.
        """
        data = np.asarray(field_values, dtype=float)
        flat = data.reshape(data.shape[0], -1)
        out = np.empty((self.points.shape[0], flat.shape[1]))
        for block in self.refinement.vertex_blocks(fields=[flat], spline=False):
            out[block.start:block.stop] = block.fields[0]
        return out.reshape((out.shape[0],) + data.shape[1:])


@dataclass(frozen=True)
class LatticePattern:
    """Barycentric lattice of one triangle at a level L: points a/L with a0 + a1 + a2 = L.

    lattice (P, 3) integer coordinates; index_of (L+1, L+1) maps (a1, a2) to a lattice row;
    interior rows; edge_rows[k] rows of the points strictly inside the edge opposite vertex
    k, ordered from vertex k+1 towards vertex k+2; template (L², 3) sub-triangles as lattice
    rows, same orientation as the parent.
    """

    level: int
    lattice: np.ndarray
    index_of: np.ndarray
    interior: np.ndarray
    edge_rows: tuple
    template: np.ndarray


def lattice_pattern(level: int) -> LatticePattern:
    L = level
    a1, a2 = np.meshgrid(np.arange(L + 1), np.arange(L + 1), indexing="ij")
    mask = a1 + a2 <= L
    a1, a2 = a1[mask], a2[mask]
    lattice = np.stack([L - a1 - a2, a1, a2], axis=1)
    index_of = np.full((L + 1, L + 1), -1, dtype=np.int64)
    index_of[a1, a2] = np.arange(a1.size)
    interior = np.flatnonzero((lattice > 0).all(axis=1))
    s = np.arange(1, L)
    edge_rows = []
    for k in range(3):
        coords = np.zeros((L - 1, 3), dtype=np.int64)
        coords[:, (k + 1) % 3] = L - s
        coords[:, (k + 2) % 3] = s
        edge_rows.append(index_of[coords[:, 1], coords[:, 2]])
    up = [(i, j) for i in range(L) for j in range(L - i)]
    down = [(i, j) for i in range(L - 1) for j in range(L - 1 - i)]
    template = [(index_of[i, j], index_of[i + 1, j], index_of[i, j + 1]) for i, j in up]
    template += [(index_of[i + 1, j], index_of[i + 1, j + 1], index_of[i, j + 1]) for i, j in down]
    return LatticePattern(L, lattice, index_of, interior, tuple(edge_rows), np.array(template))


def refined_counts(points: int, edges: int, triangles: int, level: int) -> tuple[int, int]:
    """(vertices, faces) of the level-L refinement of a triangulation with these counts of
    points, edges and triangles, without building it: the points themselves, L − 1 inside
    every edge and (L − 1)(L − 2)/2 inside every triangle (each once: the numbering of
    the module docstring); L² faces per triangle. Python ints, so the counts of outputs too
    large for 32-bit indices come out exact (the writers' limits: c1mesh.formats)."""
    L = int(level)
    return (int(points) + int(edges) * (L - 1) + int(triangles) * ((L - 1) * (L - 2) // 2),
            int(triangles) * L * L)


def fewest_refined_vertices(triangles: int, level: int) -> int:
    """The fewest vertices the level-L refinement of any triangulation of T > 0 triangles
    has (refined_counts of its fewest points and edges: at least 3 points, and at least
    3T/2 edges, as an edge lies in at most two triangles). With B boundary edges the
    count is (T·L² + B·L)/2 + (components − holes), so this is short by about B·L/2 + T/2,
    a small fraction of a large mesh; for a caller that knows T but not the edges (the
    tiled fit)."""
    if triangles <= 0:
        return 0
    return refined_counts(3, -(-3 * int(triangles) // 2), triangles, level)[0]


@dataclass
class VertexBlock:
    """Refined points [start, stop) in output order; arrays are reused by the next block.

    points (n, 2) in the triangulation's plane, values (n,), gradients (n, 2) (both None
    when the pass was asked for fields only), fields: one (n, d) blend per requested field.
    """

    start: int
    stop: int
    points: np.ndarray
    values: np.ndarray | None
    gradients: np.ndarray | None
    fields: list


class _PointSet:
    """Fixed barycentric points lam (P, 3): evaluates blocks of triangles into buffers."""

    def __init__(self, scheme: ShapeTuple, lam: np.ndarray):
        P = self.P = lam.shape[0]
        self.B = np.ascontiguousarray(rsd.basis(scheme, lam))
        d0, d1 = rsd.gradient_basis(scheme, lam)
        self.D = np.ascontiguousarray(np.stack([d0, d1], axis=2).reshape(d0.shape[0], 2 * P))  # (21, P·2)
        self.lam = lam
        self._blend = {}

    def blend_matrix(self, d: int) -> np.ndarray:
        """W (3d, dP): corners (c, 3, d) flattened @ W = blended points (c, P, d) flattened."""
        if d not in self._blend:
            W = np.zeros((3 * d, d * self.P))
            for k in range(3):
                for j in range(d):
                    W[d * k + j, j::d] = self.lam[:, k]
            self._blend[d] = W
        return self._blend[d]

    def spline(self, C, G, count, values, gradients, scratch) -> None:
        """values (count, P) and gradients (count, P, 2) of the first `count` rows of the
        full-height buffers: coefficients C (rows, 21) (rows past count are padding),
        G (count, 3, 2), values (rows, P), scratch (rows, 2P), gradients (count, P, 2).

        The two BLAS products always run over all `rows` rows, whatever count is: see
        _BlockBuffers for why a product's shape must not depend on the block."""
        P = self.P
        np.matmul(C, self.B, out=values)
        np.matmul(C, self.D, out=scratch)              # (rows, P, 2): C @ D0 and C @ D1 per point
        # ∇F = (C @ D0) G_0 + (C @ D1) G_1: per triangle, (P × 2) @ (2 × 2), one shape per triangle
        np.matmul(scratch[:count].reshape(count, P, 2), G[:, :2, :], out=gradients)

    def blend(self, corners, out) -> None:
        """out (rows, P·d) = barycentric blend of corners (rows, 3, d), all rows (padding
        included, as in spline)."""
        rows, _, d = corners.shape
        np.matmul(corners.reshape(rows, 3 * d), self.blend_matrix(d), out=out)


class Refinement:
    """A level-L refinement of an RSD spline, produced block by block in output order.

    Holds the output numbering (which triangle owns which edge, where each edge's points
    go) and the per-level basis matrices; `vertex_blocks` and `face_blocks` evaluate and
    number one block of triangles at a time, `mesh` assembles everything in memory.

    vertices: the spline's rsd.VertexData (N vertices, output points [0, N)); triangles
    (T, 3); coefficients (T, 21) and G (T, 3, 2): each triangle's rsd coefficients and
    barycentric gradients (RSDInterpolator.coefficients, .lambda_gradients); table: the
    triangles' EdgeTable; scheme: the ShapeTuple; level L >= 1.
    """

    def __init__(self, vertices: rsd.VertexData, triangles: np.ndarray, coefficients: np.ndarray,
                 G: np.ndarray, table: EdgeTable, scheme: ShapeTuple, level: int):
        if int(level) != level or level < 1:
            raise ValueError(f"level must be a positive integer, got {level!r}")
        self.level = L = int(level)
        self.pattern = pat = lattice_pattern(L)
        points = vertices.points
        self.points, self.values, self.gradients = points, vertices.values, vertices.gradients
        self.triangles, self.coefficients, self.G, self.table = triangles, coefficients, G, table
        self.scheme = scheme
        self.n_edge, self.n_int = L - 1, pat.interior.size
        self.rows = max(1, CHUNK_ENTRIES // pat.lattice.shape[0])
        self.vertex_count, self.face_count = refined_counts(points.shape[0], table.edges.shape[0],
                                                            triangles.shape[0], L)
        self.index_dtype = np.int32 if self.vertex_count < 2**31 - 1 else np.int64
        self._number_points()
        rows = np.concatenate(list(pat.edge_rows) + [pat.interior])   # per triangle: slots 0, 1, 2, interior
        self._lattice = _PointSet(scheme, pat.lattice[rows] / L)

    @property
    def largest_block(self) -> int:
        """The most points a VertexBlock can hold."""
        return max(self.rows * self._lattice.P, CHUNK_ENTRIES)

    def _number_points(self) -> None:
        """The first output index of each triangle's points and of each edge's points.

        owned (T, 3): triangle t owns the edge in its slot k. Triangle t's points start at
        tri_start[t] (T + 1 entries, the last is the point count); its slot-k edge points,
        when owned, follow those of its owned slots before k; its interior points come last.
        """
        table, T, n_edge = self.table, self.triangles.shape[0], self.n_edge
        slot = table.owner * 3 + table.owner_slot                  # flat (t, k) of each edge's owner
        owned = np.zeros((T, 3), dtype=bool)
        owned.ravel()[slot] = True
        before = np.zeros((T, 3), dtype=np.int64)                   # owned slots before k
        np.add(owned[:, 0], before[:, 1], out=before[:, 1], dtype=np.int64)
        np.add(owned[:, 1], before[:, 1], out=before[:, 2], dtype=np.int64)
        points_of = before[:, 2] + owned[:, 2]
        points_of *= n_edge
        points_of += self.n_int
        self.tri_start = np.empty(T + 1, dtype=np.int64)
        self.tri_start[0] = 0
        np.cumsum(points_of, out=self.tri_start[1:])
        self.tri_start += self.points.shape[0]
        self.owned = owned
        # per edge: 2 × (output index of its first point) + 1 if the owner runs along it
        # from edges[e, 0] to edges[e, 1] — one array, so the faces need one gather per edge
        # (computed per slot where it is contiguous, then one gather by each edge's owner slot)
        code = before
        code *= n_edge
        code += self.tri_start[:-1, None]
        code *= 2
        code += table.forward
        self.edge_code = code.ravel().take(slot)

    # --- vertices -------------------------------------------------------------------------
    def vertex_blocks(self, fields: Sequence[np.ndarray] = (), spline: bool = True,
                      out: Sequence[np.ndarray] | None = None, deal: tuple[int, int] = (0, 1)
                      ) -> Iterator[VertexBlock]:
        """Yield the refined points in output order, one block at a time.

        fields: per-input-vertex arrays (N, d) to blend linearly onto the refined points
        (colours). spline=False skips the spline values and gradients. out: full-size
        arrays [points (M, 2), values (M,), gradients (M, 2), one (M, d) per field] to
        write into (then blocks are views of them); without it the arrays of a block are
        buffers reused by the next block: copy what you keep. deal (w, count): only the
        blocks w, w + count, ... of that order (one producer of core.threads.prefetch_dealt;
        each block is the same whoever computes it), with buffers of this call's own.
        """
        N = self.points.shape[0]
        fields = [np.asarray(f, dtype=float).reshape(N, -1) for f in fields]
        w, count = deal
        inputs = -(-N // self.largest_block)                    # the input blocks come first
        yield from self._input_blocks(fields, spline, out, deal)
        yield from self._lattice_blocks(0, self.triangles.shape[0], fields, spline, out,
                                        ((w - inputs) % count, count))

    def _input_blocks(self, fields: list, spline: bool, out, deal: tuple[int, int] = (0, 1)
                      ) -> Iterator[VertexBlock]:
        """The input points themselves (output points [0, N)), in blocks (deal: those of
        vertex_blocks' deal)."""
        N = self.points.shape[0]
        w, count = deal
        for start in range(w * self.largest_block, N, count * self.largest_block):
            part = slice(start, min(start + self.largest_block, N))
            block = VertexBlock(part.start, part.stop, self.points[part],
                                self.values[part] if spline else None,
                                self.gradients[part] if spline else None, [f[part] for f in fields])
            if out is not None:
                block = _copy_block(block, out)
            yield block

    def _lattice_blocks(self, first: int, last: int, fields: list, spline: bool, out,
                        deal: tuple[int, int] = (0, 1)) -> Iterator[VertexBlock]:
        """The points of triangles [first, last) (first a multiple of rows), in blocks
        (deal (w, count): only the blocks w, w + count, ... of them)."""
        buffers = _BlockBuffers(self.rows, self._lattice.P, self.n_edge, fields, spline)
        w, count = deal
        for start_row in range(first + w * self.rows, last, count * self.rows):
            rows = slice(start_row, min(start_row + self.rows, last))
            start, stop = int(self.tri_start[rows.start]), int(self.tri_start[rows.stop])
            dest = buffers.output if out is None else _OutputSlices(out, start, stop)
            self._evaluate_block(rows, fields, spline, buffers, dest)
            n = stop - start
            yield VertexBlock(start, stop, dest.points[:n], dest.values[:n] if spline else None,
                              dest.gradients[:n] if spline else None, [f[:n] for f in dest.fields])

    def _evaluate_block(self, rows: slice, fields: list, spline: bool,
                        buf: "_BlockBuffers", dest) -> None:
        """Evaluate all non-vertex lattice points of the triangles in rows, then gather
        the ones they own (owned edges, interiors) into dest (buffers or output slices)."""
        tri = self.triangles[rows]
        c, P, at = tri.shape[0], self._lattice.P, self._lattice
        if P == 0:                                       # level 1: the input points are all
            return
        keep = buf.keep[:c]
        keep[:, :3 * self.n_edge].reshape(c, 3, self.n_edge)[...] = self.owned[rows, :, None]
        kept = np.flatnonzero(keep.ravel())             # one index list serves every array
        n = kept.size
        for source, corners, all_points, target in zip([self.points] + fields, buf.corners, buf.blended,
                                                       [dest.points] + dest.fields):
            np.take(source, tri, axis=0, out=corners[:c], mode="clip")   # clip: unbuffered out
            at.blend(corners, all_points)                                # all rows: _BlockBuffers
            np.take(all_points[:c].reshape(c * P, target.shape[1]), kept, axis=0, out=target[:n], mode="clip")
        if spline:
            buf.coefficients[:c] = self.coefficients[rows]
            at.spline(buf.coefficients, self.G[rows], c, buf.values, buf.gradients[:c], buf.scratch)
            np.take(buf.values[:c].ravel(), kept, out=dest.values[:n], mode="clip")
            np.take(buf.gradients[:c].reshape(c * P, 2), kept, axis=0, out=dest.gradients[:n], mode="clip")

    # --- faces ----------------------------------------------------------------------------
    def face_blocks(self, out: np.ndarray | None = None, ring: int = 1,
                    deal: tuple[int, int] = (0, 1)) -> Iterator[tuple[int, np.ndarray]]:
        """Yield (first face index, faces (k, 3)) blocks in output order.

        out: a full-size (K, 3) array to write into (blocks are views of it); without it
        the faces of a block are one of `ring` buffers used in turn, so a block stays
        valid until `ring` more blocks have been yielded (c1mesh.core.threads.ring).
        deal (w, count): only the blocks w, w + count, ... (as vertex_blocks').

        Per block: the output index of every lattice point of every triangle (_corner_ids,
        (Q, c) integer arithmetic along rows of length c), then one gather through the
        sub-triangle template gives the c·L² faces.
        """
        yield from self._face_range(0, self.triangles.shape[0], out, ring, deal)

    def _face_range(self, first: int, last: int, out: np.ndarray | None,
                    ring: int = 1, deal: tuple[int, int] = (0, 1)) -> Iterator[tuple[int, np.ndarray]]:
        """The faces of triangles [first, last) (first a multiple of rows), in blocks
        (deal (w, count): only the blocks w, w + count, ... of them)."""
        L, Q = self.level, self.pattern.lattice.shape[0]
        template = _template_columns(self.pattern).ravel()
        ids = np.empty(Q * self.rows, dtype=self.index_dtype)
        buffers = [np.empty(self.rows * template.size, dtype=self.index_dtype)
                   for _ in range(ring if out is None else 0)]
        gather = None
        w, count = deal
        for i, start_row in enumerate(range(first + w * self.rows, last, count * self.rows)):
            rows = slice(start_row, min(start_row + self.rows, last))
            n = rows.stop - rows.start
            if gather is None or gather.size != n * template.size:       # (n, 3L²) into ids (Q, n)
                gather = (template * n + np.arange(n)[:, None]).ravel()
            if out is None:
                faces = buffers[i % ring][:gather.size]
            else:
                faces = out[rows.start * L * L:rows.stop * L * L].reshape(-1)
            self._corner_ids(rows, ids[:Q * n].reshape(Q, n))
            np.take(ids[:Q * n], gather, out=faces, mode="clip")       # clip: no buffered copy of out
            yield rows.start * L * L, faces.reshape(-1, 3)

    def _corner_ids(self, rows: slice, out: np.ndarray) -> None:
        """out (Q, c): output index of each lattice point of the c triangles in rows, in
        _template_columns order: the 3 vertices; the L−1 points inside edge 0, 1, 2 (from
        vertex k+1 towards k+2); the interior points. Rows of length c keep numpy's inner
        loops long."""
        n_edge, n_int = self.n_edge, self.n_int
        out[:3] = self.triangles[rows].T
        codes = self.edge_code.take(self.table.tri_edge[rows].T)           # (3, c)
        same = self.table.forward[rows].T == (codes & 1).astype(bool)       # runs as its owner does
        first = codes >> 1
        if n_edge:
            first += (~same) * (n_edge - 1)                                   # else from the far end
            step = same * 2 - 1
            edges = out[3:3 + 3 * n_edge].reshape(3, n_edge, -1)
            np.multiply(step[:, None, :], np.arange(n_edge)[None, :, None], out=edges)
            edges += first[:, None, :]
        if n_int:
            interior_first = self.tri_start[rows.start + 1:rows.stop + 1] - n_int   # interiors come last
            np.add(interior_first[None, :], np.arange(n_int)[:, None], out=out[3 + 3 * n_edge:])

    # --- everything in memory -------------------------------------------------------------
    def mesh(self, workers: int | None = None) -> RefinedMesh:
        """All refined points, values, gradients and triangles as arrays (RefinedMesh).

        workers: threads sharing the work (default: c1mesh.core.threads.workers(), the
        process-wide setting, by default the CPUs this process may use), at most
        MAX_WORKERS; each evaluates a contiguous range of triangle blocks into its own disjoint
        slices of the outputs, so the result does not depend on the count.
        """
        M, L, T = self.vertex_count, self.level, self.triangles.shape[0]
        points, values, gradients = np.empty((M, 2)), np.empty(M), np.empty((M, 2))
        triangles = np.empty((self.face_count, 3), dtype=self.index_dtype)
        parent = np.empty(self.face_count, dtype=self.index_dtype)
        outputs = [points, values, gradients]

        def work(first: int, last: int) -> None:
            _populate_range(outputs, self.tri_start[first] if first else 0, self.tri_start[last])
            _populate_range([triangles, parent], first * L * L, last * L * L)
            if first == 0:
                for _ in self._input_blocks([], True, outputs):
                    pass
            for _ in self._lattice_blocks(first, last, [], True, outputs):
                pass
            for _ in self._face_range(first, last, triangles):
                pass
            _fill_parent(parent[first * L * L:last * L * L], L, first)
        blocks = -(-T // self.rows)
        count = max(1, min(thread_count(workers), MAX_WORKERS, blocks))
        bounds = [min(T, blocks * i // count * self.rows) for i in range(count + 1)]
        # One BLAS thread, with one worker too: BLAS's own threads fight ours, and alone
        # they are slower still on blocks this size (200k-point hill, level 4, one worker:
        # 1.0-2.4 s with BLAS's two threads, 0.2-0.7 s with one; busy 2-core machine).
        with blas_threads(1):
            run_parallel(work, list(zip(bounds[:-1], bounds[1:])))
        mesh = RefinedMesh(points, triangles, values, gradients, self.level, refinement=self)
        mesh._parent = parent
        return mesh


def _populate_range(arrays: Sequence[np.ndarray], start: int, stop: int) -> None:
    """Pre-fault rows [start, stop) of fresh C-contiguous arrays before writing them.

    A fresh array costs a page fault per page on first write; on virtual machines that is
    expensive and erratic, and slower still when two threads fault at once (measured
    here, 1M points, level 4, two workers: 1.0-2.5 s letting writes fault, 0.6 s with
    this). madvise(MADV_POPULATE_WRITE) (Linux ≥ 5.14) takes the faults in one call and
    changes no byte; where it is unavailable nothing is done.
    """
    for array in arrays:
        row = array.strides[0]
        if not _populate(array.ctypes.data + int(start) * row, (int(stop) - int(start)) * row):
            return


def _fill_parent(parent: np.ndarray, level: int, first: int = 0) -> None:
    """parent (t·L²,) = the input triangle of each sub-triangle (stored parent by parent),
    for the t triangles from `first` on."""
    rows = parent.reshape(-1, level * level)
    rows[...] = np.arange(first, first + rows.shape[0], dtype=parent.dtype)[:, None]


_PAGE = 4096
_MADV_POPULATE_WRITE = 23


def _populate(address: int, length: int) -> bool:
    """Pre-fault the whole pages inside [address, address + length) for writing; False
    when the system cannot (then callers stop asking)."""
    if _madvise is None:
        return False
    first = -(-address // _PAGE) * _PAGE
    last = (address + length) // _PAGE * _PAGE
    return last <= first or _madvise(first, last - first, _MADV_POPULATE_WRITE) == 0


def _template_columns(pat: LatticePattern) -> np.ndarray:
    """The sub-triangle template (L², 3) with lattice rows renumbered as _corner_ids
    columns: vertices 0, 1, 2; edge k's points i at 3 + k(L−1) + i; interior j after them."""
    L = pat.level
    column = np.empty(pat.lattice.shape[0], dtype=np.int64)
    column[[pat.index_of[0, 0], pat.index_of[L, 0], pat.index_of[0, L]]] = [0, 1, 2]
    for k in range(3):
        column[pat.edge_rows[k]] = 3 + k * (L - 1) + np.arange(L - 1)
    column[pat.interior] = 3 + 3 * (L - 1) + np.arange(pat.interior.size)
    return column[pat.template]


class _BlockBuffers:
    """Reusable per-block arrays for blocks of up to rows triangles with P evaluated points
    each: keep (rows, P) which points the triangles own (interior columns always True),
    gathered corners and blended points per source (points, then fields), the block's
    spline coefficients (rows, 21), spline values (rows, P), gradients (rows, P, 2),
    matmul scratch (rows, 2P), and `output` (the kept points, when the caller gave no
    full-size arrays).

    Every BLAS product of a block runs over all `rows` rows of these buffers, a short
    block (the last of a range) included: the rows past its triangles are padding (zeros,
    or finite rows left by the previous block) and are never read back. So every product
    has one shape, and a point's bits do not depend on which block it falls in. They
    would otherwise: OpenBLAS (0.3.31, SkylakeX kernels) computes small products
    (measured: M·N·K below about 10⁶) with a separate kernel that rounds differently, so a
    triangle in a short last block came out different in the last bit from the same
    triangle in a full block. A tile of `--seamless -O` numbers its triangles differently
    from its neighbour, so a border point fell in a short block in one tile and a full
    one in the other, and the two tiles wrote the same border vertex with different bits
    (issue 21). Within one shape, a row's bits do not depend on its position or on the
    BLAS thread count (tests/test_engine.py checks both)."""

    def __init__(self, rows: int, P: int, n_edge: int, fields: list, spline: bool):
        self.keep = np.ones((rows, P), dtype=bool)
        widths = [2] + [f.shape[1] for f in fields]
        self.corners = [np.zeros((rows, 3, d)) for d in widths]
        self.coefficients = np.zeros((rows, 21)) if spline else None
        self.blended = [np.empty((rows, P * d)) for d in widths]
        self.values = np.empty((rows, P)) if spline else None
        self.gradients = np.empty((rows, P, 2)) if spline else None
        self.scratch = np.empty((rows, 2 * P)) if spline else None
        size = rows * P
        self.output = _OutputSlices([np.empty((size, 2)), np.empty(size) if spline else None,
                                     np.empty((size, 2)) if spline else None]
                                    + [np.empty((size, d)) for d in widths[1:]], 0, size)


class _OutputSlices:
    """The [start, stop) rows of full-size outputs [points, values, gradients, *fields]."""

    def __init__(self, out: Sequence[np.ndarray], start: int, stop: int):
        part = slice(int(start), int(stop))
        self.points = out[0][part]
        self.values = None if out[1] is None else out[1][part]
        self.gradients = None if out[2] is None else out[2][part]
        self.fields = [f[part] for f in out[3:]]


def _copy_block(block: VertexBlock, out: Sequence[np.ndarray]) -> VertexBlock:
    """Copy a block into the full-size outputs; return the block as views of them."""
    dest = _OutputSlices(out, block.start, block.stop)
    dest.points[...] = block.points
    if block.values is not None:
        dest.values[...], dest.gradients[...] = block.values, block.gradients
    for source, target in zip(block.fields, dest.fields):
        target[...] = source
    return VertexBlock(block.start, block.stop, dest.points,
                       None if block.values is None else dest.values,
                       None if block.values is None else dest.gradients, dest.fields)
