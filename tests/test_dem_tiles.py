"""Issue 40: per-tile DEMs with a VRT mosaic (`--seamless -O DIR --suffix .tif --resolution R`).

Truth: the survey's one DEM (`--seamless -o`), read back by rasterio like the mosaic (GDAL
reads the VRT), and rio-cogeo's validator.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from c1mesh.cli import main

rasterio = pytest.importorskip("rasterio")
laspy = pytest.importorskip("laspy")

AUTZEN = Path(__file__).resolve().parent.parent / "data_samples" / "autzen_trim.laz"


@pytest.fixture(scope="module")
def quarters(tmp_path_factory):
    """autzen_trim's ground cut into a 2 x 2 grid of LAS files (the sample's header)."""
    folder = tmp_path_factory.mktemp("quarters")
    source = laspy.read(AUTZEN)
    ground = source.points[source.classification == 2]
    xy = np.column_stack([ground.x, ground.y])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    ij = np.minimum(((xy - lo) / (hi - lo) * 2).astype(int), 1)
    paths = []
    for i in range(4):
        part = laspy.LasData(source.header)
        part.points = ground[ij[:, 0] + 2 * ij[:, 1] == i]
        part.write(str(folder / f"q{i}.las"))
        paths.append(str(folder / f"q{i}.las"))
    return paths


def test_the_vrt_of_four_tiles_equals_the_surveys_dem_cell_for_cell(quarters, tmp_path):
    runner = CliRunner()
    out = tmp_path / "out"
    done = runner.invoke(main, ["fit", *quarters, "--seamless", "-O", str(out), "--suffix", ".tif",
                                "--resolution", "2"])
    assert done.exit_code == 0, done.output
    done = runner.invoke(main, ["fit", *quarters, "--seamless", "-o", str(tmp_path / "whole.tif"),
                                "--resolution", "2"])
    assert done.exit_code == 0, done.output
    assert sorted(p.name for p in out.iterdir()) == ["mosaic.vrt", "q0.tif", "q1.tif", "q2.tif", "q3.tif"]
    with rasterio.open(out / "mosaic.vrt") as mosaic, rasterio.open(tmp_path / "whole.tif") as whole:
        assert mosaic.transform == whole.transform and mosaic.crs == whole.crs
        assert mosaic.nodata == whole.nodata
        assert np.array_equal(mosaic.read(1), whole.read(1))
        assert (whole.read(1) != whole.nodata).sum() > 0.5 * whole.width * whole.height
        truth, res, transform = whole.read(1), whole.res[0], whole.transform
    from rio_cogeo.cogeo import cog_validate

    shared = np.zeros(truth.shape, int)
    for name in ("q0.tif", "q1.tif", "q2.tif", "q3.tif"):
        assert cog_validate(str(out / name), strict=True)[0], name
        with rasterio.open(out / name) as tile:
            assert tile.res == (res, res) and tile.transform.c % res == 0 and tile.transform.f % res == 0
            row, col = _offset(transform, tile.transform)
            window = (slice(row, row + tile.height), slice(col, col + tile.width))
            assert np.array_equal(tile.read(1), truth[window])          # each tile is the survey's cells
            shared[window] += 1
    assert (shared > 1).any()                                           # tiles overlap at their borders


def _offset(whole, tile):
    """(row, col) of a tile's north-west cell in the whole grid."""
    return round((whole.f - tile.f) / -whole.e), round((tile.c - whole.c) / whole.a)


@pytest.mark.parametrize("extra, words", [
    (["--slope", "s.tif"], "not -O"),
    (["--suffix", ".ply", "--resolution", "2"], "--suffix .tif"),
    (["--suffix", ".tif"], "need --resolution"),
])
def test_per_tile_dem_usage_errors_come_before_any_input_is_read(tmp_path, extra, words):
    args = ["fit", str(tmp_path / "a.las"), str(tmp_path / "b.las"), "--seamless", "-O", str(tmp_path / "o")]
    if "--suffix" not in extra:
        args += ["--suffix", ".tif", "--resolution", "2"]
    done = CliRunner().invoke(main, args + extra)
    assert done.exit_code == 2, done.output
    assert len([line for line in done.output.splitlines() if line.strip()]) == 1 and words in done.output
    assert list(tmp_path.iterdir()) == []
