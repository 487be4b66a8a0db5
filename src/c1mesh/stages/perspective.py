"""The perspective frame: a scan seen from one viewpoint as inverse depth over the view rays.

A depth camera or range scanner sees every point along a ray from its viewpoint. In
camera coordinates (viewpoint at the origin, looking along +z) a point (x, y, z) has the
ray parameters u = x/z, v = y/z and the inverse depth w = 1/z. The scan is a height field
w(u, v) over the rays even where it is no height field over any plane (a room corner,
the inside of a pipe), and a plane is *affine* in (u, v) that way, so a scheme that
reproduces affine functions reproduces planes exactly. See "The perspective frame" in
docs/perspective.md for the derivation of

    ∇w = (n_x, n_y) · w / (n · (u, v, 1))          (a normal n in camera coordinates)
    n  ∝ -(w_u, w_v, w - u w_u - v w_v)            (the normal back from the gradient)

`PerspectiveFrame` has the interface of frame.ScanFrame that the pipeline uses: local
coordinates are (u, v, w), `to_world` maps (u, v, w) ↦ (u, v, 1)/w, and
`normals_from_gradients` gives world normals from the spline's gradients.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from c1mesh.core.errors import InputError

FRAMES = ("auto", "axis", "perspective")


@dataclass
class PerspectiveFrame:
    """A viewpoint and the camera's orientation in the world.

    origin:   (3,) the viewpoint in world coordinates.
    rotation: (3, 3) camera-to-world rotation: world = rotation @ camera + origin; its
              columns are the camera's x, y (image right, down) and z (viewing) axes.
    """

    origin: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        r = self.rotation
        if not np.isfinite(self.origin).all() or not np.allclose(r @ r.T, np.eye(3), atol=1e-9) \
                or np.linalg.det(r) <= 0:
            raise InputError("a viewpoint needs a finite position and a rotation (unit quaternion)")

    @property
    def axes(self) -> np.ndarray:
        """Rows: the camera axes in world coordinates (as ScanFrame.axes, e3 = viewing direction)."""
        return self.rotation.T

    def to_camera(self, points: ArrayLike) -> np.ndarray:
        """World points (N, 3) -> camera coordinates (N, 3)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.rotation

    def vectors_to_local(self, vectors: ArrayLike) -> np.ndarray:
        """World directions (N, 3) -> camera components (N, 3)."""
        return np.asarray(vectors, dtype=np.float64) @ self.rotation

    def to_local(self, points: ArrayLike) -> np.ndarray:
        """World points (N, 3) -> (u, v, w) = (x/z, y/z, 1/z) in camera coordinates.

        Points at or behind the viewpoint (z <= 0) give non-finite or negative w.
        """
        cam = self.to_camera(points)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = 1.0 / cam[:, 2]
            return np.column_stack([cam[:, 0] * w, cam[:, 1] * w, w])

    def to_world(self, local: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """(u, v, w) (N, 3) -> world points (N, 3) = rotation @ (u, v, 1)/w + origin.

        Defined where w > 0 (in front of the viewpoint); ``out`` receives the result.
        """
        uvw = np.asarray(local, dtype=np.float64)
        z = 1.0 / uvw[:, 2]
        cam = np.empty_like(uvw)
        np.multiply(uvw[:, 0], z, out=cam[:, 0])
        np.multiply(uvw[:, 1], z, out=cam[:, 1])
        cam[:, 2] = z
        result = np.matmul(cam, self.rotation.T, out=out)
        result += self.origin
        return result

    def vectors_to_world(self, vectors: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Camera directions (N, 3) -> world components (N, 3), into ``out`` if given."""
        return np.matmul(np.asarray(vectors, dtype=np.float64), self.rotation.T, out=out)

    def normals_from_gradients(self, local: np.ndarray, gradients: np.ndarray,
                               out: np.ndarray | None = None) -> np.ndarray:
        """Unit world normals (N, 3) facing the viewpoint, of the surface w(u, v).

        local: (N, 3) (u, v, w); gradients: (N, 2) (w_u, w_v). The tangent plane of
        X(u, v) = (u, v, 1)/w is n·X = 1 with n = (w_u, w_v, w - u w_u - v w_v) in camera
        coordinates (docs/perspective.md); -n faces the viewpoint.
        """
        u, v, w = local[:, 0], local[:, 1], local[:, 2]
        gu, gv = gradients[:, 0], gradients[:, 1]
        cam = np.empty((local.shape[0], 3))
        x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
        np.multiply(u, gu, out=z)
        z += v * gv
        z -= w
        np.negative(gu, out=x)
        np.negative(gv, out=y)
        length = x * x
        length += y * y
        length += z * z
        np.sqrt(length, out=length)
        np.divide(1.0, length, out=length)
        cam *= length[:, None]
        return self.vectors_to_world(cam, out=out)


def inverse_depth_gradients(uvw: np.ndarray, camera_normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """∇w (N, 2) from camera-frame normals (N, 3) at points (u, v, w) (N, 3), and cos(view angle).

    ∇w = (n_x, n_y) w / (n·(u, v, 1)); the sign of n cancels. The second result (N,) is
    |cos| of the angle between the normal and the view ray: 0 where the surface is seen
    edge-on (the gradient is then infinite).
    """
    n = camera_normals
    ray_dot = n[:, 0] * uvw[:, 0] + n[:, 1] * uvw[:, 1] + n[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = uvw[:, 2] / ray_dot
        gradients = np.column_stack([n[:, 0] * scale, n[:, 1] * scale])
        ray_len = np.sqrt(uvw[:, 0] ** 2 + uvw[:, 1] ** 2 + 1.0)
        cosine = np.abs(ray_dot) / (ray_len * np.linalg.norm(n, axis=1))
    return gradients, cosine


def quaternion_matrix(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    """Rotation matrix (3, 3) of the quaternion (qw, qx, qy, qz), normalised first."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm == 0.0:
        raise InputError(f"the viewpoint orientation {q.tolist()} is not a rotation (zero or non-finite quaternion)")
    w, x, y, z = q / norm
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def parse_viewpoint(value: str | ArrayLike | None) -> np.ndarray | None:
    """'x,y,z[,qw,qx,qy,qz]' (or a sequence) -> (7,) position + quaternion; None stays None."""
    if value is None:
        return None
    try:
        parts = [float(p) for p in value.split(",")] if isinstance(value, str) else \
            [float(p) for p in np.asarray(value, dtype=np.float64).ravel()]
    except ValueError:
        parts = []
    if len(parts) not in (3, 7) or not np.isfinite(parts).all():
        raise InputError(f"a viewpoint is x,y,z or x,y,z,qw,qx,qy,qz (7 numbers), got {value!r}")
    return np.array(parts + [1.0, 0.0, 0.0, 0.0] if len(parts) == 3 else parts)


def frame_from_viewpoint(viewpoint: np.ndarray | None) -> PerspectiveFrame:
    """The frame of a (7,) viewpoint (position, quaternion qw qx qy qz); None = the origin, no rotation."""
    if viewpoint is None:
        return PerspectiveFrame(np.zeros(3), np.eye(3))
    return PerspectiveFrame(viewpoint[:3], quaternion_matrix(*viewpoint[3:7]))


def frame_kind(requested: str, organised: bool, dem: bool = False) -> str:
    """'axis' or 'perspective' for --frame `requested`: auto = perspective for organised
    scans, unless a DEM (GeoTIFF outputs, `dem`) is asked for: a DEM is heights over a map
    plane, so an organised height raster is still fitted in the axis frame (an explicit
    --frame perspective with GeoTIFF outputs is refused up front: geo.dem_frame_error)."""
    if requested not in FRAMES:
        raise InputError(f"--frame must be one of {', '.join(FRAMES)}, got {requested!r}")
    if requested == "auto":
        return "perspective" if organised and not dem else "axis"
    return requested
