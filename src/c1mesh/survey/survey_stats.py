"""Survey-wide quantities from passes over the points in chunks, never all of them at once.

A survey too big for memory is cut into tiles (c1mesh.survey.buffered_delaunay), but what the
whole-file fit takes from all points must not depend on that cut. The frame is computed
here from streamed sums and exact streamed order statistics over the points in survey
order (input files in the order given, each in its own order); the auto max_edge and the
survey's hull come from buffered_delaunay.

`chunks` is a callable returning a fresh iterator of (points (m, 3), normals (m, 3) or
None) in survey order, world coordinates; each pass calls it once.
"""
from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

from c1mesh.core.errors import InputError
from c1mesh.stages.frame import ScanFrame, axes_from_e3, parse_axis

Chunks = Callable[[], Iterable[tuple[np.ndarray, np.ndarray | None]]]

HISTOGRAM_BINS = 1 << 16
"""Bins of the histogram that narrows an order statistic down before its exact selection."""


def streamed_median(chunks: Chunks) -> np.ndarray:
    """(3,) the per-coordinate median of all finite points, as np.median gives it (the middle
    value, or the mean of the two middle values), in three passes: count and range, a
    histogram that finds the bins of the middle ranks, the values of those bins."""
    count, low, high = 0, np.full(3, np.inf), np.full(3, -np.inf)
    for points, _ in chunks():
        finite = _finite(points)
        count += len(finite)
        if len(finite):
            low, high = np.minimum(low, finite.min(axis=0)), np.maximum(high, finite.max(axis=0))
    if count == 0:
        raise InputError("there are no points with finite coordinates to choose a frame from")
    ranks = [count // 2] if count % 2 else [count // 2 - 1, count // 2]
    edges = [np.linspace(low[c], high[c], HISTOGRAM_BINS + 1) for c in range(3)]
    counts = np.zeros((3, HISTOGRAM_BINS), dtype=np.int64)
    for points, _ in chunks():
        finite = _finite(points)
        for c in range(3):
            counts[c] += np.bincount(_bin(finite[:, c], edges[c]), minlength=HISTOGRAM_BINS)
    before = np.cumsum(counts, axis=1) - counts            # points in the bins below each bin
    wanted = [sorted({int(np.searchsorted(np.cumsum(counts[c]), r, side="right")) for r in ranks})
              for c in range(3)]
    values: list[list[np.ndarray]] = [[] for _ in range(3)]
    for points, _ in chunks():
        finite = _finite(points)
        for c in range(3):
            bins = _bin(finite[:, c], edges[c])
            values[c].append(finite[np.isin(bins, wanted[c]), c])
    median = np.empty(3)
    for c in range(3):
        pool = np.sort(np.concatenate(values[c]))
        first = before[c, wanted[c][0]]
        middle = pool[[r - first for r in ranks]]
        median[c] = middle[0] if len(middle) == 1 else np.mean(middle)
    return median


def _finite(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    good = np.isfinite(points).all(axis=1)
    return points if good.all() else points[good]


def _bin(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The histogram bin of each value: bins hold [edge_i, edge_i+1), the last one closed.
    Monotone in the value, so a rank's bin holds every value between its neighbours."""
    return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)


def streamed_frame(chunks: Chunks, axis="auto"):
    """The survey's ScanFrame by frame.choose_frame's rules, from passes over chunks:
    origin = the exact per-coordinate median; e3 from the normals (the dominant direction
    of sum n n^T, the mean of the normals turned to its side, signed by the majority) or,
    when no chunk has normals, the least-variance direction of the points about the origin.
    The sums run chunk by chunk in survey order, so e3 agrees with choose_frame on the whole
    cloud to rounding (a different summation order), and does not depend on any tiling."""
    origin = streamed_median(chunks)
    e3 = parse_axis(axis)
    if e3 is None:
        e3 = _normal_axis(chunks)
    if e3 is None:
        e3 = _least_variance_axis(chunks, origin)
    return ScanFrame(origin=origin, axes=axes_from_e3(e3))


def _unit_normals(points, normals) -> np.ndarray:
    """The chunk's usable normals, unit length (rows of non-finite points dropped, as
    choose_frame drops them, then zero or non-finite normals)."""
    if normals is None:
        return np.empty((0, 3))
    normals = np.asarray(normals, dtype=np.float64)[np.isfinite(np.asarray(points, dtype=np.float64)).all(axis=1)]
    length = np.linalg.norm(normals, axis=1)
    ok = np.isfinite(length) & (length > 0)
    return normals[ok] / length[ok, None]


def _normal_axis(chunks: Chunks) -> np.ndarray | None:
    scatter, used = np.zeros((3, 3)), 0
    for points, normals in chunks():
        unit = _unit_normals(points, normals)
        scatter += unit.T @ unit
        used += len(unit)
    if used == 0:
        return None
    dominant = np.linalg.eigh(scatter)[1][:, -1]
    mean = np.zeros(3)
    for points, normals in chunks():
        unit = _unit_normals(points, normals)
        mean += (unit * np.where(unit @ dominant < 0, -1.0, 1.0)[:, None]).sum(axis=0)
    e3 = mean / np.linalg.norm(mean) if np.linalg.norm(mean) > 0 else dominant
    votes = 0.0
    for points, normals in chunks():
        votes += np.sign(_unit_normals(points, normals) @ e3).sum()
    return -e3 if votes < 0 else e3


def _least_variance_axis(chunks: Chunks, origin: np.ndarray) -> np.ndarray:
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
