"""Every notebook in notebooks/ runs top to bottom at a small size (SMOKE=1).

They run in the test process (as `python notebooks/NN.py` would run them, from the
notebooks folder): a subprocess per notebook paid a fresh interpreter, JAX and
matplotlib import and recompiled programs the tests beside it had already compiled.
"""

from __future__ import annotations

import ast
import pathlib
import runpy

import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("*.py"))


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(notebook, meshes_dir, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    monkeypatch.setenv("SMOKE", "1")
    monkeypatch.setenv("JAXVOX_MESHES", str(meshes_dir))
    monkeypatch.chdir(notebook.parent)
    monkeypatch.syspath_prepend(str(notebook.parent))
    try:
        namespace = runpy.run_path(str(notebook), run_name="__main__")
    finally:
        plt.close("all")
    # It ran to the end: every name the notebook binds at top level is bound.
    tree = ast.parse(notebook.read_text())
    bound = {
        target.id
        for node in tree.body
        if isinstance(node, ast.Assign)
        for target in node.targets
        if isinstance(target, ast.Name)
    }
    assert bound and bound <= set(namespace), sorted(bound - set(namespace))
