"""Sparse voxel octrees and DAGs: bottom-up build, expansion, voxel indexing, attributes.

A grid of resolution ``R = 2^D`` has node levels ``0`` (the root, one node covering the
grid) to ``D - 1``; a node at level ``l`` covers ``2^(D-l)`` voxels per axis. Child slot
``s`` in ``0..7`` of a node is ``x | y << 1 | z << 2`` with x, y, z the next bit of the
voxel index on each axis, so children in slot order are in Morton order. The children of
level ``D - 1`` nodes are voxels: that level stores masks only.

Layout (as in Kampe et al. 2013 and the talk in ``shared/seeds``): all nodes live in one
table, level by level, root first; level ``l`` occupies rows
``[level_offsets[l], level_offsets[l] + level_capacity[l])``. Every node has

* ``mask``: uint8, bit ``s`` set when child ``s`` is non-empty;
* ``child``: 8 uint32 absolute row indices of the children (`EMPTY` where absent),
  for nodes above level ``D - 1`` only;
* ``prefix``: 8 uint32, the number of voxels in the children before slot ``s``
  ("dynamic voxel indexing" with the prefix sums stored in the parent), again above
  level ``D - 1`` only. At level ``D - 1`` the prefix is the popcount of the mask bits
  below ``s``, computed on the fly.

A root-to-leaf walk that adds the prefix of every slot it takes yields the voxel's
index in Morton order, so attributes (triangle id, normal, colour, ...) live in a
separate array indexed by it. Counts depend only on a subtree's shape, so they are
shared in the DAG as the subtrees are.

Builds are bottom-up from Morton-sorted voxels, one segment pass per level: parents are
``ijk >> 1``, consecutive in Morton order, so each level is a boundary flag, a prefix sum
and a scatter. The DAG deduplicates each level before building the next: a
lexicographic sort of the child-pointer rows (multi-operand `jax.lax.sort`), a segment
and a remap; masks of the mask-only level are deduplicated through a 256-entry table. No
hash table, no locks, no dense grid. DAG nodes of a level are stored in the
lexicographic order of their child rows (masks by value at level ``D - 1``), so the same
voxel set always gives the same arrays.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox import morton
from jaxvox._checks import check_int, check_type, refuse
from jaxvox._errors import JaxvoxError
from jaxvox._pytree import pytree_dataclass
from jaxvox._shapes import bucket, expand_counts, key_bits
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, pad_mesh, sample_texture, validate_mesh
from jaxvox.voxelize import UNUSED, Voxels

EMPTY = morton.EMPTY  # uint32 0xFFFFFFFF: an absent child (no node has that row index)
OVERFLOW_NODES = 16  # bit of `Octree.overflow`: a level held more nodes than its capacity
MISSING = -1  # `voxel_index` of an empty voxel

_SLOTS = np.arange(8)
# _SELECT[m, k]: slot of the k-th set bit of mask m (0 past popcount(m)).
_SELECT = np.zeros((256, 8), np.uint8)
for _m in range(256):
    _bits = _SLOTS[(_m >> _SLOTS) & 1 == 1]
    _SELECT[_m, : len(_bits)] = _bits


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Octree:
    """A sparse voxel octree (``dag=False``) or DAG (``dag=True``) in fixed-size tables.

    Rows past ``level_count[l]`` within level ``l`` are padding (mask 0, children
    `EMPTY`, prefix 0). Trees returned by `build_octree` / `build_dag` without explicit
    capacities (and by `load`) are padded to the shape ladder: every level holds
    exactly its nodes (the root row always exists) except the last two, which take the
    padding rows that bring `child`/`prefix` and `mask` to power-of-two lengths (at most
    twice their rows, four times for the one-byte masks). Trees of similar size so share
    compiled consumers (`trace`, `render`, `voxel_index`, `expand`); `compact` drops the
    padding. Only the table lengths, the resolution, `dag` and `mode` are part of a
    compiled program's key: `level_capacity` is an array, and `dag` and `mode` are
    static (changing them recompiles).

    Attributes:
      mask: [N] uint8 child masks of all nodes, level by level, root first.
      child: [M, 8] uint32 absolute child rows of the nodes above level ``D - 1``
        (``M = N - level_capacity[-1]``), `EMPTY` where absent.
      prefix: [M, 8] uint32 voxels in the children before each slot.
      level_count: [D] int32 nodes per level.
      voxel_count: [] int32 voxels in the tree.
      overflow: [] int32 bitmask: the source voxels' ``OVERFLOW_*`` flags and
        `OVERFLOW_NODES`; nonzero means the tree is truncated.
      grid: the `Grid` the tree covers.
      level_capacity: [D] int32 rows reserved per level (host tuple: `level_capacities`).
      dag: static bool, whether identical subtrees are shared.
      mode: static str, the voxelization mode of the source voxels.
    """

    mask: jax.Array  # [N] uint8
    child: jax.Array  # [M, 8] uint32
    prefix: jax.Array  # [M, 8] uint32
    level_count: jax.Array  # [D] int32
    voxel_count: jax.Array  # [] int32
    overflow: jax.Array  # [] int32
    grid: Grid
    level_capacity: jax.Array  # [D] int32
    dag: bool = dataclasses.field(metadata=dict(static=True))
    mode: str = dataclasses.field(metadata=dict(static=True))

    @property
    def depth(self) -> int:
        """Number of node levels D = log2(resolution)."""
        return self.level_capacity.shape[-1]

    @property
    def level_capacities(self) -> tuple[int, ...]:
        """Rows reserved per level as host ints (host-side)."""
        return tuple(int(x) for x in np.asarray(self.level_capacity))

    @property
    def level_offsets(self) -> tuple[int, ...]:
        """First row of each level in `mask` (and, above level D - 1, `child`, `prefix`)."""
        return tuple(int(x) for x in np.cumsum((0,) + self.level_capacities[:-1]))

    @property
    def level_sizes(self) -> tuple[int, ...]:
        """Nodes per level as host ints, root level first, down to level D - 1."""
        return tuple(int(n) for n in np.asarray(self.level_count))

    @property
    def num_nodes(self) -> int:
        """Total number of nodes (host int)."""
        return sum(self.level_sizes)

    @property
    def nbytes(self) -> int:
        """Bytes of the node tables as stored: `mask`, `child` and `prefix`.

        That is 1 byte per row plus 64 bytes (8 uint32 child rows and 8 uint32 prefix
        sums) per row above level D - 1, padding rows included (see `compact_nbytes`).
        The grid, the per-level counts and the attribute arrays are not counted.
        """
        return int(self.mask.nbytes + self.child.nbytes + self.prefix.nbytes)

    @property
    def compact_nbytes(self) -> int:
        """Bytes of the node tables without padding rows: what `compact` keeps and `save` writes."""
        stored = stored_sizes(self.level_sizes)
        return sum(stored) + 64 * sum(stored[:-1])


def stored_sizes(level_sizes) -> tuple[int, ...]:
    """Rows a compact tree stores per level: `level_sizes`, but the root row always exists
    (an empty tree keeps one root with mask 0)."""
    sizes = tuple(int(n) for n in level_sizes)
    return (max(sizes[0], 1),) + sizes[1:]


def padded_sizes(level_sizes) -> tuple[int, ...]:
    """Rows per level of a tree padded to the shape ladder (see `Octree`).

    The stored sizes, with the padding that brings the rows above level D - 1 (those of
    `child` and `prefix`) to a power of two added to level D - 2, and the padding that
    brings all rows (`mask`) to a power of two added to level D - 1.
    """
    sizes = list(stored_sizes(level_sizes))
    if len(sizes) > 1:
        inner = sum(sizes[:-1])
        sizes[-2] += bucket(inner) - inner
    above = sum(sizes[:-1])
    sizes[-1] = bucket(above + sizes[-1]) - above
    return tuple(sizes)


# ----------------------------------------------------------------------------- build


def _slot(ijk: jax.Array, shift) -> jax.Array:
    """Child slot (uint32) of voxel indices [..., 3] at bit `shift`."""
    b = (ijk >> shift) & 1
    return (b[..., 0] | (b[..., 1] << 1) | (b[..., 2] << 2)).astype(jnp.uint32)


def _pack_mask(present: jax.Array) -> jax.Array:
    """[C, 8] bool child presence -> [C] uint8 masks."""
    return jnp.sum(jnp.where(present, jnp.uint8(1) << _SLOTS.astype(np.uint8), 0), axis=1, dtype=jnp.uint8)


def _popcount8(mask: jax.Array) -> jax.Array:
    return jax.lax.population_count(mask.astype(jnp.uint32)).astype(jnp.int32)


def _segments(ijk: jax.Array, n: jax.Array):
    """Groups Morton-sorted cells by parent.

    Args:
      ijk: [C, 3] int32 cells, the first `n` valid, in Morton order.
      n: [] int32.

    Returns:
      (parent [C] int32 index of each cell's parent among the distinct parents,
      first [C] bool whether the cell is the first of its parent, count [] int32 of parents).
    """
    parent_ijk = ijk >> 1
    valid = jnp.arange(ijk.shape[0]) < n
    differs = jnp.any(parent_ijk[1:] != parent_ijk[:-1], axis=1)
    first = valid & jnp.concatenate([jnp.ones(1, bool), differs])
    parent = jnp.cumsum(first, dtype=jnp.int32) - 1
    return parent, first, jnp.sum(first, dtype=jnp.int32)


def _unique_masks(mask: jax.Array, n: jax.Array):
    """Deduplicates uint8 masks (first `n` valid) through a 256-entry table.

    Returns (id [C] int32 of each mask's unique node, table [C] uint8 unique masks in
    increasing order, count [] int32).
    """
    valid = jnp.arange(mask.shape[0]) < n
    present = jnp.zeros(256, jnp.int32).at[jnp.where(valid, mask.astype(jnp.int32), 256)].set(1, mode="drop")
    rank = jnp.cumsum(present) - present
    table = jnp.zeros(mask.shape[0], jnp.uint8).at[jnp.where(present > 0, rank, mask.shape[0])].set(
        jnp.arange(256, dtype=jnp.uint8), mode="drop")
    return rank[mask.astype(jnp.int32)], table, jnp.sum(present)


def _packed_keys(rows: jax.Array, id_bits: int) -> list[jax.Array]:
    """Packs child rows into as few uint32 sort keys as their ids allow.

    Children are ids below ``2^id_bits - 1`` or `EMPTY`, which becomes ``2^id_bits - 1``
    (still the largest value), and are packed first child in the highest bits, so the
    lexicographic order of the keys is that of the rows.

    Args:
      rows: [C, 8] uint32.
      id_bits: static bit width per child (1..32).

    Returns:
      ceil(8 / floor(32 / id_bits)) uint32 [C] keys (2 for ids below 255, 8 above 2^16).
    """
    per_word = 32 // id_bits
    if per_word == 1:
        return [rows[:, s] for s in range(8)]
    top = jnp.uint32((1 << id_bits) - 1)
    small = jnp.where(rows == EMPTY, top, rows)
    keys = []
    for start in range(0, 8, per_word):
        key = jnp.zeros(rows.shape[0], jnp.uint32)
        for s in range(start, min(start + per_word, 8)):
            key = (key << id_bits) | small[:, s]
        keys.append(key)
    return keys


def _unique_rows(rows: jax.Array, n: jax.Array, id_bits: int):
    """Deduplicates child rows (first `n` valid) by a lexicographic sort.

    Args:
      rows: [C, 8] uint32; invalid rows are all `EMPTY` (a valid row never is).
      id_bits: static, child ids are below ``2^id_bits - 1`` (see `_packed_keys`).

    Returns:
      (id [C] int32 of each row's unique node, rep [C] int32 one source row of each
      unique node (in lexicographic order), count [] int32).
    """
    c = rows.shape[0]
    iota = jnp.arange(c, dtype=jnp.int32)
    keys = _packed_keys(rows, id_bits)
    *srt, perm = jax.lax.sort(keys + [iota], num_keys=len(keys))
    differs = jnp.any(jnp.stack([k[1:] != k[:-1] for k in srt]), axis=0)
    first = (iota < n) & jnp.concatenate([jnp.ones(1, bool), differs])
    sid = jnp.cumsum(first, dtype=jnp.int32) - 1
    ids = jnp.zeros(c, jnp.int32).at[perm].set(sid)
    rep = jnp.zeros(c, jnp.int32).at[jnp.where(first, sid, c)].set(perm, mode="drop")
    return ids, rep, jnp.sum(first, dtype=jnp.int32)


class _Level(NamedTuple):
    """One built level (C = its capacity) and what the level above needs from it."""

    mask: jax.Array  # [C] uint8
    child: jax.Array | None  # [C, 8] uint32 rows relative to the next level's start (None at level D - 1)
    prefix: jax.Array | None  # [C, 8] uint32
    count: jax.Array  # [] int32 rows used (after deduplication in a DAG)
    cells: jax.Array  # [C, 3] int32 octree nodes of this level, Morton order (the next step's input)
    n_cells: jax.Array  # [] int32
    cell_counts: jax.Array  # [C] int32 voxels below each octree node
    cell_ids: jax.Array  # [C] int32 stored row of each octree node
    overflow: jax.Array  # [] bool


@functools.partial(jax.jit, static_argnames=("capacity", "dag", "id_bits"))
def _build_level(ijk, n, counts, ids, *, capacity: int, dag: bool, id_bits: int = 32) -> _Level:
    """One bottom-up step: groups the cells of the level below by parent.

    Args:
      ijk: [C', 3] int32 cells of the level below (voxels for level D - 1), the first
        `n` valid, in Morton order.
      counts: [C'] int32 voxels in each cell, or None for voxels.
      ids: [C'] int32 stored row of each cell within its level, or None for voxels.
      capacity: static number of rows of this level.
      dag: static, deduplicate the rows.
      id_bits: static, `ids` are below ``2^id_bits - 1`` (narrower sort keys).
    """
    cap = capacity
    parent, first, n_parent = _segments(ijk, n)
    overflow = n_parent > cap
    n_parent = jnp.minimum(n_parent, cap)
    valid = jnp.arange(ijk.shape[0]) < n
    dest = jnp.where(valid, parent, cap)  # invalid cells go to the dropped slot `cap`
    slot = _slot(ijk, 0)
    cells = jnp.zeros((cap, 3), jnp.int32).at[jnp.where(first, parent, cap)].set(ijk >> 1, mode="drop")
    # `row`: the stored row of each octree node (the DAG maps duplicates to one row).
    row, n_rows, child, prefix = jnp.arange(cap, dtype=jnp.int32), n_parent, None, None
    if counts is None:  # level D - 1: masks only
        present = jnp.zeros((cap, 8), bool).at[dest, slot].set(True, mode="drop")  # repeats stay one bit
        mask = _pack_mask(present)
        cell_counts = _popcount8(mask)
        if dag:
            row, mask, n_rows = _unique_masks(mask, n_parent)
    else:
        child = jnp.full((cap, 8), EMPTY).at[dest, slot].set(ids.astype(jnp.uint32), mode="drop")
        per_slot = jnp.zeros((cap, 8), jnp.int32).at[dest, slot].set(counts, mode="drop")
        cell_counts = per_slot.sum(1)
        if dag:
            row, rep, n_rows = _unique_rows(child, n_parent, id_bits)
            keep = (jnp.arange(cap) < n_rows)[:, None]
            child = jnp.where(keep, child[rep], EMPTY)
            per_slot = jnp.where(keep, per_slot[rep], 0)
        mask = _pack_mask(child != EMPTY)
        prefix = (jnp.cumsum(per_slot, axis=1) - per_slot).astype(jnp.uint32)
    return _Level(mask, child, prefix, n_rows, cells, n_parent, cell_counts, row, overflow)


def _levels(vox: Voxels, capacity: tuple[int, ...], dag: bool) -> list[_Level]:
    """All levels, root first; level ``l`` has `capacity[l]` rows. The DAG's sort keys
    are as narrow as the ids of the level below allow (`key_bits`): below its capacity,
    and below 255 for the mask level."""
    depth = vox.grid.resolution.bit_length() - 1
    ijk, n, counts, ids = vox.coords, jnp.minimum(vox.count, vox.coords.shape[0]), None, None
    levels, below = [], 0
    for level_index in range(depth - 1, -1, -1):
        cap = capacity[level_index]
        level = _build_level(ijk, n, counts, ids, capacity=cap, dag=dag, id_bits=key_bits(below) if dag else 32)
        # Distinct non-empty masks number at most 255, so the level above the masks sorts
        # two packed keys whatever its capacity.
        below = min(cap, 255) if level_index == depth - 1 else cap
        levels.append(level)
        ijk, n, counts, ids = level.cells, level.n_cells, level.cell_counts, level.cell_ids
    return levels[::-1]


def _tree(vox: Voxels, mask, child, prefix, level_count, overflow, capacity, dag) -> Octree:
    return Octree(mask=mask, child=child, prefix=prefix, level_count=level_count,
                  voxel_count=jnp.minimum(vox.count, vox.coords.shape[0]).astype(jnp.int32),
                  overflow=(vox.overflow | jnp.where(overflow, OVERFLOW_NODES, 0)).astype(jnp.int32),
                  grid=vox.grid, level_capacity=jnp.asarray(capacity, jnp.int32), dag=dag, mode=vox.mode)


@functools.partial(jax.jit, static_argnames=("capacity", "dag"))
def _build(vox: Voxels, capacity: tuple[int, ...], dag: bool) -> Octree:
    """Bottom-up build with static per-level capacities, as one jittable function."""
    levels = _levels(vox, capacity, dag)
    offsets = np.cumsum((0,) + tuple(capacity))
    child = [jnp.where(lv.child == EMPTY, EMPTY, lv.child + jnp.uint32(offsets[i + 1]))
             for i, lv in enumerate(levels[:-1])]
    rows = lambda parts: jnp.concatenate(parts) if parts else jnp.zeros((0, 8), jnp.uint32)
    return _tree(vox, jnp.concatenate([lv.mask for lv in levels]), rows(child), rows([lv.prefix for lv in levels[:-1]]),
                 jnp.stack([lv.count for lv in levels]), jnp.any(jnp.stack([lv.overflow for lv in levels])),
                 capacity, dag)


def _schedule(counted) -> tuple[int, ...]:
    """Per-level build capacities from the bottom level's node count alone, so that trees
    of similar size share one compiled build.

    A surface has about a quarter as many nodes per level as the level below (measured
    0.25-0.28 near the bottom on five shared meshes at 128^3 and 1024^3), so level ``D - 1 - k`` gets
    ``bucket(P) / 4^k`` (P: the counted nodes of level D - 1), doubled above the three
    bottom levels where the ratio creeps up; a level counted above that (scattered
    voxels) gets the bucket of its own count. Capped at ``8^l``.
    """
    depth, bottom = len(counted), bucket(int(counted[-1]), 64)
    return tuple(min(8**level, max(bottom >> 2 * k << (k >= 3), bucket(int(n), 64)))
                 for level, (k, n) in enumerate(zip(range(depth - 1, -1, -1), counted)))


def _relayout(tree: Octree, sizes: tuple[int, ...]) -> Octree:
    """Host copy of `tree` with `sizes` rows per level (each at least the level's stored
    rows): every level's nodes move to the new offsets, child pointers follow them and
    the new rows are padding. Host memory copies (numpy), so it compiles nothing."""
    stored = stored_sizes(tree.level_sizes)
    old, new = tree.level_offsets, np.cumsum((0,) + tuple(sizes))
    mask, child, prefix = (np.asarray(a) for a in (tree.mask, tree.child, tree.prefix))
    out_mask = np.zeros(new[-1], np.uint8)
    out_child = np.full((new[-2], 8), EMPTY, np.uint32)
    out_prefix = np.zeros((new[-2], 8), np.uint32)
    for level in range(tree.depth):
        src, dst = slice(old[level], old[level] + stored[level]), slice(new[level], new[level] + stored[level])
        out_mask[dst] = mask[src]
        if level < tree.depth - 1:
            shift = np.int64(new[level + 1]) - np.int64(old[level + 1])
            part = child[src]
            out_child[dst] = np.where(part == EMPTY, EMPTY, (part + shift).astype(np.uint32))
            out_prefix[dst] = prefix[src]
    put = functools.partial(jax.device_put, may_alias=True)
    return dataclasses.replace(tree, mask=put(out_mask), child=put(out_child), prefix=put(out_prefix),
                               level_capacity=jnp.asarray(sizes, jnp.int32))


def _build_padded(vox: Voxels, counted: np.ndarray, dag: bool) -> Octree:
    """Host-side build: one compiled build with the capacities of `_schedule` (which fit
    the counted levels), then the tables laid out on the shape ladder (`padded_sizes`)."""
    capacity = _schedule(counted)
    tree = _build(vox, capacity=capacity, dag=dag)
    if int(tree.overflow):
        raise JaxvoxError(f"internal error: octree levels {list(counted)} overflowed capacities {capacity}")
    return padded(tree)


def padded(tree: Octree) -> Octree:
    """`tree` laid out on the shape ladder (`padded_sizes`), host-side; a tree already
    laid out so is returned as it is."""
    sizes = padded_sizes(tree.level_sizes)
    return tree if sizes == tree.level_capacities else _relayout(tree, sizes)


@functools.partial(jax.jit, static_argnames=("resolution",))
def _survey(coords: jax.Array, count: jax.Array, *, resolution: int):
    """Checks and counts a voxel buffer in one program.

    Returns:
      (in_range [] bool: valid voxels lie in the grid, ordered [] bool: they strictly
      increase in Morton order, sizes [D] int32 octree nodes per level, root first:
      level ``l`` holds the distinct ``ijk >> (D - l)``, consecutive in Morton order).
    """
    valid = jnp.arange(coords.shape[0]) < count
    inside = jnp.all((coords >= 0) & (coords < resolution) | ~valid[:, None])
    hi, lo = morton.encode(jnp.clip(coords, 0, resolution - 1))
    increasing = (hi[1:] > hi[:-1]) | ((hi[1:] == hi[:-1]) & (lo[1:] > lo[:-1]))
    # Consecutive voxels first differ at the highest set bit p of their codes' XOR; they
    # sit in different nodes of level l exactly when l >= D - p // 3.
    x_hi, x_lo = hi[1:] ^ hi[:-1], lo[1:] ^ lo[:-1]
    top = jnp.where(x_hi != 0, 61 - jax.lax.clz(x_hi), 31 - jax.lax.clz(x_lo)).astype(jnp.int32)
    depth = resolution.bit_length() - 1
    first_level = jnp.where(valid[1:] & (top >= 0), depth - top // 3, depth)
    new_nodes = jnp.cumsum(jnp.zeros(depth + 1, jnp.int32).at[first_level].add(1))[:depth]
    sizes = jnp.minimum(count, 1) + new_nodes
    return inside, jnp.all(increasing | ~valid[1:]), sizes


def _check_voxels(caller: str, vox: Voxels) -> np.ndarray:
    """Host-side validation of build input (raises `JaxvoxError` naming `caller`); returns
    the octree's nodes per level (host int [D])."""
    if int(vox.overflow):
        raise JaxvoxError(f"the voxel buffer overflowed (flags {int(vox.overflow)}); "
                          "the tree would be truncated")
    resolution = vox.grid.resolution
    inside, ordered, sizes = jax.device_get(_survey(vox.coords, vox.count, resolution=resolution))
    if not (bool(inside) and bool(ordered)):
        ijk = np.asarray(vox.coords[: int(vox.count)])
        outside = ((ijk < 0) | (ijk >= resolution)).any(1)
        if outside.any():
            raise refuse(f"{caller} vox", f"holds voxel indices outside [0, {resolution})", ijk[outside][0])
        hi, lo = (np.asarray(w).astype(np.int64) for w in morton.encode(ijk))
        codes = (hi << 30) | lo
        first = int(np.flatnonzero(codes[1:] <= codes[:-1])[0])
        raise refuse(f"{caller} vox", "voxels must be unique and in Morton order (build them with "
                     "jaxvox.voxelize or Voxels.from_coords)", ijk[first:first + 2])
    return sizes


def check_level_capacities(what: str, capacities, depth: int) -> tuple[int, ...]:
    """`capacities` as `depth` Python ints >= 0, one per octree level (root first, 1 for the
    root); raises `JaxvoxError` naming `what` otherwise."""
    try:
        caps = tuple(capacities)
    except TypeError:
        raise refuse(what, f"must be {depth} integers", capacities) from None
    caps = tuple(check_int(f"{what}[{level}]", c, minimum=0) for level, c in enumerate(caps))
    if len(caps) != depth or caps[0] != 1:
        raise refuse(what, f"must be {depth} integers >= 0, one per level, root first, with 1 for the root", caps)
    return caps


def _build_host(caller: str, vox: Voxels, capacities, dag: bool) -> Octree:
    check_type(f"{caller} vox", vox, Voxels)
    if capacities is not None:
        depth = vox.grid.resolution.bit_length() - 1
        return _build(vox, capacity=check_level_capacities(f"{caller} capacities", capacities, depth), dag=dag)
    return _build_padded(vox, _check_voxels(caller, vox), dag)


def build_octree(vox: Voxels, *, capacities: tuple[int, ...] | None = None) -> Octree:
    """Builds the sparse voxel octree of a voxel set, bottom-up from Morton order.

    Without `capacities` (host-side use) the input is checked (no overflow, indices in
    range, unique and Morton-sorted), one compiled build sized from the voxel buffer's
    length runs (a counting pass checks that every level fits) and the result is laid out
    on the shape ladder (see `Octree`; `compact` drops the padding). With `capacities` the build is a pure function of static shape, usable inside
    `jax.jit` and `jax.vmap`: a level with more nodes than its capacity sets
    `OVERFLOW_NODES` in ``tree.overflow`` and the tree is truncated.

    Args:
      vox: `Voxels` (unique, Morton-sorted, as `jaxvox.voxelize` returns them).
      capacities: static per-level node capacities, D ints (root level first, 1 for the
        root), or None.

    Returns:
      An `Octree` with ``dag=False`` whose nodes are in Morton order within each level.

    Raises:
      JaxvoxError: not `Voxels`, `capacities` that are not D integers >= 0 with 1 for the
        root; without `capacities`, an overflowed voxel buffer, indices outside the grid,
        or voxels that are not unique and Morton-sorted.
    """
    return _build_host("build_octree", vox, capacities, dag=False)


def build_dag(vox: Voxels, *, capacities: tuple[int, ...] | None = None) -> Octree:
    """Builds the sparse voxel DAG: the octree with identical subtrees stored once.

    Deduplication runs bottom-up during the build (see the module docstring), so the
    octree is never stored. `capacities` bound the *octree's* node counts per level (the
    rows deduplicated at each level); the host-side path sizes them as `build_octree`
    does and lays the result out on the ladder from the DAG's own sizes. Same contract as `build_octree`.

    Returns:
      An `Octree` with ``dag=True``; canonical (the same voxel set gives the same arrays).

    Raises:
      JaxvoxError: as `build_octree`.
    """
    return _build_host("build_dag", vox, capacities, dag=True)


def compact(tree: Octree) -> Octree:
    """Drops padding rows so that ``level_capacity == level_sizes`` (host-side).

    Child rows are absolute, so each level's pointers shift by the change of its target
    level's offset. The work is host memory copies (numpy), so it compiles nothing.

    Raises:
      JaxvoxError: not an `Octree`.
    """
    check_type("compact tree", tree, Octree)
    sizes = stored_sizes(tree.level_sizes)
    return tree if sizes == tree.level_capacities else _relayout(tree, sizes)


# ----------------------------------------------------------------------------- queries


def voxel_index(tree: Octree, ijk: jax.Array) -> jax.Array:
    """Morton-order index of each voxel in the tree, `MISSING` (-1) where empty.

    A root-to-leaf walk adding the stored prefix sums; the index addresses attribute
    arrays in the order of ``expand(tree)`` (and of the source `Voxels`). Pure and
    jittable; indices outside the grid give -1.

    Args:
      tree: an `Octree` (SVO or DAG).
      ijk: [..., 3] integer voxel indices. JAX holds them as int32 (without 64-bit
        mode it converts wider integers on entry, wrapping values beyond 2^31).

    Returns:
      [...] int32.

    Raises:
      JaxvoxError: not an `Octree`, or `ijk` is not an integer array with a last axis of 3.
    """
    check_type("voxel_index tree", tree, Octree)
    dtype = ijk.dtype if hasattr(ijk, "dtype") else np.asarray(ijk).dtype
    if not jnp.issubdtype(dtype, jnp.integer) or np.shape(ijk)[-1:] != (3,):
        raise refuse("voxel_index ijk", "must be integer indices [..., 3]",
                     ijk if jnp.issubdtype(dtype, jnp.integer) else f"{dtype} indices of shape {np.shape(ijk)}")
    return _voxel_index(tree, ijk)


@jax.jit
def _voxel_index(tree: Octree, ijk: jax.Array) -> jax.Array:
    ijk = jnp.asarray(ijk).astype(jnp.int32)
    depth = tree.depth
    alive = jnp.all((ijk >= 0) & (ijk < tree.grid.resolution), axis=-1) & (tree.voxel_count > 0)
    node = jnp.zeros(ijk.shape[:-1], jnp.int32)
    index = jnp.zeros(ijk.shape[:-1], jnp.int32)

    def step(level, state):
        node, index, alive = state
        slot = _slot(ijk, depth - 1 - level).astype(jnp.int32)
        index += jnp.where(alive, tree.prefix[node, slot].astype(jnp.int32), 0)
        nxt = tree.child[node, slot]
        alive &= nxt != EMPTY
        return jnp.where(alive, nxt, 0).astype(jnp.int32), index, alive

    if depth > 1:
        node, index, alive = jax.lax.fori_loop(0, depth - 1, step, (node, index, alive))
    slot = _slot(ijk, 0)
    mask = tree.mask[node].astype(jnp.uint32)
    alive &= ((mask >> slot) & 1) == 1
    index += _popcount8(mask & ((jnp.uint32(1) << slot) - 1))
    return jnp.where(alive, index, MISSING)


@functools.partial(jax.jit, static_argnames=("depth", "capacity"))
def _expand_nodes(mask, child, voxel_count, *, depth: int, capacity: int):
    """Top-down expansion of node tables; returns (coords [capacity, 3] int32, count).

    Takes the tables rather than the `Octree`, so trees of equal (padded) table sizes
    share one compiled program whatever their level sizes.
    """
    node = jnp.zeros(1, jnp.int32)  # absolute row of each node instance
    ijk = jnp.zeros((1, 3), jnp.int32)
    n = (voxel_count > 0).astype(jnp.int32)
    select = jnp.asarray(_SELECT)
    for level in range(depth):
        cap = min(capacity, 8 ** (level + 1))
        m = mask[node]
        live = jnp.arange(node.shape[0]) < n
        owner, rank, valid, n = expand_counts(jnp.where(live, _popcount8(m), 0), cap)
        slot = select[m[owner].astype(jnp.int32), jnp.minimum(rank, 7)].astype(jnp.int32)
        ijk = 2 * ijk[owner] + ((slot[:, None] >> jnp.arange(3)) & 1)
        if level < depth - 1:
            node = jnp.where(valid, child[node[owner], slot].astype(jnp.int32), 0)
    n = jnp.minimum(n, capacity)
    return jnp.where((jnp.arange(ijk.shape[0]) < n)[:, None], ijk, UNUSED), n


def expand(tree: Octree, *, capacity: int | None = None) -> Voxels:
    """The voxels of a tree, in Morton order (the inverse of the builds).

    A top-down pass per level: every node instance emits its children in slot order,
    so the output is Morton-sorted without a sort. Without `capacity` (host-side) the
    buffer is sized by ``tree.voxel_count`` (and a tree not yet on the shape ladder is
    laid out on it, `padded`, so that similar trees share a compiled program); with a static `capacity` it is
    jittable, and a tree with more voxels sets `OVERFLOW_NODES` in the result's
    ``overflow``.

    Returns:
      `Voxels` (``triangle`` is None; attributes stay in their own arrays).

    Raises:
      JaxvoxError: not an `Octree`, a `capacity` that is not an integer >= 1, or (host
        side) a truncated tree.
    """
    check_type("expand tree", tree, Octree)
    if capacity is not None:
        capacity = check_int("expand capacity", capacity, minimum=1)
    if capacity is None:
        if int(tree.overflow):
            raise JaxvoxError(f"the tree is truncated (overflow flags {int(tree.overflow)})")
        capacity = bucket(int(tree.voxel_count))
        tree = padded(tree)
    coords, n = _expand_nodes(tree.mask, tree.child, tree.voxel_count, depth=tree.depth, capacity=int(capacity))
    overflow = tree.overflow | jnp.where(tree.voxel_count > capacity, OVERFLOW_NODES, 0)
    return Voxels(coords, n, overflow.astype(jnp.int32), None, tree.grid, tree.mode)


# ----------------------------------------------------------------------------- attributes


def voxel_attributes(mesh: Mesh, vox: Voxels) -> dict[str, jax.Array]:
    """Per-voxel attributes from the triangle that set each voxel, in Morton order.

    Args:
      mesh: the mesh the voxels came from.
      vox: `Voxels` from ``jaxvox.voxelize(..., triangle_ids=True)``.

    Returns:
      A dict of arrays over the voxel buffer's slots (``[capacity, ...]``; slots past
      ``vox.count`` are zero or -1), to be indexed by `voxel_index`:

      * ``"triangle"``: int32 [capacity] triangle id (-1 in unused slots);
      * ``"normal"``: float32 [capacity, 3] unit face normal (0 for degenerate faces);
      * ``"color"``: float32 [capacity, C], only when the mesh has a texture or vertex
        colours: the texture (`sample_texture` at the interpolated texture coordinates)
        or the vertex colours, interpolated at the point of the triangle's plane nearest
        the voxel centre (barycentric weights clipped to the triangle).

    Raises:
      JaxvoxError: a malformed mesh, not `Voxels`, or voxels without triangle ids.
    """
    validate_mesh(mesh)
    check_type("voxel_attributes vox", vox, Voxels)
    if vox.triangle is None:
        raise refuse("voxel_attributes vox.triangle", "must hold triangle ids (voxelize with triangle_ids=True)",
                     vox.triangle)
    # Padded to the shape ladder, so that meshes of similar size share the program.
    return _attributes(pad_mesh(mesh, bucket(mesh.num_vertices), bucket(mesh.num_faces)), vox)


@jax.jit
def _attributes(mesh: Mesh, vox: Voxels) -> dict[str, jax.Array]:
    valid = jnp.arange(vox.coords.shape[0]) < vox.count
    tri = jnp.where(valid, vox.triangle, 0)
    corners = mesh.vertices[mesh.faces[tri]]  # [C, 3, 3]
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    normal = jnp.cross(e1, e2)
    length = jnp.linalg.norm(normal, axis=-1, keepdims=True)
    unit = jnp.where(length > 0, normal / jnp.where(length > 0, length, 1.0), 0.0)
    out = {"triangle": jnp.where(valid, vox.triangle, -1), "normal": jnp.where(valid[:, None], unit, 0.0)}
    if mesh.texture is not None or mesh.colors is not None:
        centre = vox.grid.origin + (vox.coords.astype(jnp.float32) + 0.5) * vox.grid.voxel_size
        weights = _barycentric(corners, centre, normal)
        if mesh.texture is not None:
            colour = sample_texture(mesh.texture, jnp.einsum("ck,ckd->cd", weights, mesh.uvs[mesh.faces[tri]]))
        else:
            colour = jnp.einsum("ck,ckd->cd", weights, mesh.colors[mesh.faces[tri]])
        out["color"] = jnp.where(valid[:, None], colour, 0.0)
    return out


def _barycentric(corners, point, normal):
    """Clipped barycentric weights [C, 3] of `point` projected onto each triangle's plane."""
    area2 = jnp.sum(normal * normal, axis=-1)
    safe = jnp.where(area2 > 0, area2, 1.0)
    sub = lambda a, b: jnp.sum(jnp.cross(corners[:, b] - point, corners[:, a] - point) * normal, -1)
    w = jnp.stack([sub(2, 1), sub(0, 2), sub(1, 0)], axis=-1) / safe[:, None]
    w = jnp.where(area2[:, None] > 0, jnp.clip(w, 0.0, None), 1.0)
    return w / jnp.sum(w, axis=-1, keepdims=True)
