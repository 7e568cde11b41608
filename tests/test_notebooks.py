"""Every notebook in notebooks/ runs top to bottom at a small size (SMOKE=1)."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("*.py"))


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(notebook, meshes_dir):
    env = dict(os.environ, SMOKE="1", MPLBACKEND="Agg", JAXVOX_MESHES=str(meshes_dir))
    result = subprocess.run(
        [sys.executable, str(notebook)], cwd=notebook.parent, env=env, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-4000:]
