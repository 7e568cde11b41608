"""The host-side octree/DAG build in numpy: the levels of `build_octree` / `build_dag`
without capacities, and of `mesh_to_dag` (`jaxvox.octree.stream`).

The jittable build (`jaxvox.octree.build`) needs static capacities, so every new size
of tree compiles it again. The host path knows its
sizes, so it runs the same algorithm in numpy, which compiles nothing and whose sorts
are faster than XLA's on the CPU: Morton-sorted codes are grouped by parent one
level at a time, bottom-up; a DAG keeps the sorted distinct masks of level D - 1 and the
lexicographically sorted distinct child rows (`EMPTY` last) above it, exactly the
canonical order of `jaxvox.octree.build._build`, table for table (checked in the tests).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import numpy as np

from jaxvox.grid import Grid
from jaxvox.octree.tree import EMPTY, Octree, padded_sizes

# One level's tables: mask [n] uint8, child [n, 8] uint32 rows within the level below
# (`EMPTY` where absent) and prefix [n, 8] uint32; child and prefix are None at level D - 1.
Level = tuple[np.ndarray, np.ndarray | None, np.ndarray | None]


class Nodes(NamedTuple):
    """The nodes of one octree level, what the level above is built from."""

    cells: np.ndarray  # [k] uint64 Morton codes of the nodes at their level's resolution, increasing
    counts: np.ndarray  # [k] int64 voxels below each node
    ids: np.ndarray  # [k] int64 stored row of each node within its level
    rows: int  # rows stored at that level (ids are below it)


def unique_rows(rows: np.ndarray, bound: int) -> tuple[np.ndarray, np.ndarray]:
    """Distinct child rows in lexicographic order (`EMPTY` largest), as the jittable
    build's `_unique_rows` orders them.

    Children below `bound` or `EMPTY` (which becomes ``2^bits - 1``, still the largest)
    are packed first child in the highest bits into uint64 keys, so the keys' order is
    the rows'. Identical rows are identical subtrees, so any of them represents them.

    Args:
      rows: [n, 8] uint32.
      bound: children are below it (or `EMPTY`).

    Returns:
      (rep [u] int64 one source row of each distinct row, in lexicographic order,
      inverse [n] int64 the distinct row of each row).
    """
    bits = max(1, int(bound).bit_length())
    per_word, top = 64 // bits, np.uint64((1 << bits) - 1)
    keys = []
    for start in range(0, 8, per_word):
        key = np.zeros(len(rows), np.uint64)
        for s in range(start, min(start + per_word, 8)):
            key <<= np.uint64(bits)
            key |= np.minimum(rows[:, s], top)  # EMPTY, the largest uint32, becomes top (>= bound)
        keys.append(key)
    # One key (ids below 255, the common case) takes numpy's vectorized sort.
    order = np.argsort(keys[0]) if len(keys) == 1 else np.lexsort(keys[::-1])  # the last key is the primary one
    first = np.ones(len(rows), bool)
    if len(rows) > 1:
        ordered = [k[order] for k in keys]
        first[1:] = functools.reduce(np.logical_or, [k[1:] != k[:-1] for k in ordered])
    inverse = np.empty(len(rows), np.int64)
    inverse[order] = np.cumsum(first) - 1
    return order[first], inverse


def _parents(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Groups increasing codes by parent: (parent codes [p] uint64, first [k] bool whether
    each cell is its parent's first child, starts [p] index of each parent's first child)."""
    parent = cells >> np.uint64(3)
    first = np.ones(len(cells), bool)
    np.not_equal(parent[1:], parent[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    return parent[starts], first, starts


def mask_level(codes: np.ndarray, dag: bool) -> tuple[Level, Nodes]:
    """Level D - 1 from voxel Morton codes [V] uint64 (increasing): the masks (a DAG keeps
    the sorted distinct ones) and its nodes."""
    cells, _, starts = _parents(codes)
    slot = codes.astype(np.uint8)  # (the low byte; its 3 low bits are the slot)
    slot &= np.uint8(7)
    bits = np.left_shift(np.uint8(1), slot)
    mask = np.bitwise_or.reduceat(bits, starts) if len(codes) else np.zeros(0, np.uint8)
    counts = np.bitwise_count(mask).astype(np.int64)
    table: np.ndarray
    ids: np.ndarray
    if dag:  # at most 256 distinct masks: a table, not a sort
        present = np.bincount(mask, minlength=256) > 0
        rank: np.ndarray = np.cumsum(present) - present
        table, ids = np.flatnonzero(present).astype(np.uint8), rank[mask]
    else:
        table, ids = mask, np.arange(len(mask))
    return (table, None, None), Nodes(cells, counts, ids, len(table))


def row_level(below: Nodes, dag: bool) -> tuple[Level, Nodes]:
    """The level above `below`: each parent's child row and prefix sums (a DAG keeps the
    distinct rows in lexicographic order) and its nodes."""
    cells, first, starts = _parents(below.cells)
    at = np.cumsum(first) - 1  # each cell's parent, then its entry in the flat [parents * 8] rows
    at <<= 3
    at |= (below.cells & np.uint64(7)).astype(np.int64)
    child = np.full((len(cells), 8), EMPTY, np.uint32)
    child.reshape(-1)[at] = below.ids
    # uint32: a tree holds at most 2^32 - 1 voxels (`jaxvox.octree.stream.MAX_VOXELS`), and
    # the prefix sums are stored as uint32 anyway; half the fresh memory of int64 rows
    per_slot = np.zeros((len(cells), 8), np.uint32)
    per_slot.reshape(-1)[at] = below.counts
    counts = np.add.reduceat(below.counts, starts) if len(starts) else np.zeros(0, np.int64)  # children in order
    if dag:
        rep, ids = unique_rows(child, below.rows)
        child, per_slot = child[rep], per_slot[rep]
    else:
        ids = np.arange(len(cells))
    mask = np.packbits(child != EMPTY, axis=1, bitorder="little")[:, 0]
    prefix = np.cumsum(per_slot, axis=1, dtype=np.uint32)
    prefix -= per_slot
    return (mask, child, prefix), Nodes(cells, counts, ids, len(child))


def levels_above(nodes: Nodes, levels: int, dag: bool) -> list[Level]:
    """The `levels` levels above `nodes`, root first."""
    out = []
    for _ in range(levels):
        level, nodes = row_level(nodes, dag)
        out.append(level)
    return out[::-1]


def voxel_levels(codes: np.ndarray, depth: int, dag: bool) -> tuple[list[Level], Nodes]:
    """All `depth` levels of the tree of voxels with Morton codes [V] uint64 (unique,
    increasing), root first, and the nodes of the top level built (the root's, one)."""
    level, nodes = mask_level(codes, dag)
    out = [level]
    for _ in range(depth - 1):
        level, nodes = row_level(nodes, dag)
        out.append(level)
    return out[::-1], nodes


def tree_from_levels(levels: list, grid: Grid, mode: str, voxels: int, dag: bool) -> Octree:
    """The tree of `levels` (`Level` tables, root first; each entry is set to None once
    copied, so the tables are not held twice) laid out on the shape ladder, as
    `build_octree` / `build_dag` return it."""
    sizes = tuple(len(m) for m, _, _ in levels)
    capacity = padded_sizes(sizes)
    offsets = np.cumsum((0,) + capacity)
    mask = np.zeros(offsets[-1], np.uint8)
    child = np.full((offsets[-2], 8), EMPTY, np.uint32)
    prefix = np.zeros((offsets[-2], 8), np.uint32)
    for level, (m, c, p) in enumerate(levels):
        rows = slice(offsets[level], offsets[level] + len(m))
        mask[rows] = m
        if c is not None:
            shift = np.uint32(offsets[level + 1])
            child[rows] = np.where(c == EMPTY, EMPTY, c + shift)
            prefix[rows] = p
        levels[level] = None  # dropped as copied
    put = functools.partial(jax.device_put, may_alias=True)
    return Octree(
        mask=put(mask),
        child=put(child),
        prefix=put(prefix),
        level_count=put(np.asarray(sizes, np.int32)),
        voxel_count=jax.device_put(np.uint32(voxels)),
        overflow=jax.device_put(np.int32(0)),
        grid=grid,
        level_capacity=put(np.asarray(capacity, np.int32)),
        dag=dag,
        mode=mode,
    )
