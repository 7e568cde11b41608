"""Queries on an `Octree`: `voxel_index` (root-to-leaf walk adding prefix sums) and `expand`
(top-down expansion to Morton-ordered voxels)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Int32, Integer

from jaxvox._core.checks import check_int, check_type, is_concrete, refuse
from jaxvox._core.shapes import expand_counts, voxel_bucket
from jaxvox.octree.compact_dag import CompactDag, compact_voxel_index
from jaxvox.octree.layout import padded
from jaxvox.octree.tree import EMPTY, MAX_INDEXED, MISSING, SLOTS, Octree, child_slot, popcount8
from jaxvox.overflow import Overflow, check_overflow, raise_if_overflow
from jaxvox.voxelize import UNUSED, Voxels

# _SELECT[m, k]: slot of the k-th set bit of mask m (0 past popcount(m)).
_SELECT = np.zeros((256, 8), np.uint8)
for _m in range(256):
    _bits = SLOTS[(_m >> SLOTS) & 1 == 1]
    _SELECT[_m, : len(_bits)] = _bits


def voxel_index(tree: Octree | CompactDag, ijk: Integer[ArrayLike, "*batch 3"]) -> Int32[Array, " *batch"]:
    """Morton-order index of each voxel in the tree, `MISSING` (-1) where empty.

    A root-to-leaf walk adding the stored prefix sums; the index addresses attribute
    arrays in the order of ``expand(tree)`` (and of the source `Voxels`). Pure and
    jittable; indices outside the grid give -1.

    Args:
      tree: an `Octree` (SVO or DAG), or a `CompactDag` with prefix sums.
      ijk: [..., 3] integer voxel indices. JAX holds them as int32 (without 64-bit
        mode it converts wider integers on entry, wrapping values beyond 2^31).

    Returns:
      [...] int32.

    Raises:
      JaxvoxError: not an `Octree` or `CompactDag`, a `CompactDag` without prefix sums,
        a tree of more than `MAX_INDEXED` (2^31 - 1) voxels, whose indices do not fit
        int32 (checked when the tree is concrete), or `ijk` is not an integer array with
        a last axis of 3.
    """
    check_type("voxel_index tree", tree, (Octree, CompactDag))
    if isinstance(tree, CompactDag) and not tree.prefix:
        raise refuse("voxel_index tree", "needs prefix sums: use compact_dag(tree, prefix=True)", "prefix=False")
    check_indexed("voxel_index tree", tree)
    dtype = ijk.dtype if hasattr(ijk, "dtype") else np.asarray(ijk).dtype
    if not jnp.issubdtype(dtype, jnp.integer) or np.shape(ijk)[-1:] != (3,):
        raise refuse(
            "voxel_index ijk",
            "must be integer indices [..., 3]",
            ijk if jnp.issubdtype(dtype, jnp.integer) else f"{dtype} indices of shape {np.shape(ijk)}",
        )
    return _voxel_index(tree, ijk)


def check_indexed(what: str, tree) -> None:
    """Refuses a concrete tree of more than `MAX_INDEXED` voxels, whose Morton indices do
    not fit int32 (a traced tree is not checked)."""
    if is_concrete(tree.voxel_count) and int(tree.voxel_count) > MAX_INDEXED:
        raise refuse(
            what,
            f"holds more than {MAX_INDEXED:,} voxels, beyond int32 Morton indices; trace it as "
            "compact_dag(tree, prefix=False)",
            int(tree.voxel_count),
        )


@jax.jit
def _voxel_index(tree: Octree | CompactDag, ijk: jax.Array) -> jax.Array:
    ijk = jnp.asarray(ijk).astype(jnp.int32)
    if isinstance(tree, CompactDag):
        index, alive = compact_voxel_index(tree, ijk)
        return jnp.where(alive, index, MISSING)
    depth = tree.depth
    alive = jnp.all((ijk >= 0) & (ijk < tree.grid.resolution), axis=-1) & (tree.voxel_count > 0)
    node = jnp.zeros(ijk.shape[:-1], jnp.int32)
    index = jnp.zeros(ijk.shape[:-1], jnp.int32)

    def step(level, state):
        node, index, alive = state
        slot = child_slot(ijk, depth - 1 - level).astype(jnp.int32)
        index += jnp.where(alive, tree.prefix[node, slot].astype(jnp.int32), 0)
        nxt = tree.child[node, slot]
        alive &= nxt != EMPTY
        return jnp.where(alive, nxt, 0).astype(jnp.int32), index, alive

    if depth > 1:
        node, index, alive = jax.lax.fori_loop(0, depth - 1, step, (node, index, alive))
    slot = child_slot(ijk, 0)
    mask = tree.mask[node].astype(jnp.uint32)
    alive &= ((mask >> slot) & 1) == 1
    index += popcount8(mask & ((jnp.uint32(1) << slot) - 1))
    return jnp.where(alive, index, MISSING)


@functools.partial(jax.jit, static_argnames=("depth", "capacity"))
def _expand_nodes(mask, child, voxel_count, *, depth: int, capacity: int):
    """Top-down expansion of node tables; returns (coords [capacity, 3] int32, count).

    Takes the tables rather than the `Octree`, so trees of equal (padded) table sizes
    share one compiled program whatever their level sizes.
    """
    node = jnp.zeros(1, jnp.int32)  # absolute row of each node instance
    ijk = jnp.zeros((1, 3), jnp.int32)
    n = (voxel_count > 0).astype(jnp.int32)
    select = jnp.asarray(_SELECT)
    for level in range(depth):
        cap = min(capacity, 8 ** (level + 1))
        m = mask[node]
        live = jnp.arange(node.shape[0]) < n
        owner, rank, valid, n = expand_counts(jnp.where(live, popcount8(m), 0), cap)
        slot = select[m[owner].astype(jnp.int32), jnp.minimum(rank, 7)].astype(jnp.int32)
        ijk = 2 * ijk[owner] + ((slot[:, None] >> jnp.arange(3)) & 1)
        if level < depth - 1:
            node = jnp.where(valid, child[node[owner], slot].astype(jnp.int32), 0)
    n = jnp.minimum(n, capacity)
    return jnp.where((jnp.arange(ijk.shape[0]) < n)[:, None], ijk, UNUSED), n


@jax.jit
def occupied(tree: Octree | CompactDag, ijk: jax.Array) -> jax.Array:
    """Whether each voxel [..., 3] (int32) is in the tree: [...] bool (jittable). Unlike
    `voxel_index` it also reads a `CompactDag` without prefix sums."""
    if isinstance(tree, CompactDag):
        return compact_voxel_index(tree, ijk)[1]
    return _voxel_index(tree, ijk) != MISSING


def expand(tree: Octree, *, capacity: int | None = None, checked: bool = False) -> Voxels:
    """The voxels of a tree, in Morton order (the inverse of the builds).

    A top-down pass per level: every node instance emits its children in slot order,
    so the output is Morton-sorted without a sort. Without `capacity` (host-side) the
    buffer is sized by ``tree.voxel_count`` (and a tree not yet on the shape ladder is
    laid out on it, `padded`, so that similar trees share a compiled program); with a static `capacity` it is
    jittable, and a tree with more voxels sets `Overflow.EXPANDED` in the result's
    ``overflow`` (or, with ``checked=True``, fails the computation).

    Returns:
      `Voxels` (``triangle`` is None; attributes stay in their own arrays).

    Raises:
      JaxvoxError: not an `Octree`, a `capacity` that is not an integer >= 1, or (host
        side) a truncated tree.
    """
    check_type("expand tree", tree, Octree)
    if capacity is not None:
        capacity = check_int("expand capacity", capacity, minimum=1)
    if capacity is None:
        check_overflow("expand tree", tree.overflow, "it is truncated; build it with the host-side build")
        capacity = voxel_bucket(int(tree.voxel_count), tree.grid.resolution)
        tree = padded(tree)
    coords, n = _expand_nodes(tree.mask, tree.child, tree.voxel_count, depth=tree.depth, capacity=int(capacity))
    overflow = tree.overflow | jnp.where(tree.voxel_count > capacity, int(Overflow.EXPANDED), 0)
    if checked:
        raise_if_overflow("expand result", overflow)
    return Voxels(coords, n, overflow.astype(jnp.int32), None, tree.grid, tree.mode)
