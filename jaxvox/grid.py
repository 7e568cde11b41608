"""The voxel grid: a cube of R^3 voxels of edge h placed at an origin."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float32

from jaxvox._core.checks import check_number, refuse
from jaxvox._core.pytree import pytree_dataclass

MAX_RESOLUTION = 1 << 20  # Morton keys are two 30-bit words: 20 bits per axis.


def check_resolution(resolution: int) -> int:
    """Returns `resolution` as an int, or raises `JaxvoxError` if it is not a power of two in [2, 2^20]."""
    integral = isinstance(resolution, (int, np.integer)) and not isinstance(resolution, (bool, np.bool_))
    r = int(resolution) if integral else 0
    if r < 2 or r > MAX_RESOLUTION or (r & (r - 1)):
        raise refuse("resolution", f"must be a power of two between 2 and {MAX_RESOLUTION}", resolution)
    return r


def _leaf(what: str, value, shape: tuple, expected: str) -> jax.Array:
    """A float32 grid leaf of `shape`; concrete values must be finite (and a voxel size > 0)."""
    if isinstance(value, jax.core.Tracer):
        return jnp.asarray(value, jnp.float32).reshape(shape)
    try:
        a = np.asarray(value)
        ok = a.dtype.kind in "fiu" and a.size == int(np.prod(shape))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise refuse(what, f"must be {expected}", value)
    a = a.astype(np.float32).reshape(shape)
    if not np.isfinite(a).all() or (shape == () and not a > 0):
        raise refuse(what, f"must be {expected}", value)
    return jnp.asarray(a, jnp.float32)


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

    origin: Float32[Array, "*batch 3"]  # [3] float32
    voxel_size: Float32[Array, " *batch"]  # [] float32
    resolution: int = dataclasses.field(metadata=dict(static=True))

    def __init__(self, origin, voxel_size, resolution):
        object.__setattr__(self, "origin", _leaf("Grid origin", origin, (3,), "three finite numbers"))
        object.__setattr__(self, "voxel_size", _leaf("Grid voxel_size", voxel_size, (), "one finite number > 0"))
        object.__setattr__(self, "resolution", check_resolution(resolution))

    @classmethod
    def fit(cls, mesh, resolution: int, *, padding: float = 0.01) -> Grid:
        """A cubic grid around `mesh`'s bounding box, centred on it.

        Args:
          mesh: a `jaxvox.Mesh` (or anything with a `vertices` [V, 3] array).
          resolution: voxels per axis, a power of two.
          padding: extra margin on each side, as a fraction of the largest extent (>= 0).

        Raises:
          JaxvoxError: bad resolution or padding, empty or non-finite vertices, or a
            box beyond float32's range.
        """
        resolution = check_resolution(resolution)
        padding = check_number("Grid.fit padding", padding, minimum=0.0)
        if not hasattr(mesh, "vertices"):
            raise refuse("Grid.fit mesh", "expected a jaxvox.Mesh", type(mesh))
        v = np.asarray(mesh.vertices, np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise refuse("Grid.fit mesh", "vertices must have shape [V, 3]", v.shape)
        if v.size == 0:
            raise refuse("Grid.fit mesh", "has no vertices", v.shape)
        if not np.isfinite(v).all():
            raise refuse("Grid.fit mesh", "has NaN or inf vertex coordinates", v[~np.isfinite(v).all(1)][0])
        lo, hi = v.min(0), v.max(0)
        extent = float((hi - lo).max())
        extent = extent * (1.0 + 2.0 * padding) if extent > 0 else 1.0
        origin = (lo + hi) / 2 - extent / 2
        if max(np.abs(origin).max(), np.abs(origin + extent).max(), extent / resolution) > np.finfo(np.float32).max:
            raise refuse("Grid.fit mesh", "has coordinates beyond float32's range", (lo, hi))
        h = np.float32(extent / resolution)
        return cls(origin=origin.astype(np.float32), voxel_size=h, resolution=resolution)

    def to_grid_units(self, points: jax.Array) -> jax.Array:
        """World points [..., 3] -> grid units [..., 3] float32 (voxel (i,j,k) spans [i, i+1] x ...)."""
        return (jnp.asarray(points, jnp.float32) - self.origin) / self.voxel_size
