"""The fit pipeline end to end on inputs with known truth, and on the real bundled scans."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from c1mesh.core.cloud import PointCloud
from c1mesh.core.errors import C1MeshError, InputError, NotAHeightFieldError
from c1mesh.formats import read_cloud
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit
from c1mesh.testing.samples import SURFACES, exact_normals, rotation_about, sample_surface, write_points_ply

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"


def _edges(faces):
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    return directed


def assert_manifold_and_oriented(faces):
    directed = _edges(faces)
    n = int(faces.max()) + 1
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    assert counts.max() <= 2, "an edge is shared by more than two faces"
    # consistent orientation: no directed edge appears twice
    _, dcounts = np.unique(directed[:, 0] * n + directed[:, 1], return_counts=True)
    assert dcounts.max() == 1, "two faces traverse an edge in the same direction"


@pytest.fixture(scope="module")
def hill_fit(tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "hill.ply"
    return fit(SAMPLES / "hill.ply", out, FitOptions(smooth="off", level=3)), out


HILL_HESSIAN_MAX = 7.5   # max |D²f| of the hill: 2·0.3/0.08, the Gaussian's curvature at its top


def _linear_peer(cloud, surface, xy):
    """The piecewise-linear interpolant of the same points (scipy, over the same Delaunay
    triangulation): per query point, its value error, facet-normal angle (degrees) and
    the longest edge of the input triangle it lies in; NaN outside the hull."""
    from scipy.spatial import Delaunay
    tri = Delaunay(cloud.points[:, :2])
    simplex = tri.find_simplex(xy)
    corners = cloud.points[tri.simplices[simplex]]                          # (m, 3, 3)
    bary = np.einsum("mij,mj->mi", tri.transform[simplex, :2], xy - tri.transform[simplex, 2])
    weights = np.column_stack([bary, 1 - bary.sum(axis=1)])
    value = np.einsum("mi,mi->m", weights, corners[:, :, 2])
    facet = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    facet *= np.sign(facet[:, 2:]) / np.linalg.norm(facet, axis=1, keepdims=True)
    truth = exact_normals(surface.grad(xy))
    angle = np.degrees(np.arccos(np.clip(np.sum(truth * facet, axis=1), -1, 1)))
    longest = np.linalg.norm(corners - corners[:, [1, 2, 0]], axis=2).max(axis=1)
    outside = simplex < 0
    err = np.abs(value - surface.f(xy))
    for a in (err, angle, longest):
        a[outside] = np.nan
    return err, angle, longest


def test_hill_surface_within_theory(hill_fit):
    """Values: the sextic reproduces affine functions, so on a triangle with longest edge h
    its error is within the Taylor remainder M2·h²/2 (M2 the largest second derivative).
    Values and normals: with exact normals it must beat the piecewise-linear interpolant
    of the same points (same O(h²) order for values, but no gradient information)."""
    result, out = hill_fit
    mesh = result.mesh
    surface = SURFACES["hill"]
    xy = mesh.vertices[:, :2]
    err = np.abs(mesh.vertices[:, 2] - surface.f(xy))
    true_n = exact_normals(surface.grad(xy))
    np.testing.assert_allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1.0, atol=1e-12)
    angle = np.degrees(np.arccos(np.clip(np.sum(true_n * mesh.vertex_normals, axis=1), -1, 1)))
    peer_err, peer_angle, h = _linear_peer(read_cloud(SAMPLES / "hill.ply"), surface, xy)
    inside = ~np.isnan(h)
    assert inside.mean() > 0.95
    assert np.all(err[inside] <= HILL_HESSIAN_MAX * h[inside] ** 2 / 2)
    assert np.sqrt(np.mean(err[inside] ** 2)) < np.sqrt(np.mean(peer_err[inside] ** 2))
    assert np.median(angle[inside]) < np.median(peer_angle[inside])
    assert angle.max() < np.nanmax(peer_angle)
    assert out.exists() and read_cloud(out).points.shape == mesh.vertices.shape


def test_every_kept_point_is_a_vertex_with_its_height(hill_fit):
    result, _ = hill_fit
    cloud = read_cloud(SAMPLES / "hill.ply")
    kept = result.report["points"]["kept"]
    assert kept >= 0.95 * len(cloud)
    # the first `kept` output vertices are the kept input points, heights included
    distance, nearest = cKDTree(cloud.points).query(result.mesh.vertices[:kept])
    assert distance.max() < 1e-12
    assert len(np.unique(nearest)) == kept


def test_output_mesh_is_manifold_and_oriented_up(hill_fit):
    result, _ = hill_fit
    mesh = result.mesh
    assert_manifold_and_oriented(mesh.faces)
    v = mesh.vertices[mesh.faces]
    face_normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert np.all(face_normal[:, 2] > 0)        # consistently facing the +z axis side
    assert np.all(mesh.vertex_normals[:, 2] > 0)


def test_report_contents(hill_fit):
    report = hill_fit[0].report
    assert report["scheme"]["name"] == "sextic" and report["scheme"]["reproduces_affine"] is True
    assert report["c1_certificate"]["edges_checked"] > 100
    assert report["c1_certificate"]["gradient_jump"] < 1e-9
    assert report["output_mesh"]["faces"] == report["triangles"]["after_trim"] * 9
    assert set(report["seconds"]) >= {"read", "triangulate", "refine", "write"}


def test_tilted_scan_at_lidar_offsets(tmp_path):
    """A surface tilted 30° and shifted to (6.4e5, 8.5e5): the fit finds the plane and keeps digits."""
    R = rotation_about([1, 1, 0], 30)
    offset = np.array([640_000.0, 850_000.0, 120.0])
    cloud = sample_surface("wave", 3000, seed=5, rotation=R, offset=offset, scale=50.0)
    path = tmp_path / "tilted.ply"
    write_points_ply(cloud, path)
    result = fit(path, tmp_path / "out.ply", FitOptions(smooth="off", level=2))
    local = (result.mesh.vertices - offset) @ R / 50.0        # back to the surface's own frame
    err = np.abs(local[:, 2] - SURFACES["wave"].f(local[:, :2]))
    assert err.max() < 2e-3
    kept = result.report["points"]["kept"]
    assert kept > 2900
    # input points come back to ~1e-9 of their world coordinates (doubles kept)
    d, _ = cKDTree(result.mesh.vertices).query(cloud.points)
    assert np.sort(d)[kept - 1] < 1e-8


def test_plane_stays_flat_with_sextic_not_quintic(tmp_path):
    cloud = sample_surface("plane", 1500, seed=3, rotation=rotation_about([0, 1, 0], 20))
    path = tmp_path / "plane.ply"
    write_points_ply(cloud, path)
    normal = exact_normals(SURFACES["plane"].grad(np.zeros((1, 2))))[0] @ rotation_about([0, 1, 0], 20).T
    deviation = {}
    # axis z: the plane is tilted in the frame (with --axis auto it would be level, a constant)
    for scheme in ("sextic", "quintic"):
        mesh = fit(path, None, FitOptions(smooth="off", level=3, scheme=scheme, axis="z")).mesh
        heights = (mesh.vertices - cloud.points[0]) @ normal
        deviation[scheme] = np.abs(heights).max()
    assert deviation["sextic"] < 1e-10
    assert deviation["quintic"] > 1e-4


def _colored_hill(tmp_path, n=800):
    """A binary PLY of the hill sample with a colour ramp in x; returns its path."""
    cloud = sample_surface("hill", n, seed=2)
    red = np.round(cloud.points[:, 0] * 250).astype(np.uint8)
    colored = PointCloud(cloud.points, cloud.normals, np.stack([red, 255 - red, 0 * red + 7], 1))
    n = len(colored)
    header = ("ply\nformat binary_little_endian 1.0\n" f"element vertex {n}\n"
              + "".join(f"property double {c}\n" for c in ("x", "y", "z", "nx", "ny", "nz"))
              + "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    dtype = np.dtype([(c, "<f8") for c in ("x", "y", "z", "nx", "ny", "nz")] + [(c, "u1") for c in "rgb"])
    rows = np.zeros(n, dtype)
    for i, c in enumerate(("x", "y", "z")):
        rows[c] = colored.points[:, i]
        rows["n" + c] = colored.normals[:, i]
    for i, c in enumerate("rgb"):
        rows[c] = colored.colors[:, i]
    path = tmp_path / "colored.ply"
    path.write_bytes(header.encode() + rows.tobytes())
    return path


def test_colours_are_carried(tmp_path):
    path = _colored_hill(tmp_path)
    # axis z: colours are blended in the plane, which is then the world xy plane
    mesh = fit(path, tmp_path / "out.ply", FitOptions(smooth="off", level=3, axis="z")).mesh
    assert mesh.vertex_colors is not None
    np.testing.assert_allclose(mesh.vertex_colors[:, 0], mesh.vertices[:, 0] * 250, atol=1.01)
    assert np.all(mesh.vertex_colors[:, 2] == 7)


def test_real_bunny_scan_with_file_normals(tmp_path):
    result = fit(SAMPLES / "pcl_bun0.pcd", tmp_path / "bunny.ply", FitOptions(smooth="off", level=2))
    assert result.report["normals"] == "file"
    assert result.report["points"]["kept"] > 200
    assert_manifold_and_oriented(result.mesh.faces)


def test_lidar_ground_class_with_estimated_normals(tmp_path):
    result = fit(SAMPLES / "4_6_crop.las", tmp_path / "ground.ply", FitOptions(smooth="off", level=2, classes=(2,)))
    report = result.report
    assert report["normals"] == "estimated"
    assert report["points"]["read"] == 9003          # the ground class of this tile
    assert report["points"]["kept"] > 8000
    # the height axis of ground LiDAR is close to world z
    assert abs(report["frame"]["axes"][2][2]) > 0.99
    with pytest.raises(InputError, match="class"):
        fit(SAMPLES / "4_6_crop.las", None, FitOptions(smooth="off", classes=(99,)))


def _plan_areas(vertices, faces):
    """Twice the signed area of each face over (x, y): positive when counter-clockwise."""
    p = vertices[faces]
    return ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
            - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))


def test_topo_csv_heights_in_feet_over_a_plan_in_50_ft_units():
    """Issue 21: R's MASS topo (x, y in 50 ft, z in ft). Its header names z, so z is the
    height in units of its own: every point is a vertex at its height and no face folds
    over the plan. Before, the auto axis was nearly y (26 of 52 points became vertices,
    279 faces folded in plan view), and --axis z refused normals that x, y and z in one
    metric made nearly horizontal."""
    from c1mesh.testing.quality import folded_faces

    table = np.genfromtxt(SAMPLES / "topo.csv", delimiter=",", skip_header=1, usecols=(1, 2, 3))
    assert table.shape == (52, 3)
    result = fit(SAMPLES / "topo.csv", None, FitOptions(smooth="off"))
    mesh, report = result.mesh, result.report
    assert report["points"]["kept"] == 52
    assert "height column 'z'" in report["frame"]["axis_choice"]
    assert report["warnings"] == []
    distance, vertex = cKDTree(mesh.vertices[:, :2]).query(table[:, :2])
    assert distance.max() < 1e-12
    np.testing.assert_allclose(mesh.vertices[vertex, 2], table[:, 2], rtol=0, atol=1e-9)
    assert (_plan_areas(mesh.vertices, mesh.faces) > 0).all()
    # in the data's own single metric (heights in 50 ft) no face turns against its normals
    foot = 1 / 50
    assert folded_faces(mesh.vertices * [1, 1, foot], mesh.faces, mesh.vertex_normals * [foot, foot, 1]) == 0


def test_topo_csv_with_axis_z_is_the_same_fit():
    """`--axis z` names the axis the header names: the same plan-unit fit, not a refusal."""
    auto = fit(SAMPLES / "topo.csv", None, FitOptions(smooth="off", level=2)).mesh
    given = fit(SAMPLES / "topo.csv", None, FitOptions(smooth="off", level=2, axis="z")).mesh
    np.testing.assert_array_equal(given.vertices, auto.vertices)
    np.testing.assert_array_equal(given.faces, auto.faces)


def test_a_header_height_with_file_normals_keeps_the_auto_axis(tmp_path):
    """File normals say x, y and z share one metric, so "auto" still finds a tilted scan's
    axis from them (wave_tilted_offset.xyz has the header x y z nx ny nz)."""
    result = fit(SAMPLES / "wave_tilted_offset.xyz", None, FitOptions(smooth="off", level=1))
    assert result.report["frame"]["axis_choice"] == "auto: the mean of the normals"
    assert abs(result.report["frame"]["axes"][2][2]) < 0.95     # tilted 30° off z


def test_a_height_column_at_two_plan_positions_is_refused(tmp_path):
    """Five heights at two (x, y) positions: the slope fit says what is missing."""
    path = tmp_path / "two.csv"
    path.write_text("x,y,z\n0,0,1\n0,0,2\n1,1,3\n1,1,4\n1,1,5\n")
    with pytest.raises(InputError, match="at least 3 distinct .x, y. positions, got 5 points at 2"):
        fit(path, None, FitOptions())


def test_room_is_not_a_height_field():
    with pytest.raises(NotAHeightFieldError, match="height field"):
        fit(SAMPLES / "o3d_cloud_bin_0.pcd", None, FitOptions())


@pytest.mark.parametrize("points, message", [
    (np.array([[0.0, 0, 0], [1, 0, 0]]), "3"),
    (np.array([[0.0, 0, 0], [1, 1, 0], [2, 2, 0], [3, 3, 0]]), "one line"),
    (np.full((10, 3), np.nan), "finite"),
])
def test_too_few_or_degenerate_points(tmp_path, points, message):
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    path = tmp_path / "few.ply"
    write_points_ply(PointCloud(points, normals), path)
    with pytest.raises(C1MeshError, match=message):
        fit(path, tmp_path / "out.ply", FitOptions())
    assert not (tmp_path / "out.ply").exists()


@pytest.mark.parametrize("ascii_ply", [False, True])
def test_streamed_output_is_the_assembled_mesh(tmp_path, monkeypatch, ascii_ply):
    """keep_mesh=False (what the CLI does) writes block by block; the file must be
    byte-identical to writing the assembled mesh, with colours, across many blocks."""
    import c1mesh.engine.refine as refine_module
    monkeypatch.setattr(refine_module, "CHUNK_ENTRIES", 300)
    path = _colored_hill(tmp_path)
    whole = fit(path, tmp_path / "whole.ply", FitOptions(smooth="off", level=3, ascii=ascii_ply, axis="z"))
    streamed = fit(path, tmp_path / "streamed.ply", FitOptions(smooth="off", level=3, ascii=ascii_ply, axis="z"),
                   keep_mesh=False)
    assert streamed.mesh is None and whole.mesh.vertex_colors is not None
    assert (tmp_path / "streamed.ply").read_bytes() == (tmp_path / "whole.ply").read_bytes()
    assert streamed.report["output_mesh"] == whole.report["output_mesh"]
    back = read_cloud(tmp_path / "streamed.ply")
    np.testing.assert_array_equal(back.points, whole.mesh.vertices)
    np.testing.assert_array_equal(back.colors, whole.mesh.vertex_colors)


def test_mesh_pieces_counts_edge_connected_parts_and_the_area_they_cover():
    """Two unit squares far apart and one half-square: 3 pieces; the largest holds 2 of 5
    triangles; they cover 2.5 of the convex hull's 38.5 (shoelace over its corners
    (0,0), (11,0), (6,6), (5,6), (0,1), worked by hand)."""
    from c1mesh.pipeline.steps import mesh_pieces

    xy = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [5, 5], [6, 5], [6, 6], [5, 6],
                   [10, 0], [11, 0], [10, 1]], float)
    triangles = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [8, 9, 10]])
    pieces = mesh_pieces(xy, triangles)
    assert pieces["count"] == 3
    assert pieces["largest_fraction"] == pytest.approx(2 / 5)
    assert pieces["area_fraction"] == pytest.approx(2.5 / 38.5)


def test_compact_vertices_numbers_the_used_points_as_np_unique_does():
    from c1mesh.pipeline.steps import compact_vertices

    rng = np.random.default_rng(4)
    triangles = rng.choice(np.arange(0, 90, 3), size=(40, 3))       # every third point at most
    used, local = compact_vertices(np.zeros((95, 2)), triangles)
    want = np.unique(triangles)
    assert np.array_equal(used, want) and np.array_equal(used[local], triangles)
    assert np.array_equal(local, np.searchsorted(want, triangles))
    with pytest.raises(ValueError):
        compact_vertices(np.zeros((10, 2)), np.array([[0, 1, 10]]))


def _pieces_by_search(triangles):
    """(count, largest) of the triangles joined through shared edges, by a search over a
    dict of edges: the reference for the union-find kernel."""
    by_edge = {}
    for t, tri in enumerate(triangles.tolist()):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            by_edge.setdefault((min(a, b), max(a, b)), []).append(t)
    label = [-1] * len(triangles)
    sizes = []
    for start in range(len(triangles)):
        if label[start] >= 0:
            continue
        label[start], stack, size = len(sizes), [start], 0
        while stack:
            t = stack.pop()
            size += 1
            tri = triangles[t].tolist()
            for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
                for u in by_edge[(min(a, b), max(a, b))]:
                    if label[u] < 0:
                        label[u] = len(sizes)
                        stack.append(u)
        sizes.append(size)
    return len(sizes), max(sizes)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mesh_pieces_kernel_agrees_with_a_search_and_the_shoelace_area(seed):
    """A Delaunay triangulation of integer points with random triangles removed: many
    pieces, some touching at a vertex only (separate pieces); areas of integer triangles
    are exact halves, so the sum is exact."""
    from c1mesh.engine.triangulation import delaunay
    from c1mesh.pipeline.steps import compact_vertices, mesh_pieces

    rng = np.random.default_rng(seed)
    xy = np.unique(rng.integers(0, 40, size=(400, 2)), axis=0).astype(float)
    triangles = delaunay(xy)
    triangles = triangles[rng.random(len(triangles)) < 0.55]
    used, local = compact_vertices(xy, triangles)
    pieces = mesh_pieces(xy[used], local)
    count, largest = _pieces_by_search(local)
    assert count > 5 and pieces["count"] == count
    assert pieces["largest_fraction"] == largest / len(local)
    p = xy[used][local]
    doubled = np.abs((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
                     - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))
    from scipy.spatial import ConvexHull
    assert pieces["area_fraction"] == pytest.approx(0.5 * doubled.sum() / ConvexHull(xy[used]).volume, rel=1e-12)


def test_a_survey_of_height_column_tables_is_fitted_like_the_whole_table(tmp_path):
    """topo.csv cut into a west and an east file: --seamless -o fits them in plan units like
    the one table (the union equals the whole fit, docs/tiles.md), and a survey where only
    one file names a height column is refused."""
    import subprocess
    import sys

    from c1mesh.formats import read_cloud

    lines = (SAMPLES / "topo.csv").read_text().splitlines()
    header, rows = lines[0], lines[1:]
    west = [r for r in rows if float(r.split(",")[1]) < 3.0]
    east = [r for r in rows if float(r.split(",")[1]) >= 3.0]
    (tmp_path / "west.csv").write_text("\n".join([header, *west]) + "\n")
    (tmp_path / "east.csv").write_text("\n".join([header, *east]) + "\n")
    cli = [sys.executable, "-m", "c1mesh.cli", "fit", "--smooth", "off"]
    whole = subprocess.run(cli + [str(SAMPLES / "topo.csv"), "--level", "2", "-o", str(tmp_path / "whole.ply")],
                           capture_output=True, text=True)
    union = subprocess.run(cli + [str(tmp_path / "west.csv"), str(tmp_path / "east.csv"), "--seamless",
                                  "--level", "2", "-o", str(tmp_path / "union.ply")], capture_output=True, text=True)
    assert whole.returncode == 0 and union.returncode == 0, union.stderr
    rows_of = lambda name: np.unique(read_cloud(tmp_path / name).points, axis=0)  # noqa: E731
    np.testing.assert_array_equal(rows_of("union.ply"), rows_of("whole.ply"))
    (tmp_path / "plain.xyz").write_text("".join(" ".join(r.split(",")[1:]) + "\n" for r in east))  # no header
    mixed = subprocess.run(cli + [str(tmp_path / "west.csv"), str(tmp_path / "plain.xyz"), "--seamless",
                                  "-o", str(tmp_path / "mixed.ply")], capture_output=True, text=True)
    assert mixed.returncode == 1 and "names a height column" in mixed.stderr
    assert not (tmp_path / "mixed.ply").exists()


@pytest.mark.parametrize("kind", ["random", "circle", "square grid", "three", "line", "repeats"])
def test_hull_area_is_scipys_convex_hull_volume(kind):
    """pipeline.steps.hull_area (Andrew's monotone chain) against scipy's ConvexHull
    (qhull) volume, to rounding, also 1e5 from the origin; 0 for points on one line
    (qhull refuses them)."""
    from scipy.spatial import ConvexHull

    from c1mesh.pipeline.steps import hull_area
    rng = np.random.default_rng(7)
    xy = {"random": rng.normal(size=(500, 2)) * [3.0, 1.0] + [1e5, 2e5],
          "circle": np.c_[np.cos(np.arange(64) / 10.19), np.sin(np.arange(64) / 10.19)],
          "square grid": np.stack(np.meshgrid(np.arange(6.0), np.arange(4.0)), -1).reshape(-1, 2),
          "three": np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 1.0]]),
          "line": np.c_[np.arange(9.0), 2 * np.arange(9.0) + 1],
          "repeats": np.repeat(rng.random((40, 2)), 3, axis=0)}[kind]
    # qhull on centred points: on the raw state-plane-like coordinates its own volume
    # moves by ~1e-12 relative; hull_area sums a fan from a hull corner, which loses nothing
    want = 0.0 if kind == "line" else ConvexHull(xy - xy.mean(axis=0)).volume
    assert hull_area(xy) == pytest.approx(want, rel=1e-12, abs=1e-12)
