"""Closest-triangle seeds and jump flooding on triangle ids (steps 1 and 2 of the
pipeline in `jaxvox.distance`, and the "jfa" and "jfa-separable" propagations).

Every voxel holds a triangle id (`NO_TRIANGLE` where none has reached it yet) and the
exact point-triangle distance from its centre to that triangle, so these methods give
distances to real triangles and never underestimate. Boxes of any shape: the narrow
band and the propagation run on the clipmap's scissor volumes too.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox.distance.exact import distance_to

NO_TRIANGLE = -1  # triangle id of a voxel no seed has reached yet
_VOXELS_PER_BLOCK = 1 << 20  # voxels per block of a jump-flooding step (bounds its temporaries)


# ------------------------------------------------------------------------- seeds


def _flat(ijk, shape: tuple[int, int, int]):
    """C-order flat index of voxels [..., 3] int32 in a box of `shape` voxels."""
    return (ijk[..., 0] * shape[1] + ijk[..., 1]) * shape[2] + ijk[..., 2]


def seed(tris, coords, triangle, shape: tuple[int, int, int], clamped: bool = True):
    """Closest-triangle seeds: ([n] int32 ids, [n] float32 distances, inf where none), n
    the voxels of a box of `shape`.

    Candidates are the voxelizer's (voxel, closest triangle) pairs (voxels with a
    negative first coordinate are unused) and, if `clamped`, per triangle the voxels of
    its centroid and corners clamped into the box; each voxel keeps the nearest
    candidate, ties to the lower id (a scatter-min on distance bits, then on ids).
    """
    n = math.prod(shape)
    ijk, tri, valid = coords, triangle, coords[:, 0] >= 0
    if clamped:
        points = jnp.concatenate([tris.mean(1), tris[:, 0], tris[:, 1], tris[:, 2]])  # [4F, 3]
        ijk = jnp.concatenate([ijk, jnp.clip(jnp.floor(points), 0, jnp.asarray(shape) - 1).astype(jnp.int32)])
        tri = jnp.concatenate([tri, jnp.tile(jnp.arange(tris.shape[0], dtype=jnp.int32), 4)])
        valid = jnp.concatenate([valid, jnp.tile(jnp.all(jnp.isfinite(tris), (1, 2)), 4)])
    flat = jnp.where(valid, _flat(ijk, shape), n)  # n: dropped
    dist = distance_to(ijk.astype(jnp.float32) + 0.5, tris, jnp.where(valid, tri, NO_TRIANGLE))
    bits = jax.lax.bitcast_convert_type(dist, jnp.int32)  # non-negative floats order as ints
    best = jnp.full(n, jnp.iinfo(jnp.int32).max, jnp.int32).at[flat].min(bits, mode="drop")
    winner = valid & (bits == best.at[flat].get(mode="fill", fill_value=0))
    ids = jnp.full(n, jnp.iinfo(jnp.int32).max, jnp.int32).at[jnp.where(winner, flat, n)].min(tri, mode="drop")
    ids = jnp.where(ids == jnp.iinfo(jnp.int32).max, NO_TRIANGLE, ids)
    return ids, jax.lax.bitcast_convert_type(jnp.where(ids >= 0, best, 0x7F800000), jnp.float32)


# ---------------------------------------------------------------- jump flooding


def jfa_offsets(steps, separable: bool) -> np.ndarray:
    """Neighbour offsets of each pass: [P, M, 3] int32 (M = 2 separable, 26 full)."""
    unit = np.array([o for o in np.ndindex(3, 3, 3) if o != (1, 1, 1)]) - 1
    passes = []
    for step in steps:
        if separable:
            passes += [np.eye(3, dtype=np.int64)[[axis, axis]] * [[-step], [step]] for axis in range(3)]
        else:
            passes.append(unit * step)
    return np.array(passes, np.int32).reshape(-1, 2 if separable else 26, 3)


def jump_flood(ids, dist, tris, offsets: np.ndarray, shape: tuple[int, int, int]):
    """Jump-flooding passes on triangle ids [n] (n voxels of a box of `shape`): each voxel
    keeps the nearest of its own and its neighbours' triangles (ties to the lower id);
    neighbours are read from the ids at the start of the pass, outside the box there are
    none (no wrap-around).

    Each neighbour offset is applied to blocks of `_VOXELS_PER_BLOCK` voxels in turn
    (`jax.lax.map`), so the temporaries of the point-triangle distances stay bounded
    (the last block is padded; its extra voxels are dropped).
    """
    if offsets.shape[0] == 0:
        return ids, dist
    size = math.prod(shape)
    block = min(size, _VOXELS_PER_BLOCK)
    pad = -size % block
    ids = jnp.concatenate([ids, jnp.full(pad, NO_TRIANGLE, ids.dtype)])
    dist = jnp.concatenate([dist, jnp.full(pad, jnp.inf, dist.dtype)])
    n = size + pad

    def one_pass(state, pass_offsets):
        prev = state[0]

        def candidate(state, offset):
            def one_block(args):
                start, ids, dist = args
                ijk = jnp.stack(jnp.unravel_index(start + jnp.arange(block, dtype=jnp.int32), shape), -1)
                q = ijk + offset
                ok = jnp.all((q >= 0) & (q < jnp.asarray(shape)), axis=1)
                cand = jnp.where(ok, prev[_flat(q, shape)], NO_TRIANGLE)
                d = distance_to(ijk.astype(jnp.float32) + 0.5, tris, cand)
                better = (d < dist) | ((d == dist) & (cand >= 0) & ((cand < ids) | (ids < 0)))
                return jnp.where(better, cand, ids), jnp.where(better, d, dist)

            starts = jnp.arange(0, n, block, dtype=jnp.int32)
            ids, dist = jax.lax.map(one_block, (starts, state[0].reshape(-1, block), state[1].reshape(-1, block)))
            return (ids.reshape(-1), dist.reshape(-1)), None

        return jax.lax.scan(candidate, state, pass_offsets)[0], None

    ids, dist = jax.lax.scan(one_pass, (ids, dist), jnp.asarray(offsets))[0]
    return ids[:size], dist[:size]


def jfa_steps(shape: tuple[int, int, int]):
    """Steps P/2, ..., 1 for the power of two P >= the box's longest side."""
    p = 1 << (max(shape) - 1).bit_length()
    return [p >> s for s in range(1, p.bit_length())]
