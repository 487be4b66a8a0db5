"""Exact medians and order statistics of float64 columns that do not fit in memory, read in
chunks.

What the whole-survey fit takes from all points or edges must not depend on how they are
cut into tiles: the frame's origin is the per-coordinate median of the points
(stages.frame), the limiter's noise floor the median |trapezoid residual| over every edge
(stages.limiter), the automatic max_edge a median of edge lengths. In memory these are
np.median of one array; over tiles the values come in chunks. This module gives np.median's
answer to the bit in both cases, holding one chunk and a small set of candidates.

Method: a float64's bit pattern, read as uint64, with the sign bit flipped for
non-negative values and every bit flipped for negative ones, orders like the float
(-inf < negatives < -0.0 < +0.0 < positives < inf). So the value of a given rank is
found by radix selection on those 64 bits: a histogram of the top RADIX_BITS bits of
every value tells which bin holds the rank; later passes look only at values in that bin,
at the next bits, until the bin holds at most `gather` values, which are collected and
partitioned. All columns and ranks asked for advance in the same pass over the chunks;
the usual case is two or three passes. The kernels (stages/_streamed_median.pyx) make
each key as they read its value and count or collect it in one loop: the 12M-point
survey's three medians took 2.2 s with numpy's key arrays, masks and bincounts, 0.6 s so
(most of it reading the chunks).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from c1mesh.core.threads import map_in_threads
from c1mesh.stages import _streamed_median as kernel

Chunks = Callable[[], Iterable[np.ndarray]]
"""A callable giving a fresh iterator of float64 arrays: (m,) values, or (m, c) rows of c
columns (no nan: the caller drops the rows it does not count)."""

RADIX_BITS = 16
"""Bits of the value's key each histogram pass resolves (2**16 bins)."""
GATHER = 1 << 20
"""A bin with at most this many values is collected and partitioned in memory (8 MB;
the collected parts, their concatenation and the partition's copy are held at once)."""
_SIGN = np.uint64(1 << 63)


class NoValues(ValueError):
    """There were no values (rows) to take a median of."""


def _value_of(key: np.uint64) -> float:
    """The float64 whose order key is `key`."""
    bits = key & ~_SIGN if key & _SIGN else ~key
    return float(np.array([bits], dtype=np.uint64).view(np.float64)[0])


def streamed_median(chunks: Chunks, gather: int = GATHER) -> float:
    """np.median of the concatenated 1-D chunks (float64), exactly: the middle value, or
    for an even count the mean of the two middle values as np.median computes it; nan
    when any value is nan or there are none (np.median's answers)."""
    count, nan = 0, False
    for part in chunks():
        part = np.asarray(part, dtype=np.float64)
        count += part.size
        nan = nan or bool(np.isnan(part).any())
    if count == 0 or nan:
        return float("nan")
    return float(_medians(_one_column(chunks), 1, count, gather)[0])


def streamed_medians(chunks: Chunks, columns: int, gather: int = GATHER) -> np.ndarray:
    """(columns,) np.median(axis=0) of the concatenated (m, columns) chunks, exactly, in the
    same passes for every column. One chunk is np.median itself. No nan allowed; NoValues
    when there are no rows."""
    parts = iter(chunks())
    first = next(parts, None)
    if first is not None and next(parts, None) is None:
        if len(first) == 0:
            raise NoValues("streamed_medians needs at least one row")
        rows = np.asarray(first, dtype=np.float64).reshape(-1, columns)
        # np.median(rows, axis=0), one column a thread (the same values; 84 -> 50 ms at 1M rows of 3)
        return np.array(map_in_threads(lambda k: np.median(rows[:, k]), list(range(columns))))
    count = sum(len(part) for part in chunks())
    if count == 0:
        raise NoValues("streamed_medians needs at least one row")
    return _medians(chunks, columns, count, gather)


def _medians(chunks: Chunks, columns: int, count: int, gather: int) -> np.ndarray:
    """(columns,) the exact per-column medians of the count (> 0) rows of chunks, by
    radix selection of the middle rank(s), every column in the same passes."""
    upper = count // 2
    ranks = [upper] if count % 2 else [upper - 1, upper]
    tasks = [_Task(c, r) for c in range(columns) for r in ranks]
    _select(chunks, tasks, gather)
    values = np.array([t.value for t in tasks]).reshape(columns, len(ranks))
    return values[:, 0] if len(ranks) == 1 else np.median(values, axis=1)


def order_statistic(chunks: Chunks, rank: int, gather: int = GATHER) -> float:
    """The value of 0-based `rank` in ascending order of the concatenated 1-D chunks
    (float64, no nan), by radix selection on the order keys."""
    task = _Task(0, rank)
    _select(_one_column(chunks), [task], gather)
    return task.value


def _one_column(chunks: Chunks) -> Chunks:
    """1-D chunks as chunks of (m, 1) rows."""
    return lambda: (np.asarray(part, dtype=np.float64).reshape(-1, 1) for part in chunks())


@dataclass
class _Task:
    """One order statistic being selected: column, rank within the values whose key has
    the top `known` bits of prefix, size of that bin (None: not yet measured), value once
    found."""

    column: int
    rank: int
    prefix: np.uint64 = np.uint64(0)
    known: int = 0
    size: int | None = None
    value: float | None = None


def _select(chunks: Chunks, tasks: list[_Task], gather: int) -> None:
    """Find every task's value: passes over chunks, each advancing all unfinished tasks
    by a histogram of RADIX_BITS more bits, or gathering a bin of at most `gather` keys."""
    while True:
        open_tasks = [t for t in tasks if t.value is None]
        if not open_tasks:
            return
        gathering = [t for t in open_tasks if t.size is not None and t.size <= gather]
        counting = [t for t in open_tasks if t not in gathering]
        # tasks in one bin of one column share its histogram (an even count's two middle ranks)
        bins = sorted({(t.column, int(t.prefix), t.known) for t in counting})
        histograms = [np.zeros(1 << RADIX_BITS, dtype=np.int64) for _ in bins]
        gathered: list[list[np.ndarray]] = [[] for _ in gathering]
        for part in chunks():
            rows = np.asarray(part, dtype=np.float64)
            if rows.size == 0:
                continue
            rows = rows.reshape(len(rows), -1)
            # one bin a thread, each into its own histogram: the same counts at any thread count
            map_in_threads(lambda b: kernel.bin_histogram(rows[:, bins[b][0]], bins[b][1], bins[b][2], RADIX_BITS,
                                                          histograms[b]), list(range(len(bins))))
            for task, found in zip(gathering, gathered):
                keys = np.empty(len(rows), dtype=np.uint64)
                found.append(keys[:kernel.gather_bin(rows[:, task.column], task.prefix, task.known, keys)].copy())
        for task, found in zip(gathering, gathered):
            pool = np.concatenate(found) if found else np.empty(0, dtype=np.uint64)
            task.value = _value_of(np.partition(pool, task.rank)[task.rank])
        for task in counting:
            _narrow(task, histograms[bins.index((task.column, int(task.prefix), task.known))])


def _narrow(task: _Task, histogram: np.ndarray) -> None:
    """Move task into the bin of `histogram` (its next RADIX_BITS) that holds its rank."""
    below = np.cumsum(histogram)
    digit = int(np.searchsorted(below, task.rank, side="right"))
    task.rank -= int(below[digit - 1]) if digit else 0
    task.size = int(histogram[digit])
    task.prefix |= np.uint64(digit) << np.uint64(64 - task.known - RADIX_BITS)
    task.known += RADIX_BITS
    if task.known == 64:                           # every bit known: the value itself
        task.value = _value_of(task.prefix)
