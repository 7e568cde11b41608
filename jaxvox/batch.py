"""Batched pipelines: many meshes through one compiled program.

The jittable cores (`voxelize_fixed`, `build_dag` / `build_octree` with static capacities,
`trace`) are pure functions of static shapes, so a batch of meshes padded to common sizes
runs through all three under one `jax.vmap` and one `jax.jit`. This module holds the
pieces around that:

* `stack_meshes` / `stack_grids`: pad (`pad_mesh`) and stack meshes and grids along a
  leading batch axis, sizes rounded on the shape ladder (`jaxvox._core.shapes.bucket`);
* `batch_capacities`: host-side *allocate*: voxelizer and per-level octree capacities that
  fit every item, on the ladder, so similar batches share one compiled program;
* `voxelize_build_trace`: the jittable, vmapped voxelize -> build -> trace, with overflow
  flags per item (``vox.overflow``, ``tree.overflow``);
* `run_batch`: the host helper: runs the pipeline, re-runs only the items that overflowed
  with the capacities counted for them, and returns per-item results equal to the one-by-one host path
  (`voxelize`, `build_dag` / `build_octree`, `compact`, `trace`).

Bit-for-bit equality with the host path holds when the grids' voxel sizes are powers of
two. Otherwise XLA may evaluate ``x / h`` (world to grid units) inside the vmapped program
as ``x * (1 / h)``, one ulp away: ``t`` can differ in its last bit, and geometry lying
exactly on a voxel plane (a flat mesh in one) or a ray exactly through a voxel edge can
land on the other side of the tie, as they can in any jitted `voxelize_fixed`.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import numpy as np

from jaxvox import morton
from jaxvox._core.checks import check_choice, check_int, check_type, refuse
from jaxvox._core.errors import JaxvoxError
from jaxvox._core.shapes import bucket
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, pad_mesh, validate_mesh
from jaxvox.octree import (
    OVERFLOW_NODES,
    Octree,
    build_dag,
    build_octree,
    check_level_capacities,
    compact,
)
from jaxvox.octree.build import level_sizes
from jaxvox.overflow import describe
from jaxvox.trace import TRACE_METHODS, Hit, trace
from jaxvox.voxelize import (
    CONSERVATIVE,
    MODES,
    OVERFLOW_CANDIDATES,
    OVERFLOW_COLUMNS,
    OVERFLOW_ROWS,
    OVERFLOW_VOXELS,
    Capacities,
    Mode,
    Voxels,
    check_capacities,
    voxel_capacities,
    voxelize,
    voxelize_fixed,
)

_OPTIONAL = ("colors", "uvs", "texture")  # optional `Mesh` fields, stacked when all items have them
# `run_batch`'s largest default capacities so far, per (resolution, mode, dag): later
# batches start from them, so that a dataset's batches share compiled programs.
_LARGEST_DEFAULTS: dict[tuple, tuple[Capacities, tuple[int, ...]]] = {}


# ----------------------------------------------------------------------------- stacking


def _stack(items):
    """Stacks the leaves of equal pytrees on the host and moves them to the device once
    (numpy, so stacking compiles nothing)."""
    return jax.device_put(jax.tree.map(lambda *leaves: np.stack([np.asarray(x) for x in leaves]), *items))


def stack_meshes(meshes: Sequence[Mesh], *, num_vertices: int | None = None, num_faces: int | None = None) -> Mesh:
    """Pads meshes to common sizes and stacks them along a new leading batch axis.

    Every mesh is validated and padded with `pad_mesh`; then its padding vertices are set
    to NaN and its padding faces point at the first of them. `voxelize_fixed` skips
    non-finite triangles before any work is expanded, so padding costs no capacity and
    adds no voxels in either mode: a padded mesh voxelizes exactly as the original, and
    `batch_capacities` of the unpadded meshes fit the stacked batch. (pad_mesh's own
    padding, faces ``(0, 0, 0)``, would take columns, rows and candidates in conservative
    mode, about two of each per padding face.) The stacked mesh is meant for the batched
    pipeline only: host-side functions that validate meshes reject the NaN vertices.

    Args:
      meshes: B `Mesh` objects with V_b vertices and F_b >= 1 faces each.
      num_vertices: V > max V_b, vertices per item (default ``bucket(max V_b + 1)``, the
        shape ladder; at least one padding vertex).
      num_faces: F >= max F_b, faces per item (default ``bucket(max F_b)``).

    Returns:
      A `Mesh` with vertices [B, V, 3] float32 (NaN past V_b), faces [B, F, 3] int32 (rows
      past F_b are ``(V_b, V_b, V_b)``), and colors [B, V, C], uvs [B, V, 2], texture
      [B, H, W, C] float32 where every item has them.

    Raises:
      JaxvoxError: no meshes, a malformed or faceless mesh, target sizes that are not
        integers or too small for a mesh, or optional fields (colours, texture
        coordinates, textures) that only some items have or whose shapes differ.
    """
    meshes = _mesh_list("stack_meshes", meshes)
    for b, mesh in enumerate(meshes):
        validate_mesh(mesh)
        if mesh.num_faces == 0:
            raise refuse(
                f"stack_meshes meshes[{b}]", "must have faces (its padding faces would add voxels)", mesh.faces.shape
            )
    v_max = max(m.num_vertices for m in meshes)
    f_max = max(m.num_faces for m in meshes)
    if num_vertices is None:
        num_vertices = bucket(v_max + 1)
    elif check_int("stack_meshes num_vertices", num_vertices) <= v_max:
        raise refuse(
            "stack_meshes num_vertices",
            f"too small: must be above the largest mesh's {v_max} vertices (one padding vertex is needed)",
            num_vertices,
        )
    if num_faces is None:
        num_faces = bucket(f_max)
    elif check_int("stack_meshes num_faces", num_faces) < f_max:
        raise refuse(
            "stack_meshes num_faces", f"too small: must be at least the largest mesh's {f_max} faces", num_faces
        )
    for name in _OPTIONAL:
        present = [getattr(m, name) is not None for m in meshes]
        if any(present) and not all(present):
            missing = [b for b, p in enumerate(present) if not p]
            raise refuse(
                f"stack_meshes meshes' {name}",
                "must be in every mesh or in none (strip them or add them to all)",
                f"missing in items {missing}",
            )
    # Padding fixes the vertex axis of colours and uvs; channels and texture sizes must match.
    for name, shape_of in (("colors", lambda a: a.shape[1:]), ("texture", lambda a: a.shape)):
        shapes = sorted({shape_of(getattr(m, name)) for m in meshes if getattr(m, name) is not None})
        if len(shapes) > 1:
            raise refuse(f"stack_meshes meshes' {name}", "must have one shape to be stacked", shapes)
    padded = []
    for mesh in meshes:
        p = pad_mesh(mesh, num_vertices, num_faces)
        vertices, faces = np.array(p.vertices), np.array(p.faces)
        vertices[mesh.num_vertices :] = np.nan
        faces[mesh.num_faces :] = mesh.num_vertices
        padded.append(Mesh(vertices, faces, colors=p.colors, uvs=p.uvs, texture=p.texture))
    return _stack(padded)


def stack_grids(grids: Sequence[Grid]) -> Grid:
    """Stacks grids of one resolution along a leading batch axis.

    Args:
      grids: B `Grid` objects, all of resolution R.

    Returns:
      A `Grid` with origin [B, 3] float32, voxel_size [B] float32 and resolution R.

    Raises:
      JaxvoxError: no grids, an item that is not a `Grid`, or different resolutions (the
        resolution is static: one compiled program has one).
    """
    return _stack(_grid_list("stack_grids", grids))


# ----------------------------------------------------------------------------- capacities


def _tree_capacities(sizes) -> tuple[int, ...]:
    """Per-level capacities on the ladder for octree node counts `sizes` (root first):
    ``bucket(n, 1)`` capped at ``8^l``; the root level holds exactly one node."""
    return (1,) + tuple(min(8**level, bucket(int(n), 1)) for level, n in enumerate(sizes) if level)


def _mesh_list(caller: str, meshes: Sequence[Mesh]) -> list[Mesh]:
    """`meshes` as a non-empty list (items are validated where they are used)."""
    try:
        items = None if isinstance(meshes, Mesh) else list(meshes)
    except TypeError:
        items = None
    if not items:
        raise refuse(
            f"{caller} meshes",
            "must be a sequence of at least one jaxvox.Mesh",
            type(meshes) if items is None else items,
        )
    return items


def _grid_list(caller: str, grids: Grid | Sequence[Grid], count: int | None = None) -> list[Grid]:
    """`grids` as a list of `Grid` objects of one resolution: one grid repeated `count`
    times, or a sequence of `count` grids (of at least one grid when `count` is None)."""
    what = f"{caller} grids"
    if isinstance(grids, Grid) and count is not None:
        return [grids] * count
    try:
        items = [grids] if isinstance(grids, Grid) else list(grids)
    except TypeError:
        raise refuse(what, "expected a jaxvox.Grid or a sequence of them", type(grids)) from None
    if count is None and not items:
        raise refuse(what, "needs at least one grid", items)
    if count is not None and len(items) != count:
        raise refuse(what, f"must be one Grid or {count} (one per mesh)", f"{len(items)} grids")
    for b, grid in enumerate(items):
        check_type(f"{what}[{b}]", grid, Grid)
    resolutions = sorted({g.resolution for g in items})
    if len(resolutions) > 1:
        raise refuse(what, "must all have one resolution (it is static)", resolutions)
    return items


def batch_capacities(
    meshes: Sequence[Mesh], grids: Grid | Sequence[Grid], *, mode: Mode = CONSERVATIVE
) -> tuple[Capacities, tuple[int, ...]]:
    """Host-side capacities with which `voxelize_build_trace` fits every item.

    The voxelizer's are the elementwise maximum over the items of `voxel_capacities`
    (each on the shape ladder); the octree's are, per level, the most octree nodes of any
    item's voxels (counted on the host; for a DAG they bound the nodes before
    deduplication, as `build_dag` expects), rounded with ``bucket(n, 1)`` and capped at
    ``8^l``, with 1 for the root. Similar batches so get equal capacities and share one
    compiled program.

    Args:
      meshes: B `Mesh` objects (unpadded).
      grids: one `Grid` for all items or B grids, all of one resolution R = 2^D.
      mode: "conservative" or "6-separating".

    Returns:
      (`Capacities`, D ints: per-level octree capacities, root level first).

    Raises:
      JaxvoxError: no meshes, a bad mode or mesh, grid count or resolutions that do not
        match.
    """
    meshes = _mesh_list("batch_capacities", meshes)
    grids = _grid_list("batch_capacities", grids, len(meshes))
    check_choice("batch_capacities mode", mode, MODES)
    depth = grids[0].resolution.bit_length() - 1
    caps, sizes = [], np.zeros(depth, np.int64)
    for mesh, grid in zip(meshes, grids):
        caps.append(voxel_capacities(mesh, grid, mode=mode))
        sizes = np.maximum(sizes, level_sizes(morton.encode_host(voxelize(mesh, grid, mode=mode).to_numpy()), depth))
    return Capacities._make(max(c) for c in zip(*caps)), _tree_capacities(sizes)


# ----------------------------------------------------------------------------- jittable pipeline


@functools.partial(
    jax.jit, static_argnames=("capacities", "tree_capacities", "mode", "dag", "method", "max_steps", "lanes")
)
def _voxelize_build_trace(
    meshes, grids, origins, directions, *, capacities, tree_capacities, mode, dag, method, max_steps, lanes
):
    build = build_dag if dag else build_octree

    def one(mesh, grid, o, d):
        vox = voxelize_fixed(mesh, grid, capacities, mode=mode)
        tree = build(vox, capacities=tree_capacities)
        return vox, tree, trace(tree, o, d, method=method, max_steps=max_steps, lanes=lanes, shard=False)

    grid_axis = 0 if grids.origin.ndim == 2 else None
    return jax.vmap(one, in_axes=(0, grid_axis, 0, 0))(meshes, grids, origins, directions)


def voxelize_build_trace(
    meshes: Mesh,
    grids: Grid,
    origins: jax.Array,
    directions: jax.Array,
    *,
    capacities: Capacities,
    tree_capacities: Sequence[int],
    mode: Mode = CONSERVATIVE,
    dag: bool = True,
    method: str = "esvo",
    max_steps: int | None = None,
    lanes: int | None = 16384,
) -> tuple[Voxels, Octree, Hit]:
    """Voxelizes, builds and traces a batch of meshes in one jitted, vmapped program.

    Per item: `voxelize_fixed` -> `build_dag` (or `build_octree`) with static capacities
    -> `trace` (``shard=False``). Pure and jittable; usable inside a caller's `jax.jit`.
    Nothing is resized: an item whose work does not fit its capacities is truncated and
    flagged (``vox.overflow[b]``: the ``OVERFLOW_*`` bits of the voxelizer;
    ``tree.overflow[b]``: those and `OVERFLOW_NODES`); its tree and hits are then not to be
    used. `run_batch` re-runs such items with larger capacities. Results equal the host
    path's bit for bit with power-of-two voxel sizes (see the module docstring).

    The capacities, `mode`, `dag`, `method`, `max_steps`, `lanes`, the grid resolution and
    all array shapes are static: changing one compiles a new program.

    Args:
      meshes: a `Mesh` with vertices [B, V, 3] float32 and faces [B, F, 3] int32
        (`stack_meshes`).
      grids: a `Grid` with origin [B, 3] and voxel_size [B] (`stack_grids`), or one
        unbatched `Grid` for every item.
      origins, directions: [B, ..., 3] float32 rays per item in world coordinates.
      capacities: `Capacities` of the voxelizer (`batch_capacities`).
      tree_capacities: D ints, per-level octree node capacities, root level first, 1 for
        the root (`batch_capacities`).
      mode: "conservative" or "6-separating".
      dag: build DAGs (True) or plain octrees (False).
      method, max_steps, lanes: as in `trace`.

    Returns:
      (voxels, trees, hits): `Voxels` with coords [B, capacities.voxels, 3] int32, count
      and overflow [B] int32; `Octree` with every leaf batched [B, ...] (tables of
      ``sum(tree_capacities)`` rows); `Hit` with fields [B, ...].

    Raises:
      JaxvoxError: not a `Mesh` or `Grid`, meshes without a batch axis, rays whose
        leading axis is not B, grids of another count, capacities or tree capacities that
        are not valid (see `voxelize_fixed`, `build_octree`), or a bad mode, method,
        max_steps or lanes.
    """
    check_type("voxelize_build_trace meshes", meshes, Mesh)
    check_type("voxelize_build_trace grids", grids, Grid)
    if np.ndim(meshes.vertices) != 3 or np.ndim(meshes.faces) != 3:
        raise refuse(
            "voxelize_build_trace meshes",
            "need a leading batch axis (stack_meshes): vertices [B, V, 3], faces [B, F, 3]",
            (np.shape(meshes.vertices), np.shape(meshes.faces)),
        )
    count = np.shape(meshes.faces)[0]
    if np.shape(origins)[:1] != (count,) or np.shape(directions)[:1] != (count,):
        raise refuse(
            "voxelize_build_trace origins, directions",
            f"need a leading batch axis of {count} (one per mesh)",
            (np.shape(origins), np.shape(directions)),
        )
    if np.ndim(grids.origin) == 2 and np.shape(grids.origin)[0] != count:
        raise refuse(
            "voxelize_build_trace grids",
            f"must be one Grid or a stack of {count} (one per mesh)",
            f"{np.shape(grids.origin)[0]} grids",
        )
    depth = grids.resolution.bit_length() - 1
    capacities = check_capacities("voxelize_build_trace capacities", capacities)
    tree_capacities = check_level_capacities("voxelize_build_trace tree_capacities", tree_capacities, depth)
    check_choice("voxelize_build_trace mode", mode, MODES)
    check_choice("voxelize_build_trace method", method, TRACE_METHODS)
    if max_steps is not None:
        max_steps = check_int("voxelize_build_trace max_steps", max_steps, minimum=1)
    if lanes is not None:
        lanes = check_int("voxelize_build_trace lanes", lanes, minimum=1)
    return _voxelize_build_trace(
        meshes,
        grids,
        origins,
        directions,
        capacities=capacities,
        tree_capacities=tree_capacities,
        mode=mode,
        dag=bool(dag),
        method=method,
        max_steps=max_steps,
        lanes=lanes,
    )


# ----------------------------------------------------------------------------- host helper


class BatchResult(NamedTuple):
    """Per-item results of `run_batch` (host-side), equal to the one-by-one host path.

    Attributes:
      voxels: B host int32 arrays [n_b, 3], each item's voxels in Morton order (as
        ``voxelize(mesh, grid).to_numpy()``).
      trees: B compact `Octree` objects (as ``compact(build_dag(voxelize(mesh, grid)))``).
      hits: `Hit` with host numpy fields [B, ...] (as ``trace(tree, origins[b],
        directions[b])``).
      retried: one tuple per re-run round: the items that overflowed and were re-run.
      capacities: the voxelizer `Capacities` of the last round.
      tree_capacities: the octree per-level capacities of the last round.
    """

    voxels: list[np.ndarray]
    trees: list[Octree]
    hits: Hit
    retried: tuple[tuple[int, ...], ...]
    capacities: Capacities
    tree_capacities: tuple[int, ...]


def _take(tree, index):
    """Host pytree of the items `index` (an int or an int array) of a batched host pytree."""
    return jax.tree.map(lambda x: np.asarray(x)[index], tree)


def _grow(capacities: Capacities, tree_capacities: tuple[int, ...], flags: int, needed):
    """Capacities for a re-run: each at least what `needed` (the `batch_capacities` of the
    items that overflowed) asks, since an overflowing stage hides what the stages after it
    need, and each whose overflow bit is set in `flags` at least doubled on the ladder
    (`OVERFLOW_NODES`: every octree level)."""
    counted, counted_tree = needed
    bits = (OVERFLOW_COLUMNS, OVERFLOW_ROWS, OVERFLOW_CANDIDATES, OVERFLOW_VOXELS)
    sizes = [max(bucket(2 * c) if flags & bit else c, n) for c, n, bit in zip(capacities[:4], counted[:4], bits)]
    if flags & OVERFLOW_NODES:
        tree_capacities = _tree_capacities((1,) + tuple(2 * c for c in tree_capacities[1:]))
    tree_capacities = tuple(max(a, b) for a, b in zip(tree_capacities, counted_tree))
    return Capacities._make([*sizes, capacities.row_chunk]), tree_capacities


def run_batch(
    meshes: Sequence[Mesh],
    grids: Grid | Sequence[Grid],
    origins,
    directions,
    *,
    capacities: Capacities | None = None,
    tree_capacities: Sequence[int] | None = None,
    mode: Mode = CONSERVATIVE,
    dag: bool = True,
    method: str = "esvo",
    max_steps: int | None = None,
    lanes: int | None = 16384,
    max_tries: int = 8,
) -> BatchResult:
    """Runs a batch through `voxelize_build_trace`; re-runs only the items that overflowed.

    The meshes are stacked with `stack_meshes` and run in one compiled program. Items
    whose ``tree.overflow`` is nonzero are re-run alone (as a sub-batch padded to a
    power-of-two size by repeating its first item) with the capacities raised to what
    `batch_capacities` counts for those items, and every flagged one at least doubled on
    the ladder (`OVERFLOW_NODES`: every octree level): one re-run, one more compiled
    program, is enough.

    Args:
      meshes: B `Mesh` objects (unpadded).
      grids: one `Grid` for all items or B grids of one resolution.
      origins, directions: [B, ..., 3] float32 rays per item in world coordinates.
      capacities, tree_capacities: the starting capacities (default: `batch_capacities`,
        which fit every item, so nothing is re-run, raised to the largest default
        capacities an earlier call in this process ran with at the same resolution,
        mode and tree kind: the batches of a dataset then run the programs of the
        batches before them instead of compiling one each, for padding that costs some
        memory and work; pass capacities to choose them).
      mode, dag, method, max_steps, lanes: as in `voxelize_build_trace`.
      max_tries: runs of the pipeline in all before giving up.

    Returns:
      `BatchResult`.

    Raises:
      JaxvoxError: bad input (see `stack_meshes`, `voxelize_build_trace`), `max_tries`
        not an integer >= 1, or items still overflowing after `max_tries` runs.
    """
    meshes = _mesh_list("run_batch", meshes)
    grid_list = _grid_list("run_batch", grids, len(meshes))
    max_tries = check_int("run_batch max_tries", max_tries, minimum=1)
    remembered = (grid_list[0].resolution, mode, bool(dag)) if capacities is None and tree_capacities is None else None
    if capacities is None or tree_capacities is None:
        found = batch_capacities(meshes, grid_list, mode=mode)
        capacities = found[0] if capacities is None else capacities
        tree_capacities = found[1] if tree_capacities is None else tree_capacities
    if remembered in _LARGEST_DEFAULTS:
        before, before_tree = _LARGEST_DEFAULTS[remembered]
        capacities = Capacities._make(max(a, b) for a, b in zip(capacities, before))
        tree_capacities = tuple(max(a, b) for a, b in zip(tree_capacities, before_tree))
    capacities = check_capacities("run_batch capacities", capacities)
    depth = grid_list[0].resolution.bit_length() - 1
    tree_capacities = check_level_capacities("run_batch tree_capacities", tree_capacities, depth)
    # Host copies: items are picked with numpy indexing, which compiles nothing.
    # (their geometry only: colours, uvs and textures take no part, and would key other programs)
    geometry = [Mesh(m.vertices, m.faces) if isinstance(m, Mesh) else m for m in meshes]  # (others: refused there)
    stacked = jax.device_get(stack_meshes(geometry))
    grid_batch = grids if isinstance(grids, Grid) else jax.device_get(stack_grids(grid_list))
    origins, directions = np.asarray(origins, np.float32), np.asarray(directions, np.float32)
    count = len(meshes)
    voxels: list = [None] * count
    trees: list = [None] * count
    hit_rows: list = [None] * count
    pending, retried = np.arange(count), []
    for attempt in range(max_tries):
        take = pending
        if attempt:  # a re-run of the overflowed items; the sub-batch size goes on the ladder too
            retried.append(tuple(int(i) for i in pending))
            take = np.concatenate([pending, np.full(bucket(len(pending), 1) - len(pending), pending[0])])
        sub_grids = grid_batch if isinstance(grids, Grid) else _take(grid_batch, take)
        out = voxelize_build_trace(
            _take(stacked, take),
            sub_grids,
            origins[take],
            directions[take],
            capacities=capacities,
            tree_capacities=tree_capacities,
            mode=mode,
            dag=dag,
            method=method,
            max_steps=max_steps,
            lanes=lanes,
        )
        vox, tree, hit = jax.device_get(out)
        flags = np.asarray(tree.overflow)[: len(pending)]
        for row, item in enumerate(pending):
            if not flags[row]:
                voxels[item] = _take(vox, row).to_numpy()
                trees[item] = compact(jax.device_put(_take(tree, row)))
                hit_rows[item] = _take(hit, row)
        if not flags.any():
            break
        pending = pending[flags != 0]
        if attempt + 1 < max_tries:
            needed = batch_capacities([meshes[i] for i in pending], [grid_list[i] for i in pending], mode=mode)
            capacities, tree_capacities = _grow(
                capacities, tuple(tree_capacities), int(np.bitwise_or.reduce(flags[flags != 0])), needed
            )
    else:
        raise JaxvoxError(
            f"run_batch: items {tuple(int(i) for i in pending)} still overflow "
            f"({describe(np.bitwise_or.reduce(flags))}) after {max_tries} runs; last capacities "
            f"{tuple(capacities)}, tree capacities {tree_capacities}"
        )
    if remembered is not None:  # (at least those remembered before: they were raised to them)
        _LARGEST_DEFAULTS[remembered] = (capacities, tuple(tree_capacities))
    hits = jax.tree.map(lambda *rows: np.stack(rows), *hit_rows)
    return BatchResult(voxels, trees, hits, tuple(retried), capacities, tuple(tree_capacities))
