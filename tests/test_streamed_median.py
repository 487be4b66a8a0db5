"""c1mesh.survey.streamed_median against np.median on the same values held in memory."""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.survey.streamed_median import order_statistic, streamed_median


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


def test_empty_nan_and_negative():
    assert np.isnan(streamed_median(_chunks(np.empty(0), 10)))
    assert np.isnan(streamed_median(_chunks(np.array([1.0, np.nan, 2.0]), 2)))
    with pytest.raises(ValueError):
        streamed_median(_chunks(np.array([1.0, -2.0]), 2))
