"""Fixtures shared by several test modules."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"


class GroundParts:
    """The ground points (class 2) of a LAS sample and a writer of chosen rows of them.

    xyz: (n, 3) scaled coordinates of the ground points, in file order.
    write(path, rows, epsg=None) writes the ground points `rows` (a boolean mask or an
    index array, whose order is kept) to a LAS file with the sample's header (its scales,
    offsets and CRS), or with a fresh header declaring EPSG code `epsg` instead; returns
    the path as a string (what the CLI takes).
    """

    def __init__(self, path: Path):
        import laspy

        self._laspy = laspy
        self._source = laspy.read(path)
        self._ground = self._source.points[self._source.classification == 2]
        self.xyz = np.column_stack([self._ground.x, self._ground.y, self._ground.z])

    def write(self, path, rows, epsg: int | None = None) -> str:
        part = self._laspy.LasData(self._source.header if epsg is None else self._header(epsg))
        part.points = self._ground[rows]
        part.write(str(path))
        return str(path)

    def _header(self, epsg: int):
        import pyproj

        source = self._source.header
        header = self._laspy.LasHeader(point_format=source.point_format, version=source.version)
        header.scales, header.offsets = source.scales, source.offsets
        header.add_crs(pyproj.CRS.from_epsg(epsg))
        return header


@pytest.fixture
def crop_ground():
    """GroundParts of data_samples/4_6_crop.las (9003 ground points, EPSG:2903)."""
    pytest.importorskip("laspy")
    return GroundParts(SAMPLES / "4_6_crop.las")
