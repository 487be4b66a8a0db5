"""The tiled fit's join: the tiles' refined parts, taken in tile order, become one vertex
file and one face file with one global vertex numbering (c1mesh.pipeline.bounded_fit).

A refined vertex that can lie in two tiles' outputs lies on the boundary of both tiles'
owned regions: a corner point, or a point on a base edge that only one owned triangle of
the tile has. Such a vertex has a key that does not depend on the tile (`border_keys`):
the survey number of a corner, or (lower end, higher end, position from the lower end)
of an edge point. The first tile that reaches a key writes its vertex and numbers it;
later tiles refer to that number.

Which keys the join must remember. A tile can meet a key only if it owns a base triangle
with that corner (an edge point: with both ends of that edge), and every corner of tile
t's own triangles lies in its cell grown by its reach (the trim's max_edge, or its
Delaunay buffer; refine_runs.RefineJob.reach). So no tile after the highest-numbered one
whose grown cell holds the point (for an edge point: the lower of its two ends' tiles)
can meet the key: that tile is the key's last tile (`KeyExpiry`). The join goes through
the tiles in ascending order and forgets a key once it has joined the key's last tile,
so it holds the keys of a band of tiles about one tile row plus the reach wide, not every
border key of the survey (a Python dict entry costs over 100 bytes). Forgetting changes
no number: a forgotten key is never asked for again.
"""
from __future__ import annotations

import numpy as np

from c1mesh.survey.tile_spill import file_blocks

CHUNK = 1_000_000
"""Vertices (faces) per block copied from a part file to the joined files."""
CELLS_PER_BLOCK = 1 << 22
"""Point-tile pairs tested at once by KeyExpiry (a bool each, several temporaries)."""


class KeyExpiry:
    """The last tile (module docstring) of points in the frame's plane. grid: the
    buffered_delaunay.TileGrid; reaches (T,): per tile how far beyond its cell the corners
    of its own triangles lie (frame units). Picklable (a refinement task computes the
    last tiles of its border keys)."""

    MARGIN = 1e-6
    """Relative growth of each reach: a later last tile is only a longer memory, never a
    wrong number, so rounding is kept on the safe side."""

    def __init__(self, grid, reaches: np.ndarray):
        cells = np.array([grid.cell(t) for t in range(len(grid))], dtype=np.float64).reshape(-1, 4)
        grow = np.asarray(reaches, dtype=np.float64) * (1 + self.MARGIN)
        self.low = cells[:, :2] - grow[:, None]
        self.high = cells[:, 2:] + grow[:, None]

    def last_tiles(self, xy: np.ndarray) -> np.ndarray:
        """(m,) int64: for each point (m, 2) the highest tile whose grown cell (closed)
        holds it; -1 for a point no grown cell holds."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        tiles = len(self.low)
        last = np.full(len(xy), -1, dtype=np.int64)
        step = max(1, CELLS_PER_BLOCK // max(tiles, 1))
        for start in range(0, len(xy), step):
            x, y = xy[start:start + step, :1], xy[start:start + step, 1:]
            holds = ((x >= self.low[:, 0]) & (x <= self.high[:, 0]) &
                     (y >= self.low[:, 1]) & (y <= self.high[:, 1]))
            found = holds.any(axis=1)
            highest = tiles - 1 - np.argmax(holds[:, ::-1], axis=1)
            last[start:start + step] = np.where(found, highest, -1)
        return last


def border_keys(refinement, survey: np.ndarray, xy: np.ndarray, expiry: KeyExpiry) -> dict[str, np.ndarray]:
    """The keys of a tile refinement's output points that may be shared with another tile
    (module docstring), as arrays: corner_keys (c,) survey numbers, corner_points (c,)
    their output points, corner_last (c,) their last tiles; edge_keys (e, 3) (lower end,
    higher end, position from the lower end), edge_points (e,), edge_last (e,).
    survey (n,), xy (n, 2): the survey numbers and frame positions of the refinement's
    corner points."""
    table, L = refinement.table, refinement.level
    border = np.flatnonzero(table.count == 1)                  # edges of one owned triangle
    ends = table.edges[border]
    corners = np.unique(ends)
    last = np.full(len(survey), -1, dtype=np.int64)
    last[corners] = expiry.last_tiles(xy[corners])
    edge_keys, edge_points, edge_last = np.empty((0, 3), np.int64), np.empty(0, np.int64), np.empty(0, np.int64)
    if L > 1 and len(border):
        code = refinement.edge_code[border]
        first, forward = (code >> 1).astype(np.int64), (code & 1).astype(bool)
        j = np.arange(L - 1)
        a = np.repeat(survey[ends[:, 0]].astype(np.int64), L - 1)
        b = np.repeat(survey[ends[:, 1]].astype(np.int64), L - 1)
        step = np.tile(j, len(border))
        position = np.where(np.repeat(forward, L - 1), step, L - 2 - step)
        edge_keys = np.column_stack([a, b, position])
        edge_points = (np.repeat(first, L - 1) + step).astype(np.int64)
        edge_last = np.repeat(np.minimum(last[ends[:, 0]], last[ends[:, 1]]), L - 1)
    return {"corner_keys": survey[corners].astype(np.int64), "corner_points": corners.astype(np.int64),
            "corner_last": last[corners], "edge_keys": edge_keys, "edge_points": edge_points,
            "edge_last": edge_last}


def stored_keys(stored) -> tuple[list, list, list]:
    """The border keys, their points and their last tiles (`border_keys`, from its .npz)
    as the lists `global_numbers` takes: corners first (int keys), then edge points
    (tuple keys)."""
    keys = stored["corner_keys"].tolist() + [tuple(k) for k in stored["edge_keys"].tolist()]
    points = stored["corner_points"].tolist() + stored["edge_points"].tolist()
    last = stored["corner_last"].tolist() + stored["edge_last"].tolist()
    return keys, points, last


class SharedKeys:
    """The global numbers of the border keys a later tile may still meet: `numbers` maps a
    key to its number; `expiring` lists the keys by last tile, for `forget`."""

    def __init__(self):
        self.numbers: dict = {}
        self.expiring: dict[int, list] = {}
        self.added = self.peak = 0

    def remember(self, key, number: int, last: int) -> None:
        self.numbers[key] = number
        self.expiring.setdefault(last, []).append(key)
        self.added += 1
        self.peak = max(self.peak, len(self.numbers))

    def forget(self, tile: int) -> None:
        """Drop the keys no tile after `tile` can meet."""
        for last in [t for t in self.expiring if t <= tile]:
            for key in self.expiring.pop(last):
                del self.numbers[key]


def global_numbers(keys: list, points: list, last: list, tile: int, vertex_count: int,
                   shared: SharedKeys, written: int) -> np.ndarray:
    """(M,) the global number of each of tile `tile`'s M output points: a key in `shared`
    keeps its number; every other point gets the next new number (written, written + 1,
    ... in output order), and its key is remembered when a later tile can meet it (its
    last tile is after this one)."""
    number = np.full(vertex_count, -1, dtype=np.int64)
    known = shared.numbers
    for k, p in zip(keys, points):
        if k in known:
            number[p] = known[k]
    new = number < 0
    number[new] = written + np.arange(int(new.sum()))
    for k, p, end in zip(keys, points, last):
        if end > tile and k not in known:
            shared.remember(k, int(number[p]), end)
    return number


class PartJoin:
    """The one vertex file and one face file made from the tiles' parts, in tile order
    (module docstring). dtype: a part's vertex record; written, faces: counts so far;
    kept: input points among the vertices written; shared: the border keys held."""

    def __init__(self, dtype: np.dtype):
        self.dtype, self.shared = dtype, SharedKeys()
        self.written = self.faces = self.kept = 0
        self.keys = 0

    def add(self, tile: int, part, row: dict, vertex_file, face_file) -> None:
        """Append tile's part (refine_runs._Part; row: its refinement's report row with
        vertices, corners, faces) to the open vertex and face files."""
        with open(part.keys, "rb") as file:
            keys, points, last = stored_keys(np.load(file))
        number = global_numbers(keys, points, last, tile, row["vertices"], self.shared, self.written)
        new = number >= self.written
        self.keys += int(new[np.asarray(points, dtype=np.int64)].sum())

        with open(part.vertices, "rb") as file:
            position = 0
            for block in file_blocks(file, self.dtype, CHUNK):
                np.compress(new[position:position + len(block)], block).tofile(vertex_file)   # 2x block[mask]
                position += len(block)
        with open(part.faces, "rb") as file:
            for block in file_blocks(file, "<i8", 3 * CHUNK):
                number.take(block).astype("<i8", copy=False).tofile(face_file)
        self.written += int(new.sum())
        self.kept += int(new[:row["corners"]].sum())
        self.faces += row["faces"]

    def passed(self, tile: int) -> None:
        """Every tile up to `tile` is joined: forget the keys no later tile can meet."""
        self.shared.forget(tile)
