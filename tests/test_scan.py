"""`jaxvox._core.scan`: `cumsum` against numpy's prefix sums, `mark`, `nth_marked` and
`compact_indices` against numpy's `flatnonzero`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvox._core.scan import cumsum


@pytest.mark.parametrize("n", [0, 1, 257, 100_003, 256 * 4096 + 3])
def test_cumsum_matches_numpy(n):
    rng = np.random.default_rng(n)
    flags = rng.random(n) < 0.3
    counts = rng.integers(-5, 6, n).astype(np.int32)
    run = jax.jit(cumsum)
    np.testing.assert_array_equal(np.asarray(run(flags)), np.cumsum(flags))
    np.testing.assert_array_equal(np.asarray(run(counts)), np.cumsum(counts))
    assert run(flags).dtype == np.int32


@pytest.mark.parametrize("n", [1, 3000, 40_000])
def test_compact_indices_matches_numpy(n):
    """The marked indices in order, `fill` past their count, cut at `size` (the lanes'
    queue)."""
    from jaxvox._core.scan import compact_indices

    mask = np.random.default_rng(n).random(n) < 0.3
    for size in (n, n + 7, max(1, n // 8)):
        for fill in (0, n):
            expected = np.full(size, fill, np.int32)
            marked = np.flatnonzero(mask)[:size]
            expected[: len(marked)] = marked
            got = jax.jit(compact_indices, static_argnums=1, static_argnames="fill")(mask, size, fill=fill)
            np.testing.assert_array_equal(np.asarray(got), expected)


@pytest.mark.parametrize("n", [33, 70_001])
def test_nth_marked_finds_every_marked_entry(n):
    """Word edges (entries 31, 32, 33), runs of empty words, no marks and all marks."""
    from jaxvox._core.scan import mark, nth_marked

    rng = np.random.default_rng(n)
    find = jax.jit(lambda mask: nth_marked(mark(mask), jnp.arange(n, dtype=jnp.int32)))
    count = jax.jit(lambda mask: mark(mask).total)
    for density in (0.0, 0.003, 0.5, 1.0):
        mask = rng.random(n) < density
        expected = np.flatnonzero(mask)
        assert int(count(mask)) == len(expected)
        np.testing.assert_array_equal(np.asarray(find(mask))[: len(expected)], expected)
