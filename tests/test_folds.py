"""The fold net's parts (stages/folds.py): the triangles whose refinement folds a face,
against the whole refinement checked face by face; the cells' stiffness levels; and the
lattice system's added energy (LatticeSystem.stiffen) against a brute-force sum."""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.engine.schemes import DEFAULT_SCHEME, get_scheme
from c1mesh.stages.folds import FOLD_LEVEL, STIFFENING, CellStiffness, fold_candidates, folded_triangles
from c1mesh.testing.quality import folded_faces
from test_lattice_system import brute_force, built, lattice_problem

SCHEME = get_scheme(DEFAULT_SCHEME)


def _lattice(n: int, spacing: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(points (n², 2), triangles) of an n × n lattice, each cell split by its (i, j)-(i+1, j+1)
    diagonal (stages.lattice_mesh's)."""
    g = np.arange(n) * spacing
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.column_stack([x, y]), np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def _brute_folded(points, values, gradients, triangles, level) -> np.ndarray:
    """The triangles (ascending) with a folded face in the whole refinement, each face
    checked against its corners' normals (quality.folded_faces, one face at a time)."""
    mesh = RSDInterpolator(points, values, gradients, triangles=triangles, scheme=SCHEME).refine(level)
    vertices = np.column_stack([mesh.points, mesh.values])
    normals = np.column_stack([-mesh.gradients, np.ones(mesh.values.size)])
    bad = [k for k in range(mesh.triangles.shape[0])
           if folded_faces(vertices, mesh.triangles[k:k + 1], normals)]
    return np.unique(mesh.parent[bad])


@pytest.mark.parametrize("seed", range(4))
def test_the_folded_triangles_are_those_of_the_whole_refinement(seed):
    """A step narrower than a cell with ringing corner gradients folds faces; folded_triangles
    refines only its candidates and finds every triangle the whole refinement folds."""
    rng = np.random.default_rng(seed)
    points, triangles = _lattice(9)
    x = points[:, 0]
    values = 3.0 * np.clip(x - 3.6, 0.0, 1.0) + rng.normal(0.0, 0.05, x.size)
    gradients = np.column_stack([np.where(np.abs(x - 4.0) < 1.5, rng.normal(0.0, 4.0, x.size), 0.0),
                                 rng.normal(0.0, 0.05, x.size)])
    want = _brute_folded(points, values, gradients, triangles, FOLD_LEVEL)
    got = folded_triangles(points, values, gradients, triangles, SCHEME)
    assert want.size > 0
    np.testing.assert_array_equal(got, want)
    assert np.isin(want, fold_candidates(points, values, gradients, triangles)).all()


def test_smooth_terrain_has_no_candidates():
    """A sloped, gently curved surface's exact data (slopes up to 0.6) leave every corner
    gradient within SPREAD of its triangle's slope: nothing is refined."""
    points, triangles = _lattice(12)
    x, y = points[:, 0], points[:, 1]
    values = 0.5 * x + 0.3 * y + 0.02 * np.sin(x / 3.0) * y
    gradients = np.column_stack([0.5 + 0.02 / 3.0 * np.cos(x / 3.0) * y, 0.3 + 0.02 * np.sin(x / 3.0)])
    assert fold_candidates(points, values, gradients, triangles).size == 0
    assert folded_triangles(points, values, gradients, triangles, SCHEME).size == 0


def test_a_folding_cell_stiffens_its_neighbourhood_and_again_more():
    """The triangles whose cell lies within one cell of a folded triangle's weigh STIFFENING
    times; a cell beside it folding again rises one level above its neighbourhood's."""
    points, triangles = _lattice(8, spacing=2.0)
    cells = CellStiffness(points, triangles, 2.0)
    assert (cells.multipliers() == 1.0).all()
    cell = (points[triangles].min(axis=1) / 2.0).round().astype(int)       # the cell's lowest corner
    first = int(np.flatnonzero((cell == [3, 3]).all(axis=1))[0])
    cells.fold(np.array([first]))
    near = (np.abs(cell - [3, 3]) <= 1).all(axis=1)
    np.testing.assert_array_equal(cells.multipliers(), np.where(near, STIFFENING, 1.0))
    second = int(np.flatnonzero((cell == [4, 3]).all(axis=1))[0])
    cells.fold(np.array([second]))
    near_second = (np.abs(cell - [4, 3]) <= 1).all(axis=1)
    want = np.where(near_second, STIFFENING ** 2, np.where(near, STIFFENING, 1.0))
    np.testing.assert_array_equal(cells.multipliers(), want)


@pytest.mark.parametrize("seed", [0, 1])
def test_stiffen_adds_each_triangles_extra_energy(seed):
    """LatticeSystem.stiffen adds s × extra[t] × triangle t's energy block at its unknowns:
    the stencil after it is the brute-force sum with those blocks added one by one."""
    problem, lattice = lattice_problem(10, 9, seed)
    system = built(problem, lattice)
    s, mu = 0.37, 0.0
    rng = np.random.default_rng(seed)
    count = system.triangles.shape[0]
    extra = np.where(rng.random(count) < 0.2, rng.choice([3.0, 15.0], count), 0.0)
    with system.data_term_ahead(problem.w, mu) as data_term:
        term = data_term()
        S, _ = system.with_strength(s, term)
    system.stiffen(S, s, term, extra)
    want = brute_force(system, s, problem.w, mu)
    T = system.triangles
    for t in np.flatnonzero(extra):
        v = T[t]
        u = [3 * v[0], 3 * v[1], 3 * v[2], 3 * v[0] + 1, 3 * v[0] + 2, 3 * v[1] + 1, 3 * v[1] + 2,
             3 * v[2] + 1, 3 * v[2] + 2]
        want[np.ix_(u, u)] += s * extra[t] * system.elements[system.shape_of[t]]
    got = S.csr().toarray()
    assert np.abs(got - want).max() <= 1e-13 * np.abs(want).max()


def test_a_triangle_whose_gradients_keep_within_the_spread_folds_no_face():
    """The candidates' premise: 400 triangles of steep random slopes (σ 2 a component) whose
    corner gradients leave that slope by SPREAD at most fold no face at FOLD_LEVEL (checked
    on the whole refinement). Folds start near 1.5 (2 and 5 of 200 such triangles at 1.5 and
    2): a SPREAD set that high would fail here."""
    from c1mesh.stages.folds import SPREAD
    rng = np.random.default_rng(0)
    points, triangles = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), np.array([[0, 1, 2]])
    for _ in range(400):
        slope = rng.normal(0.0, 2.0, 2)
        values = points @ slope + rng.normal()
        spread = rng.normal(size=(3, 2))
        spread *= SPREAD / np.linalg.norm(spread, axis=1).max()
        assert _brute_folded(points, values, slope + spread, triangles, FOLD_LEVEL).size == 0


@pytest.mark.parametrize("threads", [1, 2])
def test_the_candidates_kernel_is_the_linear_slopes_spread(monkeypatch, threads):
    """fold_candidates' kernel against numpy written here: each triangle's linear slope by
    its barycentric gradients (Σ z_k ∇λ_k), then the largest corner distance from it, on
    random triangles over random vertices (blocks of 64, one and two threads); a
    zero-area triangle is a candidate."""
    from c1mesh.core.threads import limit
    from c1mesh.engine import rsd
    from c1mesh.stages import folds
    monkeypatch.setattr(folds, "CANDIDATE_BLOCK", 64)
    rng = np.random.default_rng(3)
    points = rng.uniform(0.0, 10.0, (300, 2))
    values, gradients = rng.normal(0.0, 2.0, 300), rng.normal(0.0, 0.3, (300, 2))
    triangles = np.array([rng.choice(300, 3, replace=False) for _ in range(1000)])
    G, det = rsd.barycentric_gradients(points[triangles])
    slope = np.einsum("tk,tkd->td", values[triangles], G)
    spread = np.linalg.norm(gradients[triangles] - slope[:, None, :], axis=2).max(axis=1)
    want = np.flatnonzero(spread > folds.SPREAD)
    assert 0 < want.size < 1000
    with limit(threads):
        np.testing.assert_array_equal(fold_candidates(points, values, gradients, triangles), want)
    flat = np.vstack([triangles[:5], [[0, 0, 1]]])
    assert 5 in fold_candidates(points, values, gradients, flat)
