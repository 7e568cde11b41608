"""MkDocs hooks for the jaxvox site (listed under `hooks:` in mkdocs.yml).

* The charts in `experiments/results/*.png` and the jupytext notebooks in `notebooks/*.py`
  live outside `docs/`. They are added to the site here, so that nothing is copied or
  symlinked into `docs/`: a chart becomes `results/NAME.png`, a notebook the page
  `notebooks/NAME/` (rendered by mkdocs-jupyter, not executed).
* Pages link charts and notebooks as `../experiments/results/NAME.png` and
  `../notebooks/NAME.py`, which GitHub resolves from `docs/`; the links are rewritten to
  `results/NAME.png` and `notebooks/NAME.py` for the site.
* API pages name every object by its top-level name, `::: jaxvox.NAME`. Where `NAME` is
  also a submodule (`voxelize`, `trace`, `render`), griffe resolves the name to the module
  (mkdocstrings/griffe#124), so the directive is rewritten to the target of the
  `from ... import NAME` line in `jaxvox/__init__.py`, read statically with griffe; the
  heading still says `jaxvox.NAME`.
* Every name in `jaxvox.__all__` must appear as `jaxvox.NAME` on some API page; a missing
  one is a warning, which fails `mkdocs build --strict`.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import mkdocs.plugins
from mkdocs.structure.files import File, Files

log = logging.getLogger("mkdocs.hooks.jaxvox")

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "experiments" / "results"
NOTEBOOKS = ROOT / "notebooks"
OUTSIDE_LINK = re.compile(r"\]\((?:\.\./)+(experiments/results|notebooks)/")
SITE_FOLDER = {"experiments/results": "results", "notebooks": "notebooks"}
DIRECTIVE = re.compile(r"^::: jaxvox\.(\w+)[ \t]*$", re.MULTILINE)
MENTION = re.compile(r"\bjaxvox\.(\w+)\b")

_package = None  # the griffe model of jaxvox, loaded once per build


def _jaxvox():
    global _package
    if _package is None:
        import griffe

        _package = griffe.load("jaxvox", search_paths=[str(ROOT)], resolve_aliases=False, docstring_parser="google")
    return _package


def on_pre_build(config, **kwargs):
    global _package
    _package = None  # `mkdocs serve` rebuilds: read the package again


@mkdocs.plugins.event_priority(100)  # before mkdocs-jupyter turns notebooks into pages
def on_files(files: Files, config, **kwargs) -> Files:
    extra = [(RESULTS.parent, f"results/{p.name}") for p in sorted(RESULTS.glob("*.png"))]
    extra += [(ROOT, f"notebooks/{p.name}") for p in sorted(NOTEBOOKS.glob("*.py"))]
    for src_dir, uri in extra:
        files.append(File(uri, str(src_dir), config["site_dir"], config["use_directory_urls"]))
    return files


def on_page_markdown(markdown: str, page, config, files, **kwargs) -> str:
    up = "../" * page.file.src_uri.count("/")
    markdown = OUTSIDE_LINK.sub(lambda m: f"]({up}{SITE_FOLDER[m.group(1)]}/", markdown)
    if page.file.src_uri.startswith("api/"):
        markdown = DIRECTIVE.sub(_directive, markdown)
    return markdown


def _directive(match: re.Match) -> str:
    name = match.group(1)
    member = _jaxvox().members.get(name)
    target = _jaxvox().imports.get(name)
    if member is None or member.is_alias or not member.is_module or target in (None, f"jaxvox.{name}"):
        return match.group(0)
    return f'::: {target}\n    options:\n      heading: "jaxvox.{name}"\n      toc_label: "{name}"'


def on_post_build(config, **kwargs):
    api = Path(config["docs_dir"]) / "api"
    mentioned = set()
    for page in api.glob("*.md"):
        mentioned |= set(MENTION.findall(page.read_text()))
    missing = [name for name in _jaxvox().exports if name not in mentioned]
    if missing:
        log.warning("names in jaxvox.__all__ on no API page (docs/api/*.md): %s", ", ".join(missing))
