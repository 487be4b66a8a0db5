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


@pytest.fixture
def dask_processes():
    """A real `dask scheduler` and two `dask worker` processes on 127.0.0.1 (the `dask`
    command next to this Python, this test's sys.path as their PYTHONPATH); yields the
    scheduler address once both workers have joined, then stops them by their pids
    (SIGINT, then SIGKILL after 30 s)."""
    pytest.importorskip("distributed")
    import os
    import signal
    import socket
    import subprocess
    import sys
    import time

    from distributed import Client

    command = Path(sys.executable).with_name("dask")
    if not command.exists():
        pytest.skip("no `dask` command next to this Python")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"env": dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)),
             "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    processes = []
    try:
        processes.append(subprocess.Popen([str(command), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                           "--dashboard-address", ":0"], **quiet))
        for _ in range(2):
            processes.append(subprocess.Popen([str(command), "worker", address, "--nthreads", "1", "--nworkers", "1",
                                               "--host", "127.0.0.1", "--no-dashboard"], **quiet))
        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
        yield address
    finally:
        for process in reversed(processes):
            process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 30
        for process in reversed(processes):
            try:
                process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
