"""The `Octree` pytree (node tables, see `jaxvox.octree`), its sentinels and the per-level
row counts of compact and ladder-padded trees; child-slot helpers shared by the builds and
the queries."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int32, UInt8, UInt32

from jaxvox import morton
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.shapes import row_bucket
from jaxvox.grid import Grid
from jaxvox.overflow import Overflow

EMPTY = morton.EMPTY  # uint32 0xFFFFFFFF: an absent child (no node has that row index)
OVERFLOW_NODES = Overflow.NODES  # bit of `Octree.overflow`: a level held more nodes than its capacity
MISSING = -1  # `voxel_index` of an empty voxel
MAX_INDEXED = 2**31 - 1  # voxels an int32 Morton index addresses (`voxel_index`, `Hit.index`)

SLOTS = np.arange(8)  # child slots, slot = x | y << 1 | z << 2


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Octree:
    """A sparse voxel octree (``dag=False``) or DAG (``dag=True``) in fixed-size tables.

    Rows past ``level_count[l]`` within level ``l`` are padding (mask 0, children
    `EMPTY`, prefix 0). Trees returned by `build_octree` / `build_dag` without explicit
    capacities (and by `load`) are padded to the shape ladder: every level holds
    exactly its nodes (the root row always exists) except the last two, which take the
    padding rows that bring `child`/`prefix` and `mask` to power-of-two lengths (at most
    twice their rows, four times for the one-byte masks, or the resolution's floor of
    R^2 rows up to 1024^3, at most 2^18: `jaxvox._core.shapes.row_bucket`). Trees of similar size so share
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
      voxel_count: [] uint32 voxels in the tree (up to 2^32 - 1; Morton indices, which
        are int32, address the first `MAX_INDEXED` of them).
      overflow: [] int32 bitmask: the source voxels' ``OVERFLOW_*`` flags and
        `OVERFLOW_NODES`; nonzero means the tree is truncated.
      grid: the `Grid` the tree covers.
      level_capacity: [D] int32 rows reserved per level (host tuple: `level_capacities`).
      dag: static bool, whether identical subtrees are shared.
      mode: static str, the voxelization mode of the source voxels.
    """

    mask: UInt8[Array, "*batch N"]  # [N] uint8
    child: UInt32[Array, "*batch M 8"]  # [M, 8] uint32
    prefix: UInt32[Array, "*batch M 8"]  # [M, 8] uint32
    level_count: Int32[Array, "*batch D"]  # [D] int32
    voxel_count: UInt32[Array, " *batch"]  # [] uint32
    overflow: Int32[Array, " *batch"]  # [] int32
    grid: Grid
    level_capacity: Int32[Array, "*batch D"]  # [D] int32
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
    resolution = 1 << len(sizes)
    if len(sizes) > 1:
        inner = sum(sizes[:-1])
        sizes[-2] += row_bucket(inner, resolution) - inner
    above = sum(sizes[:-1])
    sizes[-1] = row_bucket(above + sizes[-1], resolution) - above
    return tuple(sizes)


def child_slot(ijk: jax.Array, shift) -> jax.Array:
    """Child slot (uint32) of voxel indices [..., 3] at bit `shift`."""
    b = (ijk >> shift) & 1
    return (b[..., 0] | (b[..., 1] << 1) | (b[..., 2] << 2)).astype(jnp.uint32)


def popcount8(mask: jax.Array) -> jax.Array:
    """Set bits of uint8 masks, as int32."""
    return jax.lax.population_count(mask.astype(jnp.uint32)).astype(jnp.int32)
