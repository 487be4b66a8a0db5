"""COPC (Cloud Optimized Point Cloud): a LAZ 1.4 file whose chunks are octree nodes.

A COPC file is a valid LAZ file, so a whole read goes through c1mesh.formats.las as any
LAZ. What COPC adds is a hierarchy (an EVLR listing every octree node's cube, file
offset, byte size and point count), so a reader that wants only a region of the survey
can fetch and decompress only the nodes whose cubes meet that region.

Regions here are boxes in the file's x/y (world units, after scale and offset):
`(xmin, ymin, xmax, ymax)`, closed on every side; z is not restricted. A region read
returns exactly the points of a whole read that lie in the box, in the same order
(file order: the nodes are decompressed in the order of their offsets, which is the
order of the LAZ chunk table a whole read walks), so everything downstream — survey
numbers, ownership, ties — is as if the whole file had been read and filtered.

The hierarchy is walked here from the root, descending only into cubes that meet the
box and reading the hierarchy pages it reaches (laspy parses each page); the chunks are
read here too and decompressed by lazrs, a batch of nodes at a time, so memory holds
one batch and the kept points.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import IO, Callable, Iterator, Sequence

import numpy as np

from c1mesh.core.errors import FormatError, InputError
from c1mesh.core.threads import workers

Box = tuple[float, float, float, float]
"""(xmin, ymin, xmax, ymax) in the file's world units; closed on every side."""

#: Record bytes per compressed byte a node may claim (as formats.las._MAX_LAZ_RATIO).
_MAX_NODE_RATIO = 200



def laspy_module():
    """laspy, imported on first use: it takes about 0.5 s, which a fit of a PLY file or
    `c1mesh --help` should not pay. Every LAS/LAZ reader of c1mesh gets it here."""
    import laspy

    return laspy


def lazrs_module():
    """lazrs (laspy's LAZ codec), imported on first use as laspy is (laspy_module)."""
    import lazrs

    return lazrs

def parse_box(text: str) -> Box:
    """'XMIN,YMIN,XMAX,YMAX' as a Box; InputError naming what is wrong."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"bounds '{text}' must be four numbers XMIN,YMIN,XMAX,YMAX") from None
    return check_box(values, text)


def check_box(values: Sequence[float], text: object = None) -> Box:
    """`values` as a Box after checking it: four finite numbers with min <= max."""
    label = text if text is not None else ",".join(map(str, values))
    if len(values) != 4 or not all(math.isfinite(float(v)) for v in values):
        raise InputError(f"bounds '{label}' must be four finite numbers XMIN,YMIN,XMAX,YMAX")
    xmin, ymin, xmax, ymax = (float(v) for v in values)
    if xmin > xmax or ymin > ymax:
        raise InputError(f"bounds '{label}' are empty: XMIN must not exceed XMAX, nor YMIN YMAX")
    return xmin, ymin, xmax, ymax


def inside(x: np.ndarray, y: np.ndarray, box: Box) -> np.ndarray:
    """(n,) bool: the points (x, y world coordinates) inside the closed box."""
    xmin, ymin, xmax, ymax = box
    return (x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)


def header_meets(header, box: Box) -> bool:
    """Whether a LAS header's x/y extent meets the box (False: no point can be inside)."""
    xmin, ymin, xmax, ymax = box
    lo, hi = header.mins, header.maxs
    return bool(lo[0] <= xmax and hi[0] >= xmin and lo[1] <= ymax and hi[1] >= ymin)


def is_copc_header(header) -> bool:
    """Whether a laspy LasHeader is a COPC file's: its first VLR is the COPC info VLR."""
    return len(header.vlrs) > 0 and isinstance(header.vlrs[0], laspy_module().copc.CopcInfoVlr)


@dataclass
class Node:
    """One octree node with points: its voxel key (level, x, y, z), the byte range of its
    LAZ chunk in the file and its point count."""

    key: tuple[int, int, int, int]
    offset: int
    byte_size: int
    point_count: int


@dataclass
class RegionCost:
    """What a region read fetches: the nodes, their compressed bytes and points decoded."""

    nodes: list[Node] = field(default_factory=list)

    @property
    def bytes(self) -> int:
        return sum(n.byte_size for n in self.nodes)

    @property
    def points(self) -> int:
        return sum(n.point_count for n in self.nodes)


class Copc:
    """An open COPC file: its header, octree and node reads.

    open_stream: opens the file again (a fresh binary stream); name: for messages;
    size: the file's size in bytes (node byte ranges are checked against it).
    """

    def __init__(self, open_stream: Callable[[], IO[bytes]], name: str, size: int):
        laspy = laspy_module()
        self.name, self.size = name, size
        self.stream = open_stream()
        try:
            self.reader = laspy.CopcReader(self.stream, close_fd=False)
        except BaseException:
            self.stream.close()
            raise
        self.header = self.reader.header
        self._complete: bool | None = None
        self._entries: dict | None = None

    @property
    def complete(self) -> bool:
        """Whether the hierarchy reaches every point: the nodes found by walking it from the
        root hold the header's point count. A writer that leaves a node without its parent
        makes that node unreachable; a region read would then lose its points silently, so
        callers read such a file by its chunk table instead."""
        if self._complete is None:
            self._complete = sum(n.point_count for n in self.nodes()) == self.header.point_count
        return self._complete

    def close(self) -> None:
        self.stream.close()

    def __enter__(self) -> "Copc":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def nodes(self, box: Box | None = None) -> list[Node]:
        """The nodes holding points whose cubes meet the box (None: all), in file order.

        A walk of the hierarchy from the root that descends only into cubes meeting the
        box, reading the hierarchy pages it reaches (laspy parses them). The box is grown
        by two coordinate steps so that rounding in the cube arithmetic cannot drop a node
        holding a point on the box's edge; the exact test is per point.
        """
        info = self.reader.copc_info
        lo = np.asarray(info.center, dtype=np.float64)[:2] - info.halfsize
        if box is not None:
            pad = 2 * np.asarray(self.header.scales[:2], dtype=np.float64)
            box = (box[0] - pad[0], box[1] - pad[1], box[2] + pad[0], box[3] + pad[1])
        nodes, stack = [], [(0, 0, 0, 0)]
        while stack:
            key = stack.pop()
            entry = self._entry(key)
            if entry is None or (box is not None and not _cube_meets(key, lo, 2 * info.halfsize, box)):
                continue
            offset, byte_size, point_count = entry
            if point_count > 0:
                nodes.append(Node(key, offset, byte_size, point_count))
            level, x, y, z = key
            stack.extend((level + 1, 2 * x + (d & 1), 2 * y + (d >> 1 & 1), 2 * z + (d >> 2 & 1))
                         for d in range(8))
        nodes.sort(key=lambda n: n.offset)
        self._check(nodes)
        return nodes

    def _entry(self, key: tuple[int, int, int, int]) -> tuple[int, int, int] | None:
        """(offset, byte size, point count) of a node's hierarchy entry, None if it has
        none; a page entry (point count -1) is read and its entries added first."""
        if self._entries is None:
            self._entries = _page_entries(self.reader.root_page)
        entry = self._entries.get(key)
        while entry is not None and entry[2] == -1:
            HierarchyPage = laspy_module().copc.HierarchyPage
            offset, size, _ = entry
            if size <= 0 or offset + size > self.size:
                raise FormatError(f"COPC file '{self.name}' has a corrupt hierarchy: page {key} lies at "
                                  f"bytes {offset}+{size}, outside the file.")
            self.stream.seek(offset)
            page = _page_entries(HierarchyPage.from_bytes(self.stream.read(size)))
            if page.get(key, (0, 0, 0))[2] == -1:
                raise FormatError(f"COPC file '{self.name}' has a corrupt hierarchy: page {key} refers to itself.")
            self._entries[key] = (0, 0, 0)        # replaced by the page's own entry for key, if any
            self._entries.update(page)
            entry = self._entries.get(key)
        return entry

    def _check(self, nodes: list[Node]) -> None:
        """FormatError for node entries that cannot be right: a byte range outside the file,
        more points than its bytes can hold, or more points in all than the header has."""
        record = self.header.point_format.size
        for node in nodes:
            if node.byte_size <= 0 or node.offset < self.header.offset_to_point_data \
                    or node.offset + node.byte_size > self.size:
                raise FormatError(f"COPC file '{self.name}' has a corrupt hierarchy: node {node.key} "
                                  f"lies at bytes {node.offset}+{node.byte_size}, outside the point data.")
            if node.point_count * record > _MAX_NODE_RATIO * node.byte_size + (1 << 16):
                raise FormatError(f"COPC file '{self.name}' has a corrupt hierarchy: node {node.key} "
                                  f"claims {node.point_count} points in {node.byte_size} bytes.")
        if sum(n.point_count for n in nodes) > self.header.point_count:
            raise FormatError(f"COPC file '{self.name}' has a corrupt hierarchy: its nodes hold more "
                              f"points than the header's {self.header.point_count}.")

    def records(self, nodes: list[Node], batch_points: int, selection=None) -> Iterator:
        """laspy ScaleAwarePointRecords of the nodes (file order), about batch_points at a time.

        selection: a laspy.DecompressionSelection (None: every field)."""
        batch: list[Node] = []
        for node in nodes:
            batch.append(node)
            if sum(n.point_count for n in batch) >= batch_points:
                yield self._decompress(batch, selection)
                batch = []
        if batch:
            yield self._decompress(batch, selection)

    def _decompress(self, nodes: list[Node], selection):
        """One ScaleAwarePointRecord of these nodes' points, in the order given."""
        lazrs, laspy = lazrs_module(), laspy_module()

        compressed = bytearray(sum(n.byte_size for n in nodes))
        view, at = memoryview(compressed), 0
        for node in nodes:
            self.stream.seek(node.offset)
            got = self.stream.readinto(view[at:at + node.byte_size])
            if got != node.byte_size:
                raise FormatError(f"COPC file '{self.name}' is truncated: node {node.key} ends past the file.")
            at += node.byte_size
        fmt = self.header.point_format
        points = np.zeros(sum(n.point_count for n in nodes) * fmt.size, dtype=np.uint8)
        selection = (selection or laspy.DecompressionSelection.all()).to_lazrs()
        lazrs.decompress_points_with_chunk_table(
            compressed, self.reader.laszip_vlr.record_data, points,
            [(n.point_count, n.byte_size) for n in nodes], selection)
        record = laspy.PackedPointRecord.from_buffer(points, fmt)
        return laspy.ScaleAwarePointRecord(record.array, fmt, self.header.scales, self.header.offsets)


def _page_entries(page) -> dict:
    """{(level, x, y, z): (offset, byte size, point count)} of a laspy HierarchyPage."""
    return {(e.key.level, e.key.x, e.key.y, e.key.z): (int(e.offset), int(e.byte_size), int(e.point_count))
            for e in page.entries.values()}


def _cube_meets(key: tuple[int, int, int, int], lo: np.ndarray, side: float, box: Box) -> bool:
    """Whether the x/y square of an octree node (root square from lo, of side `side`)
    meets the closed box."""
    level, x, y, _ = key
    step = side / (1 << level)
    x0, y0 = lo[0] + x * step, lo[1] + y * step
    return x0 <= box[2] and x0 + step >= box[0] and y0 <= box[3] and y0 + step >= box[1]


def region_cost(path, box: Box | None) -> RegionCost:
    """The nodes, compressed bytes and points a read of `box` (None: all) fetches from the
    COPC file at `path`, from its hierarchy alone (nothing is decompressed)."""
    with Copc(lambda: open(path, "rb"), str(path), os.path.getsize(path)) as copc:
        return RegionCost(copc.nodes(box))


def copc_summary(path) -> dict | None:
    """`c1mesh info`'s COPC facts of the file at `path` (None unless it is COPC): node
    count, octree depth, root cube and spacing, from the header and hierarchy only."""
    laspy = laspy_module()
    with laspy.open(str(path)) as reader:
        if not is_copc_header(reader.header):
            return None
    with Copc(lambda: open(path, "rb"), str(path), os.path.getsize(path)) as copc:
        nodes = copc.nodes()
        info = copc.reader.copc_info
        center, half = np.asarray(info.center, dtype=np.float64), float(info.halfsize)
        return {"nodes": len(nodes), "levels": 1 + max((n.key[0] for n in nodes), default=0),
                "cube": {"min": (center - half).tolist(), "max": (center + half).tolist()},
                "spacing": float(info.spacing), "hierarchy_reaches_every_point": copc.complete}


def region_chunks(path, box: Box | None, chunk: int) -> Iterator:
    """laspy point records of the LAS/LAZ file at `path` inside the closed x/y box, in
    file order, about `chunk` points decoded at a time: only the nodes meeting the box
    of a COPC file, nothing of a file whose header extent misses the box, else every
    chunk of the body, filtered (box None: every chunk as it is)."""
    laspy = laspy_module()

    with laspy.open(str(path), laz_backend=laz_backend()) as reader:
        if box is None:
            yield from reader.chunk_iterator(chunk)
            return
        if not header_meets(reader.header, box):
            return
        if is_copc_header(reader.header) and reader.header.are_points_compressed:
            with Copc(lambda: open(path, "rb"), str(path), os.path.getsize(path)) as copc:
                if copc.complete:
                    for part in copc.records(copc.nodes(box), chunk):
                        yield part[inside(np.asarray(part.x), np.asarray(part.y), box)]
                    return
        for part in reader.chunk_iterator(chunk):
            yield part[inside(np.asarray(part.x), np.asarray(part.y), box)]


def points_to_read(path, box: Box | None) -> int:
    """An upper bound on the points of the LAS/LAZ file at `path` inside the box, from
    the header (and a COPC file's hierarchy): what a region read decodes."""
    laspy = laspy_module()
    with laspy.open(str(path)) as reader:
        header = reader.header
        if box is None:
            return int(header.point_count)
        if not header_meets(header, box):
            return 0
        if not (is_copc_header(header) and header.are_points_compressed):
            return int(header.point_count)
    with Copc(lambda: open(path, "rb"), str(path), os.path.getsize(path)) as copc:
        return sum(n.point_count for n in copc.nodes(box)) if copc.complete else int(copc.header.point_count)


def laz_backend():
    """The laspy LAZ backend under the thread knob: lazrs in one thread when
    `workers()` is 1, else lazrs's parallel decoder (the LAZ chunks of each read decoded
    in rayon threads; laspy's own default, and the same decoded bytes).

    rayon's pool cannot be bounded per call: lazrs does not take a thread count, and its
    global pool is sized once per process, to RAYON_NUM_THREADS or the CPU count. So the
    knob chooses between one thread and that pool."""
    laspy = laspy_module()
    backends = laspy.LazBackend
    return backends.Lazrs if workers() == 1 else backends.LazrsParallel
