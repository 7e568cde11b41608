"""docs/layout.md is drawn from the tree: every module and package under `jaxvox/` appears
in it, and every module it names exists.

A module is covered when the page names its full path (`jaxvox/plot.py`), or when the
table row of its package (the row whose first cell is `jaxvox/PACKAGE/`) names its file
(`tree.py`), or when that row names no ``.py`` file at all: a row that describes a
package as a whole covers all its files. A package's ``__init__.py`` is covered by its
row.
"""

from __future__ import annotations

import pathlib
import re

import jaxvox

PACKAGE = pathlib.Path(jaxvox.__file__).parent
ROOT = PACKAGE.parent
LAYOUT = ROOT / "docs" / "layout.md"
ROW = re.compile(r"^\| `(jaxvox/[\w/]+/)` \|(.*)\|\s*$", re.MULTILINE)
FILE = re.compile(r"`(\w+\.py)`")
PATH = re.compile(r"`(jaxvox/[\w/]+(?:\.py|/))`")


def _rows(text: str) -> dict[str, set[str]]:
    """Package rows: `jaxvox/PACKAGE/` -> the file names the row names."""
    return {m.group(1): set(FILE.findall(m.group(2))) for m in ROW.finditer(text)}


def _uncovered(text: str, files: list[str]) -> list[str]:
    rows, paths = _rows(text), set(PATH.findall(text))
    missing = []
    for path in files:
        folder, _, name = path.rpartition("/")
        row = rows.get(folder + "/")
        if path in paths:
            continue
        if row is not None and (name == "__init__.py" or not row or name in row):
            continue
        missing.append(path)
    return missing


def _tree() -> list[str]:
    return sorted(str(p.relative_to(ROOT)) for p in PACKAGE.rglob("*.py"))


def test_every_module_is_on_the_layout_page():
    missing = _uncovered(LAYOUT.read_text(), _tree())
    assert not missing, f"add these to docs/layout.md: {missing}"


def test_every_package_has_a_row():
    rows = _rows(LAYOUT.read_text())
    packages = sorted(f"{p.parent.relative_to(ROOT)}/" for p in PACKAGE.rglob("__init__.py") if p.parent != PACKAGE)
    assert not [p for p in packages if p not in rows], rows.keys()


def test_the_layout_page_names_no_missing_module():
    text = LAYOUT.read_text()
    stale = [p for p in PATH.findall(text) if not (ROOT / p).exists()]
    for folder, names in _rows(text).items():
        stale += [folder + n for n in names if not (ROOT / folder / n).exists()]
    assert not stale, stale


def test_the_rules():
    text = "| `jaxvox/a/` | `x.py` (X) |\n| `jaxvox/b/` | the b things |\n`jaxvox/c.py`\n"
    files = ["jaxvox/a/x.py", "jaxvox/a/y.py", "jaxvox/a/__init__.py", "jaxvox/b/z.py", "jaxvox/c.py", "jaxvox/d.py"]
    assert _uncovered(text, files) == ["jaxvox/a/y.py", "jaxvox/d.py"]
