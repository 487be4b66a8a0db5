"""benchmarks/dtm.py measures what issue 38 says: its survey is the issue's terrain, GMT reads
the points the LAZ stores, and its RMS is taken against the analytic heights."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks import dtm


def test_the_survey_is_issue_38s_terrain_and_gmt_reads_the_stored_points(tmp_path):
    import laspy

    dtm.make(tmp_path, n=4000, seed=1)
    las = laspy.read(tmp_path / "dtm.laz")
    xyz = np.fromfile(tmp_path / "dtm.bin", dtype="<f8").reshape(-1, 3)
    assert np.array_equal(xyz, np.column_stack([las.x, las.y, las.z]))
    assert (np.asarray(las.classification) == 2).all()
    assert xyz[:, :2].min() >= 0 and xyz[:, :2].max() <= dtm.SIDE
    noise = xyz[:, 2] - (100 + 30 * np.sin(xyz[:, 0] / 97) * np.cos(xyz[:, 1] / 131))
    assert abs(noise.mean()) < 0.002 and 0.018 < noise.std() < 0.022     # 2 cm, 4000 samples


@pytest.mark.parametrize("offset", [0.0, 0.05])
def test_dem_rms_is_taken_at_cell_centres_against_the_true_heights(tmp_path, offset):
    import rasterio
    from rasterio.transform import from_origin

    r = 5.0
    cols, rows = np.meshgrid(np.arange(200), np.arange(200))
    x, y = (cols + 0.5) * r, dtm.SIDE - (rows + 0.5) * r
    z = dtm.true_height(x, y) + offset
    z[0, :] = -9999.0                                    # nodata: left out
    z[100, 100] += 7.0                                   # a cell inside the margin counts
    path = tmp_path / "dem.tif"
    with rasterio.open(path, "w", driver="GTiff", width=200, height=200, count=1, dtype="float64",
                       transform=from_origin(0, dtm.SIDE, r, r), nodata=-9999.0) as out:
        out.write(z, 1)
    inside = (x >= 10) & (x <= 990) & (y >= 10) & (y <= 990)
    inside[0, :] = False
    expected = np.sqrt(((np.full(x.shape, offset) + np.where((rows == 100) & (cols == 100), 7.0, 0)) ** 2)[inside].mean())
    assert dtm.dem_rms(path) == pytest.approx(expected, rel=1e-9, abs=1e-12)
