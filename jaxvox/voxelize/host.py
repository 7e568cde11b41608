"""The host-side voxelizer: `voxelize` streams runs of triangles through fixed work
windows into fixed candidate buffers, region by region, and `voxel_capacities` sizes
`voxelize_fixed`."""

from __future__ import annotations

import functools
from collections.abc import Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox import morton
from jaxvox._core.buffers import aligned_empty, join_rows, progress_off, reserved_empty
from jaxvox._core.checks import check_choice, check_int, check_type, refuse
from jaxvox._core.errors import JaxvoxError
from jaxvox._core.shapes import bucket, voxel_bucket
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, validate_mesh
from jaxvox.voxelize.triangles import expand_candidates, expand_columns, expand_rows, setup_triangles
from jaxvox.voxelize.voxels import (
    CONSERVATIVE,
    MODES,
    REGION_SIZE,
    ROW_CHUNK,
    SIX_SEPARATING,
    UNUSED,
    Capacities,
    Mode,
    Voxels,
)

# ------------------------------------------------------------------ host-side API

# The host path walks fixed work windows, so that every mesh at every resolution runs the
# same few compiled programs whatever its counts: triangles in runs of at most `_CHUNK`,
# expanded into windows of columns, row slots and candidates, written into a buffer of
# `_SLOTS` slots, which numpy sorts (`_sort_region`): no program depends on a mesh's
# counts.
_CHUNK = 4096
_WINDOW_COLUMNS = 1 << 15
_WINDOW_ROWS = 1 << 16
_WINDOW_CANDIDATES = 1 << 17
_SLOTS = 1 << 19  # candidate slots one emit call writes
_FILL = 0.8  # share of `_SLOTS` that a run of triangles is sized to fill
_MOST_VOXELS = 2**31 - 1  # voxels a `voxelize` result may hold (`Voxels.count` is int32)


def _walk(tris_grid, region_lo, region_hi, six_sep, visit, carry):
    """Calls ``carry = visit(rows, carry)`` on every row window of a chunk of triangles.

    Returns:
      (columns [] int32, row slots [] int32, final carry).
    """
    tris = setup_triangles(tris_grid, region_lo, region_hi, six_sep)

    def columns_step(state):
        start, slots, carry = state
        columns = expand_columns(tris, _WINDOW_COLUMNS, start)
        n_slots = jnp.sum((columns.n_rows + ROW_CHUNK - 1) // ROW_CHUNK)

        def rows_step(state):
            row_start, carry = state
            rows = expand_rows(columns, _WINDOW_ROWS, ROW_CHUNK, row_start)
            return row_start + _WINDOW_ROWS // ROW_CHUNK, visit(rows, carry)

        _, carry = jax.lax.while_loop(lambda s: s[0] < n_slots, rows_step, (jnp.int32(0), carry))
        return start + _WINDOW_COLUMNS, slots + n_slots * ROW_CHUNK, carry

    n_cols = jnp.sum(tris.n_cols)
    _, n_slots, carry = jax.lax.while_loop(lambda s: s[0] < n_cols, columns_step, (jnp.int32(0), jnp.int32(0), carry))
    return n_cols, n_slots, carry


@functools.partial(jax.jit, static_argnames=("six_sep",))
def _count_chunk(tris_grid, region_lo, region_hi, *, six_sep):
    """Counts of a chunk [_CHUNK, 3, 3] in a region: [3] int32 columns, row slots,
    candidates (`voxel_capacities`)."""
    visit = lambda rows, total: total + jnp.sum(rows.n_depth)
    n_cols, n_slots, n_cand = _walk(tris_grid, region_lo, region_hi, six_sep, visit, jnp.int32(0))
    return jnp.stack([n_cols, n_slots, n_cand])


@functools.partial(jax.jit, static_argnames=("six_sep", "with_ids"))
def _emit_chunk(tris_grid, ids, region_lo, region_hi, offset, *, six_sep, with_ids):
    """Writes a run of triangles' candidates, in triangle order, into `_SLOTS` slots and
    counts them per triangle, so the host keeps the triangles whose candidates all fit.

    Args:
      tris_grid: [_CHUNK, 3, 3] float32 triangles in grid units (NaN rows are skipped).
      ids: [_CHUNK] int32 triangle ids to record.
      offset: [] int32 slot of the run's first candidate (0, or ``-k * _SLOTS`` to write
        the k-th further part of a triangle with more candidates than `_SLOTS`);
        candidates outside ``[0, _SLOTS)`` are counted, not written.

    Returns:
      (slots: (keys,) or (keys, distance bits, triangle ids) of uint32 [_SLOTS], keys
      `morton.EMPTY` past the last candidate; per [_CHUNK] int32 candidates per triangle).
    """

    # A window's candidates fill consecutive slots, so each window is one contiguous
    # write (no scatter) into the slots between margins of a window: slots before them
    # land in the front margin, slots past them (and a window's unused tail, EMPTY keys
    # that the next window overwrites) in the back one.
    margin = _WINDOW_CANDIDATES
    size = 2 * margin + _SLOTS
    buffers = (jnp.full(size, morton.EMPTY, jnp.uint32),) + tuple(
        jnp.zeros(size, jnp.uint32) for _ in range(2 * with_ids)
    )

    def visit(rows, carry):
        buffers, offset, per = carry
        n = jnp.sum(rows.n_depth)

        def step(state):
            start, buffers = state
            keys, payload, _ = expand_candidates(tris_grid, rows, _WINDOW_CANDIDATES, 1, with_ids, start, ids)
            at = margin + offset + start  # in [1, margin + _SLOTS): the loop's bounds below
            return start + _WINDOW_CANDIDATES, tuple(
                jax.lax.dynamic_update_slice(b, v, (at,)) for b, v in zip(buffers, keys + payload)
            )

        # Only the windows that overlap the slots: from the one holding the first slot.
        first = jnp.maximum(-offset, 0) // _WINDOW_CANDIDATES * _WINDOW_CANDIDATES
        _, buffers = jax.lax.while_loop(lambda s: (s[0] < n) & (offset + s[0] < _SLOTS), step, (first, buffers))
        # (saturated: a run's candidates may pass 2^31, and nothing past the slots is written)
        return buffers, jnp.minimum(offset + n, _SLOTS), per.at[rows.place[:, 4]].add(rows.n_depth)

    carry = (buffers, offset, jnp.zeros(_CHUNK, jnp.int32))
    buffers, _, per = _walk(tris_grid, region_lo, region_hi, six_sep, visit, carry)[2]
    return tuple(b[margin : margin + _SLOTS] for b in buffers), per


def _sort_region(parts, with_ids: bool):
    """Sorts and deduplicates a region's candidates on the host.

    numpy's sort compiles nothing, so regions of any size share the device programs, and
    on the CPU it is faster than XLA's sort.
    With ids the candidates sort by (key, distance bits, triangle id), so the first of a
    key is the closest triangle, ties to the lower id, as in
    `jaxvox.voxelize.fixed.sort_unique`.

    Args:
      parts: the region's written slots: with ids, each (keys, distance bits, triangle
        ids) of uint32 [n_i] (keys region-relative Morton words); without ids, each
        run's keys as `_sorted_keys` gives them, or a future of that.

    Returns:
      (keys [n] uint32: the voxels' Morton words (`region_coords` decodes them), in
      Morton order; triangle [n] int32 or None; written: the number of candidates in the
      parts, keys other than `morton.EMPTY`).
    """
    if not with_ids:
        runs = [part.result() if isinstance(part, Future) else part for part in parts]
        keys = np.concatenate([run.keys for run in runs])
        if len(runs) > 1:
            keys.sort(kind="stable")  # a merge of the sorted runs (timsort)
        return keys[morton.run_starts(keys)], None, sum(run.written for run in runs)
    keys, *payload = (np.concatenate([part[i] for part in parts]) for i in range(len(parts[0])))
    order = np.lexsort((payload[1], payload[0], keys))
    keys, tri = keys[order], payload[1][order]
    first, written = _distinct_written(keys)
    return keys[first], tri[first].astype(np.int32), written


def _distinct_written(keys: np.ndarray) -> tuple[np.ndarray, int]:
    """Of sorted keys [n] uint32: the first index of each distinct written key (int64) and
    the number of written ones (keys other than `morton.EMPTY`, the largest, which sorts last)."""
    written = int(np.searchsorted(keys, morton.EMPTY))
    return morton.run_starts(keys[:written]), written


class _SortedKeys(NamedTuple):
    keys: np.ndarray  # [n] uint32 distinct written keys in ascending order
    written: int  # the candidates (keys other than `morton.EMPTY`) they came from


def _sorted_keys(part: tuple[np.ndarray, ...]) -> _SortedKeys:
    """One emit call's written keys (a part of `_emit_region`, without ids), sorted and
    distinct: a region's parts are sorted one by one as they come (on the worker
    thread, while the next ones are emitted), then merged (`_sort_region`)."""
    keys = np.sort(part[0])
    first, written = _distinct_written(keys)
    return _SortedKeys(keys[first], written)


def region_coords(keys: np.ndarray, region_lo, out: np.ndarray | None = None) -> np.ndarray:
    """Voxel indices [n, 3] int32 of a region's keys (as `_sort_region` returns them), in
    `out` ([n, 3] int32) when given.

    Args:
      keys: [n] uint32 Morton words of the voxels' low 10 bits per axis.
      region_lo: int32 [3] first voxel of the (aligned, at most 1024-wide) region, which
        supplies the higher bits.
    """
    high = (np.asarray(region_lo, np.int32) >> morton.WORD_BITS) << morton.WORD_BITS
    return morton.decode_word_host(keys, out=out, high=high)


def _grid_triangles(mesh: Mesh, grid: Grid) -> np.ndarray:
    """Host float32 [F, 3, 3] triangle corners in grid units (the same float32 operations
    as `Grid.to_grid_units`; numpy, so a new mesh size compiles nothing)."""
    v = np.asarray(mesh.vertices, np.float32)[np.asarray(mesh.faces)]
    return (v - np.asarray(grid.origin, np.float32)) / np.asarray(grid.voxel_size, np.float32)


def _chunks(tris: np.ndarray, idx: np.ndarray):
    """Device arrays (triangles [_CHUNK, 3, 3] NaN-padded, ids [_CHUNK] int32) per chunk of `idx`."""
    out = []
    for start in range(0, len(idx), _CHUNK):
        part = idx[start : start + _CHUNK]
        t = np.full((_CHUNK, 3, 3), np.nan, np.float32)
        t[: len(part)] = tris[part]
        ids = np.zeros(_CHUNK, np.int32)
        ids[: len(part)] = part
        out.append((jax.device_put(t), jax.device_put(ids)))
    return out


def _region_bounds(region_lo, region_size: int):
    lo = np.asarray(region_lo, np.int32)
    return jax.device_put(lo), jax.device_put(lo + np.int32(region_size - 1))


def _count_chunks(chunks, lo, hi, six_sep: bool) -> np.ndarray:
    """Host int64 [chunks, 3] counts of a region's chunks: columns, row slots, candidates."""
    counts = jax.device_get([_count_chunk(t, lo, hi, six_sep=six_sep) for t, _ in chunks])
    return np.asarray(counts, np.int64).reshape(-1, 3)


def _emit_region(
    tris: np.ndarray,
    idx: np.ndarray,
    region_lo,
    region_size: int,
    six_sep: bool,
    with_ids: bool,
    sorter: Executor,
    helper: Executor,
):
    """The emit passes of one region (`_emit_runs`). The second half of the region's
    triangles (when they make more than one run) is emitted on the `helper` thread while
    this thread emits the first: the emit programs of two threads run side by side.
    Without ids, each run's keys are sorted on `sorter` (`_sorted_keys`) while the next
    runs are emitted.

    Returns:
      (parts: the written slots, in no particular order, as `_sort_region` takes them;
      total: the candidates counted) for `_unique_region`.
    """
    lo, hi = _region_bounds(region_lo, region_size)
    emit = functools.partial(_emit_chunk, region_lo=lo, region_hi=hi, six_sep=six_sep, with_ids=with_ids)
    parts: list = []
    keep = parts.append if with_ids else lambda part: parts.append(sorter.submit(_sorted_keys, part))
    if len(idx) <= _CHUNK:
        return parts, _emit_runs(emit, tris, idx, keep)
    half = len(idx) // 2
    second = helper.submit(_emit_runs, emit, tris, idx[half:], keep)
    total = _emit_runs(emit, tris, idx[:half], keep)
    return parts, total + second.result()


def _emit_runs(emit, tris: np.ndarray, idx: np.ndarray, keep) -> int:
    """Runs of the triangles `idx` write their candidates (`emit`, an `_emit_chunk` of
    the region), each run sized from the candidates per triangle of the last one; the
    triangles whose candidates did not all fit start the next run. Each run's written
    slots go to `keep`.

    Returns:
      The candidates counted.
    """
    total, pos, run = 0, 0, _CHUNK
    while pos < len(idx):
        part = idx[pos : pos + run]
        ((t, ids),) = _chunks(tris, part)
        slots, per = emit(t, ids, offset=np.int32(0))
        ends = np.cumsum(np.asarray(per, np.int64)[: len(part)])
        done = int(np.searchsorted(ends, _SLOTS, side="right"))  # triangles whose candidates all fit
        if done:
            keep(tuple(np.asarray(b)[: ends[done - 1]] for b in slots))
        else:  # one triangle holds more than `_SLOTS` candidates (all the slots): the rest part by part
            done, ((t, ids),) = 1, _chunks(tris, idx[pos : pos + 1])
            keep(tuple(np.asarray(b) for b in slots))
            for start in range(_SLOTS, int(ends[0]), _SLOTS):
                slots = emit(t, ids, offset=np.int32(-start))[0]
                keep(tuple(np.asarray(b)[: ends[0] - start] for b in slots))
        total += int(ends[done - 1])
        pos += done
        run = int(np.clip(_FILL * _SLOTS * done / max(ends[done - 1], 1), 1, _CHUNK))
    return total


def _unique_region(parts: list, total: int, with_ids: bool):
    """One sort makes a region's candidates (`_emit_region`'s parts, as `_sort_region` takes
    them) unique.

    Returns:
      (keys [n] uint32 Morton words of the voxels, see `region_coords`; triangle [n]
      int32 ids or None) host arrays.
    """
    keys, triangle, written = _sort_region(parts, with_ids)
    # Every kept candidate was counted by the same walk that wrote it; a walk that wrote
    # fewer (or more) would lose voxels, so it raises.
    if written != total:
        raise JaxvoxError(f"internal error: {written} candidates written, {total} counted")
    return keys, triangle


def _regions(tris_np: np.ndarray, resolution: int, region_size: int):
    """Aligned regions touched by any triangle's bounding box, in Morton order.

    Returns a list of (region_lo int32[3], triangle indices) pairs.
    """
    n = resolution // region_size
    if n == 1:
        return [(np.zeros(3, np.int32), np.arange(len(tris_np)))]
    lo = np.clip(np.floor((tris_np.min(1) - 1.0) / region_size), 0, n - 1).astype(np.int64)
    hi = np.clip(np.floor(tris_np.max(1) / region_size), 0, n - 1).astype(np.int64)
    inside = (tris_np.max(1) >= 0).all(1) & (tris_np.min(1) <= resolution).all(1)
    ids = np.flatnonzero(inside)
    tri, code = morton.box_cells(ids, lo[ids], hi[ids])
    starts = morton.run_starts(code)
    cells = morton.decode_host(code[starts]) * region_size
    return [(c.astype(np.int32), part) for c, part in zip(cells, np.split(tri, starts[1:]))]


def region_voxels(
    mesh: Mesh,
    grid: Grid,
    *,
    six_sep: bool,
    region_size: int,
    triangle_ids: bool,
    progress: bool | None,
    share: tuple[int, int] = (0, 1),
) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]]:
    """The region loop: `voxelize`'s regions one at a time, for `voxelize` itself and for
    consumers that keep only a summary of each (`jaxvox.octree.stream`); the caller has
    checked the mesh, grid and region size.
    ``share=(k, n)`` takes only every n-th region from the k-th on (one of n processes).

    Yields:
      Per aligned region that a triangle's bounding box touches, in Morton order:
      (its position in that order, region_lo int32 [3], keys [n] uint32 Morton words
      of its voxels in Morton order (`region_coords` decodes them), triangle [n] int32
      ids or None) host arrays; n may be 0.
    """
    tris = _grid_triangles(mesh, grid)
    regions = _regions(tris, grid.resolution, region_size) if mesh.num_faces else []
    from tqdm.auto import tqdm

    mine = list(enumerate(regions))[share[0] :: share[1]]
    disable = progress_off(progress, len(mine))
    # A region's candidates are sorted on a worker thread while this one emits the next
    # region's, or (without ids) its own next runs, and a helper thread emits half of each
    # region's triangles (XLA's runs and numpy's sort release the GIL).
    with ThreadPoolExecutor(1) as sorter, ThreadPoolExecutor(1) as helper:
        pending = None
        for position, (region_lo, idx) in tqdm(mine, desc="regions", disable=disable, leave=False):
            parts, total = _emit_region(tris, idx, region_lo, region_size, six_sep, triangle_ids, sorter, helper)
            if pending is not None:
                yield pending[0], pending[1], *pending[2].result()
            pending = position, region_lo, sorter.submit(_unique_region, parts, total, triangle_ids)
            del parts
        if pending is not None:
            yield pending[0], pending[1], *pending[2].result()


def _pad_rows(parts: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    """Moves int32 host arrays into one buffer of `shape` padded with `UNUSED` (see `join_rows`)."""
    return join_rows(parts, shape, UNUSED, dtype=np.int32)


def voxelize(
    mesh: Mesh,
    grid: Grid,
    *,
    mode: Mode = CONSERVATIVE,
    triangle_ids: bool = False,
    region_size: int = REGION_SIZE,
    progress: bool | None = None,
) -> Voxels:
    """Voxelizes a triangle mesh exactly, whatever its counts.

    Triangles go through runs of at most a fixed chunk and fixed work windows, so every
    mesh runs the same compiled programs. Each call writes a run's candidates into a
    fixed buffer and counts them per triangle; the triangles whose candidates did not
    all fit go to the next run, so nothing is dropped. The kept candidates are checked
    against their count, and a mismatch raises instead of returning a truncated set.

    Grids above `region_size`^3 are streamed: the grid is cut into aligned cubic
    regions, visited in Morton order, each voxelized from the triangles whose bounding
    boxes touch it, so working memory follows the surface inside one region and the
    concatenated result is already in Morton order. A region's sort and the decoding of
    its voxels into the result run on worker threads beside the next region's emit calls.

    Args:
      mesh: the `Mesh` (validated: NaN/inf vertices or bad face indices raise).
      grid: the `Grid`; geometry outside it is clipped.
      mode: "conservative" (every voxel whose closed box touches the closed triangle)
        or "6-separating" (Schwarz & Seidel's thin, 6-separating subset).
      triangle_ids: also record, per voxel, the id of the triangle closest to its
        centre among those that set it (ties to the lower id).
      region_size: edge of the streaming regions, a power of two <= 1024.
      progress: show a progress bar over regions (default: when on a terminal).

    Returns:
      `Voxels` with ``overflow == 0`` and capacity rounded up to a few buckets.

    Raises:
      JaxvoxError: not a `Grid`, a bad mode, region size or mesh.
    """
    check_type("voxelize grid", grid, Grid)
    six_sep = check_choice("voxelize mode", mode, MODES) == SIX_SEPARATING
    validate_mesh(mesh)
    region_size = check_int("voxelize region_size", region_size, minimum=1, maximum=REGION_SIZE)
    if region_size & (region_size - 1):
        raise refuse("voxelize region_size", f"must be a power of two <= {REGION_SIZE}", region_size)
    region_size = min(region_size, grid.resolution)
    tri_parts: list[np.ndarray] = []
    walk = region_voxels(
        mesh, grid, six_sep=six_sep, region_size=region_size, triangle_ids=triangle_ids, progress=progress
    )
    # Each region's keys are decoded on a worker thread straight into the result (address
    # space for the most voxels a result may hold, `reserved_empty`), while this thread
    # runs the next region; where the system refuses such a map, after the last region.
    most = voxel_bucket(min(grid.resolution**3, _MOST_VOXELS), grid.resolution)
    coords = reserved_empty((most, 3), np.int32)
    parts: list[tuple[np.ndarray, np.ndarray]] = []  # (region_lo, keys) left to decode
    total = 0
    with ThreadPoolExecutor(1) as worker:
        decoded = []
        for _, region_lo, keys, triangle in walk:
            if triangle is not None:  # with triangle_ids
                tri_parts.append(triangle)
            if coords is not None and total + len(keys) <= _MOST_VOXELS:
                decoded.append(worker.submit(region_coords, keys, region_lo, coords[total : total + len(keys)]))
            else:
                parts.append((region_lo, keys))  # on the host as we go: device memory holds one region
            total += len(keys)
        for done in decoded:
            done.result()
    if total > _MOST_VOXELS:  # `Voxels.count` is int32
        raise JaxvoxError(
            f"voxelize: {total:,} voxels at {grid.resolution}^3, more than an int32 count holds; "
            "build the DAG region by region with mesh_to_dag"
        )
    cap = voxel_bucket(total, grid.resolution)
    if coords is None:
        coords, start = aligned_empty((cap, 3), np.int32), 0
        for region_lo, keys in parts:  # decoded straight into the result
            region_coords(keys, region_lo, out=coords[start : start + len(keys)])
            start += len(keys)
    del parts
    coords = coords[:cap]
    coords[total:] = UNUSED
    triangle = _pad_rows(tri_parts, (cap,)) if triangle_ids else None
    to_device = functools.partial(jax.device_put, may_alias=True)  # aligned buffers: no copy
    return Voxels(
        to_device(coords), jnp.int32(total), jnp.int32(0), None if triangle is None else to_device(triangle), grid, mode
    )


def voxel_capacities(mesh: Mesh, grid: Grid, *, mode: Mode = CONSERVATIVE) -> Capacities:
    """Capacities with which `voxelize_fixed` does not overflow for this mesh and grid.

    Found by the host-side counting pass over the whole grid as one region (and the
    voxel count of `voxelize`), each rounded up on the shape ladder so that similar
    inputs share a compiled function.

    Raises:
      JaxvoxError: not a `Grid`, a bad mode or mesh.
    """
    check_type("voxel_capacities grid", grid, Grid)
    six_sep = check_choice("voxel_capacities mode", mode, MODES) == SIX_SEPARATING
    validate_mesh(mesh)
    if mesh.num_faces == 0:
        return Capacities(*(bucket(0),) * 4, ROW_CHUNK)
    lo, hi = _region_bounds(np.zeros(3, np.int32), grid.resolution)
    chunks = _chunks(_grid_triangles(mesh, grid), np.arange(mesh.num_faces))
    columns, rows, candidates = (bucket(n) for n in _count_chunks(chunks, lo, hi, six_sep).sum(0))
    voxels = bucket(int(voxelize(mesh, grid, mode=mode).count))
    return Capacities(columns, rows, candidates, voxels, ROW_CHUNK)
