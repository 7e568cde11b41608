"""Batch loops whose slow rows are gathered into smaller batches as the others finish.

A loop over a batch of rays (sphere tracing, octree rounds) runs until its slowest ray
ends, and every iteration costs the whole batch: under `jax.vmap` a `while_loop` steps
every lane until the last one stops. Most rays end early and a few (grazing ones) take
many times longer. `run_in_stages` runs the loop on the whole batch until at most 1/`SHRINK`
of the rows are still running, gathers those into a batch `SHRINK` times smaller, and
so on down to `MIN_BATCH` rows, where the loop runs to the end. Each stage has a static
size, so the whole is one program; rows are independent, so no result changes except by
float32 rounding where XLA fuses the smaller programs differently.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from jaxvox._core.hit import RUNNING
from jaxvox._core.scan import compact_indices

SHRINK = 8  # each stage's batch is this many times smaller than the last
MIN_BATCH = 1024  # no stage below this many rows (a smaller stage costs more than it saves)


def batch_sizes(n: int, min_batch: int = MIN_BATCH) -> list[int]:
    """Static batch sizes of the stages: n, n // SHRINK, ... (none below `min_batch`)."""
    sizes = [n]
    while sizes[-1] // SHRINK >= min_batch:
        sizes.append(sizes[-1] // SHRINK)
    return sizes


def run_in_stages(body: Callable[[Any, Any], Any], inputs, state: Any, *, idle: int, min_batch: int = MIN_BATCH) -> Any:
    """Iterates ``state = body(inputs, state)`` until no row's ``state.status`` is `RUNNING`.

    Args:
      body: one iteration over a batch: ``(inputs, state) -> state``, rows independent;
        it must leave rows that are not running as they are.
      inputs: pytree of per-row arrays [n, ...] the body reads (gathered with the state).
      state: a NamedTuple of per-row arrays [n, ...] with an int32 ``status`` field.
      idle: a status other than `RUNNING`, given to the padding rows of a gathered batch.
      min_batch: the smallest stage (static).

    Returns:
      The final state [n, ...].
    """
    n = state.status.shape[0]
    sizes = batch_sizes(n, min_batch)

    def loop(rows, s, until: int):
        running = lambda s: jnp.sum(s.status == RUNNING) > until
        return jax.lax.while_loop(running, lambda s: body(rows, s), s)

    state = loop(inputs, state, sizes[1] if len(sizes) > 1 else 0)
    for k, size in enumerate(sizes[1:], 1):
        # The running rows (at most `size`); the padding rows repeat the last row, idle.
        ids = compact_indices(state.status == RUNNING, size, fill=n)
        take = lambda x: x[jnp.minimum(ids, n - 1)]
        part = jax.tree.map(take, state)
        part = part._replace(status=jnp.where(ids < n, part.status, idle).astype(part.status.dtype))
        part = loop(jax.tree.map(take, inputs), part, sizes[k + 1] if k + 1 < len(sizes) else 0)
        state = jax.tree.map(lambda x, y: x.at[ids].set(y, mode="drop"), state, part)
    return state
