"""The ``"stack"`` traversal (the talk in ``shared/seeds/000``): a node and child state,
save state and go down, one level per pop (see `jaxvox.trace`)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxvox.octree import Octree
from jaxvox.trace.ray import (
    Ray,
    argmin3,
    child_row,
    first_cell,
    mask_bit,
    max3,
    min3,
    pick,
    root_row,
    slot_bits,
    stack_set,
    state_after_step,
    step_status,
    times,
    vec,
)


class _Stacked(NamedTuple):
    level: jax.Array  # [] int32 level of the current node, 0..D-1
    node: jax.Array  # [] int32 row of the current node
    corner: tuple  # 3 x [] int32 mirrored corner of the current node
    child: jax.Array  # [] int32 current child (mirrored slot bits), -1 when exhausted
    stack_node: tuple  # D x [] int32 saved ancestors
    stack_child: tuple  # D x [] int32 their next child, -1 if none
    status: jax.Array  # [] int32


def stacked_init(tree: Octree, ray: Ray, status) -> _Stacked:
    res, depth = tree.grid.resolution, tree.depth
    zero = (jnp.int32(0),) * 3
    child = slot_bits(first_cell(ray, zero, res // 2, ray.t_start), depth - 1)
    zeros = (jnp.int32(0),) * depth
    return _Stacked(jnp.int32(0), root_row(tree), zero, child, zeros, zeros, status)


def stacked_step(tree: Octree, ray: Ray, s: _Stacked) -> _Stacked:
    depth = tree.depth
    shift = depth - 1 - s.level  # the children have size 2^shift
    half = jnp.left_shift(1, shift)
    popping = s.child < 0
    c = jnp.maximum(s.child, 0)
    child_corner = vec(lambda a, k: a + half * ((c >> k) & 1), s.corner, (0, 1, 2))
    t0 = times(ray, child_corner)
    t1 = times(ray, vec(lambda a: a + half, child_corner))
    t_in, t_out = max3(t0), min3(t1)
    slot = c ^ ray.flip
    live = ~popping & mask_bit(tree, s.node, slot, s.level) & (t_out > 0) & (t_in < t_out)
    descend = live & (s.level < depth - 1)
    # the moved bit: the child across the nearest exit plane, if still inside this node
    exit_bit = jnp.left_shift(1, argmin3(t1))
    next_child = jnp.where((c & exit_bit) == 0, c | exit_bit, -1)
    status = step_status((~popping & (t_in > ray.t_max)) | (popping & (s.level == 0)), live & (s.level == depth - 1))
    row = child_row(tree, s.node, slot)
    t_in, next_child, descend, status, row = jax.lax.optimization_barrier((t_in, next_child, descend, status, row))
    # save the parent with its next child, go down (to the grandchild the ray is in at
    # entry, or at t_start when it starts inside the child); or pop one level
    first = slot_bits(first_cell(ray, child_corner, half >> 1, jnp.maximum(t_in, ray.t_start)), shift - 1)
    up = jnp.maximum(s.level - 1, 0)
    pop = popping & (s.level > 0)
    up_mask = -jnp.left_shift(1, depth - up)
    stepped = _Stacked(
        level=jnp.where(descend, s.level + 1, jnp.where(pop, up, s.level)),
        node=jnp.where(descend, row, jnp.where(pop, pick(s.stack_node, up), s.node)),
        corner=vec(lambda a, b: jnp.where(descend, a, jnp.where(pop, b & up_mask, b)), child_corner, s.corner),
        child=jnp.where(descend, first, jnp.where(pop, pick(s.stack_child, up), jnp.where(live, s.child, next_child))),
        stack_node=stack_set(s.stack_node, s.level, s.node, descend),
        stack_child=stack_set(s.stack_child, s.level, next_child, descend),
        status=status,
    )
    return state_after_step(s, stepped, status, held=("corner", "child"))


def stacked_voxel(tree: Octree, s: _Stacked):
    return vec(lambda a, k: a + ((s.child >> k) & 1), s.corner, (0, 1, 2))
