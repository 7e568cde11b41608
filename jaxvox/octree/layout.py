"""Table layouts of an `Octree` (host-side numpy copies, no compiles): `padded` lays a
tree out on the shape ladder, `compact` drops the padding rows."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_type
from jaxvox.octree.tree import EMPTY, Octree, padded_sizes, stored_sizes


def _relayout(tree: Octree, sizes: tuple[int, ...]) -> Octree:
    """Host copy of `tree` with `sizes` rows per level (each at least the level's stored
    rows): every level's nodes move to the new offsets, child pointers follow them and
    the new rows are padding. Host memory copies (numpy), so it compiles nothing."""
    stored = stored_sizes(tree.level_sizes)
    old, new = tree.level_offsets, np.cumsum((0,) + tuple(sizes))
    mask, child, prefix = (np.asarray(a) for a in (tree.mask, tree.child, tree.prefix))
    out_mask = np.zeros(new[-1], np.uint8)
    out_child = np.full((new[-2], 8), EMPTY, np.uint32)
    out_prefix = np.zeros((new[-2], 8), np.uint32)
    for level in range(tree.depth):
        src, dst = slice(old[level], old[level] + stored[level]), slice(new[level], new[level] + stored[level])
        out_mask[dst] = mask[src]
        if level < tree.depth - 1:
            shift = np.int64(new[level + 1]) - np.int64(old[level + 1])
            part = child[src]
            out_child[dst] = np.where(part == EMPTY, EMPTY, (part + shift).astype(np.uint32))
            out_prefix[dst] = prefix[src]
    put = functools.partial(jax.device_put, may_alias=True)
    return dataclasses.replace(
        tree,
        mask=put(out_mask),
        child=put(out_child),
        prefix=put(out_prefix),
        level_capacity=jnp.asarray(sizes, jnp.int32),
    )


def padded(tree: Octree) -> Octree:
    """`tree` laid out on the shape ladder (`padded_sizes`), host-side; a tree already
    laid out so is returned as it is."""
    sizes = padded_sizes(tree.level_sizes)
    return tree if sizes == tree.level_capacities else _relayout(tree, sizes)


def compact(tree: Octree) -> Octree:
    """Drops padding rows so that ``level_capacity == level_sizes`` (host-side).

    Child rows are absolute, so each level's pointers shift by the change of its target
    level's offset. The work is host memory copies (numpy), so it compiles nothing.

    Raises:
      JaxvoxError: not an `Octree`.
    """
    check_type("compact tree", tree, Octree)
    sizes = stored_sizes(tree.level_sizes)
    return tree if sizes == tree.level_capacities else _relayout(tree, sizes)
