"""16-bit storage of distance fields: `QuantizedField`, `quantize_field`."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_choice, check_number, check_type, is_concrete, refuse
from jaxvox._core.pytree import pytree_dataclass
from jaxvox.grid import Grid

FORMATS = ("float16", "fixed16")


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class QuantizedField:
    """A distance field stored in 16 bits per voxel, in units of the voxel size.

    `format` is static (changing it recompiles).

    Attributes:
      values: [R, R, R] float16 (distance / h) or int16 (round(distance / h * steps)).
      voxel_size: [] float32 h, world units.
      steps_per_voxel: [] float32 fixed-point steps per voxel (1 for float16).
      format: "float16" or "fixed16".
    """

    values: jax.Array  # [R, R, R] float16 or int16
    voxel_size: jax.Array  # [] float32
    steps_per_voxel: jax.Array  # [] float32
    format: str = dataclasses.field(metadata=dict(static=True))

    def decode(self) -> jax.Array:
        """The field in world units: [R, R, R] float32."""
        return self.values.astype(jnp.float32) / self.steps_per_voxel * self.voxel_size


def quantize_field(
    field: jax.Array, grid: Grid, *, format: str = "fixed16", steps_per_voxel: int = 256
) -> QuantizedField:
    """Stores a field [R, R, R] float32 (world units) in 16 bits per voxel; jittable.

    * "float16": distance in voxels as float16; error at most 2^-11 of the value
      (0.25 voxel at 512-1024 voxels away), inf kept.
    * "fixed16": int16 steps of 1/`steps_per_voxel` voxel; error at most half a
      step below ``32767 / steps_per_voxel`` voxels (128 voxels at 256 steps), and
      values beyond saturate there (still a safe step for sphere tracing).

    The error a field actually costs: ``abs(q.decode() - field) / grid.voxel_size``.

    Raises:
      JaxvoxError: not a `Grid`, an unknown format, a field not of the grid's shape, or
        (when concrete) `steps_per_voxel` not a finite number > 0.
    """
    check_type("quantize_field grid", grid, Grid)
    check_choice("quantize_field format", format, FORMATS)
    if np.shape(field) != (grid.resolution,) * 3:
        raise refuse("quantize_field field", f"must have the grid's shape {(grid.resolution,) * 3}", np.shape(field))
    if is_concrete(steps_per_voxel):
        check_number("quantize_field steps_per_voxel", steps_per_voxel, above=0.0)
    voxels = field / grid.voxel_size
    if format == "float16":
        return QuantizedField(voxels.astype(jnp.float16), grid.voxel_size, jnp.float32(1.0), format)
    steps = jnp.float32(steps_per_voxel)
    codes = jnp.clip(jnp.round(jnp.clip(voxels, -1e9, 1e9) * steps), -32767, 32767).astype(jnp.int16)
    return QuantizedField(codes, grid.voxel_size, steps, format)
