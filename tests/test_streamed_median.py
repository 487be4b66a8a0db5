"""c1mesh.stages.streamed_median against np.median on the same values held in memory."""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.stages.streamed_median import order_statistic, streamed_median, streamed_medians


def _chunks(values, size):
    return lambda: (values[i:i + size] for i in range(0, len(values), size))


@pytest.mark.parametrize("count", [1, 2, 7, 1000, 1001, 50_000])
def test_median_equals_numpy_to_the_bit(count):
    rng = np.random.default_rng(count)
    values = np.abs(rng.standard_t(2, count)) * 10.0 ** rng.integers(-12, 3, count)
    values[rng.random(count) < 0.05] = 0.0
    assert streamed_median(_chunks(values, 777), gather=64) == np.median(values)
    assert streamed_median(_chunks(values, 10**6)) == np.median(values)


def test_many_equal_values_and_tight_clusters():
    rng = np.random.default_rng(1)
    base = 0.125
    values = np.concatenate([np.full(5000, base), base + rng.integers(1, 40, 5001) * np.spacing(base)])
    rng.shuffle(values)
    assert streamed_median(_chunks(values, 333), gather=16) == np.median(values)
    for rank in (0, 4999, 5000, 10000):     # every 64 bits resolved when the bin stays big
        assert order_statistic(_chunks(values, 333), rank, gather=1) == np.sort(values)[rank]


def test_empty_and_nan():
    assert np.isnan(streamed_median(_chunks(np.empty(0), 10)))
    assert np.isnan(streamed_median(_chunks(np.array([1.0, np.nan, 2.0]), 2)))


@pytest.mark.parametrize("count", [1, 2, 1000, 1001])
def test_signed_values_and_infinities_order_as_numbers(count):
    """Negative values, both zeros and infinities: the order keys sort as the floats do."""
    rng = np.random.default_rng(count)
    values = rng.normal(0, 1, count) * 10.0 ** rng.integers(-12, 12, count)
    values[rng.random(count) < 0.05] = -0.0
    values[rng.random(count) < 0.02] = np.inf
    values[rng.random(count) < 0.02] = -np.inf
    assert streamed_median(_chunks(values, 33), gather=8) == np.median(values)
    for rank in {0, count // 2, count - 1}:
        assert order_statistic(_chunks(values, 33), rank, gather=1) == np.sort(values)[rank]


@pytest.mark.parametrize("count", [1000, 1001])
def test_columns_are_selected_together_and_equal_numpys_per_column_median(count):
    rng = np.random.default_rng(7)
    rows = rng.normal(0, 1, (count, 3)) * [1e3, 1, 1e-3] + [5e5, 0, -7]
    rows[::50, 1] = rows[1, 1]                                  # ties
    chunks = _chunks(rows, 97)
    assert np.array_equal(streamed_medians(chunks, 3, gather=64), np.median(rows, axis=0))
    assert np.array_equal(streamed_medians(_chunks(rows, count), 3), np.median(rows, axis=0))
