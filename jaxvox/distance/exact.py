"""The "exact" method: brute-force minima over all triangles, chunked (O(points x F)).

Also the point-triangle distances that the other methods evaluate for each candidate
triangle id, and brute-force generalized winding numbers (the clipmap's "exact" sign).
All in the units of the triangles (grid units in the field, world units in the clipmap).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from jaxvox._core.geometry import point_triangle_dist2, solid_angle

_PAIRS_PER_CHUNK = 1 << 21  # (voxel, triangle) pairs per chunk of the brute-force loops


def voxel_centres(shape: tuple[int, int, int]) -> jax.Array:
    """Voxel centres in grid units of a box of `shape` voxels: [n, 3] float32, C order."""
    ijk = jnp.stack(jnp.unravel_index(jnp.arange(math.prod(shape)), shape), -1)
    return ijk.astype(jnp.float32) + 0.5


def distance_to(points, tris, ids):
    """Distance from points [n, 3] to triangles ``tris[ids]`` ([n] int32; inf where -1)."""
    return jnp.where(ids >= 0, _pair_distance(points, tris[jnp.maximum(ids, 0)]), jnp.inf)


def _per_point(points, tris, fn):
    """``fn(points [c, 1, 3], tris [1, F, 3, 3]) -> [c]`` over all points, in chunks of points."""
    n = points.shape[0]
    chunk = max(1, min(n, _PAIRS_PER_CHUNK // max(tris.shape[0], 1)))
    pad = -n % chunk
    pts = jnp.concatenate([points, jnp.zeros((pad, 3), points.dtype)]).reshape(-1, chunk, 3)
    out = jax.lax.map(lambda p: fn(p[:, None], tris[None]), pts)
    return out.reshape(-1)[:n]


def mesh_distance(points, tris):
    """Exact distance [n] from points [n, 3] to the nearest of all triangles (inf if none)."""
    return _per_point(points, tris, lambda p, t: _pair_distance(p, t).min(1, initial=jnp.inf))


def _pair_distance(p, t):
    """Point-triangle distances for broadcast points [..., 3] and triangles [..., 3, 3]."""
    return jnp.sqrt(point_triangle_dist2(p, t[..., 0, :], t[..., 1, :], t[..., 2, :]))


def mesh_winding_numbers(points, tris):
    """Generalized winding number [n] at points [n, 3] by brute force over all triangles, chunked."""
    return _per_point(points, tris, lambda p, t: solid_angle(p, t).sum(1))
