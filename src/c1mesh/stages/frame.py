"""The scan frame: the local frame in which a scan is (most likely) a height field.

A `ScanFrame` is an origin (subtracted before any numerics: LiDAR coordinates sit at
1e5-1e7, where a float64 ulp is already ~1e-10..1e-9) and three orthonormal,
right-handed axes e1, e2, e3, with e3 the height axis. In the frame a world point P has
local coordinates (x, y, z) = ((P - origin)·e1, (P - origin)·e2, (P - origin)·e3).
`choose_frame` picks the height axis (given, from the normals, by PCA, or among the world
axes when the coordinates are in different units); `resolve_axis` resolves "auto" for
LAS/LAZ before reading. The scan as heights and gradients in the frame is
c1mesh.stages.height_field.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
from numpy.typing import ArrayLike

from c1mesh.core.errors import InputError
from c1mesh.core.outputs import LAS_FORMATS
from c1mesh.core.tile import finite_rows
from c1mesh.stages.height_field import as_n3, check_extent, kd_tree
from c1mesh.stages.streamed_median import NoValues, streamed_medians
# Re-exported for the modules that import them from here (pipeline.driver, survey/*);
# new code imports them from c1mesh.stages.height_field.

_WORLD_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass
class ScanFrame:
    """Origin and axes of the local frame in which the scan is a height field.

    origin: (3,) float64 world point subtracted before any numerics.
    axes:   (3, 3) float64, rows e1, e2, e3: orthonormal and right-handed, e3 the height axis.
    axis_reason: how `choose_frame` chose e3 under axis "auto", in words for reports ("" when
            the axis was given).
    """

    origin: np.ndarray
    axes: np.ndarray
    axis_reason: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.axes = np.asarray(self.axes, dtype=np.float64).reshape(3, 3)
        if not np.all(np.isfinite(self.origin)) or not np.allclose(
            self.axes @ self.axes.T, np.eye(3), atol=1e-9
        ) or np.linalg.det(self.axes) <= 0:
            raise InputError("a scan frame needs a finite origin and orthonormal right-handed axes")

    def to_local(self, points: ArrayLike) -> np.ndarray:
        """World points (N, 3) -> local coordinates (N, 3) = (P - origin)·[e1, e2, e3]."""
        return _transform(points, self.axes.T, before=self.origin)

    def to_world(self, local: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Local coordinates (N, 3) -> world points (N, 3); inverse of `to_local`.

        ``out`` (N, 3) float64, if given, receives the result (no temporaries).
        """
        return _transform(local, self.axes, after=self.origin, out=out)

    def vectors_to_local(self, vectors: ArrayLike) -> np.ndarray:
        """World directions (N, 3) (normals, no origin) -> local components (N, 3)."""
        return _transform(vectors, self.axes.T)

    def vectors_to_world(self, vectors: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Local directions (N, 3) -> world components (N, 3), into ``out`` if given."""
        return _transform(vectors, self.axes, out=out)


_ROWS = 1 << 14
"""Rows of every product in `_transform`: small enough that OpenBLAS runs each product on one thread."""


def _transform(rows: ArrayLike, matrix: np.ndarray, before: np.ndarray | None = None,
               after: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """(rows - before) @ matrix + after for rows (N, 3) (or one row (3,)), into ``out`` if given.

    Every product is one BLAS call of exactly _ROWS rows (the last block padded with
    zeros), so a row's bits do not depend on how many rows come with it: a one-row
    product takes BLAS's matrix-vector path (gemv), which rounds differently from the
    matrix-matrix one, and a transposed `matrix` (to_local) showed it (issue 21: a point
    transformed alone must equal the same point transformed inside a cloud). Small
    blocks also keep OpenBLAS on one thread: its second thread waits for a free core,
    which on a busy 2-core machine made a 1M-row product take 0.4 s instead of 0.02 s;
    and they avoid a full-size temporary for ``rows - before``.
    """
    data = np.asarray(rows, dtype=np.float64)
    flat = data.reshape(-1, data.shape[-1]) if data.ndim != 2 else data
    count = flat.shape[0]
    result = np.empty((count, matrix.shape[1])) if out is None else out if out.ndim == 2 else \
        out.reshape(count, matrix.shape[1])
    matrix = np.ascontiguousarray(matrix)
    padded = None
    for start in range(0, count, _ROWS):
        block = slice(start, min(start + _ROWS, count))
        n = block.stop - block.start
        if n == _ROWS:
            part = flat[block] if before is None else flat[block] - before
            product = np.matmul(part, matrix, out=result[block])
        else:                                       # the last block: padded to _ROWS rows
            padded = np.zeros((_ROWS, flat.shape[1])) if padded is None else padded
            np.subtract(flat[block], 0.0 if before is None else before, out=padded[:n])
            product = result[block]
            product[...] = np.matmul(padded, matrix)[:n]
        if after is not None:
            product += after
    if out is not None:
        return out
    return result.reshape(data.shape[:-1] + (matrix.shape[1],)) if data.ndim != 2 else result


def choose_frame(points: ArrayLike, normals: ArrayLike | None = None,
                 axis: str | ArrayLike = "auto") -> ScanFrame:
    """Pick the frame in which the scan is (most likely) a height field.

    points:  (N, 3) world coordinates; non-finite rows are ignored.
    normals: (N, 3) or None; rows that are zero or non-finite are ignored; signs may be arbitrary.
    axis:    the height axis e3: "auto"; "x", "y", "z" with an optional sign ("-z");
             "X,Y,Z" as a string; or a 3-vector. "auto" takes the mean of the normals
             after orienting them all to the side of their dominant direction (the top
             eigenvector of Σ n nᵀ, which does not depend on signs), signed so that most
             raw normals face it; without normals, the direction of least variance of the
             points (PCA), signed so that its largest component is positive (+z for terrain).
    Returns a ScanFrame with origin = per-coordinate median of the finite points, and e1 =
    the world axis least aligned with e3 (ties: the next axis after e3's dominant one in
    x -> y -> z -> x order), orthogonalised; e2 = e3 × e1. World axes give exact
    permutation frames ("z" gives the identity).
    """
    pts = as_n3(points, "points")
    good = finite_rows(pts)
    if not good.any():
        raise InputError(NO_FINITE_POINTS)
    # Without non-finite rows, skip the (N, 3) copies; but keep the C layout that boolean
    # indexing gives, which the BLAS products in the axis sums see (their bits depend on it).
    everything = good.all()
    finite = np.ascontiguousarray(pts) if everything else pts[good]
    check_extent(finite)
    e3 = parse_axis(axis)
    if e3 is None and _units_differ(finite):
        return replace(_frame(lambda: [(finite, None)], _world_axis_by_layering(finite)),
                       axis_reason=UNITS_DIFFER)
    if e3 is None and normals is not None:
        normals = as_n3(normals, "normals", len(pts))
        normals = np.ascontiguousarray(normals) if everything else normals[good]
    return _frame(lambda: [(finite, normals)], e3)


FrameChunks = Callable[[], Iterable[tuple[np.ndarray, "np.ndarray | None"]]]
"""A callable giving a fresh iterator of (points (m, 3), normals (m, 3) or None), world
coordinates, in survey order (input files in the order given, each in its own order)."""
NO_FINITE_POINTS = "there are no points with finite coordinates to choose a frame from"


def frame_of_chunks(chunks: FrameChunks, axis: str | ArrayLike = "auto") -> ScanFrame:
    """The frame by choose_frame's rules from passes over a survey too big for memory, read
    in chunks: the exact per-coordinate median (stages.streamed_median) and the axis sums
    chunk by chunk. choose_frame is this on one chunk, so a survey's frame agrees with
    choose_frame on the whole cloud to rounding (the sums' order) whatever its chunks.
    There is no units test here: the surveys read in chunks are LAS/LAZ, whose axis
    "auto" is z (resolve_axis)."""
    return _frame(chunks, parse_axis(axis))


def _frame(chunks: FrameChunks, e3: np.ndarray | None) -> ScanFrame:
    """The frame of the finite points of chunks: origin their per-coordinate median; e3 as
    given, else from the normals (the dominant direction of Σ n nᵀ, the mean of the normals
    turned to its side, signed by the majority), else the least-variance direction of the
    points about the origin (signed so that its largest component is positive)."""
    try:
        origin = streamed_medians(lambda: (_finite(points) for points, _ in chunks()), 3)
    except NoValues:
        raise InputError(NO_FINITE_POINTS) from None
    reason = ""
    if e3 is None:
        e3, reason = _normal_axis(chunks), "auto: the mean of the normals"
    if e3 is None:
        e3, reason = _least_variance_axis(chunks, origin), "auto: least-variance direction (PCA)"
    return ScanFrame(origin=origin, axes=axes_from_e3(e3), axis_reason=reason)


def _finite(points: np.ndarray) -> np.ndarray:
    """The rows of points (m, 3) with finite coordinates (points itself when all are)."""
    points = np.asarray(points, dtype=np.float64)
    good = finite_rows(points)
    return points if good.all() else points[good]


def _unit_normals(points, normals) -> np.ndarray:
    """The chunk's usable normals, unit length: rows of non-finite points dropped, then
    zero or non-finite normals."""
    if normals is None:
        return np.empty((0, 3))
    normals = np.asarray(normals, dtype=np.float64)
    finite = finite_rows(np.asarray(points, dtype=np.float64))
    if not finite.all():
        normals = normals[finite]
    length = np.linalg.norm(normals, axis=1)
    ok = np.isfinite(length) & (length > 0)
    return normals / length[:, None] if ok.all() else normals[ok] / length[ok, None]


def _normal_axis(chunks: FrameChunks) -> np.ndarray | None:
    """e3 from the chunks' normals (_frame), None when no chunk has a usable one. Three
    passes; chunks held in memory (a list: choose_frame's one) have their unit normals
    made once for the three (0.1 s less at 1M points), streamed ones in each pass (a
    stream's iterator reads nothing until it is iterated, so the one asked for here to
    see which kind it is costs nothing)."""
    held = chunks()
    if isinstance(held, list):
        units = [_unit_normals(points, normals) for points, normals in held]
        passes: Callable[[], Iterable[np.ndarray]] = lambda: units
    else:
        passes = lambda: (_unit_normals(points, normals) for points, normals in chunks())
    scatter, used = np.zeros((3, 3)), 0
    for unit in passes():
        scatter += unit.T @ unit
        used += len(unit)
    if used == 0:
        return None
    dominant = np.linalg.eigh(scatter)[1][:, -1]
    mean = np.zeros(3)
    for unit in passes():
        mean += (unit * np.where(unit @ dominant < 0, -1.0, 1.0)[:, None]).sum(axis=0)
    e3 = mean / np.linalg.norm(mean) if np.linalg.norm(mean) > 0 else dominant
    votes = 0.0
    for unit in passes():
        votes += np.sign(unit @ e3).sum()
    return -e3 if votes < 0 else e3


def _least_variance_axis(chunks: FrameChunks, origin: np.ndarray) -> np.ndarray:
    """e3 by PCA of the chunks' finite points about origin (_frame)."""
    scatter, count = np.zeros((3, 3)), 0
    for points, _ in chunks():
        centred = _finite(points) - origin
        scatter += centred.T @ centred
        count += len(centred)
    if count < 3:
        raise InputError(f"choosing the height axis needs at least 3 points, got {count}; "
                         "give --axis x|y|z or X,Y,Z")
    e3 = np.linalg.eigh(scatter)[1][:, 0]
    return -e3 if e3[np.argmax(np.abs(e3))] < 0 else e3


def parse_axis(axis: str | ArrayLike) -> np.ndarray | None:
    """Unit e3 from an axis specification, or None for "auto"."""
    if isinstance(axis, str):
        text = axis.strip().lower()
        if text == "auto":
            return None
        sign, name = (-1.0, text[1:]) if text[:1] == "-" else (1.0, text.lstrip("+"))
        if name in _WORLD_AXES:
            return sign * np.eye(3)[_WORLD_AXES[name]]
        try:
            vec = np.array([float(part) for part in text.split(",")])
        except ValueError:
            vec = np.zeros(0)
        if vec.shape != (3,):
            raise InputError(f"axis must be 'auto', 'x', 'y', 'z' (optionally signed, e.g. '-z') "
                             f"or three numbers 'X,Y,Z', got {axis!r}")
    else:
        vec = np.asarray(axis, dtype=np.float64)
        if vec.shape != (3,):
            raise InputError(f"an axis vector must have 3 components, got shape {vec.shape}")
    scale = np.max(np.abs(vec))     # first, so that 1e200,1e200,1e200 does not overflow the norm
    if not np.isfinite(scale) or scale == 0.0:
        raise InputError(f"the axis {axis!r} has no direction (zero, NaN or Inf); give a nonzero X,Y,Z")
    vec = vec / scale
    return vec / np.linalg.norm(vec)


UNIT_ANISOTROPY = 100.0
"""Coordinates whose robust spreads differ by more than this factor are taken to be in
different units (degrees and metres, metres and millimetres): then angles, normals and
PCA directions mean nothing, and axis "auto" chooses among the world axes instead."""
UNITS_DIFFER = ("auto: the coordinates are in different units (spreads differ by more than "
                f"{UNIT_ANISOTROPY:g}x), so the world axis over which the points form a height field")
"""ScanFrame.axis_reason where choose_frame found the units differ."""


def _spreads(points: np.ndarray) -> np.ndarray:
    """Robust per-coordinate spread (3,): the 5-95% inter-percentile range of points (n, 3)."""
    low, high = np.percentile(points, [5, 95], axis=0)
    return high - low


def _units_differ(points: np.ndarray) -> bool:
    """True when the coordinates' spreads differ by more than UNIT_ANISOTROPY (see there)."""
    spread = _spreads(points)
    return bool(spread.min() > 0 and spread.max() > UNIT_ANISOTROPY * spread.min())


def _world_axis_by_layering(points: np.ndarray, samples: int = 20000) -> np.ndarray:
    """The world axis (+x, +y or +z) over which points (n, 3) are most nearly a height field.

    Each coordinate is divided by its spread (unit-free). For each axis, every sampled
    point's nearest neighbour over the other two coordinates is found; the score is the
    median height difference to it over the median distance to it. Over the right axis
    neighbours in the plane have similar heights (a slope); over a wrong one the surface
    is folded onto itself and plane neighbours lie far apart in height.
    """
    scaled = points / _spreads(points)
    scaled = scaled[:: max(1, scaled.shape[0] // samples)]
    scores = []
    for a in range(3):
        plane = np.delete(scaled, a, axis=1)
        distance, index = kd_tree(plane).query(plane, k=2)
        step = np.abs(scaled[index[:, 1], a] - scaled[:, a])
        scores.append(np.median(step) / max(np.median(distance[:, 1]), np.finfo(float).tiny))
    return np.eye(3)[int(np.argmin(scores))]


def axes_from_e3(e3: np.ndarray) -> np.ndarray:
    """Rows e1, e2, e3 of a right-handed orthonormal frame with the given unit e3."""
    dominant = int(np.argmax(np.abs(e3)))
    candidates = [(dominant + 1) % 3, (dominant + 2) % 3]
    pick = min(candidates, key=lambda i: abs(e3[i]))  # stable: ties keep cyclic order
    e1 = np.eye(3)[pick] - e3[pick] * e3
    e1 /= np.linalg.norm(e1)
    return np.array([e1, np.cross(e3, e1), e3])


def resolve_axis(source, axis, input_format: str | None = None) -> tuple[object, str]:
    """The height axis with "auto" resolved for LAS/LAZ (z: elevation by the format's
    definition), read from `input_format` or the source's extension, and a phrase saying
    how the height axis is chosen, for the report."""
    if not (isinstance(axis, str) and axis.strip().lower() == "auto"):
        return axis, f"given: {axis}"
    fmt = input_format or (Path(source).suffix if isinstance(source, (str, Path)) else "")
    if str(fmt).lower().lstrip(".") in LAS_FORMATS:
        return "z", "z: LAS/LAZ elevation"
    return axis, "auto"
