"""Uniform refinement of an RSD spline: every triangle split into level² sub-triangles.

Output point numbering (input vertex i is output point i, and every point on a shared
edge or vertex exists once, so the mesh is conforming and crack-free):

  [0, N)     the N input points (values and gradients exactly the data)
  then, for each block of consecutive triangles (CHUNK_ENTRIES lattice points per block),
             for k = 0, 1, 2: the L−1 points inside each edge that a triangle of the
             block owns in its local slot k (the edge opposite vertex k), triangle by
             triangle, ordered from the owner's vertex k+1 towards its vertex k+2;
             then the (L−1)(L−2)/2 interior points of each triangle of the block.

Each edge has one owner triangle (EdgeTable.owner), which evaluates the points on it; the
other triangle only refers to them. Blocks are the unit of work: a block of triangles
reads its own contiguous rows of the coefficients, so nothing is gathered at random
except vertex coordinates, and its output points form one contiguous range. That range
is handed to the caller as a `VertexBlock`, which is what lets `c1mesh fit` stream a
refined mesh straight to a file without holding it (`Refinement.vertex_blocks`,
`Refinement.face_blocks`), while `Refinement.mesh` copies the blocks into full arrays.

Values and gradients are matrix products: coefficients (c × 21) @ basis (21 × P), with
basis matrices built once per level and tuple (rsd.basis); point coordinates are corner
coordinates (c × 6) @ a fixed blending matrix (6 × 2P).

Memory: `Refinement` itself holds O(E + T) numbering arrays; a pass over the blocks adds
buffers of a few CHUNK_ENTRIES lattice points (≈ 1 MiB, independent of T); `mesh()` adds
the outputs (M values, 2M gradients, 2M coordinates, 3·L²·T indices).
"""
from __future__ import annotations

import ctypes
import sys
import threading
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np

from c1mesh import rsd
from c1mesh.schemes import ShapeTuple
from c1mesh.topology import EdgeTable

CHUNK_ENTRIES = 1 << 15
"""Lattice points (all (L+1)(L+2)/2 of each triangle) per block: temporaries stay in cache."""


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

    def spline(self, C, G, values, gradients, scratch) -> None:
        """values (c, P) and gradients (c, P, 2) from coefficients C (c, 21), G (c, 3, 2)."""
        c, P = C.shape[0], self.P
        np.matmul(C, self.B, out=values)
        d = scratch[:c, :2 * P]
        np.matmul(C, self.D, out=d)                    # (c, P, 2): C @ D0 and C @ D1 per point
        # ∇F = (C @ D0) G_0 + (C @ D1) G_1: per triangle, (P × 2) @ (2 × 2)
        np.matmul(d.reshape(c, P, 2), G[:, :2, :], out=gradients)

    def blend(self, corners, out) -> None:
        """out (c, P·d) = barycentric blend of corners (c, 3, d)."""
        c, _, d = corners.shape
        np.matmul(corners.reshape(c, 3 * d), self.blend_matrix(d), out=out)


class Refinement:
    """A level-L refinement of an RSD spline, produced block by block in output order.

    Holds the output numbering (which triangle owns which edge, where each edge's points
    go) and the per-level basis matrices; `vertex_blocks` and `face_blocks` evaluate and
    number one block of triangles at a time, `mesh` assembles everything in memory.
    """

    def __init__(self, points: np.ndarray, values: np.ndarray, gradients: np.ndarray,
                 triangles: np.ndarray, coefficients: np.ndarray, G: np.ndarray,
                 table: EdgeTable, scheme: ShapeTuple, level: int):
        if int(level) != level or level < 1:
            raise ValueError(f"level must be a positive integer, got {level!r}")
        self.level = L = int(level)
        self.pattern = pat = lattice_pattern(L)
        self.points, self.values, self.gradients = points, values, gradients
        self.triangles, self.coefficients, self.G, self.table = triangles, coefficients, G, table
        self.scheme = scheme
        N, T = points.shape[0], triangles.shape[0]
        self.n_edge, self.n_int = L - 1, pat.interior.size
        self.rows = max(1, CHUNK_ENTRIES // pat.lattice.shape[0])
        self.vertex_count = N + table.edges.shape[0] * self.n_edge + T * self.n_int
        self.face_count = T * L * L
        self.index_dtype = np.int32 if self.vertex_count < 2**31 - 1 else np.int64
        self._number_edges()
        lam = pat.lattice / L
        self._edges = [_PointSet(scheme, lam[pat.edge_rows[k]]) for k in range(3)]
        self._interior = _PointSet(scheme, lam[pat.interior])

    @property
    def largest_block(self) -> int:
        """The most points a VertexBlock can hold."""
        return max(self.rows * (3 * self.n_edge + self.n_int), CHUNK_ENTRIES)

    def _number_edges(self) -> None:
        """Where each block's points start and the first output index of each edge's points.

        owned (T, 3): triangle t owns the edge in its slot k. Within a block, slot-k edges
        come in triangle order, so an edge's position is its block's slot offset plus the
        number of slot-k edges owned by earlier triangles of the block. Work is done on
        slot-major (3, T) arrays, where running counts along triangles are contiguous.
        """
        table, T, n_edge = self.table, self.triangles.shape[0], self.n_edge
        slot_major = table.owner_slot * T + table.owner            # flat (k, t) of each edge's owner
        owned = np.zeros(3 * T, dtype=bool)
        owned[slot_major] = True
        owned = owned.reshape(3, T)
        starts = np.arange(0, T, self.rows)
        lengths = np.diff(np.append(starts, T))
        counts = np.add.reduceat(owned, starts, axis=1, dtype=np.int64) if T else np.zeros((3, 0), np.int64)
        block_points = counts.sum(axis=0) * n_edge + lengths * self.n_int
        self.block_start = self.points.shape[0] + np.concatenate([[0], np.cumsum(block_points)])
        slot_start = self.block_start[:-1] + np.cumsum(counts * n_edge, axis=0) - counts * n_edge
        self.interior_start = self.block_start[:-1] + counts.sum(axis=0) * n_edge
        before = np.cumsum(owned, axis=1, dtype=np.int64)
        before -= owned                                             # owned slot-k edges before t
        before -= np.repeat(before[:, starts], lengths, axis=1)     # ... within t's block
        before *= n_edge
        before += np.repeat(slot_start, lengths, axis=1)            # (3, T) output positions
        self.owned = owned.T
        # per edge: 2 × (output index of its first point) + 1 if the owner runs along it
        # from edges[e, 0] to edges[e, 1] — one array, so the faces need one gather per edge
        owner_forward = table.forward.ravel().take(table.owner * 3 + table.owner_slot)
        self.edge_code = before.ravel().take(slot_major) * 2 + owner_forward

    # --- vertices -------------------------------------------------------------------------
    def vertex_blocks(self, fields: Sequence[np.ndarray] = (), spline: bool = True,
                      out: Sequence[np.ndarray] | None = None) -> Iterator[VertexBlock]:
        """Yield the refined points in output order, one block at a time.

        fields: per-input-vertex arrays (N, d) to blend linearly onto the refined points
        (colours). spline=False skips the spline values and gradients. out: full-size
        arrays [points (M, 2), values (M,), gradients (M, 2), one (M, d) per field] to
        write into (then blocks are views of them); without it the arrays of a block are
        buffers reused by the next block: copy what you keep.
        """
        N = self.points.shape[0]
        fields = [np.asarray(f, dtype=float).reshape(N, -1) for f in fields]
        size = self.rows * (3 * self.n_edge + self.n_int)
        for start in range(0, N, self.largest_block):           # the input points themselves
            part = slice(start, min(start + self.largest_block, N))
            block = VertexBlock(part.start, part.stop, self.points[part],
                                self.values[part] if spline else None,
                                self.gradients[part] if spline else None, [f[part] for f in fields])
            if out is not None:
                block = _copy_block(block, out)
            yield block
        buffers = _BlockBuffers(size, self.rows, max(self.n_edge, self.n_int), fields, spline)
        for b, first in enumerate(range(0, self.triangles.shape[0], self.rows)):
            rows = slice(first, min(first + self.rows, self.triangles.shape[0]))
            dest = buffers if out is None else _OutputSlices(out, self.block_start[b], self.block_start[b + 1])
            yield self._evaluate_block(b, rows, fields, spline, buffers, dest)

    def _evaluate_block(self, b, rows, fields, spline, buf, dest) -> VertexBlock:
        """Evaluate the points of triangle block b into dest (buffers or output slices)."""
        tri = self.triangles[rows]
        c = tri.shape[0]
        inputs = [np.take(a, tri, axis=0, out=corners[:c])                    # corners (c, 3, d)
                  for a, corners in zip([self.points] + fields, buf.corners)]
        if spline:
            inputs += [self.coefficients[rows], self.G[rows]]
        cursor = 0
        for k, point_set in enumerate(self._edges + [self._interior]):
            if k < 3:
                mask = self.owned[rows, k]
                n = int(np.count_nonzero(mask))
                chosen = [np.compress(mask, a, axis=0, out=sel[:n]) for a, sel in zip(inputs, buf.selected)]
            else:
                n, chosen = tri.shape[0], inputs
            span = slice(cursor, cursor + n * point_set.P)
            cursor = span.stop
            if not (n and point_set.P):
                continue
            point_set.blend(chosen[0], dest.points[span].reshape(n, -1))
            for corners, target in zip(chosen[1:1 + len(fields)], dest.fields):
                point_set.blend(corners, target[span].reshape(n, -1))
            if spline:
                point_set.spline(chosen[-2], chosen[-1], dest.values[span].reshape(n, -1),
                                 dest.gradients[span].reshape(n, -1, 2), buf.scratch)
        start = int(self.block_start[b])
        return VertexBlock(start, start + cursor, dest.points[:cursor],
                           dest.values[:cursor] if spline else None,
                           dest.gradients[:cursor] if spline else None,
                           [target[:cursor] for target in dest.fields])

    # --- faces ----------------------------------------------------------------------------
    def face_blocks(self, out: np.ndarray | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """Yield (first face index, faces (k, 3)) blocks in output order.

        out: a full-size (K, 3) array to write into (blocks are views of it); without it
        the faces of a block are a buffer reused by the next block.
        """
        L = self.level
        W = _index_matrix(self.pattern)
        features = np.empty((self.rows, W.shape[0]))
        product = np.empty((self.rows, W.shape[1]))
        buffer = np.empty((self.rows, W.shape[1]), dtype=self.index_dtype) if out is None else None
        for b, first in enumerate(range(0, self.triangles.shape[0], self.rows)):
            rows = slice(first, min(first + self.rows, self.triangles.shape[0]))
            n = rows.stop - rows.start
            faces = buffer[:n] if out is None else out[first * L * L:rows.stop * L * L].reshape(n, -1)
            self._index_features(b, rows, features[:n])
            np.matmul(features[:n], W, out=product[:n])   # exact: integers below 2**53
            np.copyto(faces, product[:n], casting="unsafe")
            yield first * L * L, faces.reshape(-1, 3)

    def _index_features(self, b: int, rows: slice, out: np.ndarray) -> None:
        """out (c, 11) per triangle: vertex ids, first output index and step (±1) of the
        points on each edge (as this triangle runs along it), first interior index, 1.
        Times _index_matrix this gives the output index of every sub-triangle corner."""
        L, table = self.level, self.table
        out[:, 0:3] = self.triangles[rows]
        for k in range(3):
            code = self.edge_code.take(table.tri_edge[rows, k])
            same = table.forward[rows, k] == (code & 1).astype(bool)   # runs the way the owner does
            out[:, 3 + k] = (code >> 1) + np.where(same, 0, L - 2)
            out[:, 6 + k] = np.where(same, 1.0, -1.0)
        base = float(self.interior_start[b])
        out[:, 9] = np.arange(out.shape[0]) * float(self.n_int) + base
        out[:, 10] = 1.0

    # --- everything in memory -------------------------------------------------------------
    def mesh(self) -> RefinedMesh:
        """All refined points, values, gradients and triangles as arrays (RefinedMesh)."""
        M = self.vertex_count
        points, values, gradients = np.empty((M, 2)), np.empty(M), np.empty((M, 2))
        triangles = np.empty((self.face_count, 3), dtype=self.index_dtype)
        parent = np.empty(self.face_count, dtype=self.index_dtype)
        helper = _touch_in_background([[points, values, gradients], [triangles]],
                                      then=lambda: _fill_parent(parent, self.level))
        for _ in self.vertex_blocks(out=[points, values, gradients]):
            pass
        for _ in self.face_blocks(out=triangles):
            pass
        helper.join()
        mesh = RefinedMesh(points, triangles, values, gradients, self.level, refinement=self)
        mesh._parent = parent
        return mesh


def _fill_parent(parent: np.ndarray, level: int) -> None:
    """parent (T·L²,) = the input triangle of each sub-triangle (stored parent by parent)."""
    rows = parent.reshape(-1, level * level)
    rows[...] = np.arange(rows.shape[0], dtype=parent.dtype)[:, None]


def _touch_in_background(groups: list[list[np.ndarray]], then=None, segments: int = 64) -> threading.Thread:
    """Fault in the pages of fresh output arrays from a second thread, in the order the
    evaluation fills them (each group's arrays side by side, segment by segment); then
    run ``then()`` in that thread.

    A fresh array costs a page fault per page on first write; on virtual machines that is
    expensive and erratic (measured here: 1 to 3 s per GiB). madvise(MADV_POPULATE_WRITE)
    (Linux ≥ 5.14) takes those faults on the other core without changing any byte, so it
    cannot race with the evaluation writing the same pages. At 1M points, level 4,
    filling the outputs took 0.9-1.1 s with it and 0.95-3.2 s without. Where the call is
    unavailable nothing is touched.
    """
    def populate_all() -> None:
        for group in groups:
            for i in range(segments):
                for array in group:
                    step = -(-array.nbytes // segments)
                    if not _populate(array.ctypes.data + i * step, min(step, array.nbytes - i * step)):
                        return

    def touch() -> None:
        populate_all()
        if then is not None:
            then()
    thread = threading.Thread(target=touch, name="c1mesh-prefault", daemon=True)
    thread.start()
    return thread


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


def _load_madvise():
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        madvise = libc.madvise
    except (OSError, AttributeError):
        return None
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    madvise.restype = ctypes.c_int
    return madvise


_madvise = _load_madvise() if sys.platform.startswith("linux") else None


def _index_matrix(pat: LatticePattern) -> np.ndarray:
    """W (11, 3L²) such that _index_features (c, 11) @ W = the sub-triangles' corner indices.

    A corner at vertex k is feature k; the i-th point inside edge k is first_k + i·step_k;
    the j-th interior point is interior_first + j.
    """
    W = np.zeros((11, pat.template.size))
    L = pat.level
    vertex_rows = [pat.index_of[0, 0], pat.index_of[L, 0], pat.index_of[0, L]]
    for col, row in enumerate(pat.template.ravel()):
        if row in vertex_rows:
            W[vertex_rows.index(row), col] = 1
        elif row in pat.interior:
            W[9, col], W[10, col] = 1, np.flatnonzero(pat.interior == row)[0]
        else:
            k = next(k for k in range(3) if row in pat.edge_rows[k])
            W[3 + k, col], W[6 + k, col] = 1, np.flatnonzero(pat.edge_rows[k] == row)[0]
    return W


class _BlockBuffers:
    """Reusable per-block outputs (size points), gathered corners, inputs selected for one
    edge slot (rows triangles: corners, field corners, coefficients, G) and matmul
    scratch (rows × 2·width)."""

    def __init__(self, size: int, rows: int, width: int, fields: list, spline: bool):
        self.points = np.empty((size, 2))
        self.fields = [np.empty((size, f.shape[1])) for f in fields]
        self.values = np.empty(size) if spline else None
        self.gradients = np.empty((size, 2)) if spline else None
        self.scratch = np.empty((rows, 2 * width)) if spline else None
        self.corners = [np.empty((rows, 3, 2))] + [np.empty((rows, 3, f.shape[1])) for f in fields]
        self.selected = [np.empty((rows, 3, 2))] + [np.empty((rows, 3, f.shape[1])) for f in fields]
        if spline:
            self.selected += [np.empty((rows, rsd.N_BASIS)), np.empty((rows, 3, 2))]


class _OutputSlices:
    """The [start, stop) rows of full-size outputs [points, values, gradients, *fields]."""

    def __init__(self, out: Sequence[np.ndarray], start: int, stop: int):
        part = slice(int(start), int(stop))
        self.points, self.values, self.gradients = out[0][part], out[1][part], out[2][part]
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
