"""Ray traversal of octrees, DAGs and dense grids: first voxel hit, front to back.

Three traversals share one ray set-up and one driver:

* ``"stack"``: the talk in ``shared/seeds/000``. A node and a child index are the state;
  the first child comes from comparing the entry ``t`` with the mid-plane ``t``'s, the
  next child from the nearest exit plane (the "moved bit"); going down saves the parent
  with its next child on a stack no deeper than the tree ("save state and go down");
  an exhausted node pops one level per step.
* ``"esvo"``: Laine and Karras' PUSH / ADVANCE / POP (``shared/seeds/002``). The state
  is a cell (level and integer corner) and the stack holds node rows only. PUSH enters
  an occupied cell's first child; ADVANCE steps to the face neighbour across the nearest
  exit plane, and POP happens in the same step: the highest bit that changed in the
  corner names the common ancestor, so any number of levels is popped at once.
* `trace_dense`: Amanatides and Woo's DDA over a dense occupancy grid.

All three mirror negative directions (the coordinate becomes ``R - x`` and the child
slot is XORed with the sign bits), so the loop bodies only handle positive directions,
and stop at the first occupied voxel, which is the nearest because cells are visited
in ray order.

Hit convention: a voxel is hit when the ray passes through its interior at some
``t > 0``, that is when its slab interval ``[t_in, t_out]`` has ``t_in < t_out`` and
``t_out > 0`` (a ray starting on a face and moving away does not hit it; a ray that
only touches an edge or a corner does not either: a traversal visits one of the cells
meeting there, not all), and only if it enters the voxel at ``t <= t_max``. A zero
direction component is replaced by ``2^-100``, so a ray lying exactly in a voxel face
plane passes through the voxels on the positive side of that plane.

Work is in grid units (voxel ``(i, j, k)`` spans ``[i, i+1] x [j, j+1] x [k, k+1]``,
``o = (origin - grid.origin) / h``, ``d = direction / h``), so ``t`` is the parameter of
the world-space ray ``origin + t * direction``.

The driver. A vmapped `jax.lax.while_loop` runs every lane until the slowest ray ends.
By default the rays are instead fed to a fixed number of lanes (persistent threads,
Aila and Laine 2009): every few steps the lanes whose ray ended write its result and
take the next ray from a queue, so lanes do uniform work until the queue is empty.
Rays that miss the grid box never enter the queue. ``lanes=None`` gives the plain
vmapped loop (one lane per ray).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._checks import check_choice, check_int, check_type, is_concrete, refuse
from jaxvox._pytree import pytree_dataclass
from jaxvox._shapes import bucket
from jaxvox.grid import Grid
from jaxvox.octree import MISSING, Octree, _voxel_index

HIT, MISS, STEP_CAP, INVALID = 0, 1, 2, 3  # `Hit.status` values
_RUNNING = -1  # status while a ray is being traced
_TINY = 2.0**-100  # stands in for a zero direction component (its slab times become huge)
_AXES = np.arange(3, dtype=np.int32)
TRACE_METHODS = ("esvo", "stack")  # `trace` methods


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Hit:
    """First voxel hit per ray.

    Attributes:
      t: [...] float32 ray parameter where the ray enters the voxel (0 when it starts
        inside it), inf unless the status is `HIT`.
      voxel: [..., 3] int32 voxel index, -1 unless hit.
      normal: [..., 3] float32 outward normal of the voxel face the ray entered (zero
        when it starts inside the voxel or unless hit).
      index: [...] int32 Morton-order voxel index for attribute arrays (`trace`), or
        the C-order flat index into the occupancy grid (`trace_dense`); -1 unless hit.
      status: [...] int32 `HIT`, `MISS`, `STEP_CAP` (gave up after ``max_steps``) or
        `INVALID` (NaN origin or direction, zero direction, NaN ``t_max``).

    `jaxvox.sphere_trace` returns the same type: there ``t`` is the distance along the
    unit direction, ``normal`` the unit SDF gradient, and ``voxel`` and ``index`` are -1.
    """

    t: jax.Array  # [...] float32
    voxel: jax.Array  # [..., 3] int32
    normal: jax.Array  # [..., 3] float32
    index: jax.Array  # [...] int32
    status: jax.Array  # [...] int32


class _Ray(NamedTuple):
    """One ray in mirrored grid units (all direction components positive), per axis."""

    o: tuple  # 3 x [] float32 mirrored origin
    inv: tuple  # 3 x [] float32 1 / |d|, at most 2^100
    flip: jax.Array  # [] int32 bit a set when direction a is negative
    t_max: jax.Array  # [] float32


def _vec(f, *vectors):
    """Applies `f` per axis to 3-tuples (the loops work on scalars: no [3] reductions)."""
    return tuple(f(*c) for c in zip(*vectors))


def _max3(v):
    return jnp.maximum(jnp.maximum(v[0], v[1]), v[2])


def _min3(v):
    return jnp.minimum(jnp.minimum(v[0], v[1]), v[2])


def _argmin3(v):
    """Axis of the smallest entry, ties to the lower axis (as `jnp.argmin`)."""
    return jnp.where((v[0] <= v[1]) & (v[0] <= v[2]), 0, jnp.where(v[1] <= v[2], 1, 2)).astype(jnp.int32)


def _ray(o, d, t_max, res: int):
    """Mirrors one ray ([3] origin and direction); returns (ray, entry t, initial status)."""
    bad = jnp.any(jnp.isnan(o)) | jnp.any(jnp.isnan(d)) | jnp.all(d == 0) | jnp.isnan(t_max)
    neg = d < 0
    o = jnp.where(bad, 0.0, jnp.where(neg, res - o, o))
    inv = 1.0 / jnp.maximum(jnp.where(bad, 1.0, jnp.abs(d)), _TINY)
    t_in, t_out = jnp.max(-o * inv), jnp.min((res - o) * inv)
    enters = (t_in < t_out) & (t_out > 0) & (t_in <= t_max) & ~bad
    status = jnp.where(enters, _RUNNING, jnp.where(bad, INVALID, MISS)).astype(jnp.int32)
    flip = jnp.sum(jnp.where(neg, 1 << _AXES, 0)).astype(jnp.int32)
    ray = _Ray(tuple(o[a] for a in range(3)), tuple(inv[a] for a in range(3)), flip, t_max)
    return ray, jnp.maximum(t_in, 0.0), status


def _times(ray: _Ray, planes):
    """Times at which the ray crosses the per-axis integer `planes`."""
    return _vec(lambda p, o, i: (p.astype(jnp.float32) - o) * i, planes, ray.o, ray.inv)


def _first_cell(ray: _Ray, corner, half, t_now):
    """Corner of the child (size `half`) of the box at `corner` the ray is in at `t_now`."""
    tm = _times(ray, _vec(lambda c: c + half, corner))
    return _vec(lambda c, t: c + jnp.where(t <= t_now, half, 0), corner, tm)


def _bits(corner, shift):
    """Slot bits ``x | y << 1 | z << 2`` of the cell at `corner` whose size is ``2^shift``."""
    x, y, z = _vec(lambda c: (c >> shift) & 1, corner)
    return x | y << 1 | z << 2


def _mask_bit(tree: Octree, row, slot):
    return ((tree.mask[row].astype(jnp.int32) >> slot) & 1) == 1


def _child_row(tree: Octree, row, slot):
    if tree.child.shape[0] == 0:  # depth 1: the root's children are voxels
        return jnp.int32(0)
    flat = tree.child.reshape(-1)
    return flat[jnp.minimum(row, tree.child.shape[0] - 1) * 8 + slot].astype(jnp.int32)


def _pick(values, index):
    """``values[index]`` for a tuple of scalars and a traced index, as a chain of selects."""
    value = values[0]
    for k in range(1, len(values)):
        value = jnp.where(index == k, values[k], value)
    return value


def _stack_set(stack, level, value, when):
    return tuple(jnp.where(when & (level == k), value, s) for k, s in enumerate(stack))


def _select(keep, new, old):
    return jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, old)


def _status(miss, hit):
    return jnp.where(miss, MISS, jnp.where(hit, HIT, _RUNNING)).astype(jnp.int32)


# --- "esvo": cell state, PUSH / ADVANCE / POP ------------------------------------------


class _Esvo(NamedTuple):
    level: jax.Array  # [] int32 level of the current cell, 1..D (its size is 2^(D - level))
    corner: tuple  # 3 x [] int32 mirrored corner of the current cell
    parent: jax.Array  # [] int32 row of the node the cell belongs to
    stack: tuple  # D x [] int32 stack[l]: row of the level-l node on the current path
    status: jax.Array  # [] int32


def _esvo_init(tree: Octree, ray: _Ray, t_start, status) -> _Esvo:
    res = tree.grid.resolution
    corner = _first_cell(ray, (jnp.int32(0),) * 3, res // 2, t_start)
    return _Esvo(jnp.int32(1), corner, jnp.int32(0), (jnp.int32(0),) * tree.depth, status)


def _esvo_step(tree: Octree, ray: _Ray, s: _Esvo) -> _Esvo:
    depth, res = tree.depth, tree.grid.resolution
    shift = depth - s.level
    size = jnp.left_shift(1, shift)
    t0 = _times(ray, s.corner)
    t1 = _times(ray, _vec(lambda c: c + size, s.corner))
    t_in, t_out = _max3(t0), _min3(t1)
    slot = _bits(s.corner, shift) ^ ray.flip
    live = _mask_bit(tree, s.parent, slot) & (t_out > 0) & (t_in < t_out)
    push = live & (s.level < depth)
    axis = _argmin3(t1)
    before = _pick(s.corner, axis)
    status = _status((t_in > ray.t_max) | (~live & (before + size >= res)), live & (s.level == depth))
    row = _child_row(tree, s.parent, slot)
    # XLA would otherwise recompute these in the fusion of every output.
    t_in, axis, before, push, status, row = jax.lax.optimization_barrier(
        (t_in, axis, before, push, status, row))
    # PUSH: the cell is an occupied node; enter its child the ray is in at entry.
    pushed = _first_cell(ray, s.corner, size >> 1, jnp.maximum(t_in, 0.0))
    # ADVANCE across the nearest exit plane; POP to the cell of the highest changed bit.
    high = 31 - jax.lax.clz(before ^ (before + size))  # the new cell has size 2^high
    moved = tuple(jnp.where(axis == a, before + size, c) for a, c in enumerate(s.corner))
    popped = _vec(lambda c: c & -jnp.left_shift(1, high), moved)
    pop_level = depth - high
    stepped = _Esvo(
        level=jnp.where(push, s.level + 1, pop_level),
        corner=_vec(lambda a, b: jnp.where(push, a, b), pushed, popped),
        parent=jnp.where(push, row, _pick(s.stack, pop_level - 1)),
        stack=_stack_set(s.stack, s.level, row, push),
        status=status)
    return _select(status == _RUNNING, stepped, s._replace(status=status))


def _esvo_voxel(tree: Octree, s: _Esvo):
    return s.corner


# --- "stack": node + child state, save state and go down ---------------------------------


class _Stacked(NamedTuple):
    level: jax.Array  # [] int32 level of the current node, 0..D-1
    node: jax.Array  # [] int32 row of the current node
    corner: tuple  # 3 x [] int32 mirrored corner of the current node
    child: jax.Array  # [] int32 current child (mirrored slot bits), -1 when exhausted
    stack_node: tuple  # D x [] int32 saved ancestors
    stack_child: tuple  # D x [] int32 their next child, -1 if none
    status: jax.Array  # [] int32


def _stacked_init(tree: Octree, ray: _Ray, t_start, status) -> _Stacked:
    res, depth = tree.grid.resolution, tree.depth
    zero = (jnp.int32(0),) * 3
    child = _bits(_first_cell(ray, zero, res // 2, t_start), depth - 1)
    zeros = (jnp.int32(0),) * depth
    return _Stacked(jnp.int32(0), jnp.int32(0), zero, child, zeros, zeros, status)


def _stacked_step(tree: Octree, ray: _Ray, s: _Stacked) -> _Stacked:
    depth = tree.depth
    shift = depth - 1 - s.level  # the children have size 2^shift
    half = jnp.left_shift(1, shift)
    popping = s.child < 0
    c = jnp.maximum(s.child, 0)
    child_corner = _vec(lambda a, k: a + half * ((c >> k) & 1), s.corner, (0, 1, 2))
    t0 = _times(ray, child_corner)
    t1 = _times(ray, _vec(lambda a: a + half, child_corner))
    t_in, t_out = _max3(t0), _min3(t1)
    slot = c ^ ray.flip
    live = ~popping & _mask_bit(tree, s.node, slot) & (t_out > 0) & (t_in < t_out)
    descend = live & (s.level < depth - 1)
    # the moved bit: the child across the nearest exit plane, if still inside this node
    exit_bit = jnp.left_shift(1, _argmin3(t1))
    next_child = jnp.where((c & exit_bit) == 0, c | exit_bit, -1)
    status = _status((~popping & (t_in > ray.t_max)) | (popping & (s.level == 0)),
                     live & (s.level == depth - 1))
    row = _child_row(tree, s.node, slot)
    t_in, next_child, descend, status, row = jax.lax.optimization_barrier(
        (t_in, next_child, descend, status, row))
    # save the parent with its next child, go down; or pop one level
    first = _bits(_first_cell(ray, child_corner, half >> 1, jnp.maximum(t_in, 0.0)), shift - 1)
    up = jnp.maximum(s.level - 1, 0)
    pop = popping & (s.level > 0)
    up_mask = -jnp.left_shift(1, depth - up)
    stepped = _Stacked(
        level=jnp.where(descend, s.level + 1, jnp.where(pop, up, s.level)),
        node=jnp.where(descend, row, jnp.where(pop, _pick(s.stack_node, up), s.node)),
        corner=_vec(lambda a, b: jnp.where(descend, a, jnp.where(pop, b & up_mask, b)),
                    child_corner, s.corner),
        child=jnp.where(descend, first, jnp.where(pop, _pick(s.stack_child, up),
                                                  jnp.where(live, s.child, next_child))),
        stack_node=_stack_set(s.stack_node, s.level, s.node, descend),
        stack_child=_stack_set(s.stack_child, s.level, next_child, descend),
        status=status)
    return _select(status == _RUNNING, stepped, s._replace(status=status))


def _stacked_voxel(tree: Octree, s: _Stacked):
    return _vec(lambda a, k: a + ((s.child >> k) & 1), s.corner, (0, 1, 2))


# --- dense DDA ---------------------------------------------------------------------------


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class _DenseGrid:
    occupancy: jax.Array  # [R^3] bool, flat C order
    grid: Grid


class _Dda(NamedTuple):
    cell: tuple  # 3 x [] int32 mirrored voxel
    status: jax.Array  # [] int32


def _dda_init(dense: _DenseGrid, ray: _Ray, t_start, status) -> _Dda:
    corner, half = (jnp.int32(0),) * 3, dense.grid.resolution // 2
    while half >= 1:  # the voxel the ray is in at t_start, by the octree's tie rules
        corner = _first_cell(ray, corner, half, t_start)
        half //= 2
    return _Dda(corner, status)


def _dda_step(dense: _DenseGrid, ray: _Ray, s: _Dda) -> _Dda:
    res = dense.grid.resolution
    t0 = _times(ray, s.cell)
    t1 = _times(ray, _vec(lambda c: c + 1, s.cell))
    t_in, t_out = _max3(t0), _min3(t1)
    i, j, k = _vec(lambda c, a: jnp.where((ray.flip >> a) & 1 == 1, res - 1 - c, c), s.cell, (0, 1, 2))
    live = dense.occupancy[(i * res + j) * res + k] & (t_out > 0) & (t_in < t_out)
    axis = _argmin3(t1)
    status = _status((t_in > ray.t_max) | (~live & (_pick(s.cell, axis) + 1 >= res)), live)
    cell = tuple(jnp.where((axis == a) & (status == _RUNNING), c + 1, c) for a, c in enumerate(s.cell))
    return _Dda(cell, status)


def _dda_voxel(dense, s: _Dda):
    return s.cell


_METHODS = {
    "esvo": (_esvo_init, _esvo_step, _esvo_voxel),
    "stack": (_stacked_init, _stacked_step, _stacked_voxel),
    "dda": (_dda_init, _dda_step, _dda_voxel),
}


# --- driver ------------------------------------------------------------------------------


def _vmapped(structure, rays: _Ray, t_start, status, method: str, max_steps: int):
    """One lane per ray: a vmapped while loop. Returns (status [N], voxel [N, 3])."""
    init, step, voxel = _METHODS[method]

    def one(ray, t0, st):
        def cond(c):
            return (c[0].status == _RUNNING) & (c[1] < max_steps)

        s, _ = jax.lax.while_loop(cond, lambda c: (step(structure, ray, c[0]), c[1] + 1),
                                  (init(structure, ray, t0, st), jnp.int32(0)))
        return jnp.where(s.status == _RUNNING, STEP_CAP, s.status), jnp.stack(voxel(structure, s))

    return jax.vmap(one)(rays, t_start, status)


def _lanes(structure, rays: _Ray, t_start, status, method: str, max_steps: int, lanes: int,
           steps_per_refill: int = 4):
    """Persistent lanes fed from a queue of the rays that enter the grid box.

    Returns (status [N], voxel [N, 3] mirrored).
    """
    init, step, voxel = _METHODS[method]
    n = status.shape[0]
    running = status == _RUNNING
    queue = jnp.zeros(n + 1, jnp.int32).at[jnp.where(running, jnp.cumsum(running) - 1, n)].set(
        jnp.arange(n, dtype=jnp.int32))[:n]
    queued = jnp.sum(running)
    lane_init = jax.vmap(lambda ray, t0, st: init(structure, ray, t0, st))
    lane_step = jax.vmap(lambda ray, s: step(structure, ray, s))
    take = lambda ids: jax.tree.map(lambda a: a[ids], (rays, t_start, status))

    def fetch(ids, valid):
        ray, t0, st = take(jnp.where(valid, ids, 0))
        return ray, lane_init(ray, t0, jnp.where(valid, st, MISS))

    class Carry(NamedTuple):
        ids: jax.Array  # [W] int32 ray of each lane, n when idle
        ray: _Ray  # [W]
        state: NamedTuple  # [W]
        steps: jax.Array  # [W] int32
        next: jax.Array  # [] int32 queue position of the next ray
        out_status: jax.Array  # [N] int32
        out_voxel: jax.Array  # [N, 3] int32

    first = jnp.arange(lanes, dtype=jnp.int32)
    valid = first < queued
    ids0 = queue[jnp.minimum(first, n - 1)]
    ray0, state0 = fetch(ids0, valid)
    carry = Carry(jnp.where(valid, ids0, n), ray0, state0,
                  jnp.zeros(lanes, jnp.int32), jnp.minimum(queued, lanes),
                  jnp.where(running, _RUNNING, status), jnp.full((n, 3), -1, jnp.int32))

    def body(c: Carry) -> Carry:
        # a loop, not unrolled: XLA would fuse consecutive steps and recompute each one
        state = jax.lax.fori_loop(0, steps_per_refill, lambda _, s: lane_step(c.ray, s), c.state)
        steps = c.steps + steps_per_refill
        capped = steps >= max_steps
        done = (state.status != _RUNNING) | capped
        final = jnp.where(state.status == _RUNNING, STEP_CAP, state.status)
        slot = jnp.where(done, c.ids, n)
        out_status = c.out_status.at[slot].set(final, mode="drop")
        out_voxel = c.out_voxel.at[slot].set(jax.vmap(lambda s: jnp.stack(voxel(structure, s)))(state), mode="drop")
        ended = done & (c.ids < n)
        pos = c.next + jnp.cumsum(ended) - 1
        fresh = ended & (pos < queued)
        new_ids = queue[jnp.clip(pos, 0, n - 1)]
        new_ray, new_state = fetch(new_ids, fresh)
        refill = lambda a, b: jnp.where(jnp.reshape(done, done.shape + (1,) * (a.ndim - 1)), a, b)
        return Carry(jnp.where(fresh, new_ids, jnp.where(done, n, c.ids)),
                     jax.tree.map(refill, new_ray, c.ray), jax.tree.map(refill, new_state, state),
                     jnp.where(done, 0, steps), c.next + jnp.sum(ended), out_status, out_voxel)

    c = jax.lax.while_loop(lambda c: jnp.any(c.ids < n), body, carry)
    return c.out_status, c.out_voxel


def _trace_flat(structure, o, d, t_max, *, method, max_steps, lanes):
    """Traces [N] rays in grid units; returns a flat `Hit` (index left 0)."""
    res = structure.grid.resolution
    rays, t_start, status = jax.vmap(lambda a, b, c: _ray(a, b, c, res))(o, d, t_max)
    if lanes is None or o.shape[0] == 0:
        status, cell = _vmapped(structure, rays, t_start, status, method, max_steps)
    else:
        status, cell = _lanes(structure, rays, t_start, status, method, max_steps,
                              min(lanes, o.shape[0]))
    hit = status == HIT
    t0 = (cell - jnp.stack(rays.o, -1)) * jnp.stack(rays.inv, -1)
    t_in = jnp.max(t0, axis=-1)
    flip = ((rays.flip[:, None] >> _AXES) & 1) == 1
    entry = jnp.where(t_in > 0, jnp.argmax(t0, axis=-1), -1)
    normal = jnp.where(_AXES == entry[:, None], jnp.where(flip, 1.0, -1.0), 0.0)
    return Hit(t=jnp.where(hit, jnp.maximum(t_in, 0.0), jnp.inf),
               voxel=jnp.where(hit[:, None], jnp.where(flip, res - 1 - cell, cell), -1),
               normal=jnp.where(hit[:, None], normal, 0.0).astype(jnp.float32),
               index=jnp.zeros_like(status), status=status)


def _run(structure, origins, directions, t_max, *, method, max_steps, lanes, shard):
    """Shared front end: grid units, flattening, sharding over devices. Returns a `Hit`."""
    grid = structure.grid
    o = grid.to_grid_units(origins)
    d = jnp.asarray(directions, jnp.float32) / grid.voxel_size
    shape = jnp.broadcast_shapes(o.shape, d.shape)[:-1]
    o, d = jnp.broadcast_to(o, shape + (3,)).reshape(-1, 3), jnp.broadcast_to(d, shape + (3,)).reshape(-1, 3)
    t_max = jnp.broadcast_to(jnp.asarray(t_max, jnp.float32), shape).reshape(-1)
    run = functools.partial(_trace_flat, method=method, max_steps=max_steps, lanes=lanes)
    devices = jax.devices()
    n = o.shape[0]
    if shard and len(devices) > 1 and n >= len(devices):
        # Each device traces its own slice of the rays with its own lanes and queue.
        pad = -n % len(devices)
        o, d, t_max = (jnp.concatenate([x, jnp.zeros((pad,) + x.shape[1:], x.dtype)]) for x in (o, d, t_max))
        mesh = jax.sharding.Mesh(np.array(devices), ("rays",))
        spec = jax.sharding.PartitionSpec("rays")
        hits = jax.shard_map(lambda a, b, c: run(structure, a, b, c), mesh=mesh,
                             in_specs=(spec, spec, spec), out_specs=spec, check_vma=False)(o, d, t_max)
        hits = jax.tree.map(lambda x: x[:n], hits)
    else:
        hits = run(structure, o, d, t_max)
    return jax.tree.map(lambda x: x.reshape(shape + x.shape[1:]), hits)


def _rays_on_ladder(call, origins, directions, t_max) -> Hit:
    """``call(origins, directions, t_max)`` with the rays flattened and padded to the shape
    ladder when they are concrete arrays (host-side use), so that ray batches of similar
    counts (image sizes) share one compiled program; inside a caller's `jax.jit` the rays
    pass through unchanged. Padding rays have a zero direction (status `INVALID`, no
    work) and are sliced off on the host.
    """
    if any(isinstance(x, jax.core.Tracer) for x in (origins, directions, t_max)):
        return call(origins, directions, t_max)
    o, d, t = (np.asarray(x, np.float32) for x in (origins, directions, t_max))
    shape = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], t.shape)
    n = int(np.prod(shape, dtype=np.int64))
    pad = bucket(n) - n
    flat = lambda a, tail: np.concatenate([np.broadcast_to(a, shape + tail).reshape((n,) + tail),
                                           np.zeros((pad,) + tail, np.float32)])
    hit = call(flat(o, (3,)), flat(d, (3,)), flat(t, ()))
    return jax.tree.map(lambda x: jax.device_put(np.asarray(x)[:n].reshape(shape + x.shape[1:])), hit)


def _numeric(a) -> bool:
    """Whether `a` converts to a float array (numbers, not strings or objects)."""
    try:
        return np.asarray(a).dtype.kind in "biuf"
    except (TypeError, ValueError):
        return False


def _check_rays(caller: str, origins, directions, t_max, lanes) -> None:
    """Refuses rays and `t_max` that are not numbers, rays that are not [..., 3], batch
    shapes that do not broadcast and a lane count below 1. (NaN values are per-ray
    `INVALID` statuses, as inside jit.)"""
    for name, a in (("origins", origins), ("directions", directions), ("t_max", t_max)):
        if is_concrete(a) and not _numeric(a):
            raise refuse(f"{caller} {name}", "must be numbers", a)
        if name != "t_max" and (np.ndim(a) < 1 or np.shape(a)[-1] != 3):
            raise refuse(f"{caller} {name}", "must have shape [..., 3]", np.shape(a))
    try:
        np.broadcast_shapes(np.shape(origins)[:-1], np.shape(directions)[:-1], np.shape(t_max))
    except ValueError:
        raise refuse(f"{caller} origins, directions, t_max", "batch shapes must broadcast",
                     (np.shape(origins), np.shape(directions), np.shape(t_max))) from None
    if lanes is not None:
        check_int(f"{caller} lanes", lanes, minimum=1)


@functools.partial(jax.jit, static_argnames=("method", "max_steps", "lanes", "shard"))
def _trace(tree, origins, directions, t_max, *, method, max_steps, lanes, shard):
    hit = _run(tree, origins, directions, t_max, method=method, max_steps=max_steps, lanes=lanes,
               shard=shard)
    index = _voxel_index(tree, jnp.maximum(hit.voxel, 0))
    return dataclasses.replace(hit, index=jnp.where(hit.status == HIT, index, MISSING))


def trace(tree: Octree, origins: jax.Array, directions: jax.Array, *, t_max=float("inf"),
          method: str = "esvo", max_steps: int | None = None, lanes: int | None = 16384,
          shard: bool = True) -> Hit:
    """First voxel hit along each ray, front to back, in an SVO or a DAG (same code).

    Jittable and usable inside a caller's `jax.jit`; `method`, `max_steps`, `lanes` and
    `shard` are static. Called on concrete rays, it pads the flattened rays to the shape
    ladder first, so that similar ray counts (image sizes) share one compiled program.

    Args:
      tree: an `Octree` from `build_octree` or `build_dag`.
      origins, directions: [..., 3] float32 in world coordinates, any batch shape;
        directions need not be unit length (``t`` is the parameter of
        ``origin + t * direction``).
      t_max: float or [...] float32; voxels entered beyond it are not hits.
      method: ``"esvo"`` (PUSH/ADVANCE/POP, pops any number of levels per step) or
        ``"stack"`` (the talk's save-state-and-go-down loop, one level per pop). Both
        give identical hits.
      max_steps: cap on loop steps per ray (default ``6 R + 16 D``); rays that reach it
        get status `STEP_CAP`, never a silent miss.
      lanes: number of persistent lanes (per device) fed from the ray queue (see the
        module docstring); None for one vmapped loop per ray.
      shard: when there are several JAX devices, split the rays across all of them
        (`jax.shard_map` over a one-axis mesh; the tree is replicated). Turn it off
        inside a caller's own sharded or vmapped program.

    Returns:
      A `Hit` with the batch shape of the rays.
    """
    check_type("trace tree", tree, Octree)
    check_choice("trace method", method, TRACE_METHODS)
    _check_rays("trace", origins, directions, t_max, lanes)
    steps = (check_int("trace max_steps", max_steps, minimum=1) if max_steps is not None
             else 6 * tree.grid.resolution + 16 * tree.depth)
    return _rays_on_ladder(functools.partial(_trace, tree, method=method, max_steps=steps, lanes=lanes,
                                             shard=shard), origins, directions, t_max)


@functools.partial(jax.jit, static_argnames=("max_steps", "lanes", "shard"))
def _trace_dense(dense, origins, directions, t_max, *, max_steps, lanes, shard):
    hit = _run(dense, origins, directions, t_max, method="dda", max_steps=max_steps, lanes=lanes,
               shard=shard)
    res = dense.grid.resolution
    v = jnp.maximum(hit.voxel, 0)
    index = (v[..., 0] * res + v[..., 1]) * res + v[..., 2]
    return dataclasses.replace(hit, index=jnp.where(hit.status == HIT, index, MISSING))


def trace_dense(occupancy: jax.Array, grid: Grid, origins: jax.Array, directions: jax.Array, *,
                t_max=float("inf"), max_steps: int | None = None, lanes: int | None = 16384,
                shard: bool = True) -> Hit:
    """First voxel hit along each ray in a dense occupancy grid (Amanatides-Woo DDA).

    Same conventions and driver as `trace`; meant for small grids and as a reference.

    Args:
      occupancy: [R, R, R] bool, indexed ``[i, j, k]``.
      grid: the `Grid` the occupancy lives on (its resolution must be R).
      origins, directions, t_max, max_steps, lanes, shard: as in `trace` (default
        ``max_steps`` is ``3 R + 8``, enough for any ray).

    Returns:
      A `Hit`; ``index`` is the flat C-order index ``(i R + j) R + k``.
    """
    check_type("trace_dense grid", grid, Grid)
    occupancy = jnp.asarray(occupancy)
    res = grid.resolution
    if res > 1024:
        raise refuse("trace_dense grid", "resolutions up to 1024 only (flat int32 index)", res)
    if occupancy.shape != (res, res, res):
        raise refuse("trace_dense occupancy", f"must have shape {(res,) * 3} for the grid", occupancy.shape)
    _check_rays("trace_dense", origins, directions, t_max, lanes)
    steps = check_int("trace_dense max_steps", max_steps, minimum=1) if max_steps is not None else 3 * res + 8
    dense = _DenseGrid(occupancy.astype(bool).reshape(-1), grid)
    return _rays_on_ladder(functools.partial(_trace_dense, dense, max_steps=steps, lanes=lanes, shard=shard),
                           origins, directions, t_max)
