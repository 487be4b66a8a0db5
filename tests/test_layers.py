"""The package's layers (README, Layout): each subpackage imports only from those below it.

import-linter's layers contract in `.importlinter` checks every import of the package, also
those inside functions. The second test turns the stack upside down, so the same check on
the same code has to fail: a wrong-direction import cannot pass unseen.

Both tools walk the package's folders. meson-python's editable install gives the imported
package a virtual path (its finder serves the modules), where grimp finds no module at all, so
they run in a child Python without the site hook that installs that finder (`-S`), with
src/ and site-packages on PYTHONPATH (a folder there is searched, its .pth files are not run).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _source_python(code: str, *args: str) -> subprocess.CompletedProcess:
    """Run `code` in a child Python that imports c1mesh from src/ as plain folders."""
    path = os.pathsep.join([str(ROOT / "src"), sysconfig.get_paths()["purelib"]])
    env = {**os.environ, "PYTHONPATH": path}
    return subprocess.run([sys.executable, "-S", "-c", code, *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)


def _lint(config: Path) -> subprocess.CompletedProcess:
    return _source_python("import sys; from importlinter.cli import lint_imports_command; "
                          "sys.exit(lint_imports_command())", "--no-cache", str(config))


def package_graph():
    """grimp's import graph of c1mesh (imports inside functions included), built from src/."""
    import grimp

    done = _source_python("import grimp, json; g = grimp.build_graph('c1mesh', cache_dir=None); "
                          "print(json.dumps({m: sorted(g.find_modules_directly_imported_by(m)) "
                          "for m in g.modules}))")
    assert done.returncode == 0, done.stderr
    graph = grimp.ImportGraph()
    for module, imported in json.loads(done.stdout).items():
        graph.add_module(module)
        for other in imported:
            graph.add_import(importer=module, imported=other)
    return graph


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


def import_cycles(graph=None) -> list[set[str]]:
    """The groups of modules that import each other in a circle: the strongly connected
    components of grimp's import graph (default: c1mesh's, imports inside functions included)."""
    graph = graph or package_graph()
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


def test_no_module_imports_itself_through_others():
    """No import cycle, counting imports inside functions (issue 22's done-when)."""
    graph = package_graph()
    modules = {".".join(p.relative_to(ROOT / "src").with_suffix("").parts).removesuffix(".__init__")
               for p in (ROOT / "src" / "c1mesh").rglob("*.py")}
    assert modules <= graph.modules                  # the graph holds the whole package
    assert import_cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    """import_cycles on a throwaway package whose two modules import each other."""
    import grimp

    graph = grimp.ImportGraph()
    for module in ("pkg", "pkg.a", "pkg.b", "pkg.c"):
        graph.add_module(module)
    graph.add_import(importer="pkg.a", imported="pkg.b")
    graph.add_import(importer="pkg.b", imported="pkg.a")
    graph.add_import(importer="pkg.c", imported="pkg.a")
    assert import_cycles(graph) == [{"pkg.a", "pkg.b"}]
