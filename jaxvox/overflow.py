"""One capacity protocol: the overflow bits of fixed-capacity results, and how they are checked.

Every stage whose output size depends on the data comes as a host-side *capacities*
function (a counting pass on concrete data, rounded up to the shape ladder) and a
jittable *fixed* function with static capacities (jax-md's allocate/update split):

================  ==========================  ==============================================
stage             capacities (host)           fixed (jittable)
================  ==========================  ==============================================
voxelization      `voxel_capacities`          `voxelize_fixed(mesh, grid, capacities)`
octree / DAG      `octree_capacities`         `build_octree(vox, capacities=...)`, `build_dag`
expansion         ``bucket(tree.voxel_count)``  `expand(tree, capacity=...)`
whole pipeline    `batch_capacities`          `voxelize_build_trace`
================  ==========================  ==============================================

A fixed function never resizes: it writes what fits and sets a bit of `Overflow` in the
result's ``overflow`` field (bits accumulate down a pipeline: a tree built from truncated
voxels carries their bit too). The host-side functions (`voxelize`, `build_octree`
without capacities, `expand` without capacity, `run_batch`) size capacities themselves
and never return a truncated result. A caller inside `jax.jit` chooses between reading
the flag and passing ``checked=True``, which raises (through `jax.debug.callback`, as an
error of the running computation whose message names the bits) when a bit is set.
"""

from __future__ import annotations

import enum

import jax
import numpy as np

from jaxvox._core.errors import JaxvoxError


class Overflow(enum.IntFlag):
    """Bits of an ``overflow`` field: which fixed capacity was too small (0: none)."""

    COLUMNS = 1  # voxelization: triangle columns of a projection (`Capacities.columns`)
    ROWS = 2  # voxelization: rows of those columns (`Capacities.rows`)
    CANDIDATES = 4  # voxelization: candidate voxels before deduplication (`Capacities.candidates`)
    VOXELS = 8  # voxelization: unique voxels (`Capacities.voxels`)
    NODES = 16  # octree / DAG build: a level held more nodes than its capacity
    EXPANDED = 32  # `expand`: the tree holds more voxels than the output capacity


def describe(flags) -> str:
    """The names of the bits set in `flags` (an int or a scalar array), e.g. ``"COLUMNS|VOXELS"``."""
    flags = int(flags)
    names = [str(bit.name) for bit in Overflow if flags & bit]
    unknown = flags & ~sum(Overflow)
    return "|".join(names + ([hex(unknown)] if unknown else [])) or "none"


def check_overflow(what: str, flags, remedy: str) -> None:
    """Raises `JaxvoxError` naming the set bits when `flags` (host value, any shape) is nonzero.

    Args:
      what: the result, e.g. ``"voxelize_fixed result"``.
      flags: [] or [...] int overflow bits (several items are or-ed together).
      remedy: what the caller should do instead, e.g. ``"use jaxvox.voxelize"``.
    """
    flags = int(np.bitwise_or.reduce(np.asarray(flags, np.int64).ravel(), initial=0))
    if flags:
        raise JaxvoxError(f"{what}: overflowed ({describe(flags)}; the result is truncated); {remedy}")


def raise_if_overflow(what: str, flags: jax.Array) -> None:
    """Inside a traced function: makes the computation fail with `check_overflow`'s message
    when `flags` is nonzero at run time (for ``checked=True``). The error reaches the
    caller when the result is computed (e.g. at ``block_until_ready``), wrapped by JAX's
    runtime error type, its message naming the bits."""
    jax.debug.callback(lambda f: check_overflow(what, f, "raise the capacities"), flags)
