"""Output paths never destroy an input or a complete file (c1mesh.core.outputs, the CLI's use of it).

Each case builds the situation on a real file system and runs the real command in a
subprocess, then looks at the files: inputs byte-identical, no temporary files left,
modes and file types kept, exactly one `c1mesh: error:` line on failure.
"""
from __future__ import annotations

import contextlib
import os
import signal
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from c1mesh.core.errors import InputError
from c1mesh.core.outputs import OutputError, Outputs, atomic_output, plan_outputs

ROOT = Path(__file__).resolve().parent.parent
HILL = ROOT / "data_samples" / "hill.ply"
C1MESH = [sys.executable, "-m", "c1mesh.cli"]


def run(*args, stdin=None, cwd=None, timeout=120):
    return subprocess.run(C1MESH + [str(a) for a in args], stdin=stdin, capture_output=True,
                          timeout=timeout, cwd=cwd)


def one_error_line(proc, expected: bool = True) -> str:
    """The single stderr line of a failed run; `expected`: not a crash reported as "unexpected"."""
    lines = [line for line in proc.stderr.decode().splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr.decode()
    assert lines[0].startswith("c1mesh: error: ") and "Traceback" not in lines[0], lines
    assert not expected or "unexpected" not in lines[0], lines
    return lines[0]


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if p.name.endswith(".tmp") or ".tmp" in p.name)


@pytest.fixture
def scan(tmp_path) -> Path:
    path = tmp_path / "a.ply"
    path.write_bytes(HILL.read_bytes())
    return path


# ------------------------------------------------------------------ outputs that are inputs
def test_report_equal_to_the_input_is_refused(scan):
    before = scan.read_bytes()
    proc = run("fit", scan, "-o", scan.parent / "o.ply", "--report", scan, "--level", "1")
    assert proc.returncode == 1 and "is the input" in one_error_line(proc)
    assert scan.read_bytes() == before and not (scan.parent / "o.ply").exists()


def test_report_equal_to_the_mesh_is_refused(scan):
    out = scan.parent / "o.ply"
    proc = run("fit", scan, "-o", out, "--report", out, "--level", "1")
    assert proc.returncode == 1 and "same file" in one_error_line(proc)
    assert not out.exists()
    proc = run("fit", scan, "-o", out, "--report", scan.parent / "." / "o.ply", "--level", "1")
    assert proc.returncode == 1 and not out.exists()


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_batch_output_named_like_a_later_input_is_refused_before_work(scan, jobs):
    later = scan.parent / "a.c1.ply"
    later.write_bytes(HILL.read_bytes())
    before = later.read_bytes()
    proc = run("fit", scan, later, "-O", scan.parent, "--jobs", jobs, "--level", "1", cwd=scan.parent)
    assert proc.returncode == 1 and "is the input" in one_error_line(proc)
    assert later.read_bytes() == before
    assert sorted(p.name for p in scan.parent.iterdir()) == ["a.c1.ply", "a.ply"]


def test_output_equal_to_the_file_on_stdin_is_refused(scan):
    before = scan.read_bytes()
    with open(scan, "rb") as stdin:
        proc = run("fit", "-", "--input-format", "ply", "-o", scan, "--level", "1", stdin=stdin)
    assert proc.returncode == 1 and "is the input '-'" in one_error_line(proc)
    assert scan.read_bytes() == before


def test_links_to_the_input_are_refused_by_real_path_and_by_inode(scan):
    before = scan.read_bytes()
    (scan.parent / "sym.ply").symlink_to(scan)
    os.link(scan, scan.parent / "hard.ply")
    for name in ("sym.ply", "hard.ply"):
        proc = run("fit", scan, "-o", scan.parent / name, "--level", "1")
        assert proc.returncode == 1 and "is the input" in one_error_line(proc), name
    assert scan.read_bytes() == before and (scan.parent / "sym.ply").is_symlink()


def test_a_symlink_output_is_followed_and_stays_a_link(scan, tmp_path):
    target = tmp_path / "elsewhere" / "real.ply"
    target.parent.mkdir()
    target.write_bytes(b"old")
    link = tmp_path / "link.ply"
    link.symlink_to(target)
    proc = run("fit", scan, "-o", link, "--level", "1")
    assert proc.returncode == 0, proc.stderr
    assert link.is_symlink() and target.read_bytes().startswith(b"ply\n")
    assert leftovers(tmp_path) == []


# ---------------------------------------------------------------- mesh and report together
def test_a_failed_report_leaves_no_mesh(scan):
    out = scan.parent / "o.ply"
    proc = run("fit", scan, "-o", out, "--report", "/dev/full", "--level", "1")
    assert proc.returncode == 1 and "No space left" in one_error_line(proc)
    assert not out.exists() and leftovers(scan.parent) == []
    out.write_bytes(b"previous result")
    proc = run("fit", scan, "-o", out, "--report", "/dev/full", "--level", "1")
    assert proc.returncode == 1 and out.read_bytes() == b"previous result"


def test_missing_report_folder_fails_before_work_and_leaves_no_mesh(scan):
    out = scan.parent / "o.ply"
    proc = run("fit", scan, "-o", out, "--report", scan.parent / "nodir" / "r.json", "--level", "1")
    assert proc.returncode == 1 and "does not exist" in one_error_line(proc)
    assert not out.exists()


# --------------------------------------------------------------------- modes and file types
def test_an_existing_outputs_mode_is_kept(scan):
    out, report = scan.parent / "o.ply", scan.parent / "r.json"
    for path, mode in ((out, 0o600), (report, 0o640)):
        path.write_bytes(b"x")
        path.chmod(mode)
    proc = run("fit", scan, "-o", out, "--report", report, "--level", "1")
    assert proc.returncode == 0, proc.stderr
    assert stat.S_IMODE(out.stat().st_mode) == 0o600 and stat.S_IMODE(report.stat().st_mode) == 0o640
    assert out.read_bytes().startswith(b"ply\n") and report.read_text().startswith("{")


def test_devices_and_fifos_are_written_straight(scan, tmp_path):
    proc = run("fit", scan, "-o", "/dev/null", "--report", "/dev/null", "--level", "1")
    assert proc.returncode == 0, proc.stderr
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    proc = run("fit", scan, "-o", "/dev/stdout", "--report", "/dev/stderr", "--level", "1")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(b"ply\nformat binary_little_endian") and b'"c1_certificate"' in proc.stderr
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    received = tmp_path / "received"
    with open(received, "wb") as sink:
        reader = subprocess.Popen(["cat", str(fifo)], stdout=sink)
        proc = run("fit", scan, "-o", fifo, "--level", "1")
        reader.wait(timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert stat.S_ISFIFO(fifo.lstat().st_mode) and received.read_bytes().startswith(b"ply\n")
    assert leftovers(tmp_path) == []


def test_a_copy_of_a_character_device_stays_a_device(scan, tmp_path):
    node = tmp_path / "null-copy"
    try:
        os.mknod(node, stat.S_IFCHR | 0o666, os.stat("/dev/null").st_rdev)
    except PermissionError:
        pytest.skip("creating a device node needs root (CI runs as root)")
    proc = run("fit", scan, "-o", tmp_path / "o.ply", "--report", node, "--level", "1")
    assert proc.returncode == 0, proc.stderr
    assert stat.S_ISCHR(node.lstat().st_mode)


def test_directories_block_devices_and_sockets_are_refused(scan, tmp_path):
    sock_path = tmp_path / "s.ply"
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(sock_path))
    cases = [(tmp_path, "is a directory"), (sock_path, "is a socket")]
    block = tmp_path / "block.ply"
    try:
        os.mknod(block, stat.S_IFBLK | 0o600, os.makedev(7, 0))
        cases.append((block, "is a block device"))
    except PermissionError:
        pass
    for path, message in cases:
        for option in ("-o", "--report"):
            args = ["-o", tmp_path / "o.ply", "--report", path] if option == "--report" else ["-o", path]
            proc = run("fit", scan, *args, "--level", "1")
            assert proc.returncode == 1 and message in one_error_line(proc), (path, option)
    server.close()
    assert stat.S_ISSOCK(sock_path.lstat().st_mode) and not (tmp_path / "o.ply").exists()


# -------------------------------------------------------------- failing before any reading
def _blocking_input(tmp_path: Path) -> Path:
    """A FIFO nobody writes to: reading it would block until the timeout."""
    fifo = tmp_path / "never.ply"
    os.mkfifo(fifo)
    return fifo


@pytest.mark.parametrize("args, code, message", [
    (["-o", "OUT.xyz"], 2, "Unsupported output format 'xyz'"),
    (["-o", "NODIR/o.ply"], 1, "does not exist"),
    (["-o", "OUT.ply", "--report", "NODIR/r.json"], 1, "does not exist"),
    (["-o", "OUT.obj", "--ascii"], 2, "--ascii applies to PLY output only"),
    (["-o", "OUT.ply", "--classes", "2"], 2, "--classes needs LAS/LAZ input"),
    (["-o", "OUT.ply", "--max-edge", "inf"], 2, "finite"),
    (["-o", "OUT.ply", "--axis", "0,0,0"], 2, "no direction"),
    (["-o", "OUT.ply", "--report", "OUT.ply"], 1, "same file"),
])
def test_output_problems_fail_before_the_input_is_read(tmp_path, args, code, message):
    fifo = _blocking_input(tmp_path)
    args = [a.replace("OUT", str(tmp_path / "o")).replace("NODIR", str(tmp_path / "nodir")) for a in args]
    proc = run("fit", fifo, *args, timeout=60)
    assert proc.returncode == code, proc.stderr
    assert message in proc.stderr.decode()
    if code == 1:
        one_error_line(proc)


def test_a_huge_but_valid_axis_is_a_direction(tmp_path):
    from c1mesh.stages.frame import parse_axis

    assert np.allclose(parse_axis("1e200,1e200,1e200"), np.full(3, 3 ** -0.5))
    assert np.allclose(parse_axis("1e-320,0,0"), [1, 0, 0])
    proc = run("fit", HILL, "-o", tmp_path / "o.ply", "--axis", "1e200,1e200,1e200", "--level", "1")
    assert proc.returncode == 0, proc.stderr


def test_library_fit_checks_its_output_before_reading(monkeypatch, tmp_path):
    import c1mesh.pipeline.driver as pipeline
    from c1mesh.pipeline.run import fit

    def must_not_read(*args, **kwargs):
        raise AssertionError("the input was read before the output was checked")
    monkeypatch.setattr(pipeline, "read_cloud", must_not_read)
    for target, message in ((tmp_path / "o.xyz", "Unsupported output format"),
                            (tmp_path / "nodir" / "o.ply", "does not exist"),
                            (HILL, "is the input")):
        with pytest.raises(InputError, match=message):
            fit(HILL, target)


# ------------------------------------------------------------- environments that are broken
def test_full_disk_closed_streams_long_names_and_proc(scan, tmp_path):
    cases = [
        (["fit", scan, "-o", "/dev/full", "--level", "1"], {}, "No space left on device"),
        (["fit", "-", "--input-format", "ply", "-o", tmp_path / "o.ply"], {"stdin": "closed"}, "Standard input is closed"),
        (["fit", scan, "-o", "-", "--level", "1"], {"stdout": "closed"}, "Standard output is closed"),
        (["info", scan], {"stdout": "closed"}, "Standard output is closed"),
        (["fit", scan, "-o", tmp_path / ("n" * 300 + ".ply")], {}, "too long"),
        (["fit", scan, HILL, "-O", "/proc/c1mesh-test"], {}, "output directory '/proc/c1mesh-test'"),
        (["fit", scan, "-o", "/proc/c1mesh.ply"], {}, "/proc/c1mesh.ply"),
    ]
    for args, closed, message in cases:
        keep = {"stdin": 0, "stdout": 1}
        pass_fds = ()
        close = [keep[name] for name in closed]

        def close_streams(fds=tuple(close)):
            for fd in fds:
                os.close(fd)
        proc = subprocess.run(C1MESH + [str(a) for a in args], capture_output=True, timeout=120,
                              preexec_fn=close_streams, pass_fds=pass_fds)
        assert proc.returncode == 1, (args, proc.stderr)
        assert message in one_error_line(proc), args
    assert leftovers(tmp_path) == [] and not (tmp_path / "o.ply").exists()


def test_numeric_warnings_do_not_reach_stderr(tmp_path):
    """A cloud whose coordinates overflow on squaring fails with one line, no RuntimeWarning
    (how it fails is the frame's business; here only that stderr carries one line)."""
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(-1, 1, (200, 2)) * 1e200, rng.uniform(-1, 1, 200) * 1e200])
    path = tmp_path / "huge.xyz"
    np.savetxt(path, xyz)
    proc = run("fit", path, "-o", tmp_path / "o.ply", "--level", "1")
    assert b"RuntimeWarning" not in proc.stderr and b"Traceback" not in proc.stderr
    if proc.returncode != 0:
        one_error_line(proc, expected=False)


# ------------------------------------------------------------------------------- signals
def _synthetic_scan(path: Path, n: int) -> Path:
    """A binary PLY of `n` random points on z = sin(x) cos(y) with exact unit normals."""
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 6, n), rng.uniform(0, 6, n)
    z = np.sin(x) * np.cos(y)
    normals = np.column_stack([-np.cos(x) * np.cos(y), np.sin(x) * np.sin(y), np.ones(n)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rows = np.column_stack([x, y, z, normals]).astype("<f4")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
              + "".join(f"property float {p}\n" for p in ("x", "y", "z", "nx", "ny", "nz"))
              + "end_header\n").encode()
    path.write_bytes(header + rows.tobytes())
    return path


@pytest.fixture(scope="module")
def big_scan(tmp_path_factory) -> Path:
    return _synthetic_scan(tmp_path_factory.mktemp("big") / "big.ply", 300_000)


@pytest.fixture(scope="module")
def mid_scan(tmp_path_factory) -> Path:
    return _synthetic_scan(tmp_path_factory.mktemp("mid") / "mid.ply", 30_000)


def _wait_for_temp(folder: Path, proc: subprocess.Popen, limit: float = 240.0) -> None:
    """Wait until a temporary output file (not the quick probe) in `folder` holds over 4 MB:
    the mesh is being written."""
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        with contextlib.suppress(FileNotFoundError):
            if any(p.name.endswith(".tmp") and not p.name.startswith(".c1mesh-probe.")
                   and p.stat().st_size > 4 << 20 for p in folder.iterdir()):
                return
        if proc.poll() is not None:
            raise AssertionError(f"c1mesh ended before writing: {proc.stderr.read().decode()}")
        time.sleep(0.01)
    raise AssertionError("no temporary output file appeared")


def _children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with open(task / "children") as listing:
            found += [int(p) for p in listing.read().split()]
    return found


def _alive(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "\nState:\tZ" not in status


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_a_signal_during_the_write_removes_the_temp_file(mid_scan, tmp_path, signum):
    _signal_during_write(mid_scan, tmp_path, signum)


@pytest.mark.slow
def test_a_signal_during_the_write_of_a_big_mesh(big_scan, tmp_path):
    _signal_during_write(big_scan, tmp_path, signal.SIGTERM)


def _signal_during_write(scan: Path, tmp_path: Path, signum: int) -> None:
    out = tmp_path / "out.ply"
    proc = subprocess.Popen(C1MESH + ["fit", str(scan), "-o", str(out), "--level", "8",
                                      "--report", str(tmp_path / "r.json")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _wait_for_temp(tmp_path, proc)
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, stderr
    assert stderr.decode().splitlines() == [f"c1mesh: error: interrupted ({signal.Signals(signum).name})"]
    assert list(tmp_path.iterdir()) == []


def test_a_signal_stops_a_parallel_batch_and_its_workers(mid_scan, tmp_path):
    inputs = []
    for name in ("b1", "b2", "b3"):
        inputs.append(tmp_path / f"{name}.ply")
        os.link(mid_scan, inputs[-1])
    out = tmp_path / "out"
    out.mkdir()
    proc = subprocess.Popen(C1MESH + ["fit", *map(str, inputs), "-O", str(out), "--jobs", "2", "--level", "8"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _wait_for_temp(out, proc)
    workers = _children(proc.pid)
    assert workers, "the batch runs in worker processes"
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert stderr.decode().splitlines() == ["c1mesh: error: interrupted (SIGTERM)"]
    time.sleep(1.0)                                   # a surviving worker would write on
    assert not any(_alive(pid) for pid in workers)
    assert list(out.iterdir()) == []


# ---------------------------------------------------------------------------- the module
def test_plan_outputs_classifies_and_compares(tmp_path):
    existing = tmp_path / "e.ply"
    existing.write_bytes(b"x")
    kinds = [t.kind for t in plan_outputs([("output", existing), ("report", tmp_path / "new.json"),
                                           ("log", "/dev/null"), ("copy", "-")])]
    assert kinds == ["atomic", "atomic", "straight", "stdio"]
    assert [t.kind for t in plan_outputs([("a", "/dev/null"), ("b", "/dev/null")])] == ["straight", "straight"]
    with pytest.raises(OutputError, match="is the input"):
        plan_outputs([("output", tmp_path / "sub" / ".." / "e.ply")], [existing])
    (tmp_path / "sub").mkdir()
    with pytest.raises(OutputError, match="same file"):
        plan_outputs([("a", tmp_path / "new.ply"), ("b", tmp_path / "sub" / ".." / "new.ply")])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.ply", "sub"]    # probes removed, nothing created


def test_outputs_commit_together_or_not_at_all(tmp_path):
    mesh, report = plan_outputs([("output", tmp_path / "m.ply"), ("report", tmp_path / "r.json")])
    with pytest.raises(RuntimeError):
        with Outputs() as outputs:
            with outputs.open(mesh) as f:
                f.write(b"mesh")
            assert not (tmp_path / "m.ply").exists()
            with outputs.open(report, "w") as f:
                raise RuntimeError("report failed")
    assert list(tmp_path.iterdir()) == []
    with Outputs() as outputs:
        for target, text in ((mesh, b"mesh"), (report, b"{}")):
            with outputs.open(target) as f:
                f.write(text)
        outputs.commit()
    assert (tmp_path / "m.ply").read_bytes() == b"mesh" and (tmp_path / "r.json").read_bytes() == b"{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply", "r.json"]


def test_atomic_output_keeps_mode_and_writes_devices_straight(tmp_path):
    path = tmp_path / "keep.bin"
    path.write_bytes(b"old")
    path.chmod(0o600)
    with atomic_output(path) as f:
        f.write(b"new")
    assert path.read_bytes() == b"new" and stat.S_IMODE(path.stat().st_mode) == 0o600
    with atomic_output("/dev/null", "w") as f:
        f.write("discarded")
    with pytest.raises(OutputError, match="No space left"):
        with atomic_output("/dev/full") as f:
            f.write(b"x" * 100_000)


def _blocked_opening_a_fifo(pid: int) -> bool:
    """True while process `pid` waits in open() for the other end of a FIFO (Linux)."""
    with contextlib.suppress(OSError):
        return Path(f"/proc/{pid}/wchan").read_text().strip() == "wait_for_partner"
    return False


@pytest.mark.skipif(not Path("/proc/self/wchan").exists(), reason="needs Linux /proc/PID/wchan")
def test_a_killed_run_waiting_for_its_fifo_input_leaves_no_temp_file(tmp_path):
    """The temporary output is created at the first write, so a run killed (SIGKILL: no
    handler can clean up) while its input FIFO has no writer leaves nothing behind."""
    fifo = tmp_path / "in.xyz"
    os.mkfifo(fifo)
    out = tmp_path / "out"
    out.mkdir()
    proc = subprocess.Popen(C1MESH + ["fit", str(fifo), "-o", str(out / "out.ply"), "--report",
                                      str(out / "r.json")], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not _blocked_opening_a_fifo(proc.pid):
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "c1mesh never opened its input"
            time.sleep(0.02)
    finally:
        proc.kill()
        proc.communicate(timeout=60)
    assert list(out.iterdir()) == []


def test_an_output_with_nothing_written_is_still_created(tmp_path):
    """Creating the temp file at the first write must not lose an output that is empty."""
    (target,) = plan_outputs([("output", tmp_path / "empty.txt")])
    with Outputs() as outputs:
        with outputs.open(target, "w"):
            assert list(tmp_path.iterdir()) == []
        outputs.commit()
    assert (tmp_path / "empty.txt").read_bytes() == b""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.txt"]
