"""The frame of a survey read in chunks (stages.frame.frame_of_chunks) against
frame.choose_frame on the whole cloud at once, and the per-coordinate median of chunks
(stages.streamed_median) against np.median."""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.stages.frame import _finite, choose_frame, frame_of_chunks
from c1mesh.stages.streamed_median import streamed_medians
from c1mesh.testing.samples import sample_surface


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
    medians = streamed_medians(lambda: (_finite(p) for p, _ in _chunked(points, None, size)()), 3, gather=64)
    assert np.array_equal(medians, np.median(finite, axis=0))


@pytest.mark.parametrize("with_normals", [True, False])
def test_streamed_frame_is_choose_frame(with_normals):
    cloud = sample_surface("hill", n=5000, seed=2)
    tilt = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]    # a frame that is not z
    points = cloud.points @ tilt.T
    normals = cloud.normals @ tilt.T if with_normals else None
    whole = choose_frame(points, normals)
    for size in (333, 5000):
        streamed = frame_of_chunks(_chunked(points, normals, size))
        assert np.array_equal(streamed.origin, whole.origin)
        assert np.allclose(streamed.axes, whole.axes, rtol=0, atol=1e-12)
    assert not np.allclose(whole.axes[2], [0, 0, 1], atol=1e-3)      # the axis is a found one
