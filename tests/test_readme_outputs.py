"""After the README's commands, `git status` stays clean: every file they write into the
repository folder is ignored by git."""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# an output option or a shell redirection, then a relative path (not -, not /abs, not a PLACEHOLDER)
OUTPUT = re.compile(r"(?:-o|-O|--slope|--aspect|--hillshade|--support|--preview|--contours|--report|>)\s+([a-z][\w./-]*)")


def readme_outputs(text: str) -> set[str]:
    """The relative output paths written by the `c1mesh` command lines of a README, with the
    .prj sidecar of every mesh output (a CRS-carrying input writes one)."""
    names = set()
    for line in text.replace("\\\n", " ").splitlines():      # shell continuation lines joined
        if "c1mesh " not in line or line.lstrip().startswith(("#", "|")):
            continue
        for name in OUTPUT.findall(line.split("  #")[0]):
            names.add(name)
            if Path(name).suffix in (".ply", ".obj", ".stl", ".off", ".glb"):
                names.add(str(Path(name).with_suffix(".prj")))
    return names


def test_readme_output_names_are_found():
    names = readme_outputs((ROOT / "README.md").read_text())
    assert {"surface.ply", "ground.glb", "piped.ply", "meshes/", "dem.tif", "preview.png", "smooth.json"} <= names
    assert {"ground.json", "tiles.json"} <= readme_outputs((ROOT / "cli" / "README.md").read_text())


@pytest.mark.parametrize("readme", ["README.md", "cli/README.md"])
def test_every_output_of_the_readme_is_ignored_by_git(readme):
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.fail("the test needs the git checkout")
    names = sorted(readme_outputs((ROOT / readme).read_text()))
    done = subprocess.run(["git", "check-ignore", "--no-index", *names], cwd=ROOT, capture_output=True, text=True)
    ignored = set(done.stdout.split())
    assert [n for n in names if n not in ignored] == []
