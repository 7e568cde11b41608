"""`jaxvox._core.scan.cumsum` against numpy's prefix sums."""

from __future__ import annotations

import jax
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
