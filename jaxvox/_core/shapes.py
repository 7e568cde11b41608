"""The shape policy: every variable size in jaxvox comes from one ladder of buckets.

Compiled programs are keyed by the shapes of their arrays. Any size that depends on the
input (triangle, column, row, candidate and voxel counts, octree tables, ray batches,
attribute arrays) is rounded up with `bucket` (a power of two, at least `FLOOR`), so two
inputs whose counts fall in the same buckets run the same compiled programs. A padded
buffer is at most twice its contents (or `FLOOR` entries).

Buffers that grow with a surface (voxel lists and octree tables) have a higher floor
that depends on the resolution R, so that the meshes a user meets at one resolution
share one program instead of one per power of two: `voxel_bucket` pads voxel lists to
at least 4 R^2 entries (capped at 2^20: 12 MiB of int32 coordinates) and `row_bucket`
octree tables to at least R^2 rows (capped at 2^18: 16 MiB of child and prefix rows).
Above 1024^3 (`SURFACE_FLOORS_UP_TO`) a mesh costs seconds of work and a compile is
small beside it, so there the floor is `FLOOR` again, and a sparse set at a huge
resolution pays no padding for its work on the tables.
A closed surface at R holds about 0.5-4 R^2 voxels (the shared meshes: 0.5 R^2 for
woody, 3.3 R^2 for the bunny) and a DAG up to about R^2 / 5 rows (the bunny; woody R^2 / 95); what is larger
goes up the ladder by powers of two. At 256^3 the floors cost 3 MiB and 4 MiB.

A sparse distance field's band voxels (`band_bucket`) have the floor of a band about
twice a closed surface's, ``2 (2 band + 1) R^2`` (capped at 2^20), for the same reason.

Widths of packed sort keys go through `key_bits`, which keeps only the widths that
change how many keys are sorted.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

FLOOR = 256  # smallest bucket
SURFACE_FLOORS_UP_TO = 1024  # resolutions whose voxel lists and tree tables get surface floors


def bucket(n: int | np.integer, minimum: int = FLOOR) -> int:
    """The ladder: the smallest power of two >= max(n, minimum)."""
    return 1 << (max(int(n), int(minimum), 1) - 1).bit_length()


def surface_bucket(n: int | np.integer, resolution: int, per_area: int, cap: int) -> int:
    """`bucket` of `n` above a surface floor: ``per_area R^2`` entries, at most `cap`, for
    an R^3 grid up to `SURFACE_FLOORS_UP_TO` (`FLOOR` above it)."""
    return bucket(n, min(per_area * resolution * resolution, cap) if resolution <= SURFACE_FLOORS_UP_TO else FLOOR)


def voxel_bucket(n: int | np.integer, resolution: int) -> int:
    """Capacity of a list of `n` voxels of an R^3 grid: `surface_bucket` above 4 R^2, at
    most 2^20."""
    return surface_bucket(n, resolution, 4, 1 << 20)


def band_bucket(n: int | np.integer, resolution: int, band: int) -> int:
    """Capacity of a list of `n` band voxels of half width `band` in an R^3 grid (or
    region): `surface_bucket` above ``2 (2 band + 1) R^2``, about twice a closed
    surface's band, at most 2^20."""
    return surface_bucket(n, resolution, 2 * (2 * band + 1), 1 << 20)


def row_bucket(n: int | np.integer, resolution: int) -> int:
    """Capacity of `n` octree table rows of an R^3 grid: `surface_bucket` above R^2, at
    most 2^18."""
    return surface_bucket(n, resolution, 1, 1 << 18)


def key_bits(n: int | np.integer) -> int:
    """Bits for ids below `n` (plus one `EMPTY` value), rounded to 8, 10, 16 or 32.

    Eight child ids pack into 2, 3, 4 or 8 uint32 sort keys at those widths; a width in
    between would sort as many keys as the next one up, so it only adds programs.
    """
    need = max(1, int(n)).bit_length()
    return next(b for b in (8, 10, 16, 32) if need <= b)


def expand_counts(counts: jax.Array, capacity: int, start=0):
    """Expands per-item counts into `capacity` work slots, from slot `start` on.

    Item ``i`` owns slots ``[sum(counts[:i]), sum(counts[:i+1]))``; this returns the
    window ``[start, start + capacity)`` of that sequence, so a long expansion can be
    walked window by window with fixed shapes.

    Args:
      counts: [n] int32 non-negative counts.
      capacity: static int, number of slots.
      start: [] int32 first slot of the window (default 0).

    Returns:
      (owner [capacity] int32 item of each slot, rank [capacity] int32 position within
      its item, valid [capacity] bool, total [] int32 = sum(counts)). Slots at or past
      `total` are invalid (their owner is a real item, their rank meaningless).
    """
    if counts.shape[0] == 0:
        zeros = jnp.zeros(capacity, jnp.int32)
        return zeros, zeros, zeros > 0, jnp.int32(0)
    ends = jnp.cumsum(counts)
    starts = ends - counts
    # The owner of slot s is the last item starting at or before s, and that item is not
    # empty (an empty item starts where the next one does): the number of items starting
    # at or before s, minus one. Items starting before the window count at its first slot.
    # (A histogram and a cumulative sum: on the CPU faster than marks and a cumulative max.)
    first = jnp.clip(starts - start, 0, capacity)
    owner = jnp.cumsum(jnp.zeros(capacity, jnp.int32).at[first].add(1, mode="drop")) - 1
    slot = start + jnp.arange(capacity, dtype=jnp.int32)
    return owner, slot - starts[owner], slot < ends[-1], ends[-1]


SMALL_CHUNKS = 16  # a job smaller than one chunk runs in chunks this many times smaller


def chunk_rows(n: int | np.integer, size: int, fewer: int = SMALL_CHUNKS) -> int:
    """Rows per call for a host loop over `n` rows in fixed chunks of `size`: `size`, or
    ``size // fewer`` when the whole job is smaller than one chunk (a small mesh, or one
    small region, would otherwise pay a full chunk of padding per call). Two programs
    per kernel at most, whatever `n`."""
    return size if n >= size else max(size // fewer, 1)


def pad_rows(a: np.ndarray, rows: int, fill=0) -> np.ndarray:
    """Host array `a` with rows of `fill` appended up to `rows` rows (a shape on the
    ladder, or a fixed chunk size), same dtype."""
    out = np.full((rows,) + a.shape[1:], fill, a.dtype)
    out[: len(a)] = a
    return out
