"""Curtains in the axis frame (c1mesh.curtains): depth jumps are holes, not curtains, over a plane too."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import c1mesh.pipeline as pipeline
from c1mesh.curtains import curtain_triangles, remove_curtains
from c1mesh.pipeline import FitOptions, fit
from c1mesh.quality import folded_faces
from c1mesh.triangulation import delaunay, trim

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"


def _grid(n: int) -> np.ndarray:
    u = np.linspace(0.0, 1.0, n)
    return np.stack(np.meshgrid(u, u), axis=-1).reshape(-1, 2)


def test_a_step_between_two_layers_is_cut_and_nothing_else():
    """Two flat layers (heights 0 and 1, exact normals) side by side: exactly the triangles
    with corners on both layers hang across the step, and only they are removed."""
    xy = _grid(11)
    z = np.where(xy[:, 0] > 0.5, 1.0, 0.0)
    gradients = np.zeros_like(xy)
    tri, report = trim(xy, delaunay(xy))
    kept, report = remove_curtains(xy, z, gradients, tri, report)
    layer = z[tri]
    across = layer.min(axis=1) != layer.max(axis=1)
    assert across.any()
    assert {tuple(sorted(t)) for t in kept} == {tuple(sorted(t)) for t in tri[~across]}
    assert report.removed["shadow_edge"] + report.removed["grazing"] + report.removed["facing_away"] \
        == int(across.sum())
    assert report.triangles_after == kept.shape[0]


@pytest.mark.parametrize("slope_deg, removed", [(75.0, False), (85.0, True)])
def test_a_plane_steeper_than_the_grazing_angle_is_seen_edge_on(slope_deg, removed):
    """An exact plane whose normal is slope_deg from the axis: kept below the grazing angle
    (80°), a curtain beyond it (its edges along the fall line then also run within the
    shadow angle, 10°, of the axis)."""
    xy = _grid(6) * [0.1, 1.0]
    slope = np.tan(np.radians(slope_deg))
    z = slope * xy[:, 0]
    gradients = np.tile([slope, 0.0], (xy.shape[0], 1))
    tri = delaunay(xy)
    masks = curtain_triangles(xy, z, gradients, tri)
    cut = masks["shadow_edge"] | masks["grazing"] | masks["facing_away"]
    assert cut.all() if removed else not cut.any()


def test_facing_away_is_the_linear_triangle_folded_against_its_data_normals():
    """Random triangles and corner normals: the facing_away rule agrees with the project's fold
    measure (quality.folded_faces) applied to the flat triangle with the data normals."""
    rng = np.random.default_rng(3)
    count = 400
    xy = rng.random((3 * count, 2))
    z = rng.normal(scale=0.2, size=3 * count)
    gradients = rng.normal(scale=1.5, size=(3 * count, 2))
    tri = np.arange(3 * count).reshape(count, 3)
    p = xy[tri]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    ccw = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0
    tri[~ccw] = tri[~ccw][:, ::-1]
    masks = curtain_triangles(xy, z, gradients, tri, shadow_angle=0.0, grazing_angle=90.0)
    vertices = np.column_stack([xy, z])
    normals = np.column_stack([-gradients, np.ones(3 * count)])
    folded = np.array([folded_faces(vertices, t[None], normals) == 1 for t in tri])
    assert masks["facing_away"].any() and not masks["facing_away"].all()
    np.testing.assert_array_equal(masks["facing_away"], folded)


def test_exact_smooth_samples_lose_no_triangle_as_a_curtain():
    """hill.ply and the tilted wave: exact normals of smooth height fields."""
    for name in ("hill.ply", "wave_tilted_offset.xyz"):
        removed = fit(SAMPLES / name, None, FitOptions(level=1)).report["triangles"]["removed"]
        assert removed["shadow_edge"] == removed["grazing"] == removed["facing_away"] == 0


def _bun0_folds() -> tuple[int, int]:
    mesh = fit(SAMPLES / "pcl_bun0.pcd", None, FitOptions()).mesh
    return folded_faces(mesh.vertices, mesh.faces, mesh.vertex_normals), len(mesh.faces)


def test_range_scan_folds_come_from_curtains(monkeypatch):
    """pcl_bun0 at default options: removing the curtains at its silhouette and across its
    self-occlusions takes away most folded faces (the rest: docs/overshoot.md)."""
    removed, _ = _bun0_folds()
    monkeypatch.setattr(pipeline, "remove_curtains", lambda xy, z, g, tri, report: (tri, report))
    kept, _ = _bun0_folds()
    assert removed < kept / 4


@pytest.mark.xfail(strict=True, reason="issue 10 target not met on pcl_bun0: 6 of 10,128 faces "
                   "(0.059%) fold at default options, in two triangles whose short edges carry "
                   "a height step of the order of the scan's noise (docs/overshoot.md)")
def test_range_scan_folds_at_most_one_face_in_ten_thousand():
    folded, faces = _bun0_folds()
    assert folded <= 1e-4 * faces
