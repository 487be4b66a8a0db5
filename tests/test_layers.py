"""The package's layers (README, Layout): each subpackage imports only from those below it.

import-linter's layers contract in `.importlinter` checks every import of the package, also
those inside functions. The second test turns the stack upside down, so the same check on
the same code has to fail: a wrong-direction import cannot pass unseen.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(config: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    return subprocess.run([str(LINT), "--no-cache", str(config)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)


def test_every_import_goes_down_the_layers():
    done = _lint(ROOT / ".importlinter")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "1 kept, 0 broken" in done.stdout


def test_the_contract_fails_on_imports_in_the_wrong_direction(tmp_path):
    config = (ROOT / ".importlinter").read_text()
    layers = ["c1mesh.cli", "c1mesh.pipeline", "c1mesh.geo : c1mesh.survey", "c1mesh.stages",
              "c1mesh.engine : c1mesh.formats", "c1mesh.core"]
    listed = "\n".join(f"    {layer}" for layer in layers)
    assert listed in config                          # the stack this test turns over
    upside_down = config.replace(listed, "\n".join(f"    {layer}" for layer in reversed(layers)))
    (tmp_path / "upside_down.ini").write_text(upside_down)
    done = _lint(tmp_path / "upside_down.ini")
    assert done.returncode != 0
    assert "c1mesh.cli is not allowed to import c1mesh.core" in done.stdout   # now the lowest layer


KNOWN_CYCLES = [
    # issue 22 still to break: the survey's task runner and the tiles it runs import each other
    {"c1mesh.survey.distributed", "c1mesh.survey.tiled_fit", "c1mesh.survey.tiled_limiter",
     "c1mesh.survey.tiled_outputs", "c1mesh.survey.tiles"},
]


def import_cycles() -> list[set[str]]:
    """The groups of c1mesh modules that import each other in a circle (strongly connected
    components of grimp's import graph, imports inside functions included)."""
    import grimp

    graph = grimp.build_graph("c1mesh", cache_dir=None)
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(module):
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for imported in graph.find_modules_directly_imported_by(module):
            if imported not in index:
                visit(imported)
                low[module] = min(low[module], low[imported])
            elif imported in on_stack:
                low[module] = min(low[module], index[imported])
        if low[module] == index[module]:
            group = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.add(member)
                if member == module:
                    break
            if len(group) > 1:
                cycles.append(group)

    for module in sorted(graph.modules):
        if module not in index:
            visit(module)
    return cycles


def test_no_import_cycle_beyond_the_known_ones():
    """A new cycle fails; so does breaking a known one without removing it from the list
    (the list only shrinks)."""
    found = import_cycles()
    assert sorted(map(sorted, found)) == sorted(map(sorted, KNOWN_CYCLES))
