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

import numpy as np
import pytest
from scipy.spatial import Delaunay

from c1mesh import RSDInterpolator
from c1mesh.core.cloud import MeshStream
from c1mesh.core.errors import InputError
from c1mesh.engine.refine import fewest_refined_vertices, refined_counts
from c1mesh.formats import MeshSize, check_mesh_size, write_mesh

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
