"""COPC input: whole reads as LAZ, region reads by the octree, and fits by bounds.

Ground truth: laspy's plain LAZ reader of the same file (a whole read), and a whole read
filtered with numpy (a region read must return exactly those points, in that order).
"""
from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")

from c1mesh.core.errors import FormatError, InputError  # noqa: E402
from c1mesh.formats import read_cloud  # noqa: E402
from c1mesh.formats.copc import copc_summary, is_copc_header, parse_box, points_to_read, region_cost  # noqa: E402
from c1mesh.formats.las import read_las  # noqa: E402

DATA = Path(__file__).resolve().parent.parent / "data_samples"
COPC = DATA / "simple.copc.laz"
PLAIN_LAZ = DATA / "autzen_trim.laz"


def _whole(path=COPC):
    """The file read whole by laspy's plain reader (world x, y, z and classification)."""
    las = laspy.read(str(path))
    return np.column_stack([las.x, las.y, las.z]), np.asarray(las.classification)


def _boxes(points: np.ndarray, count: int, seed: int = 0):
    """Random boxes over the points' extent, some with sides exactly on point coordinates
    (the closed box must keep those), one around everything, one beside the data."""
    rng = np.random.default_rng(seed)
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    boxes = [(lo[0], lo[1], hi[0], hi[1]), (hi[0] + 1, hi[1] + 1, hi[0] + 2, hi[1] + 2)]
    for _ in range(count):
        a, b = np.sort(rng.uniform(lo, hi, (2, 2)), axis=0)
        boxes.append((a[0], a[1], b[0], b[1]))
        p, q = points[rng.integers(len(points), size=2)]
        boxes.append((min(p[0], q[0]), min(p[1], q[1]), max(p[0], q[0]), max(p[1], q[1])))
    return boxes


def _in(points, box):
    return ((points[:, 0] >= box[0]) & (points[:, 0] <= box[2])
            & (points[:, 1] >= box[1]) & (points[:, 1] <= box[3]))


def test_sample_is_copc_and_a_plain_read_is_the_laz_read():
    with laspy.open(str(COPC)) as copc, laspy.open(str(PLAIN_LAZ)) as plain:
        assert is_copc_header(copc.header) and not is_copc_header(plain.header)
    cloud = read_cloud(COPC)
    points, classification = _whole()
    assert len(cloud) == 1065
    np.testing.assert_array_equal(cloud.points, points)
    np.testing.assert_array_equal(cloud.classification, classification)
    assert cloud.colors is not None and cloud.crs


@pytest.mark.parametrize("path, count", [(COPC, 12), (PLAIN_LAZ, 3)], ids=["copc", "plain-laz"])
def test_a_region_read_is_the_whole_read_filtered(path, count):
    points, classification = _whole(path)
    whole = read_cloud(path)
    checked = 0
    for box in _boxes(points, count):
        part = read_cloud(path, bounds=box)
        keep = _in(points, box)
        np.testing.assert_array_equal(part.points, points[keep])
        np.testing.assert_array_equal(part.classification, classification[keep])
        if whole.colors is not None:
            np.testing.assert_array_equal(part.colors, whole.colors[keep])
        ground = read_cloud(path, bounds=box, classes=[2]) if (keep & (classification == 2)).any() else None
        if ground is not None:
            np.testing.assert_array_equal(ground.points, points[keep & (classification == 2)])
        checked += int(keep.sum())
    assert checked > len(points)          # the boxes held points, not only empty reads


def test_a_region_read_fetches_only_the_nodes_meeting_the_box():
    points, _ = _whole()
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    quarter = (lo[0], lo[1], (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2)
    everything, some = region_cost(COPC, None), region_cost(COPC, quarter)
    assert everything.points == 1065 and len(everything.nodes) == 65
    assert _in(points, quarter).sum() <= some.points < everything.points
    assert some.bytes < everything.bytes
    assert points_to_read(COPC, quarter) == some.points
    with laspy.CopcReader.open(str(COPC)) as reader:        # laspy's own walk of the hierarchy
        from laspy.copc import Bounds, load_octree_for_query

        theirs = load_octree_for_query(reader.source, reader.copc_info, reader.root_page,
                                       Bounds(np.array([*quarter[:2], -1e9]), np.array([*quarter[2:], 1e9])))
        assert {(n.key.level, n.key.x, n.key.y, n.key.z) for n in theirs if n.point_count} == {n.key for n in some.nodes}

    class Counting(io.BytesIO):
        read_bytes = 0

        def read(self, n=-1):
            out = super().read(n)
            Counting.read_bytes += len(out)
            return out

        def readinto(self, buffer):
            got = super().readinto(buffer)
            Counting.read_bytes += got
            return got

    data = COPC.read_bytes()
    read_las(data, "x", open_stream=lambda: Counting(data), bounds=quarter)
    region = Counting.read_bytes
    Counting.read_bytes = 0
    read_las(data, "x", open_stream=lambda: Counting(data))
    assert region < Counting.read_bytes
    assert region < some.bytes + (Counting.read_bytes - everything.bytes)   # nodes + header-sized reads


def test_a_corrupt_node_entry_is_a_format_error():
    data = bytearray(COPC.read_bytes())
    with laspy.CopcReader.open(str(COPC)) as reader:
        root = reader.copc_info.hierarchy_root_offset
    # the root page's first entry: key (4 x i32), offset u64, byte size i32, point count i32
    struct.pack_into("<Q", data, root + 16, len(data) + 10)
    with pytest.raises(FormatError, match="corrupt hierarchy"):
        read_las(bytes(data), "bad.copc.laz", bounds=parse_box("0,0,1e7,1e7"))
    # the same entry made a hierarchy page outside the file, then a page that holds itself
    data = bytearray(COPC.read_bytes())
    struct.pack_into("<Qii", data, root + 16, len(data) + 10, 64, -1)
    with pytest.raises(FormatError, match="page .* outside the file"):
        read_las(bytes(data), "bad.copc.laz", bounds=parse_box("0,0,1e7,1e7"))
    struct.pack_into("<Qii", data, root + 16, root, 32, -1)
    with pytest.raises(FormatError, match="refers to itself"):
        read_las(bytes(data), "bad.copc.laz", bounds=parse_box("0,0,1e7,1e7"))


def _orphaned(data: bytes) -> bytes:
    """The sample with one leaf node's key moved to level 9: its parent is missing, so a
    walk of the hierarchy from the root no longer reaches it (the chunk table still does)."""
    data = bytearray(data)
    with laspy.CopcReader.open(str(COPC)) as reader:
        root, size = reader.copc_info.hierarchy_root_offset, reader.copc_info.hierarchy_root_size
    for at in range(root, root + size, 32):
        level, points = struct.unpack_from("<i", data, at)[0], struct.unpack_from("<i", data, at + 28)[0]
        if level == 3 and points > 0:
            struct.pack_into("<i", data, at, 9)
            return bytes(data)
    raise AssertionError("no leaf entry in the root page")


def test_a_hierarchy_that_misses_a_node_is_read_by_its_chunk_table(tmp_path):
    from c1mesh.formats.copc import Copc

    broken = tmp_path / "orphan.copc.laz"
    broken.write_bytes(_orphaned(COPC.read_bytes()))
    with Copc(lambda: open(broken, "rb"), str(broken), broken.stat().st_size) as copc:
        assert not copc.complete and sum(n.point_count for n in copc.nodes()) < 1065
    points, _ = _whole()
    assert points_to_read(broken, (-1e9, -1e9, 1e9, 1e9)) == 1065
    for box in _boxes(points, 4):
        np.testing.assert_array_equal(read_cloud(broken, bounds=box).points, points[_in(points, box)])


def test_bad_bounds_are_refused():
    with pytest.raises(InputError, match="four"):
        parse_box("1,2,3")
    with pytest.raises(InputError, match="empty"):
        parse_box("3,0,1,1")
    with pytest.raises(InputError, match="finite"):
        read_cloud(COPC, bounds=(0, 0, np.nan, 1))


def test_info_names_the_octree():
    summary = copc_summary(COPC)
    assert summary["nodes"] == 65 and summary["levels"] == 4 and summary["hierarchy_reaches_every_point"]
    points, _ = _whole()
    assert np.all(points >= np.array(summary["cube"]["min"]) - 1e-6)
    assert np.all(points <= np.array(summary["cube"]["max"]) + 1e-6)
    assert copc_summary(PLAIN_LAZ) is None


# ------------------------------------------------------------------ fits by bounds
def _region(points):
    """A box over most of the sample's middle: a few hundred points, cut through the data."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    return tuple(float(v) for v in (lo[0] + 0.1 * (hi[0] - lo[0]), lo[1] + 0.15 * (hi[1] - lo[1]),
            lo[0] + 0.8 * (hi[0] - lo[0]), lo[1] + 0.9 * (hi[1] - lo[1])))


def _ply_body(path: Path) -> tuple[list[bytes], bytes]:
    """A binary PLY's header lines without comments, and its body."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = [line for line in data[:end].split(b"\n") if not line.startswith(b"comment")]
    return header, data[end:]


def _filtered_las(path: Path, box, target: Path) -> Path:
    """The whole file filtered by numpy to the box, written as a plain LAS 1.4 with the
    same scales and offsets (the points' coordinates are the same to the bit)."""
    las = laspy.read(str(path))
    keep = _in(np.column_stack([las.x, las.y]), box)
    header = laspy.LasHeader(point_format=las.header.point_format.id, version="1.4")
    header.scales, header.offsets = las.header.scales, las.header.offsets
    out = laspy.LasData(header)
    out.X, out.Y, out.Z = las.X[keep], las.Y[keep], las.Z[keep]
    out.classification = np.asarray(las.classification)[keep]
    for c in ("red", "green", "blue"):
        out[c] = np.asarray(las[c])[keep]
    out.write(str(target))
    return target


@pytest.mark.parametrize("extra", [[], ["--memory", "20M"], ["-o-tif"]])
def test_bounds_outside_the_file_with_classes_say_so(tmp_path, extra):
    """--classes 2 with --bounds that hold no point said 'no points of class [2]; the file
    has classes []', of a file with classes 1 and 2: the empty read's (nothing in the box)
    class check ran before the check that names --bounds."""
    from click.testing import CliRunner

    from c1mesh.cli import main

    out = ["-o", str(tmp_path / "dem.tif"), "--resolution", "3"] if extra == ["-o-tif"] else \
        ["-o", str(tmp_path / "out.ply"), *extra]
    result = CliRunner().invoke(main, ["fit", str(DATA / "autzen_trim.laz"), "--classes", "2",
                                       "--bounds", "0,0,1,1", *out])
    assert result.exit_code == 1
    assert result.output.count("\n") == 1 and "no points inside --bounds 0.0,0.0,1.0,1.0" in result.output, \
        result.output
    assert not list(tmp_path.iterdir())


def test_a_fit_by_bounds_is_the_fit_of_the_filtered_points(tmp_path):
    from click.testing import CliRunner

    from c1mesh.cli import main

    box = _region(_whole()[0])
    runner = CliRunner()
    by_bounds, filtered = tmp_path / "bounds.ply", tmp_path / "filtered.ply"
    source = _filtered_las(COPC, box, tmp_path / "filtered.las")
    for args in (["fit", str(COPC), "--bounds", ",".join(map(repr, box)), "-o", str(by_bounds)],
                 ["fit", str(source), "-o", str(filtered)]):
        result = runner.invoke(main, args + ["--classes", "2", "--level", "2", "-q"])
        assert result.exit_code == 0, result.output
    assert _ply_body(by_bounds) == _ply_body(filtered)
    whole = tmp_path / "whole.ply"
    assert runner.invoke(main, ["fit", str(COPC), "--classes", "2", "--level", "2", "-q", "-o", str(whole)]).exit_code == 0
    assert _ply_body(whole)[1] != _ply_body(by_bounds)[1]     # the bounds did cut something


def test_a_tiled_fit_by_bounds_is_the_tiled_fit_of_the_filtered_points(tmp_path):
    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit, in_tiles

    box = _region(_whole()[0])
    source = _filtered_las(COPC, box, tmp_path / "filtered.las")
    options = FitOptions(level=2, memory=10**9, classes="all")
    report = fit(str(COPC), tmp_path / "bounds.ply", FitOptions(level=2, memory=10**9, bounds=box, classes="all"), tiles=TiledRun(per_tile=120)).report
    fit(str(source), tmp_path / "filtered.ply", options, tiles=TiledRun(per_tile=120)).report
    assert report["tiles"] >= 4
    assert _ply_body(tmp_path / "bounds.ply") == _ply_body(tmp_path / "filtered.ply")
    # the tiling decision counts the nodes a region read decodes, not the whole header
    budget = 1065 * 1800 - 1
    assert in_tiles(str(COPC), FitOptions(memory=budget))
    assert not in_tiles(str(COPC), FitOptions(memory=budget, bounds=box))


def test_a_seamless_survey_by_bounds_reads_each_input_filtered(tmp_path):
    from c1mesh.core.plan import PointSelection
    from c1mesh.survey.tiles import load_survey

    points, _ = _whole()
    box = _region(points)
    everything = (-1e9, -1e9, 1e9, 1e9)
    plain = _filtered_las(COPC, everything, tmp_path / "plain.las")       # the same points, not COPC
    survey = load_survey([str(COPC), str(plain)], PointSelection(bounds=box, classes="all"))
    inside = points[_in(points, box)]
    np.testing.assert_array_equal(survey.cloud.points, np.concatenate([inside, inside]))
    assert list(np.diff(survey.offsets)) == [len(inside), len(inside)]
    assert 0 < len(inside) < len(points)


def test_cli_info_says_copc(tmp_path):
    import subprocess
    import sys

    def info(path):
        done = subprocess.run([sys.executable, "-m", "c1mesh.cli", "info", str(path)], capture_output=True,
                              timeout=300, check=True)
        return json.loads(done.stdout)

    facts = info(COPC)
    assert facts["copc"]["nodes"] == 65 and facts["points"] == 1065
    plain = _filtered_las(COPC, (-1e9, -1e9, 1e9, 1e9), tmp_path / "plain.laz")
    facts = info(plain)
    assert "copc" not in facts and facts["points"] == 1065


def test_copc_on_stdin_is_fitted_as_the_file(tmp_path):
    import subprocess
    import sys

    box = ",".join(map(repr, _region(_whole()[0])))
    args = ["--classes", "2", "--level", "1", "--bounds", box, "-q", "-o"]
    fit = [sys.executable, "-m", "c1mesh.cli", "fit"]
    subprocess.run(fit + [str(COPC)] + args + [str(tmp_path / "file.ply")], check=True, timeout=300)
    subprocess.run(fit + ["-", "--input-format", "copc"] + args + [str(tmp_path / "stdin.ply")],
                   input=COPC.read_bytes(), check=True, timeout=300)
    assert (tmp_path / "file.ply").read_bytes() == (tmp_path / "stdin.ply").read_bytes()
