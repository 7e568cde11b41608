"""Ray traversal of octrees and DAGs ("save state and go down", front to back).

Work in progress for issue 4: the stack traversal of the talk in ``shared/seeds/000``
(parametric slab times per node, first child from the mid-plane times, next child from
the nearest exit plane, mirroring of negative directions by XOR of the child index,
early exit at the first voxel), one `jax.lax.while_loop` per ray, vmapped.

Hit convention: voxels are closed boxes, and a voxel is hit when the ray is inside it for
some ``t > 0`` with ``t <= t_max`` at entry (a ray starting on a voxel's boundary and
moving away does not hit it; a grazing ray touching an edge does). A zero direction
component is replaced by ``2^-100``, so a ray lying exactly in a voxel face plane sees
the voxels on the positive side of that plane.

All work is in grid units (voxel ``(i, j, k)`` spans ``[i, i+1] x [j, j+1] x [k, k+1]``):
``p(t) = o + t d`` with ``o = (origin_world - grid.origin) / h`` and ``d = dir / h``, so
``t`` is the world ray parameter.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxvox._pytree import pytree_dataclass
from jaxvox.octree import EMPTY, Octree

HIT, MISS, STEP_CAP, INVALID = 0, 1, 2, 3  # `Hit.status` values
_TINY = 2.0**-100  # stands in for a zero direction component (its slab times become huge)


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Hit:
    """First voxel hit per ray.

    Attributes:
      t: [...] float32 ray parameter where the ray enters the voxel (0 when it starts
        inside it), inf on a miss.
      voxel: [..., 3] int32 voxel index, -1 on a miss.
      normal: [..., 3] float32 outward normal of the voxel face the ray entered (0 when
        it starts inside or misses).
      index: [...] int32 Morton-order voxel index (for attributes), -1 on a miss.
      status: [...] int32 `HIT`, `MISS`, `STEP_CAP` (gave up after `max_steps`) or
        `INVALID` (NaN or zero direction, NaN origin).
    """

    t: jax.Array  # [...] float32
    voxel: jax.Array  # [..., 3] int32
    normal: jax.Array  # [..., 3] float32
    index: jax.Array  # [...] int32
    status: jax.Array  # [...] int32


class _State(NamedTuple):
    level: jax.Array  # [] int32 level of the current node
    node: jax.Array  # [] int32 row of the current node
    corner: jax.Array  # [3] int32 mirrored-space corner of the current node, in voxels
    child: jax.Array  # [] int32 current child (mirrored 3-bit index), -1 when exhausted
    index: jax.Array  # [] int32 voxels before the current node in Morton order
    stack_node: jax.Array  # [D] int32
    stack_corner: jax.Array  # [D, 3] int32
    stack_child: jax.Array  # [D] int32 the next child to visit, -1 if none
    stack_index: jax.Array  # [D] int32
    status: jax.Array  # [] int32, -1 while running
    t: jax.Array  # [] float32
    voxel: jax.Array  # [3] int32 mirrored-space voxel
    entry: jax.Array  # [] int32 entry axis, -1 when the ray starts inside
    hit_index: jax.Array  # [] int32
    steps: jax.Array  # [] int32


def _bits(c):
    return (c >> jnp.arange(3)) & 1


def _first_child(corner, half, o, inv, t_now):
    """Child of the node at `corner` (children of size `half`) the ray is in at `t_now`."""
    tm = (corner + half - o) * inv
    return jnp.sum(jnp.where(tm <= t_now, 1 << jnp.arange(3), 0)).astype(jnp.int32)


def _trace_one(tree: Octree, o, d, t_max, max_steps: int):
    """Traces one ray given in grid units; returns a `Hit` of scalars."""
    depth, res = tree.depth, tree.grid.resolution
    bad = jnp.any(jnp.isnan(o)) | jnp.any(jnp.isnan(d)) | jnp.all(d == 0) | jnp.isnan(t_max)
    flip = d < 0
    a = jnp.sum(jnp.where(flip, 1 << jnp.arange(3), 0)).astype(jnp.int32)
    o = jnp.where(flip, res - o, o)
    d = jnp.abs(d)
    inv = 1.0 / jnp.where(d == 0, _TINY, d)
    t0, t1 = (0.0 - o) * inv, (res - o) * inv
    t_in, t_out = jnp.max(t0), jnp.min(t1)
    enters = (t_in <= t_out) & (t_out > 0) & (t_in <= t_max) & (tree.voxel_count > 0) & ~bad
    corner0 = jnp.zeros(3, jnp.int32)
    state = _State(
        level=jnp.int32(0), node=jnp.int32(0), corner=corner0,
        child=_first_child(corner0, res // 2, o, inv, jnp.maximum(t_in, 0.0)), index=jnp.int32(0),
        stack_node=jnp.zeros(depth, jnp.int32), stack_corner=jnp.zeros((depth, 3), jnp.int32),
        stack_child=jnp.zeros(depth, jnp.int32), stack_index=jnp.zeros(depth, jnp.int32),
        status=jnp.where(enters, -1, jnp.where(bad, INVALID, MISS)).astype(jnp.int32),
        t=jnp.float32(jnp.inf), voxel=jnp.full(3, -1, jnp.int32), entry=jnp.int32(-1),
        hit_index=jnp.int32(-1), steps=jnp.int32(0))

    def body(s: _State) -> _State:
        size = jnp.int32(res) >> s.level
        half = size >> 1
        popping = s.child < 0
        c = jnp.maximum(s.child, 0)
        cb = _bits(c)
        t0 = (s.corner - o) * inv
        tm = (s.corner + half - o) * inv
        t1 = (s.corner + size - o) * inv
        t0c, t1c = jnp.where(cb == 1, tm, t0), jnp.where(cb == 1, t1, tm)
        t_in, t_out = jnp.max(t0c), jnp.min(t1c)
        slot = c ^ a
        mask = tree.mask[s.node].astype(jnp.int32)
        occupied = ((mask >> slot) & 1) == 1
        beyond = ~popping & (t_in > t_max)
        live = ~popping & ~beyond & occupied & (t_out > 0) & (t_in <= t_out)
        leaf = s.level == depth - 1
        hit, descend = live & leaf, live & ~leaf
        exit_bit = 1 << jnp.argmin(t1c).astype(jnp.int32)
        next_c = jnp.where((c & exit_bit) == 0, c | exit_bit, -1)
        # descend: save the parent with its next child, go into the child
        inner_row = jnp.minimum(s.node, tree.child.shape[0] - 1) if tree.child.shape[0] else 0
        child_row = tree.child[inner_row, slot].astype(jnp.int32) if tree.child.shape[0] else jnp.int32(0)
        prefix = tree.prefix[inner_row, slot].astype(jnp.int32) if tree.child.shape[0] else jnp.int32(0)
        child_corner = s.corner + half * cb
        lvl = jnp.minimum(s.level, depth - 1)
        push = lambda stack, value: jnp.where(descend, stack.at[lvl].set(value), stack)
        up = jnp.maximum(s.level - 1, 0)
        pop_to_miss = popping & (s.level == 0)
        pop = popping & (s.level > 0)
        below = jax.lax.population_count(mask & ((1 << slot) - 1))
        new = _State(
            level=jnp.where(descend, s.level + 1, jnp.where(pop, up, s.level)),
            node=jnp.where(descend, child_row, jnp.where(pop, s.stack_node[up], s.node)),
            corner=jnp.where(descend, child_corner, jnp.where(pop, s.stack_corner[up], s.corner)),
            child=jnp.where(descend, _first_child(child_corner, half >> 1, o, inv, jnp.maximum(t_in, 0.0)),
                            jnp.where(pop, s.stack_child[up], jnp.where(live, s.child, next_c))),
            index=jnp.where(descend, s.index + prefix, jnp.where(pop, s.stack_index[up], s.index)),
            stack_node=push(s.stack_node, s.node), stack_corner=push(s.stack_corner, s.corner),
            stack_child=push(s.stack_child, next_c), stack_index=push(s.stack_index, s.index),
            status=jnp.where(hit, HIT, jnp.where(beyond | pop_to_miss, MISS, s.status)),
            t=jnp.where(hit, jnp.maximum(t_in, 0.0), s.t),
            voxel=jnp.where(hit, child_corner, s.voxel),
            entry=jnp.where(hit, jnp.where(t_in > 0, jnp.argmax(t0c), -1).astype(jnp.int32), s.entry),
            hit_index=jnp.where(hit, s.index + below, s.hit_index),
            steps=s.steps + 1)
        return new

    def cond(s: _State):
        return (s.status < 0) & (s.steps < max_steps)

    s = jax.lax.while_loop(cond, body, state)
    status = jnp.where(s.status < 0, STEP_CAP, s.status)
    hit = status == HIT
    voxel = jnp.where(flip, res - 1 - s.voxel, s.voxel)
    axis_onehot = jnp.arange(3) == s.entry
    normal = jnp.where(axis_onehot, jnp.where(flip, 1.0, -1.0), 0.0)
    return Hit(t=jnp.where(hit, s.t, jnp.inf), voxel=jnp.where(hit, voxel, -1),
               normal=jnp.where(hit, normal, 0.0).astype(jnp.float32),
               index=jnp.where(hit, s.hit_index, -1), status=status)


def trace(tree: Octree, origins: jax.Array, directions: jax.Array, *, t_max: float = float("inf"),
          max_steps: int | None = None) -> Hit:
    """First voxel hit along each ray, front to back (SVO or DAG, same code).

    Args:
      tree: an `Octree`.
      origins, directions: [..., 3] float32 in world coordinates (directions need not
        be unit length; ``t`` is the parameter of ``origin + t * direction``).
      t_max: ignore hits entered beyond this parameter.
      max_steps: cap on loop iterations per ray (default ``8 * R + 16 * D``); rays that
        reach it get status `STEP_CAP`.

    Returns:
      A `Hit` with the batch shape of the rays.
    """
    res = tree.grid.resolution
    max_steps = int(max_steps or 8 * res + 16 * tree.depth)
    o = (jnp.asarray(origins, jnp.float32) - tree.grid.origin) / tree.grid.voxel_size
    d = jnp.asarray(directions, jnp.float32) / tree.grid.voxel_size
    shape = o.shape[:-1]
    one = lambda oo, dd: _trace_one(tree, oo, dd, jnp.float32(t_max), max_steps)
    hits = jax.vmap(one)(o.reshape(-1, 3), d.reshape(-1, 3))
    return jax.tree.map(lambda x: x.reshape(shape + x.shape[1:]), hits)
