"""The `Hit` record every tracer returns, its statuses (`HIT`, `MISS`, `STEP_CAP`,
`INVALID`, and `RUNNING` while a ray is traced) and the ray check `valid_rays`.

Shared by the octree and grid traversals (`jaxvox.trace`), sphere tracing
(`jaxvox.sphere_tracing`), the clipmaps (`jaxvox.distance`) and the renderer, so it lives
on the ground floor."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float32, Int32

from jaxvox._core.pytree import pytree_dataclass

# `Hit.status` values.
HIT = 0
"""The ray entered an occupied voxel (or a surface) within ``t_max``."""
MISS = 1
"""The ray left the grid (or passed ``t_max``) without a hit."""
STEP_CAP = 2
"""The traversal gave up after ``max_steps`` steps: neither a hit nor a miss."""
INVALID = 3
"""The ray has a NaN origin or direction, a zero direction, or a NaN ``t_max``."""
RUNNING = -1  # status while a ray is being traced


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Hit:
    """First voxel hit per ray.

    Attributes:
      t: [...] float32 ray parameter where the ray enters the voxel (0 when it starts
        inside it), inf unless the status is `HIT`.
      voxel: [..., 3] int32 voxel index, -1 unless hit.
      normal: [..., 3] float32 outward normal of the voxel face the ray entered (zero
        when it starts inside the voxel or unless hit).
      index: [...] int32 Morton-order voxel index for attribute arrays (`trace`), or
        the C-order flat index into the occupancy grid (`trace_dense`); -1 unless hit.
      status: [...] int32 `HIT`, `MISS`, `STEP_CAP` (gave up after ``max_steps``) or
        `INVALID` (NaN origin or direction, zero direction, NaN ``t_max``).

    Every tracer returns one: `trace`, `trace_dense`, `sphere_trace` and
    `sphere_trace_octree` (``t`` along the unit direction, ``normal`` the scene's
    gradient), and `trace_clipmap` (``t`` along the unit direction, ``normal`` the field
    gradient, ``index`` the cascade hit, ``voxel`` -1).

    `jaxvox.sphere_trace` returns the same type: there ``t`` is the distance along the
    unit direction, ``normal`` the unit SDF gradient, and ``voxel`` and ``index`` are -1.
    """

    t: Float32[Array, " *rays"]  # [...] float32
    voxel: Int32[Array, "*rays 3"]  # [..., 3] int32
    normal: Float32[Array, "*rays 3"]  # [..., 3] float32
    index: Int32[Array, " *rays"]  # [...] int32
    status: Int32[Array, " *rays"]  # [...] int32


def valid_rays(origins: jax.Array | np.ndarray, directions: jax.Array | np.ndarray) -> jax.Array:
    """Which rays can be traced: [...] bool, for origins and directions [..., 3] (jittable).

    A ray is valid when neither its origin nor its direction holds a NaN and its direction
    is not zero. `trace` and `trace_dense` give the others status `INVALID` (as they do
    rays with a NaN ``t_max``); the renderer ends a path by zeroing its direction.
    """
    return ~(
        jnp.any(jnp.isnan(origins), axis=-1)
        | jnp.any(jnp.isnan(directions), axis=-1)
        | jnp.all(directions == 0, axis=-1)
    )
