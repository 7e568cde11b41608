"""The import graph of the package: no cycles, and a ground floor that stands alone.

Read statically with `ast` from every ``jaxvox/**/*.py``: an edge goes from a module to
each jaxvox module it imports (``from jaxvox.a import b`` names ``jaxvox.a.b`` when that
is a module, else ``jaxvox.a``), at any depth of the file (imports inside functions and
under ``TYPE_CHECKING`` count). A package's ``__init__`` is the module named by the
package. Importing a submodule runs its package's ``__init__`` first, which is not an
edge here: a package that re-exports its modules is not a cycle.
"""

from __future__ import annotations

import ast
import pathlib

import jaxvox

PACKAGE = pathlib.Path(jaxvox.__file__).parent
GROUND = "jaxvox._core"
MAX_LOOSE = 12  # modules directly in jaxvox/ (the rest lives in subpackages)


def _modules() -> dict[str, pathlib.Path]:
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _graph() -> dict[str, set[str]]:
    modules = _modules()

    def known(name: str) -> str:
        while name not in modules:
            name = name.rpartition(".")[0]
        return name

    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                named = [f"{base}.{alias.name}" for alias in node.names]
                targets = [t if t in modules else base for t in named]
            else:
                continue
            edges |= {known(t) for t in targets if t == "jaxvox" or t.startswith("jaxvox.")}
        edges.discard(name)
        graph[name] = edges
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of `graph` as a path [a, b, ..., a], or None (iterative depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    for root in sorted(graph):
        if state.get(root):
            continue
        path, stack = [root], [iter(sorted(graph[root]))]
        state[root] = 1
        while stack:
            child = next(stack[-1], None)
            if child is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(child) == 1:
                return path[path.index(child) :] + [child]
            elif not state.get(child):
                state[child] = 1
                path.append(child)
                stack.append(iter(sorted(graph[child])))
    return None


def test_the_graph_sees_the_imports():
    graph = _graph()
    assert "jaxvox.mesh" in graph["jaxvox.io.meshes"]
    assert "jaxvox._core.hit" in graph["jaxvox.trace.driver"]


def test_no_import_cycles():
    assert _cycle(_graph()) is None, " -> ".join(_cycle(_graph()) or [])


def test_the_cycle_finder_finds_one():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_the_ground_floor_imports_nothing_above_it():
    offenders = [
        f"{name} imports {target}"
        for name, targets in _graph().items()
        if name == GROUND or name.startswith(GROUND + ".")
        for target in targets
        if not (target == GROUND or target.startswith(GROUND + "."))
    ]
    assert not offenders, offenders


def test_few_modules_are_loose_in_the_package():
    loose = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(loose) <= MAX_LOOSE, loose
