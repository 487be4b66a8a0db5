"""The refined surface's world rows (stages.surface.world_rows, kernel stages/_surface.pyx):
world vertices and unit normals of a height field's points, values and gradients, in one
pass with the bits of the numpy composition the writers used before (frame.to_world,
height_field.gradients_to_normals, frame.vectors_to_world); and the PLY writer's one-copy
packing of such rows."""
import io

from fractions import Fraction

import numpy as np
import pytest

from c1mesh.stages.frame import ScanFrame
from c1mesh.stages.height_field import gradients_to_normals
from c1mesh.core.cloud import MeshStream
from c1mesh.formats import ply
from c1mesh.formats.ply import read_ply, write_ply
from c1mesh.stages.surface import world_rows


def _fma(a: float, b: float, c: float) -> float:
    """a * b + c rounded once (to nearest, ties to even), in exact rational arithmetic."""
    return float(Fraction(a) * Fraction(b) + Fraction(c))


def _frame(seed: int) -> ScanFrame:
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[2] *= -1
    return ScanFrame(origin=[512345.25, 4123456.5, 87.125], axes=q)


def _rows(seed: int, n: int):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 2)) * [300.0, 40.0]
    values = rng.normal(size=n) * 5.0
    gradients = rng.normal(size=(n, 2)) * rng.choice([1e-3, 0.3, 20.0], size=(n, 1))
    return points, values, gradients


def test_each_row_is_fused_multiply_adds_in_order_and_the_origin_added():
    """The documented arithmetic, row by row, with fma in exact rational arithmetic: an
    independent reference for the kernel's C code."""
    frame = _frame(1)
    points, values, gradients = _rows(2, 400)
    rows = np.empty((400, 6))
    world_rows(frame, points, values, gradients, rows)
    vertices, normals = rows[:, :3], rows[:, 3:]
    m = frame.axes
    for i in range(400):
        x, y, z = float(points[i, 0]), float(points[i, 1]), float(values[i])
        fx, fy = float(gradients[i, 0]), float(gradients[i, 1])
        inv = 1.0 / np.sqrt(fx * fx + fy * fy + 1.0)
        unit = (fx * -inv, fy * -inv, inv)
        for j in range(3):
            at = _fma(z, m[2, j], _fma(y, m[1, j], x * m[0, j]))
            assert vertices[i, j] == at + frame.origin[j]
            assert normals[i, j] == _fma(unit[2], m[2, j], _fma(unit[1], m[1, j], unit[0] * m[0, j]))


@pytest.mark.parametrize("n", [1, 5, 70_001])
def test_the_rows_equal_numpys_to_world_and_normals_bit_for_bit(n):
    """What the writers wrote before (numpy: BLAS products over blocks of rows): the same
    bytes, the first and the last rows included."""
    frame = _frame(3)
    points, values, gradients = _rows(4, n)
    rows = np.empty((n, 6))
    world_rows(frame, points, values, gradients, rows)
    vertices, normals = rows[:, :3], rows[:, 3:]
    want = frame.to_world(np.column_stack([points, values]))
    want_normals = frame.vectors_to_world(gradients_to_normals(gradients))
    assert vertices.tobytes() == want.tobytes()
    assert normals.tobytes() == want_normals.tobytes()


def test_the_normals_are_unit_and_on_the_height_axis_side():
    frame = _frame(5)
    points, values, gradients = _rows(6, 1000)
    rows = np.empty((1000, 6))
    world_rows(frame, points, values, gradients, rows)
    vertices, normals = rows[:, :3], rows[:, 3:]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=1e-14)
    assert np.all(normals @ frame.axes[2] > 0)
    local = (vertices - frame.origin) @ frame.axes.T
    np.testing.assert_allclose(local, np.column_stack([points, values]), atol=1e-9)


def _ply(blocks, faces) -> bytes:
    count = sum(len(v) for v, _, _ in blocks)
    stream = MeshStream(count, len(faces), True, 0, lambda: iter(blocks), lambda: iter([faces]))
    out = io.BytesIO()
    write_ply(stream, out)
    return out.getvalue()


def test_the_ply_of_interleaved_rows_is_the_ply_of_separate_columns():
    """stages.surface yields vertices and normals as the halves of (n, 6) rows, which the
    writer copies whole; the file is the one separate arrays give, and reads back."""
    rng = np.random.default_rng(7)
    rows = [rng.normal(size=(n, 6)) for n in (5, 1, 300)]
    faces = np.array([[0, 1, 2], [2, 3, 4]])
    halves = [(r[:, :3], r[:, 3:], None) for r in rows]
    separate = [(r[:, :3].copy(), r[:, 3:].copy(), None) for r in rows]
    dtype = np.dtype([(c, "<f8") for c in ("x", "y", "z", "nx", "ny", "nz")])
    assert all(ply._interleaved(dtype, *block) is not None for block in halves)
    assert all(ply._interleaved(dtype, *block) is None for block in separate)
    data = _ply(halves, faces)
    assert data == _ply(separate, faces)
    cloud = read_ply(data, "rows.ply")
    np.testing.assert_array_equal(cloud.points, np.vstack(rows)[:, :3])
    np.testing.assert_array_equal(cloud.normals, np.vstack(rows)[:, 3:])


def test_rows_of_mismatched_shapes_are_refused_before_the_kernel():
    frame = _frame(8)
    points, values, gradients = _rows(9, 10)
    with pytest.raises(ValueError, match="out \\(n, 6\\)"):
        world_rows(frame, points, values, gradients, np.empty((9, 6)))
    with pytest.raises(ValueError, match="values \\(n,\\)"):
        world_rows(frame, points, values[:5], gradients, np.empty((10, 6)))
