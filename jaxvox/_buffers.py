"""Fixed-capacity buffer helpers shared by the voxelizer and the octree builder."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def bucket(n: int, minimum: int = 4096) -> int:
    """Rounds up to 4, 5, 6 or 7 times a power of two (at most 25% slack, few shapes)."""
    n = max(int(n), minimum)
    shift = max(n.bit_length() - 3, 0)
    return -(-n >> shift) << shift


def bucket_pow2(n: int, minimum: int = 64) -> int:
    """Rounds up to a power of two: coarse buckets for small, frequently rebuilt buffers."""
    return 1 << (max(int(n), minimum, 1) - 1).bit_length()


def expand_counts(counts: jax.Array, capacity: int):
    """Expands per-item counts into `capacity` work slots.

    Args:
      counts: [n] int32 non-negative counts.
      capacity: static int, number of slots.

    Returns:
      (owner [capacity] int32 item of each slot, rank [capacity] int32 position within
      its item, valid [capacity] bool, total [] int32 = sum(counts)). Slots past
      `total` are invalid (their owner is a real item, their rank meaningless).
    """
    if counts.shape[0] == 0:
        zeros = jnp.zeros(capacity, jnp.int32)
        return zeros, zeros, zeros > 0, jnp.int32(0)
    ends = jnp.cumsum(counts)
    starts = ends - counts
    # The owner of slot s is the last item starting at or before s: mark starts, cummax.
    ids = jnp.where(counts > 0, jnp.arange(counts.shape[0], dtype=jnp.int32), 0)
    owner = jax.lax.cummax(jnp.zeros(capacity, jnp.int32).at[starts].max(ids, mode="drop"))
    slot = jnp.arange(capacity, dtype=jnp.int32)
    return owner, slot - starts[owner], slot < ends[-1], ends[-1]
