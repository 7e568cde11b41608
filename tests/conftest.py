"""Shared pytest fixtures."""

from __future__ import annotations

import os
import pathlib

import pytest

# The command line keeps compiled programs in a persistent cache; calling it from a test
# would switch that cache on for the whole test process (and notebooks): keep it off.
os.environ["JAXVOX_CACHE_DIR"] = ""

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO_ROOT.parent / "shared" / "meshes"


@pytest.fixture(scope="session")
def meshes_dir() -> pathlib.Path:
    """The shared test meshes (``../shared/meshes`` next to the repository); skips if absent."""
    if not SHARED_MESHES.is_dir():
        pytest.skip(f"shared test meshes not found at {SHARED_MESHES}")
    return SHARED_MESHES


@pytest.fixture(autouse=True, scope="module")
def _fresh_jax_caches(request):
    """Drops compiled programs after the modules that compile the most distinct programs.

    Keeping every program of the suite alive in one process crashed XLA's CPU compiler
    (a segfault while compiling, late in the run); the other modules share programs, so
    they keep theirs.
    """
    yield
    if request.module.__name__.rsplit(".", 1)[-1] in ("test_distance", "test_sdf_octree", "test_trace"):
        import jax

        jax.clear_caches()
