"""Normal estimation against analytic surfaces, orientation, and the missing-open3d error."""
from __future__ import annotations

import builtins
import time

import numpy as np
import pytest

from c1mesh.core.errors import DependencyError, InputError
from c1mesh.stages.normals import estimate_normals, orient_normals



def _open3d_imports() -> bool:
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError):              # OSError: a missing libusb
        return False
    return True


# only the tests that run a plane fit need Open3D; input checks, orientation and the
# missing-Open3D error are tested without it
needs_open3d = pytest.mark.skipif(not _open3d_imports(), reason="open3d does not import")


def paraboloid(n=4000, seed=0, offset=(0.0, 0.0, 0.0)):
    """Random samples of z = 0.4 (x² + y²) - 0.2 x y on [-1, 1]², and the exact unit normals."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-1, 1, (2, n))
    z = 0.4 * (x**2 + y**2) - 0.2 * x * y
    exact = np.column_stack([-(0.8 * x - 0.2 * y), -(0.8 * y - 0.2 * x), np.ones(n)])
    exact /= np.linalg.norm(exact, axis=1, keepdims=True)
    return np.column_stack([x, y, z]) + np.asarray(offset), exact


def angle_deg(a, b):
    """Angle between unit vectors row by row, ignoring sign."""
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a, b)), 0, 1)))


@needs_open3d
@pytest.mark.parametrize("offset", [(0, 0, 0), (6.4e5, 8.5e5, 420.0), (3e6, -2e6, 1e6)])
def test_normals_of_a_paraboloid_match_the_exact_ones_even_at_lidar_offsets(offset):
    pts, exact = paraboloid(offset=offset)
    n = estimate_normals(pts, k=16)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    err = angle_deg(n, exact)
    interior = np.max(np.abs(pts[:, :2] - np.asarray(offset)[:2]), axis=1) < 0.9
    assert np.median(err) < 1.0
    assert np.percentile(err[interior], 99) < 3.0
    assert err.max() < 10.0                      # one-sided neighbourhoods at the border


@needs_open3d
@pytest.mark.parametrize("towards", [(0, 0, 1), (0.3, -0.2, -1.0), (1, 0, 0)])
def test_normals_face_the_requested_side(towards):
    pts, exact = paraboloid(n=1000)
    n = estimate_normals(pts, towards=towards)
    assert np.all(n @ np.asarray(towards, float) >= 0)
    assert np.median(angle_deg(n, exact)) < 1.0


@needs_open3d
def test_per_point_directions_orient_towards_a_sensor():
    pts, exact = paraboloid(n=1000)
    sensor = np.array([0.0, 0.0, -3.0])                  # below the bowl: all see its underside
    n = estimate_normals(pts, towards=sensor - pts)
    assert np.all(np.einsum("ij,ij->i", n, sensor - pts) >= 0)
    assert np.all(n[:, 2] < 0)


@needs_open3d
def test_non_finite_points_get_nan_normals_and_do_not_disturb_the_rest():
    pts, exact = paraboloid(n=1000)
    pts[[5, 50, 500]] = [np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]
    n = estimate_normals(pts)
    assert np.all(np.isnan(n[[5, 50, 500]]))
    ok = np.ones(len(pts), bool)
    ok[[5, 50, 500]] = False
    assert np.median(angle_deg(n[ok], exact[ok])) < 1.0


@pytest.mark.parametrize("args, msg", [
    ((np.zeros((10, 2)),), "shape"),
    ((np.zeros((10, 3)), 2), "k=3"),
    ((np.array([[0, 0, 0], [1, 0, 0], [np.nan, 0, 0]], float),), "at least 3"),
    ((np.zeros((10, 3)), 16, (1, 0)), "towards"),
])
def test_bad_input_is_an_input_error(args, msg):
    with pytest.raises(InputError, match=msg):
        estimate_normals(*args)


def test_orient_normals_flips_only_the_wrong_side_and_copies():
    n = np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, -0.1]])
    out = orient_normals(n, [0, 0, 1])
    assert np.array_equal(out, [[0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 0.1]])
    assert n[1, 2] == -1.0                                  # input untouched
    per_point = orient_normals(n, -n)
    assert np.all(np.einsum("ij,ij->i", per_point, -n) >= 0)
    with pytest.raises(InputError):
        orient_normals(n, [[0, 0, 1]])


@pytest.mark.parametrize("exc", [
    OSError("libusb-1.0.so.0: cannot open shared object file: No such file or directory"),
    ImportError("No module named 'open3d'"),
])
def test_missing_open3d_is_a_dependency_error_that_says_what_to_install(monkeypatch, exc):
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "open3d" or name.startswith("open3d."):
            raise exc
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(DependencyError) as info:
        estimate_normals(paraboloid(n=50)[0])
    message = str(info.value)
    assert "libusb-1.0-0" in message and "pip install open3d" in message
    assert str(exc).split(":")[0] in message                 # the original reason, briefly
    assert "\n" not in message
    assert isinstance(info.value, ImportError)               # DependencyError is an ImportError


def test_coincident_points_are_refused_before_open3d_sees_them():
    """100k copies of one point made Open3D's neighbour search quadratic (> 30 s)."""
    start = time.perf_counter()
    with pytest.raises(InputError, match="only 1 distinct positions"):
        estimate_normals(np.tile([[1.0, 2.0, 3.0]], (100_000, 1)))
    assert time.perf_counter() - start < 5.0


def test_repeated_positions_share_the_normal_of_their_plane():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1, 1, (2000, 2))
    plane = np.column_stack([xy, 0.5 * xy[:, 0] - 0.25 * xy[:, 1]])  # z = x/2 - y/4
    pts = np.concatenate([plane, plane[:500], plane[:500]])           # 1000 exact repeats
    normals = estimate_normals(pts)
    exact = np.array([-0.5, 0.25, 1.0]) / np.linalg.norm([-0.5, 0.25, 1.0])
    np.testing.assert_allclose(normals, np.tile(exact, (len(pts), 1)), atol=1e-9)


def test_unique_positions_is_exact_and_merges_signed_zeros():
    from c1mesh.stages.normals import unique_positions

    rng = np.random.default_rng(4)
    base = rng.normal(size=(300, 3))
    pts = np.concatenate([base, base[::-1], [[0.0, 0.0, 0.0], [-0.0, 0.0, -0.0]]])
    distinct, inverse = unique_positions(pts)
    assert len(distinct) == 301
    np.testing.assert_array_equal(distinct[inverse], pts + 0.0)
    reference = np.unique(pts + 0.0, axis=0)
    np.testing.assert_array_equal(np.unique(distinct, axis=0), reference)
