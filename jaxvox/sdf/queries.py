"""Queries on SDF scenes: exactness, Lipschitz bounds, surface normals and meshing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_choice, check_number, check_type, is_concrete, refuse
from jaxvox._core.geometry import safe_norm
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh
from jaxvox.sdf.base import SDF, check_scene
from jaxvox.sdf.operations import Complement, Mix, Rotate, Scale, Translate
from jaxvox.sdf.sampled import Sampled

MAX_MESH_RESOLUTION = 512  # `to_mesh` refuses larger grids (a 512^3 float32 field is 512 MiB)
NORMAL_METHODS = ("grad", "central")  # `normal` methods


# ----------------------------------------------------------------------------- tree queries


def is_exact(scene: SDF) -> bool:
    """True when `scene` is the exact signed distance: exact primitives under translations,
    rotations, uniform (corrected) scales and complements; False for any CSG node."""
    check_scene(scene, "is_exact scene")
    if isinstance(scene, Scale):
        return scene.correct and scene.factor.ndim == 0 and is_exact(scene.child)
    if isinstance(scene, (Translate, Rotate, Complement)):
        return is_exact(scene.child)
    return type(scene).exact


def lipschitz_bound(scene: SDF) -> float:
    """Host-side upper bound on the Lipschitz constant of `scene` (1.0 for most scenes).

    Primitives 1; transforms, union, intersection, difference and the smooth operations
    keep the largest of their children's; `mix` gives ``|k| L_a + |1 - k| L_b``; an
    uncorrected scale ``L / min(s)`` (uniform or not); a `sampled` field sqrt(3) (2 sqrt(3)
    for a band below 2 voxels; see `Sampled`). Needs concrete `k` and scale factors.
    """
    check_scene(scene, "lipschitz_bound scene")
    if isinstance(scene, Sampled):
        return scene.lipschitz
    if isinstance(scene, Mix):
        k = float(scene.k)
        return abs(k) * lipschitz_bound(scene.a) + abs(1.0 - k) * lipschitz_bound(scene.b)
    if isinstance(scene, Scale):
        inner = lipschitz_bound(scene.child)
        return inner if scene.correct else inner / float(jnp.min(scene.factor))
    children = [
        c for c in jax.tree.leaves(scene, is_leaf=lambda x: x is not scene and isinstance(x, SDF)) if isinstance(c, SDF)
    ]
    return max((lipschitz_bound(c) for c in children), default=1.0)


def normal(scene: SDF, points, *, method: str = "grad", h: float = 1e-3) -> jax.Array:
    """Unit surface normals (normalized SDF gradients) at `points` [..., 3] -> [..., 3] float32.

    ``method="grad"`` differentiates the scene with `jax.grad`; ``"central"`` uses central
    differences with step `h` (world units). Zero where the gradient vanishes.

    Raises:
      JaxvoxError: a bad method or scene, points not [..., 3], or (when concrete) a step
        `h` that is not a finite number > 0.
    """
    check_choice("normal method", method, NORMAL_METHODS)
    check_scene(scene, "normal scene")
    p = jnp.asarray(points, jnp.float32)
    if p.shape[-1:] != (3,):
        raise refuse("normal points", "must have shape [..., 3]", p.shape)
    if is_concrete(h):
        check_number("normal h", h, above=0.0)
    if method == "grad":
        flat = p.reshape(-1, 3)
        g = jax.vmap(jax.grad(scene._distance))(flat).reshape(p.shape)
    else:
        offsets = jnp.eye(3, dtype=jnp.float32) * h  # [3 axes, 3]
        plus = scene._distance(p[..., None, :] + offsets)
        minus = scene._distance(p[..., None, :] - offsets)
        g = (plus - minus) / (2.0 * h)
    n = safe_norm(g)
    return g / jnp.where(n > 0, n, 1.0)[..., None]


# ----------------------------------------------------------------------------- meshing


@jax.jit
def _sample(scene: SDF, grid: Grid) -> jax.Array:
    """The scene at every voxel centre, one x-slab per `lax.map` step: [R, R, R] float32."""
    r = grid.resolution
    c = (jnp.arange(r, dtype=jnp.float32) + 0.5) * grid.voxel_size
    y, z = jnp.meshgrid(c, c, indexing="ij")

    def slab(x):
        p = jnp.stack([jnp.full_like(y, x), y, z], axis=-1) + grid.origin
        return scene._distance(p)

    return jax.lax.map(slab, c)


def to_mesh(scene: SDF, grid: Grid, *, level: float = 0.0) -> Mesh:
    """Triangle mesh of the ``scene == level`` surface by marching cubes on `grid`'s voxel centres.

    The field is sampled at ``origin + (ijk + 0.5) * voxel_size`` one slab at a time (no
    intermediate larger than the R^3 float32 field) and passed to
    `skimage.measure.marching_cubes`. Faces are counter-clockwise seen from outside
    (where ``scene > level``); vertices are in world coordinates. The surface is open
    where it leaves the grid.

    Returns:
      A `Mesh`; it has 0 vertices and 0 faces when the field does not cross `level`.

    Raises:
      JaxvoxError: not a scene or `Grid`, a resolution above `MAX_MESH_RESOLUTION`, a
        level that is not a finite number, or a NaN in the field.
    """
    from skimage.measure import marching_cubes

    check_scene(scene, "to_mesh scene")
    check_type("to_mesh grid", grid, Grid)
    level = check_number("to_mesh level", level)
    if grid.resolution > MAX_MESH_RESOLUTION:
        raise refuse(
            "to_mesh grid",
            f"resolution must be at most {MAX_MESH_RESOLUTION} "
            f"(the field alone would take {grid.resolution**3 * 4 / 2**30:.1f} GiB)",
            grid.resolution,
        )
    field = np.array(_sample(scene, grid))  # writable: marching_cubes needs it
    if np.isnan(field).any():
        raise refuse(
            "to_mesh scene",
            f"must not be NaN at a voxel centre (NaN at {int(np.isnan(field).sum())} of {field.size})",
            scene,
        )
    if not field.min() < level < field.max():
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    verts, faces, _, _ = marching_cubes(field, level, gradient_direction="descent")
    h, origin = float(grid.voxel_size), np.asarray(grid.origin, np.float64)
    return Mesh((origin + (verts + 0.5) * h).astype(np.float32), faces.astype(np.int32))
