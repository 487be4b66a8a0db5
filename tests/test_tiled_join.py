"""The tiled fit's survey-sized state replaced by halo- and band-sized state.

- tiled_limiter.halo_rows (a binary search over one halo) against a dense table over the
  survey (the RowMap it replaced: 4 bytes a survey point in every process);
- tiled_join: the join that forgets a border key once no later tile can meet it must
  number every vertex as the join that keeps every key, on real tile refinements of a
  triangulation with a hole (border keys inside the survey) at levels with edge keys.
"""
from __future__ import annotations

import numpy as np

from c1mesh.tiled_limiter import halo_rows


def test_halo_rows_equal_a_dense_table_over_the_survey():
    rng = np.random.default_rng(3)
    survey = 50_000
    index = np.sort(rng.choice(survey, 4_000, replace=False))
    dense = np.full(survey, -1, dtype=np.int64)
    dense[index] = np.arange(len(index))
    queries = rng.integers(0, survey, (20_000, 3))
    queries[:500] = index[rng.integers(0, len(index), (500, 3))]       # many present
    queries[500, 0], queries[501, 0] = survey - 1, 0                    # beyond either end
    queries[502, 0] = index[-1] + 1 if index[-1] + 1 < survey else 0
    rows = halo_rows(index, queries)
    assert rows.shape == queries.shape
    assert np.array_equal(rows, dense[queries])
    assert (rows >= 0).sum() > 1_500 and (rows < 0).sum() > 10_000
    assert np.array_equal(halo_rows(index[:0], queries[:4]), np.full((4, 3), -1))
