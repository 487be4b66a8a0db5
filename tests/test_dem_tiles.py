"""Issue 40: per-tile DEMs with a VRT mosaic (`--seamless -O DIR --suffix .tif --resolution R`).

Truth: the survey's one DEM (`--seamless -o`), read back by rasterio like the mosaic (GDAL
reads the VRT), and rio-cogeo's validator.
"""
from __future__ import annotations

import json
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


SIDES = ("slope", "hillshade", "support")


@pytest.mark.parametrize("memory", [None, "1M"])
def test_the_vrts_of_four_tiles_equal_the_surveys_rasters_cell_for_cell(quarters, tmp_path, memory):
    """The DEM, slope, hillshade and support mosaics of the four quarters equal the rasters
    of `--seamless -o` (in memory) cell for cell; each tile's raster is a valid COG holding
    its window of the survey's cells, named DIR/NAME.tif and DIR/NAME.KIND.tif; the tiles
    overlap. Also beyond --memory, the survey then fitted in tiles of its own grid."""
    from rio_cogeo.cogeo import cog_validate

    runner = CliRunner()
    out = tmp_path / "out"
    args = ["fit", "--smooth", "off", *quarters, "--seamless", "--resolution", "4"]
    budget = [] if memory is None else ["--memory", memory]
    done = runner.invoke(main, [*args, "-O", str(out), "--suffix", ".tif", *budget,
                                "--report", str(tmp_path / "tiles.json"),
                                *[a for kind in SIDES for a in (f"--{kind}", str(out / f"{kind}.vrt"))]])
    assert done.exit_code == 0, done.output
    report = json.loads((tmp_path / "tiles.json").read_text())
    assert report.get("tiles", 1) > (1 if memory else 0) and len(report["raster"]["tiles"]) == 4
    done = runner.invoke(main, [*args, "-o", str(tmp_path / "dem.tif"),
                                *[a for kind in SIDES for a in (f"--{kind}", str(tmp_path / f"{kind}.tif"))]])
    assert done.exit_code == 0, done.output
    names = [f"q{i}" for i in range(4)]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["mosaic.vrt", *[f"{kind}.vrt" for kind in SIDES], *[f"{n}.tif" for n in names],
         *[f"{n}.{kind}.tif" for n in names for kind in SIDES]])
    shared = None
    for kind, mosaic_name, whole_name in [("dem", "mosaic.vrt", "dem.tif"),
                                          *[(kind, f"{kind}.vrt", f"{kind}.tif") for kind in SIDES]]:
        with rasterio.open(out / mosaic_name) as mosaic, rasterio.open(tmp_path / whole_name) as whole:
            assert mosaic.transform == whole.transform and mosaic.crs == whole.crs, kind
            assert mosaic.nodata == whole.nodata and mosaic.dtypes == whole.dtypes, kind
            truth, transform = whole.read(1), whole.transform
            assert np.array_equal(mosaic.read(1), truth), kind
            assert (truth != whole.nodata).sum() > 0.5 * truth.size, kind
        shared = np.zeros(truth.shape, int)
        for name in names:
            path = out / (f"{name}.tif" if kind == "dem" else f"{name}.{kind}.tif")
            assert cog_validate(str(path), strict=True)[0], path
            with rasterio.open(path) as tile:
                assert tile.res == whole.res and tile.transform.c % 4 == 0 and tile.transform.f % 4 == 0
                row, col = _offset(transform, tile.transform)
                window = (slice(row, row + tile.height), slice(col, col + tile.width))
                assert np.array_equal(tile.read(1), truth[window]), path   # the survey's cells
                shared[window] += 1
    assert (shared > 1).any()                                           # tiles overlap at their borders


def _offset(whole, tile):
    """(row, col) of a tile's north-west cell in the whole grid."""
    return round((whole.f - tile.f) / -whole.e), round((tile.c - whole.c) / whole.a)


@pytest.mark.parametrize("extra, words", [
    (["--slope", "s.tif"], "give a .vrt path"),
    (["--preview", "p.png"], "not -O"),
    (["--suffix", ".ply", "--resolution", "2"], "--suffix .tif"),
    (["--suffix", ".tif"], "need --resolution"),
])
def test_per_tile_dem_usage_errors_come_before_any_input_is_read(tmp_path, extra, words):
    args = ["fit", "--smooth", "off", str(tmp_path / "a.las"), str(tmp_path / "b.las"), "--seamless", "-O", str(tmp_path / "o")]
    if "--suffix" not in extra:
        args += ["--suffix", ".tif", "--resolution", "2"]
    done = CliRunner().invoke(main, args + extra)
    assert done.exit_code == 2, done.output
    assert len([line for line in done.output.splitlines() if line.strip()]) == 1 and words in done.output
    assert list(tmp_path.iterdir()) == []
