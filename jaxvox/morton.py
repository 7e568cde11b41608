"""Morton (Z-order) codes as two 30-bit words, without 64-bit integers.

A voxel ``(i, j, k)`` with ``0 <= i, j, k < 2^20`` has the 60-bit Morton code
``sum_b i_b << 3b | j_b << (3b+1) | k_b << (3b+2)`` (x is the lowest bit of each
triple). It is carried as two uint32 words, ``hi = code >> 30`` and
``lo = code & (2^30 - 1)``: the lexicographic order of ``(hi, lo)`` is Morton order,
so sorts use `jax.lax.sort` on two operands and no 64-bit integer type is needed.
For grids up to 1024^3 ``hi`` is zero and one word suffices.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

WORD_BITS = 10  # bits of each axis per word
WORD_MASK = (1 << WORD_BITS) - 1
EMPTY = np.uint32(0xFFFFFFFF)  # a key no voxel has (bit 31 set); padding sorts last


def _spread10(x):
    """Spreads the low 10 bits of uint32 `x` to every third bit (bit b -> bit 3b)."""
    x = x & 0x3FF
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    x = (x | (x << 2)) & 0x09249249
    return x


def _compact10(x):
    """Inverse of `_spread10`: gathers every third bit of uint32 `x` into the low 10 bits (jax or numpy)."""
    x = x & 0x09249249
    x = (x | (x >> 2)) & 0x030C30C3
    x = (x | (x >> 4)) & 0x0300F00F
    x = (x | (x >> 8)) & 0x030000FF
    x = (x | (x >> 16)) & 0x3FF
    return x


def encode_word(ijk: jax.Array) -> jax.Array:
    """Interleaves the low 10 bits of each axis: int [..., 3] -> uint32 [...] (< 2^30)."""
    u = jnp.asarray(ijk).astype(jnp.uint32)
    return _spread10(u[..., 0]) | (_spread10(u[..., 1]) << 1) | (_spread10(u[..., 2]) << 2)


# Host tables: `_SPREAD[v]` is `_spread10(v)` for 10-bit v; `_GATHER_LO[v]` / `_GATHER_HI[v]`
# hold the (x, y, z) bits of a word's low / high 15 bits (5 bits per axis) in the 10-bit
# fields x | y << 10 | z << 20 of an int32. A table lookup replaces about a dozen
# whole-array operations per axis in numpy.
_SPREAD = _spread10(np.arange(1 << WORD_BITS, dtype=np.uint32))
_FIFTEEN = np.arange(1 << 15, dtype=np.uint32)
_GATHER_LO = (_compact10(_FIFTEEN) | _compact10(_FIFTEEN >> 1) << 10 | _compact10(_FIFTEEN >> 2) << 20).astype(np.int32)
_GATHER_HI = _GATHER_LO << 5
# `_SPREAD16[v]`: the 16 bits of v spread to every third bit (uint64), for `encode_axes_host`.
_SPREAD16 = (_SPREAD[np.arange(1 << 16) & WORD_MASK].astype(np.uint64)) | (
    _SPREAD[np.arange(1 << 16) >> WORD_BITS].astype(np.uint64) << np.uint64(3 * WORD_BITS)
)
_ENCODE_BLOCK = 1 << 14  # rows per block of `encode_axes_host`


def encode_word_host(ijk: np.ndarray) -> np.ndarray:
    """`encode_word` in numpy, for host-side ordering (compiles nothing): [..., 3] -> uint32 [...]."""
    u = np.asarray(ijk)
    axis = lambda a: _SPREAD[u[..., a] & WORD_MASK]
    return axis(0) | (axis(1) << 1) | (axis(2) << 2)


def curve_order_host(points: np.ndarray) -> np.ndarray:
    """Indices sorting points [n, 3] (host floats) along a 10-bit-per-axis Morton curve of
    their bounding box, stably: the order of the triangle trees (winding numbers, point
    queries). Non-finite coordinates take some cell of the box."""
    lo, hi = points.min(0), points.max(0)
    q = np.nan_to_num((points - lo) / np.maximum(hi - lo, 1e-30) * WORD_MASK)  # in [0, 1023] where finite
    return stable_order_host(encode_word_host(np.clip(q, 0, WORD_MASK).astype(np.intp)))


def encode_host(ijk: np.ndarray) -> np.ndarray:
    """The whole Morton code in numpy (compiles nothing): int [..., 3] (< 2^20) -> uint64 [...]."""
    u = np.asarray(ijk)
    if u.size and u.min() >= 0 and u.max() < len(_SPREAD16):  # (two passes over the rows as they lie)
        return _encode16(u[..., 0], u[..., 1], u[..., 2])
    return encode_axes_host(u[..., 0], u[..., 1], u[..., 2])


def encode_axes_host(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
    """`encode_host` of the axes given as separate int arrays (< 2^20, broadcast): uint64."""
    i, j, k = np.broadcast_arrays(i, j, k)
    if i.size and min(a.min() for a in (i, j, k)) >= 0 and max(a.max() for a in (i, j, k)) < len(_SPREAD16):
        return _encode16(i, j, k)
    word = lambda shift, mask: (
        _SPREAD[(i >> shift) & mask] | (_SPREAD[(j >> shift) & mask] << 1) | (_SPREAD[(k >> shift) & mask] << 2)
    ).astype(np.uint64)
    return (word(WORD_BITS, WORD_MASK) << np.uint64(3 * WORD_BITS)) | word(0, WORD_MASK)


def stable_order_host(keys: np.ndarray) -> np.ndarray:
    """``np.argsort(keys, kind="stable")`` of integer keys [n] (host): int64 [n]. Where
    the keys are non-negative and fit beside their index in 63 bits, one sort of
    ``key << bits | index``, several times faster (numpy's sort of plain integers is
    vectorized, its stable argsort is not)."""
    keys = np.asarray(keys)
    bits = max(len(keys) - 1, 1).bit_length()
    if len(keys) and keys.dtype.kind in "iu" and keys.min() >= 0 and int(keys.max()) < (1 << (63 - bits)):
        packed = keys.astype(np.int64) << bits | np.arange(len(keys))
        packed.sort()
        return packed & ((1 << bits) - 1)
    return np.argsort(keys, kind="stable")


def run_starts(values: np.ndarray) -> np.ndarray:
    """First index of each run of equal entries of a sorted 1-D array (codes, keys):
    int64 [runs], empty for an empty array."""
    if not len(values):
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.concatenate([[True], values[1:] != values[:-1]]))


def box_cells(ids: np.ndarray, first: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every cell of every box, ordered by the cell's Morton code, then by box (host).

    Args:
      ids: [n] int the boxes' ids, ascending; first, last: [n, 3] int each box's first
        and last cell (inclusive, < 2^20, last >= first).

    Returns:
      (id [m] int64 the box, code [m] uint64 `encode_host` of the cell) over all boxes'
      cells, ordered by code, then by id.
    """
    per_axis = last - first + 1
    counts = per_axis.prod(1)
    # Each item's cell, one axis at a time (1-D arrays: the [m, 3] ones cost more in fresh
    # memory than in arithmetic), in int32 where a box's cells allow it (numpy divides
    # int32 a few times faster than int64).
    index = np.int32 if counts.max(initial=0) < (1 << 31) else np.int64
    rank = (np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)).astype(index)
    along = lambda k: np.repeat(per_axis[:, k].astype(index), counts)
    rank, k_axis = np.divmod(rank, along(2))
    i_axis, j_axis = np.divmod(rank, along(1))
    offsets = (i_axis, j_axis, k_axis)
    cell = [np.repeat(first[:, k].astype(np.int32), counts) + offsets[k] for k in range(3)]
    small = len(first) and first.min() >= 0 and last.max() < len(_SPREAD16)  # (the boxes bound their cells)
    code = _encode16(*cell) if small else encode_axes_host(*cell)
    ids = np.asarray(ids, np.int64)
    if len(code) and code.max() < (1 << 16):  # (small grids) numpy's stable sort of 16-bit keys is a radix sort
        order = np.argsort(code.astype(np.uint16), kind="stable")
        return np.repeat(ids, counts)[order], code[order]
    if len(code) and last.max() < (1 << WORD_BITS) and ids.max() < (1 << 32):
        # One sort of packed keys, code high, id low: written and read as uint32 halves
        # (little-endian), fewer passes than shifts and masks.
        key = np.empty(len(code), np.uint64)
        halves = key.view(np.uint32).reshape(-1, 2)
        halves[:, 0] = np.repeat(ids.astype(np.uint32), counts)
        halves[:, 1] = code
        key.sort()
        return halves[:, 0].astype(np.int64), halves[:, 1].astype(np.uint64)
    order = np.argsort(code, kind="stable")
    return np.repeat(ids, counts)[order], code[order]


def _encode16(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
    """`encode_axes_host` of axes of one shape with values in [0, 2^16): one table lookup
    per axis, block by block so that the temporaries stay in the cache (several times
    faster than whole-array passes)."""
    shape, (i, j, k) = i.shape, (a.reshape(-1) for a in (i, j, k))
    out, part = np.empty(i.shape, np.uint64), np.empty(min(_ENCODE_BLOCK, i.size), np.uint64)
    for s in range(0, i.size, _ENCODE_BLOCK):
        rows = slice(s, s + _ENCODE_BLOCK)
        code, spread = out[rows], part[: len(out[rows])]
        np.take(_SPREAD16, i[rows], out=code)
        for shift, axis in ((1, j), (2, k)):
            np.take(_SPREAD16, axis[rows], out=spread)
            spread <<= np.uint64(shift)
            code |= spread
    return out.reshape(shape)


def decode_host(code: np.ndarray) -> np.ndarray:
    """Inverse of `encode_host`: uint64 [...] (< 2^60) -> int32 [..., 3]."""
    c = np.asarray(code, np.uint64)
    high = decode_word_host(c >> np.uint64(3 * WORD_BITS))
    return (high << WORD_BITS) | decode_word_host(c & np.uint64((1 << (3 * WORD_BITS)) - 1))


def decode_word(word: jax.Array) -> jax.Array:
    """Inverse of `encode_word`: uint32 [...] -> int32 [..., 3] with values < 1024."""
    w = jnp.asarray(word, jnp.uint32)
    return jnp.stack([_compact10(w), _compact10(w >> 1), _compact10(w >> 2)], axis=-1).astype(jnp.int32)


def decode_word_host(word: np.ndarray, out: np.ndarray | None = None, high: np.ndarray | None = None) -> np.ndarray:
    """`decode_word` in numpy (compiles nothing): int [...] (< 2^30) -> int32 [..., 3],
    written to `out` when given, with `high` (int32 [3], bits above the word's 10 per
    axis, e.g. a region's corner) OR'ed into every row when given.

    Block by block (`_ENCODE_BLOCK` words), so that the lookups' temporaries stay in the
    cache: about twice as fast as whole-array passes on millions of words."""
    w = np.asarray(word).astype(np.uint32, copy=False)
    if out is not None and not out.flags.c_contiguous:  # (a view that a reshape would copy)
        out[...] = decode_word_host(w, high=high)
        return out
    out = np.empty(w.shape + (3,), np.int32) if out is None else out
    words, rows = w.reshape(-1), out.reshape(-1, 3)
    size = min(_ENCODE_BLOCK, words.size)
    index, fields, part = np.empty(size, np.uint32), np.empty(size, np.int32), np.empty(size, np.int32)
    for s in range(0, words.size, _ENCODE_BLOCK):
        block, xyz = words[s : s + _ENCODE_BLOCK], rows[s : s + _ENCODE_BLOCK]
        n = len(block)
        np.take(_GATHER_LO, np.bitwise_and(block, 0x7FFF, out=index[:n]), out=fields[:n])
        np.take(_GATHER_HI, np.right_shift(block, 15, out=index[:n]), out=part[:n])
        fields[:n] |= part[:n]
        np.bitwise_and(fields[:n], WORD_MASK, out=xyz[:, 0])
        np.bitwise_and(np.right_shift(fields[:n], WORD_BITS, out=part[:n]), WORD_MASK, out=xyz[:, 1])
        np.right_shift(fields[:n], 2 * WORD_BITS, out=xyz[:, 2])
        if high is not None:
            xyz |= high
    return out


def encode(ijk: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Morton code of voxel indices as ``(hi, lo)`` words.

    Args:
      ijk: [..., 3] int voxel indices, each in ``[0, 2^20)``.

    Returns:
      ``(hi, lo)``, two uint32 [...] arrays: the code's bits 30..59 and 0..29.
    """
    u = jnp.asarray(ijk).astype(jnp.uint32)
    return encode_word(u >> WORD_BITS), encode_word(u & WORD_MASK)


def decode(hi: jax.Array, lo: jax.Array) -> jax.Array:
    """Inverse of `encode`: ``(hi, lo)`` uint32 words -> int32 [..., 3] voxel indices."""
    return (decode_word(hi) << WORD_BITS) | decode_word(lo)
