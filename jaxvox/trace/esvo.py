"""The ``"esvo"`` traversal (Laine and Karras): a cell state with PUSH / ADVANCE / POP,
popping any number of levels per step (see `jaxvox.trace`)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxvox.octree import Octree
from jaxvox.trace.ray import (
    Ray,
    argmin3,
    barrier_token,
    child_row,
    first_cell,
    fusion_barrier,
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


class _Esvo(NamedTuple):
    level: jax.Array  # [] int32 level of the current cell, 1..D (its size is 2^(D - level))
    corner: tuple  # 3 x [] int32 mirrored corner of the current cell
    parent: jax.Array  # [] int32 row of the node the cell belongs to
    stack: tuple  # D x [] int32 stack[l]: row of the level-l node on the current path
    status: jax.Array  # [] int32


def esvo_init(tree: Octree, ray: Ray, status) -> _Esvo:
    res = tree.grid.resolution
    corner = first_cell(ray, (jnp.int32(0),) * 3, res // 2, ray.t_start)
    return _Esvo(jnp.int32(1), corner, root_row(tree), (root_row(tree),) * tree.depth, status)


def esvo_step(tree: Octree, ray: Ray, s: _Esvo) -> _Esvo:
    depth, res = tree.depth, tree.grid.resolution
    shift = depth - s.level
    size = jnp.left_shift(1, shift)
    t0 = times(ray, s.corner)
    t1 = times(ray, vec(lambda c: c + size, s.corner))
    t_in, t_out = max3(t0), min3(t1)
    slot = slot_bits(s.corner, shift) ^ ray.flip
    t_in, axis, t_out, slot = fusion_barrier((t_in, argmin3(t1), t_out, slot), barrier_token(tree))
    live = mask_bit(tree, s.parent, slot, s.level - 1) & (t_out > 0) & (t_in < t_out)
    push = live & (s.level < depth)
    before = pick(s.corner, axis)
    status = step_status((t_in > ray.t_max) | (~live & (before + size >= res)), live & (s.level == depth))
    row = child_row(tree, s.parent, slot)
    high = 31 - jax.lax.clz(before ^ (before + size))  # after ADVANCE the cell has size 2^high
    parent = jnp.where(push, row, pick(s.stack, depth - high - 1))  # POP: the stack's node of level depth - high - 1
    t_in, axis, push, status, row, high, parent = fusion_barrier(
        (t_in, axis, push, status, row, high, parent), barrier_token(tree)
    )
    # PUSH: the cell is an occupied node; enter its child the ray is in at entry (or at
    # t_start, when the ray starts inside the cell).
    pushed = first_cell(ray, s.corner, size >> 1, jnp.maximum(t_in, ray.t_start))
    # ADVANCE across the nearest exit plane; POP to the cell of the highest changed bit.
    moved = tuple(jnp.where(axis == a, c + size, c) for a, c in enumerate(s.corner))
    popped = vec(lambda c: c & -jnp.left_shift(1, high), moved)
    stepped = _Esvo(
        level=jnp.where(push, s.level + 1, depth - high),
        corner=vec(lambda a, b: jnp.where(push, a, b), pushed, popped),
        parent=parent,
        stack=stack_set(s.stack, s.level, row, push),
        status=status,
    )
    return state_after_step(s, stepped, status, held=("corner",))


def esvo_voxel(tree: Octree, s: _Esvo):
    return s.corner
