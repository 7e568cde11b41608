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

from jaxvox.octree.attributes import voxel_attributes
from jaxvox.octree.build import build_dag, build_octree, check_level_capacities, octree_capacities
from jaxvox.octree.compact_dag import CompactDag, compact_dag
from jaxvox.octree.layout import compact, padded
from jaxvox.octree.queries import expand, occupied, voxel_index
from jaxvox.octree.stream import mesh_to_dag
from jaxvox.octree.tree import EMPTY, MAX_INDEXED, MISSING, OVERFLOW_NODES, Octree, padded_sizes, stored_sizes

__all__ = [
    "CompactDag",
    "EMPTY",
    "MAX_INDEXED",
    "MISSING",
    "OVERFLOW_NODES",
    "Octree",
    "build_dag",
    "build_octree",
    "check_level_capacities",
    "compact",
    "compact_dag",
    "expand",
    "mesh_to_dag",
    "occupied",
    "octree_capacities",
    "padded",
    "padded_sizes",
    "stored_sizes",
    "voxel_attributes",
    "voxel_index",
]
