"""The public traversals `trace` (octrees and DAGs) and `trace_dense` (dense grids): argument
checks, padding of concrete rays to the shape ladder, and the jitted entry points."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Real, Shaped

from jaxvox._core.checks import check_choice, check_int, check_type, is_concrete, refuse
from jaxvox._core.hit import HIT, Hit
from jaxvox._core.scan import on_marked
from jaxvox._core.shapes import bucket
from jaxvox.grid import Grid
from jaxvox.octree import MISSING, CompactDag, Octree, voxel_index
from jaxvox.octree.queries import check_indexed
from jaxvox.trace.beam import beam_layout, image_shaped
from jaxvox.trace.dda import DenseGrid
from jaxvox.trace.driver import trace_rays
from jaxvox.trace.ray import default_max_steps

TRACE_METHODS = ("esvo", "stack")  # `trace` methods


def _rays_on_ladder(call, origins, directions, t_max, shard: bool | None, beam: bool) -> Hit:
    """``call(origins, directions, t_max, shard=..., beam=...)`` on the rays flattened and,
    when they are concrete arrays (host-side use), padded to the shape ladder, so that ray
    batches of similar counts (image sizes) share one compiled program; inside a caller's
    `jax.jit` they pass unpadded. Padding rays have a zero direction (status `INVALID`, no
    work) and are sliced off. ``beam`` passes the `beam_layout` of the batch (None when
    off). ``shard=None`` shards concrete rays only.

    With the beam, whose program is keyed by the batch shape anyway, concrete rays go in
    at their batch shape, unpadded, and the hits are the program's own arrays (sharded
    over the devices when the rays are): no host copies (docs/ray-traversal.md).
    """
    traced = any(isinstance(x, jax.core.Tracer) for x in (origins, directions, t_max))
    shard = (not traced) if shard is None else shard
    xp = jnp if traced else np
    o, d, t = (xp.asarray(x, xp.float32) for x in (origins, directions, t_max))
    shape = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], t.shape)
    m = int(np.prod(shape, dtype=np.int64))
    layout = beam_layout(shape, m) if beam else None
    if beam and not traced:
        grow = lambda a, tail: a if a.shape == shape + tail else np.broadcast_to(a, shape + tail)
        return call(grow(o, (3,)), grow(d, (3,)), grow(t, ()), shard=shard, beam=layout)
    flat = lambda a, tail: xp.broadcast_to(a, shape + tail).reshape((m,) + tail)
    o, d, t = flat(o, (3,)), flat(d, (3,)), flat(t, ())
    if not traced:
        pad = lambda a: np.concatenate([a, np.zeros((bucket(m) - m,) + a.shape[1:], np.float32)])
        o, d, t = pad(o), pad(d), pad(t)
    hit = call(o, d, t, shard=shard, beam=layout)
    unflat = lambda x: x[:m].reshape(shape + x.shape[1:])
    if traced:
        return jax.tree.map(unflat, hit)
    return jax.tree.map(lambda x: jax.device_put(unflat(np.asarray(x))), hit)


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
        _batch_shape(origins, directions, t_max)
    except ValueError:
        raise refuse(
            f"{caller} origins, directions, t_max",
            "batch shapes must broadcast",
            (np.shape(origins), np.shape(directions), np.shape(t_max)),
        ) from None
    if lanes is not None:
        check_int(f"{caller} lanes", lanes, minimum=1)


@functools.partial(jax.jit, static_argnames=("method", "max_steps", "lanes", "shard", "beam", "indexed"))
def jit_trace(tree, origins, directions, t_max, *, method, max_steps, lanes, shard, beam, indexed=True):
    """The jitted body of `trace` (rays as given, no checks), shared with the renderer so
    that its traces of equal shapes are traced to a jaxpr once. ``indexed=False`` leaves
    every ``Hit.index`` 0 (no Morton-index walks: the renderer's shadow rays); a
    `CompactDag` without prefix sums gives `MISSING`."""
    if isinstance(tree, CompactDag) and not tree.prefix:  # no prefix sums: no Morton index
        index = lambda tree, hit: jnp.full_like(hit.status, MISSING)
    else:
        index = hit_indices if indexed else None
    return trace_rays(
        tree,
        origins,
        directions,
        t_max,
        method=method,
        max_steps=max_steps,
        lanes=lanes,
        shard=shard,
        beam=beam,
        index=index,
    )


_INDEX_CHUNK = 16384


def hit_indices(tree, hit: Hit):
    """`voxel_index` of the hit voxels only ([...] int32, `MISSING` elsewhere), looked up
    `on_marked` in chunks of `_INDEX_CHUNK`."""
    hits, voxel = hit.status.reshape(-1) == HIT, hit.voxel.reshape(-1, 3)
    lookup = lambda v: voxel_index(tree, jnp.maximum(v, 0))
    return on_marked(lookup, hits, voxel, jnp.int32(MISSING), _INDEX_CHUNK).reshape(hit.status.shape)


def trace(
    tree: Octree | CompactDag,
    origins: Real[ArrayLike, "*o 3"],
    directions: Real[ArrayLike, "*d 3"],
    *,
    t_max: Real[ArrayLike, "*t"] = float("inf"),
    method: str = "esvo",
    max_steps: int | None = None,
    lanes: int | None = 4096,
    shard: bool | None = None,
    beam: bool | None = None,
) -> Hit:
    """First voxel hit along each ray, front to back, in an SVO or a DAG (same code).

    Jittable and usable inside a caller's `jax.jit`; `method`, `max_steps`, `lanes` and
    `shard` are static. Image-shaped rays (a camera's [H, W, 3]) take the beam start by
    default, in a program keyed by their batch shape. Other concrete rays are flattened
    and padded to the shape ladder first, so that similar ray counts share one compiled
    program.

    Args:
      tree: an `Octree` from `build_octree` or `build_dag`, or a `CompactDag`
        (`compact_dag`; without prefix sums every ``Hit.index`` is -1).
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
      shard: split the rays across all JAX devices (`jax.shard_map` over a one-axis
        mesh; the tree is replicated) when there are several. The default None shards
        only a call on concrete rays (outside any `jax.jit`): inside a caller's own jit,
        sharded or vmapped program the rays stay where the caller put them, unless
        ``shard=True``.
      beam: start each ray at a distance that one coarse pass per group of 64 rays
        proves free (Laine and Karras' beam optimization; `jaxvox.trace.beam`). The
        groups are 8 x 8 tiles of the last two batch axes (so an image's rays, [H, W, 3],
        form coherent groups) or runs of 64 rays of a one-axis batch. Hits are the same
        with and without it; incoherent groups simply gain nothing. Its program is keyed
        by the batch shape: a new image size compiles once, even with a ray count in a
        familiar bucket. The default None takes it for image-shaped rays
        (`jaxvox.trace.beam.image_shaped`: at least two batch axes, the last two at
        least 8 long, what `pinhole_rays` gives), where it pays and the rays go to the
        devices without host copies (docs/benchmarks.md, ray traversal), and leaves it
        off for other batches (a list of rays, [N, 3]), whose groups need not be
        coherent and whose programs are shared by ray counts of one bucket.

    Returns:
      A `Hit` with the batch shape of the rays. With ``beam=True`` on concrete rays and
      several devices, its arrays are the sharded arrays the program leaves on the
      devices (no host copies); combining them with an array
      committed to one device needs ``jax.device_put(hit, device)`` first.

    Raises:
      JaxvoxError: not a tree, a bad method, rays or lane count, or a concrete tree of
        more than 2^31 - 1 voxels, whose Morton indices (``Hit.index``) do not fit int32
        (trace it as ``compact_dag(tree, prefix=False)``).
    """
    check_type("trace tree", tree, (Octree, CompactDag))
    check_choice("trace method", method, TRACE_METHODS)
    if not (isinstance(tree, CompactDag) and not tree.prefix):  # the hit index is computed
        check_indexed("trace tree", tree)
    _check_rays("trace", origins, directions, t_max, lanes)
    steps = check_int("trace max_steps", max_steps, minimum=1) if max_steps is not None else default_max_steps(tree)
    return _rays_on_ladder(
        functools.partial(jit_trace, tree, method=method, max_steps=steps, lanes=lanes),
        origins,
        directions,
        t_max,
        shard,
        beam=image_shaped(_batch_shape(origins, directions, t_max)) if beam is None else bool(beam),
    )


def _batch_shape(origins, directions, t_max) -> tuple[int, ...]:
    """The batch shape of rays (checked by `_check_rays` to broadcast)."""
    return np.broadcast_shapes(np.shape(origins)[:-1], np.shape(directions)[:-1], np.shape(t_max))


def _dense_index(dense, hit: Hit):
    res = dense.grid.resolution
    v = jnp.maximum(hit.voxel, 0)
    return jnp.where(hit.status == HIT, (v[..., 0] * res + v[..., 1]) * res + v[..., 2], MISSING)


@functools.partial(jax.jit, static_argnames=("max_steps", "lanes", "shard", "beam"))
def _trace_dense(dense, origins, directions, t_max, *, max_steps, lanes, shard, beam):
    assert beam is None  # no beam start on a dense grid
    return trace_rays(
        dense,
        origins,
        directions,
        t_max,
        method="dda",
        max_steps=max_steps,
        lanes=lanes,
        shard=shard,
        index=_dense_index,
    )


def trace_dense(
    occupancy: Shaped[ArrayLike, "R R R"],
    grid: Grid,
    origins: Real[ArrayLike, "*o 3"],
    directions: Real[ArrayLike, "*d 3"],
    *,
    t_max: Real[ArrayLike, "*t"] = float("inf"),
    max_steps: int | None = None,
    lanes: int | None = 16384,
    shard: bool | None = None,
) -> Hit:
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
    dense = DenseGrid(occupancy.astype(bool).reshape(-1), grid)
    return _rays_on_ladder(
        functools.partial(_trace_dense, dense, max_steps=steps, lanes=lanes),
        origins,
        directions,
        t_max,
        shard,
        beam=False,
    )
