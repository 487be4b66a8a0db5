"""Synthetic LiDAR terrain files for the tests (deterministic)."""
from __future__ import annotations

import numpy as np


def write_terrain_las(path, n: int, seed: int = 0, classes=(2,), offset=(0.0, 0.0)) -> None:
    """A LAS 1.2 file of n points, about 4 per unit area, over a smooth terrain
    z = 100 + 3 sin(x/17) cos(y/23) with 2 cm Gaussian noise, millimetre scales around
    (500000, 4000000); each point's class drawn from `classes`. `offset` shifts the square
    (side sqrt(n/4)) in x and y, so files side by side make one survey."""
    import laspy

    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [500000, 4000000, 0]
    rng = np.random.default_rng(seed)
    side = np.sqrt(n / 4.0)
    x, y = rng.uniform(0, side, n) + offset[0], rng.uniform(0, side, n) + offset[1]
    z = 100 + 3 * np.sin(x / 17) * np.cos(y / 23) + rng.normal(0, 0.02, n)
    record = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    record.x, record.y, record.z = x + 500000, y + 4000000, z
    record.classification = rng.choice(np.asarray(classes, np.uint8), n)
    with laspy.open(str(path), mode="w", header=header) as writer:
        writer.write_points(record)
