"""Prefix sums of long one-dimensional arrays in jitted code.

`jnp.cumsum` lowers to a tree of reduce-windows that XLA:CPU runs slowly on long arrays,
and `jax.lax.associative_scan`, fast to run, adds much to a program's compilation
(about 20 levels of slices and pads for 1M). `cumsum` here lays the array out as
[L, K] columns, runs one `lax.scan` over the L rows adding whole [K] vectors, and adds
the columns' offsets: nearly the scan's speed with one small loop to compile.

`mark` and `nth_marked` find the marked entries of a long mask by position, where a
compaction (a prefix sum and a scatter of every entry) would move them all.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

_COLUMNS = 256  # K: columns of the layout, at least (the vectors each scan step adds)
_ROWS = 4096  # L: scan steps, at most
_CHUNK = 16384  # positions looked up per step of `compact_indices`


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


class Marks(NamedTuple):
    """The True entries of an [N] bool mask, found by position without moving them
    (`mark`, `nth_marked`): a bit per entry and a prefix count per word of 32 entries."""

    bits: jax.Array  # [ceil(N / 32)] uint32 bit i of word w: entry 32 w + i is marked
    starts: jax.Array  # [ceil(N / 32)] int32 marked entries before word w
    total: jax.Array  # [] int32 marked entries


def mark(mask: jax.Array) -> Marks:
    """`Marks` of [N] bool `mask`: one pass over the mask and a prefix sum of N / 32
    words. It stands in for a compaction (a prefix sum of N entries and a scatter), which
    costs far more on XLA:CPU (docs/design-history.md): the queue of the persistent lanes
    and `on_marked` look up only the positions they read (`nth_marked`)."""
    n = mask.shape[0]
    words = max(1, -(-n // 32))
    m = jnp.pad(mask.astype(jnp.uint32), (0, words * 32 - n)).reshape(words, 32)
    bits = jnp.sum(m << jnp.arange(32, dtype=jnp.uint32), axis=1, dtype=jnp.uint32)  # distinct bits: a sum is an or
    counts = jax.lax.population_count(bits).astype(jnp.int32)
    ends = cumsum(counts)
    return Marks(bits, ends - counts, ends[-1])


def nth_marked(marks: Marks, pos: jax.Array) -> jax.Array:
    """The index of the `pos`-th marked entry ([...] int32 positions below ``marks.total``):
    [...] int32. Other positions give some index below ``32 * len(marks.bits)``:
    callers mask them. A binary search over the words' prefix counts, then one over the word's bits by
    popcounts of its halves."""
    words = marks.bits.shape[0]
    word = jnp.clip(jnp.searchsorted(marks.starts, pos, side="right", method="scan") - 1, 0, words - 1)
    word = word.astype(jnp.int32)
    bits = marks.bits[word]

    def halve(k, carry):  # the set bit lies in the low or the high `width` bits from `at`
        at, rank = carry
        width = jnp.right_shift(jnp.uint32(16), k.astype(jnp.uint32))
        low = jax.lax.population_count((bits >> at) & ((jnp.uint32(1) << width) - 1))
        skip = rank >= low
        return at + jnp.where(skip, width, jnp.uint32(0)), rank - jnp.where(skip, low, jnp.uint32(0))

    rank = (pos - marks.starts[word]).astype(jnp.uint32)  # the rank-th set bit of the word
    at, _ = jax.lax.fori_loop(0, 5, halve, (jnp.zeros_like(rank), rank))
    return word * 32 + at.astype(jnp.int32)


def compact_indices(mask: jax.Array, size: int, *, fill: int = 0) -> jax.Array:
    """The indices of the True entries of [N] bool `mask`, in order, in an int32 [size]
    array (static `size`); the slots past their count hold `fill`, and indices past `size`
    are dropped. Looked up by position (`nth_marked`) in chunks of `_CHUNK`, as many as
    there are marked entries: the queue of the persistent lanes."""
    marks = mark(mask)
    chunk = min(_CHUNK, max(size, 1))
    padded = size + -size % chunk

    def body(carry):
        k, out = carry
        pos = k * chunk + jnp.arange(chunk, dtype=jnp.int32)
        return k + 1, jax.lax.dynamic_update_slice(out, nth_marked(marks, pos), (k * chunk,))

    more = lambda c: (c[0] * chunk < marks.total) & (c[0] * chunk < size)
    out = jax.lax.while_loop(more, body, (jnp.int32(0), jnp.zeros(padded, jnp.int32)))[1]
    return jnp.where(jnp.arange(size) < marks.total, out[:size], fill)


def on_marked(fn, marked: jax.Array, rows: jax.Array, fill: jax.Array, chunk: int) -> jax.Array:
    """``fn(rows[i])`` where ``marked[i]``, `fill` elsewhere: [N] of `fill`'s dtype.

    `fn` maps [chunk, ...] rows to [chunk] values (a walk down a tree, say). The marked
    rows are found by position (`mark`) and `fn` runs on `chunk` of them at a time inside a `while_loop`
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
    marks = mark(marked)
    count = marks.total

    def body(carry):
        k, out = carry
        pos = k * chunk + jnp.arange(chunk, dtype=jnp.int32)
        live = pos < count
        ids = jnp.where(live, jnp.minimum(nth_marked(marks, pos), n - 1), 0)
        return k + 1, out.at[jnp.where(live, ids, n)].set(fn(rows[ids]), mode="drop")

    out = jnp.full(n, fill)
    return jax.lax.while_loop(lambda c: c[0] * chunk < count, body, (jnp.int32(0), out))[1]
