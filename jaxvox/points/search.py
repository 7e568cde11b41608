"""Breadth-first search of a `MeshIndex` by blocks of points, with static shapes.

Query points are sorted along a Morton curve of the mesh's box and cut into blocks of
`BLOCK` consecutive points (a block's box is small where points are dense). The search
walks the tree from the root down, one level at a time, over (block, node) *pairs*: a
pair is evaluated for the whole block at once, which shares each node's data among
`BLOCK` points. What a level keeps opens into its children's pairs (count, prefix sum,
emit: `jaxvox._core.shapes.expand_counts`), what must be evaluated per point goes into *rows*
of `ROW` nodes of one block, evaluated in chunks and reduced per block.

Capacities are static: each level's pairs and each set of rows have a capacity chosen by
the caller (`descend`, `make_rows`), which are told what was needed. A block whose pairs or rows did not fit
is reported per point (``lost``); the host API (`jaxvox.points.queries`) runs the search
again with the capacities the lost blocks needed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxvox._core.shapes import bucket, expand_counts
from jaxvox.points.index import FAN_OUT, MeshIndex

BLOCK = 32  # points per block (design history: 16 and 64 were slower)
ROW = 16  # nodes per row of per-point work
ROW_CHUNK = 1024  # rows evaluated together
SLACK = 1.0 + 1e-5  # relative margin on squared-distance comparisons (float32 rounding)


class Blocks(NamedTuple):
    """Query points in Morton order, cut into blocks (relative to the index's centre)."""

    p: jax.Array  # [3, nb, BLOCK] float32 coordinates (padding repeats the last point)
    bounds: jax.Array  # [nb, 6] float32 block box: lo xyz, hi xyz
    order: jax.Array  # [n] int32 position of each input point in the sorted sequence


def make_blocks(index: MeshIndex, points: jax.Array, size: int = BLOCK) -> Blocks:
    """Sorts points [n, 3] (float32, world units, finite) into `Blocks` of `size` points; n >= 1."""
    n = points.shape[0]
    p = points - index.centre
    root = index.levels[-1][0]
    lo, hi = index.nodes[root, :3], index.nodes[root, 3:6]
    span = jnp.maximum(hi - lo, 1e-30)
    q = jnp.clip((p - lo) / span * 1024, 0, 1023).astype(jnp.uint32)
    code = jnp.zeros(n, jnp.uint32)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    _, perm = jax.lax.sort_key_val(code, jnp.arange(n, dtype=jnp.int32))
    nb = -(-n // size)
    perm_padded = jnp.concatenate([perm, jnp.full(nb * size - n, perm[-1], jnp.int32)])
    sorted_p = p[perm_padded].T.reshape(3, nb, size)
    order = jnp.zeros(n, jnp.int32).at[perm].set(jnp.arange(n, dtype=jnp.int32))
    return Blocks(sorted_p, jnp.concatenate([sorted_p.min(-1), sorted_p.max(-1)]).T, order)


def per_point(blocks: Blocks, values: jax.Array) -> jax.Array:
    """Per-block values [nb, BLOCK, ...] back to the input points' order: [n, ...]."""
    flat = values.reshape((-1,) + values.shape[2:])
    return flat[blocks.order]


class Pairs(NamedTuple):
    """A frontier: (block, node) pairs sorted by block; slots at or past ``filled`` are unused
    (their block is the block count, past every real one)."""

    block: jax.Array  # [capacity] int32
    node: jax.Array  # [capacity] int32 node id within its level
    filled: jax.Array  # [] int32 slots in use


def root_pairs(nb: int) -> Pairs:
    """Every block paired with the root."""
    return Pairs(jnp.arange(nb, dtype=jnp.int32), jnp.zeros(nb, jnp.int32), jnp.int32(nb))


def _lost_blocks(block, needed, capacity: int, nb: int):
    """[nb] bool: blocks owning an item whose end (exclusive prefix sum + own count) passes capacity."""
    ends = jnp.cumsum(needed)
    return jax.ops.segment_max((ends > capacity) & (needed > 0), block, nb, indices_are_sorted=True)


def children(pairs: Pairs, keep, child_level_size) -> jax.Array:
    """[capacity] int32 children of each kept pair in the level below (of `child_level_size` nodes)."""
    return jnp.where(keep, jnp.clip(child_level_size - FAN_OUT * pairs.node, 0, FAN_OUT), 0)


def open_pairs(pairs: Pairs, keep, child_level_size, capacity: int, nb: int) -> tuple[Pairs, jax.Array]:
    """The children (in the level below, of `child_level_size` nodes) of the pairs kept
    ([capacity_in] bool), at most `capacity` of them; and [nb] bool blocks that lost some."""
    counts = children(pairs, keep, child_level_size)
    owner, rank, ok, _ = expand_counts(counts, capacity)
    block = jnp.where(ok, pairs.block[owner], nb)
    node = jnp.where(ok, FAN_OUT * pairs.node[owner] + rank, 0)
    count = jnp.minimum(jnp.sum(counts), capacity)  # (the sum is what was needed)
    return Pairs(block, node, count), _lost_blocks(pairs.block, counts, capacity, nb)


class Rows(NamedTuple):
    """Kept pairs regrouped per block into rows of `ROW` nodes (-1: none)."""

    node: jax.Array  # [capacity, ROW] int32 node ids within the level, -1 for unused
    block: jax.Array  # [capacity] int32 (the block count for unused rows)
    filled: jax.Array  # [] int32 rows in use
    needed: jax.Array  # [] int32 rows the pairs needed (more than the capacity: some lost)


def make_rows(pairs: Pairs, keep, capacity: int, nb: int) -> tuple[Rows, jax.Array]:
    """The pairs kept ([size] bool) as `Rows` (at most `capacity`), and [nb] bool blocks
    that lost some."""
    keep = keep & (pairs.block < nb)
    per_block = jax.ops.segment_sum(keep.astype(jnp.int32), pairs.block, nb, indices_are_sorted=True)
    rows = -(-per_block // ROW)
    first = jnp.cumsum(per_block) - per_block
    first_row = jnp.cumsum(rows) - rows
    b = jnp.minimum(pairs.block, nb - 1)
    j = jnp.cumsum(keep) - 1 - first[b]
    row = jnp.where(keep, first_row[b] + j // ROW, capacity)
    table = jnp.full((capacity, ROW), -1, jnp.int32).at[row, j % ROW].set(pairs.node, mode="drop")
    owner, _, ok, total = expand_counts(rows, capacity)
    lost = (first_row + rows > capacity) & (rows > 0)
    return Rows(table, jnp.where(ok, owner, nb), jnp.minimum(total, capacity), total), lost


def join_rows(parts: list[Rows], nb: int) -> Rows:
    """Several `Rows` (node ids already global, equal widths) as one, rows in use first."""
    node = jnp.concatenate([r.node for r in parts])
    block = jnp.concatenate([r.block for r in parts])
    used = block < nb
    at = jnp.where(used, jnp.cumsum(used) - 1, block.shape[0])
    node = jnp.full_like(node, -1).at[at].set(node, mode="drop")
    block = jnp.full_like(block, nb).at[at].set(block, mode="drop")
    return Rows(node, block, jnp.sum(used), jnp.sum(jnp.stack([r.needed for r in parts])))


def eval_rows(rows: Rows, blocks: Blocks, fn: Callable, empty) -> tuple:
    """``fn(p, nodes)`` for each row in use, chunk by chunk.

    `fn` takes the row's block points ``p`` (3 arrays [c, BLOCK]) and node ids
    ``nodes`` [c, ROW] int32 (-1: none) and returns a tuple of [c, BLOCK] arrays; `empty`
    the matching tuple of fill values. Returns the tuple of [capacity, BLOCK] arrays
    (unused rows hold the fill values).
    """
    capacity = rows.node.shape[0]
    chunk = min(ROW_CHUNK, capacity)
    padded = -(-capacity // chunk) * chunk
    table = jnp.pad(rows.node, ((0, padded - capacity), (0, 0)), constant_values=-1)
    owner = jnp.pad(jnp.minimum(rows.block, blocks.p.shape[1] - 1), (0, padded - capacity))
    out = tuple(jnp.full((padded, blocks.p.shape[2]), e) for e in empty)

    def body(state):
        i, out = state
        start = i * chunk
        nodes = jax.lax.dynamic_slice_in_dim(table, start, chunk)
        b = jax.lax.dynamic_slice_in_dim(owner, start, chunk)
        p = tuple(blocks.p[k][b] for k in range(3))
        values = fn(p, nodes)
        return i + 1, tuple(jax.lax.dynamic_update_slice_in_dim(o, v, start, 0) for o, v in zip(out, values))

    steps = -(-rows.filled // chunk)
    _, out = jax.lax.while_loop(lambda s: s[0] < steps, body, (jnp.int32(0), out))
    return tuple(o[:capacity] for o in out)


def box_gap2(box, node):
    """Squared distance between block boxes ``box`` [m, 6] and node boxes ``node`` [m, >= 6]
    (lo xyz, hi xyz each)."""
    gap = [jnp.maximum(0.0, jnp.maximum(node[:, k] - box[:, 3 + k], box[:, k] - node[:, 3 + k])) for k in range(3)]
    return gap[0] * gap[0] + gap[1] * gap[1] + gap[2] * gap[2]


def frame_gap(box, frame):
    """Lower bound on the distance between block boxes ``box`` [m, 6] and oriented boxes
    ``frame`` [m, 15] (centre, three axes, half extents): the distance from the block's
    centre, less its half diagonal ([m]; negative inside)."""
    c = [(box[:, k] + box[:, 3 + k]) * 0.5 - frame[:, k] for k in range(3)]
    r2 = sum((box[:, 3 + k] - box[:, k]) ** 2 for k in range(3)) * 0.25
    gap2 = 0.0
    for a in range(3):
        along = c[0] * frame[:, 3 + 3 * a] + c[1] * frame[:, 4 + 3 * a] + c[2] * frame[:, 5 + 3 * a]
        g = jnp.maximum(jnp.abs(along) - frame[:, 12 + a], 0.0)
        gap2 = gap2 + g * g
    return jnp.sqrt(gap2) - jnp.sqrt(r2)


def point_gap2(p, node):
    """Lower bound on the squared distance from points p (3 arrays [m, BLOCK]) to the
    triangles of nodes ``node`` [m, 24] (`MeshIndex.nodes`): the larger of the distances
    to their box and to their oriented box ([m, BLOCK])."""
    col = lambda i: node[:, i, None]
    box = sum(jnp.maximum(0.0, jnp.maximum(col(k) - p[k], p[k] - col(3 + k))) ** 2 for k in range(3))
    c = [p[k] - col(9 + k) for k in range(3)]
    frame = 0.0
    for a in range(3):
        along = c[0] * col(12 + 3 * a) + c[1] * col(13 + 3 * a) + c[2] * col(14 + 3 * a)
        frame = frame + jnp.maximum(jnp.abs(along) - col(21 + a), 0.0) ** 2
    return jnp.maximum(box, frame * (1.0 - 1e-5))


def far_corner2(box, q):
    """Squared distance from points q [m, 3] to the farthest corner of block boxes ``box`` [m, 6]."""
    far = [jnp.maximum(jnp.abs(q[:, k] - box[:, k]), jnp.abs(box[:, 3 + k] - q[:, k])) for k in range(3)]
    return far[0] * far[0] + far[1] * far[1] + far[2] * far[2]


def descend(select, nb: int, levels, pair_caps: tuple[int, ...]):
    """Walks a search from the root down to the leaves with static capacities.

    ``select(pairs, depth) -> keep`` picks the pairs to open at a level. `pair_caps[d]`
    is the capacity of the pairs at depth d (0: the leaves, as `MeshIndex.levels`).

    Returns:
      (leaf pairs, their keep mask, [nb] bool blocks that lost pairs, [len(levels) - 1]
      int32 pairs each level needed).
    """
    pairs = root_pairs(nb)
    lost = jnp.zeros(nb, bool)
    needs = []
    for depth in range(len(levels) - 1, 0, -1):
        keep = select(pairs, depth)
        size = levels[depth - 1][1]
        needs.append(jnp.sum(children(pairs, keep, size)))
        pairs, dropped = open_pairs(pairs, keep, size, pair_caps[depth - 1], nb)
        lost |= dropped
    keep = select(pairs, 0)
    return pairs, keep, lost, jnp.stack(needs[::-1]) if needs else jnp.zeros(0, jnp.int32)


def grown(caps: tuple[int, ...], needs, row_depths: tuple[int, ...]) -> tuple[int, ...]:
    """Capacities after a run that needed `needs` (host ints): each at least its need with
    a quarter to spare, on the shape ladder; never smaller than before.

    The first ``len(caps) - len(row_depths)`` entries are the pairs at each depth (leaves
    first, `descend`); each other entry holds rows made from the pairs at depth
    ``row_depths[i]``. A level whose pairs overflowed by a factor r passed on only 1/r of
    them, so every need that depends on it (the pairs below it, the rows of its depth and
    below) is scaled by r, so that a retry can fit the levels below an overflow too
    rather than one more level per retry.
    """
    n_pairs = len(caps) - len(row_depths)
    over = [max(1.0, int(n) / c) for c, n in zip(caps[:n_pairs], needs[:n_pairs])]
    above = lambda depth: math.prod(over[depth:])  # the overflow of the pairs at this depth and above
    scale = [above(d + 1) for d in range(n_pairs)] + [above(d) for d in row_depths]
    estimate = [math.ceil(int(n) * f) for n, f in zip(needs, scale)]
    return tuple(max(c, bucket(n + n // 4)) for c, n in zip(caps, estimate))
