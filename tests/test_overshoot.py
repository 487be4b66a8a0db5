"""Issue 10: surfaces people trust on real scans (overshoot, pits, folds, holdout, defaults).

Peers are computed here on the same data: matplotlib's reduced HCT (CubicTriInterpolator,
kind='user') given the same normal-derived gradients on the same triangles, and scipy's
linear TIN. Exact-data checks use analytic functions.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib.tri as mtri
import numpy as np
import pytest
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import Delaunay

from c1mesh.engine import rsd
from c1mesh.core.cloud import PointCloud
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.stages.limiter import (RATIO_LIMIT, control_overshoot, edge_directions, limit_gradients,
                             reconcile_gradients)
from c1mesh.pipeline.driver import FitOptions, build_surface, load_cloud
from c1mesh.pipeline.run import fit
from c1mesh.testing.quality import (folded_faces, interior_lattice, lattice_points, overshoot,
                            reduced_hct_folded_faces)
from c1mesh.engine.topology import edge_table

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
GROUND = {"4_6_crop": (SAMPLES / "4_6_crop.las", {}),
          "autzen": (SAMPLES / "autzen_trim.laz", {}),
          "autzen, --max-edge none": (SAMPLES / "autzen_trim.laz", {"max_edge": None})}


def height_data(path, **options):
    """(xy, z, gradients, triangles) as the fit pipeline builds them, before the limiter
    (LiDAR ground unless options say otherwise)."""
    opts = FitOptions(smooth="off", **{"classes": (2,), "axis": "z", **options, "overshoot": "off"})
    model = build_surface(load_cloud(path, opts), opts)
    interp = model.interp
    return interp.points, interp.values, interp.gradients, interp.triangles


def rhct_surface(xy, z, g, tri, lam):
    """matplotlib reduced HCT with gradients g, sampled inside every triangle (T, P)."""
    t = mtri.Triangulation(xy[:, 0], xy[:, 1], triangles=tri)
    interp = mtri.CubicTriInterpolator(t, z, kind="user", dz=(g[:, 0], g[:, 1]))
    pts = lattice_points(xy, tri, lam).reshape(-1, 2)
    return np.ma.filled(interp(pts[:, 0], pts[:, 1]), np.nan).reshape(tri.shape[0], -1)


def c1mesh_surface(xy, z, g, tri, lam, mode="limit"):
    values, gradients, directions, _ = control_overshoot(xy, z, g, tri, mode)
    interp = RSDInterpolator(xy, values, gradients, triangles=tri, directions=directions)
    return interp.coefficients @ rsd.basis(interp.scheme, lam), interp


@pytest.fixture(scope="module", params=list(GROUND))
def ground(request):
    path, options = GROUND[request.param]
    return request.param, height_data(path, **options)


@pytest.mark.slow
def test_lidar_ground_overshoot_count_is_no_worse_than_reduced_hct(ground):
    """Triangles leaving their corner range by > 1/4 of the longest edge: c1mesh (limited)
    against matplotlib's reduced HCT given the raw gradients on the same triangles."""
    name, (xy, z, g, tri) = ground
    lam = interior_lattice(8)
    ours = overshoot(c1mesh_surface(xy, z, g, tri, lam)[0], z, xy, tri)
    peer = overshoot(rhct_surface(xy, z, g, tri, lam), z, xy, tri)
    assert ours["count"] <= peer["count"], name


@pytest.mark.slow
@pytest.mark.parametrize("options", [{}, {"max_edge": None}])
def test_autzen_ground_largest_overshoot_is_no_worse_than_reduced_hct(options):
    """Largest overshoot on Autzen ground (the river bank): at most the reduced HCT's, and
    without the limiter it is not (so the test can fail)."""
    xy, z, g, tri = height_data(SAMPLES / "autzen_trim.laz", **options)
    lam = interior_lattice(8)
    peer = overshoot(rhct_surface(xy, z, g, tri, lam), z, xy, tri)["max"]
    assert overshoot(c1mesh_surface(xy, z, g, tri, lam)[0], z, xy, tri)["max"] <= peer
    if options:
        assert overshoot(c1mesh_surface(xy, z, g, tri, lam, "off")[0], z, xy, tri)["max"] > peer


@pytest.mark.slow
def test_4_6_crop_ground_largest_overshoot_is_no_worse_than_reduced_hct():
    """With gradients fitted to the heights (the default for estimated normals) c1mesh's
    largest overshoot is below rHCT's given the same gradients; with the PCA normals'
    gradients it was not (0.155 against 0.149 ft), so the test can fail."""
    lam = interior_lattice(8)
    for gradients, ours_wins in (("auto", True), ("normals", False)):
        xy, z, g, tri = height_data(SAMPLES / "4_6_crop.las", gradients=gradients)
        peer = overshoot(rhct_surface(xy, z, g, tri, lam), z, xy, tri)["max"]
        ours = overshoot(c1mesh_surface(xy, z, g, tri, lam)[0], z, xy, tri)["max"]
        assert (ours <= peer) == ours_wins, (gradients, ours, peer)


def test_folded_faces_compares_with_every_corner_normal():
    """A flat face with one corner normal tilted 100° away is folded; the mean of the three
    corners still agrees with the face, so a mean-based measure would miss it."""
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    faces = np.array([[0, 1, 2]])
    up = [0.0, 0, 1]
    tilted = [np.sin(np.radians(100)), 0, np.cos(np.radians(100))]
    assert folded_faces(vertices, faces, np.array([up, up, up])) == 0
    assert folded_faces(vertices, faces, np.array([up, up, tilted])) == 1
    assert folded_faces(vertices, faces, -np.array([up, up, up])) == 1


@pytest.mark.slow
def test_autzen_ground_has_no_pits_below_the_lowest_input_point():
    """--max-edge none used to give closed pits 3 ft below the lowest ground point."""
    result = fit(SAMPLES / "autzen_trim.laz", None, FitOptions(smooth="off", classes=(2,), max_edge=None))
    cloud = load_cloud(SAMPLES / "autzen_trim.laz", FitOptions(smooth="off", classes=(2,)))
    assert result.mesh.vertices[:, 2].min() >= cloud.points[:, 2].min() - 0.1


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    "4_6_crop.las",
    pytest.param("autzen_trim.laz", marks=pytest.mark.xfail(
        strict=True, reason="issue 10 target not met: 9 faces of 808k in creases of 2 needles whose "
                            "residuals exceed the noise (35 and 14 floors) and that level 4 "
                            "undersamples (level 16 has none); needs finer refinement there "
                            "(docs/overshoot.md, Sliver creases on Autzen)"))])
def test_lidar_ground_has_no_folded_faces_at_default_options(name):
    """Folded: geometric normal more than 90° from ANY corner normal (quality.folded_faces)."""
    result = fit(SAMPLES / name, None, FitOptions(smooth="off", classes=(2,)))
    mesh = result.mesh
    assert folded_faces(mesh.vertices, mesh.faces, mesh.vertex_normals) == 0


def holdout_rms(path, seeds=(0, 1, 2)):
    """Mean held-out RMS over seeds of c1mesh (default options) and scipy's linear TIN of
    the same points and their input heights: 10% of the ground points held out, the
    surface built from the rest by the pipeline's own stages (build_surface), errors at
    held-out points inside its triangles."""
    cloud = load_cloud(path, FitOptions(smooth="off", classes=(2,)))
    ours, linear = [], []
    for seed in seeds:
        test = np.random.default_rng(seed).random(len(cloud)) < 0.1
        model = build_surface(PointCloud(points=cloud.points[~test]), FitOptions(smooth="off", axis="z"))
        interp = model.interp
        local = model.frame.to_local(cloud.points[test])
        inside = interp.find_simplex(local[:, :2]) >= 0
        q, truth = local[inside, :2], local[inside, 2]
        ours.append(np.sqrt(np.mean((interp(q) - truth) ** 2)))
        tin = LinearNDInterpolator(interp.points, model.hf.z[model.used])(q)   # the data's heights
        linear.append(np.sqrt(np.mean((tin - truth) ** 2)))
    return np.mean(ours), np.mean(linear)


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    "autzen_trim.laz",
    pytest.param("4_6_crop.las", marks=pytest.mark.xfail(
        strict=True, reason="issue 10 target not met: 1.017x the linear TIN (1.011x before the heights "
                            "of near pairs were reconciled); the sextic's Psi1 = Phi carries each "
                            "noisy vertex gradient about twice as far into a triangle as cubic "
                            "Hermite (quintic 1.001x, rHCT 0.989x with the same gradients)"))])
def test_lidar_ground_holdout_rms_is_no_worse_than_a_linear_tin(name):
    """10% of the ground points held out (3 seeds); the fit sees the rest only."""
    ours, linear = holdout_rms(SAMPLES / name)
    assert ours <= linear


@pytest.mark.slow
@pytest.mark.parametrize("name, options", [("autzen_trim.laz", {"classes": (2,), "axis": "z"})])
def test_folded_faces_are_fewer_than_reduced_hct_with_the_same_gradients(name, options):
    """c1mesh's default output against matplotlib's reduced HCT given the raw gradients on
    the same triangles, refined to the same 16 faces per triangle. (pcl_bun0 was a case too:
    without its curtains (c1mesh.stages.curtains) neither folds, and test_curtains asks c1mesh for
    at most 0.01%.)"""
    xy, z, g, tri = height_data(SAMPLES / name, **options)
    mesh = fit(SAMPLES / name, None, FitOptions(smooth="off", **options)).mesh
    ours = folded_faces(mesh.vertices, mesh.faces, mesh.vertex_normals)
    peer, faces = reduced_hct_folded_faces(xy, z, g, tri)
    assert len(mesh.faces) == faces
    assert ours < peer


def test_range_scan_folds_drop_with_the_limiter():
    """pcl_bun0: folded faces (black specks) with the limiter are fewer than without."""
    counts = {}
    for mode in ("off", "limit"):
        mesh = fit(SAMPLES / "pcl_bun0.pcd", None, FitOptions(smooth="off", overshoot=mode)).mesh
        counts[mode] = folded_faces(mesh.vertices, mesh.faces, mesh.vertex_normals)
    assert counts["limit"] < counts["off"] / 2


# ---- exact data: nothing that matters changes ----------------------------------------------
def _square(n, seed):
    """n points in the unit square with its corners and ~sqrt(n) points on each side (so no
    long hull edges; benchmarks/accuracy.py samples the same way)."""
    rng = np.random.default_rng(seed)
    k = int(np.sqrt(n))
    t = rng.random((4, k))
    sides = np.concatenate([np.c_[t[0], 0 * t[0]], np.c_[t[1], 1 + 0 * t[1]],
                            np.c_[0 * t[2], t[2]], np.c_[1 + 0 * t[3], t[3]]])
    corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1.0]])
    return np.concatenate([corners, sides, rng.random((n - 4 - 4 * k, 2))])


def test_limiter_leaves_exact_smooth_data_alone():
    """Exact values and gradients of smooth functions pass the trapezoid test everywhere."""
    pts = _square(1600, 3)
    tri = Delaunay(pts).simplices
    edges = edge_table(tri, len(pts)).edges
    x, y = pts[:, 0], pts[:, 1]
    for f, g in ((np.exp(x) * np.sin(2 * y), np.c_[np.exp(x) * np.sin(2 * y), 2 * np.exp(x) * np.cos(2 * y)]),
                 (x * x + 2 * y * y + 0.5 * x * y, np.c_[2 * x + 0.5 * y, 4 * y + 0.5 * x])):
        limited, changed = limit_gradients(pts, f, g, edges)
        assert not changed.any()
        np.testing.assert_array_equal(limited, g)
        reconciled, moved = reconcile_gradients(pts, f, g, edges)
        assert not moved.any()
        np.testing.assert_array_equal(reconciled, g)


def test_reconciled_gradient_follows_the_heights_where_the_normal_contradicts_them():
    """Heights of the plane z = x with one vertex's normal saying slope (0, 3): that vertex
    gets the least-squares gradient of its edges' secant slopes and its normal (solved
    here by numpy's lstsq on the stacked rows); its neighbours, whose heights agree with
    their gradient (1, 0), keep it."""
    pts = _square(400, 7)
    tri = Delaunay(pts).simplices
    edges = edge_table(tri, len(pts)).edges
    z = pts[:, 0].copy()
    g = np.tile([1.0, 0.0], (len(pts), 1))
    k = int(np.argmin(np.linalg.norm(pts - 0.5, axis=1)))
    g[k] = [0.0, 3.0]
    reconciled, moved = reconcile_gradients(pts, z, g, edges)
    ring = np.concatenate([edges[edges[:, 0] == k, 1], edges[edges[:, 1] == k, 0]])
    d = pts[ring] - pts[k]
    u = d / np.linalg.norm(d, axis=1)[:, None]
    rows = np.vstack([u, np.sqrt(len(ring)) * np.eye(2)])
    rhs = np.concatenate([(z[ring] - z[k]) / np.linalg.norm(d, axis=1), np.sqrt(len(ring)) * g[k]])
    expected = np.linalg.lstsq(rows, rhs, rcond=None)[0]
    assert moved[k]
    np.testing.assert_allclose(reconciled[k], expected, atol=1e-12)
    np.testing.assert_allclose(np.delete(reconciled, k, axis=0), np.delete(g, k, axis=0), atol=1e-12)


def test_limited_fit_reproduces_planes_and_keeps_c1():
    pts = _square(2000, 4)
    tri = Delaunay(pts).simplices
    z = 3 * pts[:, 0] - 2 * pts[:, 1] + 1
    g = np.tile([3.0, -2.0], (len(pts), 1))
    values, gradients, directions, report = control_overshoot(pts, z, g, tri)
    assert report.directions_changed > 0 and report.gradients_limited == 0
    np.testing.assert_array_equal(values, z)              # a plane: no residual, no move
    interp = RSDInterpolator(pts, values, gradients, triangles=tri, directions=directions)
    q = np.random.default_rng(5).random((3000, 2)) * 0.9 + 0.05
    np.testing.assert_allclose(interp(q), 3 * q[:, 0] - 2 * q[:, 1] + 1, atol=1e-12)


def test_noisy_gradients_are_limited_and_the_spline_stays_c1():
    """Gradients that contradict flat heights are scaled down; the certificate still holds."""
    pts = _square(400, 6)
    tri = Delaunay(pts).simplices
    z = np.zeros(len(pts))
    g = np.zeros((len(pts), 2))
    g[::7] = [5.0, 0.0]                                   # wild slopes on flat ground
    values, gradients, directions, report = control_overshoot(pts, z, g, tri)
    assert report.gradients_limited >= len(pts[::7]) - 4
    assert np.abs(gradients).max() < 1e-12
    interp = RSDInterpolator(pts, values, gradients, triangles=tri, directions=directions)
    cert = interp.c1_certificate()
    assert cert["gradient_jump"] < 1e-9 and cert["value_jump"] < 1e-12


def _ratios(points, tri, table, directions):
    """|G_l·u_n / G_n·u_n| for all (l, n), per triangle (T, 6)."""
    G, _ = rsd.barycentric_gradients(points[tri])
    u = directions[table.tri_edge]
    out = []
    for l, _, n in rsd.PERMS:
        out.append(np.abs(np.einsum("ij,ij->i", G[:, l], u[:, n]) / np.einsum("ij,ij->i", G[:, n], u[:, n])))
    return np.stack(out, axis=1)


def test_edge_directions_bound_the_rsd_ratios_of_obtuse_slivers():
    """Two obtuse slivers on the edge [(0,0), (1,0)]: the unit normal's foot from (3, 0.02)
    falls at s = 3 (ratio 3); through the opposite vertices the line meets the edge at its
    midpoint (ratios 1/2), and no edge keeps a ratio above RATIO_LIMIT."""
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 0.02], [-2.0, -0.02]])
    tri = np.array([[0, 1, 2], [1, 0, 3]])
    table = edge_table(tri, len(pts))
    directions, changed = edge_directions(pts, tri, table)
    normal = RSDInterpolator(pts, np.zeros(4), np.zeros((4, 2)), triangles=tri).directions
    assert _ratios(pts, tri, table, normal).max() > 2.9
    assert _ratios(pts, tri, table, directions).max() <= RATIO_LIMIT
    shared = table.tri_edge[0][np.isin(table.tri_edge[0], table.tri_edge[1])][0]
    assert changed[shared]
    u = directions[shared]
    assert abs(u[0] * 0.04 - u[1] * 5.0) < 1e-12 * np.hypot(5.0, 0.04)   # parallel to (5, 0.04)


# ---- defaults -------------------------------------------------------------------------------
def test_las_height_axis_is_z_and_the_report_says_so():
    report = fit(SAMPLES / "4_6_crop.las", None, FitOptions(smooth="off", classes=(2,))).report
    np.testing.assert_array_equal(report["frame"]["axes"], np.eye(3))
    assert "LAS" in report["frame"]["axis_choice"]
    assert report["overshoot"]["gradients_limited"] > 0
    assert report["warnings"] == []


def test_a_surface_in_many_pieces_draws_a_warning():
    report = fit(SAMPLES / "4_6_crop.las", None, FitOptions(smooth="off", classes=(2,), max_edge=2.5)).report
    assert report["pieces"]["count"] > 20
    assert any("pieces" in w for w in report["warnings"])
    assert any("--max-edge" in w for w in report["warnings"])


def test_given_noise_floors_and_edge_table_reproduce_the_measured_ones():
    """A tile of a survey is limited with the survey's noise floors (limiter.tile_limits);
    on the in-memory fit's one tile, given the floors this data set itself measures
    (independently: the medians of the trapezoid residuals of the input, and after the
    heights and gradients are reconciled), the result is the in-memory one, and so is the
    one of a prebuilt edge table; floors ten times larger tolerate more and limit fewer
    vertices."""
    from c1mesh.core.tile import Tile
    from c1mesh.stages.limiter import NoiseFloors, reconcile_heights, tile_limits, trapezoid_residuals
    xy, z, g, tri = height_data(GROUND["4_6_crop"][0])
    table = edge_table(tri, xy.shape[0])
    before = float(np.median(np.abs(trapezoid_residuals(xy, z, g, table.edges))))
    heights, _ = reconcile_heights(xy, z, g, tri, table, noise_floor=before)
    reconciled, _ = reconcile_gradients(xy, heights, g, table.edges, noise_floor=before)
    after = float(np.median(np.abs(trapezoid_residuals(xy, heights, reconciled, table.edges))))
    measured = control_overshoot(xy, z, g, tri)
    given = control_overshoot(xy, z, g, tri, table=table)
    for ours, theirs in zip(given[:3], measured[:3]):
        np.testing.assert_array_equal(ours, theirs)
    tile = tile_limits(Tile.whole(xy, z, g, tri), tri, NoiseFloors(before, after))
    corners = tile.records["index"]
    np.testing.assert_array_equal(corners[tile.triangles], tri)
    np.testing.assert_array_equal(tile.records["z"], measured[0][corners])
    np.testing.assert_array_equal(tile.gradients, measured[1][corners])
    np.testing.assert_array_equal(tile.directions, measured[2])       # every edge, in the table's order
    assert (tile.limited, tile.turned, tile.lifted) == (measured[3].gradients_limited,
                                                       measured[3].directions_changed,
                                                       measured[3].heights_reconciled)
    looser = tile_limits(Tile.whole(xy, z, g, tri), tri, NoiseFloors(10 * before, 10 * after))
    assert 0 < looser.limited < measured[3].gradients_limited
    plain = RSDInterpolator(xy, given[0], given[1], triangles=tri, directions=given[2])
    shared = RSDInterpolator(xy, given[0], given[1], triangles=tri, directions=given[2], edge_table=table)
    np.testing.assert_array_equal(shared.coefficients, plain.coefficients)
    with pytest.raises(Exception, match="edge_table has"):
        RSDInterpolator(xy, z, g, triangles=tri[:-1], edge_table=table)


def _folded_per_face(mesh):
    """(K,) bool: quality.folded_faces' test per sub-face of a RefinedMesh in the height-field
    frame (vertices (x, y, F), normals (−∇F, 1))."""
    p = np.c_[mesh.points, mesh.values][mesh.triangles]
    normals = np.c_[-mesh.gradients, np.ones(mesh.values.shape[0])][mesh.triangles]
    geometric = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return (np.einsum("fd,fkd->fk", geometric, normals) < 0).any(axis=1)


def test_autzen_folds_are_level_4_sampling_of_creases_not_folds_of_the_spline():
    """The base triangles that hold Autzen's folded level-4 faces are needles (longest edge
    over width above 8) and, refined to level 32 with the same coefficients, have no folded
    face: the spline is a graph whose gradient turns across the needle faster than 4
    sub-faces can follow (a graph's fine facets tend to its normals, so its own normals
    never face away from them). docs/overshoot.md, "Sliver creases"."""
    xy, z, g, tri = height_data(SAMPLES / "autzen_trim.laz")
    table = edge_table(tri, xy.shape[0])
    z, gradients, directions, _ = control_overshoot(xy, z, g, tri, table=table)
    coarse = RSDInterpolator(xy, z, gradients, triangles=tri, directions=directions,
                             edge_table=table).refine(4)
    folding = np.unique(coarse.parent[_folded_per_face(coarse)])
    assert folding.size > 0
    corners = xy[tri[folding]]
    longest = np.max([np.linalg.norm(corners[:, k] - corners[:, (k + 1) % 3], axis=1)
                      for k in range(3)], axis=0)
    side_a, side_b = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    width = np.abs(side_a[:, 0] * side_b[:, 1] - side_a[:, 1] * side_b[:, 0]) / longest
    assert (longest / width).min() > 8
    keep = edge_table(tri[folding], xy.shape[0])
    lookup = {tuple(e): i for i, e in enumerate(table.edges.tolist())}
    own = directions[[lookup[tuple(e)] for e in keep.edges.tolist()]]
    patch = RSDInterpolator(xy, z, gradients, triangles=tri[folding], directions=own,
                            edge_table=keep)
    np.testing.assert_array_equal(_folded_per_face(patch.refine(4)).reshape(folding.size, -1).any(axis=1),
                                  np.ones(folding.size, dtype=bool))
    assert not _folded_per_face(patch.refine(32)).any()


def noisy_random_ground(side: float = 40.0, density: float = 4.0, noise: float = 0.02, seed: int = 0):
    """(n, 3) points of benchmarks.tiled_delaunay's synthetic LiDAR ground in a side × side m
    square: uniform random positions at `density` per m², smooth relief, Gaussian height
    noise of `noise` m (no normals: the fit estimates gradients from the heights)."""
    rng = np.random.default_rng(seed)
    n = int(side * side * density)
    x, y = rng.uniform(0, side, n), rng.uniform(0, side, n)
    z = 100 + 10 * np.sin(x / 150) * np.cos(y / 200) + 3 * np.sin(x / 37 + y / 53) + rng.normal(0, noise, n)
    return np.column_stack([x, y, z])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noisy_random_ground_has_no_folded_faces_at_default_options(seed):
    """Random ground points with 2 cm noise, fitted as a LAS ground tile is (axis z, gradients
    fitted to the heights, the limiter): no folded face at level 4. The same triangles and
    gradients without the remedies fold (81, 55 and 57 faces of about 200k), in needles
    whose short edge joins two points a few centimetres apart."""
    cloud = PointCloud(points=noisy_random_ground(seed=seed))
    model = build_surface(cloud, FitOptions(smooth="off", axis="z"))
    assert not _folded_per_face(model.interp.refine(4)).any()
    assert model.overshoot.heights_reconciled > 0
    hf, used = model.hf, model.used
    raw = RSDInterpolator(hf.xy[used], hf.z[used], hf.gradients[used], triangles=model.interp.triangles)
    assert _folded_per_face(raw.refine(4)).sum() > 20


def bank_ground(side: float = 60.0, seed: int = 0, height: float = 7.0, spacing: float = 1.3) -> np.ndarray:
    """(n, 3) points of LiDAR ground with a bank (issue 38, item 3): a jittered grid of
    `spacing` m (each point moved up to 0.3 spacing per axis) over a side x side m square,
    heights 50 m plus a tanh step of `height` m and about 1 m width along the line
    y = x/2 + side/2, and 2 cm Gaussian noise."""
    rng = np.random.default_rng(seed)
    grid = np.arange(0, side, spacing)
    x, y = (c.ravel() for c in np.meshgrid(grid, grid))
    x = x + rng.uniform(-0.3, 0.3, x.size) * spacing
    y = y + rng.uniform(-0.3, 0.3, y.size) * spacing
    across = (y - 0.5 * x - side / 2) / np.hypot(0.5, 1.0)
    z = 50 + height * 0.5 * (1 + np.tanh(across / 0.25)) + rng.normal(0, 0.02, x.size)
    return np.column_stack([x, y, z])


@pytest.mark.parametrize("seed, smooth", [
    pytest.param(2, "off", marks=pytest.mark.xfail(
        strict=True, reason="issue 38 item 3 not met: a triangle spanning the bank with flat (limited) "
                            "corners; its spline is steeper than the facet and turns within the "
                            "triangle faster than level 4 samples (docs/overshoot.md, Steps)")),
    pytest.param(1, "auto", marks=pytest.mark.xfail(
        strict=True, reason="issue 38 item 3 not met: the smoothing fit's gradients are not limited, "
                            "so at the bank they overshoot (docs/overshoot.md, Steps)"))])
def test_ground_with_a_bank_has_no_folded_faces(seed, smooth):
    """A 7 m bank over 1 m, sampled at 1.3 m with 2 cm noise, fitted as a LAS ground tile
    (axis z): no folded face at level 4, exact or smoothed."""
    model = build_surface(PointCloud(points=bank_ground(seed=seed)), FitOptions(axis="z", smooth=smooth))
    assert not _folded_per_face(model.interp.refine(4)).any()


def _noisy_pair_patch(rng, noise=0.02):
    """Random points on the quadratic z = 0.1x² − 0.05xy on [0, 1]² with its exact gradients,
    plus one point 1 mm from the first: (xy, z, g, triangles) before any noise."""
    xy = rng.random((400, 2))
    xy = np.vstack([xy, xy[:1] + [0.001, 0.0]])
    z = 0.1 * xy[:, 0] ** 2 - 0.05 * xy[:, 0] * xy[:, 1]
    g = np.column_stack([0.2 * xy[:, 0] - 0.05 * xy[:, 1], -0.05 * xy[:, 0]])
    return xy, z, g, Delaunay(xy).simplices


def test_reconcile_heights_leaves_exact_quadratic_data_alone():
    """The trapezoid residual vanishes on every quadratic, so even the 1 mm edge moves nothing."""
    from c1mesh.stages.limiter import reconcile_heights
    xy, z, g, tri = _noisy_pair_patch(np.random.default_rng(1))
    moved, _ = reconcile_heights(xy, z, g, tri)
    assert np.abs(moved - z).max() <= 1e-15


def test_reconcile_heights_closes_a_noisy_near_pair_within_the_clip():
    """0.1 mm noise on the quadratic (h about 5 cm: no ordinary edge creases) and the 1 mm
    pair 0.3 mm apart in height, a slope of 0.3 its gradients deny: only the ends of
    near pairs (edges under 5 mm; random points have two more) move, the pair's residual
    closes exactly (half of it is under HEIGHT_CLIP noise floors), and a far
    larger misfit (a 20-floor step) moves each end by exactly the clip and keeps the rest."""
    from c1mesh.stages.limiter import HEIGHT_CLIP, reconcile_heights, trapezoid_residuals
    rng = np.random.default_rng(2)
    xy, z, g, tri = _noisy_pair_patch(rng)
    exact_rise = z[-1] - z[0]
    z = z + rng.normal(0, 1e-4, len(z))
    z[-1] = z[0] + 3e-4
    edges = edge_table(tri, len(xy)).edges
    floor = float(np.median(np.abs(trapezoid_residuals(xy, z, g, edges))))
    moved, changed = reconcile_heights(xy, z, g, tri)
    length = np.linalg.norm(xy[edges[:, 1]] - xy[edges[:, 0]], axis=1)
    near = np.zeros(len(xy), dtype=bool)
    near[edges[length < 0.005].ravel()] = True
    assert changed[0] and changed[-1] and not np.any(changed & ~near)
    pair = np.flatnonzero((edges[:, 0] == 0) & (edges[:, 1] == len(xy) - 1))
    before = trapezoid_residuals(xy, z, g, edges)[pair][0]
    after = trapezoid_residuals(xy, moved, g, edges)[pair][0]
    assert floor < abs(before) < 2 * HEIGHT_CLIP * floor and abs(after) <= 1e-15
    assert moved[-1] - moved[0] == pytest.approx(exact_rise, abs=1e-9)   # the quadratic's rise
    z[-1] = z[0] + 20 * floor
    stepped, _ = reconcile_heights(xy, z, g, tri, noise_floor=floor)
    assert stepped[-1] - z[-1] == pytest.approx(-HEIGHT_CLIP * floor, rel=1e-9)
    assert stepped[0] - z[0] == pytest.approx(HEIGHT_CLIP * floor, rel=1e-9)



def test_longest_adjacent_edge_is_the_longest_edge_of_the_edges_triangles_by_a_loop():
    """The limiter's reach of each edge (its kernel) against a loop over the triangles that
    hold the edge; a NaN length makes NaN every edge whose triangles take it in."""
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.stages.limiter import _longest_adjacent_edge2

    rng = np.random.default_rng(21)
    xy = rng.random((500, 2))
    tri = delaunay(xy)
    table = edge_table(tri, len(xy))
    length2 = ((xy[table.edges[:, 1]] - xy[table.edges[:, 0]]) ** 2).sum(axis=1)
    holders = {}
    for t in range(len(tri)):
        for k in range(3):
            holders.setdefault(int(table.tri_edge[t, k]), []).append(t)
    expected = [max(length2[table.tri_edge[t]].max() for t in holders[e]) for e in range(len(length2))]
    np.testing.assert_array_equal(_longest_adjacent_edge2(length2, table), expected)
    length2[7] = np.nan
    reach = _longest_adjacent_edge2(length2, table)
    touched = {int(e) for t in holders[7] for e in table.tri_edge[t]}
    tainted = {e for e in range(len(length2)) if any(t2 in holders[7] for t2 in holders[e])}
    assert touched <= tainted
    assert set(np.flatnonzero(np.isnan(reach)).tolist()) == tainted
