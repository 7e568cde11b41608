"""The beam start (Laine and Karras, section 4.2): one coarse pass per group of rays gives
every ray of the group a safe distance at which to start its traversal.

Groups are 8 x 8 tiles of the last two batch axes of the rays (an image's [H, W, 3] rays:
a group is a tile), or runs of `BEAM_RAYS` rays of a one-axis batch (`beam_layout`); the
rays stay in row order, only the group statistics are taken over tiles. A group's rays are bounded by a
thick segment around one axis ray: with ``o_0`` the first ray's origin, ``a`` the unit
mean direction, ``e`` the largest distance of an origin from ``o_0`` and ``delta`` the
largest distance of a unit direction from ``a``, the point at distance ``s`` along any
ray of the group lies within ``e + s * delta`` of ``o_0 + s a``. The pass marches ``s``
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
from jaxvox.trace.ray import child_row, mask_bit, materialize, opaque, root_row

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


def group_values(x, layout):
    """[N] values of rays in row order -> [G, a b], the groups of `layout` (padded with zeros)."""
    count, height, width, a, b = layout
    img = x[: count * height * width].reshape(count, height, width)
    img = jnp.pad(img, ((0, 0), (0, -height % a), (0, -width % b)))
    rows, cols = img.shape[1] // a, img.shape[2] // b
    return img.reshape(count, rows, a, cols, b).transpose(0, 1, 3, 2, 4).reshape(-1, a * b)


def ungroup_values(g, layout, n):
    """The inverse of `group_values` for one value per group ([G]) -> [n] per ray (0 past the layout)."""
    count, height, width, a, b = layout
    rows, cols = -(-height // a), -(-width // b)
    x = jnp.broadcast_to(g.reshape(count, rows, 1, cols, 1), (count, rows, a, cols, b))
    x = x.reshape(count, rows * a, cols * b)[:, :height, :width].reshape(-1)
    return jnp.pad(x, (0, n - x.shape[0]))


def beam_layout(batch: tuple, n: int) -> tuple:
    """The groups of a flat batch of `n` rays in row order whose batch shape was `batch`:
    (images, height, width, a, b) with a x b = `BEAM_RAYS` rays per group: 8 x 8 tiles of
    the last two axes, or runs of 64 rays of a one-axis batch."""
    if len(batch) >= 2:
        return (int(np.prod(batch[:-2], dtype=np.int64)), int(batch[-2]), int(batch[-1]), BEAM_SIDE, BEAM_SIDE)
    return (1, 1, n, 1, BEAM_RAYS)


def slice_layout(layout: tuple, n: int) -> tuple:
    """The layout for a slice of `n` consecutive rays of a batch with `layout` (one
    device's share): rows of the same width from wherever the slice starts, the rays
    after the last whole band of `BEAM_SIDE` rows left without a beam start (a partial
    band would be padded to whole tiles, a copy of every ray's values: on 540 rows of
    the bunny's 1080p frame the pass took 31-36 ms, on 536 rows 18-20 ms)."""
    width = layout[2]
    rows = n // width // BEAM_SIDE * BEAM_SIDE
    if layout[3] == 1 or rows == 0:
        return (1, 1, n, 1, BEAM_RAYS)
    return (1, rows, width, BEAM_SIDE, BEAM_SIDE)


def beam_starts(tree: Octree | CompactDag, o, d, entering, layout: tuple):
    """Safe start distances per ray, in the ray parameter ``t`` of ``o + t d``.

    Args:
      tree: the traced tree.
      o, d: [N, 3] float32 ray origins and directions in grid units (not mirrored), in
        row order.
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

    # per axis: XLA's CPU code is slow on [..., 3] arrays reduced over the last axis
    norm = lambda v: jnp.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    length = jnp.where(entering, norm(tuple(d[:, a] for a in range(3))), 1.0)
    o, d = (tuple(group_values(x[:, a], layout) for a in range(3)) for x in (o, d))
    on = group_values(entering, layout)
    unit = tuple(c / jnp.where(on, norm(d), 1.0) for c in d)
    inv = tuple(1.0 / jnp.where(c == 0, 2.0**-100, c) for c in d)
    exit_t = functools.reduce(jnp.minimum, (jnp.maximum(-p * i, (res - p) * i) for p, i in zip(o, inv)))
    far = jnp.max(jnp.where(on, exit_t * norm(d), 0.0), axis=1)
    anyone = jnp.any(on, axis=1)
    first = jnp.argmax(on, axis=1)[:, None]
    origin = tuple(jnp.take_along_axis(p, first, axis=1) for p in o)  # [G, 1] each
    mean = tuple(jnp.sum(jnp.where(on, u, 0.0), axis=1, keepdims=True) for u in unit)
    scale = jnp.maximum(norm(mean), 1e-30)
    axis = tuple(m / scale for m in mean)
    spread = lambda v: jnp.max(jnp.where(on, norm(v), 0.0), axis=1)
    e = spread(tuple(p - q for p, q in zip(o, origin)))
    delta = spread(tuple(u - a for u, a in zip(unit, axis)))
    origin, axis = tuple(x[:, 0] for x in origin), tuple(x[:, 0] for x in axis)

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
        free = materialize(empty_box(s, step), opaque(tree))
        return jnp.where(free, s + step, s), jnp.where(free, step * 2, step * 0.5)

    g = anyone.shape[0]
    s, _ = jax.lax.fori_loop(0, _MARCH_STEPS, march, (jnp.zeros(g, jnp.float32), jnp.full(g, float(cell))))
    s = jnp.where(~anyone, 0.0, jnp.where(s >= far, jnp.inf, s))
    return ungroup_values(s, layout, entering.shape[0]) / length
