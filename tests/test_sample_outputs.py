"""The sha256 of every output of a fixed list of runs: the guard of every refactor.

Each run is a `c1mesh` command line on the bundled samples (the same files as
../shared/data/real/), run in a fresh folder; its outputs are hashed and compared with
tests/sample_outputs.sha256. Meshes and GeoTIFFs are hashed as bytes; a PNG as its decoded
pixels (its metadata names the matplotlib version). A change of any byte fails the test.
The runs pin OpenBLAS to its Haswell (AVX2) kernels and numpy to its AVX2 loops: both pick
their kernels by CPU at run time, and an AVX-512 kernel rounds the last bits differently
(a product in OpenBLAS; a sum in numpy, whose reductions accumulate in vector-wide
partial sums), so without the pins the list would hold only on one kind of machine. When a byte changes on purpose,
re-record the list and say in the commit which outputs changed and why:

    .venv/bin/python tests/test_sample_outputs.py --record
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from terrain_scenes import write_terrain_las

ROOT = Path(__file__).resolve().parent.parent
SAMPLES = ROOT / "data_samples"
RECORD = Path(__file__).resolve().with_name("sample_outputs.sha256")
BLAS_KERNELS = {"OPENBLAS_CORETYPE": "Haswell",     # the same BLAS bits on every x86-64 with AVX2
                # and the same numpy loops: its AVX-512 dispatch off (numpy >= 2.4 names the
                # group X86_V4; the older names are listed too, unknown names are ignored)
                "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR AVX512F AVX512CD AVX512_SKX "
                                            "AVX512_CLX AVX512_CNL AVX512_KNL AVX512_KNM"}
CROP_PARTS = tuple(f"crop{i}.las" for i in range(4))    # 4_6_crop's ground cut into 2 x 2 files
TERRAIN_PARTS = ("terrain0.las", "terrain1.las")         # 2 x 12,000 synthetic points, west and east

# name: (arguments after `c1mesh fit`, the outputs to hash); {S} is data_samples/
RUNS = {
    "hill": (["{S}/hill.ply", "-o", "hill.ply"], ["hill.ply"]),
    "hill-obj": (["{S}/hill.ply", "--level", "2", "-o", "hill.obj"], ["hill.obj"]),
    "hill-stl": (["{S}/hill.ply", "--level", "2", "-o", "hill.stl"], ["hill.stl"]),
    "hill-off": (["{S}/hill.ply", "--level", "2", "-o", "hill.off"], ["hill.off"]),
    "hill-glb": (["{S}/hill.ply", "--level", "2", "-o", "hill.glb"], ["hill.glb"]),
    "hill-ascii": (["{S}/hill.ply", "--level", "2", "--ascii", "-o", "hill_ascii.ply"], ["hill_ascii.ply"]),
    "wave": (["{S}/wave_tilted_offset.xyz", "-o", "wave.ply"], ["wave.ply"]),
    "topo": (["{S}/topo.csv", "--smooth", "off", "-o", "topo.ply"], ["topo.ply"]),
    "bunny": (["{S}/pcl_bun0.pcd", "-o", "bunny.ply"], ["bunny.ply"]),
    "crop": (["{S}/4_6_crop.las", "--classes", "2", "--smooth", "off", "-o", "crop.ply"], ["crop.ply", "crop.prj"]),
    "autzen": (["{S}/autzen_trim.laz", "--classes", "2", "--smooth", "off", "-o", "autzen.ply"],
               ["autzen.ply", "autzen.prj"]),
    "copc": (["{S}/simple.copc.laz", "--smooth", "off", "-o", "copc.ply"], ["copc.ply", "copc.prj"]),
    "mug": (["{S}/table_scene_mug_stereo_textured.pcd", "--smooth", "off", "-o", "mug.ply"], ["mug.ply"]),
    "mug-preview": (["{S}/table_scene_mug_stereo_textured.pcd", "--smooth", "off", "-o", "mug2.ply",
                     "--preview", "mug.png"], ["mug.png"]),
    "mug-default": (["{S}/table_scene_mug_stereo_textured.pcd", "-o", "mug_default.ply"], ["mug_default.ply"]),
    "autzen-terrain": (["{S}/autzen_trim.laz", "--classes", "2", "--smooth", "off", "-o", "dem.tif", "--resolution", "3",
                        "--slope", "slope.tif", "--hillshade", "hillshade.tif", "--preview", "dem.png"],
                       ["dem.tif", "slope.tif", "hillshade.tif", "dem.png"]),
    "crop-smooth": (["{S}/4_6_crop.las", "--classes", "2", "--smooth", "0.1", "-o", "crop_smooth.ply"],
                    ["crop_smooth.ply"]),
    "hill-smooth-auto": (["{S}/hill.ply", "--smooth", "auto", "-o", "hill_auto.ply"], ["hill_auto.ply"]),
    "crop-seamless": ([*CROP_PARTS, "--seamless", "--smooth", "off", "-o", "union.ply"], ["union.ply", "union.prj"]),
    "crop-seamless-O": ([*CROP_PARTS, "--seamless", "--smooth", "off", "-O", "tiles"],
                        [f"tiles/crop{i}.c1.{ext}" for i in range(4) for ext in ("ply", "prj")]),
    "terrain-memory": (["terrain.las", "--classes", "2", "--level", "2", "-o", "terrain.ply",
                        "--memory", "1M", "--smooth", "off"], ["terrain.ply"]),                   # 4 tiles
    "terrain-memory-smooth": (["terrain.las", "--classes", "2", "--level", "2", "-o", "terrain_smooth.ply",
                               "--memory", "1M", "--smooth", "1"], ["terrain_smooth.ply"]),   # Schwarz sweep
    "terrain-seamless-memory": ([*TERRAIN_PARTS, "--seamless", "--smooth", "off", "-o", "union_mem.ply",
                                 "--memory", "1M"],
                                ["union_mem.ply"]),
    "terrain-seamless-O-memory": ([*TERRAIN_PARTS, "--seamless", "--smooth", "off", "-O", "tiles_mem",
                                   "--memory", "1M"],
                                  [f"tiles_mem/terrain{i}.c1.ply" for i in range(2)]),
    # the defaults where the normals are estimated: the smoothing fit on the lattice (issue 38)
    "crop-default": (["{S}/4_6_crop.las", "--classes", "2", "-o", "crop_default.ply"], ["crop_default.ply"]),
    "autzen-terrain-default": (["{S}/autzen_trim.laz", "--classes", "2", "-o", "dem_default.tif", "--resolution",
                                "5", "--hillshade", "hillshade_default.tif"],
                               ["dem_default.tif", "hillshade_default.tif"]),
    "terrain-memory-default": (["terrain.las", "--classes", "2", "--level", "2", "-o", "terrain_default.ply",
                                "--memory", "1M"], ["terrain_default.ply"]),         # tiles
}


def write_inputs(folder: Path) -> None:
    """The generated inputs of RUNS: CROP_PARTS, terrain.las (24,000 synthetic points, more
    than --memory 1M holds) and TERRAIN_PARTS (two such files side by side)."""
    _write_crop_parts(folder)
    write_terrain_las(folder / "terrain.las", 24000)
    write_terrain_las(folder / "terrain0.las", 12000, seed=1)
    write_terrain_las(folder / "terrain1.las", 12000, seed=2, offset=(np.sqrt(3000.0), 0.0))


def _write_crop_parts(folder: Path) -> None:
    """4_6_crop's ground points (class 2) cut into a 2 x 2 grid of LAS files, each with the
    sample's header, the points in file order (deterministic)."""
    import laspy

    source = laspy.read(SAMPLES / "4_6_crop.las")
    ground = source.points[source.classification == 2]
    xy = np.column_stack([ground.x, ground.y])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    ij = np.minimum(((xy - lo) / (hi - lo) * 2).astype(int), 1)
    for i, name in enumerate(CROP_PARTS):
        part = laspy.LasData(source.header)
        part.points = ground[ij[:, 0] + 2 * ij[:, 1] == i]
        part.write(str(folder / name))


def digest(path: Path) -> str:
    """sha256 of a file's bytes; of the decoded RGBA pixels and size for a PNG."""
    if path.suffix == ".png":
        from PIL import Image

        with Image.open(path) as image:
            pixels = np.asarray(image.convert("RGBA"))
        return hashlib.sha256(repr(pixels.shape).encode() + pixels.tobytes()).hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run(name: str, folder: Path) -> dict[str, str]:
    """Run one entry of RUNS in `folder`; the digest of each of its outputs (a missing output
    is recorded as "missing", so a run that stops writing one fails the comparison)."""
    args, outputs = RUNS[name]
    command = [sys.executable, "-m", "c1mesh.cli", "fit", *(a.format(S=SAMPLES) for a in args)]
    done = subprocess.run(command, cwd=folder, capture_output=True, text=True, timeout=300,
                          env={**os.environ, **BLAS_KERNELS})
    if done.returncode != 0:
        return {"exit": f"{done.returncode}: {done.stderr.strip()[-300:]}"}
    return {out: digest(folder / out) if (folder / out).exists() else "missing" for out in outputs}


def _has_avx2() -> bool:
    """Whether this CPU can run the pinned Haswell kernels (x86-64 with AVX2)."""
    try:
        return " avx2" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


pytestmark = pytest.mark.skipif(not _has_avx2(), reason="the recorded bytes are those of OpenBLAS's "
                                "AVX2 kernels, which this CPU cannot run")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("samples")
    write_inputs(path)
    return path


def _recorded() -> dict:
    return json.loads(RECORD.read_text())


@pytest.mark.parametrize("name", sorted(RUNS))
def test_sample_output_bytes_are_unchanged(name, folder):
    assert run(name, folder) == _recorded()[name]


def test_the_record_lists_exactly_the_runs():
    assert sorted(_recorded()) == sorted(RUNS)


def record() -> None:
    """Run every entry of RUNS in a temporary folder and rewrite the record."""
    import tempfile

    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        write_inputs(folder)
        table = {name: run(name, folder) for name in sorted(RUNS)}
    RECORD.write_text(json.dumps(table, indent=1, sort_keys=True) + "\n")
    print(f"wrote {RECORD}", file=sys.stderr)


if __name__ == "__main__":
    if sys.argv[1:] != ["--record"]:
        sys.exit("usage: python tests/test_sample_outputs.py --record")
    record()
