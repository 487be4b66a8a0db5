"""Curtains in the axis frame (c1mesh.stages.curtains): depth jumps are holes, not curtains, over a
plane too; slivers narrower than the height noise go with them."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import c1mesh.pipeline.driver as pipeline
from c1mesh.stages.curtains import REASONS, curtain_triangles, noise_floor, remove_curtains
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit
from c1mesh.testing.quality import folded_faces
from c1mesh.engine.triangulation import delaunay
from c1mesh.stages.trim import retrim, trim, trim_mesh

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
    assert sum(report.removed[reason] for reason in REASONS) == int(across.sum())
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
    cut = np.logical_or.reduce([masks[reason] for reason in REASONS])
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


def test_noise_floor_is_the_height_noise():
    """Heights of a plane with Gaussian noise σ and the plane's exact gradients: every edge's
    residual is the difference of two independent N(0, σ²) errors, whose median absolute
    value is 0.6745·√2·σ; exact quadratics have none."""
    xy = np.random.default_rng(5).random((4000, 2))
    tri = delaunay(xy)
    sigma = 0.01
    plane = 0.3 * xy[:, 0] - 0.2 * xy[:, 1]
    noisy = plane + np.random.default_rng(6).normal(scale=sigma, size=len(plane))
    gradients = np.tile([0.3, -0.2], (len(plane), 1))
    assert noise_floor(xy, noisy, gradients, tri) == pytest.approx(0.6745 * np.sqrt(2) * sigma, rel=0.05)
    quadratic = xy[:, 0] ** 2 + xy[:, 0] * xy[:, 1]
    exact = np.column_stack([2 * xy[:, 0] + xy[:, 1], xy[:, 0]])
    assert noise_floor(xy, quadratic, exact, tri) < 1e-14


def test_slivers_narrower_than_the_noise_are_dropped_and_only_they():
    """A noisy plane on an 11 x 11 grid (spacing 0.1, every quad split the same way) whose
    point (0.5, 0.5) is moved to 0.005 above the row below: the slivers it makes are
    narrower than the noise (σ = 0.01), every other triangle is 0.07 wide. Widths here from
    Heron's formula (twice the area over the longest edge)."""
    xy = _grid(11)
    moved = 5 * 11 + 5
    xy[moved] = [0.5, 0.405]
    index = np.arange(121).reshape(11, 11)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()
    tri = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    z = np.random.default_rng(7).normal(scale=0.01, size=len(xy))
    gradients = np.zeros_like(xy)
    sides = np.stack([np.linalg.norm(xy[tri[:, k]] - xy[tri[:, (k + 1) % 3]], axis=1) for k in range(3)])
    half = sides.sum(axis=0) / 2
    area = np.sqrt(np.maximum(half * np.prod(half - sides, axis=0), 0.0))
    width = 2 * area / sides.max(axis=0)
    masks = curtain_triangles(xy, z, gradients, tri)
    expected = (width < noise_floor(xy, z, gradients, tri)) \
        & ~(masks["shadow_edge"] | masks["grazing"] | masks["facing_away"])
    assert expected.any() and (tri[expected] == moved).any(axis=1).all()
    np.testing.assert_array_equal(masks["thinner_than_noise"], expected)


def test_retrim_around_the_holes_is_a_whole_trim_again():
    """remove_curtains re-trims only around its holes (trim.retrim): on random holes in
    random trimmed triangulations (some with near-collinear runs, which make slivers and
    bowties), it keeps exactly the triangles, in the same order, that trim itself keeps
    when run again on what the holes left, and counts the same slivers and bowties."""
    rng = np.random.default_rng(1)
    changed = 0
    for trial in range(120):
        xy = rng.random((300, 2))
        if trial % 3 == 0:
            xy[:40, 1] = 0.5 + 1e-4 * rng.random(40)
        mesh, _ = trim_mesh(xy, delaunay(xy))
        cut = rng.random(len(mesh.triangles)) < (0.005, 0.02, 0.1)[trial % 3]
        cut[trial % len(mesh.triangles)] = True
        kept = mesh.triangles[~cut]
        expected, report = trim(xy, kept, max_edge=None)
        after, counts = retrim(mesh, np.flatnonzero(mesh.alive)[cut])
        assert np.array_equal(after.triangles, expected)
        assert counts == report.removed
        changed += expected.shape[0] < kept.shape[0]
    assert 0 < changed < 120


def test_a_trimmed_mesh_gives_what_the_triangle_array_gives():
    """remove_curtains of trim_mesh's TrimmedMesh: the triangles and report of the array
    path, and a noise floor from the mesh's own edges equal to the one of a fresh sort."""
    rng = np.random.default_rng(4)
    xy = rng.random((3000, 2))
    xy[:300, 1] = 0.5 + 1e-4 * rng.random(300)        # slivers for the re-trim to peel
    z = np.sin(3 * xy[:, 0]) + 0.02 * rng.standard_normal(len(xy))
    gradients = np.stack([3 * np.cos(3 * xy[:, 0]), np.zeros(len(xy))], axis=1)
    tri, report = trim(xy, delaunay(xy))
    mesh, mesh_report = trim_mesh(xy, delaunay(xy))
    assert np.array_equal(mesh.triangles, tri) and mesh_report == report
    from c1mesh.stages.curtains import _curtain_masks, _live_noise_floor, point_rows
    rows = point_rows(xy, z, gradients)
    floor = _live_noise_floor(xy, z, gradients, mesh)
    assert floor == noise_floor(xy, z, gradients, tri)
    over_kept = _curtain_masks(rows, tri, 60.0, 60.0, floor, True)   # wide angles: rules fire
    over_source = _curtain_masks(rows, mesh.source, 60.0, 60.0, floor, True, alive=mesh.alive)
    for reason, mask in over_kept.items():
        assert np.array_equal(over_source[reason][mesh.alive], mask) and not over_source[reason][~mesh.alive].any()
    assert sum(int(mask.sum()) for mask in over_kept.values()) > 100
    kept, report = remove_curtains(xy, z, gradients, tri, report)
    after, mesh_report = remove_curtains(xy, z, gradients, mesh, mesh_report)
    assert report.removed["thinner_than_noise"] > 0
    assert np.array_equal(after.triangles, kept) and mesh_report == report


def test_exact_smooth_samples_lose_no_triangle_as_a_curtain():
    """hill.ply and the tilted wave: exact normals of smooth height fields."""
    for name in ("hill.ply", "wave_tilted_offset.xyz"):
        removed = fit(SAMPLES / name, None, FitOptions(level=1)).report["triangles"]["removed"]
        assert [removed[reason] for reason in REASONS] == [0] * len(REASONS)


def _bun0_folds() -> tuple[int, int]:
    mesh = fit(SAMPLES / "pcl_bun0.pcd", None, FitOptions()).mesh
    return folded_faces(mesh.vertices, mesh.faces, mesh.vertex_normals), len(mesh.faces)


def test_range_scan_folds_come_from_curtains(monkeypatch):
    """pcl_bun0 at default options: removing the curtains at its silhouette and across its
    self-occlusions (and slivers narrower than its noise) takes away the folded faces."""
    removed, _ = _bun0_folds()
    monkeypatch.setattr(pipeline, "remove_curtains", lambda xy, z, g, tri, report, *view: (tri, report))
    kept, _ = _bun0_folds()
    assert removed < kept / 4


def test_range_scan_folds_at_most_one_face_in_ten_thousand():
    """Issue 10's target for the range scans in data_samples/, on pcl_bun0 at default options
    (Open3D's room fragment is refused there as no height field)."""
    folded, faces = _bun0_folds()
    assert folded <= 1e-4 * faces


def _curtain_reasons_one_by_one(xy, z, gradients, triangles, floor):
    """The REASONS of each triangle from the module docstring's angles, one triangle at a
    time with vectors, norms and arccos (the reference for curtain_triangles' squared,
    component-wise comparisons)."""
    from c1mesh.stages.curtains import GRAZING_ANGLE, SHADOW_ANGLE

    reasons = []
    for tri in triangles:
        p = np.column_stack([xy[tri], z[tri]])
        edges = [p[(k + 1) % 3] - p[k] for k in range(3)]
        from_axis = [np.degrees(np.arccos(abs(e[2]) / np.linalg.norm(e))) for e in edges]
        normal = np.cross(p[1] - p[0], p[2] - p[0])
        normal *= np.sign(normal[2])
        tilt = np.degrees(np.arccos(normal[2] / np.linalg.norm(normal)))
        data = [np.array([-gx, -gy, 1.0]) for gx, gy in gradients[tri]]
        width = normal[2] / max(np.linalg.norm(e[:2]) for e in edges)      # in the plane: 2 area / longest
        if min(from_axis) < SHADOW_ANGLE:
            reasons.append("shadow_edge")
        elif tilt > GRAZING_ANGLE:
            reasons.append("grazing")
        elif any(normal @ d < 0 for d in data):
            reasons.append("facing_away")
        elif width < floor:
            reasons.append("thinner_than_noise")
        else:
            reasons.append(None)
    return np.array(reasons, dtype=object)


def test_curtain_masks_match_the_angles_triangle_by_triangle_on_strided_inputs():
    """Rough random heights over random points (every reason occurs), the inputs passed as
    strided views and int32 triangles: each triangle's mask is its reason by the angles."""
    rng = np.random.default_rng(11)
    table = rng.random((3000, 5))
    xy, z = table[:, :2], 0.08 * table[:, 2] + 0.02 * np.sin(9 * table[:, 0])   # (n, 2) view, stride 5
    gradients = np.asfortranarray(rng.normal(scale=2.0, size=(3000, 2)))
    triangles = delaunay(np.ascontiguousarray(xy)).astype(np.int32)[:, ::-1][:, [2, 1, 0]]  # strided view
    floor = 0.004
    masks = curtain_triangles(xy, z, gradients, triangles, floor=floor)
    truth = _curtain_reasons_one_by_one(xy, z, gradients, triangles, floor)
    for reason in REASONS:
        assert masks[reason].sum() > 0
        np.testing.assert_array_equal(masks[reason], truth == reason, err_msg=reason)


def test_the_noise_floor_is_the_median_residual_of_a_loop_over_the_edges_at_any_thread_count():
    """noise_floor against the trapezoid residual written out edge by edge in Python floats
    (the same operations in the same order: equal to the bit), over a mesh large enough for
    several of the kernel's blocks; the masks too are the same at 1 and 3 threads."""
    from c1mesh.core.threads import limit

    rng = np.random.default_rng(12)
    xy = rng.random((30000, 2))
    z = np.sin(5 * xy[:, 0]) * xy[:, 1] + rng.normal(scale=0.01, size=len(xy))
    g = rng.normal(size=(len(xy), 2))
    triangles = delaunay(xy)
    edges = sorted({tuple(sorted((int(t[i]), int(t[(i + 1) % 3])))) for t in triangles for i in range(3)})
    loop = []
    for a, b in edges:
        dx, dy = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]
        loop.append(abs((z[b] - z[a]) - 0.5 * ((g[a, 0] * dx + g[a, 1] * dy) + (g[b, 0] * dx + g[b, 1] * dy))))
    masks = {}
    for threads in (1, 3):
        with limit(threads):
            assert noise_floor(xy, z, g, triangles) == float(np.median(loop))
            masks[threads] = curtain_triangles(xy, z, g, triangles, floor=0.01)
    for reason in REASONS:
        np.testing.assert_array_equal(masks[1][reason], masks[3][reason])
