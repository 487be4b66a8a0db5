"""Outputs beyond a format's 32-bit counts or indices are refused before the work (issue 35).

Ground truth: the refined counts are counted on an actual refinement (its distinct points,
the vertices its faces use, its faces), the edges of the triangulation by numpy from its
triangles; the limits are the numbers of each format's specification (int32 counts and
indices of PLY and OFF, OBJ's int32 references, STL's uint32 triangle count, glTF's uint32
indices with 2³² − 1 reserved and its uint32 lengths), written out here, not read from
the code.
"""
from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial import Delaunay

from c1mesh import RSDInterpolator
from c1mesh.cli import main
from c1mesh.core.cloud import MeshStream, PointCloud
from c1mesh.core.errors import InputError
from c1mesh.engine.refine import fewest_refined_vertices, refined_counts
from c1mesh.formats import MeshSize, check_mesh_size, write_mesh
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit

ROOT = Path(__file__).resolve().parents[1]
INT32 = 2**31 - 1
UINT32 = 2**32 - 1


def _holed_triangulation(n: int = 300, seed: int = 3):
    """Points (m, 2) and triangles (T, 3) of a Delaunay triangulation with a hole and a cut
    into two pieces, every point used: boundary, holes and pieces all count."""
    rng = np.random.default_rng(seed)
    pts = rng.random((n, 2))
    tri = Delaunay(pts).simplices
    centre = pts[tri].mean(axis=1)
    keep = (np.hypot(*(centre - 0.3).T) > 0.12) & (np.abs(centre[:, 0] - 0.7) > 0.04)
    tri = tri[keep]
    used = np.unique(tri)
    remap = np.full(n, -1)
    remap[used] = np.arange(used.size)
    return pts[used], remap[tri]


def _edge_count(triangles: np.ndarray) -> int:
    """Distinct edges of the triangles, by numpy alone (not the engine's edge table)."""
    pairs = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return len(np.unique(pairs, axis=0))


@pytest.mark.parametrize("level", [1, 2, 3, 4, 6])
def test_refined_counts_are_those_of_a_refinement(level):
    """refined_counts(points, edges, triangles, L) is the refinement's vertex and face
    count: every point of the refinement is distinct and used by a face, and there are L²
    faces per triangle; fewest_refined_vertices never exceeds it."""
    pts, tri = _holed_triangulation()
    interp = RSDInterpolator(pts, pts[:, 0] + 2 * pts[:, 1], np.tile([1.0, 2.0], (len(pts), 1)), triangles=tri)
    mesh = interp.refinement(level).mesh()
    distinct = len(np.unique(np.round(mesh.points, 12), axis=0))
    used = np.unique(mesh.triangles)
    assert distinct == len(mesh.points) == used.size and used[-1] == used.size - 1
    assert len(mesh.triangles) == len(tri) * level**2
    assert refined_counts(len(pts), _edge_count(tri), len(tri), level) == (distinct, len(mesh.triangles))
    assert fewest_refined_vertices(len(tri), level) <= distinct


def _size(vertices=0, faces=0, normals=True, channels=0):
    return MeshSize(vertices, faces, normals, channels)


def _glb_bytes(vertices, faces, normals, channels):
    """A GLB's length by the glTF layout: 12-byte header, two 8-byte chunk headers,
    float32 positions (and normals), RGB(A) padded to 4 bytes, three uint32 per face."""
    per_vertex = 12 + (12 if normals else 0) + (4 if channels else 0)
    return 28 + per_vertex * vertices + 12 * faces


def _glb_faces_at_limit(vertices, normals, channels):
    """The most faces a GLB of this many vertices holds (JSON chunk not counted)."""
    return (UINT32 - _glb_bytes(vertices, 0, normals, channels)) // 12


# (format, largest size it holds, smallest it does not, what the message counts)
EDGES = [
    ("ply", _size(INT32, 1), _size(INT32 + 1, 1), "vertices"),
    ("ply", _size(3, INT32), _size(3, INT32 + 1), "faces"),
    ("off", _size(INT32, 1), _size(INT32 + 1, 1), "vertices"),
    ("off", _size(3, INT32), _size(3, INT32 + 1), "faces"),
    ("obj", _size(INT32, 10**12), _size(INT32 + 1, 1), "vertices"),
    ("stl", _size(10**12, UINT32), _size(3, UINT32 + 1), "triangles"),
    ("glb", _size(1000, _glb_faces_at_limit(1000, True, 3), True, 3),
     _size(1000, _glb_faces_at_limit(1000, True, 3) + 1, True, 3), "bytes"),
    ("glb", _size(1000, _glb_faces_at_limit(1000, False, 0), False, 0),
     _size(1000, _glb_faces_at_limit(1000, False, 0) + 1, False, 0), "bytes"),
]


@pytest.mark.parametrize("fmt, fits, beyond, what", EDGES)
def test_each_format_holds_up_to_its_limit_and_refuses_one_more(fmt, fits, beyond, what, tmp_path):
    check_mesh_size(tmp_path / f"out.{fmt}", None, fits)
    check_mesh_size(io.BytesIO(), fmt, fits)
    with pytest.raises(InputError) as refused:
        check_mesh_size(tmp_path / f"out.{fmt}", None, beyond)
    text = str(refused.value)
    assert text.startswith(fmt.upper()) and "\n" not in text and "--level" in text
    count = {"vertices": beyond.vertex_count, "faces": beyond.face_count, "triangles": beyond.face_count,
             "bytes": _glb_bytes(beyond.vertex_count, beyond.face_count, beyond.has_normals,
                                 beyond.color_channels)}[what]
    limit = INT32 if fmt in ("ply", "off", "obj") else UINT32
    assert f"{count:,} {what} are more than {limit:,}" in text


def test_glb_indexes_2_32_minus_1_vertices_but_not_more():
    """glTF reserves the index 2³² − 1 (primitive restart): 2³² − 1 vertices (indices up to
    2³² − 2) are indexable, 2³² are not. So many vertices are past the 4 GiB length too,
    which the message then names instead: the index clause is asked first."""
    from c1mesh.formats.meshes import glb_size_problem

    assert "vertices" not in glb_size_problem(_size(UINT32, 0, False, 0))
    assert f"{UINT32 + 1:,} vertices are more than {UINT32:,}" in glb_size_problem(_size(UINT32 + 1, 0, False, 0))


def _unwritable(size: MeshSize) -> MeshStream:
    """A stream of this size whose blocks must never be asked for."""
    def never():
        raise AssertionError("the writer evaluated a block")
    return MeshStream(size.vertex_count, size.face_count, size.has_normals, size.color_channels, never, never)


@pytest.mark.parametrize("fmt, size", [(fmt, beyond) for fmt, _, beyond, _ in EDGES])
def test_writers_refuse_before_writing_a_byte(fmt, size):
    target = io.BytesIO()
    with pytest.raises(InputError):
        write_mesh(_unwritable(size), target, fmt)
    assert target.getvalue() == b""


def _plane(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2)) * 1000.0
    return np.column_stack([xy, 0.01 * xy[:, 0] + 0.02 * xy[:, 1]])


def test_fit_refuses_before_interpolating(tmp_path):
    """The in-memory fit checks once the trimmed triangulation is known: the stages up to
    triangulate finish, interpolate and refine never do, and no file is written. A GLB of
    25k points at level 64 needs ~5 GiB, beyond its uint32 length."""
    stages = []
    with pytest.raises(InputError, match=r"^GLB stores its length in a uint32"):
        fit(PointCloud(points=_plane(25_000)), tmp_path / "out.glb", FitOptions(smooth="off", axis="z", level=64),
            on_stage=stages.append)
    assert stages == ["read", "normals", "frame", "gradients", "triangulate"]
    assert os.listdir(tmp_path) == []


def _write_plane_ply(path: Path, n: int) -> None:
    """A binary PLY of n points of a tilted plane with their exact unit normals."""
    points = _plane(n, seed=1)
    normal = np.array([-0.01, -0.02, 1.0]) / np.linalg.norm([-0.01, -0.02, 1.0])
    rows = np.column_stack([points, np.tile(normal, (n, 1))]).astype("<f8")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
              + "".join(f"property double {p}\n" for p in ("x", "y", "z", "nx", "ny", "nz")) + "end_header\n")
    path.write_bytes(header.encode("ascii") + rows.tobytes())


def test_cli_refuses_an_off_too_large_for_32_bit_counts_at_once(tmp_path):
    """`c1mesh fit big.ply -o out.off --level 64` of 270k points: about 540k triangles, so
    2.2 billion faces, past OFF's 2³¹ − 1. Exit 1 within seconds (the fit itself would run
    for many minutes), one line naming the input, the format, the count and the limit, and
    nothing left in the output folder, hidden files included."""
    (tmp_path / "in").mkdir()
    (tmp_path / "out").mkdir()
    source = tmp_path / "in" / "big.ply"
    _write_plane_ply(source, 270_000)
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "c1mesh.cli", "fit", str(source), "-o",
                           str(tmp_path / "out" / "out.off"), "--level", "64"],
                          capture_output=True, text=True, env=env, timeout=120)
    seconds = time.monotonic() - start
    assert done.returncode == 1, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"c1mesh: error: {source}: OFF "), done.stderr
    count = int(re.search(r"([\d,]+) faces are more than 2,147,483,647", lines[0]).group(1).replace(",", ""))
    assert count % 64**2 == 0 and INT32 < count < 270_000 * 2 * 64**2   # L² faces per triangle, T < 2n
    assert os.listdir(tmp_path / "out") == []
    assert seconds < 30, f"refused after {seconds:.1f} s"


laspy = pytest.importorskip("laspy")


def _terrain_las(path: Path, n: int, seed: int = 0) -> None:
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [500000, 4000000, 0]
    rng = np.random.default_rng(seed)
    side = np.sqrt(n / 4.0)
    x, y = rng.uniform(0, side, n), rng.uniform(0, side, n)
    record = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    record.x, record.y = x + 500000, y + 4000000
    record.z = 100 + 3 * np.sin(x / 17) * np.cos(y / 23)
    record.classification = np.full(n, 2, np.uint8)
    with laspy.open(str(path), mode="w", header=header) as writer:
        writer.write_points(record)


def _count_refined_tiles(monkeypatch) -> list:
    import c1mesh.survey.refine_runs as refine_runs

    calls, real = [], refine_runs._refine_tile

    def counted(job, t, part):
        calls.append(t)
        return real(job, t, part)
    monkeypatch.setattr(refine_runs, "_refine_tile", counted)
    return calls


def test_tiled_fit_refuses_before_refining_a_tile(tmp_path, monkeypatch):
    """The fit beyond --memory (4 tiles) checks once its trimmed triangles are counted:
    ~48k triangles at level 64 need at least ~4.7 GB as GLB. Exit 1, one line, no tile
    refined, nothing left beside the input."""
    source = tmp_path / "terrain.las"
    _terrain_las(source, 24_000)
    calls = _count_refined_tiles(monkeypatch)
    result = CliRunner().invoke(main, ["fit", "--smooth", "off", str(source), "-o", str(tmp_path / "out.glb"), "--level", "64",
                                       "--memory", "1M", "-j", "1"])
    assert result.exit_code == 1, result.output
    assert result.output.startswith(f"c1mesh: error: {source}: GLB stores its length in a uint32")
    assert result.output.count("\n") == 1 and calls == []
    assert sorted(os.listdir(tmp_path)) == ["terrain.las"]


def test_tiled_fit_stops_at_the_first_tile_past_the_limit(tmp_path, monkeypatch):
    """Where the early bound cannot tell (here: it is switched off), the joined counts are
    checked tile by tile: with a limit of 1000 vertices the fit stops after its first tile
    (each holds ~3000 level-1 vertices), exit 1, nothing left."""
    import c1mesh.formats as formats
    import c1mesh.pipeline.bounded_fit as bounded_fit

    source = tmp_path / "terrain.las"
    _terrain_las(source, 12_000, seed=5)
    monkeypatch.setattr(bounded_fit, "_check_size", lambda *args: None)
    monkeypatch.setitem(formats._SIZE_LIMITS, "ply",
                        lambda size: f"PLY test limit: {size.vertex_count:,} vertices" if size.vertex_count > 1000
                        else None)
    calls = _count_refined_tiles(monkeypatch)
    result = CliRunner().invoke(main, ["fit", "--smooth", "off", str(source), "-o", str(tmp_path / "out.ply"), "--level", "1",
                                       "--memory", "1M", "-j", "1", "--report", str(tmp_path / "r.json")])
    assert result.exit_code == 1, result.output
    assert result.output.startswith(f"c1mesh: error: {source}: PLY test limit: ")
    assert len(calls) == 1
    assert sorted(os.listdir(tmp_path)) == ["terrain.las"]
