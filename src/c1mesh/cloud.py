"""The in-memory point cloud every reader returns and the pipeline consumes."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PointCloud:
    """Scanned points in world coordinates.

    points:         (N, 3) float64, world units (metres, feet, ... as in the file).
    normals:        (N, 3) float64 or None when the file has none (not necessarily unit length).
    colors:         (N, 3) or (N, 4) uint8 RGB(A) or None.
    classification: (N,) integer LAS classification codes or None.
    extra:          other per-point fields by name, each (N,) array (kept, not interpreted).
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    classification: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def subset(self, mask: np.ndarray) -> "PointCloud":
        """Return the cloud restricted to the points where `mask` (N,) bool or index array selects."""
        pick = lambda a: None if a is None else a[mask]  # noqa: E731
        return PointCloud(
            points=self.points[mask],
            normals=pick(self.normals),
            colors=pick(self.colors),
            classification=pick(self.classification),
            extra={k: v[mask] for k, v in self.extra.items()},
        )


@dataclass
class SurfaceMesh:
    """A triangle mesh ready to write, in world coordinates.

    vertices: (M, 3) float64; faces: (K, 3) int64, counter-clockwise seen from the
    outward side; vertex_normals: (M, 3) unit float64 or None; vertex_colors: (M, 3|4)
    uint8 or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None
