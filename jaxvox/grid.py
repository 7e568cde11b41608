"""The voxel grid: a cube of R^3 voxels of edge h placed at an origin."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._errors import JaxvoxError
from jaxvox._pytree import pytree_dataclass

MAX_RESOLUTION = 1 << 20  # Morton keys are two 30-bit words: 20 bits per axis.


def check_resolution(resolution: int) -> int:
    """Returns `resolution` as an int, or raises `JaxvoxError` if it is not a power of two in [2, 2^20]."""
    r = int(resolution)
    if r != resolution or r < 2 or r > MAX_RESOLUTION or (r & (r - 1)):
        raise JaxvoxError(
            f"resolution must be a power of two between 2 and {MAX_RESOLUTION}, got {resolution!r}")
    return r


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Grid:
    """A cubic grid of ``resolution^3`` voxels.

    Voxel ``(i, j, k)`` covers ``[origin + (i, j, k) * h, origin + (i+1, j+1, k+1) * h)``
    with ``0 <= i, j, k < resolution``. `origin` and `voxel_size` are array leaves (a new
    placement does not recompile); `resolution` is static (changing it recompiles).

    Attributes:
      origin: [3] float32, world position of the grid's minimum corner.
      voxel_size: [] float32, edge length h of a voxel in world units.
      resolution: static int R, a power of two.
    """

    origin: jax.Array  # [3] float32
    voxel_size: jax.Array  # [] float32
    resolution: int = dataclasses.field(metadata=dict(static=True))

    def __init__(self, origin, voxel_size, resolution):
        object.__setattr__(self, "origin", jnp.asarray(origin, jnp.float32).reshape(3))
        object.__setattr__(self, "voxel_size", jnp.asarray(voxel_size, jnp.float32).reshape(()))
        object.__setattr__(self, "resolution", check_resolution(resolution))

    @classmethod
    def fit(cls, mesh, resolution: int, *, padding: float = 0.01) -> "Grid":
        """A cubic grid around `mesh`'s bounding box, centred on it.

        Args:
          mesh: a `jaxvox.Mesh` (or anything with a `vertices` [V, 3] array).
          resolution: voxels per axis, a power of two.
          padding: extra margin on each side, as a fraction of the largest extent.

        Raises:
          JaxvoxError: bad resolution, empty or non-finite vertices.
        """
        resolution = check_resolution(resolution)
        v = np.asarray(mesh.vertices, np.float64)
        if v.size == 0:
            raise JaxvoxError("Grid.fit: the mesh has no vertices")
        if not np.isfinite(v).all():
            raise JaxvoxError("Grid.fit: the mesh has NaN or inf vertex coordinates")
        lo, hi = v.min(0), v.max(0)
        extent = float((hi - lo).max())
        extent = extent * (1.0 + 2.0 * padding) if extent > 0 else 1.0
        h = np.float32(extent / resolution)
        origin = (lo + hi) / 2 - extent / 2
        return cls(origin=origin.astype(np.float32), voxel_size=h, resolution=resolution)

    def to_grid_units(self, points: jax.Array) -> jax.Array:
        """World points [..., 3] -> grid units [..., 3] float32 (voxel (i,j,k) spans [i, i+1] x ...)."""
        return (jnp.asarray(points, jnp.float32) - self.origin) / self.voxel_size
