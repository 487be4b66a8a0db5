"""The public face: `import c1mesh` gives the verbs and types of the README, lazily."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import c1mesh

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"


@pytest.mark.parametrize("name", c1mesh.__all__)
def test_every_public_name_resolves(name):
    assert getattr(c1mesh, name) is not None
    assert name in dir(c1mesh)


def test_every_error_class_is_a_c1mesh_error():
    for name in ("InputError", "FormatError", "NotAHeightFieldError", "DependencyError", "TileError"):
        assert issubclass(getattr(c1mesh, name), c1mesh.C1MeshError)


def test_importing_c1mesh_loads_no_numpy():
    code = "import sys, c1mesh; print('numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_fit_is_the_pipeline_verb_even_after_the_stage_package_is_imported():
    """`c1mesh.fit` is the function; no subpackage of that name may shadow it once the
    stages are imported (the stage package is c1mesh.stages)."""
    import c1mesh.stages.frame  # noqa: F401

    result = c1mesh.fit(SAMPLES / "hill.ply", None, c1mesh.FitOptions(level=2))
    cloud = c1mesh.read_cloud(SAMPLES / "hill.ply")
    assert callable(c1mesh.fit) and isinstance(result, c1mesh.FitResult)
    assert isinstance(result.mesh, c1mesh.SurfaceMesh) and isinstance(cloud, c1mesh.PointCloud)
    # every input point is a vertex of the interpolating surface, at its own height
    rows = {tuple(p) for p in np.round(result.mesh.vertices, 12)}
    assert sum(tuple(p) in rows for p in np.round(cloud.points, 12)) == len(cloud)


@pytest.mark.parametrize("level", ["a", 2.5, 0, 65, True])
def test_a_level_that_is_no_whole_number_in_range_is_an_input_error_before_reading(tmp_path, level):
    """FitOptions.level, as a library caller may set it: anything but None or a whole number
    1..64 is an InputError naming --level, raised before the input is read (the input does
    not exist) and before any output is written."""
    from c1mesh.pipeline.driver import FitOptions
    with pytest.raises(c1mesh.InputError, match="--level must be a whole number from 1 to 64"):
        c1mesh.fit(tmp_path / "missing.ply", tmp_path / "out.ply", FitOptions(level=level))
    assert not (tmp_path / "out.ply").exists()


def test_an_empty_survey_is_an_input_error(tmp_path):
    """c1mesh.fit of an empty list of inputs says there is none (it was an IndexError)."""
    with pytest.raises(c1mesh.InputError, match="at least one input"):
        c1mesh.fit([], tmp_path / "out.ply")


@pytest.mark.parametrize("sample", ["hill.ply", "autzen_trim.laz", "table_scene_mug_stereo_textured.pcd"])
def test_a_plain_fit_imports_no_scipy(tmp_path, sample):
    """An exact mesh fit of a PLY with normals, a LAS ground tile and a depth frame needs no
    scipy (its import is about 0.27 s of a command's start: core.lazy), so none is imported.
    (The LAS tile's default, the smoothing fit, needs scipy.sparse: --smooth off here.)"""
    code = ("import sys; from c1mesh.cli import main; "
            "main(['fit', '--smooth', 'off', sys.argv[1], '-o', sys.argv[2]], standalone_mode=False); "
            "print(sorted(m for m in sys.modules if m == 'scipy' or m.startswith('scipy.')))")
    out = subprocess.run([sys.executable, "-c", code, str(SAMPLES / sample), str(tmp_path / "out.ply")],
                         capture_output=True, text=True, check=True)
    assert (tmp_path / "out.ply").stat().st_size > 0
    assert out.stdout.strip().splitlines()[-1] == "[]"
