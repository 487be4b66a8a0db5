"""Readers and writers of c1mesh.formats against independent truth.

Truth is either values constructed here (files assembled byte by byte with struct /
numpy, not with the code under test), another library's reading of the same file
(open3d, laspy, trimesh), or a round trip through a writer with exact comparison.
"""
from __future__ import annotations

import functools
import io
import struct
import time
import warnings
from pathlib import Path

import laspy
import lzf
import numpy as np
import open3d as o3d
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from c1mesh.core.cloud import PointCloud, SurfaceMesh
from c1mesh.core.errors import C1MeshError, DependencyError, FormatError, InputError
from c1mesh.formats import SUPPORTED_INPUT, SUPPORTED_OUTPUT, atomic_output, read_cloud, write_mesh
from c1mesh.formats.lzf import LZFError, lzf_decompress

REAL = Path(__file__).resolve().parent.parent / "data_samples"  # copies of ../shared/data/real
SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"
BIG = 6.4e5 + 1e-7  # needs a double: float32 would round it to 640000.0


def real(name: str) -> Path:
    """A real scan: the data_samples copy if there is one, else the shared original."""
    path = SAMPLES / name if (SAMPLES / name).exists() else REAL / name
    assert path.exists(), f"real sample {name} is missing from data_samples/"
    return path


# ============================================================================ PLY, built by hand
PLY_CODES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
             "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2",
             "int32": "i4", "uint32": "u4", "float32": "f4", "float64": "f8"}
VERTEX_PROPS = [("x", "double"), ("y", "float32"), ("z", "float"), ("nx", "float"), ("ny", "float"),
                ("nz", "float"), ("red", "uchar"), ("green", "uint8"), ("blue", "uchar"), ("alpha", "uchar"),
                ("c_char", "char"), ("c_short", "short"), ("c_ushort", "ushort"), ("c_int", "int"),
                ("c_uint", "uint"), ("c_int16", "int16"), ("c_uint32", "uint32"), ("c_f64", "float64")]


def vertex_table(endian: str = "<") -> np.ndarray:
    """Four vertices with one value per property type; floats exact in float32 where declared so."""
    rows = np.zeros(4, [(n, endian + PLY_CODES[t]) for n, t in VERTEX_PROPS])
    rows["x"] = [BIG, -1.5, 0.0, 1e-300]
    rows["y"] = [0.25, 2.0, -3.5, 1e6]
    rows["z"] = [1.0, 2.5, -0.125, 7.0]
    rows["nx"], rows["ny"], rows["nz"] = [0, 1, 0, 0.6], [0, 0, 1, 0.8], [1, 0, 0, 0]
    rows["red"], rows["green"], rows["blue"], rows["alpha"] = [255, 0, 1, 2], [0, 255, 3, 4], [9, 8, 7, 6], [255] * 4
    rows["c_char"], rows["c_short"], rows["c_ushort"] = [-128, 127, 0, -1], [-32768, 5, 6, 32767], [65535, 0, 1, 2]
    rows["c_int"], rows["c_uint"] = [-(2**31), 2**31 - 1, 0, 1], [2**32 - 1, 0, 1, 2]
    rows["c_int16"], rows["c_uint32"], rows["c_f64"] = [-5, 5, 0, 1], [7, 8, 9, 10], [0.1, 1 / 3, -2.0, 1e-10]
    return rows


FACES_RAGGED = [([0, 1, 2], 7), ([0, 1, 2, 3], 9)]
FACES_UNIFORM = [([0, 1, 2], 7), ([1, 2, 3], 9)]


def ply_bytes(fmt: str, faces=FACES_RAGGED, faces_first: bool = True) -> bytes:
    """A PLY with a face element (list + scalar) before or after the vertices, and an edge element."""
    endian = {"ascii": "<", "binary_little_endian": "<", "binary_big_endian": ">"}[fmt]
    verts = vertex_table(endian)
    vhead = [f"element vertex {len(verts)}"] + [f"property {t} {n}" for n, t in VERTEX_PROPS]
    fhead = [f"element face {len(faces)}", "property list uchar int vertex_indices", "property uchar flags"]
    ehead = ["element edge 1", "property int vertex1", "property int vertex2"]
    head = ["ply", f"format {fmt} 1.0", "comment built by hand", "obj_info test"]
    head += (fhead + vhead if faces_first else vhead + fhead) + ehead + ["end_header"]
    if fmt == "ascii":
        vbody = "".join(" ".join(repr(v.item()) for v in row) + "\n" for row in verts)
        fbody = "".join(f"{len(idx)} {' '.join(map(str, idx))} {flag}\n" for idx, flag in faces)
        body = ((fbody + vbody) if faces_first else (vbody + fbody)) + "0 1\n"
        return ("\n".join(head) + "\n" + body).encode()
    fbody = b"".join(struct.pack(f"{endian}B{len(i)}iB", len(i), *i, fl) for i, fl in faces)
    vbody = verts.tobytes()
    body = (fbody + vbody if faces_first else vbody + fbody) + struct.pack(endian + "ii", 0, 1)
    return ("\n".join(head) + "\n").encode() + body


def check_hand_ply(cloud: PointCloud) -> None:
    truth = vertex_table("=")
    expect_pts = np.column_stack([truth["x"], truth["y"], truth["z"]]).astype(np.float64)
    np.testing.assert_array_equal(cloud.points, expect_pts)
    assert cloud.points.dtype == np.float64 and cloud.points[0, 0] == BIG
    np.testing.assert_array_equal(cloud.normals, np.column_stack([truth["nx"], truth["ny"], truth["nz"]]))
    np.testing.assert_array_equal(cloud.colors, np.column_stack([truth[c] for c in ("red", "green", "blue", "alpha")]))
    assert cloud.colors.dtype == np.uint8
    assert set(cloud.extra) == {n for n, _ in VERTEX_PROPS[10:]}
    for name, t in VERTEX_PROPS[10:]:
        assert cloud.extra[name].dtype == np.dtype(PLY_CODES[t]), name
        np.testing.assert_array_equal(cloud.extra[name], truth[name])


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("faces", [FACES_RAGGED, FACES_UNIFORM], ids=["ragged", "uniform"])
@pytest.mark.parametrize("faces_first", [True, False], ids=["faces-first", "faces-last"])
def test_ply_hand_built(tmp_path, fmt, faces, faces_first):
    path = tmp_path / "hand.PLY"  # upper-case extension on purpose
    path.write_bytes(ply_bytes(fmt, faces, faces_first))
    check_hand_ply(read_cloud(path))


@pytest.mark.parametrize("ascii", [False, True])
def test_ply_written_by_open3d(tmp_path, ascii):
    src = o3d.io.read_point_cloud(str(real("o3d_cloud_bin_0.pcd")))
    path = tmp_path / "room.ply"
    o3d.io.write_point_cloud(str(path), src, write_ascii=ascii)
    truth = o3d.io.read_point_cloud(str(path))
    cloud = read_cloud(path)
    np.testing.assert_allclose(cloud.points, np.asarray(truth.points), rtol=0, atol=1e-12)
    np.testing.assert_allclose(cloud.normals, np.asarray(truth.normals), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(cloud.colors, np.round(np.asarray(truth.colors) * 255).astype(np.uint8))


# ============================================================================ OBJ
def test_obj_per_vertex_normals_and_colors(tmp_path):
    path = tmp_path / "cloud.obj"
    path.write_text("# export\nmtllib x.mtl\no cloud\nv 1 2 3 1 0 0.5\nv 640000.0000001 -5 6.5 0 1 0\n"
                    "vn 0 0 1\nvn 0 1 0\nvt 0.5 0.5\nf 1//1 2//2 1//1\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [BIG, -5, 6.5]])
    np.testing.assert_array_equal(cloud.normals, [[0, 0, 1], [0, 1, 0]])
    np.testing.assert_array_equal(cloud.colors, [[255, 0, 128], [0, 255, 0]])


def test_obj_normals_from_faces(tmp_path):
    path = tmp_path / "mesh.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 5 5 5\nvn 0 0 1\nvn 1 0 0\nf 1//1 2//2 -2//-1\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.normals[:3], [[0, 0, 1], [1, 0, 0], [1, 0, 0]])
    assert np.isnan(cloud.normals[3]).all()  # no face names a normal for vertex 4


def test_obj_without_normals(tmp_path):
    path = tmp_path / "plain.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    cloud = read_cloud(path)
    assert cloud.normals is None and cloud.colors is None and len(cloud) == 3


# ============================================================================ XYZ / TXT / CSV
PTS = np.array([[BIG, 1.5, -2.0], [0.1, 0.2, 0.3], [-7.0, 8.0, 9.0]])
NRM = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0], [-1.0, 0.0, 0.0]])
RGB = np.array([[255, 0, 10], [1, 2, 3], [200, 100, 50]])


def table_text(*blocks: np.ndarray, sep: str = " ") -> str:
    return "".join(sep.join(repr(float(v)) for v in row) + "\n" for row in np.hstack(blocks))


@pytest.mark.parametrize("ext", ["xyz", "txt", "csv"])
def test_xyz_with_header(tmp_path, ext):
    sep = "," if ext == "csv" else " "
    path = tmp_path / f"points.{ext}"
    scalar = np.array([[1.0], [2.0], [3.0]])
    path.write_text("# comment\n" + sep.join(["X", "Y", "Z", "red", "green", "blue", "nx", "ny", "nz", "intensity"])
                    + "\n" + table_text(PTS, RGB, NRM, scalar, sep=sep))
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.points, PTS)
    np.testing.assert_array_equal(cloud.normals, NRM)
    np.testing.assert_array_equal(cloud.colors, RGB)
    np.testing.assert_array_equal(cloud.extra["intensity"], scalar[:, 0])


def test_xyz_cloudcompare_header(tmp_path):
    path = tmp_path / "cc.txt"
    path.write_text("//X,Y,Z,R,G,B,Nx,Ny,Nz\n" + table_text(PTS, RGB, NRM, sep=","))
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.colors, RGB)
    np.testing.assert_array_equal(cloud.normals, NRM)


@pytest.mark.parametrize(
    "blocks, expect",
    [
        ((PTS,), {}),
        ((PTS, NRM[:, :1]), {"scalar": NRM[:, 0]}),
        ((PTS, NRM), {"normals": NRM}),
        ((PTS, RGB), {"colors": RGB}),
        ((PTS, NRM[:, :1], RGB), {"scalar": NRM[:, 0], "colors": RGB}),  # .pts order
        ((PTS, NRM, NRM[:, 1:2]), {"normals": NRM, "scalar": NRM[:, 1]}),
        ((PTS, NRM, RGB), {"normals": NRM, "colors": RGB}),
        ((PTS, RGB, NRM), {"normals": NRM, "colors": RGB}),
    ],
    ids=["3", "4", "6-normals", "6-rgb", "7-pts", "7-normals", "9-n-rgb", "9-rgb-n"],
)
def test_xyz_without_header(tmp_path, blocks, expect):
    path = tmp_path / "bare.xyz"
    path.write_text("# written by hand\n\n" + table_text(*blocks))
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.points, PTS)
    for key in ("normals", "colors"):
        if key in expect:
            np.testing.assert_array_equal(getattr(cloud, key), expect[key])
        else:
            assert getattr(cloud, key) is None
    if "scalar" in expect:
        np.testing.assert_array_equal(cloud.extra["scalar"], expect["scalar"])
    else:
        assert cloud.extra == {}


@pytest.mark.parametrize("text", [
    '"","x","y","z"\n"1",{0}\n"2",{1}\n"3",{2}\n',              # R write.csv: quoted, index column
    ',x,y,z\n0,{0}\n1,{1}\n2,{2}\n',                           # pandas to_csv: unnamed index column
    '\ufeffX;Y;Z\n{0;}\n{1;}\n{2;}\n',                          # byte-order mark, semicolons
], ids=["R", "pandas", "bom"])
def test_csv_from_r_and_pandas(tmp_path, text):
    rows = [",".join(repr(float(v)) for v in row) for row in PTS]
    text = text.replace("{0;}", rows[0].replace(",", ";")).replace("{1;}", rows[1].replace(",", ";"))
    text = text.replace("{2;}", rows[2].replace(",", ";")).format(*rows)
    (tmp_path / "r.csv").write_bytes(text.encode("utf-8"))
    cloud = read_cloud(tmp_path / "r.csv")
    np.testing.assert_array_equal(cloud.points, PTS)
    assert cloud.normals is None and cloud.colors is None


@pytest.mark.parametrize("text, line", [("6,370;2,698;0,026\n0,410;0,165;0,120\n8,133;9,128;0,288\n", 1),
                                        ("X;Y;Z\n6,370;2,698;0,026\n0,410;0,165;0,120\n8,133;9,128;0,288\n", 2)],
                         ids=["no header", "header"])
def test_semicolon_values_with_decimal_commas_are_named_as_such(tmp_path, text, line):
    """Excel's CSV in many locales: semicolons between values, decimal commas in them. One
    line names the line and the decimal commas (it said "3 values, expected 6")."""
    (tmp_path / "excel.csv").write_text(text)
    with pytest.raises(FormatError, match=f"line {line} writes decimal commas .*decimal points"):
        read_cloud(tmp_path / "excel.csv")


def test_csv_named_columns_in_any_order(tmp_path):
    (tmp_path / "geo.csv").write_text("elev,Lat,LON,red,green,blue\n" + table_text(PTS[:, ::-1], RGB, sep=","))
    cloud = read_cloud(tmp_path / "geo.csv")
    np.testing.assert_array_equal(cloud.points, PTS)
    np.testing.assert_array_equal(cloud.colors, RGB)


@pytest.mark.parametrize("header, column", [
    ('"","x","y","z"', "z"),                                    # R's write.csv (MASS topo)
    ("easting,northing,h", "h"),
    ("East,North,Elevation", "elevation"),
    ("lon;lat;height", "height"),
    ("x y elev nx ny nz", "elev"),
], ids=["R-z", "h", "elevation", "height", "with-normals"])
def test_header_names_the_height_column(tmp_path, header, column):
    """Issue 21: a header's z, elev, elevation, height or h column is recorded as the height
    (and h is read as the third coordinate), so the fit can take it in units of its own."""
    sep = ";" if ";" in header else "," if "," in header else " "
    blocks = (np.arange(3.0)[:, None], PTS) if header.startswith('""') else (PTS,)
    blocks += (NRM,) if "nx" in header else ()
    (tmp_path / "h.csv").write_text(header + "\n" + table_text(*blocks, sep=sep))
    cloud = read_cloud(tmp_path / "h.csv")
    np.testing.assert_array_equal(cloud.points, PTS)
    assert cloud.height_column == column
    assert cloud.subset(np.array([True, False, True])).height_column == column


def test_headerless_table_names_no_height_column(tmp_path):
    (tmp_path / "bare.xyz").write_text(table_text(PTS))
    assert read_cloud(tmp_path / "bare.xyz").height_column is None


@pytest.mark.parametrize("scale", [1.0, 255.0], ids=["0..1", "0..255"])
def test_headerless_xyzrgb_is_not_read_as_normals(tmp_path, scale):
    rgb = np.array([[0.2, 0.4, 0.6], [1.0, 1.0, 1.0], [0.0, 0.5, 0.25]])
    (tmp_path / "c.xyz").write_text(table_text(PTS, np.round(rgb * scale) if scale > 1 else rgb))
    cloud = read_cloud(tmp_path / "c.xyz")
    assert cloud.normals is None
    np.testing.assert_array_equal(cloud.colors, np.round(rgb * 255))


def test_headerless_triple_that_is_neither_normals_nor_colours_is_refused(tmp_path):
    (tmp_path / "odd.xyz").write_text(table_text(PTS, PTS * 3.5))
    with pytest.raises(FormatError, match=r"odd.xyz.*columns 4-6 are neither unit normals nor colours.*header"):
        read_cloud(tmp_path / "odd.xyz")


def test_xyzn_written_by_open3d(tmp_path):
    src = o3d.io.read_point_cloud(str(real("pcl_bun0.pcd")))
    o3d.io.write_point_cloud(str(tmp_path / "bunny.xyzn"), src)
    (tmp_path / "bunny.xyzn").rename(tmp_path / "bunny.xyz")
    cloud = read_cloud(tmp_path / "bunny.xyz")
    np.testing.assert_allclose(cloud.points, np.asarray(src.points), atol=1e-9)
    np.testing.assert_allclose(cloud.normals, np.asarray(src.normals), atol=1e-9)


# ============================================================================ PCD
def o3d_cloud(n: int, seed: int = 0, repetitive: bool = False) -> o3d.geometry.PointCloud:
    rng = np.random.default_rng(seed)
    pts = rng.random((n, 3)) * 100
    if repetitive:  # long runs and short periods exercise LZF back references
        pts = np.repeat(np.round(pts[: n // 50], 1), 50, axis=0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    cloud.normals = o3d.utility.Vector3dVector(rng.normal(size=(len(pts), 3)))
    cloud.colors = o3d.utility.Vector3dVector(rng.integers(0, 256, (len(pts), 3)) / 255)
    return cloud


@pytest.mark.parametrize("kind", ["ascii", "binary", "binary_compressed", "compressed-repetitive"])
def test_pcd_written_by_open3d(tmp_path, kind):
    src = o3d_cloud(5000, repetitive=kind == "compressed-repetitive")
    path = tmp_path / "cloud.pcd"
    o3d.io.write_point_cloud(str(path), src, write_ascii=kind == "ascii", compressed="compressed" in kind)
    assert f"DATA {kind.replace('compressed-repetitive', 'binary_compressed')}".encode() in path.read_bytes()[:400]
    truth = o3d.io.read_point_cloud(str(path))
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.points, np.asarray(truth.points))
    np.testing.assert_array_equal(cloud.normals, np.asarray(truth.normals))
    np.testing.assert_array_equal(cloud.colors, np.round(np.asarray(truth.colors) * 255).astype(np.uint8))
    np.testing.assert_allclose(cloud.points, np.asarray(src.points), rtol=1e-6)  # float32 of the truth


def test_pcd_hand_built_organised_binary(tmp_path):
    """2 x 3 organised cloud: NaN point kept, COUNT 2 field split, '_' padding dropped, rgba unpacked."""
    rows = np.zeros(6, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_", "<f4"), ("rgba", "<u4"), ("h", "<i2", (2,))])
    rows["x"], rows["y"], rows["z"] = np.arange(6), np.arange(6) * 2, np.arange(6) * 3
    rows["x"][4] = rows["y"][4] = rows["z"][4] = np.nan
    rows["rgba"] = [0x80FF0001, 0xFF000000, 0, 0x01020304, 0xFFFFFFFF, 0x00ABCDEF]
    rows["h"] = np.arange(12).reshape(6, 2)
    head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z _ rgba h\nSIZE 4 4 4 4 4 2\nTYPE F F F F U I\n"
            "COUNT 1 1 1 1 1 2\nWIDTH 3\nHEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 6\nDATA binary\n")
    path = tmp_path / "organised.pcd"
    path.write_bytes(head.encode() + rows.tobytes())
    cloud = read_cloud(path)
    assert len(cloud) == 6 and np.isnan(cloud.points[4]).all()
    np.testing.assert_array_equal(cloud.points[5], [5, 10, 15])
    np.testing.assert_array_equal(cloud.colors[:4], [[255, 0, 1, 128], [0, 0, 0, 255], [0, 0, 0, 0], [2, 3, 4, 1]])
    np.testing.assert_array_equal(cloud.extra["h_1"], np.arange(1, 12, 2))
    assert set(cloud.extra) == {"h_0", "h_1"} and cloud.normals is None


def test_pcd_v06_ascii_without_count_and_viewpoint(tmp_path):
    path = tmp_path / "old.pcd"
    path.write_text("VERSION .6\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH 2\nHEIGHT 1\nPOINTS 2\n"
                    "DATA ascii\n1 2 3 4278190335\n640000.0000001 5 6 0\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [BIG, 5, 6]])  # ascii keeps the text's precision
    np.testing.assert_array_equal(cloud.colors, [[0, 0, 255], [0, 0, 0]])  # 0xFF0000FF: alpha ignored for rgb


def test_real_pcd_files_match_open3d():
    for name in ("pcl_bun0.pcd", "o3d_cloud_bin_0.pcd", "table_scene_mug_stereo_textured.pcd"):
        path = real(name)
        truth = o3d.io.read_point_cloud(str(path))
        cloud = read_cloud(path)
        np.testing.assert_array_equal(cloud.points, np.asarray(truth.points))  # NaN == NaN here
        if truth.has_normals():
            np.testing.assert_array_equal(cloud.normals, np.asarray(truth.normals))
        if truth.has_colors():
            np.testing.assert_array_equal(cloud.colors[:, :3], np.round(np.asarray(truth.colors) * 255))
    bunny = read_cloud(real("pcl_bun0.pcd"))
    assert len(bunny) == 397 and "curvature" in bunny.extra
    scene = read_cloud(real("table_scene_mug_stereo_textured.pcd"))
    assert len(scene) == 307200 and int((~np.isnan(scene.points).any(axis=1)).sum()) == 209280


def test_lzf_overlapping_and_long_back_references():
    # literal 'ab', then copy 5 from distance 2 (overlapping), then copy 9+2 from distance 1 (length byte)
    stream = bytes([1]) + b"ab" + bytes([(5 - 2) << 5, 1]) + bytes([7 << 5, 9 + 2 - 2 - 7, 0])
    assert lzf_decompress(stream, 2 + 5 + 11) == b"ab" + b"ababa" + b"a" * 11
    for bad, size in ((bytes([5]) + b"abc", 6),                    # literal run longer than the input
                      (bytes([0]) + b"a" + bytes([1 << 5, 9]), 4),  # reference before the start
                      (stream, 2 + 5 + 10), (stream, 2 + 5 + 12),   # decodes to another size
                      (bytes([0]) + b"a", 0)):                      # data where nothing is promised
        with pytest.raises(LZFError):
            lzf_decompress(bad, size)


def test_lzf_has_one_decoder_the_required_c_library():
    """python-lzf is a required dependency, so there is no pure-Python fallback to keep in step."""
    import c1mesh.formats.lzf as module

    assert not [n for n in vars(module) if "python" in n.lower()]
    payload = np.random.default_rng(5).integers(0, 4, 100_000, np.uint8).tobytes()
    assert lzf_decompress(lzf.compress(payload), len(payload)) == payload


# ============================================================================ LAS / LAZ
def laspy_file(path: Path | io.BytesIO) -> laspy.LasData:
    """Three points with large scaled coordinates, classes and 16-bit colours, written to `path`."""
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = [0.001, 0.001, 0.01]
    header.offsets = [640000.0, 850000.0, 0.0]
    las = laspy.LasData(header)
    las.x = np.array([640000.123, 640001.5, 640002.999])
    las.y = np.array([850000.0, 850000.001, 850010.5])
    las.z = np.array([1.25, 2.5, -3.75])
    las.classification = np.array([2, 5, 2], np.uint8)
    las.red = np.array([65535, 256, 0], np.uint16)
    las.green = np.array([0, 512, 4096], np.uint16)
    las.blue = np.array([255 * 256, 0, 1], np.uint16)
    las.intensity = np.array([10, 20, 30], np.uint16)
    las.write(path if isinstance(path, io.BytesIO) else str(path))
    return las


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_written_by_laspy(tmp_path, ext):
    las = laspy_file(tmp_path / f"tile.{ext}")
    cloud = read_cloud(tmp_path / f"tile.{ext}")
    np.testing.assert_array_equal(cloud.points, np.column_stack([las.x, las.y, las.z]))
    np.testing.assert_allclose(cloud.points[0], [640000.123, 850000.0, 1.25], atol=1e-9)
    np.testing.assert_array_equal(cloud.classification, [2, 5, 2])
    np.testing.assert_array_equal(cloud.colors, [[255, 0, 255], [1, 2, 0], [0, 16, 0]])  # 16-bit >> 8
    assert cloud.extra == {}  # intensity etc. are not kept: the fit never uses them


@pytest.mark.parametrize("name", ["4_6_crop.las", "autzen_trim.laz"])
def test_real_las_files_match_laspy(name):
    path = real(name)
    truth = laspy.read(str(path))
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.points, np.column_stack([truth.x, truth.y, truth.z]))
    np.testing.assert_array_equal(cloud.classification, truth.classification)
    assert int((cloud.classification == 2).sum()) == {"4_6_crop.las": 9003, "autzen_trim.laz": 26107}[name]
    if name == "autzen_trim.laz":
        np.testing.assert_array_equal(cloud.colors, np.column_stack([truth.red, truth.green, truth.blue]))
    else:
        assert cloud.colors is None  # its RGB fields are all zero


@pytest.mark.parametrize("name", ["4_6_crop.las", "autzen_trim.laz"])
def test_las_classes_filter_matches_laspy(name):
    truth = laspy.read(str(real(name)))
    mask = np.isin(truth.classification, [2, 9])
    cloud = read_cloud(real(name), classes=(2, 9))
    np.testing.assert_array_equal(cloud.points, np.column_stack([truth.x, truth.y, truth.z])[mask])
    np.testing.assert_array_equal(cloud.classification, truth.classification[mask])
    with pytest.raises(InputError, match=r"no points of class \[77\]; the file has classes \[.*2"):
        read_cloud(real(name), classes=(77,))


def many_chunk_laz(path: Path, n: int = 120_000) -> None:
    """A LAZ of n points with RGB over several 50 000-point LAZ chunks (lazrs's parallel
    decoder splits its work by chunk), coordinates and classes from a seeded generator."""
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [500000.0, 4000000.0, 0.0]
    rng = np.random.default_rng(7)
    las = laspy.LasData(header)
    las.x, las.y = 500000 + rng.uniform(0, 200, n), 4000000 + rng.uniform(0, 200, n)
    las.z = rng.normal(100, 3, n)
    las.classification = rng.choice(np.array([1, 2, 6], np.uint8), n)
    for band in ("red", "green", "blue"):
        las[band] = rng.integers(0, 65536, n, dtype=np.uint16)
    las.write(str(path))


@pytest.mark.parametrize("read", ["whole", "survey chunks"])
def test_laz_decoder_follows_the_thread_knob_and_decodes_the_same_points(tmp_path, monkeypatch, read):
    """One worker decodes in lazrs's single thread, more in its parallel decoder; both give
    laspy's points exactly (the whole-file reader and the survey's chunk reader alike)."""
    from c1mesh.core.threads import limit
    from c1mesh.formats.copc import region_chunks

    many_chunk_laz(tmp_path / "tile.laz")
    truth = laspy.read(str(tmp_path / "tile.laz"), laz_backend=laspy.LazBackend.Lazrs)
    opened, laspy_open = [], laspy.open

    def recording_open(*args, **kwargs):
        opened.append(kwargs.get("laz_backend"))
        return laspy_open(*args, **kwargs)
    monkeypatch.setattr(laspy, "open", recording_open)

    def decode():
        if read == "whole":
            cloud = read_cloud(tmp_path / "tile.laz")
            return cloud.points, cloud.classification
        parts = list(region_chunks(tmp_path / "tile.laz", None, 30_000))
        return (np.concatenate([np.column_stack([p.x, p.y, p.z]) for p in parts]),
                np.concatenate([np.asarray(p.classification) for p in parts]))
    for threads, backend in ((1, laspy.LazBackend.Lazrs), (2, laspy.LazBackend.LazrsParallel)):
        opened.clear()
        with limit(threads):
            points, classes = decode()
        assert opened == [backend]
        np.testing.assert_array_equal(points, np.column_stack([truth.x, truth.y, truth.z]))
        np.testing.assert_array_equal(classes, truth.classification)


def test_laz_without_backend_raises_dependency_error(monkeypatch):
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    with pytest.raises(DependencyError, match=r'pip install "laspy\[lazrs\]"'):
        read_cloud(real("autzen_trim.laz"))


# ============================================================================ streams
def test_read_from_binary_streams():
    check_hand_ply(read_cloud(io.BytesIO(ply_bytes("binary_little_endian")), fmt="ply"))
    cloud = read_cloud(io.BytesIO(table_text(PTS).encode()), fmt=".XYZ")
    np.testing.assert_array_equal(cloud.points, PTS)
    cloud = read_cloud(io.BytesIO(real("4_6_crop.las").read_bytes()), fmt="las")
    assert len(cloud) == 23875
    with pytest.raises(InputError, match="explicit format"):
        read_cloud(io.BytesIO(b"1 2 3\n"))


def test_write_to_binary_streams():
    mesh = sample_mesh()
    out = io.BytesIO()
    write_mesh(mesh, out)
    assert out.getvalue().startswith(b"ply\nformat binary_little_endian 1.0\n")
    np.testing.assert_array_equal(read_cloud(io.BytesIO(out.getvalue()), fmt="ply").points, mesh.vertices)
    text = io.TextIOWrapper(io.BytesIO())  # like sys.stdout: its .buffer takes the bytes
    write_mesh(mesh, text, fmt="obj")
    assert text.buffer.getvalue().startswith(b"# written by c1mesh\nv ")


# ============================================================================ writers
def sample_mesh(colors: bool = True) -> SurfaceMesh:
    """A closed tetrahedron, counter-clockwise from outside, far from the origin."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.5 + [BIG, 8.5e5 + 1e-7, 1e-7]
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    n = (v - v.mean(axis=0)) / np.linalg.norm(v - v.mean(axis=0), axis=1, keepdims=True)
    c = np.array([[255, 0, 0, 255], [0, 255, 0, 128], [0, 0, 255, 0], [1, 2, 3, 4]], np.uint8) if colors else None
    return SurfaceMesh(vertices=v, faces=f, vertex_normals=n, vertex_colors=c)


@pytest.mark.parametrize("ascii", [False, True])
def test_ply_writer_round_trip_double_precision(tmp_path, ascii):
    mesh = sample_mesh()
    path = tmp_path / "mesh.ply"
    write_mesh(mesh, path, ascii=ascii)
    head = path.read_bytes()[:400]
    assert (b"format ascii 1.0" if ascii else b"format binary_little_endian 1.0") in head
    assert b"property double x" in head and b"property list uchar int vertex_indices" in head
    tm = trimesh.load(path, process=False)
    np.testing.assert_array_equal(tm.vertices, mesh.vertices)
    np.testing.assert_array_equal(tm.faces, mesh.faces)
    np.testing.assert_array_equal(tm.visual.vertex_colors, mesh.vertex_colors)
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.points, mesh.vertices)
    np.testing.assert_array_equal(cloud.normals, mesh.vertex_normals)
    np.testing.assert_array_equal(cloud.colors, mesh.vertex_colors)
    assert cloud.points[0, 0] == BIG


def test_obj_writer_round_trip(tmp_path):
    mesh = sample_mesh()
    write_mesh(mesh, tmp_path / "mesh.obj")
    cloud = read_cloud(tmp_path / "mesh.obj")
    np.testing.assert_array_equal(cloud.points, mesh.vertices)
    np.testing.assert_array_equal(cloud.normals, mesh.vertex_normals)
    np.testing.assert_array_equal(cloud.colors, mesh.vertex_colors[:, :3])
    tm = trimesh.load(tmp_path / "mesh.obj", process=False)
    np.testing.assert_array_equal(tm.vertices[tm.faces], mesh.vertices[mesh.faces])


def test_stl_off_glb_writers_read_by_trimesh(tmp_path):
    mesh = sample_mesh()
    for ext, atol in (("stl", 0.07), ("off", 0.0), ("glb", 0.07)):  # float32 at 6.4e5: steps of 1/16
        write_mesh(mesh, tmp_path / f"mesh.{ext}")
        tm = trimesh.load(tmp_path / f"mesh.{ext}", process=False, force="mesh")
        np.testing.assert_allclose(tm.vertices[tm.faces], mesh.vertices[mesh.faces], rtol=0, atol=atol, err_msg=ext)
    stl = trimesh.load(tmp_path / "mesh.stl", process=False)
    outward = stl.triangles_center - stl.triangles_center.mean(axis=0)
    assert (np.einsum("ij,ij->i", stl.face_normals, outward) > 0).all()
    stl.merge_vertices()
    assert stl.is_volume  # watertight and consistently wound


# ============================================================================ atomic writes
def failing_writer(mesh, f, ascii=False):
    f.write(b"half a file")
    raise RuntimeError("disk on fire")


def test_failed_write_leaves_no_file(tmp_path, monkeypatch):
    import c1mesh.formats as formats

    monkeypatch.setitem(formats._WRITERS, "ply", failing_writer)
    with pytest.raises(RuntimeError):
        write_mesh(sample_mesh(), tmp_path / "new.ply")
    assert list(tmp_path.iterdir()) == []
    old = tmp_path / "old.ply"
    old.write_bytes(b"previous result")
    with pytest.raises(RuntimeError):
        write_mesh(sample_mesh(), old)
    assert old.read_bytes() == b"previous result" and list(tmp_path.iterdir()) == [old]


def test_atomic_output_modes(tmp_path):
    with atomic_output(tmp_path / "report.json", mode="w") as f:
        f.write('{"ok": true}')
        assert not (tmp_path / "report.json").exists()  # only visible once complete
    assert (tmp_path / "report.json").read_text() == '{"ok": true}'
    with pytest.raises(KeyError):
        with atomic_output(tmp_path / "other.bin", mode="path") as tmp:
            tmp.write_bytes(b"x")
            raise KeyError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o077])
def test_atomic_output_permissions_follow_the_umask_without_changing_it(tmp_path, monkeypatch, umask):
    """Files get 0666 minus the umask (as open() would give), and the umask is read, never
    set: setting it, even briefly, would race with files other threads create."""
    import os
    old = os.umask(umask)
    try:
        def no_umask_changes(mask):
            raise AssertionError("atomic_output changed the process umask")
        monkeypatch.setattr(os, "umask", no_umask_changes)
        with atomic_output(tmp_path / "out.bin") as f:
            f.write(b"x")
        monkeypatch.undo()
    finally:
        os.umask(old)
    assert (tmp_path / "out.bin").stat().st_mode & 0o777 == 0o666 & ~umask


def test_unwritable_directory(tmp_path, monkeypatch):
    import c1mesh.core.outputs as atomic

    def denied(**kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(atomic.tempfile, "mkstemp", denied)  # tests run as root: chmod would not stop us
    with pytest.raises(InputError, match="Cannot write .*out.ply.*Permission denied"):
        write_mesh(sample_mesh(), tmp_path / "out.ply")


def test_write_errors(tmp_path):
    (tmp_path / "file").write_text("x")
    cases = [(tmp_path / "missing" / "m.ply", "does not exist"), (tmp_path / "file" / "m.ply", "not a directory"),
             (tmp_path, "is a directory"), (tmp_path / "m.xyz", "supported: ply, obj, stl, off, glb"),
             (tmp_path / "noext", "Cannot tell")]
    for target, message in cases:
        with pytest.raises(InputError, match=message):
            write_mesh(sample_mesh(), target)
    bad = SurfaceMesh(vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 3]]))
    with pytest.raises(InputError, match="outside"):
        write_mesh(bad, tmp_path / "bad.ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    assert set(SUPPORTED_OUTPUT) == {"ply", "obj", "stl", "off", "glb"}


# ============================================================================ malformed corpus
GARBAGE = bytes(np.random.default_rng(7).integers(0, 256, 4096, dtype=np.uint8))


def corpus() -> list[tuple[str, bytes, str]]:
    """(file name, content, regex the message must contain)."""
    good_ply = ply_bytes("binary_little_endian", FACES_UNIFORM, faces_first=False)
    good_pcd_head = (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10\nHEIGHT 1\n"
                     b"POINTS 10\nDATA binary\n")
    las = real("4_6_crop.las").read_bytes()
    return [
        ("empty.ply", b"", "empty"),
        ("empty.xyz", b"", "empty"),
        ("magic.ply", b"plyx\nformat ascii 1.0\nend_header\n", "magic"),
        ("noend.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n1\n", "end_header"),
        ("noend2.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x", "end_header"),
        ("badline.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n1\n", "line 4"),
        ("badfmt.ply", b"ply\nformat binary_middle_endian 1.0\nend_header\n", "line 2"),
        ("noxyz.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float u\nend_header\n1\n", "x, y and z"),
        ("novertex.ply", b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no 'vertex'"),
        ("dup.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n1 2\n",
         "repeats the property 'x'"),
        ("digits.ply", "ply\nformat ascii 1.0\nelement vertex \u00b3\nend_header\n".encode(), "line 3"),
        ("trunc.ply", good_ply[:-40], "truncated"),
        ("trunc_ragged.ply", ply_bytes("binary_big_endian")[:-40], "truncated"),
        ("trunc_ascii.ply", ply_bytes("ascii", faces_first=False).rsplit(b"\n", 4)[0], "truncated"),
        ("garbage.ply", GARBAGE, "magic"),
        ("garbage.pcd", GARBAGE, "PCD"),
        ("garbage.las", GARBAGE, "LASF"),
        ("garbage.obj", GARBAGE, "binary"),
        ("garbage.xyz", GARBAGE, "binary"),
        ("trunc.las", las[: len(las) // 2], "truncated"),
        ("header_only.las", las[:227], "header_only.las"),
        ("vlr_cut.las", las[:400], "vlr_cut.las"),
        ("lasf_garbage.las", b"LASF" + GARBAGE, "lasf_garbage.las"),
        ("nodata.pcd", good_pcd_head.replace(b"DATA binary\n", b""), "DATA"),
        ("height.pcd", good_pcd_head.replace(b"HEIGHT 1", b"HEIGHT"), "one number on its HEIGHT line"),
        ("trunc.pcd", good_pcd_head + b"\0" * 100, "truncated"),
        ("trunc_c.pcd", good_pcd_head.replace(b"binary", b"binary_compressed") + struct.pack("<II", 50, 120) + b"\0" * 9,
         "truncated"),
        ("corrupt_c.pcd", good_pcd_head.replace(b"binary", b"binary_compressed") + struct.pack("<II", 2, 120) + b"\x05a",
         "corrupt"),
        ("trunc_ascii.pcd", good_pcd_head.replace(b"binary", b"ascii") + b"1 2 3\n", "truncated"),
        ("types.pcd", good_pcd_head.replace(b"TYPE F F F", b"TYPE F F Q"), "unsupported field types"),
        ("text.xyz", b"1 2 3\n4 5 6\n7 eight 9\n", "line 3"),
        ("columns.csv", b"x,y,z\n1,2,3\n4,5\n", "line 3"),
        ("five.xyz", b"1 2 3 4 5\n", "5 columns"),
        ("noxyzhead.txt", b"a b c\n1 2 3\n", "without x, y and z"),
        ("words.obj", b"v 1 2 3\nv 1 two 3\n", "line 2"),
        ("novertex.obj", b"# nothing\nvn 0 0 1\n", "no 'v'"),
        ("unknown.e57", b"anything", "supported: ply, obj, xyz, txt, csv, pcd, las, laz"),
        *hostile_headers(),
    ]


def hostile_headers() -> list[tuple[str, bytes, str]]:
    """Headers that lie: each message names the file, the field and what is wrong."""
    xyz = "property float x\nproperty float y\nproperty float z\n"
    head = lambda lines, fmt="binary_little_endian": f"ply\nformat {fmt} 1.0\n{lines}end_header\n".encode()  # noqa: E731
    pcd = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nPOINTS {p}\nDATA {k}\n"
    las14 = io.BytesIO()
    header = laspy.LasHeader(point_format=6, version="1.4")
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.zeros((3, 5))
    las.write(las14)
    evlr = bytearray(las14.getvalue())
    evlr[235:247] = struct.pack("<QI", len(evlr), 0xFFFFFFFF)
    return [
        ("rows.ply", head(f"element vertex {2**63 + 1}\n" + xyz) + bytes(12), r"element 'vertex' claims 9223372036854775809 rows"),
        ("twice.ply", head("element vertex 1\n" + xyz + "element vertex 1\n" + xyz) + bytes(24), "repeats the element 'vertex'"),
        ("props.ply", head("element vertex 1\n" + "".join(f"property uchar p{i}\n" for i in range(10_001))),
         "more than 10000 properties"),
        ("noprops.ply", head("element vertex 1\n" + xyz + "element junk 5\n") + bytes(12), "'junk' has 5 rows but no properties"),
        ("list.ply", head("element vertex 1\n" + xyz + "element face 1\nproperty list uint int v\n")
         + bytes(12) + struct.pack("<I", 2**32 - 1), "truncated"),
        ("header.ply", b"ply\nformat ascii 1.0\n" + b"comment x\n" * 120_000, "no 'end_header' line within its first 1048576 bytes"),
        ("rows.pcd", (pcd.format(n=150, p=150, k="ascii") + "1 2 3 4 5 6\n" * 150).encode(), "6 values per ascii data line"),
        ("width.pcd", pcd.format(n=10, p=5000, k="binary").encode() + bytes(120), r"POINTS 5000, but WIDTH x HEIGHT is 10"),
        ("bomb.pcd", pcd.format(n=10**6, p=10**6, k="binary_compressed").encode() + struct.pack("<II", 100, 12 * 10**6)
         + bytes(100), "claims 12000000 bytes from 100 compressed ones"),
        ("evlr.las", bytes(evlr), "4294967295 extended VLRs cannot fit"),
    ]


def test_long_ply_comment_is_accepted(tmp_path):
    data = ply_bytes("binary_little_endian")
    cut = data.index(b"end_header")
    (tmp_path / "c.ply").write_bytes(data[:cut] + b"comment " + b"z" * 10_000 + b"\n" + data[cut:])
    check_hand_ply(read_cloud(tmp_path / "c.ply"))


def test_30k_properties_are_refused_fast(tmp_path):
    import time

    lines = "".join(f"property float p{i}\n" for i in range(30_000))
    (tmp_path / "p.ply").write_bytes(f"ply\nformat ascii 1.0\nelement vertex 1\n{lines}end_header\n".encode())
    start = time.perf_counter()
    with pytest.raises(FormatError, match="p.ply.*more than 10000 properties"):
        read_cloud(tmp_path / "p.ply")
    assert time.perf_counter() - start < 2.0


class EndlessText(io.RawIOBase):
    """A binary stream of '1 2 3' lines that never ends; counts the bytes it served."""

    def __init__(self, line: bytes = b"1 2 3\n"):
        self.line, self.served, self.name = line, 0, "endless"

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        chunk = (self.line * (len(buffer) // len(self.line) + 1))[:len(buffer)]
        buffer[:len(chunk)] = chunk
        self.served += len(chunk)
        return len(chunk)


def test_reading_budget_bounds_files_and_endless_streams(tmp_path):
    with pytest.raises(FormatError, match="'endless' goes on past the reading budget of 2.0 MiB"):
        read_cloud(io.BufferedReader(EndlessText()), fmt="xyz", memory="2M")
    (tmp_path / "big.xyz").write_bytes(b"1 2 3\n" * 400_000)
    with pytest.raises(FormatError, match="big.xyz.*2.3 MiB, more than the reading budget of 1.0 MiB"):
        read_cloud(tmp_path / "big.xyz", memory=1 << 20)
    assert len(read_cloud(tmp_path / "big.xyz", memory="3M")) == 400_000
    with pytest.raises(FormatError, match="reading budget"):
        read_cloud(io.BytesIO(b"1 2 3\n" * 400_000), fmt="xyz", memory="1M")
    with pytest.raises(InputError, match="--memory must be a size"):
        read_cloud(tmp_path / "big.xyz", memory="lots")


@pytest.mark.parametrize("name, content, message", corpus(), ids=[c[0] for c in corpus()])
def test_malformed_inputs(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(InputError, match=message) as info:
        read_cloud(path)
    if name != "unknown.e57":
        assert type(info.value) is FormatError
    assert name in str(info.value)


def test_truncated_las_is_reported_not_logged(tmp_path, caplog):
    data = real("4_6_crop.las").read_bytes()
    (tmp_path / "cut.las").write_bytes(data[:-34])
    with pytest.raises(FormatError, match="truncated"):
        read_cloud(tmp_path / "cut.las")
    assert not caplog.records  # laspy would log an ERROR and return fewer points
    laz = real("autzen_trim.laz").read_bytes()
    (tmp_path / "cut.laz").write_bytes(laz[: len(laz) // 2])
    with pytest.raises(FormatError, match="cut.laz"):
        read_cloud(tmp_path / "cut.laz")
    huge = bytearray(laz)
    huge[107:111] = struct.pack("<I", 2**32 - 1)  # legacy point count: 146 GB of points
    (tmp_path / "huge.laz").write_bytes(bytes(huge))
    with pytest.raises(FormatError, match="huge.laz"):
        read_cloud(tmp_path / "huge.laz")


def test_corrupt_laz_chunk_table_is_format_error(tmp_path):
    """lazrs would abort the process allocating buffers for 2**31 chunks; the reader must refuse first."""
    buf = io.BytesIO()
    laspy.read(str(real("4_6_crop.las")))[:50].write(buf, do_compress=True)
    data = bytearray(buf.getvalue())
    table_at = struct.unpack_from("<q", data, struct.unpack_from("<I", data, 96)[0])[0]
    data[table_at + 4: table_at + 8] = struct.pack("<I", 2**31)
    (tmp_path / "chunks.laz").write_bytes(bytes(data))
    with pytest.raises(FormatError, match="chunks.laz.*chunk table"):
        read_cloud(tmp_path / "chunks.laz")


@functools.lru_cache(maxsize=1)
def fuzz_seeds() -> dict[str, bytes]:
    """Small valid files of each format whose mutations the fuzz test feeds to the readers."""
    seeds = {f"{fmt}.ply": ply_bytes(fmt) for fmt in ("ascii", "binary_little_endian", "binary_big_endian")}
    seeds["x.xyz"] = ("x y z nx ny nz\n" + table_text(PTS, NRM)).encode()
    seeds["x.obj"] = b"v 1 2 3\nv 4 5 6\nvn 0 0 1\nf 1//1 2//1 1//1\n"
    seeds["x.pcd"] = (b"VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 3\n"
                      b"HEIGHT 1\nPOINTS 3\nDATA binary\n" + np.arange(12, dtype="<f4").tobytes())
    buf = io.BytesIO()
    laspy_file(buf)
    seeds["x.las"] = buf.getvalue()
    return seeds


@settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_mutated_files_raise_only_c1mesh_errors(data):
    """Cut, overwritten or stretched files either read or raise a C1MeshError, nothing else."""
    name, original = data.draw(st.sampled_from(sorted(fuzz_seeds().items())))
    content = bytearray(original)
    at = data.draw(st.integers(0, len(content) - 1))
    action = data.draw(st.sampled_from(["cut", "overwrite", "insert"]))
    if action == "cut":
        content = content[:at]
    elif action == "overwrite":
        content[at:at + 4] = data.draw(st.binary(min_size=1, max_size=4))
    else:
        content[at:at] = data.draw(st.binary(min_size=1, max_size=8))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy warning escaping a reader is a bug too
        try:
            read_cloud(io.BytesIO(bytes(content)), fmt=name.rsplit(".", 1)[1])
        except C1MeshError:
            pass


def test_missing_and_directory_inputs(tmp_path):
    with pytest.raises(InputError, match="nowhere.ply.*does not exist"):
        read_cloud(tmp_path / "nowhere.ply")
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(InputError, match="is a directory"):
        read_cloud(tmp_path / "dir.ply")
    assert "laz" in SUPPORTED_INPUT and "csv" in SUPPORTED_INPUT



@pytest.mark.parametrize("ascii_ply", [False, True])
def test_ply_writer_streams_in_blocks(tmp_path, monkeypatch, ascii_ply):
    """Blocks smaller than the mesh must give the same file as one block (no rows lost or doubled)."""
    import c1mesh.formats.ply as ply_module
    rng = np.random.default_rng(3)
    mesh = SurfaceMesh(vertices=rng.random((50, 3)) + 6.4e5, faces=rng.integers(0, 50, (37, 3)),
                       vertex_normals=rng.random((50, 3)), vertex_colors=rng.integers(0, 255, (50, 3)).astype(np.uint8))
    write_mesh(mesh, tmp_path / "whole.ply", ascii=ascii_ply)
    monkeypatch.setattr(ply_module, "_WRITE_BLOCK", 7)
    write_mesh(mesh, tmp_path / "blocks.ply", ascii=ascii_ply)
    assert (tmp_path / "blocks.ply").read_bytes() == (tmp_path / "whole.ply").read_bytes()
    back = read_cloud(tmp_path / "blocks.ply")
    np.testing.assert_array_equal(back.points, mesh.vertices)


def test_atomic_output_starts_writeback_as_it_goes(tmp_path, monkeypatch):
    """Every WRITE_BEHIND bytes the file asks the kernel to start writeback (and the
    bytes on disk are exactly what was written, buffered or not)."""
    import os

    import c1mesh.core.outputs as atomic_module
    calls = []
    real = os.posix_fadvise

    def recording(fd, offset, length, advice):
        calls.append((offset, length, advice))
        return real(fd, offset, length, advice)
    monkeypatch.setattr(atomic_module, "WRITE_BEHIND", 1000)
    monkeypatch.setattr(os, "posix_fadvise", recording)
    payload = bytes(range(256)) * 400                      # 102,400 bytes
    with atomic_output(tmp_path / "big.bin") as f:
        for start in range(0, len(payload), 300):
            f.write(payload[start:start + 300])
        f.write(memoryview(payload)[:5000])
    assert (tmp_path / "big.bin").read_bytes() == payload + payload[:5000]
    assert len(calls) >= 8 and all(advice == os.POSIX_FADV_DONTNEED for _, _, advice in calls)


@pytest.mark.parametrize("raised, message", [(MemoryError(), "out of memory while decoding"),
                                             (RuntimeError(""), "cannot be read: RuntimeError")])
def test_laspy_failures_always_say_why(raised, message):
    from c1mesh.formats.las import laspy_errors

    with pytest.raises(FormatError, match=f"'tile.laz'.*{message}"):
        with laspy_errors("tile.laz"):
            raise raised


def test_non_regular_input_is_capped_unless_memory_is_given(monkeypatch):
    """Without --memory an endless stream stops at STREAM_LIMIT (here 1 MiB), not at the
    budget; an explicit --memory lifts the cap to itself."""
    import c1mesh.formats._limits as limits

    monkeypatch.setattr(limits, "STREAM_LIMIT", 1 << 20)
    stream = EndlessText()
    with pytest.raises(FormatError, match="'endless' is not a regular file and goes on past 1.0 MiB"):
        read_cloud(io.BufferedReader(stream), fmt="xyz")
    assert stream.served <= (1 << 20) + (16 << 20)
    stream = EndlessText()
    with pytest.raises(FormatError, match="'endless' goes on past the reading budget of 3.0 MiB"):
        read_cloud(io.BufferedReader(stream), fmt="xyz", memory="3M")
    assert stream.served > 3 << 20


def test_stdin_from_a_regular_file_or_bytes_in_memory_is_not_capped(tmp_path, monkeypatch):
    """Only what can be endless is capped: stdin redirected from a file and a BytesIO read
    up to the budget, past STREAM_LIMIT (here 1 MiB)."""
    import c1mesh.formats._limits as limits

    monkeypatch.setattr(limits, "STREAM_LIMIT", 1 << 20)
    path = tmp_path / "big.xyz"
    path.write_bytes(b"1 2 3\n" * 400_000)                 # 2.3 MiB
    with open(path, "rb") as stdin:
        assert len(read_cloud(stdin, fmt="xyz")) == 400_000
    assert len(read_cloud(io.BytesIO(path.read_bytes()), fmt="xyz")) == 400_000
    with pytest.raises(FormatError, match="not a regular file and goes on past 1.0 MiB"):
        read_cloud(io.BufferedReader(EndlessText()), fmt="xyz")


@pytest.mark.parametrize("fmt, line, message", [
    ("ply", b"\x93garbage", "'endless' is not a PLY file"),
    ("xyz", b"\0", "'endless' contains binary data"),
    ("pcd", b"\x01\x02 3\n", "'endless' is not a PCD file"),
    ("las", b"NOTLAS", "'endless' is not a LAS/LAZ file"),
])
def test_garbage_stream_fails_after_its_first_64_kib(fmt, line, message):
    """A stream that does not start like its format is refused from its head, with the
    reading budget far away: /dev/urandom as PLY, /dev/zero as text."""
    stream = EndlessText(line)
    with pytest.raises(FormatError, match=message):
        read_cloud(io.BufferedReader(stream, buffer_size=4096), fmt=fmt, memory="1G")
    assert stream.served <= 64 << 10


@pytest.mark.parametrize("device, fmt, message", [("/dev/urandom", "ply", "not a PLY file"),
                                                  ("/dev/zero", "xyz", "contains binary data")])
def test_devices_fail_fast(device, fmt, message):
    """Refused from the first 64 KiB, not at the budget (64M here: a regression reads that much
    and fails with the budget's message instead)."""
    start = time.perf_counter()
    with pytest.raises(FormatError, match=message):
        read_cloud(device, fmt=fmt, memory="64M")
    assert time.perf_counter() - start < 2.0


def _zero_pcd(points: int) -> bytes:
    """A binary_compressed PCD of `points` points at the origin: LZF's 88-fold best case."""
    packed = lzf.compress(bytes(12 * points))
    head = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {points}\n"
            f"HEIGHT 1\nPOINTS {points}\nDATA binary_compressed\n").encode()
    return head + struct.pack("<II", len(packed), 12 * points) + packed


def test_lzf_bomb_is_refused_before_decoding_unless_memory_is_given(tmp_path, monkeypatch):
    """A body that expands more than SANE_RATIO-fold past SMALL_DECODE (here 1 MiB) is
    refused without being decoded; --memory (the user vouching for the file) lifts that."""
    import c1mesh.formats._limits as limits
    import c1mesh.formats.pcd as pcd

    monkeypatch.setattr(limits, "SMALL_DECODE", 1 << 20)
    path = tmp_path / "bomb.pcd"
    path.write_bytes(_zero_pcd(200_000))          # 2.4 MB from ~30 KB
    decoded = []
    monkeypatch.setattr(pcd, "lzf_decompress", lambda src, n: decoded.append(n) or lzf.decompress(src, n))
    with pytest.raises(FormatError, match=r"bomb.pcd.*2.3 MiB \(\d\d-fold.*decompression bomb.*--memory"):
        read_cloud(path)
    assert decoded == []
    cloud = read_cloud(path, memory="64M")
    assert decoded == [2_400_000] and len(cloud) == 200_000 and not cloud.points.any()


def test_lzf_bomb_within_small_decode_reads():
    """Below SMALL_DECODE (16 MiB) any ratio is harmless and reads."""
    cloud = read_cloud(io.BytesIO(_zero_pcd(100_000)), fmt="pcd")
    assert len(cloud) == 100_000 and not cloud.points.any()


def test_pcd_ascii_point_count_checked_against_the_body_size(tmp_path):
    path = tmp_path / "lies.pcd"
    path.write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000\n"
                     b"HEIGHT 1\nPOINTS 1000000\nDATA ascii\n" + b"1 2 3\n" * 100)
    with pytest.raises(FormatError, match="lies.pcd' is truncated: 600 data bytes for the 1000000 points"):
        read_cloud(path)


@pytest.mark.parametrize("list_name", ["__count1", "f0"])
def test_ply_list_named_like_an_internal_field(tmp_path, list_name):
    """A list property may carry any name a header allows, also that of a count field
    (the list at index 1 named '__count1' was "field occurs more than once")."""
    xyz = np.arange(12, dtype="<f4").reshape(4, 3)
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\n"
              f"property list uchar float {list_name}\nproperty float y\nproperty float z\n"
              "property uchar __count0x\nend_header\n").encode()
    rows = b"".join(struct.pack("<fBff", x, 2, 7.0, 8.0) + struct.pack("<ffB", y, z, 5) for x, y, z in xyz)
    path = tmp_path / "clash.ply"
    path.write_bytes(header + rows)
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.points, xyz)
    np.testing.assert_array_equal(cloud.extra["__count0x"], [5, 5, 5, 5])


def test_depth_png_bomb_is_refused_before_decoding(monkeypatch):
    """A small PNG claiming a big frame of zeros: its header size is checked against the
    compression-ratio rule (SMALL_DECODE here 64 KiB) and the budget before the pixels are
    decoded; --memory lifts the ratio rule."""
    from PIL import Image

    import c1mesh.formats._limits as limits
    from c1mesh.formats.depth import read_depth

    monkeypatch.setattr(limits, "SMALL_DECODE", 64 << 10)
    buf = io.BytesIO()
    Image.fromarray(np.zeros((500, 400), np.uint16)).save(buf, format="PNG")
    data = buf.getvalue()
    assert len(data) < 10_000                               # 400 kB of pixels from a few kB
    intrinsics = (500.0, 500.0, 200.0, 250.0)
    with pytest.raises(FormatError, match=r"the 400x500 image would decode .* decompression bomb"):
        read_depth(data, "bomb.png", intrinsics)
    with limits.reading_budget("8M"):                       # 200k pixels x 96 bytes > 8 MiB
        with pytest.raises(FormatError, match="decoding the 400x500 image needs 18.3 MiB"):
            read_depth(data, "bomb.png", intrinsics)
    with limits.reading_budget("64M"):
        cloud = read_depth(data, "bomb.png", intrinsics)
    assert cloud.grid_shape == (500, 400) and np.isnan(cloud.points).all()


@pytest.mark.parametrize("kind", ["ply", "pcd"])
def test_decoded_vertices_count_against_the_budget(tmp_path, kind):
    """--memory bounds what a file decodes to, not only its size: 100k float32 points
    (1.2 MB) become 4.8 MB of float64 points and normals, more than a 4 MiB budget."""
    rows = np.random.default_rng(6).uniform(0, 1, (100_000, 3)).astype("<f4")
    if kind == "ply":
        head = b"ply\nformat binary_little_endian 1.0\nelement vertex 100000\n" + b"".join(
            f"property float {c}\n".encode() for c in "xyz") + b"end_header\n"
    else:
        head = (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100000\n"
                b"HEIGHT 1\nPOINTS 100000\nDATA binary\n")
    path = tmp_path / f"p.{kind}"
    path.write_bytes(head + rows.tobytes())
    with pytest.raises(FormatError, match=r"p\.%s': decoding the 100000 (vertices|points) needs 5.7 MiB, "
                                          r"more than the reading budget of 4.0 MiB" % kind):
        read_cloud(path, memory="4M")
    np.testing.assert_array_equal(read_cloud(path, memory="8M").points, rows.astype(np.float64))


def test_pcd_head_check_accepts_any_start_of_a_real_header():
    """The 64 KiB head of a PCD stream may be all comments or end inside a keyword; only a
    line that is neither a comment nor a PCD keyword is refused."""
    from c1mesh.formats.pcd import check_pcd_head

    check_pcd_head(b"# comment\n" * 6000, "s.pcd")              # 60 kB of comments
    check_pcd_head(b"# .PCD v0.7\nVERSION 0.7\nFIE", "s.pcd")
    check_pcd_head(b"# .PCD v0.7\nVERS", "s.pcd")
    for bad in (b"\x93\x01garbage", b"# c\nply\nformat ascii 1.0\n"):
        with pytest.raises(FormatError, match="'s.pcd' is not a PCD file"):
            check_pcd_head(bad, "s.pcd")
    data = real("table_scene_mug_stereo_textured.pcd").read_bytes()
    check_pcd_head(data[:64 << 10], "mug.pcd")


def test_info_on_a_height_column_says_what_fit_does():
    """Issue 21 leftover: `c1mesh info data_samples/topo.csv` suggested the axis chosen from
    estimated normals (about y), while `fit` takes the header's height column z. The peer
    here is the fit itself: info's suggested axis is the fit's height axis, and both name
    the height column as the reason."""
    from c1mesh.pipeline.inspect import describe
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    facts = describe(REAL / "topo.csv")
    frame = fit(REAL / "topo.csv", None, FitOptions(level=1)).report["frame"]
    assert facts["suggested_axis"] == frame["axes"][2] == [0.0, 0.0, 1.0]
    assert facts["height_field"] is True
    assert "height column 'z'" in facts["axis_choice"] and "height column 'z'" in frame["axis_choice"]
    assert "units of their own" in facts["axis_choice"]


def test_info_on_a_height_column_refuses_what_fit_refuses(tmp_path):
    """Five heights at two plan positions: the fit refuses them as no height field over the
    header's z, and info says so with the fit's reason instead of suggesting another axis."""
    from c1mesh.pipeline.inspect import describe
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    path = tmp_path / "two.csv"
    path.write_text("x,y,z\n0,0,1\n0,0,2\n1,1,3\n1,1,4\n1,1,5\n")
    with pytest.raises(InputError) as refused:
        fit(path, None, FitOptions())
    facts = describe(path)
    assert facts["height_field"] is False and facts["suggested_axis"] is None
    assert facts["height_field_note"] == str(refused.value)
