"""Prefix sums of long one-dimensional arrays in jitted code.

`jnp.cumsum` lowers to a tree of reduce-windows that XLA:CPU runs slowly on long arrays,
and `jax.lax.associative_scan`, fast to run, adds much to a program's compilation
(about 20 levels of slices and pads for 1M). `cumsum` here lays the array out as
[L, K] columns, runs one `lax.scan` over the L rows adding whole [K] vectors, and adds
the columns' offsets: nearly the scan's speed with one small loop to compile.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

_COLUMNS = 256  # K: columns of the layout, at least (the vectors each scan step adds)
_ROWS = 4096  # L: scan steps, at most


def cumsum(x: jax.Array) -> jax.Array:
    """Inclusive prefix sums of [N] bool or integer `x`: [N] int32."""
    x = x.astype(jnp.int32)
    n = x.shape[0]
    rows = max(1, min(_ROWS, n // _COLUMNS))
    columns = -(-n // rows)
    a = jnp.pad(x, (0, rows * columns - n)).reshape(columns, rows).T  # a[r, c] = x[c L + r]
    totals, sums = jax.lax.scan(lambda carry, row: (carry + row, carry + row), jnp.zeros(columns, jnp.int32), a)
    offsets = jnp.cumsum(totals) - totals  # of each column's run of L values
    return (sums + offsets).T.reshape(-1)[:n]


def compact_indices(mask: jax.Array, size: int, *, fill: int = 0) -> jax.Array:
    """The indices of the True entries of [N] bool `mask`, in order, in an int32 [size]
    array (static `size`); the slots past their count hold `fill`, and indices past `size`
    are dropped. The compaction by a prefix sum of the mask and one scatter, shared by the
    ray queue of the persistent lanes, `on_marked` and the staged loops."""
    n = mask.shape[0]
    slot = jnp.where(mask, cumsum(mask) - 1, size)  # unmarked entries go one past the end
    return jnp.full(size, fill, jnp.int32).at[slot].set(jnp.arange(n, dtype=jnp.int32), mode="drop")


def on_marked(fn, marked: jax.Array, rows: jax.Array, fill: jax.Array, chunk: int) -> jax.Array:
    """``fn(rows[i])`` where ``marked[i]``, `fill` elsewhere: [N] of `fill`'s dtype.

    `fn` maps [chunk, ...] rows to [chunk] values (a walk down a tree, say). The marked
    rows are compacted and `fn` runs on `chunk` of them at a time inside a `while_loop`
    that runs as many chunks as there are marked rows, so the lookups cost what the
    marked rows cost, not what all N cost (an image of the bunny: 14% of the rays hit).

    Args:
      fn: jittable [chunk, ...] -> [chunk].
      marked: [N] bool.
      rows: [N, ...] the per-ray inputs of `fn`.
      fill: [] the value of the unmarked rays (its dtype is the result's).
      chunk: rows per call of `fn` (static).
    """
    n = marked.shape[0]
    if n == 0:
        return jnp.full(0, fill)
    size = n + -n % chunk
    order = compact_indices(marked, size)
    count = jnp.sum(marked)

    def body(carry):
        k, out = carry
        ids = jax.lax.dynamic_slice(order, (k * chunk,), (chunk,))
        live = k * chunk + jnp.arange(chunk) < count
        return k + 1, out.at[jnp.where(live, ids, n)].set(fn(rows[ids]), mode="drop")

    out = jnp.full(n, fill)
    return jax.lax.while_loop(lambda c: c[0] * chunk < count, body, (jnp.int32(0), out))[1]
