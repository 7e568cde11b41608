"""Library comments and docstrings say what and why; measured figures live elsewhere.

Throughput (Mrays/s), image-quality scores (PSNR, dB), timings (ms, s), dated
measurements and temporary paths go to `experiments/results/` and the design history
(`docs/design-history.md`); the guide pages describe the design and link there. The
check reads every comment (`tokenize`) and docstring (`ast`) under `jaxvox/`, and the
guide pages under `docs/` except the history, the benchmarks page and the changelog.
"""

from __future__ import annotations

import ast
import io
import pathlib
import re
import tokenize

import jaxvox

PACKAGE = pathlib.Path(jaxvox.__file__).parent
DOCS = PACKAGE.parent / "docs"
# Pages whose subject is measurement (or the record of changes).
MEASUREMENT_PAGES = {"design-history.md", "benchmarks.md", "changelog.md"}
FIGURE = re.compile(
    r"Mrays|PSNR|\b\d+(\.\d+)? ?dB\b|/tmp/|\b\d+(\.\d+)? ?(ms|s)\b|\b20\d\d-\d\d-\d\d\b",
)


def _texts(path: pathlib.Path):
    """(line, text) of every comment and docstring of a Python file."""
    source = path.read_text()
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            yield token.start[0], token.string
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                yield node.body[0].lineno, doc
        elif isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            yield node.lineno, node.value.value  # attribute docstrings


def _figures(text: str) -> list[str]:
    return [m.group(0) for m in FIGURE.finditer(text)]


def test_the_pattern_finds_figures():
    assert _figures("10.38 Mrays/s, 36.5 dB PSNR, 7.2 ms, 1.5 s, on 2026-12-04 in /tmp/x")
    assert not _figures("[N, 3] float32, O(R^3 F), 6 steps, 2 stages, 64 rays, 8 ms_per_x")


def test_library_comments_and_docstrings_hold_no_measurements():
    offenders = [
        f"{path.relative_to(PACKAGE.parent)}:{line}: {_figures(text)}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for line, text in _texts(path)
        if _figures(text)
    ]
    assert not offenders, "\n".join(offenders)


def test_guide_pages_hold_no_measurements():
    offenders = [
        f"docs/{path.relative_to(DOCS)}:{number}: {_figures(line)}"
        for path in sorted(DOCS.rglob("*.md"))
        if path.name not in MEASUREMENT_PAGES
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if _figures(line)
    ]
    assert not offenders, "\n".join(offenders)
