"""The public signatures' annotations (jaxtyping shapes and dtypes, `Literal` modes) hold
on typical use: the quick-start pipeline runs with jaxtyping's import hook and beartype
checking every annotated call in jaxvox.

It runs in a subprocess because the hook must be installed before jaxvox is imported, and
because the rest of the suite (the fuzzed API in particular) passes bad input on purpose
to reach the validation that raises `JaxvoxError`, which the type checker would stop first.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

PIPELINE = textwrap.dedent(
    """
    import jax, numpy as np
    from jaxtyping import install_import_hook
    with install_import_hook("jaxvox", "beartype.beartype"):
        import jaxvox as jv
        from jaxvox import sdf
    from jaxtyping import TypeCheckError

    jv.enable_compilation_cache()  # $JAXVOX_CACHE_DIR from the suite: programs the other tests compiled
    mesh = jv.default_scene()
    grid = jv.Grid.fit(mesh, 32)
    vox = jv.voxelize(mesh, grid, mode="conservative", triangle_ids=True)
    caps = jv.voxel_capacities(mesh, grid)
    fixed = jax.jit(lambda m: jv.voxelize_fixed(m, grid, caps))(mesh)
    dag = jv.build_dag(vox)
    levels = jv.octree_capacities(vox)
    tree = jax.jit(lambda v: jv.build_octree(v, capacities=levels))(vox)
    attributes = jv.voxel_attributes(mesh, vox)
    eye, target = jv.look_at_view(mesh)
    origins, directions = jv.pinhole_rays(eye, target, width=8, height=6)
    hit = jv.trace(dag, origins, directions)
    assert hit.status.shape == (6, 8)
    index = jv.voxel_index(dag, vox.coords[:5])
    back = jv.expand(dag)
    sphere = sdf.sphere(0.5, center=(0.0, 0.0, 0.0))
    traced = jv.sphere_trace(sphere, np.zeros((3, 3), np.float32) - 2, np.ones((3, 3), np.float32))
    albedo = jv.voxel_albedo(attributes)
    # render and the dense fields are left out: their compiles would double this test's
    # time, so their annotations are checked by mypy only. The hook does check: a ray
    # batch of the wrong width is a type error at the door.
    try:
        jv.trace(dag, np.zeros((4, 2), np.float32), np.zeros((4, 2), np.float32))
    except TypeCheckError:
        print("checked")
    """
)


def test_annotations_hold_under_the_jaxtyping_import_hook():
    result = subprocess.run([sys.executable, "-c", PIPELINE], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-4000:]
    assert result.stdout.strip().endswith("checked"), result.stdout
