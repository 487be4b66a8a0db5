"""The exact median of non-negative floats that do not fit in memory, read in chunks.

The overshoot limiter's noise floor is the median |trapezoid residual| over every edge of
the survey (c1mesh.stages.limiter). A survey fitted in tiles spills those residuals to a file;
this module finds `np.median` of them to the bit while holding one chunk and a small
set of candidates.

Method: a non-negative float64's bit pattern, read as uint64, orders like the float
(+0.0 < subnormals < normals < inf < nan). So the value of a given rank is found by
radix selection on those 64 bits: a histogram of the top RADIX_BITS bits of every value
tells which bin holds the rank; later passes look only at values in that bin, at the next
bits, until the bin holds at most `gather` values, which are collected and partitioned.
Each pass reads the chunks once; the usual case is two passes per rank.
"""
from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

Chunks = Callable[[], Iterable[np.ndarray]]
"""A callable giving a fresh iterator of float64 arrays (non-negative values or nan)."""

RADIX_BITS = 16
"""Bits of the value's pattern each histogram pass resolves (2**16 bins)."""
GATHER = 1 << 20
"""A bin with at most this many values is collected and partitioned in memory (8 MB;
the collected parts, their concatenation and the partition's copy are held at once)."""


def streamed_median(chunks: Chunks, gather: int = GATHER) -> float:
    """np.median of the concatenated chunks (non-negative float64), exactly: the middle
    value, or for an even count the mean of the two middle values as np.median computes
    it; nan when any value is nan or there are none (np.median's answers)."""
    count, nan, negative = 0, False, False
    for part in chunks():
        part = np.asarray(part, dtype=np.float64)
        count += part.size
        nan = nan or bool(np.isnan(part).any())
        negative = negative or bool((part < 0).any())
    if negative:
        raise ValueError("streamed_median takes non-negative values only")
    if count == 0 or nan:
        return float("nan")
    upper = count // 2
    if count % 2:
        return float(order_statistic(chunks, upper, gather))
    middle = np.array([order_statistic(chunks, upper - 1, gather), order_statistic(chunks, upper, gather)])
    return float(np.median(middle))


def order_statistic(chunks: Chunks, rank: int, gather: int = GATHER) -> float:
    """The value of 0-based `rank` in ascending order of the concatenated chunks
    (non-negative float64, no nan), by radix selection on the bit patterns."""
    prefix, known, size = np.uint64(0), 0, None   # the top `known` bits of the answer, values with them
    while True:
        if size is not None and size <= gather:
            values = np.concatenate([_in_bin(part, prefix, known) for part in chunks()] or [np.empty(0)])
            return float(np.partition(values, rank)[rank])
        shift = 64 - known - RADIX_BITS
        histogram = np.zeros(1 << RADIX_BITS, dtype=np.int64)
        for part in chunks():
            bits = _in_bin(part, prefix, known).view(np.uint64)
            histogram += np.bincount(((bits >> np.uint64(shift)) & np.uint64((1 << RADIX_BITS) - 1))
                                     .astype(np.int64), minlength=1 << RADIX_BITS)
        below = np.cumsum(histogram)
        digit = int(np.searchsorted(below, rank, side="right"))
        rank -= int(below[digit - 1]) if digit else 0
        size = int(histogram[digit])
        prefix |= np.uint64(digit) << np.uint64(shift)
        known += RADIX_BITS
        if known == 64:                           # every bit known: the value itself
            return float(np.array([prefix], dtype=np.uint64).view(np.float64)[0])


def _in_bin(part, prefix: np.uint64, known: int) -> np.ndarray:
    """The values of part whose top `known` bits equal those of prefix."""
    values = np.ascontiguousarray(part, dtype=np.float64).ravel()
    if not known:
        return values
    shift = np.uint64(64 - known)
    return values[(values.view(np.uint64) >> shift) == (prefix >> shift)]
