"""`CompactDag`: an octree or DAG with the empty child slots dropped (a mask header and one
pointer per present child, found by popcount), which `trace`, `render` and `voxel_index`
read as they read an `Octree`; `compact_dag` converts one.

Layout, one uint32 array ``words`` (Kampe et al.'s SVDAG layout, with the mask-only level
folded into its parents). A node above level ``D - 1`` at word offset ``o`` with mask
``m`` (``c = popcount(m)`` children) is

* ``words[o]``: the mask (bits 0-7; the other bits are 0);
* ``words[o + 1 + k]``, ``k < c``: its ``k``-th present child in slot order. A child
  above level ``D - 1`` is its word offset; a child at level ``D - 1`` (whose children
  are voxels) is its own 8-bit mask, so that level is never stored: a DAG has at most
  255 distinct such nodes, and storing the mask costs no more than a pointer to it;
* with prefix sums, ``words[o + c + k]``, ``1 <= k < c``: the voxels in the children
  before the ``k``-th (the first child's is always 0, so it is not stored).

The root is at offset 0; ``root`` holds it (or, for a depth-1 tree, the root's mask).
Child ``s`` of a node is present when bit ``s`` of its mask is set, and is its
``popcount(m & ((1 << s) - 1))``-th child. ``words`` is padded with zeros to the shape
ladder (`jaxvox._core.shapes.bucket`), so trees of similar size share compiled consumers.
Without prefix sums the layout is smaller but cannot address attributes: `voxel_index`
refuses it and `trace` leaves ``Hit.index`` at -1 (`MISSING`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int32, UInt32

from jaxvox._core.checks import check_type
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.shapes import bucket
from jaxvox.grid import Grid
from jaxvox.octree.tree import EMPTY, Octree, child_slot, stored_sizes

_POPCOUNT = np.array([bin(m).count("1") for m in range(256)], np.uint8)  # set bits per mask
_BLOCK = 1 << 20  # rows converted at once


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class CompactDag:
    """An octree or DAG in the pointer-per-present-child layout of `jaxvox.octree.compact_dag`.

    Attributes:
      words: [W] uint32 nodes above level ``D - 1`` (see the module docstring), padded
        with zeros to a power of two.
      root: [] uint32 word offset of the root (0), or the root's mask when ``D == 1``.
      word_count: [] int32 words in use (the rest is padding).
      level_count: [D] int32 nodes per level of the source tree.
      voxel_count: [] uint32 voxels in the tree.
      overflow: [] int32 the source tree's overflow flags.
      grid: the `Grid` the tree covers.
      prefix: static bool, whether per-child prefix sums are stored (needed by
        `voxel_index` and by attributes).
      dag: static bool, whether the source was a DAG.
      mode: static str, the voxelization mode of the source voxels.
    """

    words: UInt32[Array, " W"]
    root: UInt32[Array, ""]
    word_count: Int32[Array, ""]
    level_count: Int32[Array, " D"]
    voxel_count: UInt32[Array, ""]
    overflow: Int32[Array, ""]
    grid: Grid
    prefix: bool = dataclasses.field(metadata=dict(static=True))
    dag: bool = dataclasses.field(metadata=dict(static=True))
    mode: str = dataclasses.field(metadata=dict(static=True))

    @property
    def depth(self) -> int:
        """Number of node levels D = log2(resolution)."""
        return self.grid.resolution.bit_length() - 1

    @property
    def level_sizes(self) -> tuple[int, ...]:
        """Nodes per level of the source tree (host ints), root level first."""
        return tuple(int(n) for n in np.asarray(self.level_count))

    @property
    def nbytes(self) -> int:
        """Bytes of the words in use (4 per word; the ladder padding is not counted)."""
        return 4 * int(self.word_count)


def compact_dag(tree: Octree, *, prefix: bool = True) -> CompactDag:
    """`tree` (SVO or DAG) in the pointer-per-present-child layout (host-side numpy, no compiles).

    Args:
      tree: an `Octree` from `build_octree`, `build_dag`, `mesh_to_dag` or `load`.
      prefix: store per-child prefix sums (``c - 1`` words per node with ``c`` children),
        so that `voxel_index` and attribute lookups work; False keeps only what traversal
        needs.

    Returns:
      A `CompactDag` that `trace` and `render` (and, with prefix sums, `voxel_index`)
      accept in place of `tree`, with identical results.

    Raises:
      JaxvoxError: not an `Octree`.
    """
    check_type("compact_dag tree", tree, Octree)
    depth, sizes = tree.depth, stored_sizes(tree.level_sizes)
    offsets = tree.level_offsets
    mask = np.asarray(tree.mask)
    leaf = slice(offsets[-1], offsets[-1] + sizes[-1])
    if depth == 1:
        root, used, words = int(mask[0]), 1, np.zeros(bucket(1), np.uint32)
    else:
        rows = np.concatenate([np.arange(offsets[lv], offsets[lv] + sizes[lv]) for lv in range(depth - 1)])
        masks = mask[rows]
        count = _POPCOUNT[masks].astype(np.int64)
        size = 1 + count + (np.maximum(count - 1, 0) if prefix else 0)
        start = np.cumsum(size) - size
        used = int(size.sum())
        del size
        # What a parent stores for each row: the word offset of a node above level D - 1,
        # the mask of a node at level D - 1.
        ref = np.zeros(mask.shape[0], np.uint32)
        ref[rows] = start
        ref[leaf] = mask[leaf]
        words = np.zeros(bucket(used), np.uint32)
        words[start] = masks
        child, prefix_sums = np.asarray(tree.child), np.asarray(tree.prefix)
        for first in range(0, len(rows), _BLOCK):  # blocks of rows bound the temporaries
            block = rows[first : first + _BLOCK]
            kids = child[block]
            present = kids != EMPTY  # [b, 8], in slot order
            node, slot = np.nonzero(present)
            rank = np.cumsum(present, axis=1, dtype=np.int32)[node, slot] - 1  # position among the present
            at = start[first + node]
            words[at + 1 + rank] = ref[kids[node, slot]]
            if prefix:
                later = rank > 0  # the first child's prefix is 0 and not stored
                words[(at + count[first + node] + rank)[later]] = prefix_sums[block][node, slot][later]
        root = 0
    put = jax.device_put
    return CompactDag(
        words=put(words),
        root=put(np.uint32(root)),
        word_count=put(np.int32(used)),
        level_count=put(np.asarray(tree.level_count, np.int32)),
        voxel_count=put(np.asarray(tree.voxel_count, np.uint32)),
        overflow=put(np.asarray(tree.overflow, np.int32)),
        grid=tree.grid,
        prefix=prefix,
        dag=tree.dag,
        mode=tree.mode,
    )


def _mask_of(tree: CompactDag, ref, leaf):
    """Mask (int32) of the node a parent stores as `ref`; `leaf` where it is at level D - 1."""
    words = tree.words
    return jnp.where(leaf, ref, words[jnp.minimum(ref, words.shape[0] - 1)] & 0xFF).astype(jnp.int32)


def compact_mask_bit(tree: CompactDag, ref, slot, leaf):
    """Whether child `slot` of the node at `ref` is present (`leaf`: the node is at level D - 1)."""
    return ((_mask_of(tree, ref, leaf) >> slot) & 1) == 1


def compact_child(tree: CompactDag, ref, slot):
    """What the node at word offset `ref` stores for its child `slot` (int32; meaningless
    when the child is absent or the node is at level D - 1)."""
    m = _mask_of(tree, ref, False)
    k = jax.lax.population_count(m & ((1 << slot) - 1))
    return tree.words[jnp.minimum(ref + 1 + k, tree.words.shape[0] - 1)].astype(jnp.int32)


def compact_voxel_index(tree: CompactDag, ijk: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A root-to-leaf walk for int32 voxel indices [..., 3]: (Morton-order index [...] int32,
    meaningful only with prefix sums; occupied [...] bool)."""
    depth = tree.depth
    words = tree.words
    last = words.shape[0] - 1
    alive = jnp.all((ijk >= 0) & (ijk < tree.grid.resolution), axis=-1) & (tree.voxel_count > 0)
    node = jnp.broadcast_to(tree.root.astype(jnp.int32), ijk.shape[:-1])
    index = jnp.zeros(ijk.shape[:-1], jnp.int32)

    def step(level, state):
        node, index, alive = state
        slot = child_slot(ijk, depth - 1 - level).astype(jnp.int32)
        m = (words[jnp.minimum(node, last)] & 0xFF).astype(jnp.int32)
        alive &= ((m >> slot) & 1) == 1
        k = jax.lax.population_count(m & ((1 << slot) - 1))
        if tree.prefix:
            c = jax.lax.population_count(m)
            before = words[jnp.minimum(node + c + k, last)].astype(jnp.int32)
            index += jnp.where(alive & (k > 0), before, 0)
        nxt = words[jnp.minimum(node + 1 + k, last)].astype(jnp.int32)
        return jnp.where(alive, nxt, 0), index, alive

    if depth > 1:
        node, index, alive = jax.lax.fori_loop(0, depth - 1, step, (node, index, alive))
    slot = child_slot(ijk, 0).astype(jnp.int32)
    alive &= ((node >> slot) & 1) == 1
    index += jax.lax.population_count(node & ((1 << slot) - 1))
    return index, alive
