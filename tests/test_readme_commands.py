"""Every shell command README.md shows runs as written on the bundled samples: exit 0 and
no warning, error or note on stderr (issue 21: "the README's commands run as written with no
warning on its own samples"). (The advice to fit noisy heights with --smooth auto is a
note on a terminal only: these pipes see none.)

The commands are read from README.md's indented code blocks, so a new one is tested as
soon as it is written. They run one after another in a temporary copy of `data_samples/`
(outputs land there, never in the checkout), with the installed `c1mesh` (the venv of
`./setup.sh`) first on PATH and this checkout's `src/` on PYTHONPATH. Every file a command
writes there must be one .gitignore ignores in the checkout (issue 35: `git status` stays
clean after the README). Commands that need the user's own data or cluster are listed in
EXEMPT, each with the reason.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import c1mesh

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
SETUP = "./setup.sh && . .venv/bin/activate && "
"""The start of the README's first command: installing and activating, done before the tests."""

EXEMPT = {
    ".venv/bin/python -m pytest -q -n 2": "the test suite itself",
    "c1mesh fit TILES/*.laz --classes 2 --seamless -o all.ply": "TILES/: the user's survey",
    "c1mesh fit TILES/*.laz --classes 2 --seamless -o dem.tif --resolution 1": "TILES/: the user's survey",
    "c1mesh fit TILES/*.laz --classes 2 --seamless -o all.ply --memory 2G": "TILES/: the user's survey",
    "c1mesh fit BIG.laz --classes 2 -o big.ply --memory 2G": "BIG.laz: the user's file",
    "c1mesh fit BIG.laz --classes 2 -o /shared/big.ply --memory 2G --scheduler tcp://HOST:8786":
        "BIG.laz, HOST: the user's file and cluster",
    "c1mesh fit TILES/*.laz --classes 2 --seamless -O out/ -j 2": "TILES/: the user's survey",
    "c1mesh fit TILES/*.laz --classes 2 --seamless -O out/ --memory 2G": "TILES/: the user's survey",
    "c1mesh fit TILES/*.laz --classes 2 --seamless -O out/ --scheduler tcp://HOST:8786 --report -":
        "TILES/, HOST: the user's survey and cluster",
    "c1mesh fit DEPTH.png --intrinsics 525,525,319.5,239.5 --color RGB.png -o frame.ply":
        "DEPTH.png, RGB.png: the user's depth image",
}
"""README commands not run here (exactly as README.md writes them, comments dropped)."""

AFTER = {"c1mesh fit data_samples/autzen_trim.laz --classes 2 -o dem.tif --resolution 3 "
         "--slope slope.tif --hillshade hillshade.tif --support support.tif --preview preview.png":
         ["c1mesh preview dem.tif -o dem.png"]}
"""Commands the README's prose shows inline, run right after the block command that makes their input."""


def readme_commands(text: str) -> list[str]:
    """The shell commands of README.md's indented code blocks (fenced blocks, such as the
    Python example, skipped), a trailing-backslash continuation joined, `# comments` kept
    (the shell drops them)."""
    commands, fenced, pending = [], False, ""
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced or not line.startswith("    ") or not line.strip():
            continue
        pending += line.strip()
        if pending.endswith("\\"):
            pending = pending[:-1]
            continue
        commands.append(pending)
        pending = ""
    return commands


def _without_comment(command: str) -> str:
    return re.sub(r"\s+#.*$", "", command).strip()


COMMANDS = readme_commands(README.read_text())
RUN = [c for c in COMMANDS if _without_comment(c.removeprefix(SETUP)) not in EXEMPT]


def test_the_exemptions_are_commands_of_the_readme():
    """EXEMPT names only commands README.md shows (a stale entry would hide a new command),
    and the inline commands run here are in README.md too."""
    shown = {_without_comment(c) for c in COMMANDS}
    assert set(EXEMPT) <= shown, set(EXEMPT) - shown
    assert COMMANDS[0].startswith(SETUP) and len(RUN) >= 8
    for block, inline in AFTER.items():
        assert block in {_without_comment(c) for c in RUN}
        assert all(f"`{c}`" in README.read_text() for c in inline)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """A temporary folder with a copy of data_samples/, where the README's commands run."""
    folder = tmp_path_factory.mktemp("readme")
    shutil.copytree(ROOT / "data_samples", folder / "data_samples")
    return folder


def _environment() -> dict:
    """The installed c1mesh first on PATH, importing this checkout's c1mesh."""
    bin_dir = Path(sys.executable).parent
    if not (bin_dir / "c1mesh").exists():
        pytest.fail(f"console script {bin_dir / 'c1mesh'} is not installed; run ./setup.sh")
    source = str(Path(c1mesh.__file__).resolve().parent.parent)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '/usr/bin:/bin')}",
            "PYTHONPATH": os.pathsep.join([source, *filter(None, [os.environ.get("PYTHONPATH")])])}


def _complaints(command: str, stderr: str) -> list[str]:
    """What on stderr is a warning, an error or a note: c1mesh's own lines, Python warnings,
    and the warnings of a JSON report sent to stderr by `--report -`."""
    found = [line for line in stderr.splitlines()
             if line.startswith("c1mesh:") or re.search(r"\b\w*Warning\b", line)]
    if "--report -" in command and stderr.strip().startswith("{"):
        report = json.loads(stderr[stderr.index("{"):stderr.rindex("}") + 1])
        found += [f"report warning: {w}" for w in report.get("warnings", [])]
    return found


def _files(folder: Path) -> set[str]:
    """The files under `folder`, as paths relative to it."""
    return {str(path.relative_to(folder)) for path in folder.rglob("*") if path.is_file()}


def _not_ignored(paths: set[str]) -> list[str]:
    """Those of `paths` (relative to the repository's root) that `git status` would show:
    not ignored by .gitignore, whether or not such a file exists there now."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.fail("the test needs the git checkout")
    done = subprocess.run(["git", "check-ignore", "--no-index", "--stdin"], cwd=ROOT, input="\n".join(sorted(paths)),
                          capture_output=True, text=True)
    assert done.returncode in (0, 1), done.stderr             # 1: none of them is ignored
    return sorted(paths - set(done.stdout.splitlines()))


def _run_as_written(command: str, folder: Path) -> None:
    """Run `command` in `folder`: exit 0, no complaint on stderr, and every file it writes
    ignored by git, so `git status` stays clean after the README is followed in a checkout."""
    before = _files(folder)
    proc = subprocess.run(["bash", "-o", "pipefail", "-c", command], cwd=folder, env=_environment(),
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"{command}\n{proc.stderr}"
    assert _complaints(command, proc.stderr) == [], f"{command}\n{proc.stderr}"
    written = _files(folder) - before
    assert _not_ignored(written) == [], f"{command}\nwrites files .gitignore does not list"


@pytest.mark.slow
@pytest.mark.parametrize("command", RUN, ids=[_without_comment(c.removeprefix(SETUP))[:70] for c in RUN])
def test_readme_command_runs_as_written(command, workdir):
    _run_as_written(command.removeprefix(SETUP), workdir)
    for inline in AFTER.get(_without_comment(command), []):
        _run_as_written(inline, workdir)
