"""Sparse narrow-band signed distance fields: exact distances at the voxels near the surface.

`sparse_distance_field` keeps only the *band voxels*, those whose centre lies within
``band`` voxel edges of the surface (distance ``<= band * h``), with their exact float32
distance to the mesh, and `sample` interpolates them trilinearly under `jax.jit`.

Method (no propagation, so no propagation error):

* **Pairs.** A band voxel's centre lies within ``band`` of its closest triangle, so it lies
  in that triangle's bounding box dilated by ``band`` (grid units). Space is cut into
  aligned bricks of ``BRICK^3`` voxels. The host splits each triangle's dilated,
  grid-clipped box at brick boundaries (one *item* per (triangle, brick)), orders the
  items by the Morton code of their brick and packs consecutive bricks into groups of
  `BRICKS` (the counting pass). A jitted kernel walks a group's (triangle, voxel) pairs,
  `TRIANGLE_CHUNK` items at a time, in fixed windows of `WINDOW` pairs
  (`jaxvox._shapes.expand_counts`), evaluates the float32 point-triangle distance in grid
  units relative to the brick (`jaxvox._geometry.point_triangle_dist2`), keeps pairs
  within ``band`` and scatter-mins their distance bits (non-negative float32 bits order
  like the floats) into the brick cell, with the triangle id of the minimum (lowest id on
  ties). Cells are laid out in Morton order within each brick, so compacting a group's
  set cells yields its band voxels in global Morton order: no merge is needed, and every
  voxel is final when its brick is. The group's bricks are local scratch (8 MiB), not a
  grid-sized array; all shapes are fixed, so a new mesh compiles nothing new.
* **Sign** (`jaxvox.band_sign`): negative where the generalized winding number exceeds
  1/2. Pseudo-normals of the closest feature for watertight meshes without crossing or
  irregular triangles; for every other mesh, the boundary is closed by caps (fans), the
  band voxels are joined into components by moves that provably cross neither mesh nor
  caps, and one fast winding number per component (plus the exact cap term near the caps)
  signs all its voxels. Measured on the shared meshes at 32^3-64^3 and on generated
  damaged meshes: every sign equals the brute-force winding number's.

Nothing of size R^3 is allocated; the work is O(sum over triangles of their dilated
boxes), at least ``(2 band + 1)^3`` pairs per triangle. Host memory: about 32 bytes per
band voxel while the groups' results are gathered, then the `SparseField` itself.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Float32

from jaxvox import morton
from jaxvox._checks import check_int, check_type, refuse
from jaxvox._geometry import point_triangle_dist2
from jaxvox._pytree import pytree_dataclass
from jaxvox._shapes import bucket, expand_counts
from jaxvox.band_sign import band_signs, pad_rows
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, host_triangles, validate_mesh
from jaxvox.octree import Octree, build_octree, voxel_index
from jaxvox.voxelize import CONSERVATIVE, UNUSED, Voxels

WINDOW = 1 << 17  # (triangle, voxel) pairs evaluated per call of the pair kernel
TRIANGLE_CHUNK = 1 << 12  # triangle boxes per chunk of the pair kernel
BRICK = 32  # edge of a chunk's scratch brick of voxels (BRICK^3 cells, 8 bytes each)
BRICKS = 32  # bricks (chunks) handled together by one group of kernel calls
_CELLS = BRICK**3
_CELL_BITS = 3 * (BRICK.bit_length() - 1)  # Morton bits of a cell within its brick
_GROUP_CELLS = BRICKS * _CELLS
_FAR_BITS = np.uint32(0x7F800000)  # float32 bits of +inf: a brick cell without a pair
_NO_TRIANGLE = np.int32(np.iinfo(np.int32).max)
MAX_BAND = 64  # largest accepted `band` (voxels)
UNUSED_VALUE = np.float32(np.inf)  # `SparseField.values` past `count`


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class SparseField:
    """A narrow-band signed distance field: the band voxels and their distances.

    Attributes:
      voxels: the band voxels (`Voxels`, Morton order, mode "conservative"): every voxel
        whose centre lies within ``band * h`` of the surface. ``voxels.triangle`` holds
        each voxel's closest triangle (ties to the lower id).
      values: [capacity] float32 distances in world units aligned with ``voxels.coords``
        (negative inside when signed); slots past `count` hold `UNUSED_VALUE` (+inf).
      tree: `Octree` of the band voxels (`build_octree`), for `voxel_index` lookups.
      grid: the `Grid`.
      band: static int, the half width in voxels (changing it recompiles consumers).
    """

    voxels: Voxels
    values: Float32[Array, " capacity"]  # [capacity] float32
    tree: Octree
    grid: Grid
    band: int = dataclasses.field(metadata=dict(static=True))

    @property
    def count(self) -> jax.Array:
        """[] int32 number of band voxels."""
        return self.voxels.count


# --------------------------------------------------------------------------------------
# Jitted cores (static shapes: WINDOW, TRIANGLE_CHUNK, BRICKS * BRICK^3, POINT_CHUNK,
# bucketed face counts)
# --------------------------------------------------------------------------------------


@functools.partial(jax.jit, donate_argnums=(0, 1))
def _pair_window(bits, tri, tris, ids, slot, lo, ext, counts, start, band):
    """Scatter-min of one window of (triangle, voxel) pairs into a group's bricks.

    Args:
      bits: [BRICKS * BRICK^3] uint32 float32 bits of the smallest squared distance per
        brick cell (`_FAR_BITS` where none); tri: [BRICKS * BRICK^3] int32 its triangle
        (lowest id on ties).
      tris: [T, 3, 3] float32 triangles in grid units relative to their brick's origin;
      ids: [T] int32 their mesh ids; slot: [T] int32 their brick; lo, ext: [T, 3] int32
      first voxel (in the brick) and extent of each item's box; counts: [T] int32
      ``prod(ext)``; start: [] int32 first pair of the window; band: [] float32.

    Returns:
      The updated (bits, tri).
    """
    owner, rank, valid, _ = expand_counts(counts, WINDOW, start)
    e = ext[owner]
    k = rank % e[:, 2]
    j = (rank // e[:, 2]) % e[:, 1]
    i = rank // (e[:, 2] * e[:, 1])
    ijk = lo[owner] + jnp.stack([i, j, k], -1)
    t = tris[owner]
    d2 = point_triangle_dist2(ijk.astype(jnp.float32) + 0.5, t[:, 0], t[:, 1], t[:, 2])
    keep = valid & (d2 <= band * band)
    local = morton.encode_word(ijk).astype(jnp.int32)  # Morton order within the brick
    cell = jnp.where(keep, slot[owner] * _CELLS + local, _GROUP_CELLS)
    b = jax.lax.bitcast_convert_type(jnp.maximum(d2, 0.0), jnp.uint32)  # sorts like the float
    new = bits.at[cell].min(b, mode="drop")
    at = jnp.minimum(cell, _GROUP_CELLS - 1)
    smaller = new[at] < bits[at]  # a smaller distance arrived: forget the cell's old id
    tri = tri.at[jnp.where(smaller, cell, _GROUP_CELLS)].set(_NO_TRIANGLE, mode="drop")
    mine = jnp.where(b == new[at], ids[owner], _NO_TRIANGLE)
    return new, tri.at[cell].min(mine, mode="drop")


@jax.jit
def _extract(bits, tri):
    """The set cells of a group's bricks, compacted: (cell [G] int32, d2 [G] float32,
    tri [G] int32, n [] int32), ``G = BRICKS * BRICK^3``; slots past n are padding."""
    keep = bits != _FAR_BITS
    slot = jnp.where(keep, jnp.cumsum(keep) - 1, _GROUP_CELLS)
    cells = jnp.arange(_GROUP_CELLS, dtype=jnp.int32)
    cell = jnp.zeros(_GROUP_CELLS + 1, jnp.int32).at[slot].set(cells)[:_GROUP_CELLS]
    return cell, jax.lax.bitcast_convert_type(bits[cell], jnp.float32), tri[cell], jnp.sum(keep)


@functools.partial(jax.jit, static_argnames="size")
def _head(arrays, size: int):
    """The first `size` entries of each array (`size` on the shape ladder)."""
    return tuple(a[:size] for a in arrays)


@jax.jit
def _fresh_brick():
    return jnp.full(_GROUP_CELLS, _FAR_BITS, jnp.uint32), jnp.full(_GROUP_CELLS, _NO_TRIANGLE, jnp.int32)


# --------------------------------------------------------------------------------------
# Host side
# --------------------------------------------------------------------------------------


def _items(tris: np.ndarray, shape, band: int):
    """Every triangle's dilated voxel box, clipped to the box of `shape` (an int R for R^3,
    or [3] ints), split at brick boundaries: (triangle
    id [n] int64, brick [n, 3] int64, lo [n, 3] int64, hi [n, 3] int64 inclusive voxel
    bounds), in Morton order of the bricks."""
    lo = np.maximum(np.ceil(tris.min(1) - band - 0.5), 0).astype(np.int64)
    hi = np.minimum(np.floor(tris.max(1) + band - 0.5), np.asarray(shape) - 1).astype(np.int64)
    ids = np.flatnonzero((hi >= lo).all(1))
    lo, hi = lo[ids], hi[ids]
    first, last = lo // BRICK, hi // BRICK
    per_axis = last - first + 1
    counts = per_axis.prod(1)
    owner = np.repeat(np.arange(len(ids)), counts)
    rank = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    n = per_axis[owner]
    brick = first[owner] + np.stack([rank // (n[:, 1] * n[:, 2]), (rank // n[:, 2]) % n[:, 1], rank % n[:, 2]], -1)
    order = np.argsort(morton.encode_host(brick), kind="stable")
    brick, owner = brick[order], owner[order]
    tile_lo = np.maximum(lo[owner], brick * BRICK)
    tile_hi = np.minimum(hi[owner], brick * BRICK + BRICK - 1)
    return ids[owner], brick, tile_lo, tile_hi


def band_pairs(tris: np.ndarray, shape, band: int):
    """Per-voxel minima over all triangles in the box of voxels ``0 <= ijk < shape``.

    Args:
      tris: [F, 3, 3] float64 triangles in grid units of the box (voxel ijk has its centre
        at ijk + 1/2); triangles outside the box count where within `band` of it.
      shape: int R (an R^3 box) or [3] ints, each below 2^20.
      band: half width in voxels.

    Returns:
      (ijk int64 [n, 3], d2 float32 [n] squared distance in grid units, tri int32 [n]
      closest triangle, lower id on ties, keys uint64 [n] Morton codes) for every voxel
      within `band`, in Morton order
      (see the module docstring).
    """
    ids, brick, lo, hi = _items(tris, shape, band)
    starts = np.flatnonzero(np.concatenate([[True], (brick[1:] != brick[:-1]).any(1)])) if len(ids) else ids
    bounds = np.append(starts, len(ids))  # items of brick b: bounds[b] .. bounds[b + 1]
    parts = []
    bits, tri = _fresh_brick()
    for g in range(0, len(starts), BRICKS):
        s, e = int(bounds[g]), int(bounds[min(g + BRICKS, len(starts))])
        origins = brick[starts[g : g + BRICKS]] * BRICK
        slot = np.searchsorted(bounds[g : g + BRICKS + 1], np.arange(s, e), side="right") - 1
        for c in range(s, e, TRIANGLE_CHUNK):
            rows = np.arange(c, min(c + TRIANGLE_CHUNK, e))
            origin = origins[slot[rows - s]]
            ext = hi[rows] - lo[rows] + 1
            counts = ext.prod(1)
            pad = lambda a, fill=0: jnp.asarray(pad_rows(a, TRIANGLE_CHUNK, fill))
            args = (
                pad((tris[ids[rows]] - origin[:, None]).astype(np.float32)),
                pad(ids[rows].astype(np.int32)),
                pad(slot[rows - s].astype(np.int32)),
                pad((lo[rows] - origin).astype(np.int32)),
                pad(ext.astype(np.int32), 1),
                pad(counts.astype(np.int32)),
            )
            for start in range(0, int(counts.sum()), WINDOW):
                bits, tri = _pair_window(bits, tri, *args, jnp.int32(start), jnp.float32(band))
        cell, d2, t, n = _extract(bits, tri)
        bits, tri = _fresh_brick()
        n = int(n)
        if n:  # sliced to the ladder on the device, exactly on the host: no program per n
            cell, d2, t = (np.asarray(x)[:n] for x in _head((cell, d2, t), size=bucket(n)))
            k, local = np.divmod(cell, _CELLS)
            code = morton.encode_host(origins // BRICK)[k] << np.uint64(_CELL_BITS) | local.astype(np.uint64)
            parts.append((origins[k] + morton.decode_word_host(local), d2, t, code))
    if not parts:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros(0, np.uint64)
    ijk, d2, t, code = (np.concatenate(x) for x in zip(*parts))
    return ijk, d2, t, code


def sparse_distance_field(mesh: Mesh, grid: Grid, *, band: int = 3, signed: bool = True) -> SparseField:
    """The narrow-band distance field of `mesh`: exact distances at the band voxels.

    Host-side (counting passes size the work; see the module docstring for the method and
    its cost). Band voxels are those whose centre lies within ``band * h`` of the surface
    (``h = grid.voxel_size``; in float32 grid units, ``d <= band``).

    Args:
      mesh: `Mesh` (validated); for the sign, outward (counter-clockwise) orientation.
      grid: `Grid` of R^3 voxels (geometry outside it is clipped: only voxels in the grid
        exist).
      band: half width in voxels, an int in ``[0, MAX_BAND]``. ``band=0`` keeps only
        voxels whose centre lies on the surface (usually none).
      signed: negative inside (pseudo-normals for watertight meshes, winding numbers
        otherwise); False gives unsigned distances.

    Returns:
      A `SparseField` (empty, ``count == 0``, for a mesh without faces).

    Raises:
      JaxvoxError: a malformed mesh, not a `Grid`, a bad `band` or `signed`, or a
        triangle whose dilated box holds more than about 2^31 voxels.
    """
    validate_mesh(mesh)
    check_type("sparse_distance_field grid", grid, Grid)
    band = check_int("sparse_distance_field band", band, minimum=0, maximum=MAX_BAND)
    if not isinstance(signed, (bool, np.bool_)):
        raise refuse("sparse_distance_field signed", "must be True or False", signed)
    origin = np.asarray(grid.origin, np.float64)
    h = float(grid.voxel_size)
    tris = (host_triangles(mesh) - origin) / h
    ijk, d2, tri, keys = band_pairs(tris, grid.resolution, band)
    n = len(ijk)
    capacity = bucket(n)
    dist = np.sqrt(d2.astype(np.float64))
    if signed and n:
        dist = dist * band_signs(mesh, tris, ijk, keys, dist, tri, band)
    values = pad_rows((dist * h).astype(np.float32), capacity, UNUSED_VALUE)
    voxels = Voxels(
        jnp.asarray(pad_rows(ijk.astype(np.int32), capacity, UNUSED)),
        jnp.int32(n),
        jnp.int32(0),
        jnp.asarray(pad_rows(tri.astype(np.int32), capacity, UNUSED)),
        grid,
        CONSERVATIVE,
    )
    return SparseField(voxels, jnp.asarray(values), build_octree(voxels), grid, band)


_CORNERS = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], np.int32)  # [8, 3] xyz bits


def sample(
    field: SparseField, points: Float[ArrayLike, "*batch 3"]
) -> tuple[Float32[Array, " *batch"], Bool[Array, " *batch"]]:
    """Trilinear interpolation of a sparse field at world points; pure and jittable.

    The 8 voxel centres around each point are looked up in ``field.tree``. A neighbour
    outside the band (or the grid) takes ``s * band * h``, where ``s`` is -1 if the sum of
    the present neighbours' values is negative and +1 otherwise (also when none is
    present): the clamp of a truncated field, with the sign known from the band.
    Differentiable with respect to `points` (piecewise trilinear) and ``field.values``.

    Args:
      field: a `SparseField`.
      points: [..., 3] float world coordinates.

    Returns:
      (values [...] float32 world units, inside_band [...] bool: all 8 neighbours present,
      so the value is the exact trilinear interpolation of band values).

    Raises:
      JaxvoxError: not a `SparseField`, or `points` without a last axis of 3.
    """
    return _sample(field, checked_points("sample", field, points))


def checked_points(what: str, field: SparseField, points) -> jax.Array:
    """`points` as float32 [..., 3] after checking that `field` is a `SparseField` and the
    points have a last axis of 3 (`JaxvoxError` naming ``what``)."""
    check_type(f"{what} field", field, SparseField)
    if np.shape(points)[-1:] != (3,):
        raise refuse(f"{what} points", "must have shape [..., 3]", np.shape(points))
    return jnp.asarray(points, jnp.float32)


@jax.jit
def _sample(field: SparseField, points: jax.Array):
    g = field.grid.to_grid_units(points) - 0.5
    base = jnp.floor(jax.lax.stop_gradient(g))
    frac = g - base
    ijk = base.astype(jnp.int32)[..., None, :] + _CORNERS  # [..., 8, 3]
    idx = voxel_index(field.tree, ijk)
    present = idx >= 0
    v = field.values[jnp.maximum(idx, 0)]
    v = jnp.where(present, v, 0.0)
    far = jnp.float32(field.band) * field.grid.voxel_size
    s = jnp.where(jnp.sum(jax.lax.stop_gradient(v), -1) < 0, -1.0, 1.0)
    v = jnp.where(present, v, (s * far)[..., None])
    w = jnp.where(_CORNERS == 1, frac[..., None, :], 1.0 - frac[..., None, :]).prod(-1)
    return jnp.sum(w * v, -1), jnp.all(present, -1)
