"""The ground floor: what every other part of jaxvox shares, importing nothing above it.

* `checks`: input validation in one message style (`refuse`, `check_int`, ...);
* `errors`: `JaxvoxError`;
* `shapes`: the ladder of bucketed sizes every compiled program is shaped by;
* `pytree`: the pytree dataclass decorator of the result types;
* `geometry`: kernels used by several modules (point-triangle distance, solid angle,
  safe norms);
* `scan`: prefix sums and the compaction of marked rows (`cumsum`, `on_marked`);
* `lanes`: the scheduler of the per-ray loops (persistent lanes fed from a queue);
* `hit`: the `Hit` record every tracer returns and its statuses;
* `buffers`: page-aligned and reserved host buffers, row joins, progress bars;
* `devices`: work split over the JAX devices and tables shared by all of them;
* `compilation_cache`: `enable_compilation_cache`.

Private: the public names are re-exported from `jaxvox`. `tests/test_imports.py` checks
that no module here imports anything of jaxvox outside `jaxvox._core`.
"""
