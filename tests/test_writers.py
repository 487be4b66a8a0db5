"""The mesh writers (PLY binary and ASCII, OBJ, OFF, STL, GLB) checked by an independent
reader, trimesh, and their memory checked to stay bounded whatever the output's size.

Truth: an analytic mesh (a paraboloid patch on a regular grid, with its exact unit
normals and a colour pattern) written in every format and read back by trimesh's own
loaders; a streamed mesh must give the same bytes as the mesh in memory. Memory: the
writers stream (issue 21: `--level 64` to OBJ reached 2 GB from a 19 KB input), so the
peak a write allocates must not grow with the output, except for what a format must hold
(STL: the vertex positions, since a face may name any vertex).
"""
from __future__ import annotations

import inspect
import io
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import trimesh
from trimesh.exchange import gltf as tm_gltf
from trimesh.exchange import obj as tm_obj
from trimesh.exchange import ply as tm_ply
from trimesh.exchange import stl as tm_stl

from c1mesh.core.cloud import MeshStream, SurfaceMesh
from c1mesh.formats import write_mesh

ROOT = Path(__file__).resolve().parent.parent
FORMATS = ("ply", "ascii.ply", "obj", "off", "stl", "glb")
OFFSET = np.array([512_000.5, 4_100_000.25, 80.0])    # world coordinates, as a survey has


def paraboloid(nx: int = 7, ny: int = 5) -> SurfaceMesh:
    """z = 0.3 x² − 0.2 x y + 0.1 y² over [-1, 1]², moved to OFFSET: vertices on the grid,
    two counter-clockwise triangles per cell, exact unit normals (−z_x, −z_y, 1)/|…| and
    RGB colours that differ between neighbours."""
    x, y = np.meshgrid(np.linspace(-1, 1, nx), np.linspace(-1, 1, ny))
    x, y = x.ravel(), y.ravel()
    z = 0.3 * x * x - 0.2 * x * y + 0.1 * y * y
    normals = np.column_stack([-(0.6 * x - 0.2 * y), -(-0.2 * x + 0.2 * y), np.ones_like(x)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colors = (np.arange(x.size * 3).reshape(-1, 3) * 37 % 256).astype(np.uint8)
    cells = [(j * nx + i) for j in range(ny - 1) for i in range(nx - 1)]
    faces = np.array([[a, a + 1, a + nx + 1] for a in cells] + [[a, a + nx + 1, a + nx] for a in cells])
    return SurfaceMesh(np.column_stack([x, y, z]) + OFFSET, faces, normals, colors)


def reused_buffer_stream(mesh: SurfaceMesh, rows: int) -> MeshStream:
    """`mesh` as a MeshStream of `rows`-row blocks that are copies into one buffer per
    array, overwritten by the next block (as refine.py's streams do)."""
    def vertex_blocks():
        v, n, c = np.empty((rows, 3)), np.empty((rows, 3)), np.empty((rows, 3), np.uint8)
        for start in range(0, len(mesh.vertices), rows):
            k = len(mesh.vertices[start:start + rows])
            v[:k], n[:k], c[:k] = (a[start:start + rows] for a in
                                   (mesh.vertices, mesh.vertex_normals, mesh.vertex_colors))
            yield v[:k], n[:k], c[:k]

    def face_blocks():
        buffer = np.empty((rows, 3), np.int32)
        for start in range(0, len(mesh.faces), rows):
            k = len(mesh.faces[start:start + rows])
            buffer[:k] = mesh.faces[start:start + rows]
            yield buffer[:k]
    return MeshStream(len(mesh.vertices), len(mesh.faces), True, 3, vertex_blocks, face_blocks)


def written(mesh, fmt: str) -> bytes:
    """The bytes write_mesh writes for `mesh` in format `fmt` ('ascii.ply': ASCII PLY)."""
    out = io.BytesIO()
    write_mesh(mesh, out, fmt.split(".")[-1], ascii=fmt == "ascii.ply")
    return out.getvalue()


def _load(data: bytes, fmt: str) -> trimesh.Trimesh:
    return trimesh.load(io.BytesIO(data), file_type=fmt.split(".")[-1], process=False, force="mesh")


# ----------------------------------------------------------------- read back by trimesh
@pytest.mark.parametrize("fmt", ["ply", "ascii.ply", "obj", "off"])
def test_exact_formats_read_back_by_trimesh(fmt):
    """PLY and OBJ/OFF text keep every double: trimesh reads the same vertices and faces."""
    mesh = paraboloid()
    loaded = _load(written(mesh, fmt), fmt)
    np.testing.assert_array_equal(loaded.vertices, mesh.vertices)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    if fmt != "off":                            # plain OFF has no colours
        np.testing.assert_array_equal(loaded.visual.vertex_colors[:, :3], mesh.vertex_colors)


def test_ply_normals_read_back_by_trimesh():
    for fmt in ("ply", "ascii.ply"):
        raw = tm_ply.load_ply(io.BytesIO(written(paraboloid(), fmt)))
        np.testing.assert_array_equal(raw["vertex_normals"], paraboloid().vertex_normals)


def test_obj_normals_read_back_by_trimesh():
    raw = tm_obj.load_obj(io.BytesIO(written(paraboloid(), "obj")), maintain_order=True)
    (geometry,) = raw["geometry"].values()
    np.testing.assert_array_equal(geometry["vertex_normals"], paraboloid().vertex_normals)


def test_stl_read_back_by_trimesh():
    """STL: float32 corners of every face, and its facet normal (the right-hand normal of
    the triangle, computed here in float64 from the doubles) to float32 precision."""
    mesh = paraboloid()
    raw = tm_stl.load_stl(io.BytesIO(written(mesh, "stl")))
    corners = mesh.vertices[mesh.faces]
    np.testing.assert_array_equal(raw["vertices"][raw["faces"]], corners.astype(np.float32))
    right_hand = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    right_hand /= np.linalg.norm(right_hand, axis=1, keepdims=True)
    np.testing.assert_allclose(raw["face_normals"], right_hand, atol=2e-7)
    assert (right_hand[:, 2] > 0).all()        # counter-clockwise seen from above: up


def test_glb_read_back_by_trimesh():
    """GLB: world positions (float32 offsets + the node's translation, applied by trimesh)
    within float32 precision of the mesh's half extent, normals to float32, colours exact."""
    mesh = paraboloid()
    data = written(mesh, "glb")
    loaded = _load(data, "glb")
    np.testing.assert_allclose(loaded.vertices, mesh.vertices, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    np.testing.assert_array_equal(loaded.visual.vertex_colors,
                                  np.column_stack([mesh.vertex_colors, np.full(len(mesh.vertices), 255)]))
    raw = tm_gltf.load_glb(io.BytesIO(data))
    (geometry,) = raw["geometry"].values()
    np.testing.assert_allclose(geometry["vertex_normals"], mesh.vertex_normals, rtol=0, atol=1e-7)


@pytest.mark.parametrize("fmt", FORMATS)
def test_streamed_mesh_writes_the_bytes_of_the_mesh_in_memory(fmt):
    """A MeshStream of 4-row blocks in reused buffers (and int32 faces) writes exactly the
    bytes of the whole SurfaceMesh: blocks are written in order, none is overwritten
    before it is written, and a second pass (OBJ normals, GLB attributes) starts afresh."""
    mesh = paraboloid()
    assert written(reused_buffer_stream(mesh, 4), fmt) == written(mesh, fmt)


@pytest.mark.parametrize("fmt", FORMATS)
def test_empty_mesh_is_read_back_by_trimesh_as_empty(fmt):
    empty = SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3)), None)
    data = written(empty, fmt)
    assert data and written(empty.stream(), fmt) == data
    if fmt not in ("stl", "glb"):               # trimesh refuses these without triangles
        assert len(_load(data, fmt).vertices) == 0


# ---------------------------------------------------------------------------- memory
class _Sink:
    """A binary output that counts the bytes written and keeps none of them."""

    def __init__(self):
        self.size = 0

    def write(self, data) -> int:
        self.size += memoryview(data).nbytes
        return memoryview(data).nbytes

    def flush(self) -> None:
        pass


def grid_stream(n: int, block: int = 4096) -> MeshStream:
    """An n × n vertex grid (paraboloid heights, exact normals, colours) as a MeshStream
    computed `block` vertices (and faces) at a time into reused buffers, as refine.py's
    streams are: a stream of any size from a few blocks of memory."""
    x = np.linspace(-1.0, 1.0, n)
    cells = (n - 1) ** 2

    def vertex_blocks():
        v, normals, colors = np.empty((block, 3)), np.empty((block, 3)), np.empty((block, 3), np.uint8)
        for first in range(0, n * n, block):
            index = np.arange(first, min(first + block, n * n))
            k = len(index)
            v[:k, 0], v[:k, 1] = x[index % n], x[index // n]
            v[:k, 2] = 0.3 * v[:k, 0] ** 2 + 0.1 * v[:k, 1] ** 2
            normals[:k] = np.column_stack([-0.6 * v[:k, 0], -0.2 * v[:k, 1], np.ones(k)])
            normals[:k] /= np.linalg.norm(normals[:k], axis=1, keepdims=True)
            colors[:k] = (index[:, None] * (1, 3, 7) % 256).astype(np.uint8)
            yield v[:k], normals[:k], colors[:k]

    def face_blocks():
        for first in range(0, 2 * cells, block):      # the lower triangles of all cells, then the upper
            index = np.arange(first, min(first + block, 2 * cells))
            cell = index % cells
            a = cell // (n - 1) * n + cell % (n - 1)
            upper = index >= cells
            yield np.column_stack([a, np.where(upper, a + n + 1, a + 1), np.where(upper, a + n, a + n + 1)])
    return MeshStream(n * n, 2 * cells, True, 3, vertex_blocks, face_blocks)


_PEAKS_IMPORTS = """
import json, sys
import numpy as np
from c1mesh.core.cloud import MeshStream
from c1mesh.formats import write_mesh
"""

_PEAKS_MEASURED = """
def peak_rss():
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmHWM"))

results = {}
for fmt, n in json.loads(sys.argv[1]).items():
    with open("/proc/self/clear_refs", "w") as clear:
        clear.write("5")                   # the peak RSS restarts from the current RSS
    before, sink = peak_rss(), _Sink()
    write_mesh(grid_stream(n), sink, fmt.split(".")[-1], ascii=fmt == "ascii.ply")
    results[fmt] = (peak_rss() - before, sink.size)
print(json.dumps(results))
"""

GRID_SIDE = {"ply": 600, "stl": 600, "glb": 600, "ascii.ply": 250, "obj": 250, "off": 400}
"""Vertices a side of the written grid: 360,000 for the fast binary writers, fewer for text;
each output is larger than its bound below."""

HELD_PER_VERTEX = {"stl": 24}
"""Bytes a writer must hold per vertex: STL the float64 positions (a face may name any
vertex); every other format nothing."""

BLOCKS_HELD = 8 << 20
"""Bytes of blocks a writer may hold whatever the output's size: formats/_background.py
queues 4 chunks (at most 0.8 MB each: 2^14 STL records), plus the temporaries of the
chunk being made (2^12 text rows as Python floats and strings, or STL corners, ~3 MB)."""


@pytest.fixture(scope="module")
def write_peaks() -> dict:
    """{format: (rise of the peak RSS while writing its grid to a sink, bytes written)},
    measured in one fresh process, the peak reset before each format (Linux clear_refs)."""
    if not os.access("/proc/self/clear_refs", os.W_OK):
        pytest.skip("needs Linux /proc/self/clear_refs to reset the peak RSS")
    script = _PEAKS_IMPORTS + inspect.getsource(_Sink) + inspect.getsource(grid_stream) + _PEAKS_MEASURED
    run = subprocess.run([sys.executable, "-c", script, json.dumps(GRID_SIDE)], capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=str(ROOT / "src")), timeout=300)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


@pytest.mark.parametrize("fmt", FORMATS)
def test_writing_memory_does_not_grow_with_the_output(fmt, write_peaks):
    """Writing a streamed grid raises the peak RSS by no more than a few blocks plus what
    the format must hold per vertex, for an output larger than that bound; assembling the
    mesh, as write_mesh did for every format but PLY, holds ~100 bytes a vertex and the
    text or records of the whole file."""
    rise, size = write_peaks[fmt]
    allowed = BLOCKS_HELD + HELD_PER_VERTEX.get(fmt.split(".")[-1], 0) * GRID_SIDE[fmt] ** 2
    assert size > allowed                              # holding the output would break the bound
    assert rise <= allowed, (rise / 2**20, size / 2**20)


# Levels of data_samples/hill.ply (144 KB) whose output is over 200 MB in each format.
CLI_LEVELS = {"obj": 18, "off": 26, "stl": 27, "glb": 38, "ascii.ply": 21}
RSS_BOUND = 300 << 20


# The child's own peak: Linux carries a parent's ru_maxrss into its children (a pytest
# process grown to 2 GB made every child report 2 GB), so the peak is reset at the start
# (clear_refs 5) and read as VmHWM, this process's high-water mark.
_MEASURE = """
import os, sys
with open("/proc/self/clear_refs", "w") as reset:
    reset.write("5")
from c1mesh.cli import main
try:
    main.main(sys.argv[1:], prog_name="c1mesh")
except SystemExit as exc:
    code = exc.code
finally:
    with open("/proc/self/status") as status:
        peak = next(line.split()[1] for line in status if line.startswith("VmHWM:"))
    os.write(2, b"maxrss_kb %d" % int(peak))
"""


@pytest.mark.slow
@pytest.mark.parametrize("fmt", sorted(CLI_LEVELS))
def test_cli_peak_memory_is_bounded_for_a_200_MB_output(fmt, tmp_path):
    """`c1mesh fit hill.ply --level L -o FIFO.ext`: the output (counted from the FIFO,
    nothing on disk) is over 200 MB and the fit's peak RSS stays under 300 MB + the input."""
    source = ROOT / "data_samples" / "hill.ply"
    fifo = tmp_path / f"out.{fmt.split('.')[-1]}"
    os.mkfifo(fifo)
    counted = []
    reader = threading.Thread(target=lambda: counted.append(_count_bytes(fifo)))
    reader.start()
    extra = ["--ascii"] if fmt == "ascii.ply" else []
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    run = subprocess.run([sys.executable, "-c", _MEASURE, "fit", str(source), "--level", str(CLI_LEVELS[fmt]),
                          *extra, "-o", str(fifo)], env=env, capture_output=True, text=True, timeout=600)
    if reader.is_alive():                       # the fit failed before opening its output
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    reader.join()
    assert run.returncode == 0, run.stderr
    peak = int(run.stderr.rsplit("maxrss_kb ", 1)[1]) * 1024
    assert counted[0] > 200e6
    assert peak < RSS_BOUND + source.stat().st_size, (peak / 2**20, counted[0] / 2**20)


def _count_bytes(path: Path) -> int:
    total = 0
    with open(path, "rb") as stream:
        while chunk := stream.read(1 << 20):
            total += len(chunk)
    return total
