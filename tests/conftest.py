"""Shared pytest fixtures."""

from __future__ import annotations

import gzip
import os
import pathlib
import shutil

import numpy as np
import pytest

import jaxvox

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]

# Compiled programs persist in the repository's .cache/xla (ignored by git), so a second
# run of the suite is warm; the command line and the notebooks (subprocesses) inherit
# the folder through $JAXVOX_CACHE_DIR. CI starts cold.
os.environ.setdefault("JAXVOX_CACHE_DIR", str(REPO_ROOT / ".cache" / "xla"))
# XLA flags, read when the backend starts (after this module runs):
# * The suite compiles about 2,800 programs, and compiling is most of its time. XLA's
#   loop emitters (``--xla_cpu_use_fusion_emitters=false``) compile them in about two
#   thirds of the time of its default fusion emitters, whose code runs faster (what users
#   get, and what the benchmarks time), and LLVM's level 1 optimizations
#   (``--xla_backend_optimization_level=1``) take a sixth less of the suite's time than
#   the default level 2, and LLVM told to optimize for size, without loop unrolling or the
#   SLP vectorizer (``--xla_backend_extra_options``, XLA's CPU options; none changes what
#   is computed) a further seventh (`docs/design-history.md`). The tests marked ``codegen`` also run
#   with XLA's defaults (`tests/test_codegen.py`, ``JAXVOX_TEST_EMITTERS=default``), so
#   the code users run is checked against the references too.
# * Under pytest-xdist every worker runs XLA's CPU code on one thread: the workers already
#   keep the cores busy, and a thread pool per worker on top only oversubscribes them.
DEFAULT_EMITTERS = os.environ.get("JAXVOX_TEST_EMITTERS") == "default"
SUITE_FLAGS = (  # not users' defaults
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_backend_optimization_level=1",
    "--xla_backend_extra_options=xla_cpu_optimize_for_size,xla_cpu_disable_loop_unrolling,xla_cpu_disable_slp_vectorizer",
)
_flags = [] if DEFAULT_EMITTERS else list(SUITE_FLAGS)
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    _flags.append("--xla_cpu_multi_thread_eigen=false")
os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *_flags]).strip()
jaxvox.enable_compilation_cache()
TEST_DATA = REPO_ROOT / "tests" / "data"  # the test meshes, with their sources (SOURCES.md)


# The modules whose tests take longest run first, so that with pytest-xdist no worker
# starts a long test when the others have run out of work.
LONGEST_FIRST = ("test_codegen", "test_notebooks", "test_clipmap", "test_render", "test_sparse_field", "test_distance")


CODEGEN_FILES: list[str] = []  # the test files that hold tests marked codegen (set when collected)


def pytest_collection_modifyitems(config, items):
    # When test_codegen runs the tests marked codegen with the default emitters, they do
    # not run here as well (a run of those tests alone still runs them here).
    if not DEFAULT_EMITTERS and any(item.module.__name__.endswith("test_codegen") for item in items):
        twice = [item for item in items if item.get_closest_marker("codegen")]
        CODEGEN_FILES[:] = sorted({str(item.path.relative_to(REPO_ROOT)) for item in twice})
        if twice:
            config.hook.pytest_deselected(items=twice)
            items[:] = [item for item in items if not item.get_closest_marker("codegen")]
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    key = lambda item: rank.get(item.module.__name__.rsplit(".", 1)[-1], len(rank))
    items[:] = sorted(items, key=key)  # stable: the other modules keep their order


@pytest.fixture(scope="session")
def meshes_dir(tmp_path_factory) -> pathlib.Path:
    """A folder of the test meshes (``tests/data``, see its SOURCES.md): the OBJ files as
    they are and the gzip-compressed ones unpacked, once per session (per xdist worker)."""
    folder = tmp_path_factory.mktemp("meshes")
    for path in sorted(TEST_DATA.iterdir()):
        if path.suffix == ".obj":
            shutil.copyfile(path, folder / path.name)
        elif path.name.endswith(".obj.gz"):
            with gzip.open(path, "rb") as src, open(folder / path.name[: -len(".gz")], "wb") as dst:
                shutil.copyfileobj(src, dst)
    return folder


@pytest.fixture(autouse=True, scope="module")
def _fresh_jax_caches(request):
    """Drops compiled programs after the modules that compile the most distinct programs.

    Keeping every program of the suite alive in one process crashed XLA's CPU compiler
    (a segfault while compiling, late in the run); the other modules share programs, so
    they keep theirs.
    """
    yield
    if request.module.__name__.rsplit(".", 1)[-1] in ("test_distance", "test_clipmap", "test_sdf_octree", "test_trace"):
        import jax

        jax.clear_caches()


@pytest.fixture
def textured_quad(tmp_path):
    """(path, texels): an OBJ unit quad in z = 0 whose uv is its (x, y), with a 4x4 PNG
    texture of four 2x2 quadrants (top row first: red, green / blue, yellow), texels as
    float64 [4, 4, 3] in [0, 1]."""
    import imageio.v3 as iio

    texels = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [255, 255, 0]]], np.uint8)
    (tmp_path / "quad.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd tex.png\n")
    (tmp_path / "quad.obj").write_text(
        "mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    )
    texels = texels.repeat(2, axis=0).repeat(2, axis=1)
    iio.imwrite(tmp_path / "tex.png", texels)
    return tmp_path / "quad.obj", texels / 255.0
