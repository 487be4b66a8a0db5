"""Synthetic LiDAR terrain files for the tests (deterministic)."""
from __future__ import annotations

import numpy as np


def write_terrain_las(path, n: int, seed: int = 0, classes=(2,), offset=(0.0, 0.0)) -> None:
    """A LAS 1.2 file of n points, about 4 per unit area, over a smooth terrain
    z = 100 + 3 sin(x/17) cos(y/23) with 2 cm Gaussian noise, millimetre scales around
    (500000, 4000000); each point's class drawn from `classes`. `offset` shifts the square
    (side sqrt(n/4)) in x and y, so files side by side make one survey."""
    rng = np.random.default_rng(seed)
    side = np.sqrt(n / 4.0)
    x, y = rng.uniform(0, side, n) + offset[0], rng.uniform(0, side, n) + offset[1]
    z = 100 + 3 * np.sin(x / 17) * np.cos(y / 23) + rng.normal(0, 0.02, n)
    write_points_las(path, np.column_stack([x, y, z]), rng.choice(np.asarray(classes, np.uint8), n))


def write_points_las(path, points: np.ndarray, classes=2, z_scale: float = 0.001) -> None:
    """A LAS 1.2 file of points (n, 3) moved by (500000, 4000000, 0), x and y at millimetre
    scale, z at z_scale; classes: each point's class (n,), or one for all."""
    import laspy

    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001, 0.001, z_scale], [500000, 4000000, 0]
    record = laspy.ScaleAwarePointRecord.zeros(len(points), header=header)
    record.x, record.y, record.z = points[:, 0] + 500000, points[:, 1] + 4000000, points[:, 2]
    record.classification = np.broadcast_to(np.asarray(classes, np.uint8), (len(points),))
    with laspy.open(str(path), mode="w", header=header) as writer:
        writer.write_points(record)
