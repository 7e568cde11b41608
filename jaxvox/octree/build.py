"""Bottom-up builds of octrees and DAGs (see `jaxvox.octree`): the jittable build with
static capacities (one segment pass per level from Morton-sorted voxels, DAG
deduplication by a lexicographic sort of child rows), the host-side checks and counting
pass (`_checked_codes`, `level_sizes`) and capacity schedule (`_schedule`), and the
public `build_octree`, `build_dag`, `octree_capacities` and `check_level_capacities`.
Without capacities the build runs in numpy (`jaxvox.octree.host`), table for table the
same, and compiles nothing."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox import morton
from jaxvox._core.checks import check_int, check_type, refuse
from jaxvox._core.shapes import bucket, key_bits
from jaxvox.octree.host import tree_from_levels, voxel_levels
from jaxvox.octree.tree import EMPTY, OVERFLOW_NODES, SLOTS, Octree, child_slot, popcount8
from jaxvox.overflow import check_overflow, raise_if_overflow
from jaxvox.voxelize import Voxels


def _pack_mask(present: jax.Array) -> jax.Array:
    """[C, 8] bool child presence -> [C] uint8 masks."""
    return jnp.sum(jnp.where(present, jnp.uint8(1) << SLOTS.astype(np.uint8), 0), axis=1, dtype=jnp.uint8)


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
    table = (
        jnp.zeros(mask.shape[0], jnp.uint8)
        .at[jnp.where(present > 0, rank, mask.shape[0])]
        .set(jnp.arange(256, dtype=jnp.uint8), mode="drop")
    )
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
    count: jax.Array  # type: ignore[assignment]  # [] int32 rows used (after deduplication in a DAG)
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
    slot = child_slot(ijk, 0)
    cells = jnp.zeros((cap, 3), jnp.int32).at[jnp.where(first, parent, cap)].set(ijk >> 1, mode="drop")
    # `row`: the stored row of each octree node (the DAG maps duplicates to one row).
    row, n_rows, child, prefix = jnp.arange(cap, dtype=jnp.int32), n_parent, None, None
    if counts is None:  # level D - 1: masks only
        present = jnp.zeros((cap, 8), bool).at[dest, slot].set(True, mode="drop")  # repeats stay one bit
        mask = _pack_mask(present)
        cell_counts = popcount8(mask)
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
    return Octree(
        mask=mask,
        child=child,
        prefix=prefix,
        level_count=level_count,
        voxel_count=jnp.minimum(vox.count, vox.coords.shape[0]).astype(jnp.uint32),
        overflow=(vox.overflow | jnp.where(overflow, OVERFLOW_NODES, 0)).astype(jnp.int32),
        grid=vox.grid,
        level_capacity=jnp.asarray(capacity, jnp.int32),
        dag=dag,
        mode=vox.mode,
    )


@functools.partial(jax.jit, static_argnames=("capacity", "dag"))
def _build(vox: Voxels, capacity: tuple[int, ...], dag: bool) -> Octree:
    """Bottom-up build with static per-level capacities, as one jittable function."""
    levels = _levels(vox, capacity, dag)
    offsets = np.cumsum((0,) + tuple(capacity))
    child = [
        jnp.where(lv.child == EMPTY, EMPTY, lv.child + jnp.uint32(offsets[i + 1])) for i, lv in enumerate(levels[:-1])
    ]
    rows = lambda parts: jnp.concatenate(parts) if parts else jnp.zeros((0, 8), jnp.uint32)
    return _tree(
        vox,
        jnp.concatenate([lv.mask for lv in levels]),
        rows(child),
        rows([lv.prefix for lv in levels[:-1]]),
        jnp.stack([lv.count for lv in levels]),
        jnp.any(jnp.stack([lv.overflow for lv in levels])),
        capacity,
        dag,
    )


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
    return tuple(
        min(8**level, max(bottom >> 2 * k << (k >= 3), bucket(int(n), 64)))
        for level, (k, n) in enumerate(zip(range(depth - 1, -1, -1), counted))
    )


def _bit_length(x: np.ndarray) -> np.ndarray:
    """int64 [n] bit lengths of uint64 [n] values (exact: 32-bit halves through frexp)."""
    hi, lo = (x >> np.uint64(32)).astype(np.float64), (x & np.uint64(0xFFFFFFFF)).astype(np.float64)
    return np.where(hi > 0, 32 + np.frexp(hi)[1], np.frexp(lo)[1]).astype(np.int64)


def _checked_codes(caller: str, vox: Voxels) -> np.ndarray:
    """Host-side validation of build input, in numpy (so that a new voxel count compiles
    nothing); raises `JaxvoxError` naming `caller`.

    Returns:
      uint64 [V] Morton codes of the valid voxels, strictly increasing.
    """
    check_overflow(f"{caller} vox", vox.overflow, "the tree would be truncated; use jaxvox.voxelize")
    resolution = vox.grid.resolution
    ijk = np.asarray(vox.coords)[: min(int(vox.count), vox.coords.shape[0])]
    if ijk.size and (ijk.min() < 0 or ijk.max() >= resolution):  # (two reductions, no [V, 3] masks)
        outside = ((ijk < 0) | (ijk >= resolution)).any(1)
        raise refuse(f"{caller} vox", f"holds voxel indices outside [0, {resolution})", ijk[outside][0])
    codes = morton.encode_host(ijk)
    if (codes[1:] <= codes[:-1]).any():
        first = int(np.flatnonzero(codes[1:] <= codes[:-1])[0])
        raise refuse(
            f"{caller} vox",
            "voxels must be unique and in Morton order (build them with jaxvox.voxelize or Voxels.from_coords)",
            ijk[first : first + 2],
        )
    return codes


def level_sizes(codes: np.ndarray, depth: int) -> np.ndarray:
    """Host int64 [D] octree nodes per level, root first, of voxels with increasing Morton
    codes [V] uint64: level ``l`` holds the distinct ``code >> 3 (D - l)``. Shared by
    `octree_capacities` and `jaxvox.batch.batch_capacities`."""
    # Consecutive voxels first differ at the highest set bit p of their codes' XOR; they
    # sit in different nodes of level l exactly when l >= D - p // 3.
    first_level = depth - (_bit_length(codes[1:] ^ codes[:-1]) - 1) // 3
    return min(len(codes), 1) + np.cumsum(np.bincount(first_level, minlength=depth + 1))[:depth]


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


def _build_host(caller: str, vox: Voxels, capacities, dag: bool, checked: bool) -> Octree:
    check_type(f"{caller} vox", vox, Voxels)
    depth = vox.grid.resolution.bit_length() - 1
    if capacities is not None:
        tree = _build(vox, capacity=check_level_capacities(f"{caller} capacities", capacities, depth), dag=dag)
        if checked:
            raise_if_overflow(f"{caller} result", tree.overflow)
        return tree
    codes = _checked_codes(caller, vox)
    levels, _ = voxel_levels(codes, depth, dag)
    return tree_from_levels(levels, vox.grid, vox.mode, len(codes), dag)


def octree_capacities(vox: Voxels) -> tuple[int, ...]:
    """Per-level node capacities with which `build_octree` / `build_dag` (``capacities=``)
    do not overflow for these voxels: the counted octree levels rounded up to the shape
    ladder (host-side counting pass in numpy, no compiled program).

    Returns:
      D Python ints, root level first (1 for the root).

    Raises:
      JaxvoxError: not `Voxels`, an overflowed voxel buffer, indices outside the grid, or
        voxels that are not unique and Morton-sorted.
    """
    check_type("octree_capacities vox", vox, Voxels)
    depth = vox.grid.resolution.bit_length() - 1
    return _schedule(level_sizes(_checked_codes("octree_capacities", vox), depth))


def build_octree(vox: Voxels, *, capacities: tuple[int, ...] | None = None, checked: bool = False) -> Octree:
    """Builds the sparse voxel octree of a voxel set, bottom-up from Morton order.

    Without `capacities` (host-side use) the input is checked (no overflow, indices in
    range, unique and Morton-sorted), the tree is built in numpy (`jaxvox.octree.host`:
    the same tables as the jittable build, and no program to compile for a new size)
    and laid out on the shape ladder (see `Octree`; `compact` drops the padding). With `capacities` the
    build is a pure function of static shape, usable inside `jax.jit` and `jax.vmap`: a
    level with more nodes than its capacity sets `OVERFLOW_NODES` in ``tree.overflow`` and
    the tree is truncated.

    Args:
      vox: `Voxels` (unique, Morton-sorted, as `jaxvox.voxelize` returns them).
      capacities: static per-level node capacities, D ints (root level first, 1 for the
        root; `octree_capacities` gives ones that fit), or None.
      checked: with `capacities`, raise (as an error of the running computation) instead
        of returning a truncated tree when a level overflows.

    Returns:
      An `Octree` with ``dag=False`` whose nodes are in Morton order within each level.

    Raises:
      JaxvoxError: not `Voxels`, `capacities` that are not D integers >= 0 with 1 for the
        root; without `capacities`, an overflowed voxel buffer, indices outside the grid,
        or voxels that are not unique and Morton-sorted.
    """
    return _build_host("build_octree", vox, capacities, dag=False, checked=checked)


def build_dag(vox: Voxels, *, capacities: tuple[int, ...] | None = None, checked: bool = False) -> Octree:
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
    return _build_host("build_dag", vox, capacities, dag=True, checked=checked)
