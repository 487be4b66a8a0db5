"""Independent checks of contour lines for the tests: segment crossings found by a
brute-force orientation test over the pairs of segments whose bounding boxes share a
bucket of a uniform grid (no use of how the lines were traced)."""
from __future__ import annotations

from collections import defaultdict

import numpy as np


def segments(lines) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(start (S, 2), end (S, 2), line (S,), index in its line (S,), segments of its line (S,))
    of the lines ((n, 2) arrays; a closed line repeats its first vertex at the end)."""
    starts, ends, line_of, index, count = [], [], [], [], []
    for k, xy in enumerate(lines):
        n = xy.shape[0] - 1
        starts.append(xy[:-1])
        ends.append(xy[1:])
        line_of.append(np.full(n, k))
        index.append(np.arange(n))
        count.append(np.full(n, n))
    return tuple(np.concatenate(a) for a in (starts, ends, line_of, index, count))


def _orient(a, b, c):
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def candidate_pairs(start, end) -> np.ndarray:
    """(K, 2) pairs i < j of segments whose bounding boxes meet a common bucket."""
    lo, hi = np.minimum(start, end), np.maximum(start, end)
    cell = 4 * max(float(np.median(np.linalg.norm(end - start, axis=1))), 1e-12)
    first, last = np.floor(lo / cell).astype(np.int64), np.floor(hi / cell).astype(np.int64)
    buckets = defaultdict(list)
    for s in range(start.shape[0]):
        for i in range(first[s, 0], last[s, 0] + 1):
            for j in range(first[s, 1], last[s, 1] + 1):
                buckets[i, j].append(s)
    pairs = set()
    for members in buckets.values():
        for a in range(len(members)):
            for b in range(a + 1, len(members)):
                pairs.add((members[a], members[b]))
    return np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)


def crossings(lines, closed) -> np.ndarray:
    """(K, 2) pairs of segments that meet (cross or touch), leaving out the two segments
    around each vertex of a line (and the closing pair of a closed line)."""
    start, end, line, index, count = segments(lines)
    pairs = candidate_pairs(start, end)
    a, b = pairs[:, 0], pairs[:, 1]
    same = line[a] == line[b]
    gap = np.abs(index[a] - index[b])
    closing = np.asarray(closed, bool)[line[a]] & (gap == count[a] - 1)
    neighbours = same & ((gap == 1) | closing)
    a, b = a[~neighbours], b[~neighbours]
    p, q, r, s = start[a], end[a], start[b], end[b]
    d1, d2, d3, d4 = _orient(p, q, r), _orient(p, q, s), _orient(r, s, p), _orient(r, s, q)
    boxes = (np.minimum(p, q) <= np.maximum(r, s)).all(axis=1) & (np.minimum(r, s) <= np.maximum(p, q)).all(axis=1)
    meet = (d1 * d2 <= 0) & (d3 * d4 <= 0) & boxes
    return np.column_stack([a[meet], b[meet]])
