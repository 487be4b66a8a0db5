"""The thinned vertex set of --spacing: one point per cell, the one nearest its centre."""
import numpy as np
import pytest

from c1mesh.core.errors import InputError
from c1mesh.stages.thinning import check_spacing, thin_cells, thin_to_cells


def _brute_force(xy, spacing, low=None, tie=None):
    """One point per cell by a plain loop: the nearest to the cell centre, the lowest tie
    (index) among equals; cells aligned at low (the points' lower-left corner)."""
    low = xy.min(axis=0) if low is None else low
    tie = np.arange(len(xy)) if tie is None else tie
    best = {}
    for i, p in enumerate(xy):
        cell = tuple(np.floor((p - low) / spacing).astype(int))
        centre = low + (np.array(cell) + 0.5) * spacing
        d = float(((p - centre) ** 2).sum())
        if cell not in best or (d, tie[i]) < best[cell][:2]:
            best[cell] = (d, tie[i], i)
    return np.sort([i for _, _, i in best.values()])


def test_matches_a_plain_loop_on_random_points():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 10, (2000, 2))
    np.testing.assert_array_equal(thin_to_cells(xy, 0.7), _brute_force(xy, 0.7))


def test_cells_aligned_at_a_given_corner_with_ties_by_a_given_number():
    """thin_cells (the tiles' form): cells aligned at any corner, ties by survey number;
    on a grid whose points tie in distance, the numbers decide."""
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 10, (1500, 2))
    tie = rng.permutation(1500) * 7
    low = np.array([-0.3, -1.1])
    np.testing.assert_array_equal(thin_cells(xy, 0.9, low, tie), _brute_force(xy, 0.9, low, tie))
    grid = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0)), -1).reshape(-1, 2)   # 4 per 2 x 2 cell, tied
    tie = np.arange(16)[::-1]
    np.testing.assert_array_equal(thin_cells(grid, 2.0, np.array([-0.5, -0.5]), tie),
                                  _brute_force(grid, 2.0, np.array([-0.5, -0.5]), tie))


def test_a_regular_grid_thinned_by_its_own_step_keeps_every_point():
    g = np.stack(np.meshgrid(np.arange(20.0), np.arange(15.0)), -1).reshape(-1, 2) + 0.5
    assert thin_to_cells(g, 1.0).size == g.shape[0]
    assert thin_to_cells(g, 2.0).size == 10 * 8          # ceil(20/2) × ceil(15/2) cells


def test_order_of_the_input_does_not_change_the_chosen_points():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 5, (500, 2))
    perm = rng.permutation(500)
    chosen = xy[thin_to_cells(xy, 0.5)]
    chosen_perm = xy[perm][thin_to_cells(xy[perm], 0.5)]
    assert {tuple(p) for p in chosen} == {tuple(p) for p in chosen_perm}


def test_nan_rows_are_never_kept():
    xy = np.array([[0.0, 0.0], [np.nan, 1.0], [3.0, 3.0]])
    np.testing.assert_array_equal(thin_to_cells(xy, 1.0), [0, 2])


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_spacing_is_refused(bad):
    with pytest.raises(InputError, match="--spacing"):
        check_spacing(bad)
