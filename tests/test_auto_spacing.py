"""--spacing auto (stages.lattice_mesh.auto_spacing): the lattice at the points' mean spacing
sqrt(box area / n), whatever a DEM's resolution, chosen alike in memory and in tiles; a bad
--spacing is one line before any input is read."""
from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from c1mesh.cli import main
from c1mesh.core.errors import InputError
from c1mesh.core.plan import TiledRun
from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit
from c1mesh.stages.lattice_mesh import auto_spacing
from test_tiled_smoothing import _terrain_las


def test_the_mean_spacing_to_two_digits():
    assert auto_spacing((0, 0), (100, 50), 5000) == 1.0                    # sqrt(5000 / 5000)
    assert auto_spacing((0, 0), (100, 60), 5000) == 1.1                    # 1.095...
    assert auto_spacing((10, 10), (13.0, 13.0), 20000) == 0.021            # 0.0212...
    with pytest.raises(InputError, match="span no area"):
        auto_spacing((0, 0), (100, 0), 50)


def _whole_and_tiled(tmp_path, points: int, seed: int, resolution: float, per_tile: int) -> tuple[dict, dict]:
    """The reports of `--smooth 3 --spacing auto` fits of a _terrain_las survey (mean spacing
    0.5) to a DEM at `resolution`, in memory and in tiles of per_tile points; asserts that
    the two DEMs have the same cells and heights within the tiled lattice fit's bound."""
    import rasterio

    source = tmp_path / "terrain.las"
    _terrain_las(source, points, seed=seed)
    options = dict(classes=(2,), smooth=3.0, spacing="auto", resolution=resolution)
    whole = fit(source, tmp_path / "whole.tif", FitOptions(**options)).report
    tiled = fit(source, tmp_path / "tiled.tif", FitOptions(**options, memory=10**9),
                tiles=TiledRun(per_tile=per_tile)).report
    a, b = (rasterio.open(tmp_path / f"{name}.tif").read(1, masked=True) for name in ("whole", "tiled"))
    np.testing.assert_array_equal(a.mask, b.mask)
    assert np.abs(a - b).max() < 0.01 * whole["smoothing"]["residual_rms"]
    return whole, tiled


def test_auto_in_tiles_chooses_the_in_memory_lattice(tmp_path):
    """12,000 points over a 54.8 m square (mean spacing 0.5): D = 0.5 in memory and in 9
    tiles, and the same DEM within the tiled lattice fit's bound."""
    whole, tiled = _whole_and_tiled(tmp_path, 12000, seed=2, resolution=0.25, per_tile=1500)
    assert tiled["tiles"] == 9
    assert whole["smoothing"]["lattice"] == tiled["smoothing"]["lattice"]
    assert whole["smoothing"]["lattice"]["spacing"] == 0.5


def test_a_coarser_resolution_keeps_the_datas_lattice(tmp_path):
    """3,000 points over a 27.4 m square (mean spacing 0.5) to a 2 m DEM: the lattice stays
    at 0.5, in memory and in tiles (a lattice at the DEM's cells fitted the terrain
    coarser: its slopes were worse, docs/smoothing.md), and the two DEMs agree."""
    whole, tiled = _whole_and_tiled(tmp_path, 3000, seed=5, resolution=2.0, per_tile=800)
    assert tiled["tiles"] > 1
    assert whole["smoothing"]["lattice"]["spacing"] == tiled["smoothing"]["lattice"]["spacing"] == 0.5


@pytest.mark.parametrize("value", ["-1", "0", "abc", "nan"])
def test_a_bad_spacing_is_one_line_and_no_output(tmp_path, value):
    out = tmp_path / "dem.tif"
    run = CliRunner().invoke(main, ["fit", str(tmp_path / "absent.las"), "-o", str(out), "--smooth", "3",
                                    "--spacing", value])
    assert run.exit_code == 2
    assert run.stderr.count("\n") == 1 and "--spacing" in run.stderr and "auto or a positive" in run.stderr
    assert not out.exists()
