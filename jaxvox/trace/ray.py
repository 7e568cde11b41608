"""Ray set-up in mirrored grid units and the per-axis scalar helpers shared by the loops
of `jaxvox.trace` (esvo, stack, dda)."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxvox._core.hit import HIT, INVALID, MISS, RUNNING
from jaxvox.octree import Octree
from jaxvox.octree.compact_dag import CompactDag, compact_child, compact_mask_bit

_TINY = 2.0**-100  # stands in for a zero direction component (its slab times become huge)


class Ray(NamedTuple):
    """One ray in mirrored grid units (all direction components positive), per axis."""

    o: tuple  # 3 x [] float32 mirrored origin
    inv: tuple  # 3 x [] float32 1 / |d|, at most 2^100
    flip: jax.Array  # [] int32 bit a set when direction a is negative
    t_max: jax.Array  # [] float32
    t_start: jax.Array  # [] float32 where the traversal starts (the grid entry, or a beam start)


def vec(f, *vectors):
    """Applies `f` per axis to 3-tuples (the loops work on scalars: no [3] reductions)."""
    return tuple(f(*c) for c in zip(*vectors))


def max3(v):
    return jnp.maximum(jnp.maximum(v[0], v[1]), v[2])


def min3(v):
    return jnp.minimum(jnp.minimum(v[0], v[1]), v[2])


def argmax3(v):
    """Axis of the largest entry, ties to the lower axis (as `jnp.argmax`)."""
    return jnp.where((v[0] >= v[1]) & (v[0] >= v[2]), 0, jnp.where(v[1] >= v[2], 1, 2)).astype(jnp.int32)


def argmin3(v):
    """Axis of the smallest entry, ties to the lower axis (as `jnp.argmin`)."""
    return jnp.where((v[0] <= v[1]) & (v[0] <= v[2]), 0, jnp.where(v[1] <= v[2], 1, 2)).astype(jnp.int32)


def setup_ray(o, d, t_max, res: int):
    """Mirrors one ray ([3] origin and direction); returns (ray, initial status), the ray
    starting where it enters the grid.

    Works per axis: batched over rays, XLA's CPU code for [N, 3] arrays reduced over the
    last axis is several times slower than the same maths on three [N] arrays.
    """
    o, d = tuple(o[a] for a in range(3)), tuple(d[a] for a in range(3))
    nan = functools.reduce(jnp.logical_or, (jnp.isnan(c) for c in o + d)) | jnp.isnan(t_max)
    bad = nan | ((d[0] == 0) & (d[1] == 0) & (d[2] == 0))
    neg = tuple(c < 0 for c in d)
    o = vec(lambda p, n: jnp.where(bad, 0.0, jnp.where(n, res - p, p)), o, neg)
    inv = vec(lambda c: 1.0 / jnp.maximum(jnp.where(bad, 1.0, jnp.abs(c)), _TINY), d)
    t_in = max3(vec(lambda p, i: -p * i, o, inv))
    t_out = min3(vec(lambda p, i: (res - p) * i, o, inv))
    enters = (t_in < t_out) & (t_out > 0) & (t_in <= t_max) & ~bad
    status = jnp.where(enters, RUNNING, jnp.where(bad, INVALID, MISS)).astype(jnp.int32)
    flip = neg[0].astype(jnp.int32) | neg[1].astype(jnp.int32) << 1 | neg[2].astype(jnp.int32) << 2
    return Ray(o, inv, flip, t_max, jnp.maximum(t_in, 0.0)), status


def times(ray: Ray, planes):
    """Times at which the ray crosses the per-axis integer `planes`."""
    return vec(lambda p, o, i: (p.astype(jnp.float32) - o) * i, planes, ray.o, ray.inv)


def first_cell(ray: Ray, corner, half, t_now):
    """Corner of the child (size `half`) of the box at `corner` the ray is in at `t_now`."""
    tm = times(ray, vec(lambda c: c + half, corner))
    return vec(lambda c, t: c + jnp.where(t <= t_now, half, 0), corner, tm)


def slot_bits(corner, shift):
    """Slot bits ``x | y << 1 | z << 2`` of the cell at `corner` whose size is ``2^shift``."""
    x, y, z = vec(lambda c: (c >> shift) & 1, corner)
    return x | y << 1 | z << 2


def root_row(tree: Octree | CompactDag):
    """The root's row (`Octree`) or reference (`CompactDag`), int32."""
    return tree.root.astype(jnp.int32) if isinstance(tree, CompactDag) else jnp.int32(0)


def mask_bit(tree: Octree | CompactDag, row, slot, level):
    """Whether child `slot` of the level-`level` node at `row` is present."""
    if isinstance(tree, CompactDag):
        return compact_mask_bit(tree, row, slot, level == tree.depth - 1)
    return ((tree.mask[row].astype(jnp.int32) >> slot) & 1) == 1


def child_row(tree: Octree | CompactDag, row, slot):
    """Row (reference) of child `slot` of the node at `row` above level D - 1."""
    if isinstance(tree, CompactDag):
        return compact_child(tree, row, slot)
    if tree.child.shape[0] == 0:  # depth 1: the root's children are voxels
        return jnp.int32(0)
    flat = tree.child.reshape(-1)
    return flat[jnp.minimum(row, tree.child.shape[0] - 1) * 8 + slot].astype(jnp.int32)


def pick(values, index):
    """``values[index]`` for a tuple of scalars and a traced index, as a chain of selects."""
    value = values[0]
    for k in range(1, len(values)):
        value = jnp.where(index == k, values[k], value)
    return value


def stack_set(stack, level, value, when):
    return tuple(jnp.where(when & (level == k), value, s) for k, s in enumerate(stack))


def barrier_token(tree) -> jax.Array:
    """A [] int32 0 or 1 that XLA cannot fold: the token of `fusion_barrier`. `tree` is an
    `Octree`, a `CompactDag` or a dense grid (its first cell's occupancy)."""
    if hasattr(tree, "voxel_count"):
        return (tree.voxel_count == 0).astype(jnp.int32)
    return (tree.occupancy[:1].astype(jnp.int32).sum() > 1).astype(jnp.int32)  # a dense grid: 0


def fusion_barrier(values, token):
    """`values` (a pytree of int32/float32/bool arrays) computed once and stored, not
    recomputed by every consumer.

    XLA's CPU fusion copies a shared producer into the fusion of each consumer, so a loop
    step whose decision feeds a dozen state fields computed the whole step a dozen times
    (`jax.lax.optimization_barrier` is expanded away before fusion, and a conditional
    with equal branches is turned into selects). A while loop is never fused: this one
    runs once (`token` is a [] int32 zero that XLA cannot see is zero) and XORs its
    values with ``token``.
    """

    def body(carry):
        k, v = carry
        flip = lambda x: (
            x ^ k.astype(x.dtype)
            if x.dtype != jnp.float32
            else jax.lax.bitcast_convert_type(jax.lax.bitcast_convert_type(x, jnp.int32) ^ k, jnp.float32)
        )
        return k + 1, jax.tree.map(flip, v)

    return jax.lax.while_loop(lambda c: c[0] < 1, body, (token, values))[1]


def select(keep, new, old):
    return jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, old)


def state_after_step(s, stepped, status, held):
    """The state after a step: `stepped` while the ray runs on; a ray that ended, in this
    step (`status`) or before (``s.status``, e.g. `STEP_CAP` set by the driver), keeps
    its first status and the fields named in `held` (those its voxel is read from). Its
    other fields run on unread: they only feed gathers, which clamp their indices, and
    selecting them back cost a select per field per step."""
    go = (s.status == RUNNING) & (status == RUNNING)
    kept = {name: select(go, getattr(stepped, name), getattr(s, name)) for name in held}
    return stepped._replace(status=jnp.where(s.status == RUNNING, status, s.status), **kept)


def step_status(miss, hit):
    return jnp.where(miss, MISS, jnp.where(hit, HIT, RUNNING)).astype(jnp.int32)


def default_max_steps(tree: Octree | CompactDag) -> int:
    """The default cap on loop steps per ray in `tree`, for `trace` and `render`:
    ``6 R + 16 D`` (R the grid's resolution, D the tree's depth)."""
    return 6 * tree.grid.resolution + 16 * tree.depth
