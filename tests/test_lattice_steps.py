"""The lattice route at steep steps (issue 38): the search's least strength on the lattice
(stages.lattice_mesh.least_strength) keeps the fit from folding its faces beside banks and
ditches narrower than a cell, and the smoothing length it is built on is the fit's own; the
fold net (stages.folds) mends what folds still, in memory and in tiles, and touches nothing
else."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

import c1mesh.pipeline.driver as driver
from c1mesh.core.cloud import PointCloud
from c1mesh.core.plan import TiledRun
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit
from c1mesh.stages.lattice_mesh import BENDING_CELLS, least_strength, lattice_mesh
from c1mesh.stages.smoothing import SmoothingControl, SmoothingData, SmoothingError, smooth_fit
from c1mesh.testing.quality import folded_faces
from c1mesh.testing.steps import SPACING, banks as _banks, lattice_folds as _lattice_folds, walls
from terrain_scenes import write_points_las


@pytest.mark.parametrize("seed", [0, 5])
def test_the_lattice_does_not_fold_beside_steep_banks(seed):
    """With the least strength the search keeps to, no face of the fit folds; these samples
    each fold one without it (the search then chooses s = 1e-6, its old limit: the
    cross-validation is nearly flat there, its score held by the points on the banks)."""
    folds, strength = _lattice_folds(_banks(seed))
    assert folds == 0
    assert strength >= 0.0049                 # the least strength here, 0.005-0.0055 (10^log10: a last bit)


def _without_the_net(monkeypatch) -> None:
    """The lattice route without stages.folds' net (SmoothingControl.fold_net off)."""
    control = driver.SmoothingControl
    monkeypatch.setattr(driver, "SmoothingControl", lambda *a, **k: control(*a, **{**k, "fold_net": False}))


@pytest.mark.parametrize("seed", [0, 5])
def test_without_the_least_strength_the_same_banks_fold(monkeypatch, seed):
    """The failure the least strength mends, on the same samples: searched down to 1e-6 the
    lattice fit folds faces beside the banks (so the test above can fail; without the
    fold net, which would mend these two too)."""
    monkeypatch.setattr(driver, "support_least_strength", lambda *args: 0.0)
    _without_the_net(monkeypatch)
    folds, strength = _lattice_folds(_banks(seed))
    assert folds >= 1 and strength == pytest.approx(1e-6)


def test_the_least_strength_is_the_smoothing_length_of_a_quarter_cell():
    """least_strength's s is the one whose smoothing length ℓ = (s h² a²)^¼ is BENDING_CELLS
    lattice spacings, for any point spacing h and area per point a², to 2 digits."""
    for D, h, area in ((1.3, 0.9, 1.69), (4.87, 2.0, 25.0), (0.65, 0.61, 1.69)):
        s = least_strength(D, h, area)
        assert (s * h * h * area) ** 0.25 == pytest.approx(BENDING_CELLS * D, rel=0.02)
    assert least_strength(1.0, 0.0, 1.0) == 0.0 and least_strength(1.0, 1.0, 0.0) == 0.0


def _kept_height(h: float, area: float, length: float, seed: int = 3) -> float:
    """The height a sine wave 2π `length` long (unit amplitude, along x) keeps in the lattice
    fit (D = 0.5) at least_strength's s for smoothing length `length`, strength unit h, to
    random points covering `area` each over 40 × 40; measured in the middle 20 × 20."""
    rng = np.random.default_rng(seed)
    side, D = 40.0, 0.5
    xy = rng.uniform(0.0, side, (int(side * side / area), 2))
    wave = 2 * np.pi * length
    s = least_strength(length / BENDING_CELLS, h, area)
    mesh = lattice_mesh(xy, D, 2 * D)
    fitted = smooth_fit(mesh.points, mesh.triangles, SmoothingData(np.sin(2 * np.pi * xy[:, 0] / wave), spacing=h,
                                                                   xy=xy), SmoothingControl(strength=s))
    spline = RSDInterpolator(mesh.points, fitted.values, fitted.gradients, mesh.triangles)
    probe = rng.uniform(10.0, 30.0, (4000, 2))
    basis = np.column_stack([np.sin(2 * np.pi * probe[:, 0] / wave), np.cos(2 * np.pi * probe[:, 0] / wave)])
    return float(np.hypot(*np.linalg.lstsq(basis, spline(probe), rcond=None)[0]))


def test_the_smoothing_length_holds_at_any_strength_unit_and_density():
    """The rule's premise against an analytic truth: at least_strength's s the fit smooths a
    sine wave alike whatever the strength's length unit h and the points' density 1/a², as
    its data weigh 1/a² an area (h = 0.37 a and h = a here; taking ℓ⁴ = s h⁴, as if a = h
    always, the first would keep 0.04 of the wave where the second keeps 0.2). A wave 2π ℓ long keeps about 1/5 of its
    height, not the 1/2 of 1 / (1 + (2π ℓ / L)⁴): the RSD spline of a smooth function bends
    more than the function (4.6 times the energy of x²/2 on this lattice, with its exact
    values and gradients at the nodes), so its energy weighs about 4 times the integral's."""
    sparse = _kept_height(h=0.37, area=1.0, length=1.0)
    dense = _kept_height(h=0.5, area=0.25, length=1.0)
    assert sparse == pytest.approx(dense, abs=0.03)
    assert sparse == pytest.approx(0.2, abs=0.04)


def test_the_search_goes_no_lower_than_the_least_strength():
    """Exact data want as little smoothing as the search may give: with a least strength
    the search tries nothing below it, stops there and says it reached its limit; a bad
    least strength is refused before any work."""
    rng = np.random.default_rng(1)
    xy = rng.uniform(0.0, 20.0, (600, 2))
    z = np.sin(xy[:, 0] / 3.0) + 0.1 * xy[:, 1]
    mesh = lattice_mesh(xy, 1.0, 1.0)
    data = SmoothingData(z, spacing=0.8, xy=xy)
    fitted = smooth_fit(mesh.points, mesh.triangles, data, SmoothingControl(strength="auto", least_strength=0.03))
    assert min(s for s, _ in fitted.cv_curve) == pytest.approx(0.03)
    assert fitted.strength == pytest.approx(0.03) and fitted.search_limit_reached is True
    free = smooth_fit(mesh.points, mesh.triangles, data, SmoothingControl(strength="auto"))
    assert free.strength < 0.003                          # below it when free to go there
    for bad in (-1.0, float("nan")):
        with pytest.raises(SmoothingError, match="least strength"):
            smooth_fit(mesh.points, mesh.triangles, data, SmoothingControl(strength="auto", least_strength=bad))


@pytest.mark.parametrize("seed", [0, 2])
def test_the_fold_net_mends_the_walls(monkeypatch, seed):
    """Lines of points 0-6 m off the ground (walls left in the ground class) fold faces at the
    strength the search chooses (9 and 11 here); the net stiffens the cells around the
    folds, solves again at the same s, and the fit folds none, saying so in its report."""
    points = walls(seed)
    result = fit(PointCloud(points=points), None, FitOptions(smooth="auto", spacing=SPACING))
    mesh, smoothing = result.mesh, result.report["smoothing"]
    assert folded_faces(mesh.vertices, mesh.faces, mesh.vertex_normals) == 0
    assert smoothing["fold_rounds"] >= 1 and smoothing["stiffened_cells"] >= 1
    _without_the_net(monkeypatch)
    folds, strength = _lattice_folds(points)
    assert folds >= 1 and strength == smoothing["strength"]


def test_a_fit_that_folds_nothing_keeps_its_bits(monkeypatch):
    """The net only acts where a face folds: a bank sample that folds none gives the same
    vertices, to the bit, with the net and without it."""
    options = FitOptions(smooth="auto", spacing=SPACING)
    result = fit(PointCloud(points=_banks(5)), None, options)
    assert result.report["smoothing"]["fold_rounds"] == 0 and result.report["smoothing"]["stiffened_cells"] == 0
    _without_the_net(monkeypatch)
    plain = fit(PointCloud(points=_banks(5)), None, options)
    np.testing.assert_array_equal(result.mesh.vertices, plain.mesh.vertices)


def test_the_fold_net_in_tiles_is_the_whole_fits(tmp_path):
    """Beyond --memory each tile runs the net on its halo (smooth_tile is the in-memory fit's
    stage): the walls sample as class-2 LiDAR folds no face in tiles either, the tiles'
    report sums the same rounds and cells, and the heights are the whole fit's."""
    source = tmp_path / "walls.las"
    write_points_las(source, walls(3) + [0.0, 0.0, 100.0], z_scale=0.0001)
    options = FitOptions(classes=[2], smooth="auto", spacing=SPACING)
    whole = fit(source, tmp_path / "whole.ply", options)
    tiled = fit(source, tmp_path / "tiled.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=200))
    assert tiled.report["tiles"] > 1
    for result in (whole, tiled):
        assert result.report["smoothing"]["fold_rounds"] >= 1
    assert tiled.report["smoothing"]["stiffened_cells"] == whole.report["smoothing"]["stiffened_cells"] >= 1
    meshes = [trimesh.load(tmp_path / f"{name}.ply", process=False) for name in ("whole", "tiled")]
    for mesh in meshes:
        assert folded_faces(np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.vertex_normals)) == 0
    a, b = (np.asarray(mesh.vertices) for mesh in meshes)
    np.testing.assert_array_equal(np.sort(a[:, :2], axis=0), np.sort(b[:, :2], axis=0))
    assert np.abs(np.sort(a[:, 2]) - np.sort(b[:, 2])).max() < 0.01 * whole.report["smoothing"]["residual_rms"]
