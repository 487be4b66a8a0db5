"""Scan frame and height-field projection, checked against analytic surfaces and real scans."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from c1mesh.core.errors import InputError, NotAHeightFieldError
from c1mesh.stages.frame import ScanFrame, choose_frame
from c1mesh.stages.height_field import HeightField, gradients_to_normals, height_field

REAL = Path(__file__).resolve().parent.parent / "data_samples"  # copies of ../shared/data/real
LIDAR_OFFSET = np.array([6.4e5, 8.5e5, 420.0])


def rotation(axis, angle):
    """Rodrigues rotation matrix, independent of c1mesh's frame code."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def wave(xy):
    """Analytic height field f and its gradient."""
    x, y = xy[:, 0], xy[:, 1]
    f = 0.3 * np.sin(x) * np.cos(0.7 * y) + 0.05 * x * y
    fx = 0.3 * np.cos(x) * np.cos(0.7 * y) + 0.05 * y
    fy = -0.21 * np.sin(x) * np.sin(0.7 * y) + 0.05 * x
    return f, np.stack([fx, fy], axis=1)


def tilted_scan(n=2000, seed=0, flip_fraction=0.0):
    """World points/normals of `wave` sampled in a rotated, LiDAR-offset frame.

    Returns (points, normals, R, xy, f, grad): local (x, y, f) maps to world as
    LIDAR_OFFSET + R @ (x, y, f); normals are the exact ones, a fraction flipped.
    """
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-3, 3, size=(n, 2))
    f, grad = wave(xy)
    R = rotation([1.0, -2.0, 0.5], 0.6)
    local = np.column_stack([xy, f])
    nrm = np.column_stack([-grad, np.ones(n)])
    nrm *= rng.uniform(0.5, 2.0, size=(n, 1))                      # not unit length
    nrm[rng.random(n) < flip_fraction] *= -1
    return LIDAR_OFFSET + local @ R.T, nrm @ R.T, R, xy, f, grad


# --- ScanFrame ------------------------------------------------------------------------

def test_round_trip_at_lidar_offsets_is_within_an_ulp_or_two():
    rng = np.random.default_rng(1)
    pts = LIDAR_OFFSET + rng.uniform(-1000, 1000, size=(10000, 3))
    frame = choose_frame(pts, axis="0.3,-0.2,1")
    back = frame.to_world(frame.to_local(pts))
    err = np.abs(back - pts)
    # within one ulp of the point's largest coordinate...
    assert np.all(err <= np.spacing(np.abs(pts).max(axis=1, keepdims=True)))
    # ...and per coordinate within its own ulp plus rounding of the small local offsets
    local_size = np.linalg.norm(pts - frame.origin, axis=1, keepdims=True)
    assert np.all(err <= np.spacing(np.abs(pts)) + 8 * np.finfo(float).eps * local_size)
    assert np.mean(back == pts) > 0.5                                 # mostly bit-exact
    vec = rng.normal(size=(100, 3))
    assert np.allclose(frame.vectors_to_world(frame.vectors_to_local(vec)), vec, rtol=0, atol=1e-15)


def test_to_local_preserves_distances_and_puts_a_tilted_plane_at_constant_height():
    pts, _, R, *_ = tilted_scan()
    plane = LIDAR_OFFSET + np.column_stack([np.random.default_rng(2).uniform(-50, 50, (500, 2)),
                                            np.full(500, 7.0)]) @ R.T
    frame = choose_frame(plane, axis=R[:, 2])
    local = frame.to_local(plane)
    assert np.ptp(local[:, 2]) < 1e-9
    d_world = np.linalg.norm(plane[1:] - plane[:-1], axis=1)
    d_local = np.linalg.norm(local[1:] - local[:-1], axis=1)
    assert np.allclose(d_world, d_local, rtol=1e-12, atol=1e-9)


def test_z_axis_frame_is_the_identity_and_exact():
    pts = LIDAR_OFFSET + np.random.default_rng(3).uniform(-500, 500, (1000, 3))
    frame = choose_frame(pts, axis="z")
    assert np.array_equal(frame.axes, np.eye(3))
    assert np.array_equal(frame.to_local(pts), pts - frame.origin)
    assert np.array_equal(frame.to_world(frame.to_local(pts)), pts)


@pytest.mark.parametrize("axis, e1, e2, e3", [
    ("x", [0, 1, 0], [0, 0, 1], [1, 0, 0]),
    ("y", [0, 0, 1], [1, 0, 0], [0, 1, 0]),
    ("+z", [1, 0, 0], [0, 1, 0], [0, 0, 1]),
    ("-z", [1, 0, 0], [0, -1, 0], [0, 0, -1]),
    (" X ", [0, 1, 0], [0, 0, 1], [1, 0, 0]),
])
def test_world_axes_give_exact_right_handed_permutations(axis, e1, e2, e3):
    frame = choose_frame(np.zeros((3, 3)), axis=axis)
    assert np.array_equal(frame.axes, np.array([e1, e2, e3], float))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3).filter(
    lambda v: np.linalg.norm(v) > 1e-3))
def test_any_axis_gives_an_orthonormal_right_handed_frame_with_that_e3(v):
    frame = choose_frame(np.zeros((3, 3)), axis=np.array(v))
    A = frame.axes
    assert np.allclose(A @ A.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(A), 1.0)
    assert np.allclose(A[2], np.array(v) / np.linalg.norm(v), atol=1e-12)
    same = choose_frame(np.ones((4, 3)), axis=",".join(repr(c) for c in v))
    assert np.allclose(same.axes, A, atol=1e-12)                           # string form agrees


@pytest.mark.parametrize("axis", ["0,0,0", [0.0, 0.0, 0.0], "nan,0,1", [np.inf, 0, 0], "w", "1,2",
                                  "up", [1.0, 2.0]])
def test_unusable_axes_are_input_errors(axis):
    with pytest.raises(InputError, match="axis"):
        choose_frame(np.zeros((3, 3)), axis=axis)


def test_auto_axis_follows_the_normals_even_with_arbitrary_signs():
    pts, nrm, R, *_ = tilted_scan(flip_fraction=0.3)
    frame = choose_frame(pts, nrm)
    # the mean upward normal of `wave` is close to the rotated +z, and 70% of the raw
    # normals point that way, so e3 must be on that side
    assert np.degrees(np.arccos(frame.axes[2] @ R[:, 2])) < 5
    flipped_majority = choose_frame(pts, -nrm)
    assert np.allclose(flipped_majority.axes[2], -frame.axes[2])


def test_auto_axis_without_normals_is_the_least_variance_direction_signed_up():
    pts, _, R, *_ = tilted_scan()
    frame = choose_frame(pts)
    assert np.degrees(np.arccos(abs(frame.axes[2] @ R[:, 2]))) < 5
    assert frame.axes[2][np.argmax(np.abs(frame.axes[2]))] > 0
    assert np.allclose(frame.origin, np.median(pts, axis=0))


def test_choose_frame_ignores_non_finite_rows():
    pts, nrm, *_ = tilted_scan()
    ref = choose_frame(pts, nrm)
    pts2, nrm2 = pts.copy(), nrm.copy()
    pts2[::7] = np.nan
    nrm2[1::5] = 0.0
    frame = choose_frame(pts2, nrm2)
    assert np.isfinite(frame.origin).all()
    assert np.degrees(np.arccos(frame.axes[2] @ ref.axes[2])) < 2
    with pytest.raises(InputError, match="finite"):
        choose_frame(np.full((5, 3), np.nan))


# --- height_field -----------------------------------------------------------------------

def test_height_field_recovers_the_analytic_heights_and_gradients():
    pts, nrm, R, xy, f, grad = tilted_scan(flip_fraction=0.3)
    frame = choose_frame(pts, axis=R[:, 2])
    hf = height_field(pts, nrm, frame)
    assert isinstance(hf, HeightField)
    assert np.array_equal(hf.source_index, np.arange(len(pts)))
    # local xy is the analytic xy up to the frame's in-plane rotation and origin: compare
    # through distances to the first point and through the heights and slopes
    shift = frame.to_local(LIDAR_OFFSET[None])[0]
    rot2 = (frame.axes[:2] @ R[:, :2])                          # in-plane rotation, 2x2
    assert np.allclose(hf.xy, xy @ rot2.T + shift[:2], atol=1e-8)
    assert np.allclose(hf.z, f + shift[2], atol=1e-8)
    assert np.allclose(hf.gradients, grad @ rot2.T, atol=1e-9)
    assert hf.flipped == int(np.sum(np.einsum("ij,j->i", nrm, R[:, 2]) < 0))
    assert hf.dropped == {"non_finite": 0, "bad_normal": 0, "too_steep": 0, "duplicate": 0}
    assert hf.stacked == 0


def test_drops_are_counted_by_reason_and_source_index_points_at_the_input():
    pts, nrm, R, *_ = tilted_scan(n=500)
    pts, nrm = pts.copy(), nrm.copy()
    pts[3, 1] = np.nan
    pts[4, 2] = np.inf
    nrm[10] = 0.0
    nrm[11, 0] = np.nan
    # too steep: the normal 86° away from e3 (in the plane spanned by e3 and R's x axis)
    a = np.radians(86)
    nrm[20] = np.cos(a) * R[:, 2] + np.sin(a) * R[:, 0]
    nrm[21] = -nrm[20]
    frame = choose_frame(pts, axis=R[:, 2])
    hf = height_field(pts, nrm, frame)
    assert hf.dropped == {"non_finite": 2, "bad_normal": 2, "too_steep": 2, "duplicate": 0}
    assert set(hf.source_index).isdisjoint({3, 4, 10, 11, 20, 21})
    assert np.allclose(frame.to_world(np.column_stack([hf.xy, hf.z])), pts[hf.source_index])
    hf_steeper = height_field(pts, nrm, frame, max_slope_deg=87.0)
    assert hf_steeper.dropped["too_steep"] == 0


def test_duplicates_are_merged_keeping_the_first_with_its_own_height():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 10, (400, 2))
    pts = np.column_stack([xy, 0.01 * xy[:, 0]])
    nrm = np.tile([-0.01, 0.0, 1.0], (400, 1))
    # an exact copy placed later, a near copy (1e-9 of the spacing away) placed earlier
    pts = np.vstack([pts, pts[5] + [0, 0, 0.001]])
    pts[0] = pts[7] + [1e-9, 0, 0]
    nrm = np.vstack([nrm, nrm[5]])
    hf = height_field(pts, nrm, choose_frame(pts, axis="z"))
    assert hf.dropped["duplicate"] == 2
    assert 400 not in hf.source_index and 7 not in hf.source_index
    assert {0, 5} <= set(hf.source_index)
    assert hf.z[list(hf.source_index).index(5)] == pytest.approx(pts[5, 2] - np.median(pts[:, 2]))
    assert hf.stacked == 0                               # the copies agree in height


def test_two_layers_are_not_a_height_field():
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 10, (2000, 2))
    pts = np.column_stack([xy, np.where(np.arange(2000) % 2, 0.0, 3.0)])
    nrm = np.tile([0.0, 0.0, 1.0], (2000, 1))
    with pytest.raises(NotAHeightFieldError, match="--axis"):
        height_field(pts, nrm, choose_frame(pts, axis="z"))


def test_a_few_stacked_points_are_kept_and_counted():
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 10, (2000, 2))
    pts = np.column_stack([xy, np.zeros(2000)])
    pts[:40, 2] = 5.0                                     # 2% "birds" above the ground
    nrm = np.tile([0.0, 0.0, 1.0], (2000, 1))
    hf = height_field(pts, nrm, choose_frame(pts, axis="z"))
    assert 40 <= hf.stacked <= 160                       # the birds and the ground below them
    assert hf.xy.shape[0] == 2000


def test_a_wall_seen_along_z_is_too_steep():
    rng = np.random.default_rng(7)
    pts = np.column_stack([rng.uniform(0, 1, 300), np.zeros(300), rng.uniform(0, 1, 300)])
    nrm = np.tile([0.0, 1.0, 0.0], (300, 1))
    with pytest.raises(NotAHeightFieldError, match="steep"):
        height_field(pts, nrm, choose_frame(pts, axis="z"))
    hf = height_field(pts, nrm, choose_frame(pts, nrm))    # auto finds the wall's normal
    assert hf.xy.shape[0] == 300


def test_trusted_signs_reject_a_surface_seen_from_both_sides():
    pts, nrm, R, *_ = tilted_scan(flip_fraction=0.2)
    frame = choose_frame(pts, nrm)
    assert height_field(pts, nrm, frame).flipped > 0
    with pytest.raises(NotAHeightFieldError, match="away from the height axis"):
        height_field(pts, nrm, frame, max_facing_away=0.05)
    oriented = nrm * np.sign(nrm @ R[:, 2])[:, None]
    assert height_field(pts, oriented, frame, max_facing_away=0.05).flipped == 0


@pytest.mark.parametrize("pts, msg", [
    (np.zeros((0, 3)), "only 0"),
    (np.array([[0.0, 0, 0], [1, 0, 0]]), "only 2"),
    (np.column_stack([np.arange(10.0), 2 * np.arange(10.0), np.zeros(10)]), "one line"),
    (np.tile([1.0, 2.0, 3.0], (10, 1)), "distinct"),
])
def test_too_few_or_collinear_points_are_input_errors(pts, msg):
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    with pytest.raises(InputError, match=msg):
        height_field(pts, nrm, ScanFrame(np.zeros(3), np.eye(3)))


def test_bad_shapes_are_input_errors():
    frame = ScanFrame(np.zeros(3), np.eye(3))
    with pytest.raises(InputError, match="shape"):
        height_field(np.zeros((5, 2)), np.zeros((5, 3)), frame)
    with pytest.raises(InputError, match="shape"):
        height_field(np.zeros((5, 3)), np.zeros((4, 3)), frame)
    with pytest.raises(InputError, match="normals"):
        height_field(np.zeros((5, 3)), None, frame)
    with pytest.raises(InputError):
        ScanFrame(np.zeros(3), np.diag([1.0, 1.0, -1.0]))          # left-handed


def test_gradients_to_normals_are_unit_upward_and_perpendicular_to_the_surface():
    g = np.random.default_rng(8).normal(scale=3, size=(100, 2))
    n = gradients_to_normals(g)
    assert np.allclose(np.linalg.norm(n, axis=1), 1)
    assert np.all(n[:, 2] > 0)
    assert np.allclose(np.einsum("ij,ij->i", n, np.column_stack([np.ones(100), 0 * g[:, 0], g[:, 0]])), 0)
    assert np.allclose(np.einsum("ij,ij->i", n, np.column_stack([0 * g[:, 0], np.ones(100), g[:, 1]])), 0)


# --- real scans -------------------------------------------------------------------------

def open3d():
    """Open3D, needed only by the real-scan tests below (they skip without it)."""
    return pytest.importorskip("open3d")


def read_pcd(name):
    pc = open3d().io.read_point_cloud(str(REAL / name))
    return np.asarray(pc.points), np.asarray(pc.normals)


def lidar(name, ground_only):
    laspy = pytest.importorskip("laspy")
    las = laspy.read(str(REAL / name))
    pts = np.column_stack([las.x, las.y, las.z])
    pts = pts[np.asarray(las.classification) == 2] if ground_only else pts
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts - pts.mean(axis=0)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    nrm = np.asarray(cloud.normals)
    return pts, nrm * np.sign(nrm[:, 2:3])


def test_bunny_scan_is_a_height_field_although_7_percent_of_its_normals_face_away():
    pts, nrm = read_pcd("pcl_bun0.pcd")
    frame = choose_frame(pts, nrm)
    assert frame.axes[2][2] < -0.8                      # README: mostly facing -z
    hf = height_field(pts, nrm, frame)
    assert hf.flipped > 0.05 * len(pts)                 # signs from a viewpoint inside the bunny
    assert hf.stacked <= 0.1 * len(pts)
    assert hf.xy.shape[0] + sum(hf.dropped.values()) == len(pts)
    with pytest.raises(NotAHeightFieldError):           # trusting those signs would reject it
        height_field(pts, nrm, frame, max_facing_away=0.05)


@pytest.mark.parametrize("axis", ["auto", "x", "y", "z"])
def test_room_scan_is_not_a_height_field_over_any_axis(axis):
    pts, nrm = read_pcd("o3d_cloud_bin_0.pcd")
    with pytest.raises(NotAHeightFieldError, match="--axis"):
        height_field(pts, nrm, choose_frame(pts, nrm, axis))


def test_lidar_ground_is_a_height_field_and_all_returns_are_not():
    pts, nrm = lidar("4_6_crop.las", ground_only=True)
    frame = choose_frame(pts, axis="z")
    hf = height_field(pts, nrm, frame)
    assert hf.stacked == 0 and hf.xy.shape[0] == len(pts)
    assert np.allclose(frame.to_world(np.column_stack([hf.xy, hf.z])), pts[hf.source_index],
                       rtol=0, atol=1e-9)
    pts, nrm = lidar("4_6_crop.las", ground_only=False)
    with pytest.raises(NotAHeightFieldError, match="--classes 2"):
        height_field(pts, nrm, choose_frame(pts, axis="z"))


# --- fast paths must give the slow paths' exact bits ----------------------------------------

def test_sort_xy_is_lexsort_with_ties_in_x_and_y():
    from c1mesh.stages.height_field import sort_xy
    rng = np.random.default_rng(5)
    xy = rng.integers(-30, 30, size=(5000, 2)).astype(float)   # many ties, exact duplicates
    xy[::7, 0] = -0.0
    xy[1::7, 0] = 0.0
    xy[2::11, 1] = rng.normal(size=xy[2::11].shape[0]) * 1e300    # keys over every exponent
    assert np.array_equal(sort_xy(xy[:, 0], xy[:, 1]), np.lexsort((xy[:, 1], xy[:, 0])))


def test_position_groups_match_a_dictionary_of_positions():
    from c1mesh.stages.height_field import position_groups
    rng = np.random.default_rng(8)
    x, y = rng.integers(0, 12, size=(2, 600)).astype(float)
    x[::5] = -0.0                                              # the same position as 0.0
    z = rng.normal(size=600)
    gradients = rng.normal(size=(600, 2))
    groups = position_groups(np.column_stack([x, y, z]), gradients)
    group, first, z_range = groups.group, groups.first, groups.z_range
    assert np.array_equal(groups.columns, np.vstack([x[first], y[first], z[first], gradients[first].T]))
    members = {}
    for i in range(600):
        members.setdefault((x[i] + 0.0, y[i]), []).append(i)
    assert sorted(first.tolist()) == sorted(m[0] for m in members.values())
    for g, f in enumerate(first):
        rows = members[(x[f] + 0.0, y[f])]
        assert np.flatnonzero(group == g).tolist() == rows
        assert z_range[g] == max(z[rows]) - min(z[rows])
    assert np.all(np.diff(x[first]) >= 0)                     # groups in (x, y) order


@pytest.mark.parametrize("sparse, shape", [(0, "square"), (2000, "square"), (0, "corridor"), (0, "columns")])
def test_spacing_is_the_3d_tree_median_bit_for_bit(sparse, shape):
    """A sparse layer over a dense one (its plane neighbours are all in the other layer), a
    corridor along y and a grid of tied x columns (the strips' awkward shapes)."""
    from c1mesh.stages.height_field import Positions, PositionTile, kd_tree as _tree, sample_spacings

    def _spacing(x, y, z, sample):
        zero = np.zeros(len(x))
        tile = PositionTile(Positions(x, y, z, zero, zero, zero), np.arange(len(x)), np.ones(len(x), np.int64), sample)
        return float(np.median(sample_spacings(tile, 1)))
    rng = np.random.default_rng(6)
    xy = rng.random((20000 + sparse, 2))
    if shape == "corridor":
        xy[:, 0] *= 0.01
    if shape == "columns":
        xy = np.stack(np.meshgrid(np.arange(8.0), np.linspace(0, 1, 2500)), -1).reshape(-1, 2)
    z = np.sin(4 * xy[:, 0]) * 0.1 + np.cos(3 * xy[:, 1]) * 0.05
    z[:sparse] += 0.3
    pts = np.column_stack([xy, z])
    every = np.ones(len(pts), dtype=bool)
    some = np.arange(len(pts)) % 7 == 3
    for sample in (every, some):
        want = float(np.median(_tree(pts).query(pts[sample], k=2)[0][:, 1]))
        assert _spacing(pts[:, 0], pts[:, 1], pts[:, 2], sample) == want
    plane = float(np.median(_tree(pts[:, :2]).query(pts[:, :2], k=2)[0][:, 1]))
    assert _spacing(pts[:, 0], pts[:, 1], np.zeros(len(pts)), every) == plane


def _brute_stacked(xy, z, gradients, z_range, h, merge_radius, rank):
    """stacked_positions by a loop over every pair, with numpy's arithmetic."""
    m = len(z)
    bad = z_range > 3.0 * h
    parent = list(range(m))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i
    for i in range(m):
        for j in range(i + 1, m):
            d2 = (xy[i, 0] - xy[j, 0]) ** 2 + (xy[i, 1] - xy[j, 1]) ** 2
            if d2 > h * h:
                continue
            dist = np.sqrt(d2)
            slope = max(np.hypot(*gradients[i]), np.hypot(*gradients[j]))
            if abs(z[i] - z[j]) > 3.0 * h + slope * dist:
                bad[i] = bad[j] = True
            if dist <= merge_radius:
                a, b = sorted((root(i), root(j)), key=lambda r: rank[r])
                parent[b] = a
    return bad, np.array([root(i) for i in range(m)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stacked_positions_match_a_loop_over_every_pair(seed):
    """Clusters closer than the merge radius (chains too), jumps, a far outlier (wide
    strips), a lattice with distances exactly h (the squared test decides as cKDTree's)."""
    from c1mesh.stages.height_field import Positions, stacked_positions
    rng = np.random.default_rng(seed)
    lattice = np.stack(np.meshgrid(np.arange(8.0), np.arange(8.0)), -1).reshape(-1, 2) * 0.25
    xy = np.concatenate([rng.random((300, 2)) * 3, lattice + 4,
                         [[1.0, 1.0], [1.0 + 1e-3, 1.0], [1.0 + 2e-3, 1.0], [50.0, -7.0]]])
    m = len(xy)
    z = rng.normal(size=m) * 0.2
    z[:20] += 5.0                                             # a second layer: jumps
    gradients = rng.normal(size=(m, 2)) * 0.5
    z_range = np.where(rng.random(m) < 0.05, 2.0, 0.0)
    rank = rng.permutation(m)
    h = 0.25
    bad, root = stacked_positions(Positions(*xy.T, z, *gradients.T, z_range), h, merge_radius=1.5e-3, rank=rank)
    want_bad, want_root = _brute_stacked(xy, z, gradients, z_range, h, 1.5e-3, rank)
    assert np.array_equal(bad, want_bad) and bad.sum() > 20
    assert np.array_equal(root, want_root) and root[-3] == root[-4] and root[-2] == root[-4]


def test_stacked_positions_flag_pairs_that_cKDTree_finds():
    """On quantised LiDAR-like positions the pairs within h are query_pairs' pairs."""
    from c1mesh.stages.height_field import Positions, kd_tree as _tree, stacked_positions
    rng = np.random.default_rng(9)
    xy = np.unique(np.round(rng.random((4000, 2)) * 20, 2), axis=0)
    h = float(np.hypot(0.3, 0.4))
    pairs = _tree(xy).query_pairs(h, output_type="ndarray")
    z = np.zeros(len(xy))
    z[pairs[:, 0]] = 10.0 * (pairs[:, 0] % 2)               # a jump across some pairs
    want = np.zeros(len(xy), dtype=bool)
    jump = z[pairs[:, 0]] != z[pairs[:, 1]]
    want[pairs[jump].ravel()] = True
    bad, _ = stacked_positions(Positions(*xy.T, z, *np.zeros((2, len(xy))), np.zeros(len(xy))), h)
    assert np.array_equal(bad, want) and want.sum() > 100


def test_blocked_transforms_equal_one_matrix_product():
    rng = np.random.default_rng(7)
    axes = choose_frame(rng.normal(size=(50, 3)), axis="1,2,3").axes
    frame = ScanFrame(origin=[6.4e5, 8.5e5, 120.0], axes=axes)
    pts = rng.normal(size=(40000, 3)) * 100 + frame.origin        # > one block of rows
    assert np.array_equal(frame.to_local(pts), (pts - frame.origin) @ axes.T)
    assert np.array_equal(frame.vectors_to_local(pts), pts @ axes.T)
    out = np.empty_like(pts)
    assert frame.to_world(pts, out=out) is out
    assert np.array_equal(out, pts @ axes + frame.origin)
    assert np.array_equal(frame.vectors_to_world(np.asfortranarray(pts)), pts @ axes)


# ---- coordinates too large for float64 distances (issue 14) ------------------------------
@pytest.mark.parametrize("with_normals", [True, False])
def test_coordinates_near_1e155_are_an_input_error_not_an_index_error(with_normals):
    """Squared distances overflow at 1e155 and cKDTree then reports 'no neighbour' (index n);
    that must surface as an InputError naming the cause, from choose_frame and height_field."""
    pts = np.random.default_rng(0).random((200, 3)) * 1e155
    nrm = np.tile([0.0, 0.0, 1.0], (200, 1))
    with pytest.raises(InputError, match="byte order"):
        frame = choose_frame(pts, nrm if with_normals else None, "auto")
        height_field(pts, nrm, frame)


def test_a_little_endian_body_read_as_big_endian_is_an_input_error():
    """The bytes of ordinary doubles read with the wrong byte order give huge or tiny values."""
    xyz = np.random.default_rng(1).random((300, 3)) * 100 + 1000
    swapped = xyz.astype("<f8").view(">f8")
    finite = np.isfinite(swapped).all(axis=1)
    with pytest.raises(InputError, match="byte order"):
        frame = choose_frame(swapped[finite], None, "z")
        height_field(swapped[finite], np.tile([0.0, 0.0, 1.0], (int(finite.sum()), 1)), frame)


# ---- auto axis with coordinates in different units (issue 10) ------------------------------
def _lonlat_terrain(n=5000, seed=0):
    """Terrain with x, y in degrees (spread 0.02) and z in metres (spread ~60)."""
    rng = np.random.default_rng(seed)
    lon, lat = -122 + 0.02 * rng.random(n), 44 + 0.02 * rng.random(n)
    z = 120 + 30 * np.sin((lon + 122) * 300) * np.cos((lat - 44) * 200) + rng.normal(0, 0.1, n)
    return np.c_[lon, lat, z]


@pytest.mark.parametrize("with_normals", [False, True])
def test_auto_axis_survives_coordinates_in_different_units(with_normals, monkeypatch):
    """Degrees for x, y and metres for z: PCA and estimated normals point sideways; the
    auto axis must still be z. Without the unit check (monkeypatched off) it is not."""
    import c1mesh.stages.frame as frame_module
    pts = _lonlat_terrain()
    nrm = None
    if with_normals:
        from c1mesh.stages.normals import estimate_normals
        nrm = estimate_normals(pts, towards=(0.0, 0.0, 1.0))
    np.testing.assert_array_equal(choose_frame(pts, nrm).axes[2], [0.0, 0.0, 1.0])
    monkeypatch.setattr(frame_module, "UNIT_ANISOTROPY", np.inf)
    assert abs(choose_frame(pts, nrm).axes[2][2]) < 0.5


@pytest.mark.parametrize("method", ["to_local", "to_world", "vectors_to_local", "vectors_to_world"])
def test_a_row_has_the_same_bits_alone_and_inside_a_cloud(method):
    """A point transformed alone, or in a short last block, must come out with the bits it
    has inside a large cloud (issue 21: a one-row product took BLAS's matrix-vector path
    and rounded differently; --seamless -O tiles transform their border points in
    differently sized blocks)."""
    from c1mesh.stages.frame import _ROWS
    rng = np.random.default_rng(7)
    frames = [ScanFrame(LIDAR_OFFSET + rng.normal(size=3), rotation(rng.normal(size=3), rng.uniform(0.1, 3)))
              for _ in range(4)]
    rows = rng.normal(size=(2 * _ROWS + 5, 3)) * 300 + LIDAR_OFFSET
    for frame in frames:
        transform = getattr(frame, method)
        cloud = transform(rows)
        for i in [0, 1, 17, _ROWS - 1, _ROWS, 2 * _ROWS + 4]:
            assert transform(rows[i:i + 1]).tobytes() == cloud[i:i + 1].tobytes(), i
            assert transform(rows[i]).tobytes() == cloud[i].tobytes(), i
        for first, count in [(3, 2), (5, 100), (1, _ROWS + 1)]:
            assert transform(rows[first:first + count]).tobytes() == cloud[first:first + count].tobytes()
        if method.endswith("world"):                       # the world transforms take out=
            out = np.empty_like(rows)
            assert transform(rows, out=out) is out and out.tobytes() == cloud.tobytes()
