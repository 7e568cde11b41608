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


def _lanes(structure, rows, status, method: str, max_steps: int, lanes: int):
    """Persistent lanes fed from a queue of the rays that enter the grid box
    (`jaxvox._core.lanes.run_in_lanes`). `rows` are the rays as given (world units),
    ``(o [N, 3], d [N, 3], t_max [N], t_beam [N] or None)``: a lane sets its ray up when it takes
    it, so that no [N] array of set-up rays is made. Returns the `_hit_fields` of the [N]
    rays, each written when its lane ends (the rays that never run keep their status)."""
    start, step, voxel = _METHODS[method]
    res = structure.grid.resolution

    def init(row, st):
        ray = _set_up(structure.grid, *row)
        return ray, start(structure, ray, st)

    finish = jax.vmap(lambda ray, s: _hit_fields(res, ray, s.status, voxel(structure, s)))
    n = status.shape[0]
    out = (jnp.full(n, jnp.inf), jnp.full((n, 3), -1, jnp.int32), jnp.zeros((n, 3), jnp.float32), status)
    return run_in_lanes(
        jax.vmap(init),
        jax.vmap(lambda ray, s: step(structure, ray, s)),
        finish,
        rows,
        status,
        out,
        lanes=lanes,
        idle=MISS,
        max_steps=max_steps,
    )


def _grid_units(grid, o, d):
    """World origins and directions (per axis, 3 x [...] float32) in grid units."""
    return tuple((o[a] - grid.origin[a]) / grid.voxel_size for a in range(3)), tuple(c / grid.voxel_size for c in d)


def _set_up(grid, o, d, t_max, t_beam):
    """One ray (world origin and direction, [3] each) set up in grid units (`setup_ray`),
    starting no earlier than `t_beam` (None: no beam)."""
    ray, _ = setup_ray(*_grid_units(grid, tuple(o), tuple(d)), t_max, grid.resolution)
    return ray if t_beam is None else ray._replace(t_start=jnp.maximum(ray.t_start, t_beam))


def _trace_flat(structure, o, d, t_max, layout, *, method, max_steps, lanes):
    """Traces [N] rays (world units, [N, 3] origins and directions); returns a flat `Hit`
    (index left 0). With a beam `layout` (or None), the rays start at their group's beam
    distance."""
    grid, res, n = structure.grid, structure.grid.resolution, o.shape[0]
    # per axis in grid units, each axis read out of the [N, 3] rows once (XLA's fusions
    # would read the strided columns in each of their many consumers)
    columns = _grid_units(grid, *(tuple(x[:, a] for a in range(3)) for x in (o, d)))
    columns = fusion_barrier(columns, barrier_token(structure))
    status = jax.vmap(lambda a, b, c: setup_ray(a, b, c, res)[1])(*columns, t_max)
    t_beam = None
    if layout is not None and n > 0:
        t_beam = beam_starts(structure, *columns, status == RUNNING, layout)
        status = jnp.where((status == RUNNING) & jnp.isinf(t_beam), MISS, status)
        t_beam = jnp.where(jnp.isinf(t_beam), 0.0, t_beam)
    if lanes is None or n == 0:
        rays = jax.vmap(lambda a, b, c, e: _set_up(grid, a, b, c, e))(o, d, t_max, t_beam)
        t, voxel, normal, status = _vmapped(structure, rays, status, method, max_steps)
    else:
        t, voxel, normal, status = _lanes(structure, (o, d, t_max, t_beam), status, method, max_steps, min(lanes, n))
    return Hit(t=t, voxel=voxel, normal=normal, index=jnp.zeros_like(status), status=status)


def trace_rays(structure, origins, directions, t_max, *, method, max_steps, lanes, shard, beam=None, index=None):
    """Shared front end: flattening, sharding over devices. Returns a `Hit`.
    With `beam` (a `beam_layout` of the flat rays), the rays start at their group's beam
    distance, computed by each device on its own rays. `index(structure, hit)` fills ``Hit.index`` on each
    device's own rays (work on a sharded array across devices would be partitioned by
    XLA, with communication in every step of its loops)."""
    o, d = jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32)
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
