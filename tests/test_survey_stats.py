"""Survey-wide frame from streamed passes (c1mesh.survey.survey_stats) against frame.choose_frame
on the whole cloud at once."""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.stages.frame import choose_frame
from c1mesh.testing.samples import sample_surface
from c1mesh.survey.survey_stats import streamed_frame, streamed_median


def _chunked(points, normals, size):
    def chunks():
        for start in range(0, len(points), size):
            yield points[start:start + size], None if normals is None else normals[start:start + size]
    return chunks


@pytest.mark.parametrize("n", [1000, 1001])
@pytest.mark.parametrize("size", [1, 97, 5000])
def test_streamed_median_is_numpys_to_the_bit(n, size):
    rng = np.random.default_rng(n)
    points = rng.normal(0, 1, (n, 3)) * [1e3, 1, 1e-3] + [5e5, 0, 7]
    points[::50, 1] = points[1, 1]                              # ties
    points[3] = [np.nan, 0, 0]                                  # dropped, as choose_frame drops it
    finite = points[np.isfinite(points).all(axis=1)]
    assert np.array_equal(streamed_median(_chunked(points, None, size)), np.median(finite, axis=0))


@pytest.mark.parametrize("with_normals", [True, False])
def test_streamed_frame_is_choose_frame(with_normals):
    cloud = sample_surface("hill", n=5000, seed=2)
    tilt = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]    # a frame that is not z
    points = cloud.points @ tilt.T
    normals = cloud.normals @ tilt.T if with_normals else None
    whole = choose_frame(points, normals)
    for size in (333, 5000):
        streamed = streamed_frame(_chunked(points, normals, size))
        assert np.array_equal(streamed.origin, whole.origin)
        assert np.allclose(streamed.axes, whole.axes, rtol=0, atol=1e-12)
    assert not np.allclose(whole.axes[2], [0, 0, 1], atol=1e-3)      # the axis is a found one
