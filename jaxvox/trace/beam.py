"""The beam start (Laine and Karras, section 4.2): one coarse pass per group of rays gives
every ray of the group a safe distance at which to start its traversal.

Groups are 8 x 8 tiles of the last two batch axes of the rays (an image's [H, W, 3] rays:
a group is a tile), or runs of `BEAM_RAYS` rays of a one-axis batch (`beam_layout`); the
rays stay in row order, and the group statistics are reductions over the tiles in place
(`tiles`, `per_group`). A group's rays are bounded by a thick segment around one axis
ray: with ``c`` the centre of the box of the group's origins, ``e`` half its diagonal,
``a`` the unit mean direction and ``delta`` the largest distance of a unit direction
from ``a``, the point at distance ``s`` along any ray of the group lies within
``e + s * delta`` of ``c + s a``. The pass marches ``s``
along the axis with steps that double while the box around the swept segment holds no
occupied coarse cell and halve when it does; the box test is exact on the coarse cells
(a summed-volume table of their occupancy, 8 lookups). So every voxel a ray of the group
can meet lies beyond the returned distance, and starting there changes no hit: the
tests compare hits with and without it.

The coarse cells are the tree's nodes at level `coarse_level` (at most `COARSE_CELLS`
per axis), read by a dense descent of that many levels. Groups of rays that do not share
an origin or spread their directions widely get a box that is never empty, and start
where they would have started anyway.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox.octree import CompactDag, Octree
from jaxvox.trace.ray import barrier_token, child_row, fusion_barrier, mask_bit, root_row

BEAM_SIDE = 8  # image tiles of 8 x 8 rays form the groups
BEAM_RAYS = BEAM_SIDE * BEAM_SIDE
COARSE_CELLS = 64  # coarse cells per axis, at most
_MARCH_STEPS = 24  # doubling and halving steps of the march per group
_MARGIN = 1e-2  # grid units added to every box, against float32 rounding


def coarse_level(tree: Octree | CompactDag) -> int:
    """Level whose nodes are the coarse cells: at most `COARSE_CELLS` per axis."""
    return min(tree.depth, COARSE_CELLS.bit_length() - 1)


def coarse_occupancy(tree: Octree | CompactDag, levels: int) -> jax.Array:
    """Which level-`levels` cells hold a voxel: [n, n, n] bool indexed ``[i, j, k]``, n = 2^levels."""
    rows = jnp.reshape(root_row(tree), (1, 1, 1))
    occupied = jnp.ones((1, 1, 1), bool)
    slots = jnp.arange(8, dtype=jnp.int32)

    def spread(a):
        """[n, n, n, 8] per-slot children (slot = x | y << 1 | z << 2) -> [2n, 2n, 2n]."""
        n = a.shape[0]
        return a.reshape(n, n, n, 2, 2, 2).transpose(0, 5, 1, 4, 2, 3).reshape(2 * n, 2 * n, 2 * n)

    for level in range(levels):
        occupied = spread(occupied[..., None] & mask_bit(tree, rows[..., None], slots, level))
        if level + 1 < levels:
            rows = spread(child_row(tree, rows[..., None], slots))
    return occupied


def _box_counts(table, lo, hi):
    """Occupied cells in the inclusive cell boxes [lo, hi] (3 x [G] int32) of a summed table."""
    side = table.shape[0]
    flat = table.reshape(-1)
    total = 0
    for corner in range(8):
        i, j, k = ((hi[a] + 1) if (corner >> a) & 1 else lo[a] for a in range(3))
        sign = (-1) ** (3 - bin(corner).count("1"))
        total = total + sign * flat[(i * side + j) * side + k]
    return total


def tiles(x, layout):
    """[N] values of rays in row order -> [images, rows, a, cols, b], the groups of
    `layout` as tiles of the rows they stand in (padded with zeros; no copy when the rows
    fill whole tiles). Reductions over axes 2 and 4 give one value per group without
    moving the rays into groups: on CPU a copy into groups cost more than the statistics."""
    count, height, width, a, b = layout
    img = x[: count * height * width].reshape(count, height, width)
    img = jnp.pad(img, ((0, 0), (0, -height % a), (0, -width % b)))
    return img.reshape(count, img.shape[1] // a, a, img.shape[2] // b, b)


def per_group(ops, values):
    """One value per group ([images, rows, cols]) of each of several `tiles` arrays, by
    `ops` (`jax.lax.max`, `min`, `add` or `bitwise_or`, one per value) over a row of a
    tile, then over the tile's rows: one variadic reduction per tile axis, so the values
    are read together instead of each written out for a reduction of its own."""
    neutral = {jax.lax.max: -np.inf, jax.lax.min: np.inf, jax.lax.add: 0, jax.lax.bitwise_or: False}
    inits = tuple(np.array(neutral[op], v.dtype) for op, v in zip(ops, values))
    combine = lambda xs, ys: tuple(op(x, y) for op, x, y in zip(ops, xs, ys))
    return jax.lax.reduce(jax.lax.reduce(tuple(values), inits, combine, (4,)), inits, combine, (2,))


def to_tiles(g):
    """A per-group value [images, rows, cols] broadcastable against `tiles` arrays."""
    return g[:, :, None, :, None]


def ungroup_values(g, layout, n):
    """One value per group ([images, rows, cols]) -> [n] per ray in row order (0 past the layout)."""
    count, height, width, a, b = layout
    rows, cols = g.shape[1], g.shape[2]
    x = jnp.broadcast_to(to_tiles(g), (count, rows, a, cols, b))
    x = x.reshape(count, rows * a, cols * b)[:, :height, :width].reshape(-1)
    return jnp.pad(x, (0, n - x.shape[0]))


def beam_layout(batch: tuple, n: int) -> tuple:
    """The groups of a flat batch of `n` rays in row order whose batch shape was `batch`:
    (images, height, width, a, b) with a x b = `BEAM_RAYS` rays per group: 8 x 8 tiles of
    the last two axes, or runs of 64 rays of a one-axis batch."""
    if len(batch) >= 2:
        return (int(np.prod(batch[:-2], dtype=np.int64)), int(batch[-2]), int(batch[-1]), BEAM_SIDE, BEAM_SIDE)
    return (1, 1, n, 1, BEAM_RAYS)


def image_shaped(batch: tuple) -> bool:
    """Whether rays of batch shape `batch` look like a camera's: at least two axes, the last
    two at least `BEAM_SIDE` long (an image's [H, W] rays, or a stack of images). `trace`
    uses the beam start for these unless told otherwise."""
    return len(batch) >= 2 and min(batch[-2:]) >= BEAM_SIDE


def slice_layout(layout: tuple, n: int) -> tuple:
    """The layout for a slice of `n` consecutive rays of a batch with `layout` (one
    device's share): rows of the same width from wherever the slice starts, the rays
    after the last whole band of `BEAM_SIDE` rows left without a beam start (a partial
    band would be padded to whole tiles, a copy of every ray's values)."""
    width = layout[2]
    rows = n // width // BEAM_SIDE * BEAM_SIDE
    if layout[3] == 1 or rows == 0:
        return (1, 1, n, 1, BEAM_RAYS)
    return (1, rows, width, BEAM_SIDE, BEAM_SIDE)


def beam_starts(tree: Octree | CompactDag, o, d, entering, layout: tuple):
    """Safe start distances per ray, in the ray parameter ``t`` of ``o + t d``.

    Args:
      tree: the traced tree.
      o, d: 3 x [N] float32 ray origins and directions in grid units (not mirrored),
        per axis, in row order.
      entering: [N] bool, the rays that enter the grid box (the others are ignored).
      layout: the groups, from `beam_layout`.

    Returns:
      [N] float32 ``t`` before which no ray of the group meets a voxel (0 where nothing
      is known); inf where no ray of the group meets one at all.
    """
    res = tree.grid.resolution
    levels = coarse_level(tree)
    cell = res >> levels
    n = 1 << levels
    counts = coarse_occupancy(tree, levels).astype(jnp.int32)
    table = jnp.pad(counts.cumsum(0).cumsum(1).cumsum(2), ((1, 0), (1, 0), (1, 0)))

    # Per axis (XLA's CPU code is slow on [..., 3] arrays reduced over the last axis),
    # per ray in row order, reduced over the tiles in place.
    square = lambda v: v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    length = jnp.where(entering, jnp.sqrt(square(d)), 1.0)
    on = tiles(entering, layout)
    o, d = (tuple(tiles(c, layout) for c in x) for x in (o, d))
    size = tiles(length, layout)
    unit = tuple(c / size for c in d)
    inv = tuple(1.0 / jnp.where(c == 0, 2.0**-100, c) for c in d)
    exit_t = functools.reduce(jnp.minimum, (jnp.maximum(-p * i, (res - p) * i) for p, i in zip(o, inv)))
    # the origins' box (its centre is the reference point, half its diagonal `e`) and the
    # sum of the unit directions, in one reduction
    mx, mn, add = jax.lax.max, jax.lax.min, jax.lax.add
    stats = per_group(
        (mx, jax.lax.bitwise_or) + (mn,) * 3 + (mx,) * 3 + (add,) * 3,
        (jnp.where(on, exit_t * size, 0.0), on)
        + tuple(jnp.where(on, p, jnp.inf) for p in o)
        + tuple(jnp.where(on, p, -jnp.inf) for p in o)
        + tuple(jnp.where(on, u, 0.0) for u in unit),
    )
    far, anyone, lo, hi, mean = stats[0], stats[1], stats[2:5], stats[5:8], stats[8:11]
    origin = tuple(jnp.where(anyone, (l + h) * 0.5, 0.0) for l, h in zip(lo, hi))
    e = jnp.where(anyone, 0.5 * jnp.sqrt(square(tuple(h - l for l, h in zip(lo, hi)))), 0.0)
    scale = jnp.maximum(jnp.sqrt(square(mean)), 1e-30)
    axis = tuple(m / scale for m in mean)
    # the largest distance of a unit direction from the axis: the root of the largest square
    gap = square(tuple(u - to_tiles(c) for u, c in zip(unit, axis)))
    delta = jnp.sqrt(per_group((mx,), (jnp.where(on, gap, 0.0),))[0])
    groups = far.shape  # [images, rows, cols]
    far, anyone, e, delta = (x.reshape(-1) for x in (far, anyone, e, delta))
    origin, axis = (tuple(c.reshape(-1) for c in x) for x in (origin, axis))

    def empty_box(s, step):
        """Whether no coarse cell is occupied in the box around the group's segment [s, s + step]."""
        r = e + (s + step) * delta + _MARGIN + 1e-6 * (s + step)
        outside, lo, hi = False, [], []
        for p, u in zip(origin, axis):
            a, b = p + s * u, p + (s + step) * u
            low, high = jnp.minimum(a, b) - r, jnp.maximum(a, b) + r
            outside |= (high < 0) | (low > res)
            lo.append(jnp.clip(jnp.floor(low / cell), 0, n - 1).astype(jnp.int32))
            hi.append(jnp.clip(jnp.floor(high / cell), 0, n - 1).astype(jnp.int32))
        return outside | (_box_counts(table, lo, hi) == 0)

    def march(_, carry):
        s, step = carry
        free = fusion_barrier(empty_box(s, step), barrier_token(tree))
        return jnp.where(free, s + step, s), jnp.where(free, step * 2, step * 0.5)

    g = anyone.shape[0]
    s, _ = jax.lax.fori_loop(0, _MARCH_STEPS, march, (jnp.zeros(g, jnp.float32), jnp.full(g, float(cell))))
    s = jnp.where(~anyone, 0.0, jnp.where(s >= far, jnp.inf, s))
    return ungroup_values(s.reshape(groups), layout, entering.shape[0]) / length
