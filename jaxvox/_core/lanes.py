"""The one scheduler of jaxvox's per-ray loops: persistent lanes fed from a queue.

A loop over a batch of rays (octree traversal, sphere tracing, leaf marches) runs until
its slowest ray ends, and under `jax.vmap` a `while_loop` steps every lane until the
last one stops; most rays end early and a few (grazing ones) take many times longer.
`run_in_lanes` keeps a fixed number of lanes busy instead: the rows that need work
wait in a queue (in row order), each round of the loop runs `steps_per_refill` steps on
all lanes, and the lanes whose rows ended are refilled from the queue once enough of
them have (refilling costs about two steps). A row's result is written when it ends,
so the lanes' state never has the batch's size. The lane count is static: the whole is
one program, and rows are independent, so results do not depend on it except by
float32 rounding where XLA fuses a program of another size differently.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxvox._core.hit import RUNNING, STEP_CAP
from jaxvox._core.scan import compact_indices


def run_in_lanes(
    init: Callable[[Any, jax.Array], tuple[Any, Any]],
    step: Callable[[Any, Any], Any],
    finish: Callable[[Any, Any], Any],
    rows: Any,
    status: jax.Array,
    out: Any,
    *,
    lanes: int,
    idle: int,
    max_steps: int | None = None,
    steps_per_refill: int = 8,
) -> Any:
    """Runs every row whose `status` is `RUNNING` to its end on `lanes` persistent lanes.

    Args:
      init: ``(rows [W], status [W]) -> (inputs [W], state [W])``, for the rows given:
        the inputs the lanes' steps read (the rows, or values derived from them once per
        row) and the lanes' state (a pytree of arrays with an int32 ``status`` field;
        lanes without a row get the status `idle`).
      step: ``(inputs [W], state [W]) -> state [W]``, one step of every lane; it must
        leave lanes that are not `RUNNING` as they are (their result is read later).
      finish: ``(inputs [W], state [W]) -> results [W, ...]``, a lane's result (a
        pytree like `out`).
      rows: pytree of per-row arrays [n, ...] (what `init` reads).
      status: [n] int32; the `RUNNING` rows are queued, the others keep `out`.
      out: pytree of arrays [n, ...], the results of rows that never run.
      lanes: static lane count (at most n is used).
      idle: static status other than `RUNNING` for lanes without a row.
      max_steps: static cap on a row's steps, counted here (the row then ends with
        `STEP_CAP`); None where `step` ends rows itself.
      steps_per_refill: static steps per round of the loop.

    Returns:
      `out` with every queued row's result ``finish(inputs, state)`` at its end.
    """
    n = status.shape[0]
    width = max(min(lanes, n), 1)
    running = status == RUNNING
    queue = compact_indices(running, n)  # the rows to run, in order
    queued = jnp.sum(running)
    queue_row = lambda pos: queue[jnp.clip(pos, 0, n - 1)]
    take = lambda ids: jax.tree.map(lambda a: a[ids], (rows, status))

    def fetch(ids, valid):
        row, st = take(jnp.where(valid, ids, 0))
        return init(row, jnp.where(valid, st, idle))

    class Carry(NamedTuple):
        ids: jax.Array  # [W] int32 row of each lane, n when idle
        row: Any  # [W] the lanes' inputs (from `init`)
        state: Any  # [W]
        steps: jax.Array  # [W] int32
        next: jax.Array  # [] int32 queue position of the next row
        out: Any  # [n, ...]

    # The lanes start idle and the loop's first refill fills them: `init` appears once in
    # the program (`eval_shape` only reads its output's shapes).
    empty = jnp.full(width, n, jnp.int32)
    row0, state0 = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(fetch, empty, empty < 0))
    state0 = state0._replace(status=jnp.full(width, idle, state0.status.dtype))
    carry = Carry(empty, row0, state0, jnp.zeros(width, jnp.int32), jnp.int32(0), out)

    def body(c: Carry) -> Carry:
        # a loop, not unrolled: XLA would fuse consecutive steps and recompute each one
        state = jax.lax.fori_loop(0, steps_per_refill, lambda _, s: step(c.row, s), c.state)
        steps = c.steps + steps_per_refill
        if max_steps is not None:
            capped = (state.status == RUNNING) & (steps >= max_steps)
            state = state._replace(status=jnp.where(capped, STEP_CAP, state.status).astype(state.status.dtype))
        free = state.status != RUNNING  # the lanes whose row ended, and idle ones
        # Refilling waits until an eighth of the lanes are free (ended rows keep their
        # state meanwhile) or the queue is empty.
        refill_now = (jnp.sum(free) * 8 >= width) | (c.next >= queued)
        return jax.lax.cond(refill_now, refill, lambda c, s, t, _: c._replace(state=s, steps=t), c, state, steps, free)

    def refill(c: Carry, state, steps, free) -> Carry:
        slot = jnp.where(free, c.ids, n)  # idle lanes have no row: n, dropped
        out = jax.tree.map(lambda o, r: o.at[slot].set(r, mode="drop"), c.out, finish(c.row, state))
        pos = c.next + jnp.cumsum(free) - 1
        fresh = free & (pos < queued)
        new_ids = queue_row(pos)
        new_row, new_state = fetch(new_ids, fresh)
        swap = lambda a, b: jnp.where(jnp.reshape(free, free.shape + (1,) * (a.ndim - 1)), a, b)
        return Carry(
            jnp.where(fresh, new_ids, jnp.where(free, n, c.ids)),
            jax.tree.map(swap, new_row, c.row),
            jax.tree.map(swap, new_state, state),
            jnp.where(free, 0, steps),
            c.next + jnp.sum(free),
            out,
        )

    if n == 0:
        return out
    more = lambda c: jnp.any(c.ids < n) | (c.next < queued)
    return jax.lax.while_loop(more, body, carry).out


def run_states_in_lanes(
    step: Callable[[Any, Any], Any], rows: Any, start: Any, *, lanes: int, idle: int, steps_per_refill: int = 8
) -> Any:
    """`run_in_lanes` for a loop whose rows' start states are all known: ``step(rows [W],
    state [W]) -> state [W]`` (it ends rows itself and leaves the ended ones as they are)
    runs from `start` (a pytree of [n] arrays with a ``status`` field) until no row is
    `RUNNING`; returns the final states [n]."""
    return run_in_lanes(
        lambda r, status: (r, r[1]._replace(status=status)),
        lambda r, s: step(r[0], s),
        lambda r, s: s,
        (rows, start),
        start.status,
        start,
        lanes=lanes,
        idle=idle,
        steps_per_refill=steps_per_refill,
    )
