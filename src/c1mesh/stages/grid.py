"""Organised scans: triangles on the pixel grid, normals from grid neighbours, no curtains.

An organised scan (a depth image, a PCD with HEIGHT > 1) already says which points are
neighbours, so it needs no Delaunay triangulation: every quad of valid pixels becomes two
triangles. Depth jumps (an object's silhouette against the background) would become
"curtains" of triangles seen edge-on; `depth_jumps` removes them for any triangulation
in the perspective frame, organised or not.

All coordinates here are camera coordinates (viewpoint at the origin, looking along +z).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SHADOW_ANGLE = 10.0
"""Degrees: an edge closer than this to its view ray spans a depth jump (PCL's shadow angle)."""
GRAZING_ANGLE = 80.0
"""Degrees: a triangle whose normal is farther than this from its view ray is seen edge-on."""
NORMAL_RADIUS = 2
"""Grid normals fit a plane to the (2r+1)² window of pixels around each pixel."""


_SHAPES = ("abd", "adc", "abc", "bdc")
"""The four triangles a quad a=(i, j), b=(i, j+1), c=(i+1, j), d=(i+1, j+1) can hold."""


def grid_mesh(points: np.ndarray, uv: np.ndarray, valid: np.ndarray, shadow_angle: float = SHADOW_ANGLE,
              grazing_angle: float = GRAZING_ANGLE) -> tuple[np.ndarray, "JumpReport"]:
    """Triangles (T, 3) int64 of the pixel grid without depth jumps, counter-clockwise in (u, v).

    points: (H, W, 3) camera coordinates; uv: (H, W, 2) ray parameters; valid: (H, W)
    bool, the pixels that may be vertices. Indices are into the row-major pixels. Each
    quad with four valid corners gives two triangles split along the shorter 3D diagonal
    (ties: a-d), a quad with three gives the one triangle they make; the rule is local and
    deterministic. Triangles spanning a depth jump are dropped by the rules of
    `depth_jumps`, evaluated here on whole grid slices of x, y, z planes (no gathers, each
    edge tested once), which is what makes the grid an order of magnitude faster than
    Delaunay.
    """
    height, width = valid.shape
    xyz = [np.ascontiguousarray(points[..., k], dtype=np.float32) for k in range(3)]   # tests only
    flat_xyz = [plane.ravel() for plane in xyz]
    flat_uv = uv.reshape(-1, 2)
    corner = {"a": (slice(None, -1), slice(None, -1)), "b": (slice(None, -1), slice(1, None)),
              "c": (slice(1, None), slice(None, -1)), "d": (slice(1, None), slice(1, None))}
    p = {k: [plane[s] for plane in xyz] for k, s in corner.items()}
    v = {k: valid[s] for k, s in corner.items()}
    cos_shadow = np.cos(np.radians(shadow_angle))
    across = _shadow([c[:, :-1] for c in xyz], [c[:, 1:] for c in xyz], cos_shadow)    # (H, W-1)
    down = _shadow([c[:-1] for c in xyz], [c[1:] for c in xyz], cos_shadow)            # (H-1, W)
    shadow = {"ab": across[:-1], "cd": across[1:], "ac": down[:, :-1], "bd": down[:, 1:],
              "ad": _shadow(p["a"], p["d"], cos_shadow), "bc": _shadow(p["b"], p["c"], cos_shadow)}
    split_ad = _length2(_minus(p["a"], p["d"])) <= _length2(_minus(p["b"], p["c"]))
    index = np.arange(height * width, dtype=np.int64).reshape(height, width)
    cos_grazing = np.float32(np.cos(np.radians(grazing_angle)))
    kept, removed = [], {"zero_area": 0, "shadow_edge": 0, "grazing": 0}
    for shape in _SHAPES:
        q, r, t = shape
        missing = ({"a", "b", "c", "d"} - set(shape)).pop()
        diagonal = split_ad if "a" in shape and "d" in shape else ~split_ad
        exists = v[q] & v[r] & v[t] & (~v[missing] | diagonal)
        cut_shadow = exists & (shadow[_edge(q, r)] | shadow[_edge(r, t)] | shadow[_edge(q, t)])
        removed["shadow_edge"] += int(cut_shadow.sum())
        candidate = exists & ~cut_shadow
        tri = np.column_stack([index[corner[k]][candidate] for k in shape])      # the rest, gathered
        at = [[plane[tri[:, m]] for plane in flat_xyz] for m in range(3)]
        e1, e2 = _minus(at[1], at[0]), _minus(at[2], at[0])
        normal = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]]
        centroid = [at[0][k] + at[1][k] + at[2][k] for k in range(3)]
        with np.errstate(invalid="ignore"):
            seen = np.abs(normal[0] * centroid[0] + normal[1] * centroid[1] + normal[2] * centroid[2])
            grazing = ~(seen >= cos_grazing * np.sqrt(_length2(normal) * _length2(centroid)))
        area = _area(flat_uv[tri[:, 0]], flat_uv[tri[:, 1]], flat_uv[tri[:, 2]])
        flat = ~grazing & ~(np.abs(area) > 0)
        removed["grazing"] += int(grazing.sum())
        removed["zero_area"] += int(flat.sum())
        keep = ~grazing & ~flat
        tri, area = tri[keep], area[keep]
        backwards = area < 0
        tri[backwards, 1], tri[backwards, 2] = tri[backwards, 2], tri[backwards, 1].copy()
        kept.append(tri)
    return np.concatenate(kept), JumpReport(shadow_angle, grazing_angle, removed)


def _edge(first: str, second: str) -> str:
    """The key of the quad edge between two corners ("ab", "ac", "ad", "bc", "bd", "cd")."""
    return "".join(sorted(first + second))


def _minus(p: list, q: list) -> list:
    return [p[k] - q[k] for k in range(3)]


def _length2(vector: list) -> np.ndarray:
    return vector[0] * vector[0] + vector[1] * vector[1] + vector[2] * vector[2]


def _shadow(p: list, q: list, cos_shadow: float) -> np.ndarray:
    """bool array: the edge p-q (x, y, z planes) runs within the shadow angle of the view ray
    through its midpoint."""
    edge = _minus(q, p)
    mid = [q[k] + p[k] for k in range(3)]
    with np.errstate(invalid="ignore"):
        along = np.abs(edge[0] * mid[0] + edge[1] * mid[1] + edge[2] * mid[2])
        return along > cos_shadow * np.sqrt(_length2(edge) * _length2(mid))


def _area(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Twice the signed area of the triangles (p0, p1, p2), points (..., 2)."""
    return ((p1[..., 0] - p0[..., 0]) * (p2[..., 1] - p0[..., 1])
            - (p1[..., 1] - p0[..., 1]) * (p2[..., 0] - p0[..., 0]))


def _squared_length(vectors: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", vectors, vectors)


def counter_clockwise(uv: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, int]:
    """Triangles (T', 3) turned counter-clockwise in (u, v), without zero-area ones; and how many those were."""
    p0, p1, p2 = uv[triangles[:, 0]], uv[triangles[:, 1]], uv[triangles[:, 2]]
    area = (p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1]) - (p1[:, 1] - p0[:, 1]) * (p2[:, 0] - p0[:, 0])
    tri = triangles.copy()
    clockwise = area < 0
    tri[clockwise, 1], tri[clockwise, 2] = triangles[clockwise, 2], triangles[clockwise, 1]
    flat = ~(np.abs(area) > 0)
    return tri[~flat], int(flat.sum())


@dataclass
class JumpReport:
    """Triangles removed as spanning a depth jump, by reason (a triangle counts once, first reason)."""

    shadow_angle: float
    grazing_angle: float
    removed: dict[str, int] = field(default_factory=dict)


def depth_jumps(points: np.ndarray, triangles: np.ndarray, shadow_angle: float = SHADOW_ANGLE,
                grazing_angle: float = GRAZING_ANGLE) -> tuple[np.ndarray, JumpReport]:
    """Drop triangles that span a depth discontinuity; returns (kept triangles, report).

    points: (N, 3) camera coordinates; triangles: (T, 3) indices. Two rules:
    "shadow_edge": an edge within `shadow_angle` degrees of the view ray through its
    midpoint: it runs (almost) along the line of sight, which a surface seen from here
    cannot do, so it bridges a depth step far larger than the pixel footprint (PCL's
    OrganizedFastMesh shadow test). "grazing": the triangle's plane is seen within
    90° - `grazing_angle` of edge-on at its centroid, i.e. its depth changes by more
    than tan(grazing_angle) times its width across the view: a curtain.
    """
    p = [points[triangles[:, k]] for k in range(3)]
    cos_shadow = np.cos(np.radians(shadow_angle))
    shadow = np.zeros(triangles.shape[0], dtype=bool)
    for k in range(3):
        edge = p[(k + 1) % 3] - p[k]
        mid = p[(k + 1) % 3] + p[k]
        dot = np.abs(np.einsum("ij,ij->i", edge, mid))
        with np.errstate(invalid="ignore"):
            shadow |= dot > cos_shadow * np.sqrt(_squared_length(edge) * _squared_length(mid))
    normal = np.cross(p[1] - p[0], p[2] - p[0])
    centroid = p[0] + p[1] + p[2]
    cos_view = np.abs(np.einsum("ij,ij->i", normal, centroid))
    with np.errstate(invalid="ignore"):
        grazing = ~(cos_view >= np.cos(np.radians(grazing_angle))
                    * np.sqrt(_squared_length(normal) * _squared_length(centroid)))
    grazing &= ~shadow
    keep = ~(shadow | grazing)
    report = JumpReport(shadow_angle, grazing_angle,
                        {"shadow_edge": int(shadow.sum()), "grazing": int(grazing.sum())})
    return triangles[keep], report


def grid_normals(points: np.ndarray, valid: np.ndarray, radius: int = NORMAL_RADIUS,
                 shadow_angle: float = SHADOW_ANGLE) -> np.ndarray:
    """Unit normals (H, W, 3) facing the viewpoint, from plane fits to grid neighbours.

    points: (H, W, 3) camera coordinates; valid: (H, W) bool. Each pixel's normal is the
    direction of least variance of the valid pixels in its (2r+1)² window that are not
    across a depth jump from it, signed so that n·p < 0 (towards the viewpoint at the
    origin). A neighbour k pixels away is across a jump when the depths differ by more
    than k footprints / tan(shadow_angle), a footprint being the pixel's width at that
    depth (the median angle between neighbouring rays times z): the offset would then run
    within about `shadow_angle` of the view ray, as in `depth_jumps`. Pixels with fewer
    than 3 such neighbours, or collinear ones, get NaN.
    """
    height, width = valid.shape
    pad = radius
    z = np.where(valid, points[..., 2], np.nan)
    padded = np.zeros((3, height + 2 * pad, width + 2 * pad))
    for axis in range(3):
        padded[axis, pad:-pad, pad:-pad] = np.where(valid, points[..., axis], 0.0)
    inside = np.zeros((height + 2 * pad, width + 2 * pad), dtype=bool)
    inside[pad:-pad, pad:-pad] = valid
    centre = padded[:, pad:-pad, pad:-pad]
    step = _pixel_angle(points, valid) / np.tan(np.radians(shadow_angle)) * z
    # Offsets are exact float64 differences; their sums and products are float32 (half the
    # memory traffic of this loop, which is the stage's cost): normals to ~1e-7.
    count = np.zeros((height, width), dtype=np.float32)
    total = np.zeros((3, height, width), dtype=np.float32)
    outer = np.zeros((6, height, width), dtype=np.float32)
    pairs = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
    offset = np.empty((3, height, width))
    rel = np.empty((3, height, width), dtype=np.float32)
    product = np.empty((height, width), dtype=np.float32)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            window = (slice(pad + dy, pad + dy + height), slice(pad + dx, pad + dx + width))
            np.subtract(padded[(slice(None),) + window], centre, out=offset)
            with np.errstate(invalid="ignore"):
                ok = np.abs(offset[2]) <= step * max(abs(dx), abs(dy))    # False where step is NaN
            ok &= inside[window]
            np.multiply(offset, ok, out=rel, casting="same_kind")
            count += ok
            total += rel
            for slot, (i, j) in enumerate(pairs):
                np.multiply(rel[i], rel[j], out=product)
                outer[slot] += product
    return _plane_normals(count, total, outer, np.where(valid[..., None], points, np.nan))


def _pixel_angle(points: np.ndarray, valid: np.ndarray) -> float:
    """Median angle (radians) between the rays of horizontally neighbouring valid pixels
    (of every 8th row: a median needs no more)."""
    points, valid = points[::8], valid[::8]
    pair = valid[:, 1:] & valid[:, :-1]
    a, b = points[:, 1:][pair], points[:, :-1][pair]
    if a.shape[0] == 0:
        return 1.0
    cos = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return float(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))) or 1.0


def _plane_normals(count, total, outer, centre) -> np.ndarray:
    """Least-variance directions (H, W, 3) of the accumulated neighbourhoods, facing the origin.

    count (H, W); total (3, H, W) sums of offsets; outer (6, H, W) sums of their products
    xx, yy, zz, xy, xz, yz; centre (H, W, 3) the pixels' points.
    """
    enough = count >= 3
    n = count[enough].astype(np.float64)
    mean = [total[k][enough] / n for k in range(3)]
    cov = [outer[slot][enough] / n - mean[i] * mean[j]
           for slot, (i, j) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)))]
    normal, flat = smallest_eigenvectors(*cov)
    normal[flat] = np.nan
    facing = np.einsum("ij,ij->i", normal, centre[enough])
    normal[facing > 0] *= -1.0
    out = np.full(centre.shape, np.nan)
    out[enough] = normal
    return out


def smallest_eigenvectors(a00, a11, a22, a01, a02, a12) -> tuple[np.ndarray, np.ndarray]:
    """Unit eigenvectors (n, 3) of the smallest eigenvalue of symmetric 3×3 matrices, and (n,) bool
    where the two smallest eigenvalues coincide (collinear or single points: no plane).

    The eigenvalues in closed form (Smith 1961, trigonometric), the eigenvector as the
    largest cross product of two rows of A - λ I: some 40 flops per matrix, where
    numpy.linalg.eigh takes ~30x longer on 300k small matrices.
    """
    q = (a00 + a11 + a22) / 3.0
    off = a01 * a01 + a02 * a02 + a12 * a12
    d0, d1, d2 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * off) / 6.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = 1.0 / p
        det = (d0 * (d1 * d2 - a12 * a12) - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02))
        r = np.clip(det * inv ** 3 / 2.0, -1.0, 1.0)
    phi = np.arccos(np.nan_to_num(r)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = 3.0 * q - largest - smallest
    b00, b11, b22 = a00 - smallest, a11 - smallest, a22 - smallest
    crosses = [(a01 * a12 - a02 * b11, a02 * a01 - b00 * a12, b00 * b11 - a01 * a01),    # row0 × row1
               (a01 * b22 - a02 * a12, a02 * a02 - b00 * b22, b00 * a12 - a01 * a02),    # row0 × row2
               (b11 * b22 - a12 * a12, a12 * a02 - a01 * b22, a01 * a12 - b11 * a02)]    # row1 × row2
    lengths = [x * x + y * y + z * z for x, y, z in crosses]
    best = np.argmax(np.stack(lengths), axis=0)
    vector = np.empty((q.size, 3))
    for k in range(3):
        vector[:, k] = np.choose(best, [c[k] for c in crosses])
    with np.errstate(invalid="ignore", divide="ignore"):
        vector /= np.sqrt(np.choose(best, lengths))[:, None]
        flat = ~(middle - smallest > 1e-10 * np.abs(largest)) | ~np.isfinite(vector).all(axis=1)
    return vector, flat
