"""The tiled fit (c1mesh.tiled_fit) against the in-memory fit of the same points.

Ground truth: the in-memory stages on the whole cloud (estimate_normals, choose_frame,
height_field, delaunay, the long-edge trim, RSDInterpolator with unit-normal directions,
refinement), which never cut the survey. The tiled fit must give the same mesh: the same
vertices to rounding, the same faces (compared through the matched vertices).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

laspy = pytest.importorskip("laspy")

from click.testing import CliRunner

from c1mesh.cli import main
from c1mesh.frame import choose_frame, height_field
from c1mesh.interpolator import RSDInterpolator
from c1mesh.normals import estimate_normals
from c1mesh.pipeline import FitOptions, surface_stream
from c1mesh.tiled_fit import fit_tiled, fits_in_memory, points_per_tile
from c1mesh.triangulation import delaunay, trim

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"


def _terrain_las(path, n, seed=0, classes=(2,)):
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [500000, 4000000, 0]
    rng = np.random.default_rng(seed)
    side = np.sqrt(n / 4.0)
    x, y = rng.uniform(0, side, n), rng.uniform(0, side, n)
    z = 100 + 3 * np.sin(x / 17) * np.cos(y / 23) + rng.normal(0, 0.02, n)
    record = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    record.x, record.y, record.z = x + 500000, y + 4000000, z
    record.classification = rng.choice(np.asarray(classes, np.uint8), n)
    with laspy.open(str(path), mode="w", header=header) as writer:
        writer.write_points(record)


def _in_memory(path, classes, level):
    """The whole-cloud fit with the tiled path's reduced options (long-edge trim, no limiter)."""
    las = laspy.read(str(path))
    keep = np.isin(np.asarray(las.classification), classes)
    points = np.column_stack([las.x, las.y, las.z])[keep]
    normals = estimate_normals(points, k=16, towards=(0, 0, 1))
    frame = choose_frame(points, normals, "z")
    hf = height_field(points, normals, frame)
    triangles, report = trim(hf.xy, delaunay(hf.xy), max_edge="auto", min_circle_ratio=0.0)
    assert report.removed["bowtie"] == 0          # else the reference is not the long-edge rule
    used = np.unique(triangles)
    interp = RSDInterpolator(hf.xy[used], hf.z[used], hf.gradients[used],
                             triangles=np.searchsorted(used, triangles))
    mesh = surface_stream(interp.refinement(level), frame, None).materialize()
    return mesh, report.max_edge, len(used)


def _match(a, b):
    """(order) with b[order] == a to rounding: vertices matched by lexicographic sorting."""
    ia, ib = np.lexsort(np.round(a, 6).T[::-1]), np.lexsort(np.round(b, 6).T[::-1])
    order = np.empty(len(a), dtype=np.int64)
    order[ia] = ib
    return order


def _assert_same_mesh(path, whole):
    """The mesh file at path has whole's vertices (to rounding) and faces, each face once."""
    tiled = trimesh.load(path, process=False, force="mesh")
    vertices, faces = np.asarray(tiled.vertices, float), np.asarray(tiled.faces, np.int64)
    assert vertices.shape == whole.vertices.shape
    assert faces.shape == whole.faces.shape
    order = _match(whole.vertices, vertices)
    scale = np.abs(whole.vertices).max()
    np.testing.assert_allclose(vertices[order], whole.vertices, rtol=0, atol=1e-13 * scale)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    faces_tiled = np.sort(inverse[faces], axis=1)
    faces_whole = np.sort(whole.faces, axis=1)
    assert set(map(tuple, faces_tiled.tolist())) == set(map(tuple, faces_whole.tolist()))
    assert len(np.unique(faces_tiled, axis=0)) == len(faces_tiled)     # every face once


@pytest.mark.parametrize("level", [1, 3])
def test_tiled_fit_equals_whole_cloud_fit(tmp_path, level):
    source = tmp_path / "terrain.las"
    _terrain_las(source, 12000, classes=(2, 5))
    whole, max_edge, kept = _in_memory(source, [2], level)
    options = FitOptions(classes=(2,), overshoot="off", level=level)
    report = fit_tiled(source, tmp_path / "tiled.ply", options, memory=10**9, per_tile=700)
    assert report["tiles"] >= 9
    assert report["max_edge"] == max_edge
    _assert_same_mesh(tmp_path / "tiled.ply", whole)
    assert report["points"]["kept"] == kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["terrain.las", "tiled.ply"]   # no spill left


def test_tiled_fit_of_lidar_ground_equals_whole_fit(tmp_path):
    source = SAMPLES / "4_6_crop.las"
    whole, max_edge, kept = _in_memory(source, [2], 2)
    options = FitOptions(classes=(2,), overshoot="off", level=2)
    report = fit_tiled(source, tmp_path / "tiled.ply", options, memory=10**9, per_tile=1000)
    assert report["tiles"] == 16
    assert report["max_edge"] == max_edge
    _assert_same_mesh(tmp_path / "tiled.ply", whole)


def test_cli_fits_in_tiles_beyond_memory(tmp_path):
    source = tmp_path / "terrain.las"
    _terrain_las(source, 24000)
    whole, _, _ = _in_memory(source, [2], 2)
    args = ["fit", str(source), "--classes", "2", "-o", str(tmp_path / "out.ply"), "--level", "2",
            "--memory", "1M"]
    refused = CliRunner().invoke(main, args)
    assert refused.exit_code == 1
    assert "--overshoot off" in refused.output and "terrain.las" in refused.output
    assert not (tmp_path / "out.ply").exists()
    result = CliRunner().invoke(main, args + ["--overshoot", "off", "--report", str(tmp_path / "r.json")])
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "r.json").read_text())["tiles"] == 4      # 24000 points, >= 10000 a tile
    _assert_same_mesh(tmp_path / "out.ply", whole)


def test_memory_rule():
    assert fits_in_memory(1_000_000, 2 * 10**9)
    assert not fits_in_memory(12_000_000, 2 * 10**9)
    assert fits_in_memory(10**9, None)
    assert points_per_tile(2 * 10**9) * 1_800 * 4 <= 2 * 10**9
