"""One capacity protocol: capacities functions that fit, distinct named overflow bits, and
``checked=True`` raising inside jit."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

import jaxvox as jv
from jaxvox.overflow import check_overflow, describe

V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32) * 0.8 + 0.1
F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
GRID = jv.Grid(np.zeros(3), 1.0 / 32, 32)


@functools.partial(jax.jit, static_argnames=("caps", "checked"))
def fixed_voxels(mesh, caps, checked=False):
    """`voxelize_fixed` on GRID inside jit: one compiled program per capacities, shared by the tests."""
    return jv.voxelize_fixed(mesh, GRID, caps, checked=checked)


def test_bits_are_distinct_and_named():
    bits = [int(b) for b in jv.Overflow]
    assert len(set(bits)) == len(bits) and all(b & (b - 1) == 0 for b in bits)
    assert (jv.OVERFLOW_COLUMNS, jv.OVERFLOW_ROWS, jv.OVERFLOW_CANDIDATES, jv.OVERFLOW_VOXELS, jv.OVERFLOW_NODES) == (
        jv.Overflow.COLUMNS,
        jv.Overflow.ROWS,
        jv.Overflow.CANDIDATES,
        jv.Overflow.VOXELS,
        jv.Overflow.NODES,
    )
    assert describe(jv.Overflow.COLUMNS | jv.Overflow.NODES) == "COLUMNS|NODES" and describe(0) == "none"
    with pytest.raises(jv.JaxvoxError, match=r"result: overflowed \(VOXELS\|EXPANDED;"):
        check_overflow("result", np.array([8, 0, 32]), "do better")
    check_overflow("result", np.zeros(3, np.int32), "never raised")


def test_capacities_functions_fit_the_fixed_functions():
    mesh = jv.Mesh(V, F)
    caps = jv.voxel_capacities(mesh, GRID)
    vox = fixed_voxels(mesh, caps)
    np.testing.assert_array_equal(vox.to_numpy(), jv.voxelize(mesh, GRID).to_numpy())
    levels = jv.octree_capacities(vox)
    assert len(levels) == 5 and levels[0] == 1
    for build in (jv.build_octree, jv.build_dag):
        fixed = jax.jit(lambda v: build(v, capacities=levels))(vox)
        assert int(fixed.overflow) == 0
        np.testing.assert_array_equal(jv.expand(fixed).to_numpy(), vox.to_numpy())
        # Results carry the capacities they were built with.
        assert fixed.level_capacities == levels


def test_checked_raises_inside_jit():
    mesh = jv.Mesh(V, F)
    caps = jv.voxel_capacities(mesh, GRID)
    tiny = caps._replace(voxels=8)
    flagged = fixed_voxels(mesh, tiny)
    assert int(flagged.overflow) == jv.Overflow.VOXELS
    with pytest.raises(Exception, match=r"voxelize_fixed result: overflowed \(VOXELS;"):
        jax.block_until_ready(fixed_voxels(mesh, tiny, checked=True))
    # Checked and fitting: no error, the same voxels.
    fine = fixed_voxels(mesh, caps, checked=True)
    assert int(fine.overflow) == 0

    vox = jv.voxelize(mesh, GRID)
    small = tuple(max(1, c // 4) if level > 1 else c for level, c in enumerate(jv.octree_capacities(vox)))
    with pytest.raises(Exception, match=r"build_dag result: overflowed \(NODES;"):
        jax.block_until_ready(jax.jit(lambda v: jv.build_dag(v, capacities=small, checked=True))(vox).mask)
    tree = jv.build_dag(vox)
    with pytest.raises(Exception, match=r"expand result: overflowed \(EXPANDED;"):
        jax.block_until_ready(jax.jit(lambda t: jv.expand(t, capacity=4, checked=True))(tree).coords)


def test_host_side_messages_name_the_bits(tmp_path):
    mesh = jv.Mesh(V, F)
    tiny = jv.voxel_capacities(mesh, GRID)._replace(voxels=8)
    flagged = fixed_voxels(mesh, tiny)  # the program test_checked_raises_inside_jit compiles (eager: tests/test_api.py)
    for call in (flagged.to_numpy, lambda: jv.build_octree(flagged)):
        with pytest.raises(jv.JaxvoxError, match=r"overflowed \(VOXELS; the result is truncated\)"):
            call()
    truncated = jv.build_octree(jv.voxelize(mesh, GRID), capacities=(1, 1, 1, 1, 1))
    with pytest.raises(jv.JaxvoxError, match=r"save tree: overflowed \(NODES"):
        jv.save(tmp_path / "t.jvx", truncated)
