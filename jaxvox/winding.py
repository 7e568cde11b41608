"""Generalized winding numbers of triangle meshes at voxel centres, fast (Barill et al. 2018).

The generalized winding number ``w(p) = sum_t solid_angle_t(p) / (4 pi)`` is 1 inside a
closed, outward-oriented mesh and 0 outside; for an open mesh (holes, like the bunny's
base) it varies smoothly across the holes, and ``w > 1/2`` is a robust inside test.
Summing every triangle at every voxel costs O(R^3 F). Here:

* **Triangle tree.** Triangles are ordered by the Morton code of their centroids and
  grouped eight by eight, level by level, into an implicit 8-ary tree. Each node keeps
  its area vector ``A = sum_t area_t n_t`` (the dipole moment), the area-weighted centre
  ``c`` of its triangles and a radius ``r`` bounding them about ``c``.
* **Query blocks.** Voxels are grouped in ``b^3`` blocks (centre ``q``, half-diagonal
  ``h``). A node is *far* from a block when ``|q - c| > beta (r + h)``: then each voxel
  of the block takes the node's dipole term ``A . (c - p) / (4 pi |c - p|^3)``, the
  first-order far field of the node's triangles. Otherwise the node opens: its children
  are tested next, and a near single triangle adds its exact solid angle (Van Oosterom
  and Strackee).
* **Breadth first, static shapes.** The (block, node) pairs of one tree level form a
  frontier; far pairs add their terms, near pairs expand into their children's pairs
  (count, prefix-sum, emit into a power-of-two capacity), level by level from the root
  to the triangles. The host sizes each frontier, so nothing is dropped.

The error of a far term falls as ``(r / |q - c|)^2`` relative to it, so ``beta`` trades
accuracy for time (`winding_numbers`); a sign decision can only flip where ``w`` is
within that error of 1/2, which happens near holes, not near closed parts of a surface.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float32

from jaxvox._checks import check_int, check_number, check_type, refuse
from jaxvox._geometry import solid_angle
from jaxvox._shapes import bucket, expand_counts
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, validate_mesh

_PAIRS_PER_CHUNK = 1 << 15  # (block, node) pairs evaluated together (x b^3 voxels each)


class _Tree(NamedTuple):
    """An implicit 8-ary tree over Morton-ordered triangles, all levels in one table.

    Node ``g`` (global id) has children ``first[g] .. first[g] + count[g] - 1``; level 0
    (the triangles themselves) has ``count == 0``.
    """

    centre: jax.Array  # [N, 3] float32, grid units
    radius: jax.Array  # [N] float32
    area: jax.Array  # [N, 3] float32 area vector
    first: jax.Array  # [N] int32
    count: jax.Array  # type: ignore[assignment]  # [N] int32
    triangles: jax.Array  # [F, 3, 3] float32 in tree order (level 0 node i is triangle i)
    levels: tuple[tuple[int, int], ...]  # (offset, size) per level, root first


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Indices sorting points [n, 3] along a 10-bit-per-axis Morton curve of their bounding box."""
    lo, hi = points.min(0), points.max(0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-30) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def _build_tree(tris: np.ndarray) -> _Tree:
    """The triangle tree of float64 triangles [F, 3, 3] (grid units), F >= 1."""
    tris = tris[_morton_order(tris.mean(1))]
    area = 0.5 * np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    centre = tris.mean(1)
    radius = np.linalg.norm(tris - centre[:, None], axis=-1).max(1)
    levels = [(centre, radius, area)]
    while len(levels[-1][0]) > 1:
        c, r, a = levels[-1]
        n = len(c)
        pad = -n % 8
        group = lambda x, fill=0.0: np.concatenate([x, np.full((pad,) + x.shape[1:], fill)]).reshape(
            -1, 8, *x.shape[1:]
        )
        weight = group(np.linalg.norm(a, axis=-1))
        present = group(np.ones(n)) > 0
        total = weight.sum(1)
        mean = np.where(present[..., None], group(c), 0).sum(1) / present.sum(1)[:, None]
        centroid = np.where(
            (total > 0)[:, None], (weight[..., None] * group(c)).sum(1) / np.where(total > 0, total, 1)[:, None], mean
        )
        reach = np.where(present, np.linalg.norm(group(c) - centroid[:, None], axis=-1) + group(r), 0.0)
        levels.append((centroid, reach.max(1), group(a).sum(1)))
    levels = levels[::-1]  # root first
    sizes = [len(level[0]) for level in levels]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    first, count = [], []
    for depth, size in enumerate(sizes):
        if depth + 1 < len(sizes):
            below = sizes[depth + 1]
            start = offsets[depth + 1] + 8 * np.arange(size)
            first.append(start)
            count.append(np.clip(below - 8 * np.arange(size), 0, 8))
        else:
            first.append(np.zeros(size, np.int64))
            count.append(np.zeros(size, np.int64))
    stack = lambda i: np.concatenate([level[i] for level in levels]).astype(np.float32)
    return _Tree(
        centre=jnp.asarray(stack(0)),
        radius=jnp.asarray(stack(1)),
        area=jnp.asarray(stack(2)),
        first=jnp.asarray(np.concatenate(first).astype(np.int32)),
        count=jnp.asarray(np.concatenate(count).astype(np.int32)),
        triangles=jnp.asarray(tris.astype(np.float32)),
        levels=tuple(zip(offsets.tolist(), sizes)),
    )


def _block_offsets(block: int) -> np.ndarray:
    """Voxel-centre offsets [b^3, 3] float32 inside a block, from its corner."""
    return (np.stack(np.unravel_index(np.arange(block**3), (block,) * 3), -1) + 0.5).astype(np.float32)


def _block_corners(blocks, per_axis: tuple[int, int, int], block: int):
    """Corner [n, 3] float32 (grid units) of blocks given by flat index [n] over `per_axis` blocks."""
    return jnp.stack(jnp.unravel_index(blocks, per_axis), -1).astype(jnp.float32) * block


def _far(tree: _Tree, blocks, nodes, per_axis: tuple[int, int, int], block: int, beta: float):
    centre = _block_corners(blocks, per_axis, block) + block / 2
    gap = jnp.linalg.norm(centre - tree.centre[nodes], axis=-1)
    return gap > beta * (tree.radius[nodes] + block * math.sqrt(3) / 2)


@functools.partial(jax.jit, static_argnames=("per_axis", "block", "beta"))
def _near_children(tree: _Tree, blocks, nodes, n, *, per_axis: tuple[int, int, int], block: int, beta: float):
    """Number of child pairs the near pairs of a frontier open into: [] int32."""
    valid = jnp.arange(blocks.shape[0]) < n
    near = valid & ~_far(tree, blocks, nodes, per_axis, block, beta)
    return jnp.sum(jnp.where(near, tree.count[nodes], 0))


@functools.partial(jax.jit, static_argnames=("per_axis", "block", "beta", "leaves", "capacity"))
def _level(
    tree: _Tree,
    w,
    blocks,
    nodes,
    n,
    *,
    per_axis: tuple[int, int, int],
    block: int,
    beta: float,
    leaves: bool,
    capacity: int,
):
    """Adds one frontier's terms to ``w`` [B, b^3] and opens its near pairs.

    Returns (w, child blocks [capacity], child nodes [capacity]).
    """
    offsets = jnp.asarray(_block_offsets(block))
    valid = jnp.arange(blocks.shape[0]) < n
    far = _far(tree, blocks, nodes, per_axis, block, beta)

    def add(w, chunk):
        b, g, ok, is_far = chunk
        p = _block_corners(b, per_axis, block)[:, None] + offsets  # [c, b^3, 3]
        d = tree.centre[g][:, None] - p
        r2 = jnp.sum(d * d, -1)
        dipole = jnp.sum(tree.area[g][:, None] * d, -1) / (4 * jnp.pi * r2 * jnp.sqrt(r2))
        term = jnp.where(is_far[:, None], dipole, 0.0)
        if leaves:
            exact = solid_angle(p, tree.triangles[jnp.maximum(g - tree.levels[-1][0], 0)][:, None])
            term = jnp.where(is_far[:, None], term, exact)
        return w.at[b].add(jnp.where(ok[:, None], term, 0.0), mode="drop"), None

    size = blocks.shape[0]
    chunk = min(size, _PAIRS_PER_CHUNK)  # both powers of two
    split = lambda x: x.reshape(size // chunk, chunk)
    w = jax.lax.scan(add, w, (split(blocks), split(nodes), split(valid), split(far)))[0]
    counts = jnp.where(valid & ~far, tree.count[nodes], 0)
    owner, rank, ok, _ = expand_counts(counts, capacity)
    return w, jnp.where(ok, blocks[owner], 0), jnp.where(ok, tree.first[nodes[owner]] + rank, 0)


def winding_numbers(mesh: Mesh, grid: Grid, *, beta: float = 2.0, block: int = 4) -> Float32[Array, "R R R"]:
    """Generalized winding number of `mesh` at every voxel centre of `grid`, fast.

    Host-side (each tree level's frontier is sized on the host); see the module
    docstring for the method. Memory grows with the frontier (pairs near the surface),
    plus the [R, R, R] result.

    Args:
      mesh: `Mesh` (validated); its orientation sets the sign (outward normals give 1 inside).
      grid: `Grid` of R^3 voxels.
      beta: far-field acceptance ratio, > 1 (larger: more exact, slower; inf: exact). At
        2 the error measured on spot and the bunny at 32^3 stays below about 5e-3 (tests
        allow 1e-2).
      block: voxels per block edge, a power of two (clipped to R).

    Returns:
      [R, R, R] float32, indexed (i, j, k); zeros for a mesh without faces.

    Raises:
      JaxvoxError: a malformed mesh, not a `Grid`, `beta` not a number > 1, or `block`
        not a power of two.
    """
    check_type("winding_numbers grid", grid, Grid)
    validate_mesh(mesh)
    beta = check_number("winding_numbers beta", beta, above=1.0, finite=False)
    block = check_int("winding_numbers block", block, minimum=1)
    if block & (block - 1):
        raise refuse("winding_numbers block", "must be a power of two", block)
    r = grid.resolution
    return box_winding_numbers(
        mesh, np.asarray(grid.origin, np.float64), float(grid.voxel_size), (r, r, r), beta=beta, block=block
    )


def box_winding_numbers(
    mesh: Mesh, origin, voxel_size: float, shape: tuple[int, int, int], *, beta: float = 2.0, block: int = 4
) -> jax.Array:
    """`winding_numbers` at the centres of a box of voxels of any shape.

    Voxel (i, j, k) has its centre at ``origin + (i + 1/2, j + 1/2, k + 1/2) * voxel_size``.
    The box is covered by whole blocks (a ragged edge is computed and dropped).

    Args:
      mesh: `Mesh` (not validated here).
      origin: [3] world position of the box's minimum corner.
      voxel_size: voxel edge, world units.
      shape: (nx, ny, nz) voxels, each >= 1.
      beta, block: as for `winding_numbers` (not checked here).

    Returns:
      [nx, ny, nz] float32.
    """
    block = min(block, 1 << (max(shape) - 1).bit_length())  # no larger than the box
    per_axis = tuple(-(-int(n) // block) for n in shape)
    w = jnp.zeros((math.prod(per_axis), block**3), jnp.float32)
    if mesh.num_faces:
        tris = (np.asarray(mesh.triangles(), np.float64) - np.asarray(origin, np.float64)) / float(voxel_size)
        tree = _build_tree(tris)
        settings = dict(per_axis=per_axis, block=block, beta=float(beta))
        n = math.prod(per_axis)
        capacity = bucket(n)
        blocks = jnp.arange(capacity, dtype=jnp.int32)
        nodes = jnp.zeros(capacity, jnp.int32)  # the root
        for depth in range(len(tree.levels)):
            leaves = depth == len(tree.levels) - 1
            opened = 0 if leaves else int(_near_children(tree, blocks, nodes, n, **settings))
            w, blocks, nodes = _level(tree, w, blocks, nodes, n, leaves=leaves, capacity=bucket(opened), **settings)
            n = opened
    w = w.reshape(per_axis + (block,) * 3).transpose(0, 3, 1, 4, 2, 5)
    w = w.reshape(tuple(a * block for a in per_axis))
    return w[: shape[0], : shape[1], : shape[2]]
