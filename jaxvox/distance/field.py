"""`distance_field`: the method table, memory estimates and the pipeline on a box.

How each method works and what error it makes: see `jaxvox.distance`. Here the
pipeline is put together: the closest-triangle voxelization seeds `jfa.seed`, the
narrow band and propagation (`jfa`, `sweep`, `exact`) give unsigned distances in
voxels of any box made of a grid's first voxels (`box_distance`, also the clipmap's
scissor volumes), and `jaxvox.distance.solid` gives the sign.

Memory: a dense field costs 4 R^3 bytes; the build needs more for temporaries, see
`distance_field_bytes`. `distance_field` refuses sizes above ``max_bytes``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float32

from jaxvox._core.checks import check_choice, check_int, check_type
from jaxvox._core.shapes import bucket
from jaxvox.distance.exact import mesh_distance, voxel_centres
from jaxvox.distance.jfa import jfa_offsets, jfa_steps, jump_flood, seed
from jaxvox.distance.solid import (
    SIGN_BYTES_PER_VOXEL,
    SIGN_METHODS,
    check_bytes,
    grid_triangles,
    padded_mesh,
    sign_method,
    solid_inside,
)
from jaxvox.distance.sweep import fast_sweep
from jaxvox.grid import Grid, check_resolution
from jaxvox.mesh import Mesh, validate_mesh
from jaxvox.voxelize import CONSERVATIVE, UNUSED, voxelize

METHODS = ("exact", "jfa", "jfa-separable", "sweep", "jfa+sweep", "band")

# Peak working memory per voxel of each method (bytes), measured as the process's peak
# resident memory at 64^3-256^3 with room to spare (jump flooding works on blocks of
# voxels: ~30 measured; sweeping holds a skewed [3R-2, R, R] copy and the shears'
# temporaries: 41 measured at 256^3); add SIGN_BYTES_PER_VOXEL for a signed field.
BYTES_PER_VOXEL = {"exact": 16, "jfa": 48, "jfa-separable": 48, "sweep": 64, "jfa+sweep": 64, "band": 48}


def distance_field_bytes(resolution: int, *, method: str = "jfa-separable", signed: bool = True) -> int:
    """Estimated peak working memory of `distance_field` at R^3 voxels, in bytes.

    ``R^3 * (BYTES_PER_VOXEL[method] + (SIGN_BYTES_PER_VOXEL if signed else 0))``; the
    result itself is 4 R^3 bytes (512^3: 0.5 GiB; a signed "jfa+sweep" build is estimated
    at 14 GiB there).

    Raises:
      JaxvoxError: an unknown method, or a resolution that is not a power of two.
    """
    per_voxel = BYTES_PER_VOXEL[check_choice("distance_field_bytes method", method, METHODS)]
    return check_resolution(resolution) ** 3 * (per_voxel + (SIGN_BYTES_PER_VOXEL if signed else 0))


@functools.partial(jax.jit, static_argnames=("shape", "method", "band", "sweeps", "clamped"))
def _unsigned(
    tris, coords, triangle, *, shape: tuple[int, int, int], method: str, band: int, sweeps: int, clamped: bool = True
):
    """Unsigned field of a box of `shape` voxels (triangles and seed voxels in its units):
    [nx, ny, nz] float32 in voxels (inf where no seed reached; `clamped`: see `seed`)."""
    if method == "exact":
        return mesh_distance(voxel_centres(shape), tris).reshape(shape)
    ids, dist = seed(tris, coords, triangle, shape, clamped)
    ids, dist = jump_flood(ids, dist, tris, jfa_offsets([1] * band, True), shape)
    if method in ("jfa", "jfa-separable"):
        ids, dist = jump_flood(ids, dist, tris, jfa_offsets(jfa_steps(shape), method == "jfa-separable"), shape)
    dist = dist.reshape(shape)
    if method in ("sweep", "jfa+sweep"):
        dist = fast_sweep(dist, jnp.isinf(dist), sweeps)
    return dist


def distance_field(
    mesh: Mesh,
    grid: Grid,
    *,
    method: str = "jfa-separable",
    signed: bool = True,
    band: int | None = None,
    sweeps: int = 3,
    sign: str = "auto",
    max_bytes: int | None = None,
) -> Float32[Array, "R R R"]:
    """Distance from every voxel centre to the mesh surface, in world units.

    Host-side (it sizes the voxelization and checks memory); the propagation and sign
    steps are compiled once per (resolution, method, band, sweeps). See
    `jaxvox.distance` for how each method works and what error it makes.

    Args:
      mesh: `Mesh` with F faces (validated: NaN/inf vertices or bad indices raise).
      grid: `Grid` of R^3 voxels. Geometry outside the grid is taken into account.
      method: "jfa-separable" (jump flooding one axis at a time: the most accurate for its
        time on the measurements, within 0.75 voxel of exact), "jfa", "jfa+sweep"
        (narrow band by jump flooding, then fast sweeping: the seed thread's pipeline,
        formerly the default), "sweep", "exact" (brute force, O(R^3 F): small grids)
        or "band" (the narrow band only: +inf beyond it, -inf inside when signed).
      signed: negative inside the mesh (see `solid_voxelize` for the sign).
      band: separable 3x3x3 jump-flooding passes around the surface voxels before the
        propagation (exact distances within that many voxels of the surface voxels);
        default 1 for "jfa+sweep", 4 for "band", 0 otherwise; ignored by "exact".
      sweeps: fast-sweeping iterations (each visits the 8 diagonal orders), for
        "sweep" and "jfa+sweep".
      sign: "auto", "parity" or "winding" (see `solid_voxelize`).
      max_bytes: refuse builds whose estimated working memory
        (`distance_field_bytes`) exceeds this; default half the physical memory.

    Returns:
      [R, R, R] float32 indexed (i, j, k); +inf everywhere for a mesh without faces.

    Raises:
      JaxvoxError: bad method, band, sweeps, sign or mesh; "parity" sign on a mesh that
        is not watertight; a grid that would not fit in `max_bytes`.
    """
    check_type("distance_field grid", grid, Grid)
    validate_mesh(mesh)
    check_choice("distance_field method", method, METHODS)
    check_choice("distance_field sign", sign, SIGN_METHODS)
    band = {"jfa+sweep": 1, "band": 4}.get(method, 0) if band is None else band
    if method == "exact":
        band = 0
    band = check_int("distance_field band", band, minimum=0)
    sweeps = check_int("distance_field sweeps", sweeps, minimum=1)
    if max_bytes is not None:
        max_bytes = check_int("distance_field max_bytes", max_bytes, minimum=0)
    r = grid.resolution
    check_bytes("distance_field", r, BYTES_PER_VOXEL[method] + (SIGN_BYTES_PER_VOXEL if signed else 0), max_bytes)
    if mesh.num_faces == 0:
        return jnp.full((r, r, r), jnp.inf, jnp.float32)
    if signed:
        sign = sign_method("distance_field sign", mesh, sign)
    dist = box_distance(mesh, grid, (r, r, r), method=method, band=band, sweeps=sweeps)
    if signed:
        inside = solid_inside(mesh, grid_triangles(padded_mesh(mesh), grid), grid, (r, r, r), sign, 2.0)
        dist = jnp.where(inside, -dist, dist)
    return dist * grid.voxel_size


def box_distance(
    mesh: Mesh, grid: Grid, shape: tuple[int, int, int], *, method: str, band: int, sweeps: int, clamped: bool = True
) -> jax.Array:
    """Unsigned distance in voxels [nx, ny, nz] float32 at the centres of the box made of
    the first `shape` voxels of `grid`, by `method` (`mesh` has faces; `clamped`: seed
    the box with the clamped centroids and corners of triangles, see `seed`)."""
    padded = padded_mesh(mesh)
    tris = grid_triangles(padded, grid)
    if method == "exact":
        coords, triangle = jnp.zeros((0, 3), jnp.int32), jnp.zeros(0, jnp.int32)
    else:
        vox = voxelize(padded, grid, mode=CONSERVATIVE, triangle_ids=True, progress=False)
        n = int(vox.count)
        cap = bucket(n, 4096)  # few shapes: similar meshes share the compiled field
        assert vox.triangle is not None  # voxelized with triangle ids
        found, ids = vox.to_numpy(), vox.triangle_ids()  # on the host: no small program per count
        host_coords = np.full((cap, 3), UNUSED, np.int32)
        host_coords[:n] = np.where(np.all(found < np.asarray(shape), axis=1, keepdims=True), found, UNUSED)  # the box
        host_triangle = np.full(cap, UNUSED, np.int32)
        host_triangle[:n] = ids
        coords, triangle = jax.device_put(host_coords), jax.device_put(host_triangle)
    return _unsigned(tris, coords, triangle, shape=shape, method=method, band=band, sweeps=sweeps, clamped=clamped)


def box_grid(origin, voxel_size, shape: tuple[int, int, int]) -> Grid:
    """The cubic grid whose first `shape` voxels form a box: same origin and voxels,
    resolution the power of two >= the box's longest side."""
    return Grid(origin, voxel_size, max(2, 1 << (max(shape) - 1).bit_length()))
