"""Sorting and deduplication of candidates, and the jittable `voxelize_fixed`."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxvox import morton
from jaxvox._core.checks import check_choice, check_type
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh
from jaxvox.overflow import raise_if_overflow
from jaxvox.voxelize.triangles import NARROW, expand_candidates, expand_columns, expand_rows, setup_triangles
from jaxvox.voxelize.voxels import (
    CONSERVATIVE,
    MODES,
    OVERFLOW_CANDIDATES,
    OVERFLOW_COLUMNS,
    OVERFLOW_ROWS,
    OVERFLOW_VOXELS,
    REGION_SIZE,
    SIX_SEPARATING,
    UNUSED,
    Capacities,
    Mode,
    Voxels,
    check_capacities,
)


def _compact(keep, arrays, capacity, fill):
    """Moves entries where `keep` to the front of `capacity`-sized buffers (order kept).

    Returns:
      (tuple of [capacity] arrays padded with `fill`, number of kept entries [] int32).
    """
    pos = jnp.where(keep, jnp.cumsum(keep) - 1, capacity)  # dropped entries go past the end
    out = tuple(jnp.full(capacity, fill, a.dtype).at[pos].set(a, mode="drop") for a in arrays)
    return out, jnp.sum(keep, dtype=jnp.int32)


def sort_unique(keys, payload, words: int, region_lo, vox_cap: int):
    """Sorts candidates (EMPTY padding sorts last), keeps the first of each key, decodes.

    With a payload the sort's later keys are (distance, triangle), so the kept entry is
    the closest triangle, ties to the lower id.

    Returns:
      (coords [vox_cap, 3] int32, triangle [vox_cap] int32 or None, count [] int32).
    """
    operands = keys + payload
    if len(operands) == 1:
        ordered = (jnp.sort(operands[0]),)
    else:
        ordered = jax.lax.sort(operands, num_keys=len(operands))
    k = ordered[:words]
    changed = functools.reduce(jnp.logical_or, [a[1:] != a[:-1] for a in k])
    keep = (k[-1] != morton.EMPTY) & jnp.concatenate([jnp.ones(1, bool), changed])
    extra = (ordered[-1].astype(jnp.int32),) if payload else ()
    out, count = _compact(keep, k + extra, vox_cap, 0)
    if words == 1:  # the region is aligned and at most 1024 wide: its high word is shared
        coords = morton.decode_word(out[0]) | ((region_lo >> morton.WORD_BITS) << morton.WORD_BITS)
    else:
        coords = morton.decode(out[0], out[1])
    used = jnp.arange(vox_cap) < count
    coords = jnp.where(used[:, None], coords, UNUSED)
    triangle = jnp.where(used, out[-1], UNUSED) if payload else None
    return coords, triangle, jnp.minimum(count, vox_cap), count


# ------------------------------------------------------------------- jittable core


def _words(region_size: int) -> int:
    return 1 if region_size <= REGION_SIZE else 2


def _pipeline(tris_grid, region_lo, region_size: int, six_sep: bool, caps: Capacities, with_ids: bool):
    """All stages for one aligned cubic region; returns (coords, triangle, count, overflow)."""
    region_hi = region_lo + region_size - 1
    words = _words(region_size)
    tris = setup_triangles(tris_grid, region_lo, region_hi, six_sep)
    wide = region_size > NARROW  # (the whole grid is one region here)
    columns = expand_columns(tris, caps.columns, wide=wide)
    rows = expand_rows(columns, caps.rows, caps.row_chunk, wide=wide)
    keys, payload, n_cand = expand_candidates(tris_grid, rows, caps.candidates, words, with_ids)
    coords, triangle, count, n_vox = sort_unique(keys, payload, words, region_lo, caps.voxels)
    overflow = functools.reduce(
        jnp.bitwise_or,
        [
            jnp.where(columns.total > caps.columns, OVERFLOW_COLUMNS, 0),
            jnp.where(rows.total > caps.rows, OVERFLOW_ROWS, 0),
            jnp.where(n_cand > caps.candidates, OVERFLOW_CANDIDATES, 0),
            jnp.where(n_vox > caps.voxels, OVERFLOW_VOXELS, 0),
        ],
    ).astype(jnp.int32)
    return coords, triangle, count, overflow


def voxelize_fixed(
    mesh: Mesh,
    grid: Grid,
    capacities: Capacities,
    *,
    mode: Mode = CONSERVATIVE,
    triangle_ids: bool = False,
    checked: bool = False,
) -> Voxels:
    """Jittable voxelization with static capacities; usable inside a user's `jax.jit`.

    Never resizes: what does not fit is dropped and flagged in ``Voxels.overflow``
    (`jaxvox.Overflow` bits COLUMNS, ROWS, CANDIDATES, VOXELS). Get capacities that fit
    from `voxel_capacities`, or use the host-side `voxelize`, which sizes them and never
    returns a truncated result (see `jaxvox.overflow` for the protocol).
    Input validation (NaN vertices, face indices) is the caller's job here: non-finite
    triangles are skipped and out-of-range indices are clamped by JAX's gather.

    Args:
      mesh: `Mesh` with F faces.
      grid: `Grid`; the whole grid is one region (Morton keys take two words above 1024^3).
      capacities: `Capacities` (static).
      mode: "conservative" or "6-separating" (static).
      triangle_ids: also return the closest triangle id per voxel (static).
      checked: raise (as an error of the running computation) instead of returning a
        flagged result when a capacity is too small (static).

    Returns:
      `Voxels` with capacity ``capacities.voxels``.

    Raises:
      JaxvoxError: not a `Mesh` or `Grid`, a bad mode, or capacities that are not
        integers >= 1 with a power-of-two ``row_chunk`` dividing ``rows``.
    """
    check_type("voxelize_fixed mesh", mesh, Mesh)
    check_type("voxelize_fixed grid", grid, Grid)
    capacities = check_capacities("voxelize_fixed capacities", capacities)
    six_sep = check_choice("voxelize_fixed mode", mode, MODES) == SIX_SEPARATING
    tris = grid.to_grid_units(mesh.triangles())
    coords, triangle, count, overflow = _pipeline(
        tris, jnp.zeros(3, jnp.int32), grid.resolution, six_sep, capacities, triangle_ids
    )
    if checked:
        raise_if_overflow("voxelize_fixed result", overflow)
    return Voxels(coords, count, overflow, triangle, grid, mode)
