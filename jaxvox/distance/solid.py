"""Solid voxelization: which voxel centres lie inside a triangle mesh.

Two methods, the sign of `jaxvox.distance_field`:

* ``"parity"`` (Schwarz & Seidel): every triangle flips the inside bit of the voxels of
  a +x column beyond the column's crossing, then a prefix XOR along x; exact and
  O(surface), right for watertight meshes only, which `open_edges` checks;
* ``"winding"``: the generalized winding number, inside where it exceeds 1/2, by
  `jaxvox.winding_numbers`' tree of dipoles: right for open meshes with holes, like the
  bunny, and for closed ones.

Both run on boxes of any shape made of a grid's first voxels (the clipmap's scissor
volumes). The helpers without an underscore are shared with `jaxvox.distance`.

Memory: the result costs R^3 bytes, plus temporaries (`SIGN_BYTES_PER_VOXEL` in all);
`solid_voxelize` refuses grids above half the physical memory (`check_bytes`).

`solid_boundary` is the sparse counterpart for rendering: the solid voxels with a face
neighbour outside (all a ray from outside can reach), found from the signed narrow band
of `jaxvox.sparse_distance_field` without any R^3 array.
"""

from __future__ import annotations

import functools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool

from jaxvox._core.buffers import join_rows
from jaxvox._core.checks import check_choice, check_number, check_type, refuse
from jaxvox._core.errors import JaxvoxError
from jaxvox._core.shapes import bucket, expand_counts, voxel_bucket
from jaxvox.distance.sparse import band_regions
from jaxvox.distance.topology import welded_faces
from jaxvox.distance.winding import box_winding_numbers
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, pad_mesh, validate_mesh
from jaxvox.voxelize import REGION_SIZE, SOLID_BOUNDARY, UNUSED, Voxels

SIGN_METHODS = ("auto", "parity", "winding")
SIGN_BYTES_PER_VOXEL = 16  # peak working memory per voxel of a solid voxelization (bytes)
# `solid_boundary` reads the signed band of half width 1: around a watertight mesh, a
# boundary voxel and its outside neighbour both lie in it (the segment between their
# centres, of length 1, crosses the surface).
BOUNDARY_BAND = 1


def open_edges(mesh: Mesh) -> int:
    """Number of edges not shared by an even number of faces (0 for a watertight mesh).

    Vertices at equal positions are welded first, so seams of duplicated vertices
    (texture or normal seams) do not count as holes; zero-length edges are ignored.

    Args:
      mesh: `Mesh` with F faces.

    Returns:
      int, host-side.

    Raises:
      JaxvoxError: not a `Mesh`.
    """
    check_type("open_edges mesh", mesh, Mesh)
    v = np.asarray(mesh.vertices)
    if mesh.num_faces == 0:
        return 0
    f = welded_faces(v, np.asarray(mesh.faces))
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    _, counts = np.unique(e[:, 0] * len(v) + e[:, 1], return_counts=True)
    return int(np.sum(counts % 2))


def _parity_columns(tris, shape: tuple[int, int, int]):
    """Per triangle: first (j, k) column and the number of columns (j, k) its yz box covers."""
    yz = jnp.asarray(shape[1:])
    lo = jnp.clip(jnp.ceil(tris.min(1)[:, 1:] - 0.5), 0, yz)
    hi = jnp.clip(jnp.floor(tris.max(1)[:, 1:] - 0.5), -1, yz - 1)
    n = jnp.maximum(hi - lo + 1, 0).astype(jnp.int32)
    live = jnp.all(jnp.isfinite(tris), (1, 2)) & (tris.min(1)[:, 0] < shape[0])
    return lo.astype(jnp.int32), jnp.where(live, n[:, 0] * n[:, 1], 0), n[:, 1]


@functools.partial(jax.jit, static_argnames=("shape",))
def _parity_count(tris, *, shape):
    return jnp.sum(_parity_columns(tris, shape)[1])


@functools.partial(jax.jit, static_argnames=("shape", "capacity"))
def _parity(tris, *, shape: tuple[int, int, int], capacity: int):
    """Schwarz & Seidel's solid voxelization of a box of `shape` voxels (triangles in its
    units): [nx, ny, nz] bool, voxel centres inside.

    For every (triangle, column (j, k) whose centre the triangle's yz projection covers)
    the voxels of the column beyond the crossing flip; a prefix XOR along x gives the
    parity of crossings before each centre. Coverage uses edge functions evaluated
    with each edge's endpoints in a canonical order, and the top-left rule on the
    edges, so that a column through a shared edge or vertex is counted exactly once.
    """
    lo, n_cols, nk = _parity_columns(tris, shape)
    tri, rank, valid, _ = expand_counts(n_cols, capacity)
    j = lo[tri, 0] + rank // jnp.maximum(nk[tri], 1)
    k = lo[tri, 1] + rank % jnp.maximum(nk[tri], 1)
    t = tris[tri]  # [C, 3, 3]
    yz = t[:, :, 1:]
    c = jnp.stack([j, k], -1).astype(jnp.float32) + 0.5
    p, q = yz, jnp.roll(yz, -1, axis=1)  # edge p -> q
    swap = (p[..., 0] > q[..., 0]) | ((p[..., 0] == q[..., 0]) & (p[..., 1] > q[..., 1]))
    lo_e = jnp.where(swap[..., None], q, p)
    d = jnp.where(swap[..., None], p - q, q - p)
    e = d[..., 0] * (c[:, None, 1] - lo_e[..., 1]) - d[..., 1] * (c[:, None, 0] - lo_e[..., 0])
    normal = jnp.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    orient = jnp.sign(normal[:, 0])  # +1: counter-clockwise in (y, z)
    sign = jnp.where(swap, -1.0, 1.0) * orient[:, None]
    e = e * sign
    gy, gz = -d[..., 1] * sign, d[..., 0] * sign  # gradient of e: the inward edge normal
    top_left = (gy > 0) | ((gy == 0) & (gz > 0))
    covered = jnp.all((e > 0) | ((e == 0) & top_left), axis=1) & valid & (orient != 0)
    nx = jnp.where(orient != 0, normal[:, 0], 1.0)
    x = t[:, 0, 0] - (normal[:, 1] * (c[:, 0] - t[:, 0, 1]) + normal[:, 2] * (c[:, 1] - t[:, 0, 2])) / nx
    i = jnp.clip(jnp.ceil(x - 0.5), 0, shape[0]).astype(jnp.int32)  # first voxel whose centre is beyond
    n = math.prod(shape)
    flat = jnp.where(covered & (i < shape[0]), (i * shape[1] + j) * shape[2] + k, n)  # C order
    flips = jnp.zeros(n, jnp.int32).at[flat].add(1, mode="drop").reshape(shape)
    return (jnp.cumsum(flips, axis=0) & 1).astype(bool)


@jax.jit
def grid_triangles(mesh: Mesh, grid: Grid):
    return grid.to_grid_units(mesh.triangles())


def padded_mesh(mesh: Mesh) -> Mesh:
    """`mesh` padded to a power-of-two number of faces with ``(0, 0, 0)`` faces (points at
    vertex 0, on the surface: they change no distance, cross no ray and subtend no solid
    angle) and of vertices (copies of vertex 0, used by no face), its geometry only (no
    colours, uvs or texture), so that meshes of similar size share compiled code."""
    geometry = Mesh(mesh.vertices, mesh.faces)
    return pad_mesh(geometry, bucket(mesh.num_vertices, 256), bucket(mesh.num_faces, 256))


def sign_method(what: str, mesh: Mesh, method: str) -> str:
    """`method` of `SIGN_METHODS` for `mesh`: "auto" becomes "parity" for a watertight mesh,
    else "winding"; "parity" on a mesh with open edges is refused (`what` names the method)."""
    if method == "winding" or mesh.num_faces == 0:
        return method
    holes = open_edges(mesh)
    if method == "auto":
        return "winding" if holes else "parity"
    if holes:
        raise refuse(
            what,
            f"'parity' needs a watertight mesh, but {holes} edges are not shared by an even "
            "number of faces (holes or non-manifold edges); use 'winding' for open meshes",
            method,
        )
    return method


def solid_inside(mesh: Mesh, tris, grid: Grid, shape: tuple[int, int, int], method: str, beta: float):
    """Inside bits [nx, ny, nz] of the voxel centres of the box made of the first `shape`
    voxels of `grid` (`tris`: `mesh`'s padded triangles in grid units, for parity; the
    winding number reads `mesh`; `method`: "parity" or "winding", see `sign_method`)."""
    if mesh.num_faces == 0:
        return jnp.zeros(shape, bool)
    if method == "parity":
        return parity_boxes([(tris, shape)])[0]
    return (
        box_winding_numbers(mesh, np.asarray(grid.origin, np.float64), float(grid.voxel_size), shape, beta=beta) > 0.5
    )


def parity_boxes(boxes: list) -> list[jax.Array]:
    """The "parity" inside bits of several boxes: [(tris, shape)] (a box's padded
    triangles in its grid units, [nx, ny, nz] voxels) -> [nx, ny, nz] bool each. Every
    box's crossing count, then every box's voxelization, is dispatched before any is
    waited for (the counts size the voxelizations, with the floor of a voxel list: a
    surface's (triangle, column) pairs number about as many as its voxels, so that the
    meshes met at one resolution share one program)."""
    counts = [_parity_count(tris, shape=shape) for tris, shape in boxes]
    return [
        _parity(tris, shape=shape, capacity=voxel_bucket(int(c), max(shape))) for (tris, shape), c in zip(boxes, counts)
    ]


def solid_voxelize(mesh: Mesh, grid: Grid, *, method: str = "auto", beta: float = 2.0) -> Bool[Array, "R R R"]:
    """Voxels whose centre lies inside the mesh: [R, R, R] bool (True inside).

    Args:
      mesh: `Mesh`, outward-facing (counter-clockwise seen from outside) for "winding".
      grid: `Grid` of R^3 voxels; geometry outside it still counts (rays and winding
        numbers see the whole mesh).
      method: "parity" (Schwarz & Seidel: parity of the crossings of the +x ray,
        O(R^3 + surface); exact for watertight meshes, raises for open ones),
        "winding" (generalized winding number > 1/2 at each centre, by
        `jaxvox.winding_numbers`' tree: right for open meshes with holes such as the
        Stanford bunny, and for closed ones), or "auto" (parity when
        `open_edges(mesh) == 0`, else winding).
      beta: the far-field ratio of `jaxvox.winding_numbers` ("winding" only), > 1.

    Raises:
      JaxvoxError: bad method, beta, grid or mesh, "parity" on a mesh that is not
        watertight, or a grid too large (the result costs R^3 bytes plus temporaries).
    """
    check_type("solid_voxelize grid", grid, Grid)
    validate_mesh(mesh)
    check_choice("solid_voxelize method", method, SIGN_METHODS)
    beta = check_number("solid_voxelize beta", beta, above=1.0, finite=False)
    check_bytes("solid_voxelize", grid.resolution, SIGN_BYTES_PER_VOXEL, None)
    method = sign_method("solid_voxelize method", mesh, method)
    r = grid.resolution
    return solid_inside(mesh, grid_triangles(padded_mesh(mesh), grid), grid, (r, r, r), method, beta)


def _default_max_bytes() -> int:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2


def check_bytes(caller: str, resolution: int, per_voxel: int, max_bytes: int | None) -> None:
    """Refuses a grid of `resolution`^3 voxels whose working memory (`per_voxel` bytes
    each) exceeds `max_bytes` (default half the physical memory)."""
    need = resolution**3 * per_voxel
    limit = _default_max_bytes() if max_bytes is None else max_bytes
    if need > limit:
        raise refuse(
            f"{caller} grid resolution",
            f"needs about {need / 2**30:.2f} GiB ({per_voxel} bytes per "
            f"voxel), above max_bytes = {limit / 2**30:.2f} GiB (default: half the physical memory); use "
            "a lower resolution or raise max_bytes",
            resolution,
        )


def solid_boundary(mesh: Mesh, grid: Grid, *, triangle_ids: bool = False, progress: bool | None = None) -> Voxels:
    """The boundary of the solid voxelization: voxels whose centre lies inside the mesh and
    that have a face neighbour whose centre does not (or that lie on the grid's faces),
    both within one voxel of the mesh.

    A ray from outside enters the solid through these voxels, so they render exactly as
    `solid_voxelize`'s set does, with O(surface) voxels. Unlike `jaxvox.voxelize`'s sets,
    which enclose the surface (a conservative voxel touches it, a 6-separating one holds it
    within half a voxel of its centre), they straddle it: the surface passes within one
    voxel of every centre and runs through or beside the set's outer faces, so silhouettes
    and shading positions are not biased outward by half a voxel.

    Host-side, like `jaxvox.voxelize` (counting passes size everything; not jittable).
    Inside is the generalized winding number above 1/2, as in `sparse_distance_field`'s
    sign; the voxels come from its signed band of half width `BOUNDARY_BAND` (centres
    within one voxel of the mesh, float32 grid units), region by region: memory holds that
    band's voxels (2.3 per boundary voxel on spot at 2048^3) and one region's work, no
    R^3 array.
    Around a watertight mesh every boundary voxel and the neighbour that exposes it lie in
    the band, so the set is exactly the solid's boundary.
    Across the holes of an open mesh (the Stanford bunny's base) the inside ends where the
    winding number crosses 1/2, away from the mesh: that part of the boundary is kept
    within one voxel of the hole's rim and the rest of the hole stays open, as it is in
    the mesh.

    Args:
      mesh: `Mesh` (validated), outward-facing (counter-clockwise seen from outside).
      grid: `Grid` of R^3 voxels; a solid beyond the grid is cut at its faces, exposed
        there within one voxel of the mesh.
      triangle_ids: also record each voxel's closest triangle (ties to the lower id), for
        `jaxvox.voxel_attributes` (shading normals, colours).
      progress: a progress bar over the regions (None: when there are several).

    Returns:
      `Voxels` in Morton order, mode "solid-boundary", ``overflow == 0``, capacity on the
      voxel-list ladder (`voxel_bucket`); empty for a mesh without faces.

    Raises:
      JaxvoxError: a malformed mesh, not a `Grid`, or `triangle_ids` not a bool.
    """
    check_type("solid_boundary grid", grid, Grid)
    validate_mesh(mesh)
    if not isinstance(triangle_ids, (bool, np.bool_)):
        raise refuse("solid_boundary triangle_ids", "must be True or False", triangle_ids)
    r = grid.resolution
    size = min(REGION_SIZE, r)
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = [
        (np.zeros((0, 3), np.int32), np.zeros(0, bool), np.zeros(0, np.int32))
    ]
    for coords, dist, closest, done in band_regions(mesh, grid, BOUNDARY_BAND, True, size, progress, _no_build):
        done.result()  # the region's values are final
        parts.append((coords, dist < 0, closest))
    ijk, inside, tri = (np.concatenate(column) for column in zip(*parts))
    rows = np.flatnonzero(_exposed(ijk, inside, r))
    n = len(rows)
    if n > 2**31 - 1:  # `Voxels.count` is int32
        raise JaxvoxError(f"solid_boundary: {n:,} voxels at {r}^3, more than an int32 count holds")
    capacity = voxel_bucket(n, r)
    to_device = functools.partial(jax.device_put, may_alias=True)  # aligned buffers: no copy
    coords = to_device(join_rows([ijk[rows]], (capacity, 3), UNUSED, np.int32))
    ids = to_device(join_rows([tri[rows]], (capacity,), UNUSED, np.int32)) if triangle_ids else None
    return Voxels(coords, jnp.int32(n), jnp.int32(0), ids, grid, SOLID_BOUNDARY)


def _no_build(keys, region_lo) -> None:
    """`band_regions`' per-region step: nothing (the regions' voxels are all we need)."""


def _exposed(ijk: np.ndarray, inside: np.ndarray, resolution: int) -> np.ndarray:
    """[n] bool: which voxels ijk (int32 [n, 3], no repeats) are inside (`inside`, [n]
    bool) with a face neighbour among those that are not, or lie on the grid's faces
    (int64 linear keys; a neighbour key that wraps to another row belongs to a voxel on
    the grid's faces, which counts anyway)."""
    r = np.int64(resolution)
    key = (ijk[:, 0].astype(np.int64) * r + ijk[:, 1]) * r + ijk[:, 2]
    outside = np.sort(key[~inside])
    rows = np.flatnonzero(inside)
    order = np.argsort(key[rows])  # sorted queries: neighbouring binary searches
    rows = rows[order]
    mine = key[rows]
    exposed = ((ijk[rows] == 0) | (ijk[rows] == resolution - 1)).any(axis=1)
    if len(outside):
        for step in (1, r, r * r):
            for shift in (-step, step):
                query = mine + shift
                at = np.minimum(np.searchsorted(outside, query), len(outside) - 1)
                exposed |= outside[at] == query
    out = np.zeros(len(ijk), bool)
    out[rows[exposed]] = True
    return out
