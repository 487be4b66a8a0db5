"""The meson build installs all of the package: meson-python installs only the files that a
meson.build names, so a module left out of one would be missing from a wheel (and from the
editable install's imports) while the tests run from src/ could not tell."""
from __future__ import annotations

import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "c1mesh"


def _named(folder: Path) -> set[str]:
    """The quoted file names in folder/meson.build."""
    return set(re.findall(r"'([^'/]+\.(?:py|pyx))'", (folder / "meson.build").read_text()))


def test_every_module_and_kernel_is_named_in_its_folders_meson_build():
    folders = [PACKAGE, *(p for p in PACKAGE.iterdir() if (p / "__init__.py").exists())]
    missing = []
    for folder in folders:
        named = _named(folder)
        missing += [str(f.relative_to(PACKAGE)) for f in sorted(folder.glob("*.py*"))
                    if f.suffix in (".py", ".pyx") and f.name not in named]
    assert missing == []


def test_every_subpackage_is_entered_by_the_package_meson_build():
    text = (PACKAGE / "meson.build").read_text()
    subpackages = sorted(p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists())
    assert [name for name in subpackages if f"'{name}'" not in text] == []
