"""The driver shared by the traversals: a vmapped while loop per ray or persistent lanes fed
from a ray queue, the conversion of cells to `Hit`s, and the front end (grid units,
flattening, sharding over devices); see `jaxvox.trace`."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxvox._core.devices import on_each_device
from jaxvox._core.hit import HIT, MISS, RUNNING, STEP_CAP, Hit
from jaxvox._core.lanes import run_in_lanes
from jaxvox.trace.beam import beam_starts, slice_layout
from jaxvox.trace.dda import dda_init, dda_step, dda_voxel
from jaxvox.trace.esvo import esvo_init, esvo_step, esvo_voxel
from jaxvox.trace.ray import Ray, argmax3, barrier_token, fusion_barrier, max3, setup_ray
from jaxvox.trace.stack import stacked_init, stacked_step, stacked_voxel

_METHODS: dict[str, tuple[Callable, Callable, Callable]] = {
    "esvo": (esvo_init, esvo_step, esvo_voxel),
    "stack": (stacked_init, stacked_step, stacked_voxel),
    "dda": (dda_init, dda_step, dda_voxel),
}


def _hit_fields(res: int, ray: Ray, status, cell):
    """One ray's `Hit` fields but the index, from its final status and mirrored cell (3 x
    [] int32): (t [], voxel [3] int32, normal [3] float32, status [])."""
    hit = status == HIT
    t0 = [(cell[a] - ray.o[a]) * ray.inv[a] for a in range(3)]  # per axis, see `setup_ray`
    t_in = max3(t0)
    entry = jnp.where(hit & (t_in > 0), argmax3(t0), -1)
    flip = [((ray.flip >> a) & 1) == 1 for a in range(3)]
    voxel = jnp.stack([jnp.where(hit, jnp.where(flip[a], res - 1 - cell[a], cell[a]), -1) for a in range(3)])
    normal = jnp.stack([jnp.where(entry == a, jnp.where(flip[a], 1.0, -1.0), 0.0) for a in range(3)])
    return jnp.where(hit, jnp.maximum(t_in, 0.0), jnp.inf), voxel, normal.astype(jnp.float32), status


def _vmapped(structure, rays: Ray, status, method: str, max_steps: int):
    """One lane per ray: a vmapped while loop. Returns the `_hit_fields` of the [N] rays."""
    init, step, voxel = _METHODS[method]
    res = structure.grid.resolution

    def one(ray, st):
        def cond(c):
            return (c[0].status == RUNNING) & (c[1] < max_steps)

        s, _ = jax.lax.while_loop(
            cond, lambda c: (step(structure, ray, c[0]), c[1] + 1), (init(structure, ray, st), jnp.int32(0))
        )
        return _hit_fields(res, ray, jnp.where(s.status == RUNNING, STEP_CAP, s.status), voxel(structure, s))

    return jax.vmap(one)(rays, status)


def _lanes(structure, rays: Ray, status, method: str, max_steps: int, lanes: int):
    """Persistent lanes fed from a queue of the rays that enter the grid box
    (`jaxvox._core.lanes.run_in_lanes`). Returns the `_hit_fields` of the [N] rays, each
    written when its lane ends (the rays that never run keep their status)."""
    init, step, voxel = _METHODS[method]
    res = structure.grid.resolution
    finish = jax.vmap(lambda ray, s: _hit_fields(res, ray, s.status, voxel(structure, s)))
    n = status.shape[0]
    out = (jnp.full(n, jnp.inf), jnp.full((n, 3), -1, jnp.int32), jnp.zeros((n, 3), jnp.float32), status)
    return run_in_lanes(
        jax.vmap(lambda ray, st: init(structure, ray, st)),
        jax.vmap(lambda ray, s: step(structure, ray, s)),
        finish,
        rays,
        status,
        out,
        lanes=lanes,
        idle=MISS,
        max_steps=max_steps,
    )


def _trace_flat(structure, o, d, t_max, layout, *, method, max_steps, lanes):
    """Traces [N] rays in grid units; returns a flat `Hit` (index left 0). With a beam
    `layout` (or None), the rays start at their group's beam distance."""
    res = structure.grid.resolution
    # per axis, each axis read out of the [N, 3] rows once (XLA's fusions would read the
    # strided columns in each of their many consumers)
    o, d = fusion_barrier(tuple(tuple(x[:, a] for a in range(3)) for x in (o, d)), barrier_token(structure))
    rays, status = jax.vmap(lambda a, b, c: setup_ray(a, b, c, res))(o, d, t_max)
    if layout is not None and o[0].shape[0] > 0:
        t_beam = beam_starts(structure, o, d, status == RUNNING, layout)
        status = jnp.where((status == RUNNING) & jnp.isinf(t_beam), MISS, status)
        rays = rays._replace(t_start=jnp.maximum(rays.t_start, jnp.where(jnp.isinf(t_beam), 0.0, t_beam)))
    if lanes is None or o[0].shape[0] == 0:
        t, voxel, normal, status = _vmapped(structure, rays, status, method, max_steps)
    else:
        t, voxel, normal, status = _lanes(structure, rays, status, method, max_steps, min(lanes, o[0].shape[0]))
    return Hit(t=t, voxel=voxel, normal=normal, index=jnp.zeros_like(status), status=status)


def trace_rays(structure, origins, directions, t_max, *, method, max_steps, lanes, shard, beam=None, index=None):
    """Shared front end: grid units, flattening, sharding over devices. Returns a `Hit`.
    With `beam` (a `beam_layout` of the flat rays), the rays start at their group's beam
    distance, computed by each device on its own rays. `index(structure, hit)` fills ``Hit.index`` on each
    device's own rays (work on a sharded array across devices would be partitioned by
    XLA, with communication in every step of its loops)."""
    grid = structure.grid
    o = grid.to_grid_units(origins)
    d = jnp.asarray(directions, jnp.float32) / grid.voxel_size
    shape = jnp.broadcast_shapes(o.shape, d.shape)[:-1]
    o, d = jnp.broadcast_to(o, shape + (3,)).reshape(-1, 3), jnp.broadcast_to(d, shape + (3,)).reshape(-1, 3)
    t_max = jnp.broadcast_to(jnp.asarray(t_max, jnp.float32), shape).reshape(-1)
    devices = jax.devices()
    n = o.shape[0]
    sharded = shard and len(devices) > 1 and n >= len(devices)
    flat = functools.partial(_trace_flat, method=method, max_steps=max_steps, lanes=lanes)

    def run(structure, o, d, t_max, layout):
        hit = flat(structure, o, d, t_max, layout)
        return hit if index is None else dataclasses.replace(hit, index=index(structure, hit))

    if sharded:
        # Each device traces its own slice of the rays with its own lanes and queue.
        pad = -n % len(devices)
        grow = lambda x: jnp.concatenate([x, jnp.zeros((pad,) + x.shape[1:], x.dtype)])
        # Each device groups its own slice for the beam (the slices need not start at a
        # tile: a group of rays from two rows only gets a looser bound).
        local = None if beam is None else slice_layout(beam, (n + pad) // len(devices))
        hits = on_each_device(lambda s, a, b, c: run(s, a, b, c, local), structure, grow(o), grow(d), grow(t_max))
        hits = jax.tree.map(lambda x: x[:n], hits)
    else:
        hits = run(structure, o, d, t_max, beam)
    return jax.tree.map(lambda x: x.reshape(shape + x.shape[1:]), hits)
