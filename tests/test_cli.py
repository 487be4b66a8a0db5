"""The `c1mesh` command: exit codes, one-line errors, no partial outputs, stdin/stdout, batch."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from c1mesh.cli import main, usage_error
from stderr_lines import stderr_on_a_terminal
from c1mesh.formats import read_cloud

ROOT = Path(__file__).resolve().parent.parent
SAMPLES = ROOT / "data_samples"
C1MESH = [sys.executable, "-m", "c1mesh.cli"]


def run(*args, stdin: bytes | None = None):
    return subprocess.run(C1MESH + [str(a) for a in args], input=stdin, capture_output=True, timeout=300)


def assert_one_line_error(stderr: bytes):
    text = stderr.decode()
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1, text
    assert lines[0].startswith("c1mesh: error: ") and "Traceback" not in text


def test_fit_through_a_real_subprocess(tmp_path):
    out = tmp_path / "hill.ply"
    proc = run("fit", SAMPLES / "hill.ply", "-o", out, "--level", "2", "--report", tmp_path / "r.json")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == b""                       # quiet in a pipe
    report = json.loads((tmp_path / "r.json").read_text())
    mesh = read_cloud(out)
    assert len(mesh) == report["output_mesh"]["vertices"]
    assert not list(tmp_path.glob("*.tmp*")) and len(list(tmp_path.iterdir())) == 2


def test_stdin_to_stdout(tmp_path):
    data = (SAMPLES / "wave_tilted_offset.xyz").read_bytes()
    proc = run("fit", "-", "--input-format", "xyz", "-o", "-", "--level", "2", stdin=data)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(b"ply\nformat binary_little_endian")
    (tmp_path / "piped.ply").write_bytes(proc.stdout)
    assert len(read_cloud(tmp_path / "piped.ply")) > 2000


def run_on_terminal(*args, timeout: float = 120) -> tuple[int, bytes, bytes]:
    """Run c1mesh with its stdout on a real pseudo-terminal and stderr on a pipe: (exit code,
    what reached the terminal with its \\r\\n turned back into \\n, stderr). The terminal is
    read while the process runs, so a large output cannot block it."""
    import os
    import pty
    import select

    master, slave = pty.openpty()
    try:
        proc = subprocess.Popen(C1MESH + [str(a) for a in args], stdin=subprocess.DEVNULL, stdout=slave,
                                stderr=subprocess.PIPE)
        os.close(slave)
        screen = bytearray()
        while select.select([master], [], [], timeout)[0]:
            try:
                chunk = os.read(master, 1 << 16)
            except OSError:                  # EIO: the process closed its end of the terminal
                break
            if not chunk:
                break
            screen += chunk
        stderr = proc.stderr.read()
        code = proc.wait(timeout)
    finally:
        os.close(master)
    return code, bytes(screen).replace(b"\r\n", b"\n"), stderr


def test_binary_output_to_a_terminal_is_a_usage_error_before_reading(tmp_path):
    """Issue 35: `fit X -o -` with stdout a terminal would print binary PLY on the screen.
    Refused like gzip does: exit 2, one line, nothing on the terminal; the input does not
    exist, so the refusal came before it was looked at. Other problems share the line."""
    code, screen, stderr = run_on_terminal("fit", tmp_path / "missing.ply", "-o", "-")
    assert code == 2 and screen == b""
    assert_one_line_error(stderr)
    assert "refusing to write binary output to a terminal; redirect it or use -o FILE" in stderr.decode()
    assert "missing.ply" not in stderr.decode()
    code, screen, stderr = run_on_terminal("fit", tmp_path / "missing.ply", "-o", "-", "--classes", "2")
    assert code == 2 and screen == b""
    assert_one_line_error(stderr)
    assert "refusing to write binary output" in stderr.decode() and "--classes needs LAS/LAZ" in stderr.decode()


def test_text_output_to_a_terminal_is_written(tmp_path):
    """ASCII PLY is text: `-o - --ascii` on a terminal shows the same bytes as the file."""
    code, screen, stderr = run_on_terminal("fit", SAMPLES / "hill.ply", "-o", "-", "--ascii", "--level", "1")
    assert code == 0, stderr
    proc = run("fit", SAMPLES / "hill.ply", "-o", tmp_path / "hill.ply", "--ascii", "--level", "1")
    assert proc.returncode == 0, proc.stderr
    assert screen.startswith(b"ply\nformat ascii 1.0\n") and screen == (tmp_path / "hill.ply").read_bytes()


@pytest.mark.parametrize("fmt, ascii_ply", [("ply", False), ("ply", True), ("obj", False), ("stl", False),
                                            ("off", False), ("glb", False)])
def test_the_registry_knows_which_outputs_are_binary(tmp_path, fmt, ascii_ply):
    """c1mesh.core.outputs.is_binary_output, behind the terminal refusal, against what each
    writer really writes: text is printable ASCII lines, anything else is binary."""
    from c1mesh.core.cloud import SurfaceMesh
    from c1mesh.core.outputs import is_binary_output
    from c1mesh.formats import write_mesh

    mesh = SurfaceMesh(vertices=np.array([[0.0, 0, 0], [1, 0, 0.5], [0, 1, 0.25]]), faces=np.array([[0, 1, 2]]),
                       vertex_normals=np.array([[0.0, 0, 1]] * 3))
    write_mesh(mesh, tmp_path / f"m.{fmt}", ascii=ascii_ply)
    data = (tmp_path / f"m.{fmt}").read_bytes()
    text = all(32 <= byte < 127 or byte in b"\n\r\t" for byte in data)
    assert is_binary_output(fmt, ascii_ply) == (not text)


def test_report_to_stderr_and_verbose(tmp_path):
    result = CliRunner().invoke(main, ["fit", str(SAMPLES / "hill.ply"), "-o", str(tmp_path / "o.ply"),
                                       "--level", "1", "--report", "-"])
    assert result.exit_code == 0
    assert '"c1_certificate"' in result.stderr


def _notes(stderr: str) -> list[str]:
    """The `c1mesh: note:` lines of stderr (a terminal's: progress may share a line's start)."""
    return re.findall(r"c1mesh: note: [^\r\n]*", stderr)


def _ground_with_normals(path) -> None:
    """Autzen's ground points as an ASCII PLY with the normals (0, 0, 1): a file with
    normals, whose default is the exact fit, and whose heights are noisy."""
    import laspy

    las = laspy.read(SAMPLES / "autzen_trim.laz")
    ground = las.classification == 2
    x, y, z = np.asarray(las.x)[ground], np.asarray(las.y)[ground], np.asarray(las.z)[ground]
    header = ["ply", "format ascii 1.0", f"element vertex {x.size}", "property double x", "property double y",
              "property double z", "property double nx", "property double ny", "property double nz", "end_header"]
    rows = [f"{a:.3f} {b:.3f} {c:.3f} 0 0 1" for a, b, c in zip(x, y, z)]
    path.write_text("\n".join(header + rows) + "\n")


def test_noisy_heights_draw_the_advice_to_smooth_once_on_a_terminal(tmp_path):
    """Issue 35: the report's advice to fit noisy heights with --smooth auto is also one
    `c1mesh: note:` line on a terminal (issue 38: as progress, never on a pipe). Autzen
    ground with its normals in the file (the default there is the exact fit) is noisy by
    the rule's own measure (the limiter changed the gradients of over 10% of the kept
    points), hill.ply's exact heights are not; -q silences the note. Without normals the
    default is the smoothing fit, which draws no advice."""
    sample, report = tmp_path / "ground.ply", tmp_path / "r.json"
    _ground_with_normals(sample)
    shown = stderr_on_a_terminal(["fit", str(sample), "-o", str(tmp_path / "g.ply"), "--axis", "z",
                                  "--report", str(report)])
    facts = json.loads(report.read_text())
    assert facts["overshoot"]["gradients_limited"] > 0.1 * facts["points"]["kept"]
    assert facts["suggestion"].startswith("the heights look noisy") and "--smooth auto" in facts["suggestion"]
    assert shown.count(f"c1mesh: note: {sample}: {facts['suggestion']}") == 1, shown
    piped = run("fit", sample, "--axis", "z", "-o", tmp_path / "p.ply")
    assert piped.returncode == 0 and piped.stderr == b""
    quiet = stderr_on_a_terminal(["fit", str(sample), "--axis", "z", "-o", str(tmp_path / "q.ply"), "-q"])
    assert quiet == ""
    exact = stderr_on_a_terminal(["fit", str(SAMPLES / "hill.ply"), "-o", str(tmp_path / "h.ply"), "-q"])
    assert "note" not in exact
    smoothed = tmp_path / "s.json"
    default = stderr_on_a_terminal(["fit", str(SAMPLES / "autzen_trim.laz"), "--classes", "2", "-o",
                                    str(tmp_path / "s.ply"), "--report", str(smoothed)])
    assert "suggestion" not in json.loads(smoothed.read_text())
    notes = [line for line in default.splitlines() if line.startswith("c1mesh: note: ")]
    assert len(notes) == 1 and "fitted to the points by default (--smooth off" in notes[0]
    assert "--smooth auto chose strength" in notes[0]


@pytest.mark.parametrize("smooth", ["auto", "off"])
def test_no_advice_to_smooth_when_smooth_is_given(tmp_path, smooth):
    """topo.csv's exact fit draws the advice (52 noisy-looking heights); with --smooth given,
    auto or off, the user has chosen and no advice is printed (auto's one note says which
    strength it chose)."""
    sample = SAMPLES / "topo.csv"
    plain = stderr_on_a_terminal(["fit", str(sample), "-o", str(tmp_path / "p.ply"), "--level", "1"])
    assert len(_notes(plain)) == 1 and "--smooth auto" in _notes(plain)[0]
    chosen = stderr_on_a_terminal(["fit", str(sample), "-o", str(tmp_path / "s.ply"), "--level", "1",
                                   "--smooth", smooth, "--report", str(tmp_path / "r.json")])
    strength = [note for note in _notes(chosen) if "--smooth auto chose strength" in note]
    assert len(strength) == (smooth == "auto") and len(_notes(chosen)) == len(strength)
    assert ("smoothing" in json.loads((tmp_path / "r.json").read_text())) == (smooth == "auto")


def test_quintic_warns(tmp_path):
    result = CliRunner().invoke(main, ["fit", str(SAMPLES / "hill.ply"), "-o", str(tmp_path / "q.ply"),
                                       "--level", "1", "--scheme", "quintic", "--report", str(tmp_path / "q.json")])
    assert result.exit_code == 0, result.stderr
    assert result.stderr.splitlines() == [
        "c1mesh: warning: the quintic scheme does not reproduce planes and its normals do not converge; "
        "use sextic unless you need the 2022 procedure"]
    assert json.loads((tmp_path / "q.json").read_text())["scheme"]["name"] == "quintic"
    assert read_cloud(tmp_path / "q.ply").points.shape[1] == 3


@pytest.mark.parametrize("args", [
    ["fit", "IN"],                                         # no -o
    ["fit", "-", "-o", "OUT"],                             # stdin without format
    ["fit", "IN", "-o", "OUT", "--level", "0"],
    ["fit", "IN", "-o", "OUT", "--max-edge", "-3"],
    ["fit", "IN", "IN", "-o", "OUT"],                      # several inputs need -O
    ["fit", "IN", "-o", "OUT", "--classes", "two"],
    ["frobnicate"],
])
def test_usage_errors_exit_2(tmp_path, args):
    args = [str(SAMPLES / "hill.ply") if a == "IN" else str(tmp_path / "out.ply") if a == "OUT" else a
            for a in args]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 2
    assert not (tmp_path / "out.ply").exists()


@pytest.mark.parametrize("viewpoint", ["1,2", "a,b,c", "1,2,3,4,5", "1,2,nan", "1,2,3,0,0,0,0"])
def test_a_malformed_viewpoint_is_a_usage_error_before_reading(tmp_path, viewpoint):
    """--viewpoint was parsed only by the perspective fit, after the input was read: exit 1
    naming the input there, and silently ignored in the axis frame (exit 0)."""
    for frame in ("auto", "perspective"):
        result = CliRunner().invoke(main, ["fit", str(tmp_path / "missing.xyz"), "-o", str(tmp_path / "out.ply"),
                                           "--frame", frame, "--viewpoint", viewpoint])
        assert result.exit_code == 2, result.stderr
        assert result.stderr.count("\n") == 1 and "'--viewpoint'" in result.stderr
        assert not (tmp_path / "out.ply").exists()


def _malformed(tmp_path: Path) -> dict[str, Path]:
    files = {
        "missing": tmp_path / "missing.ply",
        "empty": tmp_path / "empty.ply",
        "bad-magic": tmp_path / "magic.ply",
        "no-end-header": tmp_path / "noend.ply",
        "truncated": tmp_path / "trunc.ply",
        "garbage-pcd": tmp_path / "garbage.pcd",
        "garbage-las": tmp_path / "garbage.las",
        "two-points": tmp_path / "two.xyz",
        "collinear": tmp_path / "line.xyz",
        "all-nan": tmp_path / "nan.xyz",
        "text-in-xyz": tmp_path / "words.xyz",
        "directory": tmp_path / "adir.ply",
    }
    files["empty"].write_bytes(b"")
    files["bad-magic"].write_bytes(b"plx\nformat ascii 1.0\nend_header\n")
    files["no-end-header"].write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n")
    files["truncated"].write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 500\n"
                                   b"property float x\nproperty float y\nproperty float z\nend_header\n"
                                   + bytes(range(256)) * 3)
    files["garbage-pcd"].write_bytes(np.random.default_rng(0).bytes(3000))
    files["garbage-las"].write_bytes(np.random.default_rng(1).bytes(3000))
    files["two-points"].write_text("0 0 0 0 0 1\n1 0 0 0 0 1\n")
    files["collinear"].write_text("".join(f"{i} {2 * i} 0 0 0 1\n" for i in range(10)))
    files["all-nan"].write_text("nan nan nan 0 0 1\n" * 10)
    files["text-in-xyz"].write_text("1 2 3\nfour five six\n")
    files["directory"].mkdir()
    return files


def test_malformed_inputs_fail_cleanly(tmp_path):
    for name, path in _malformed(tmp_path).items():
        out = tmp_path / f"out-{name}.ply"
        proc = run("fit", path, "-o", out)
        assert proc.returncode == 1, (name, proc.stderr)
        assert_one_line_error(proc.stderr)
        assert not out.exists(), name
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith("out-") or ".tmp" in p.name]
    assert leftovers == []


def test_not_a_height_field_fails_with_advice(tmp_path):
    proc = run("fit", SAMPLES / "o3d_cloud_bin_0.pcd", "-o", tmp_path / "room.ply")
    assert proc.returncode == 1
    assert_one_line_error(proc.stderr)
    assert b"height field" in proc.stderr and b"--axis" in proc.stderr
    assert not (tmp_path / "room.ply").exists()


def test_output_equal_to_input_is_refused_and_input_untouched(tmp_path):
    src = tmp_path / "scan.ply"
    shutil.copy(SAMPLES / "hill.ply", src)
    before = src.read_bytes()
    proc = run("fit", src, "-o", src)
    assert proc.returncode == 1 and b"input" in proc.stderr
    assert src.read_bytes() == before


def test_unwritable_output_directory(tmp_path):
    proc = run("fit", SAMPLES / "hill.ply", "-o", tmp_path / "nope" / "deeper" / "out.ply")
    assert proc.returncode == 1
    assert_one_line_error(proc.stderr)


def test_existing_output_survives_a_failed_run(tmp_path):
    out = tmp_path / "out.ply"
    out.write_bytes(b"precious")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nnonsense\n")
    assert run("fit", bad, "-o", out).returncode == 1
    assert out.read_bytes() == b"precious"


def test_batch_with_a_bad_file_exits_3(tmp_path):
    good = tmp_path / "good.ply"
    shutil.copy(SAMPLES / "hill.ply", good)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"garbage")
    proc = run("fit", good, bad, "-O", tmp_path / "out", "--jobs", "2", "--level", "1")
    assert proc.returncode == 3
    assert (tmp_path / "out" / "good.c1.ply").exists()
    assert not (tmp_path / "out" / "bad.c1.ply").exists()
    assert b"bad.ply" in proc.stderr and b"1 of 2 inputs failed" in proc.stderr


def test_info_and_schemes():
    info = run("info", SAMPLES / "hill.ply")
    assert info.returncode == 0
    facts = json.loads(info.stdout)
    assert facts["points"] == 3000 and facts["normals"] and facts["height_field"] is True
    room = json.loads(run("info", SAMPLES / "o3d_cloud_bin_0.pcd").stdout)
    assert room["height_field"] is False
    schemes = run("schemes").stdout.decode().splitlines()
    rows = {line.split()[0]: line.split() for line in schemes[1:]}
    assert rows["sextic"][2:4] == ["yes", "yes"] and rows["quintic"][2:4] == ["yes", "no"]
    assert [line.count("(default)") for line in schemes[1:]] == [1, 0, 0]   # sextic, marked once


_STARTUP_PROBE = """
import sys, time
start = time.perf_counter()
from c1mesh.cli import main
try:
    main({args!r}, prog_name="c1mesh")
except SystemExit as stop:
    code = stop.code
heavy = sorted(m for m in ("numpy", "scipy", "open3d", "trimesh", "laspy", "matplotlib") if m in sys.modules)
print(code, heavy, time.perf_counter() - start, file=sys.stderr)
"""


@pytest.mark.parametrize("args, code", [(["--help"], 0), (["fit", "--help"], 0), (["fit", "x.ply"], 2),
                                        (["fit", "x.ply", "-o", "y.ply", "--level", "0"], 2),
                                        (["fit", "x.ply", "-o", "y.ply", "--max-edge", "inf"], 2)])
def test_help_and_usage_errors_load_nothing_heavy(args, code):
    """--help and usage errors answer without importing the numerical stack (which takes
    seconds): checked by the modules loaded, not by a timing."""
    proc = subprocess.run([sys.executable, "-c", _STARTUP_PROBE.format(args=args)], capture_output=True,
                          timeout=60)
    last = proc.stderr.decode().splitlines()[-1].split(" ", 1)
    assert last[0] == str(code), proc.stderr
    assert last[1].startswith("[]"), last


def test_shell_end_to_end_script(tmp_path):
    """cli/e2e.sh against the installed command (the venv's console script)."""
    exe = Path(sys.executable).parent / "c1mesh"
    if not exe.exists():
        pytest.fail(f"console script {exe} is not installed; run ./setup.sh")
    proc = subprocess.run(["bash", str(ROOT / "cli" / "e2e.sh"), str(exe)], capture_output=True, timeout=600)
    assert proc.returncode == 0, proc.stdout.decode() + proc.stderr.decode()
    assert b"all end-to-end checks passed" in proc.stdout


def test_examples_run(tmp_path):
    for script in ("interpolate_surface.py", "fit_scan.py"):
        proc = subprocess.run([sys.executable, str(ROOT / "examples" / script)], capture_output=True, timeout=300)
        assert proc.returncode == 0, proc.stderr.decode()
    exe = Path(sys.executable).parent / "c1mesh"
    proc = subprocess.run(["bash", str(ROOT / "examples" / "batch_and_pipe.sh"), str(exe)],
                          capture_output=True, timeout=300)
    assert proc.returncode == 0, proc.stderr.decode()
    assert b"hill.c1.ply" in proc.stdout and b"element vertex" in proc.stdout


def test_fit_scan_example_fits_the_bundled_las_ground(tmp_path):
    out = tmp_path / "ground.ply"
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "fit_scan.py"), str(SAMPLES / "4_6_crop.las"),
                           str(out)], capture_output=True, timeout=300)
    assert proc.returncode == 0, proc.stderr.decode()
    assert "of 9003 points" in proc.stdout.decode()       # the tile's class-2 (ground) points
    assert len(read_cloud(out)) > 9003


def test_batch_example_finds_the_setup_venv_without_path(tmp_path):
    """After ./setup.sh, with nothing on PATH, the example uses <repo>/.venv/bin/c1mesh."""
    repo = tmp_path / "repo"
    (repo / "examples").mkdir(parents=True)
    (repo / "data_samples").mkdir()
    shutil.copy(ROOT / "examples" / "batch_and_pipe.sh", repo / "examples")
    for name in ("hill.ply", "wave_tilted_offset.xyz"):
        shutil.copy(SAMPLES / name, repo / "data_samples")
    (repo / ".venv" / "bin").mkdir(parents=True)
    (repo / ".venv" / "bin" / "c1mesh").symlink_to(Path(sys.executable).parent / "c1mesh")
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path),
           **{k: v for k, v in __import__("os").environ.items() if k == "PYTHONPATH"}}
    proc = subprocess.run(["bash", str(repo / "examples" / "batch_and_pipe.sh")], env=env,
                          capture_output=True, timeout=300)
    assert proc.returncode == 0, proc.stderr.decode()
    assert b"hill.c1.ply" in proc.stdout and b"element vertex" in proc.stdout


@pytest.mark.parametrize("shell", ["bash", "zsh", "fish"])
def test_completion_files_are_current(shell):
    """cli/completions/ must match what click generates for the installed command."""
    exe = Path(sys.executable).parent / "c1mesh"
    env = {**__import__("os").environ, "_C1MESH_COMPLETE": f"{shell}_source"}
    generated = subprocess.run([str(exe)], env=env, capture_output=True, timeout=60).stdout
    assert generated == (ROOT / "cli" / "completions" / f"c1mesh.{shell}").read_bytes()
    # and completion works: options of `fit` are offered
    env = {**__import__("os").environ, "_C1MESH_COMPLETE": "bash_complete", "COMP_WORDS": "c1mesh fit --le",
           "COMP_CWORD": "2"}
    offered = subprocess.run([str(exe)], env=env, capture_output=True, timeout=60).stdout
    assert b"--level" in offered


# ------------------------------------------------------------------- usage errors: one line
_USAGE_CASES = {
    "level 0": (["fit", "IN.ply", "-o", "OUT.ply", "--level", "0"], ["'--level'"]),
    "no -o": (["fit", "IN.ply"], ["give -o OUTPUT"]),
    "classes on a PLY": (["fit", "IN.ply", "-o", "OUT.ply", "--classes", "2"], ["--classes needs LAS/LAZ"]),
    "slope with a mesh output": (["fit", "IN.laz", "-o", "OUT.ply", "--slope", "SLOPE.tif"],
                                 ["need --resolution", "come with a DEM: give -o DEM.tif"]),
    "slope not a tif, no resolution": (["fit", "IN.laz", "-o", "OUT.tif", "--slope", "SLOPE.ply"],
                                       ["need --resolution", "'SLOPE.ply' must be a GeoTIFF"]),
    "unsupported output": (["fit", "IN.ply", "-o", "OUT.xyz", "--ascii"],
                           ["Unsupported output format 'xyz'", "--ascii applies to PLY output only"]),
    "several inputs to -o": (["fit", "IN.ply", "IN2.ply", "-o", "OUT.ply"], ["several inputs need -O"]),
    "unknown command": (["frobnicate"], ["No such command 'frobnicate'"]),
    "preview not a PNG": (["preview", "IN.tif", "-o", "OUT.jpg"], ["must be a .png file"]),
    "z-factor zero": (["fit", "IN.ply", "-o", "OUT.tif", "--resolution", "1", "--slope", "SLOPE.tif",
                       "--z-factor", "0"], ["--z-factor must be a positive finite number"]),
    "z-factor NaN with another problem": (["fit", "IN.ply", "-o", "OUT.ply", "--z-factor", "nan", "--level", "2",
                                           "--resolution", "1"],
                                          ["--z-factor must be a positive finite number", "got nan",
                                           "either --level or --resolution"]),
    "z-factor inf": (["fit", "IN.ply", "-o", "OUT.ply", "--z-factor", "inf"], ["got inf"]),
}


@pytest.mark.parametrize("case", list(_USAGE_CASES))
def test_usage_errors_are_one_line_and_exit_2_before_any_input_is_read(tmp_path, case):
    """cli/README.md: a usage error is one `c1mesh: error:` line, exit 2, nothing written;
    conflicting options are all named in that line. The inputs do not exist, so an error
    about them would show that they were looked at before the command line was checked."""
    args, words = _USAGE_CASES[case]
    names = {"IN.ply": "missing.ply", "IN2.ply": "missing2.ply", "IN.laz": "missing.laz",
             "OUT.ply": "out.ply", "OUT.tif": "out.tif", "OUT.xyz": "out.xyz", "SLOPE.tif": "slope.tif",
             "SLOPE.ply": "slope.ply", "IN.tif": "missing.tif", "OUT.jpg": "out.jpg"}
    argv = [str(tmp_path / names[a]) if a in names else a for a in args]
    proc = run(*argv)
    assert proc.returncode == 2, proc.stderr
    assert_one_line_error(proc.stderr)
    line = proc.stderr.decode().strip()
    for word in words:
        assert word.replace("SLOPE.ply", str(tmp_path / "slope.ply")) in line, line
    assert "does not exist" not in line and list(tmp_path.iterdir()) == []
    assert usage_error(argv) == line.replace("python -m c1mesh.cli", "c1mesh")   # the public check agrees


def test_usage_error_is_none_for_good_command_lines(tmp_path):
    assert usage_error(["fit", "scan.ply", "-o", "mesh.ply", "--level", "2"]) is None
    assert usage_error(["fit", "tile.laz", "--classes", "2", "-o", "dem.tif", "--resolution", "1",
                        "--slope", "slope.tif", "--preview", "p.png"]) is None
    assert usage_error(["fit", "--help"]) is None and usage_error(["info", "scan.ply"]) is None
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------- one list of formats
def _option_help(command, name: str) -> str:
    return next(p.help for p in command.params if p.name == name)


def test_help_and_errors_list_exactly_the_registry_formats():
    """-o's help, --input-format's help (fit and info) and the unsupported-format errors name
    the formats of c1mesh.core.outputs, which c1mesh.formats and c1mesh.geo.raster read and write."""
    import re

    from c1mesh import formats

    from c1mesh.geo import raster
    from c1mesh.cli import fit, info
    from c1mesh.core.outputs import INPUT_FORMATS, MESH_FORMATS, OUTPUT_FORMATS, RASTER_FORMATS

    assert formats.SUPPORTED_INPUT == INPUT_FORMATS and formats.SUPPORTED_OUTPUT == MESH_FORMATS
    assert OUTPUT_FORMATS == MESH_FORMATS + RASTER_FORMATS
    assert raster.RASTER_SUFFIXES == tuple("." + f for f in RASTER_FORMATS)
    assert tuple(re.findall(r"\.([a-z]+)\b", _option_help(fit, "output"))) == OUTPUT_FORMATS
    for command in (fit, info):
        listed = re.search(r"\(([a-z, ]+)\)", _option_help(command, "input_format")).group(1)
        assert tuple(listed.split(", ")) == INPUT_FORMATS

    def supported(message: str) -> tuple[str, ...]:
        return tuple(re.search(r"supported: ([a-z, ]+)", message).group(1).split(", "))
    assert supported(usage_error(["fit", "a.ply", "-o", "b.xyz"])) == OUTPUT_FORMATS
    assert supported(usage_error(["fit", "a.e57", "--input-format", "e57", "-o", "b.ply"])) == INPUT_FORMATS


@pytest.mark.parametrize("args, culprit", [
    (["-o", "OUT"], "No output format (no extension) for 'OUT'"),
    (["-o", "OUT.las"], "Unsupported output format 'las' for 'OUT.las'"),
    (["-o", "FILE"], "No output format (no extension) for 'FILE'"),
    (["--seamless", "-o", "OUT"], "No output format (no extension) for 'OUT'"),
    (["-O", "DIR", "--suffix", ".las"], "Unsupported output format 'las' for --suffix '.las'"),
    (["-O", "DIR", "--suffix", "_mesh"], "No output format (no extension) for --suffix '_mesh'"),
], ids=["-o x", "-o x.las", "-o existing file", "--seamless -o x", "--suffix .las", "--suffix _mesh"])
def test_an_unknown_or_missing_output_extension_is_a_usage_error(tmp_path, args, culprit):
    """Issue 35: `-o x` exited 1 with a list of mesh formats only, `-o x.las` 2. Both are
    usage errors: exit 2, one line, before the inputs (missing here) are looked at, nothing
    created (not even -O's folder), listing what c1mesh writes: the mesh writers of
    c1mesh.formats and the GeoTIFF suffixes of c1mesh.geo.raster. With -O the line names
    the --suffix once, not each input's path."""
    import re

    from c1mesh import formats
    from c1mesh.geo import raster

    (tmp_path / "file").write_bytes(b"an existing file without an extension")
    names = {"OUT": str(tmp_path / "out"), "OUT.las": str(tmp_path / "out.las"), "FILE": str(tmp_path / "file"),
             "DIR": str(tmp_path / "dir")}
    argv = ["fit", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), *(names.get(a, a) for a in args)]
    if "-o" in args and "--seamless" not in args:
        del argv[2]                                   # -o takes one input
    proc = run(*argv)
    assert proc.returncode == 2, proc.stderr
    assert_one_line_error(proc.stderr)
    line = proc.stderr.decode()
    for name, path in names.items():
        culprit = culprit.replace(f"'{name}'", f"'{path}'")
    assert line.count("output format") == 1 and culprit in line, line
    listed = re.search(r"supported: ([a-z, ]+)", line).group(1).split(", ")
    assert listed == [*formats.SUPPORTED_OUTPUT, *(suffix.lstrip(".") for suffix in raster.RASTER_SUFFIXES)]
    assert "a.ply" not in line and sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    assert (tmp_path / "file").read_bytes() == b"an existing file without an extension"


def test_readmes_list_exactly_the_registry_formats():
    """README.md's 'in'/'out' lists and cli/README.md's --input-format row and output
    paragraph name the registry's formats, no more, no fewer."""
    import re

    from c1mesh.core.outputs import INPUT_FORMATS, OUTPUT_FORMATS

    readme = (ROOT / "README.md").read_text()
    read_in = re.search(r"# ([A-Z/]+) in\b", readme).group(1)
    written = re.search(r"; ([a-z ]+) out\b", readme).group(1)
    assert tuple(read_in.lower().split("/")) == INPUT_FORMATS
    assert tuple(written.split()) == OUTPUT_FORMATS
    reference = (ROOT / "cli" / "README.md").read_text()
    row = next(line for line in reference.splitlines() if line.startswith("| `--input-format FMT`"))
    meaning = row.split("|")[3]
    assert tuple(re.match(r" `([a-z ]+)`", meaning).group(1).split()) == INPUT_FORMATS
    paragraph = reference[reference.index("Output formats by extension:"):reference.index("What each format keeps")]
    assert tuple(re.findall(r"`\.([a-z]+)`", paragraph)) == OUTPUT_FORMATS


# ------------------------------------------------------------------- --scheduler, in memory
@pytest.mark.parametrize("survey", [False, True], ids=["one file", "--seamless -o"])
def test_scheduler_for_a_fit_in_memory_fits_here_with_a_note(tmp_path, survey):
    """README: `fit BIG.laz ... -o big.ply --memory 2G --scheduler ADDR`. When the input fits
    in memory there are no tiles to send: the fit runs here, writes what a run without
    --scheduler writes, prints one `c1mesh: note:` line about it and says so in the report."""
    distributed = pytest.importorskip("distributed")
    args = ["fit", str(SAMPLES / "4_6_crop.las"), "--classes", "2", "--level", "2", "--memory", "2G"]
    args += ["--seamless"] if survey else []
    here = CliRunner().invoke(main, args + ["-o", str(tmp_path / "here.ply")])
    assert here.exit_code == 0, here.output
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        sent = CliRunner().invoke(main, args + ["-o", str(tmp_path / "big.ply"), "--scheduler",
                                                cluster.scheduler_address, "--report", str(tmp_path / "r.json")])
    assert sent.exit_code == 0, sent.output
    notes = [line for line in sent.stderr.splitlines() if line.startswith("c1mesh: note: ")]
    assert len(notes) == 1 and "--scheduler not used" in notes[0], sent.stderr   # not a terminal: no advice
    assert "c1mesh: error" not in sent.stderr
    assert json.loads((tmp_path / "r.json").read_text())["scheduler"].startswith("not used: ")
    assert (tmp_path / "big.ply").read_bytes() == (tmp_path / "here.ply").read_bytes()


@pytest.mark.parametrize("stdin", [False, True])
def test_an_error_of_the_fit_itself_names_the_input(tmp_path, stdin):
    """The room scan is walls and floor, not a height field: the one error line says which
    input it is about (the fit's own message does not name it), and no output is left."""
    room, out = SAMPLES / "o3d_cloud_bin_0.pcd", tmp_path / "room.ply"
    if stdin:
        proc = subprocess.run([sys.executable, "-m", "c1mesh.cli", "fit", "-", "--input-format", "pcd",
                               "-o", str(out)], stdin=room.open("rb"), capture_output=True, text=True)
    else:
        proc = run("fit", room, "-o", out)
    lines = (proc.stderr if isinstance(proc.stderr, str) else proc.stderr.decode()).splitlines()
    assert proc.returncode == 1 and len(lines) == 1 and not out.exists()
    name = "<stdin>" if stdin else str(room)
    assert lines[0].startswith(f"c1mesh: error: {name}: ") and "not a height field" in lines[0]


def test_a_cloud_whose_fit_needs_more_than_memory_is_refused_before_the_fit(tmp_path):
    """hill.ply's 3,000 points need about 5.4 MB in memory (1.8 kB each); a PLY is not fitted
    in tiles, so --memory 4M refuses it in one line, and 8M fits it."""
    out = tmp_path / "hill.ply"
    proc = run("fit", SAMPLES / "hill.ply", "-o", out, "--memory", "4M")
    assert proc.returncode == 1 and not out.exists()
    assert_one_line_error(proc.stderr)
    assert "3000 points need about 5 MB" in proc.stderr.decode() and "hill.ply" in proc.stderr.decode()
    assert run("fit", SAMPLES / "hill.ply", "-o", out, "--memory", "8M", "--level", "1").returncode == 0


# ------------------------------------------ --max-slope of a header height column (issue 21)
def _paraboloid_csv(path, n=500, seed=5):
    """x,y in km on [0, 3]², z = 500 m/km² · x² in metres (header x,y,z: a height column).
    With 0.001 km per m the true slope is atan(x) (∇z = (1000 x, 0) m/km, exactly what the
    height fit returns for a quadratic); points within 0.02 km of x = 1 are left out, so
    that --max-slope 45 drops exactly those with x > 1."""
    xy = np.random.default_rng(seed).random((n, 2)) * 3.0
    xy = xy[np.abs(xy[:, 0] - 1.0) > 0.02]
    path.write_text("x,y,z\n" + "".join(f"{x:.17g},{y:.17g},{500 * x * x:.17g}\n" for x, y in xy))
    return path, xy


def test_max_slope_of_a_height_column_applies_with_the_z_factor(tmp_path):
    """Issue 21 leftover: with a header height column --max-slope was silently not applied.
    With --z-factor the slope is an angle, and the points steeper than 45° (x > 1) are the
    ones dropped, counted as too_steep."""
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    src, xy = _paraboloid_csv(tmp_path / "bowl.csv")
    report = fit(src, None, FitOptions(level=1, max_slope=45.0, z_factor=0.001)).report
    assert report["points"]["dropped"]["too_steep"] == int((xy[:, 0] > 1).sum()) > 100
    assert "max_slope_not_applied" not in report
    everything = fit(src, None, FitOptions(level=1, max_slope=89.9, z_factor=0.001)).report
    assert everything["points"]["dropped"]["too_steep"] == 0


def test_max_slope_given_without_z_factor_is_a_note(tmp_path):
    """Without --z-factor slopes of metres over km are no angles: --max-slope given drops
    nothing and says so in one note line (the output is written, exit 0); left at its
    default it says nothing."""
    src, _ = _paraboloid_csv(tmp_path / "bowl.csv")
    given = run("fit", src, "-o", tmp_path / "a.ply", "--level", "1", "--max-slope", "45")
    assert given.returncode == 0, given.stderr
    notes = [line for line in given.stderr.decode().splitlines() if line.startswith("c1mesh: note:")]
    assert len(notes) == 1 and "--max-slope was not applied" in notes[0] and "--z-factor" in notes[0]
    assert read_cloud(tmp_path / "a.ply").points.shape[0] > 0
    default = run("fit", src, "-o", tmp_path / "b.ply", "--level", "1")
    assert default.returncode == 0 and "--max-slope" not in default.stderr.decode()


def test_a_ctrl_c_during_the_commands_imports_is_one_line_and_exit_130(tmp_path):
    """c1mesh.command (the console script's entry) answers SIGINT before the command has
    imported click and installed its own handler: one line, exit 130, no traceback (it
    was Python's KeyboardInterrupt traceback). The signal arrives while the command's
    modules are being imported (a sleep stands in for the 0.2 s of imports)."""
    code = ("import os, signal, sys, time; import c1mesh.command as c; c.install_early_handler(); "
            "os.kill(os.getpid(), signal.SIGINT); time.sleep(5); print('not interrupted')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130
    assert proc.stderr.splitlines() == ["c1mesh: error: interrupted (SIGINT)"]
    assert proc.stdout == ""


def test_the_installed_console_script_runs_the_command_through_its_early_handler():
    """The installed c1mesh-python entry point (what bin/c1mesh runs) is c1mesh.command:run,
    so the early handler is in place before click is imported."""
    from importlib.metadata import entry_points
    (script,) = entry_points(group="console_scripts", name="c1mesh-python")
    assert script.value == "c1mesh.command:run"
