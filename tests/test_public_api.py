"""The public API's shape (in the style of dm_pix's api_test): every public callable has a
docstring, optional arguments are keyword-only, `__all__` is sorted, no module imports
another module's private names, and ``import jaxvox`` loads none of the optional libraries."""

from __future__ import annotations

import ast
import dataclasses
import enum
import inspect
import pathlib
import subprocess
import sys

import jaxvox as jv

PACKAGE = pathlib.Path(jv.__file__).parent
# Classes whose constructors are data containers (pytrees rebuilt without __init__) or
# enums: their fields are documented on the class.
_NAMESPACES = {
    "jaxvox": jv,
    "jaxvox.distance": jv.distance,
    "jaxvox.io": jv.io,
    "jaxvox.octree": jv.octree,
    "jaxvox.sdf": jv.sdf,
    "jaxvox.sphere_tracing": jv.sphere_tracing,
}


def _public_callables():
    for prefix, namespace in _NAMESPACES.items():
        for name in namespace.__all__:
            obj = getattr(namespace, name)
            if callable(obj) and not inspect.ismodule(obj):
                yield f"{prefix}.{name}", obj


def _has_own_signature(obj) -> bool:
    """Functions and classes with a hand-written constructor; enums, named tuples and
    generated dataclass constructors list their fields, which are documented on the class."""
    if not inspect.isclass(obj):
        return True
    if issubclass(obj, (enum.Enum, tuple)):
        return False
    generated = getattr(getattr(obj.__init__, "__code__", None), "co_filename", "") == "<string>"
    return not (dataclasses.is_dataclass(obj) and generated)


def test_all_is_sorted_and_complete():
    for namespace in _NAMESPACES.values():
        assert list(namespace.__all__) == sorted(namespace.__all__)
        assert all(hasattr(namespace, name) for name in namespace.__all__)


def test_every_public_callable_has_a_docstring():
    missing = [name for name, obj in _public_callables() if not (inspect.getdoc(obj) or "").strip()]
    assert not missing, missing


def test_optional_arguments_are_keyword_only():
    offenders = []
    for name, obj in filter(lambda item: _has_own_signature(item[1]), _public_callables()):
        try:
            signature = inspect.signature(obj)
        except (TypeError, ValueError):  # builtins without a signature
            continue
        for parameter in signature.parameters.values():
            if parameter.kind == parameter.POSITIONAL_OR_KEYWORD and parameter.default is not parameter.empty:
                offenders.append(f"{name}({parameter.name}=...)")
    assert not offenders, offenders


def test_no_module_imports_another_modules_private_names():
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jaxvox"):
                private_module = any(part.startswith("_") for part in node.module.split("."))
                for alias in node.names:
                    if alias.name.startswith("_") and not private_module:
                        offenders.append(f"{path.relative_to(PACKAGE)}: from {node.module} import {alias.name}")
    assert not offenders, offenders


def test_import_jaxvox_loads_no_optional_library():
    heavy = ["trimesh", "skimage", "OpenEXR", "scipy", "embreex", "matplotlib", "tqdm", "imageio", "open3d"]
    code = f"import sys, jaxvox; print([m for m in {heavy!r} if m in sys.modules])"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "[]", loaded


def test_the_namespaces_hold_the_flat_names():
    """Every public name of a topic namespace that `jaxvox` also exports is the same object."""
    for prefix, namespace in _NAMESPACES.items():
        for name in namespace.__all__:
            if prefix != "jaxvox" and name in jv.__all__:
                assert getattr(jv, name) is getattr(namespace, name), f"{prefix}.{name}"
