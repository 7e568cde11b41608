"""Sparse narrow-band signed distance fields: exact distances at the voxels near the surface.

`sparse_distance_field` keeps only the *band voxels*, those whose centre lies within
``band`` voxel edges of the surface (distance ``<= band * h``), with their exact float32
distance to the mesh, and `sample` interpolates them trilinearly under `jax.jit`.

Method (no propagation, so no propagation error):

* **Pairs.** A band voxel's centre lies within ``band`` of its closest triangle, so it lies
  in that triangle's bounding box dilated by ``band`` (grid units). Space is cut into
  aligned tiles of ``TILE^3`` voxels. The host lists the tiles each triangle's dilated,
  grid-clipped box overlaps (one *item* per (triangle, tile)), orders the items by the
  Morton code of their tile, then by triangle, and deals each tile's triangles into work
  units of `SLOTS` (the counting pass). A jitted kernel of fixed shape evaluates every
  cell of a unit's tile against each of its triangles (`jaxvox._core.geometry.rows_dist2`:
  float32 grid units relative to the tile, from per-triangle rows computed once in
  float64, the first corner carried as a float32 pair so that no precision is lost far
  from the origin; no division per pair) and keeps the minimum and its triangle (the
  lowest id on ties); the host merges the units of a tile and keeps the cells within
  ``band``. Dense tiles cost no scatter, which XLA's CPU backend runs slowly. The host
  works in rounds of at most `ROUND_UNITS` units (whole tiles), whose arrays are small
  enough to reuse memory (first touches of fresh memory cost more here than the
  arithmetic) and which fill whole kernel calls (only a round's last call is padded,
  by less than a tile's units). Cells are numbered
  in Morton order within a tile, so the band voxels come out in global Morton order, no merge needed; all shapes
  are fixed, so a new mesh compiles nothing new.
* **Sign** (`jaxvox.distance.band_sign`): negative where the generalized winding number exceeds
  1/2. Pseudo-normals of the closest feature for watertight meshes without crossing or
  irregular triangles; for every other mesh, the boundary is closed by caps (fans), the
  band voxels are joined into components by moves that provably cross neither mesh nor
  caps, and one fast winding number per component (plus the exact cap term near the caps)
  signs all its voxels. Measured on the shared meshes at 32^3-64^3 and on generated
  damaged meshes: every sign equals the brute-force winding number's.

Nothing of size R^3 is allocated (the field's buffers are reserved for every voxel of
the grid as address space only, and take memory as the band is written into them); the
work is O(sum over triangles of the tiles their dilated boxes overlap). The grid is built
in aligned regions (`sparse_distance_field`'s ``region``), so the working memory follows
one region, and the result is the `SparseField` itself (the peak is the field plus one
region's work), or one region's field at a time (`sparse_field_regions`); measured peaks
are in ``experiments/results/sparse_distance.md``.

Precision: the tile kernel's float32 error grows with the closest triangle's size (up to
about `jaxvox.distance.band_sign.F32_ERROR` per grid unit of its longest edge); voxels of
triangles longer than `jaxvox.distance.band_sign.REFINE_EDGE` get float64 distances
(`jaxvox.distance.band_sign.exact_closest`), so every value stays within 1e-4 voxel.
"""

from __future__ import annotations

import dataclasses
import functools
import mmap
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Float32, Int32

from jaxvox import morton
from jaxvox._core.buffers import aligned_empty, join_rows, progress_off, release_free_memory, reserved_empty
from jaxvox._core.checks import check_int, check_type, refuse
from jaxvox._core.geometry import corner_bounds, rows_dist2, triangle_rows
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.shapes import band_bucket, bucket, chunk_rows, pad_rows
from jaxvox.distance.band_sign import REFINE_EDGE, Sides, exact_closest, longest_edges, prepare_signs
from jaxvox.distance.topology import edge_table, welded_faces
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, host_triangles, validate_mesh
from jaxvox.octree import Octree, expand, voxel_index
from jaxvox.octree.stream import check_count, check_region, finish_dag, merge_all, push_region
from jaxvox.voxelize import CONSERVATIVE, UNUSED, Voxels

TILE = 4  # edge of a tile of voxels evaluated together (TILE^3 cells)
SLOTS = 4  # triangles per work unit (a tile overlapped by more takes several); 4 pads less than 8
UNITS = 1 << 13  # work units per call of the tile kernel
ROUND_UNITS = 4 * UNITS  # work units per host round: its arrays stay small enough to reuse memory
CULL_CHUNK = 1 << 16  # items per call of the cull kernel
TRIM_ROWS = 1 << 16  # band voxels found between two returns of freed heap memory (`release_free_memory`)
_REACH = float(np.sqrt(3) * (TILE - 1) / 2)  # farthest cell centre from its tile's centre (voxels)
CULL_SLACK = 1e-2  # voxels: far above the float32 error of the cull's distance
_CELLS = TILE**3
_CELL_BITS = 3 * (TILE.bit_length() - 1)  # Morton bits of a cell within its tile
_LOCAL = morton.decode_word_host(np.arange(_CELLS)).astype(np.int64)  # [TILE^3, 3] cells in Morton order
_FAR = 1e9  # corners of the padding triangle (grid units)
MAX_BAND = 64  # largest accepted `band` (voxels)
UNUSED_VALUE = np.float32(np.inf)  # `SparseField.values` past `count`


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class SparseField:
    """A narrow-band signed distance field: the band voxels and their distances.

    Attributes:
      voxels: the band voxels (`Voxels`, Morton order, mode "conservative"): every voxel
        whose centre lies within ``band * h`` of the surface. ``voxels.triangle`` holds
        each voxel's closest triangle (ties to the lower id). None in a compact field
        (``compact=True``): the tree alone stands for the voxels (`voxel_coords`).
      values: [capacity] float32 distances in world units, in Morton order of the band
        voxels (aligned with ``voxels.coords``; the value of voxel ijk is at
        ``voxel_index(tree, ijk)``), negative inside when signed; slots past `count` hold
        `UNUSED_VALUE` (+inf).
      tree: `Octree`, the DAG of the band voxels (`build_dag`'s layout), for `voxel_index`
        lookups.
      grid: the `Grid`.
      band: static int, the half width in voxels (changing it recompiles consumers).
    """

    voxels: Voxels | None
    values: Float32[Array, " capacity"]  # [capacity] float32
    tree: Octree
    grid: Grid
    band: int = dataclasses.field(metadata=dict(static=True))

    @property
    def count(self) -> jax.Array:
        """[] int32 number of band voxels."""
        return self.tree.voxel_count.astype(jnp.int32) if self.voxels is None else self.voxels.count

    def voxel_coords(self) -> Int32[Array, "count 3"]:
        """[count, 3] int32 voxel indices of the band voxels in Morton order (host-side):
        ``voxels.coords``, or in a compact field the tree's voxels (`jaxvox.octree.expand`)."""
        voxels = self.voxels if self.voxels is not None else expand(self.tree)
        return jax.device_put(np.asarray(voxels.coords)[: int(self.count)])  # cut on the host: no program per count

    def memory(self) -> dict[str, float]:
        """Bytes the field holds, by part (host ints; buffers at their capacity, padding
        included): ``coords`` (int32 ijk per slot, 0 in a compact field), ``triangles``
        (int32 closest triangle per slot, 0 in a compact field), ``values`` (float32 per
        slot), ``topology`` (the DAG's tables: `Octree.nbytes`), ``other`` (counts, flags
        and the grid), ``total`` (every array leaf of the pytree), and ``per_voxel``
        (total over the band voxels)."""
        voxels = self.voxels
        parts = {
            "coords": 0 if voxels is None else voxels.coords.nbytes,
            "triangles": 0 if voxels is None or voxels.triangle is None else voxels.triangle.nbytes,
            "values": self.values.nbytes,
            "topology": self.tree.nbytes,
        }
        total = sum(x.nbytes for x in jax.tree_util.tree_leaves(self))
        out: dict[str, float] = dict(parts, other=total - sum(parts.values()), total=total)
        out["per_voxel"] = total / max(int(self.count), 1)
        return out


# --------------------------------------------------------------------------------------
# Jitted core (static shapes: SLOTS, UNITS, TILE^3, bucketed face counts)
# --------------------------------------------------------------------------------------


@jax.jit
def _tile_units(rows, ids, origin):
    """The closest of each work unit's triangles to every cell of its tile.

    Args:
      rows: [28, F'] float32 `triangle_rows` of the triangles (grid units); the last
        column is a far-away padding triangle.
      ids: [S, U] int32 each unit's S triangles (ascending; padding F' - 1).
      origin: [3, U] int32 each unit's tile origin (voxels).

    Returns:
      (d2 [U, TILE^3] float32 squared distance in grid units from the cell centres,
      tri [U, TILE^3] int32 the triangle: the first of the slots on ties), cells in Morton
      order within the tile.
    """
    # Cells along the minor axis ([U, TILE^3]): XLA's CPU loops then vectorize over the
    # cells of a unit, with the unit's triangle row a scalar (faster than [TILE^3, U]).
    # The slots are unrolled.
    o = [origin[k].astype(jnp.float32)[:, None] for k in range(3)]
    p = [jnp.asarray(_LOCAL[:, k] + 0.5, jnp.float32)[None, :] for k in range(3)]
    slot_rows = [row[ids] for row in rows]  # 28 x [S, U]
    shape = (ids.shape[1], _CELLS)
    best, tri = jnp.full(shape, jnp.inf, jnp.float32), jnp.zeros(shape, jnp.int32)
    for s in range(ids.shape[0]):  # strictly closer: ties keep the earlier slot (the lower id)
        d2 = rows_dist2(p, [r[s][:, None] for r in slot_rows], o)
        better = d2 < best
        best, tri = jnp.where(better, d2, best), jnp.where(better, ids[s][:, None], tri)
    return best, tri


@jax.jit
def _tile_gaps(rows, ids, origin):
    """Squared distance [N] float32 (grid units) from the centre of each item's tile to
    its triangle: ids [N] int32 triangles, origin [3, N] int32 tile origins (voxels);
    rows as in `_tile_units`."""
    o = [origin[k].astype(jnp.float32) for k in range(3)]
    return rows_dist2([jnp.float32(TILE / 2)] * 3, [row[ids] for row in rows], o)


# --------------------------------------------------------------------------------------
# Host side
# --------------------------------------------------------------------------------------


def _tile_items(tris: np.ndarray, shape, band: int, cell: int = TILE):
    """Every triangle's dilated voxel box, clipped to the box of `shape` (an int R for R^3,
    or [3] ints), as the aligned cells of edge `cell` (tiles, or regions) it overlaps:
    (triangle id [n] int64, cell Morton code [n] uint64), ordered by code, then by
    triangle id (`jaxvox.morton.decode_host` gives the cells)."""
    lo, hi = corner_bounds(tris)
    lo = np.maximum(np.ceil(lo - band - 0.5), 0).astype(np.int64)
    hi = np.minimum(np.floor(hi + band - 0.5), np.asarray(shape) - 1).astype(np.int64)
    ids = np.flatnonzero((hi >= lo).all(1))
    if cell >= np.max(shape):  # one cell: every box lies in it
        return ids, np.zeros(len(ids), np.uint64)
    return morton.box_cells(ids, lo[ids] // cell, hi[ids] // cell)


def band_pairs(
    tris: np.ndarray,
    shape,
    band: int,
    on_round: Callable | None = None,
    out: tuple | None = None,
    decoder: ThreadPoolExecutor | None = None,
):
    """Per-voxel minima over all triangles in the box of voxels ``0 <= ijk < shape``.

    Args:
      tris: [F, 3, 3] float64 triangles in grid units of the box (voxel ijk has its centre
        at ijk + 1/2); triangles outside the box count where within `band` of it.
      shape: int R (an R^3 box) or [3] ints, each at most 1024 (`REGION_SIZE`: a voxel's
        Morton code fits one 30-bit word).
      band: half width in voxels.
      on_round: called as ``on_round(ijk, tri)`` with the band voxels of each round (in
        order) as soon as they are known, e.g. to start device work on them while the
        next rounds are computed. They are views of the outputs, which the caller may
        change later: copy what is kept.
      out: (ijk int32 [m, 3], d2 float32 [m], tri int32 [m]) host arrays to write the
        results into, from their first row; m at least every cell of every tile that
        holds a triangle within `band` (e.g. the box's volume, in whole tiles). Default
        (and for each part given as None): new page-aligned arrays.
      decoder: an executor that decodes each round's voxels (and calls `on_round`), in
        order, while this thread finds the next round; None: this thread does.

    Returns:
      (ijk int32 [n, 3], d2 float32 [n] squared distance in grid units, tri int32 [n]
      closest triangle, lower id on ties, keys uint64 [n] Morton codes) for every voxel
      within `band`, in Morton order (see the module docstring); the first three are
      views of `out` when given.
    """
    nothing = np.zeros((0, 3), np.int32), np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros(0, np.uint64)
    ids, code = _tile_items(tris, shape, band)
    if not len(ids):
        return nothing
    columns = bucket(len(tris) + 1)
    rows = jax.device_put(triangle_rows(pad_rows(tris, columns, _FAR)))
    pad_id = columns - 1
    # The cull: an item whose triangle lies farther than band + _REACH from its tile's
    # centre has no cell within `band` (about 40% of the bunny's items).
    width = chunk_rows(len(ids), CULL_CHUNK)
    culls = []  # every chunk dispatched before the first is waited for
    for s in range(0, len(ids), width):
        origin = morton.decode_word_host(code[s : s + width]) * TILE
        chunk = pad_rows(ids[s : s + width].astype(np.int32), width, pad_id), pad_rows(origin, width).T
        culls.append(_tile_gaps(rows, *(jax.device_put(np.ascontiguousarray(a)) for a in chunk)))
    gap2 = np.concatenate([np.asarray(g) for g in culls])[: len(ids)]
    keep = np.flatnonzero(gap2 <= np.float32((band + _REACH + CULL_SLACK) ** 2))
    ids, code = ids[keep], code[keep]
    if not len(ids):
        return nothing
    starts = morton.run_starts(code)
    counts = np.diff(np.append(starts, len(ids)))
    tile_code = code[starts].astype(np.int64)
    limit = np.float32(band * band)  # compared in float32, as d2 is
    # The outputs, at most every cell of every tile: pages past the band voxels are never
    # touched, so the bound costs address space only, and no parts are joined at the end.
    bound = len(starts) * _CELLS
    # (page-aligned: a single region's outputs become the field's buffers, `_joined`)
    fresh = (((bound, 3), np.int32), ((bound,), np.float32), ((bound,), np.int32))
    ijk, band_d2, band_tri = (
        aligned_empty(*spec) if part is None else part for part, spec in zip(out or (None,) * 3, fresh)
    )
    if min(len(ijk), len(band_d2), len(band_tri)) < bound:
        raise ValueError(f"band_pairs: out has fewer rows than the {bound} cells of its tiles")
    keys = np.empty(bound, np.int64)
    tile_units = -(-counts // SLOTS)
    unit_end = np.cumsum(tile_units)

    def dispatch(t0: int):
        """Starts the kernels of the round from tile t0 (whole tiles, at most ROUND_UNITS
        units unless its first tile has more): (t0, t1, units per tile, [(kernel outputs,
        rows)])."""
        t1 = max(int(np.searchsorted(unit_end, unit_end[t0] - tile_units[t0] + ROUND_UNITS, side="right")), t0 + 1)
        tiles = np.arange(t0, t1)
        n_units = tile_units[tiles]
        owner = np.repeat(tiles, n_units)  # each unit's tile
        rank = np.arange(len(owner)) - np.repeat(np.cumsum(n_units) - n_units, n_units)
        item = (starts[owner] + rank * SLOTS)[:, None] + np.arange(SLOTS)
        mine = item < (starts[owner] + counts[owner])[:, None]
        slot_ids = np.where(mine, ids[np.minimum(item, len(ids) - 1)], pad_id)
        origin = morton.decode_word_host(tile_code[owner]) * TILE
        width = chunk_rows(len(owner), UNITS)
        calls = []
        for u in range(0, len(owner), width):
            args = (
                jax.device_put(pad_rows(slot_ids[u : u + width].astype(np.int32), width, pad_id).T),
                jax.device_put(pad_rows(origin[u : u + width], width).T),
            )
            calls.append((_tile_units(rows, *args), min(width, len(owner) - u)))
        return t0, t1, n_units, calls

    def collect(n: int, t0: int, t1: int, n_units, calls) -> int:
        """Waits for a round's kernels, keeps each cell's closest triangle within the band
        and writes it at row n of the outputs; returns the next free row."""
        # Each unit's (distance, triangle) per cell as one uint64 key: the bits of a
        # non-negative float32 order as the float does, so the least key of a tile's
        # units is the least distance, ties to the lowest triangle id.
        packed = np.empty((int(n_units.sum()), _CELLS), np.uint64)
        u = 0
        for (dc, tc), m in calls:
            units = packed[u : u + m]
            np.left_shift(np.asarray(dc)[:m].view(np.uint32), np.uint64(32), out=units, dtype=np.uint64)
            units |= np.asarray(tc)[:m].view(np.uint32)
            u += m
        # The tiles with the most units first: those with more than j units are a prefix.
        order = np.argsort(-n_units, kind="stable")
        first = (np.cumsum(n_units) - n_units)[order]  # each tile's first unit
        more = np.searchsorted(-n_units[order], -np.arange(int(n_units.max())), side="left")  # tiles with > j units
        best_sorted = packed[first]
        for j in range(1, len(more)):
            np.minimum(best_sorted[: more[j]], packed[first[: more[j]] + j], out=best_sorted[: more[j]])
        best = np.empty_like(best_sorted)
        best[order] = best_sorted
        best_d2 = (best >> np.uint64(32)).astype(np.uint32).view(np.float32)
        best_tri = best.astype(np.uint32).view(np.int32)  # (the low 32 bits)
        flat = np.flatnonzero(best_d2.reshape(-1) <= limit)  # tile order, then Morton order within
        part = slice(n, n + len(flat))
        # A cell's code is its tile's code, then its own bits: flat + (code - row) * 2^bits.
        keys[part] = flat + ((tile_code[t0:t1] - np.arange(t1 - t0)) << _CELL_BITS)[flat >> _CELL_BITS]
        band_d2[part], band_tri[part] = best_d2.reshape(-1)[flat], best_tri.reshape(-1)[flat]
        if decoder is None:
            decode_round(part)
        else:
            decoding.append(decoder.submit(decode_round, part))
        return n + len(flat)

    def decode_round(part: slice) -> None:
        """Decodes the voxels of rows `part` from their keys and hands them to `on_round`."""
        morton.decode_word_host(keys[part], out=ijk[part])
        if on_round is not None and part.stop > part.start:
            on_round(ijk[part], band_tri[part])

    # The kernels of each round run (asynchronously, on XLA's threads) while the host
    # prepares the next round and collects the previous one.
    n, pending = 0, dispatch(0)
    decoding: list = []  # the decoder's pending rounds
    while pending is not None:
        started = dispatch(pending[1]) if pending[1] < len(starts) else None
        n = collect(n, *pending)
        pending = started
    for done in decoding:
        done.result()
    return ijk[:n], band_d2[:n], band_tri[:n], keys[:n].view(np.uint64)  # non-negative int64


def sparse_distance_field(
    mesh: Mesh,
    grid: Grid,
    *,
    band: int = 3,
    signed: bool = True,
    region: int | None = None,
    progress: bool | None = None,
    compact: bool = False,
) -> SparseField:
    """The narrow-band distance field of `mesh`: exact distances at the band voxels.

    Host-side (counting passes size the work; see the module docstring for the method and
    its cost). Band voxels are those whose centre lies within ``band * h`` of the surface
    (``h = grid.voxel_size``; in float32 grid units, ``d <= band``). The grid is built in
    aligned cubic regions of edge `region`, in Morton order, each region's voxels
    distanced, signed and built into the field's DAG alone, so that the work's memory
    follows one region, not the whole band (`jaxvox.mesh_to_dag` does the same).

    Args:
      mesh: `Mesh` (validated); for the sign, outward (counter-clockwise) orientation.
      grid: `Grid` of R^3 voxels (geometry outside it is clipped: only voxels in the grid
        exist).
      band: half width in voxels, an int in ``[0, MAX_BAND]``. ``band=0`` keeps only
        voxels whose centre lies on the surface (usually none).
      signed: negative inside (pseudo-normals for watertight meshes, winding numbers
        otherwise); False gives unsigned distances.
      region: edge of the regions (a power of two up to `REGION_SIZE`, 1024, the
        default; capped at R). The field does not depend on it.
      progress: a progress bar over the regions (None: when there are several).
      compact: keep the values and the tree only (``field.voxels`` is None): 4 bytes per
        band voxel (in the capacity's padding too) plus the DAG's, against 12 more for
        the coordinates and 4 for the closest triangles. `sample`, `field_to_mesh` and
        the sampled SDF node work alike; `SparseField.voxel_coords` expands the tree.

    Returns:
      A `SparseField` (empty, ``count == 0``, for a mesh without faces) whose tree is the
      DAG of the band voxels (`build_dag`'s layout; `voxel_index` finds each voxel's row).

    Raises:
      JaxvoxError: a malformed mesh, not a `Grid`, a bad `band`, `signed` or `region`, or
        a triangle whose dilated box holds more than about 2^31 voxels.
    """
    size = _checked("sparse_distance_field", mesh, grid, band, signed, region, compact)
    out = _field_rows(grid.resolution, size, compact)
    coords, values, closest = [], [], []
    stack: list = []
    build = lambda keys, region_lo: push_region(stack, keys, region_lo, size)  # in region order (one worker)
    pushed = []  # waited for at the end: each region is finished while the next is found
    for ijk, dist, tri, done in band_regions(mesh, grid, band, signed, size, progress, build, out):
        pushed.append(done)
        values.append(dist)
        if not compact:
            coords.append(ijk)
            closest.append(tri)
        del ijk, dist, tri
    for done in pushed:
        done.result()
    n = sum(len(v) for v in values)
    if out is not None:  # the regions' rows follow each other in the reserved buffers
        coords, values, closest = ([] if a is None else [a[:n]] for a in out)
    check_count(n, grid, "sparse_distance_field")
    tree = finish_dag(merge_all(stack), grid, size, CONSERVATIVE, n)
    return _field(grid, band, n, coords, values, closest, tree, compact, grid.resolution)


def sparse_field_regions(
    mesh: Mesh,
    grid: Grid,
    *,
    band: int = 3,
    signed: bool = True,
    region: int | None = None,
    progress: bool | None = None,
    compact: bool = False,
) -> Iterator[SparseField]:
    """`sparse_distance_field` handed out region by region, for fields larger than memory:
    the peak follows one region's field and work, not the whole field's
    (``experiments/sparse_distance.py --stream``).

    The same regions and values as `sparse_distance_field` (arguments alike); each is
    dropped by the generator once yielded, so memory follows one region. Concatenated in
    the order yielded, the regions' voxels, values and triangles are those of the whole
    field.

    Yields:
      Per non-empty region, in Morton order: a `SparseField` of the region's band voxels
      (global voxel indices, Morton order) in the whole grid, its tree the DAG of those
      voxels alone. `sample` on it sees only the region: near the region's faces a
      neighbour in the next region counts as outside the band.
    """
    size = _checked("sparse_field_regions", mesh, grid, band, signed, region, compact)

    def build(keys: np.ndarray, region_lo: np.ndarray) -> Octree:  # the region's DAG alone
        stack: list = []
        push_region(stack, keys, region_lo, size)
        return finish_dag(merge_all(stack), grid, size, CONSERVATIVE, len(keys))

    for ijk, dist, tri, tree in band_regions(mesh, grid, band, signed, size, progress, build):
        yield _field(grid, band, len(ijk), [ijk], [dist], [tri], tree.result(), compact, min(size, grid.resolution))


def _checked(caller: str, mesh: Mesh, grid: Grid, band, signed, region, compact) -> int:
    """Checks the arguments of `caller` (`JaxvoxError` naming the bad one); returns the
    region edge, capped at the resolution."""
    validate_mesh(mesh)
    check_type(f"{caller} grid", grid, Grid)
    check_int(f"{caller} band", band, minimum=0, maximum=MAX_BAND)
    for name, flag in (("signed", signed), ("compact", compact)):
        if not isinstance(flag, (bool, np.bool_)):
            raise refuse(f"{caller} {name}", "must be True or False", flag)
    return min(check_region(f"{caller} region", region), grid.resolution)


def _field_rows(resolution: int, size: int, compact: bool) -> tuple | None:
    """Buffers for a whole field's rows (ijk int32 [m, 3], values float32 [m], triangles
    int32 [m]; `compact`: the values only, None for the others) written region after
    region (`band_regions`' ``out``), so that they become the field's own without a join
    (a join of a large field's rows costs as much as a region's work). m bounds both
    the rows (every cell, in whole tiles, of the regions of edge `size` that cover the
    grid) and the field's capacity (`bucket` of R^3): address space only
    (`reserved_empty`). None where the system will not reserve it; the regions are then
    joined."""
    span = -(-resolution // size) * size
    tiled = -(-span // TILE) * TILE
    rows = max(bucket(resolution**3), tiled**3)
    values = reserved_empty((rows,), np.float32)
    if compact:
        return None if values is None else (None, values, None)
    out = reserved_empty((rows, 3), np.int32), values, reserved_empty((rows,), np.int32)
    return None if any(a is None for a in out) else out


def band_regions(
    mesh: Mesh, grid: Grid, band: int, signed: bool, size: int, progress: bool | None, build, out: tuple | None = None
):
    """The band voxels of each aligned region of edge `size` that holds some, in Morton
    order: (ijk int32 [n, 3] global voxel indices, values float32 [n] world units, tri
    int32 [n] closest triangles, a `Future` of ``build(keys, region_lo)``), host arrays in
    Morton order, final when the `Future` is done; keys [n] uint64 are the voxels' Morton
    codes within the region and region_lo [3] its first voxel. With `out` (`_field_rows`), each region's rows are
    written into it after the last region's, and the arrays are views of it.

    Both cores work: a worker thread prepares the signs (crossings, caps, winding tree:
    what depends on the mesh alone) while the first region's distances are computed,
    then finishes each region (its values: square roots, float64 distances near large
    triangles, signs, world units) and runs `build` on its keys (e.g. its DAG) while the
    next region's distances are computed; the last region is finished on this thread
    while the worker builds. The worker takes the tasks
    in order, so `build` sees the regions in Morton order. The kernels of the voxels'
    pseudo-normal sides (`band_sign.Sides`) start round by round during the tile pairs
    (`band_pairs`'s ``on_round``), so they run while the next rounds are found. With one
    region the worker, once the signs are prepared, also decodes the pairs' rounds and
    starts their sides (`band_pairs`'s ``decoder``): it has nothing else to do until then.
    """
    band = int(band)
    origin = np.asarray(grid.origin, np.float64)
    h = float(grid.voxel_size)
    tris = (host_triangles(mesh) - origin) / h
    from tqdm.auto import tqdm

    with ThreadPoolExecutor(1) as worker:
        edge = longest_edges(tris)
        large = edge > REFINE_EDGE
        signs = sides = None
        if signed and len(tris):  # the welded faces, their edges and the longest edges serve both threads
            welded = welded_faces(np.asarray(mesh.vertices), np.asarray(mesh.faces))
            edges = edge_table(welded)
            signs = worker.submit(prepare_signs, tris, welded, edges, edge, band)
            sides = Sides(mesh, tris, edge, welded, edges)  # beside the worker
        ids, codes = _tile_items(tris, grid.resolution, band, cell=size)
        starts = morton.run_starts(codes)
        ends = np.append(starts[1:], len(ids))
        shift = np.uint64(3 * (size.bit_length() - 1))
        # With one region the worker has nothing else to do after the signs' preparation:
        # it decodes the pairs' rounds (and starts their sides) while this thread finds the next.
        decoder = worker if len(starts) == 1 else None

        def finish(ijk, dist, tri, keys, region_lo, code, mine, started):
            """A region's values, in place: ijk global, tri mesh ids, dist signed world units."""
            codes_in_grid = keys  # (passes over every voxel are skipped where they change nothing)
            if region_lo.any():
                ijk += region_lo
                codes_in_grid = code << shift | keys
            if len(mine) < len(tris):  # else mine is every id, in order
                tri[:] = mine[tri]
            np.sqrt(dist, out=dist)  # float32 grid units
            refine = np.flatnonzero(large[tri]) if large.any() else np.zeros(0, np.int64)  # float64 distances
            if len(refine):
                dist[refine] = np.linalg.norm(exact_closest(tris, ijk[refine], tri[refine])[1], axis=1)
            if sides is not None and signs is not None:
                behind, on = sides.finish(started, ijk, tri, dist)
                np.negative(dist, out=dist, where=signs.result()(ijk, codes_in_grid, dist, tri, behind, on))
            dist *= np.float32(h)

        def finish_and_build(ijk, dist, tri, keys, region_lo, code, mine, started):
            finish(ijk, dist, tri, keys, region_lo, code, mine, started)
            return build(keys, region_lo)

        regions, n, trimmed = zip(starts, ends), 0, 0
        for a, b in tqdm(regions, total=len(starts), desc="regions", disable=progress_off(progress, len(starts))):
            if n - trimmed >= TRIM_ROWS:  # what the last regions freed (`jaxvox._core.buffers`)
                release_free_memory()
                trimmed = n
            region_lo = morton.decode_host(codes[a]) * size
            mine = ids[a:b]  # ascending, so ties still go to the lower id
            started: list = []  # the sides' kernels, started round by round
            start = None if sides is None else functools.partial(_start_sides, sides, started, region_lo, mine)
            rows = None if out is None else tuple(None if part is None else part[n:] for part in out)
            ijk, d2, tri, keys = band_pairs(tris[mine] - region_lo, size, band, start, rows, decoder)
            if not len(ijk):
                continue
            n += len(ijk)
            region = ijk, d2, tri, keys, region_lo, codes[a], mine, started
            if b < len(ids):  # finished on the worker while the next region's pairs are found
                yield ijk, d2, tri, worker.submit(finish_and_build, *region)
            else:  # the last region: finished here, while the worker builds
                built = worker.submit(build, keys, region_lo)
                finish(*region)
                yield ijk, d2, tri, built


def _start_sides(sides: Sides, started: list, region_lo: np.ndarray, ids: np.ndarray, ijk, tri) -> None:
    """`band_pairs`'s ``on_round`` for a region: starts the sides of a round's voxels ijk
    (region-local) with closest triangles tri (indices into the region's triangle ids
    `ids`), appending the pending kernels to `started`."""
    started.append(sides.start(ijk + region_lo, ids[tri]))


def _field(
    grid: Grid, band: int, n: int, coords: list, values: list, closest: list, tree: Octree, compact: bool, extent: int
) -> SparseField:
    """The `SparseField` of `n` band voxels given as parts (lists of host arrays, emptied
    as they are joined into buffers of the shape ladder, `band_bucket` of an `extent`^3
    grid or region) and their tree; `compact`: the values and the tree only (coords and
    closest are dropped)."""
    capacity = band_bucket(n, extent, band)
    put = functools.partial(jax.device_put, may_alias=True)
    field_values = put(_joined(values, (capacity,), UNUSED_VALUE, np.float32))
    if compact:
        return SparseField(None, field_values, tree, grid, int(band))
    voxels = Voxels(
        put(_joined(coords, (capacity, 3), UNUSED, np.int32)),
        put(np.int32(n)),
        put(np.int32(0)),
        put(_joined(closest, (capacity,), UNUSED, np.int32)),
        grid,
        CONSERVATIVE,
    )
    return SparseField(voxels, field_values, tree, grid, int(band))


def _joined(parts: list, shape: tuple[int, ...], fill, dtype) -> np.ndarray:
    """`join_rows` of the parts, except that a single part at the start of a page-aligned
    buffer of `band_pairs` (`aligned_empty`) that holds `shape` is extended in place: its
    rows past the part, which nothing else uses, are set to `fill` (no copy, and
    `jax.device_put` aliases the buffer)."""
    if len(parts) == 1:
        part, whole = parts[0], parts[0].base
        size = int(np.prod(shape))
        address = lambda a: a.__array_interface__["data"][0]
        if (
            isinstance(whole, np.ndarray)
            and part.dtype == whole.dtype == dtype
            and part.flags.c_contiguous
            and address(part) == address(whole)
            and address(whole) % mmap.PAGESIZE == 0
            and whole.size >= size
        ):
            parts.clear()
            out = whole[:size].reshape(shape)
            out[len(part) :] = fill
            return out
    return join_rows(parts, shape, fill, dtype)


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
