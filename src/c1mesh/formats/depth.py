"""Depth images (PNG, TIFF): one depth per pixel, turned into an organised point cloud.

A depth camera writes its frame as a 16-bit single-channel image (PNG or TIFF; 32-bit
float TIFF also works): pixel (row, col) holds the depth along the camera's z axis in
units of `depth_scale` metres (1 mm = 0.001 for most cameras; TUM RGB-D uses 1/5000);
0 means "no measurement". With the pinhole intrinsics fx, fy, cx, cy (pixels) the point is

    z = value * depth_scale,  x = (col - cx) z / fx,  y = (row - cy) z / fy

in camera coordinates (x right, y down, z forward), which are also the world coordinates
(the viewpoint is the origin). An optional colour image of the same size gives colours.
Images are read with Pillow.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from c1mesh.core.cloud import PointCloud
from c1mesh.core.errors import FormatError, InputError
from c1mesh.formats._limits import check_alloc, check_expansion, read_bounded, reading_budget
from c1mesh.formats.reading import limit_of_stream, read_path

DEPTH_FORMATS = ("png", "tif", "tiff")
DEFAULT_DEPTH_SCALE = 0.001


def read_depth(data: bytes, name: str, intrinsics=None, depth_scale: float = DEFAULT_DEPTH_SCALE,
               color: bytes | None = None, color_name: str = "") -> PointCloud:
    """An organised PointCloud (grid_shape = image shape, viewpoint at the origin) from a depth image.

    data: the image file's bytes; intrinsics: (fx, fy, cx, cy) pixels, required;
    depth_scale: metres per depth unit; color: bytes of an RGB image of the same size.
    """
    if intrinsics is None:
        raise InputError(f"'{name}' is a depth image; give the camera's --intrinsics fx,fy,cx,cy "
                         "(and --depth-scale, default 0.001 m per unit)")
    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise InputError(f"--depth-scale must be a positive number of metres per unit, got {depth_scale}")
    depth = _image(data, name)
    if depth.ndim != 2:
        raise FormatError(f"'{name}' has {depth.shape[2]} channels; a depth image has one")
    if depth.dtype.kind not in "uif":
        raise FormatError(f"'{name}' holds {depth.dtype} pixels, not depths")
    fx, fy, cx, cy = intrinsics
    height, width = depth.shape
    z = depth.astype(np.float64) * depth_scale
    z[~(z > 0) | ~np.isfinite(z)] = np.nan
    cols, rows = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    points = np.stack([(cols - cx) * z / fx, (rows - cy) * z / fy, z], axis=-1).reshape(-1, 3)
    cloud = PointCloud(points=points, grid_shape=(height, width),
                       viewpoint=np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))
    if color is not None:
        rgb = _image(color, color_name, mode="RGB")
        if rgb.shape[:2] != depth.shape:
            raise InputError(f"the colour image '{color_name}' is {rgb.shape[1]}x{rgb.shape[0]} pixels, "
                             f"the depth image '{name}' {width}x{height}; they must match")
        cloud.colors = np.ascontiguousarray(rgb.reshape(-1, 3), dtype=np.uint8)
    return cloud


#: Bytes per pixel a depth frame takes once decoded: the pixel, z, the pixel grid and the
#: (N, 3) float64 points with their temporaries.
_BYTES_PER_PIXEL = 96
#: Bytes per pixel of the decoded image, by Pillow mode (4 for modes not listed).
_MODE_BYTES = {"1": 1, "L": 1, "P": 1, "LA": 2, "I;16": 2, "I;16B": 2, "I;16L": 2, "RGB": 3}


def _image(data: bytes, name: str, mode: str | None = None) -> np.ndarray:
    """Pixels of an image file's bytes as an array ((H, W) or (H, W, C)), via Pillow.

    The size in the header is checked against the reading budget (and, without --memory,
    the compression ratio of formats._limits) before the pixels are decoded: a small PNG
    can claim a huge frame of zeros.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as image:
            pixels = image.width * image.height
            raw = pixels * _MODE_BYTES.get(image.mode, 4)
            check_expansion(len(data), raw, name, f"the {image.width}x{image.height} image")
            check_alloc(pixels * _BYTES_PER_PIXEL, name, f"decoding the {image.width}x{image.height} image")
            if mode is not None and image.mode != mode:
                image = image.convert(mode)
            return np.asarray(image)
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError) as exc:
        raise FormatError(f"'{name}' is not a readable image: {exc}") from None


def is_depth_image(source, fmt: str | None) -> bool:
    """Whether `source` (path or stream) is read as a depth image, by `fmt` or its extension."""
    key = fmt if fmt else (Path(source).suffix if isinstance(source, (str, Path)) else "")
    return key.lower().lstrip(".") in DEPTH_FORMATS


@dataclass(frozen=True)
class DepthCamera:
    """What reading a depth image needs besides its bytes: intrinsics (fx, fy, cx, cy) in
    pixels (None: refused by read_depth), depth_scale metres per depth unit, color the
    path of an RGB image of the same size (None: no colours)."""

    intrinsics: tuple[float, float, float, float] | None = None
    depth_scale: float = 0.001
    color: str | None = None


def read_depth_source(source, camera: DepthCamera, memory: int | None = None) -> PointCloud:
    """read_depth on a path or binary stream with the camera's intrinsics, scale and
    colour, within the reading budget of `memory` bytes (formats.read_cloud's rules)."""
    with reading_budget(memory):
        if isinstance(source, (str, Path)):
            name, data = str(source), read_path(Path(source), Path(source).suffix.lower().lstrip(".") or None)
        else:
            name = str(getattr(source, "name", "<stream>"))
            try:
                data = read_bounded(source, name, limit_of_stream(source))
            except OSError as exc:
                raise InputError(f"Cannot read input stream '{name}': {exc.strerror or exc}.") from exc
        if not data:
            raise FormatError(f"Input '{name}' is empty.")
        color = None if camera.color is None else read_path(Path(camera.color))
    return read_depth(data, name, camera.intrinsics, camera.depth_scale, color, str(camera.color or ""))
