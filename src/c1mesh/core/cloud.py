"""The in-memory point cloud every reader returns and the pipeline consumes."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np


@dataclass
class PointCloud:
    """Scanned points in world coordinates.

    points:         (N, 3) float64, world units (metres, feet, ... as in the file).
    normals:        (N, 3) float64 or None when the file has none (not necessarily unit length).
    colors:         (N, 3) or (N, 4) uint8 RGB(A) or None.
    classification: (N,) integer LAS classification codes or None.
    extra:          other per-point fields by name, each (N,) array (kept, not interpreted).
    crs:            WKT2 of the coordinate reference system the file declares, or None.
    grid_shape:     (height, width) when the points are an organised scan (pixels row by
                    row, N = height * width, invalid pixels non-finite), else None.
    viewpoint:      (7,) sensor position x, y, z and orientation quaternion qw, qx, qy, qz
                    in world coordinates when the file gives one (PCD VIEWPOINT), else None.
    height_column:  the header name of the column read as points[:, 2] when the file names
                    it as a height (a text table's z, elev, elevation, height, h, alt or
                    altitude), else None. Such heights need not share the units of x and y
                    (R's `topo`: x, y in 50 ft, z in ft), so the fit takes them as heights
                    over the plan (x, y) instead of angles in one 3-D metric.
    selection:      how the fit chose these points from a LAS/LAZ file's (the report's
                    "classes": the codes kept, and whether from the file, an option or
                    the ground filter: c1mesh.stages.ground.choose_points), else None.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    classification: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    crs: str | None = None
    grid_shape: tuple[int, int] | None = None
    viewpoint: np.ndarray | None = None
    height_column: str | None = None
    selection: dict | None = None

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
            crs=self.crs,
            viewpoint=self.viewpoint,        # a subset is no longer a grid
            height_column=self.height_column,
            selection=self.selection,
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

    def stream(self, block: int = 1 << 18) -> "MeshStream":
        """This mesh as a MeshStream of `block`-row slices (views, nothing copied)."""
        def vertex_blocks():
            for start in range(0, len(self.vertices), block):
                part = slice(start, start + block)
                yield (self.vertices[part],
                       None if self.vertex_normals is None else self.vertex_normals[part],
                       None if self.vertex_colors is None else self.vertex_colors[part])

        def face_blocks():
            for start in range(0, len(self.faces), block):
                yield np.asarray(self.faces[start:start + block]).reshape(-1, 3)
        return MeshStream(len(self.vertices), len(self.faces), self.vertex_normals is not None,
                          0 if self.vertex_colors is None else int(self.vertex_colors.shape[1]),
                          vertex_blocks, face_blocks)


@dataclass
class MeshStream:
    """A mesh delivered in blocks, in file order, so it can be written without being held.

    vertex_blocks() yields (vertices (n, 3) float64, normals (n, 3) or None, colors (n, c)
    uint8 or None) with c = color_channels; face_blocks() yields faces (k, 3) integer
    arrays. Each call starts a fresh pass; yielded arrays may be buffers that the next
    block overwrites.
    """

    vertex_count: int
    face_count: int
    has_normals: bool
    color_channels: int
    vertex_blocks: Callable[[], Iterator[tuple]]
    face_blocks: Callable[[], Iterator[np.ndarray]]

    def materialize(self) -> SurfaceMesh:
        """Run both passes into full arrays (int64 faces unless int32 blocks were given)."""
        vertices = np.empty((self.vertex_count, 3))
        normals = np.empty((self.vertex_count, 3)) if self.has_normals else None
        colors = np.empty((self.vertex_count, self.color_channels), np.uint8) if self.color_channels else None
        start = 0
        for v, n, c in self.vertex_blocks():
            part = slice(start, start + len(v))
            vertices[part] = v
            if normals is not None:
                normals[part] = n
            if colors is not None:
                colors[part] = c
            start = part.stop
        faces, start = None, 0
        for block in self.face_blocks():
            if faces is None:
                faces = np.empty((self.face_count, 3), dtype=block.dtype)
            faces[start:start + len(block)] = block
            start += len(block)
        if faces is None:
            faces = np.empty((0, 3), dtype=np.int64)
        return SurfaceMesh(vertices, faces, normals, colors)
