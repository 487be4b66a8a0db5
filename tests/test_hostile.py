"""A hostile-input corpus: every case runs `c1mesh fit CASE -o out.ply` and `c1mesh info CASE`.

The cases are generated here (nothing in git): headers that lie about counts and sizes,
decompression bombs, endless streams, truncations at every header boundary of every
bundled sample, and random byte flips (fixed seeds) of every bundled sample. For each
run the test asserts: no traceback and no "unexpected" message; a failure prints exactly
one line, `c1mesh: error: ...`, and a success writes a valid mesh (fit) or JSON (info);
no file is left behind besides the input and the output; the run ends within
CASE_SECONDS; and its peak RSS grows by at most 2 x the input size + 200 MB over the
RSS it starts with, an interpreter that has imported c1mesh, numpy, scipy and Open3D
(about 300 MB, most of it Open3D).

Runs are forked from one server process that has done those imports (a fresh
interpreter would spend 2-3 s importing per run); each child resets its peak RSS
(/proc/self/clear_refs) and reports VmHWM minus its starting RSS. The fast part (crafted cases and the small samples) runs by default, the
rest (large samples) under -m slow.
"""
from __future__ import annotations

import io
import json
import os
import struct
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
CASE_SECONDS = 20.0
RSS_SLACK = 200 << 20
SMALL_SAMPLES = ("hill.ply", "pcl_bun0.pcd", "o3d_cloud_bin_0.pcd", "wave_tilted_offset.xyz")
LARGE_SAMPLES = ("4_6_crop.las", "autzen_trim.laz", "table_scene_mug_stereo_textured.pcd")


@dataclass
class Case:
    """One hostile input: file name (its extension picks the reader) and content.

    `path` replaces the file (a device such as /dev/zero); `args` are extra options of
    both commands, `fit_args` of fit only; `size` is the input size the memory limit is
    based on (the file's length by default).
    """

    name: str
    data: bytes = b""
    path: str | None = None
    args: tuple[str, ...] = ()
    fit_args: tuple[str, ...] = ()
    size: int | None = None


# ------------------------------------------------------------------------------ crafted cases
def _ply(header_lines: list[str], body: bytes = b"", fmt: str = "binary_little_endian") -> bytes:
    return ("\n".join(["ply", f"format {fmt} 1.0", *header_lines, "end_header"]) + "\n").encode() + body


_XYZ_PROPS = ["property float x", "property float y", "property float z"]


def crafted_ply() -> list[Case]:
    pts = np.random.default_rng(1).uniform(0, 1, (50, 3)).astype("<f4")
    body = pts.tobytes()
    hill = (SAMPLES / "hill.ply").read_bytes()
    cut = hill.index(b"end_header\n")
    return [
        Case("list_int_max.ply", _ply(["element vertex 50", *_XYZ_PROPS, "element face 1",
                                       "property list int int vertex_indices"], body + struct.pack("<i", 2**31 - 1))),
        Case("list_uint_max.ply", _ply(["element vertex 50", *_XYZ_PROPS, "element face 1",
                                        "property list uint int vertex_indices"], body + struct.pack("<I", 2**32 - 1))),
        Case("faces_first_list_max.ply", _ply(["element face 2", "property list uint int vertex_indices",
                                               "element vertex 50", *_XYZ_PROPS],
                                              struct.pack("<I", 2**32 - 1) + body)),
        Case("elements_2_63.ply", _ply([f"element vertex {2**63 + 1}", *_XYZ_PROPS], body)),
        Case("elements_huge_digits.ply", _ply(["element vertex " + "9" * 5000, *_XYZ_PROPS], body)),
        Case("two_vertex_elements.ply", _ply(["element vertex 25", *_XYZ_PROPS, "element vertex 25", *_XYZ_PROPS], body)),
        Case("big_endian_header.ply", hill.replace(b"binary_little_endian", b"binary_big_endian", 1)),
        Case("empty_elements_100k.ply", _ply(["element vertex 50", *_XYZ_PROPS]
                                             + [f"element e{i} 0" for i in range(100_000)], body)),
        Case("rows_without_properties.ply", _ply(["element vertex 50", *_XYZ_PROPS, "element junk 1000000000"], body)),
        Case("properties_30k.ply", _ply(["element vertex 1", *_XYZ_PROPS]
                                        + [f"property float p{i}" for i in range(30_000)], body)),
        Case("properties_9k.ply", _ply(["element vertex 1", *_XYZ_PROPS]
                                       + [f"property uchar p{i}" for i in range(9_000)], body)),
        Case("long_comment.ply", hill[:cut] + b"comment " + b"c" * 10_000 + b"\n" + hill[cut:]),
        Case("header_over_1mib.ply", b"ply\nformat ascii 1.0\n" + b"comment filler\n" * 80_000 + b"end_header\n"),
        Case("no_newline.ply", b"ply\n" + b"x" * 3_000_000),
        Case("negative_list.ply", _ply(["element vertex 50", *_XYZ_PROPS, "element face 1",
                                        "property list char int vertex_indices"], body + struct.pack("<b", -1))),
        Case("ascii_count_lies.ply", _ply(["element vertex 1000000", *_XYZ_PROPS], b"1 2 3\n4 5 6\n", fmt="ascii")),
        Case("ascii_short_row.ply", _ply(["element vertex 3", *_XYZ_PROPS], b"1 2 3\n4 5\n6 7 8\n", fmt="ascii")),
        Case("zero_vertices.ply", _ply(["element vertex 0", *_XYZ_PROPS])),
        Case("nan_vertices.ply", _ply(["element vertex 50", *_XYZ_PROPS], np.full((50, 3), np.nan, "<f4").tobytes())),
        Case("list_named_like_a_count_field.ply", _ply(["element vertex 50", "property float x",
                                                        "property list uchar float __count1", "property float y",
                                                        "property float z"],
                                                       b"".join(struct.pack("<fB", x, 0) + struct.pack("<ff", y, z)
                                                                for x, y, z in pts.tolist()))),
        Case("huge_values.ply", _ply(["element vertex 50", "property double x", "property double y",
                                      "property double z"], (pts.astype("<f8") * 1e300).tobytes())),
    ]


_PCD_HEAD = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
             "POINTS {n}\nDATA {kind}\n")


def _pcd(n: int, kind: str, body: bytes) -> bytes:
    return _PCD_HEAD.format(n=n, kind=kind).encode() + body


def crafted_pcd() -> list[Case]:
    import lzf

    zeros = lzf.compress(bytes(12 * 1_000_000))   # 1M points at the origin, ~140 KB
    return [
        Case("compressed_claims_huge.pcd", _pcd(400_000_000, "binary_compressed",
                                                struct.pack("<II", 1000, 4_800_000_000 % 2**32) + bytes(1000))),
        Case("compressed_ratio.pcd", _pcd(5_000_000, "binary_compressed", struct.pack("<II", 1000, 60_000_000)
                                          + bytes(1000))),
        Case("compressed_bomb.pcd", _pcd(1_000_000, "binary_compressed",
                                         struct.pack("<II", len(zeros), 12_000_000) + zeros)),
        Case("compressed_bomb_3m.pcd", _pcd(3_000_000, "binary_compressed",    # 36 MB from ~420 KB
                                            struct.pack("<II", 3 * len(zeros), 36_000_000) + zeros * 3)),
        Case("compressed_packed_past_end.pcd", _pcd(10, "binary_compressed", struct.pack("<II", 10**9, 120))),
        Case("compressed_garbage.pcd", _pcd(1000, "binary_compressed", struct.pack("<II", 4000, 12_000)
                                            + bytes(np.random.default_rng(2).integers(0, 256, 4000, np.uint8)))),
        Case("binary_points_huge.pcd", _pcd(2**62, "binary", bytes(120))),
        Case("ascii_rows_too_long.pcd", _pcd(150, "ascii", b"1 2 3 4 5 6\n" * 150)),
        Case("ascii_rows_ragged.pcd", _pcd(3, "ascii", b"1 2 3\n4 5\n6 7 8\n")),
        Case("points_not_width.pcd", _PCD_HEAD.format(n=10, kind="binary").replace("POINTS 10", "POINTS 5000")
             .encode() + bytes(120)),
        Case("fields_20k.pcd", ("VERSION 0.7\nFIELDS " + " ".join(f"f{i}" for i in range(20_000)) + "\nSIZE "
                                + " 4" * 20_000 + "\nTYPE" + " F" * 20_000 + "\nWIDTH 1\nPOINTS 1\nDATA binary\n")
             .encode() + bytes(80_000)),
        Case("count_huge.pcd", _PCD_HEAD.format(n=1, kind="binary").replace("COUNT 1 1 1", "COUNT 1 1 4000000000")
             .encode() + bytes(64)),
        Case("header_over_1mib.pcd", b"# filler\n" * 150_000 + _pcd(1, "ascii", b"1 2 3\n")),
        Case("width_huge_digits.pcd", _PCD_HEAD.format(n="9" * 5000, kind="binary").encode()),
    ]


def _las_14(points: int = 200) -> bytes:
    import laspy

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.array([0.01] * 3), np.zeros(3)
    las = laspy.LasData(header)
    rng = np.random.default_rng(3)
    las.x, las.y, las.z = rng.uniform(0, 100, (3, points))
    las.classification = np.full(points, 2, np.uint8)
    buf = io.BytesIO()
    las.write(buf)
    return buf.getvalue()


def crafted_las() -> list[Case]:
    las14 = bytearray(_las_14())
    evlr = bytearray(las14)
    evlr[235:247] = struct.pack("<QI", len(las14), 0xFFFFFFFF)
    laz = (SAMPLES / "autzen_trim.laz").read_bytes()
    las = (SAMPLES / "4_6_crop.las").read_bytes()

    def patched(data: bytes, at: int, fmt: str, value: int) -> bytes:
        out = bytearray(data)
        out[at:at + struct.calcsize(fmt)] = struct.pack(fmt, value)
        return bytes(out)

    record = struct.unpack_from("<H", laz, 105)[0]
    return [
        Case("evlr_count_max.las", bytes(evlr)),
        Case("laz_max_points.laz", patched(laz, 107, "<I", 2**32 - 1)),
        Case("laz_1000x.laz", patched(laz, 107, "<I", 1000 * len(laz) // record)),
        Case("laz_chunk_table_plus_one.laz", patched(laz, 107, "<I", 150_001)),
        Case("laz_half.laz", laz[: len(laz) // 2]),
        Case("las_points_huge.las", patched(las, 107, "<I", 2**32 - 1)),
        Case("las14_points_2_64.las", patched(patched(bytes(las14), 247, "<Q", 2**64 - 1), 107, "<I", 0)),
        Case("las_header_size.las", patched(las, 94, "<H", 65535)),
        Case("las_offset_past_end.las", patched(las, 96, "<I", 2**32 - 1)),
        Case("las_vlr_count_max.las", patched(las, 100, "<I", 2**32 - 1)),
        Case("las_classes_none_kept.las", las, fit_args=("--classes", "77")),
    ]


def crafted_text() -> list[Case]:
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 10, (300, 2))
    z = np.sin(xy[:, 0]) + 0.1 * xy[:, 1]
    rows = "".join(f"{a!r},{b!r},{c!r}\n" for a, b, c in zip(xy[:, 0], xy[:, 1], z))
    return [
        Case("dev_zero.xyz", path="/dev/zero", args=("--memory", "64M"), size=64 << 20),
        # Garbage from a device fails from its first 64 KiB, not at --memory (512M here, so
        # that reading up to it breaks the RSS bound of a zero-byte input).
        Case("dev_zero_512m.xyz", path="/dev/zero", args=("--memory", "512M"), size=0),
        Case("dev_urandom_512m.ply", path="/dev/urandom", args=("--memory", "512M"), size=0),
        Case("bom.csv", b"\xef\xbb\xbfx,y,z\n" + rows.encode()),
        Case("r_write_csv.csv", ('"","x","y","z"\n' + "".join(f'"{i}",{r}' for i, r in
                                                              enumerate(rows.splitlines(True)))).encode()),
        Case("coincident_100k.xyz", b"1.5 2.5 3.5\n" * 100_000),
        Case("one_long_line.xyz", b"1 " * 2_000_000),
        Case("binary.xyz", bytes(rng.integers(0, 256, 100_000, np.uint8))),
        Case("whitespace.xyz", b" \n\t\n" * 1000),
        Case("ambiguous.xyz", "".join(f"{a} {b} {c} {3 * a} {2 * b} {c}\n" for a, b, c in
                                      zip(xy[:, 0], xy[:, 1], z)).encode()),
        Case("rgb01.xyz", "".join(f"{a} {b} {c} 0.5 0.25 1\n" for a, b, c in zip(xy[:, 0], xy[:, 1], z)).encode()),
        Case("empty.ply", b""),
    ]


# ------------------------------------------------------------------------------ sample-derived cases
def header_boundaries(name: str, data: bytes) -> list[int]:
    """Offsets just after every header line (PLY, PCD, text) or header field (LAS)."""
    if name.endswith((".las", ".laz")):
        header_size, offset, n_vlrs = struct.unpack_from("<HII", data, 94)
        cuts = [0, 4, 24, 26, 94, 96, 100, 104, 107, 131, 179, 227, header_size]
        at = header_size
        for _ in range(min(n_vlrs, 20)):
            cuts += [at + 54, at + 54 + struct.unpack_from("<H", data, at + 20)[0]]
            at = cuts[-1]
        return sorted({c for c in cuts + [offset, offset + 8, offset + 100] if 0 < c < len(data)})
    end = data.find(b"end_header\n") if name.endswith(".ply") else data.find(b"\nDATA ")
    end = data.find(b"\n", end + 1) + 1 if end >= 0 else min(len(data), 200)
    cuts = [i + 1 for i in range(end) if data[i:i + 1] == b"\n"]
    return sorted({c for c in cuts + [end + 1, end + 7] if 0 < c < len(data)})


def sample_cases(names: tuple[str, ...]) -> list[Case]:
    """Truncations at every header boundary and three byte-flip variants per sample."""
    cases = []
    for sample in names:
        data = (SAMPLES / sample).read_bytes()
        stem, ext = sample.rsplit(".", 1)
        for cut in header_boundaries(sample, data):
            cases.append(Case(f"{stem}.cut{cut}.{ext}", data[:cut]))
        for seed in range(3):
            rng = np.random.default_rng(seed)
            flipped = bytearray(data)
            head = min(len(data), 1024)
            for at in np.concatenate([rng.integers(0, head, 6), rng.integers(0, len(data), 6)]):
                flipped[at] ^= 1 << int(rng.integers(0, 8))
            cases.append(Case(f"{stem}.flip{seed}.{ext}", bytes(flipped)))
    return cases


def _params(cases: list[Case]) -> list:
    return [pytest.param(c, id=c.name) for c in cases]


def fast_cases() -> list[Case]:
    return crafted_ply() + crafted_pcd() + crafted_las() + crafted_text() + sample_cases(SMALL_SAMPLES)


def slow_cases() -> list[Case]:
    import lzf

    zeros = lzf.compress(bytes(12 * 5_000_000))   # 5M points at the origin from ~680 KB
    bomb = _pcd(5_000_000, "binary_compressed", struct.pack("<II", len(zeros), 60_000_000) + zeros)
    # Decoding is legitimate (88x is LZF's limit) but the fit of 5M points needs more than
    # 2 x 680 KB + 200 MB; --memory is how a user bounds that, and it must refuse cleanly.
    return sample_cases(LARGE_SAMPLES) + [Case("compressed_bomb_5m.pcd", bomb, args=("--memory", "256M"))]


# ------------------------------------------------------------------------------ fork server
SERVER = textwrap.dedent(r"""
    import json, os, signal, sys, time
    import numpy, scipy.spatial, open3d
    import c1mesh.cli, c1mesh.pipeline.driver, c1mesh.pipeline.inspect, c1mesh.stages.normals

    def status_kb(field):
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])

    def child(job):
        os.chdir(job["cwd"])
        for fd, path in ((1, job["stdout"]), (2, job["stderr"])):
            os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), fd)
        os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
        with open("/proc/self/clear_refs", "w") as f:   # reset VmHWM to the current RSS
            f.write("5")
        start_kb = status_kb("VmRSS")
        sys.argv = ["c1mesh", *job["args"]]
        code = 0
        try:
            c1mesh.cli.main(args=job["args"], prog_name="c1mesh")
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException:
            import traceback
            traceback.print_exc()
            code = 98
        sys.stdout.flush()
        sys.stderr.flush()
        with open(job["memory"], "w") as f:
            json.dump({"start_kb": start_kb, "peak_kb": status_kb("VmHWM")}, f)
        return code

    print(json.dumps({"rss_kb": status_kb("VmRSS")}), flush=True)
    for line in sys.stdin:
        job = json.loads(line)
        start = time.monotonic()
        pid = os.fork()
        if pid == 0:
            code = 97
            try:
                code = child(job)
            finally:
                os._exit(code)
        timed_out = False
        while True:
            done, status, usage = os.wait4(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() - start > job["timeout"]:
                os.kill(pid, signal.SIGKILL)
                _, status, usage = os.wait4(pid, 0)
                timed_out = True
                break
            time.sleep(0.005)
        print(json.dumps({"code": os.waitstatus_to_exitcode(status), "seconds": time.monotonic() - start,
                          "maxrss_kb": usage.ru_maxrss, "timed_out": timed_out}), flush=True)
""")


class ForkServer:
    """A process with c1mesh imported that forks one child per command (see SERVER)."""

    def __init__(self):
        env = dict(os.environ, PYTHONPATH=str(ROOT / "src"), PYTHONWARNINGS="default")
        self.proc = subprocess.Popen([sys.executable, "-c", SERVER], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env)
        self.baseline = json.loads(self.proc.stdout.readline())["rss_kb"] * 1024

    def run(self, args: list[str], cwd: Path, logs: Path) -> dict:
        job = {"args": args, "cwd": str(cwd), "stdout": str(logs / "out"), "stderr": str(logs / "err"),
               "memory": str(logs / "memory"), "timeout": CASE_SECONDS}
        (logs / "memory").unlink(missing_ok=True)
        self.proc.stdin.write(json.dumps(job) + "\n")
        self.proc.stdin.flush()
        result = json.loads(self.proc.stdout.readline())
        result["stdout"] = (logs / "out").read_text(errors="replace")
        result["stderr"] = (logs / "err").read_text(errors="replace")
        memory = json.loads((logs / "memory").read_text()) if (logs / "memory").exists() else None
        # Growth of the run itself: its peak RSS (VmHWM, reset at the start) minus its RSS at
        # the start; a killed run has no report, and then its whole peak counts.
        result["growth"] = ((memory["peak_kb"] - memory["start_kb"]) if memory else result["maxrss_kb"]) * 1024
        return result

    def close(self):
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


@pytest.fixture(scope="module")
def server():
    srv = ForkServer()
    yield srv
    srv.close()


# ------------------------------------------------------------------------------ checks
def check_run(case: Case, command: str, result: dict, workdir: Path, input_size: int, baseline: int) -> None:
    """Every promise of the module doc for one run."""
    where = f"{command} {case.name}: exit {result['code']}, stderr {result['stderr'][-400:]!r}"
    assert not result["timed_out"], f"{where}: ran past {CASE_SECONDS} s"
    assert result["seconds"] < CASE_SECONDS, where
    err = result["stderr"]
    assert "Traceback" not in err and "unexpected" not in err.lower(), where
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert result["code"] in (0, 1), where
    leftovers = sorted(p.name for p in workdir.iterdir())
    # out.prj: the CRS sidecar of a mesh whose input carries a CRS (never without the mesh)
    expected = [p for p in (case.name, "out.ply", "out.prj") if (workdir / p).exists() and (p != case.name or not case.path)]
    assert leftovers == sorted(expected), f"{where}: files left {leftovers}"
    assert "out.prj" not in expected or "out.ply" in expected, f"{where}: a CRS sidecar without its mesh"
    if result["code"] == 0:
        assert not [ln for ln in lines if not ln.startswith("c1mesh: warning:")], where
        if command == "fit":
            check_mesh(workdir / "out.ply", where)
        else:
            assert "points" in json.loads(result["stdout"]), where
    else:
        assert len(lines) == 1 and lines[0].startswith("c1mesh: error: "), where
        assert not (workdir / "out.ply").exists(), where
    growth = result["growth"]
    assert growth <= 2 * input_size + RSS_SLACK, f"{where}: peak RSS {growth / 2**20:.0f} MB above its start"


def check_mesh(path: Path, where: str) -> None:
    """A readable PLY whose faces index its vertices and whose vertices are finite."""
    import trimesh

    mesh = trimesh.load(path, process=False)
    assert len(mesh.vertices) and len(mesh.faces), where
    assert np.isfinite(mesh.vertices).all(), where
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices), where


def run_case(server: ForkServer, case: Case, tmp_path: Path) -> None:
    workdir, logs = tmp_path / "work", tmp_path / "logs"
    workdir.mkdir()
    logs.mkdir()
    ext = case.name.rsplit(".", 1)[1]
    if case.path is None:
        source = workdir / case.name
        source.write_bytes(case.data)
        size = len(case.data)
    else:
        source, size = Path(case.path), case.size or 0
    fmt = ["--input-format", ext]
    for command, args in (("fit", ["fit", str(source), "-o", "out.ply", "--level", "2", *fmt, *case.args,
                                    *case.fit_args]),
                          ("info", ["info", str(source), *fmt, *case.args])):
        result = server.run(args, workdir, logs)
        check_run(case, command, result, workdir, size, server.baseline)
        (workdir / "out.ply").unlink(missing_ok=True)
        (workdir / "out.prj").unlink(missing_ok=True)          # the mesh's CRS sidecar goes with it


def test_corpus_is_large_enough():
    assert len(fast_cases()) + len(slow_cases()) >= 100
    assert len({c.name for c in fast_cases() + slow_cases()}) == len(fast_cases()) + len(slow_cases())


@pytest.mark.parametrize("case", _params(fast_cases()))
def test_hostile_input(server, case, tmp_path):
    run_case(server, case, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("case", _params(slow_cases()))
def test_hostile_input_large_samples(server, case, tmp_path):
    run_case(server, case, tmp_path)


def test_memory_option_is_checked_before_reading(tmp_path):
    from click.testing import CliRunner

    from c1mesh.cli import main

    result = CliRunner().invoke(main, ["info", "/dev/zero", "--input-format", "xyz", "--memory", "lots"])
    assert result.exit_code == 2 and "--memory must be a size" in result.output


def test_standard_input_that_is_a_directory_is_one_error_line(tmp_path):
    """CPython cannot start with a directory on stdin (a 4-line fatal error before any
    Python code runs), so bin/c1mesh, the installed `c1mesh` command, checks for it and
    otherwise runs c1mesh-python (here a stand-in beside it), also through a symlink."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    launcher = bindir / "c1mesh"
    launcher.write_bytes((ROOT / "bin" / "c1mesh").read_bytes())
    launcher.chmod(0o755)
    stand_in = bindir / "c1mesh-python"
    stand_in.write_text(f"#!{sys.executable}\nimport sys\nfrom c1mesh.cli import run\nsys.exit(run())\n")
    stand_in.chmod(0o755)
    (tmp_path / "link").symlink_to(launcher)
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    directory = os.open("/", os.O_RDONLY)
    try:
        fatal = subprocess.run([sys.executable, "-c", "pass"], stdin=directory, capture_output=True, timeout=60)
        proc = subprocess.run([str(launcher), "fit", "-", "--input-format", "xyz", "-o", str(tmp_path / "x.ply")],
                              stdin=directory, capture_output=True, timeout=60, env=env, cwd=tmp_path)
    finally:
        os.close(directory)
    assert fatal.returncode != 0 and b"Fatal Python error" in fatal.stderr   # why the launcher exists
    assert proc.returncode == 1
    assert proc.stderr.decode().splitlines() == ["c1mesh: error: Input '<stdin>' is a directory, not a point file."]
    assert not (tmp_path / "x.ply").exists()
    with open(SAMPLES / "wave_tilted_offset.xyz", "rb") as stdin:
        ok = subprocess.run([str(tmp_path / "link"), "info", "-", "--input-format", "xyz"], stdin=stdin,
                            capture_output=True, timeout=120, env=env, cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr.decode()
    assert json.loads(ok.stdout)["points"] == len(read_cloud_points(SAMPLES / "wave_tilted_offset.xyz"))
    usage = subprocess.run([str(launcher), "fit"], capture_output=True, timeout=60, env=env)
    assert usage.stderr.startswith(b"c1mesh: error: ") and b"see 'c1mesh fit --help'" in usage.stderr
    completion = subprocess.run([str(launcher)], capture_output=True, timeout=60,
                                env=dict(env, _C1MESH_COMPLETE="bash_source"))
    assert completion.stdout == (ROOT / "cli" / "completions" / "c1mesh.bash").read_bytes()


def read_cloud_points(path: Path):
    from c1mesh.formats import read_cloud

    return read_cloud(path).points
