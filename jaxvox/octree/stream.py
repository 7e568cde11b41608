"""`mesh_to_dag`: the DAG of a mesh built region by region, so that memory follows the
result, not the voxel count.

The grid is cut into the voxelizer's aligned cubic regions of edge ``S = 2^s``, visited in
Morton order (`jaxvox.voxelize.host`: the regions any triangle's bounding box touches).
A region is one node of level ``L = D - s``; it is voxelized alone and built into its
sub-DAG (the DAG build of `build_dag` on the region's voxels in a local ``S^3`` grid:
levels ``L .. D - 1``), and then its voxels are dropped.

Sub-DAGs merge level by level, bottom-up, into `build_dag`'s canonical order: the mask
level is the sorted set of distinct masks, every level above it the lexicographically
sorted set of distinct child rows (`EMPTY` last) written with the merged ids of the
level below, each with the prefix sums of any of its copies (they depend on the shape
alone). A DAG of some regions holds a subset of the distinct nodes of every level of the
whole DAG, in the same relative order, so the merged tables are exactly those of the
whole voxel set. Merges go as in a binary counter: a new DAG merges with the one before
it while it holds at least half as many rows, so the DAGs held together stay below
twice the merged one and each node is merged a logarithmic number of times.

Regions and the levels above ``L`` (over the regions' roots: cells in Morton order,
root ids, voxel counts) are built by `build_dag`'s host levels (`jaxvox.octree.host`).
The result is laid out on the shape ladder, as `build_dag` returns it.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
import pickle
import threading
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox import morton
from jaxvox._core.checks import check_choice, check_int, check_type, refuse
from jaxvox._core.errors import JaxvoxError
from jaxvox._core.shapes import bucket, voxel_bucket
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, validate_mesh
from jaxvox.octree.attributes import voxel_attributes
from jaxvox.octree.build import build_dag
from jaxvox.octree.host import Nodes, levels_above, tree_from_levels, unique_rows, voxel_levels
from jaxvox.octree.tree import EMPTY, Octree
from jaxvox.voxelize.host import region_coords, region_voxels
from jaxvox.voxelize.voxels import CONSERVATIVE, MODES, REGION_SIZE, SIX_SEPARATING, UNUSED, Mode, Voxels

MAX_VOXELS = 2**32 - 1  # `Octree.voxel_count` is uint32
_BLOCK = 1 << 20  # rows remapped at once (bounds the index temporaries)


@dataclasses.dataclass
class _Partial:
    """The canonical DAG of some regions, over levels ``L .. D - 1`` (entry ``j`` is level ``L + j``)."""

    masks: list[np.ndarray]  # [n_j] uint8 per level
    child: list[np.ndarray]  # [n_j, 8] uint32 rows within level j + 1, EMPTY where absent (levels above the last)
    prefix: list[np.ndarray]  # [n_j, 8] uint32 voxels in the children before each slot
    cells: np.ndarray  # [k, 3] int32 region cells (region_lo // S), Morton order
    roots: np.ndarray  # [k] int64 row of each region's root within level L
    counts: np.ndarray  # [k] int64 voxels per region

    @property
    def rows(self) -> int:
        """Nodes over all levels."""
        return sum(len(m) for m in self.masks)


def _region_dag(keys: np.ndarray, region_lo: np.ndarray, region: int) -> _Partial:
    """The sub-DAG of one region's voxels (host [n] Morton codes, uint32 words as
    `region_voxels` yields them or uint64; only the region's own bits are read; Morton
    order), by `build_dag`'s host levels in the region's own grid."""
    depth = region.bit_length() - 1
    local = (keys & np.uint32((1 << 3 * depth) - 1)).astype(np.uint64)  # the region is aligned
    levels, _ = voxel_levels(local, depth, dag=True)
    return _Partial(
        masks=[m for m, _, _ in levels],
        child=[c for _, c, _ in levels[:-1] if c is not None],
        prefix=[p for _, _, p in levels[:-1] if p is not None],
        cells=(region_lo // region).astype(np.int32)[None],
        roots=np.zeros(1, np.int64),
        counts=np.array([len(keys)], np.int64),
    )


def _remap(child: np.ndarray, ids: np.ndarray, out: np.ndarray) -> None:
    """Writes child rows [n, 8] uint32 (`EMPTY` where absent) through `ids` [m], the new
    id of each row of the level below, to `out` [n, 8]; block by block, so temporaries
    stay small."""
    table = np.append(ids.astype(np.uint32), np.uint32(EMPTY))
    for start in range(0, len(child), _BLOCK):
        part = child[start : start + _BLOCK]
        out[start : start + _BLOCK] = table[np.where(part == EMPTY, np.uint32(len(ids)), part)]


def _merge(a: _Partial, b: _Partial) -> _Partial:
    """The canonical DAG of the regions of `a` and then `b` (consumes both: their level
    tables are dropped as the merge goes up)."""
    depth = len(a.masks)
    masks: list = [None] * depth
    child: list = [None] * (depth - 1)
    prefix: list = [None] * (depth - 1)
    ids_a = ids_b = np.zeros(0, np.int64)  # new ids of the rows of `a` and `b` in the level below
    for j in range(depth - 1, -1, -1):
        n_a = len(a.masks[j])
        if j == depth - 1:  # masks, by value
            masks[j], inverse = np.unique(np.concatenate([a.masks[j], b.masks[j]]), return_inverse=True)
        else:
            rows = np.empty((n_a + len(b.masks[j]), 8), np.uint32)
            _remap(a.child[j], ids_a, rows[:n_a])
            _remap(b.child[j], ids_b, rows[n_a:])
            rep, inverse = unique_rows(rows, len(masks[j + 1]))
            child[j] = rows[rep]
            del rows
            prefix[j] = np.concatenate([a.prefix[j], b.prefix[j]])[rep]
            masks[j] = np.concatenate([a.masks[j], b.masks[j]])[rep]
            a.child[j] = b.child[j] = a.prefix[j] = b.prefix[j] = None  # type: ignore[call-overload]
        ids_a, ids_b = inverse[:n_a], inverse[n_a:]
    return _Partial(
        masks=masks,
        child=child,
        prefix=prefix,
        cells=np.concatenate([a.cells, b.cells]),
        roots=np.concatenate([ids_a[a.roots], ids_b[b.roots]]),
        counts=np.concatenate([a.counts, b.counts]),
    )


def _empty(grid: Grid, mode: str) -> Voxels:
    """No voxels, in the buffer `voxelize` returns for none."""
    coords = jnp.full((voxel_bucket(0, grid.resolution), 3), UNUSED, jnp.int32)
    return Voxels(coords, jnp.int32(0), jnp.int32(0), None, grid, mode)


def check_region(what: str, region) -> int:
    """`region` (None: `REGION_SIZE`) as a power of two in ``[2, REGION_SIZE]``; raises
    `JaxvoxError` naming `what` otherwise."""
    if region is None:
        return REGION_SIZE
    region = check_int(what, region, minimum=2, maximum=REGION_SIZE)
    if region & (region - 1):
        raise refuse(what, f"must be a power of two between 2 and {REGION_SIZE}", region)
    return region


def stream_dag(
    mesh: Mesh,
    grid: Grid,
    *,
    mode: Mode = CONSERVATIVE,
    region: int | None = None,
    progress: bool | None = None,
    distributed: bool = False,
    triangle_ids: bool = False,
    on_region: Callable[[int, Voxels], None] | None = None,
    caller: str = "mesh_to_dag",
) -> Octree:
    """`mesh_to_dag`, which also hands every non-empty region's voxels (global indices,
    with triangle ids if asked) to ``on_region(position, voxels)``, in Morton order
    (`position` is the region's place in that order; with ``distributed=True`` a process
    sees only its own regions, from one thread per local device, so not in order), e.g.
    to gather per-voxel attributes region by region."""
    check_type(f"{caller} mesh", mesh, Mesh)
    check_type(f"{caller} grid", grid, Grid)
    six_sep = check_choice(f"{caller} mode", mode, MODES) == SIX_SEPARATING
    region = min(check_region(f"{caller} region", region), grid.resolution)
    validate_mesh(mesh)
    processes = jax.process_count() if distributed else 1
    devices = jax.local_devices() if distributed else [None]
    threads = len(devices)
    total = [0]  # voxels so far, over this process's threads
    lock = threading.Lock()

    def build(thread: int) -> _Partial | None:
        """The merged sub-DAG of one share of the regions: this process's (every
        `processes`-th region) and, of those, this thread's (every `threads`-th), with
        their programs on the thread's local device."""
        share = (jax.process_index() + processes * thread, processes * threads)
        stack: list[_Partial] = []
        with jax.default_device(devices[thread]):
            parts = region_voxels(
                mesh,
                grid,
                six_sep=six_sep,
                region_size=region,
                triangle_ids=triangle_ids,
                progress=progress if thread == 0 else False,
                share=share,
            )
            for position, region_lo, keys, triangle in parts:
                if not len(keys):
                    continue
                with lock:
                    total[0] += len(keys)
                    check_count(total[0], grid, caller)
                if on_region is not None:  # from this thread
                    on_region(position, _global_voxels(region_coords(keys, region_lo), triangle, grid, mode))
                push_region(stack, keys, region_lo, region)
                del keys, triangle
        return merge_all(stack)

    if threads > 1:  # one thread per local device: XLA runs and numpy sorts release the GIL
        with concurrent.futures.ThreadPoolExecutor(threads) as pool:
            mine = merge_all([p for p in pool.map(build, range(threads)) if p is not None])
    else:
        mine = build(0)
    # every process merges every process's sub-DAG, in process order
    parts = [p for p in (all_processes(mine) if processes > 1 else [mine]) if p is not None]
    voxels = sum(int(p.counts.sum()) for p in parts)
    check_count(voxels, grid, caller)
    return finish_dag(merge_all(parts), grid, region, mode, voxels)


def push_region(stack: list[_Partial], keys: np.ndarray, region_lo: np.ndarray, region: int) -> None:
    """Appends the sub-DAG of one region's voxels (Morton codes [n] uint32 or uint64, in
    Morton order, n > 0) to `stack`, merging as in a binary counter (module docstring)."""
    stack.append(_region_dag(keys, region_lo, region))
    while len(stack) > 1 and 2 * stack[-1].rows >= stack[-2].rows:
        b, a = stack.pop(), stack.pop()
        stack.append(_merge(a, b))


def finish_dag(dag: _Partial | None, grid: Grid, region: int, mode: str, voxels: int) -> Octree:
    """The `Octree` (laid out as `build_dag` returns it) of the merged sub-DAGs of regions
    of edge `region` (None: no voxels), with the levels above the regions."""
    if dag is None:
        return build_dag(_empty(grid, mode))
    depth_above = grid.resolution.bit_length() - region.bit_length()  # L = D - s
    levels: list = []
    if depth_above:  # the levels above the regions, over their roots (cells in Morton order)
        codes = morton.encode_host(dag.cells)
        order = morton.stable_order_host(codes)
        roots = Nodes(codes[order], dag.counts[order], dag.roots[order], len(dag.masks[0]))
        levels = levels_above(roots, depth_above, dag=True)
    levels += [(m, c, p) for m, c, p in zip(dag.masks, dag.child + [None], dag.prefix + [None])]
    del dag
    return tree_from_levels(levels, grid, mode, voxels, dag=True)


def merge_all(parts: list[_Partial]) -> _Partial | None:
    """The canonical DAG of all `parts` (None for none): merged pairwise from the back."""
    while len(parts) > 1:
        b, a = parts.pop(), parts.pop()
        parts.append(_merge(a, b))
    return parts[0] if parts else None


def check_count(voxels: int, grid: Grid, caller: str) -> None:
    if voxels > MAX_VOXELS:
        raise JaxvoxError(
            f"{caller}: more than {MAX_VOXELS:,} voxels at {grid.resolution}^3, beyond the uint32 voxel "
            "count of an Octree"
        )


def all_processes(value: Any) -> list[Any]:
    """`value` (any picklable object) of every JAX process, in process order, on every
    process: a `jax.experimental.multihost_utils.process_allgather` of the pickled bytes
    (lengths first, then the bytes padded to the longest). Needs the processes' collectives
    (on CPU: ``jax.config.update("jax_cpu_collectives_implementation", "gloo")`` before
    `jax.distributed.initialize`)."""
    from jax.experimental import multihost_utils

    data = np.frombuffer(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL), np.uint8)
    lengths = np.asarray(multihost_utils.process_allgather(np.array([len(data)], np.int32))).reshape(-1)
    padded = np.zeros(int(lengths.max()), np.uint8)
    padded[: len(data)] = data
    gathered = np.asarray(multihost_utils.process_allgather(padded))
    return [pickle.loads(gathered[k, :n].tobytes()) for k, n in enumerate(lengths)]


_ATTRIBUTE_SLOTS = 1 << 16  # the least buffer the streamed build computes attributes on


class _Spool:
    """Per-voxel attribute arrays appended region by region to raw files in `folder`, so
    that they never need to fit in memory; `arrays` maps them back (read-only memmaps)."""

    def __init__(self, folder: str, resolution: int):
        self.folder = folder
        self.resolution = resolution
        self.layout: dict[str, tuple[np.dtype, tuple[int, ...]]] = {}  # dtype and row shape per name
        self.rows = 0

    def append(self, attributes: dict[str, np.ndarray]) -> None:
        for key, value in attributes.items():
            self.layout.setdefault(key, (value.dtype, value.shape[1:]))
            with open(os.path.join(self.folder, key), "ab") as fh:
                fh.write(np.ascontiguousarray(value).tobytes())
        self.rows += len(next(iter(attributes.values())))

    def arrays(self) -> dict[str, np.ndarray]:
        """The files as [V, ...] read-only memmaps. Each file is first extended with zero
        rows (a sparse tail: no disk written) to the voxel-list ladder, and the memmap is
        the leading V rows of a map of all of them: `render` takes such a table on the
        ladder as it is, with no copy (`jaxvox.render.materials`)."""
        capacity = voxel_bucket(self.rows, self.resolution)
        arrays = {}
        for key, (dtype, shape) in self.layout.items():
            if not self.rows:
                arrays[key] = np.zeros((0, *shape), dtype)
                continue
            path = os.path.join(self.folder, key)
            os.truncate(path, capacity * np.dtype((dtype, shape)).itemsize)
            arrays[key] = np.memmap(path, dtype, "r", shape=(capacity, *shape))[: self.rows]
        return arrays


def dag_with_attributes(
    mesh: Mesh,
    grid: Grid,
    folder,
    *,
    mode: Mode = CONSERVATIVE,
    region: int | None = None,
    progress: bool | None = None,
    distributed: bool = False,
    caller: str = "mesh_to_dag",
) -> tuple[Octree, dict[str, np.ndarray]]:
    """`mesh_to_dag` and the `voxel_attributes` of its voxels, computed region by region and
    appended to one raw file per attribute in `folder` in Morton order; returns (tree,
    attributes as read-only memmaps of those files). With `distributed` every process's
    (and thread's) regions are gathered in memory and every process writes them, in Morton
    order, to its own `folder`."""
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise refuse(f"{caller} attributes", "must be an existing folder", folder)
    for name in ("triangle", "normal", "color"):
        if os.path.exists(os.path.join(folder, name)):
            raise refuse(f"{caller} attributes", f"already holds a file {name!r}", folder)
    spool = _Spool(folder, grid.resolution)
    parts: list[tuple[int, dict[str, np.ndarray]]] = []  # (region position, attributes), distributed

    def attributes_of(vox: Voxels) -> dict[str, np.ndarray]:
        # The attributes are per voxel, but XLA's CPU code for short buffers (measured:
        # 256 and 1,024 slots, not 2,048 and up) rounds some normals and colours
        # differently in the last bit, so every region runs on a long buffer.
        n, pad = int(vox.count), max(_ATTRIBUTE_SLOTS - vox.capacity, 0)
        coords = np.pad(np.asarray(vox.coords), ((0, pad), (0, 0)), constant_values=UNUSED)
        triangle = np.pad(np.asarray(vox.triangle), (0, pad), constant_values=UNUSED)
        vox = Voxels(jnp.asarray(coords), vox.count, vox.overflow, jnp.asarray(triangle), vox.grid, vox.mode)
        return {key: np.asarray(value)[:n] for key, value in voxel_attributes(mesh, vox).items()}

    def gather(position: int, vox: Voxels) -> None:
        if distributed:
            parts.append((position, attributes_of(vox)))
        else:
            spool.append(attributes_of(vox))

    tree = stream_dag(
        mesh,
        grid,
        mode=mode,
        region=region,
        progress=progress,
        distributed=distributed,
        triangle_ids=True,
        on_region=gather,
        caller=caller,
    )
    if distributed:  # regions in Morton order, whichever process or thread voxelized them
        everyone = all_processes(parts) if jax.process_count() > 1 else [parts]
        for _, attributes in sorted((p for process in everyone for p in process), key=lambda p: p[0]):
            spool.append(attributes)
    if not spool.layout:  # no voxels: empty attribute arrays, as voxel_attributes gives them
        none = jnp.zeros((0, 3), jnp.int32), jnp.int32(0), jnp.int32(0), jnp.zeros(0, jnp.int32)
        spool.append(attributes_of(Voxels(*none, grid, tree.mode)))
    return tree, spool.arrays()


def _global_voxels(coords: np.ndarray, triangle: np.ndarray | None, grid: Grid, mode: str) -> Voxels:
    """One region's voxels as `Voxels` of the whole grid (buffer on the shape ladder)."""
    n = len(coords)
    buf = np.full((bucket(n), 3), UNUSED, np.int32)
    buf[:n] = coords
    ids = None
    if triangle is not None:
        padded_ids = np.full(bucket(n), UNUSED, np.int32)
        padded_ids[:n] = triangle
        ids = jax.device_put(padded_ids)
    return Voxels(jax.device_put(buf), jnp.int32(n), jnp.int32(0), ids, grid, mode)


def mesh_to_dag(
    mesh: Mesh,
    grid: Grid,
    *,
    mode: Mode = CONSERVATIVE,
    region: int | None = None,
    progress: bool | None = None,
    distributed: bool = False,
    attributes: str | os.PathLike | None = None,
) -> Octree | tuple[Octree, dict[str, np.ndarray]]:
    """Voxelizes a mesh straight into its sparse voxel DAG, one region at a time.

    Returns the DAG of ``build_dag(voxelize(mesh, grid, mode=mode))``, table for table
    (same node order, same ladder-padded layout), but never holds the whole voxel list:
    the grid is cut into aligned cubic regions of edge `region`, visited in Morton order;
    each region is voxelized alone and built into its sub-DAG, its voxels are dropped,
    and sub-DAGs merge level by level in `build_dag`'s canonical (lexicographic) order.
    The levels above the regions are built from the regions' roots. Memory is about the
    merged DAG (at most twice it while merging) plus one region's voxels and build;
    nothing is truncated.

    Args:
      mesh: the `Mesh` (validated: NaN/inf vertices or bad face indices raise).
      grid: the `Grid`; geometry outside it is clipped.
      mode: "conservative" or "6-separating" (as in `voxelize`).
      region: voxels per region edge, a power of two in ``[2, 1024]`` (None: 1024, the
        voxelizer's region); clipped to the grid's resolution. Smaller regions hold
        fewer voxels at once but run more, smaller steps.
      progress: show a progress bar over regions (default: when there are several).
      distributed: in a program started under `jax.distributed.initialize`, split the
        regions over the ``jax.process_count()`` processes (every n-th region in Morton
        order to each) and a process's regions over its local devices (one thread per
        device, e.g. ``jax.config.update("jax_num_cpu_devices", 2)``), gather their
        sub-DAGs and merge them, so that every process returns the same DAG as one
        process would. On CPU the processes need collectives:
        ``jax.config.update("jax_cpu_collectives_implementation", "gloo")`` before
        `jax.distributed.initialize` (see the guide's "Across processes"). Every process
        must call it with the same arguments. With one process it changes nothing.
      attributes: an existing, empty folder: also compute `voxel_attributes` (triangle
        id, normal, and colour for a coloured mesh) region by region and append them, in
        Morton order, to one raw file per attribute there, so that they need not fit in
        memory; the call then returns ``(dag, attributes)``, the attributes as read-only
        `numpy.memmap` arrays [voxel_count, ...] of those files, which `voxel_index`
        addresses and `save` writes without loading them. Each file ends in zero rows up
        to the voxel-list ladder, so that `render` takes the normals (or an albedo) as
        its table with no copy. With `distributed` each
        process gathers them in memory and writes its own folder.

    Returns:
      An `Octree` (with `attributes`: the pair above) with ``dag=True`` and
      ``overflow == 0``, laid out on the shape ladder (`compact` drops the padding); for
      a mesh that sets no voxel, what `build_dag` returns for no voxels (a root with
      mask 0).

    Raises:
      JaxvoxError: not a `Mesh` or `Grid`, a malformed mesh, a bad mode or region, an
        `attributes` folder that does not exist or already holds attribute files, or
        more than ``2^32 - 1`` voxels (the uint32 voxel count of an `Octree`). A DAG of
        more than ``2^31 - 1`` voxels traces as ``compact_dag(dag, prefix=False)``: its
        Morton indices do not fit `voxel_index`'s int32.
    """
    if attributes is not None:
        return dag_with_attributes(
            mesh, grid, attributes, mode=mode, region=region, progress=progress, distributed=distributed
        )
    return stream_dag(mesh, grid, mode=mode, region=region, progress=progress, distributed=distributed)
