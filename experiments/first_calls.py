"""First calls on new inputs, with the number of XLA programs each compiles: `jv.voxelize` of
the bunny at 4096^3 (first and second call, then a new mesh, spot, at the same resolution)
and `jv.trace` of 1920x1080 primary rays on the bunny's `compact_dag` at 1024^3 (with and
without prefix sums, then spot's). Run it with a fresh compilation cache folder to see cold
first calls, e.g. ``JAXVOX_CACHE_DIR=$(mktemp -d) python experiments/first_calls.py``.

Prints one line per call: seconds (with `jax.block_until_ready`) and programs compiled
(`jax.monitoring`'s backend-compile events).
"""

from __future__ import annotations

import time

import _common
import jax
import jax.numpy as jnp

import jaxvox as jv

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


def main() -> None:
    jv.enable_compilation_cache()
    compiled: list[float] = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: compiled.append(secs) if name == COMPILE_EVENT else None
    )

    def run(label, call):
        before, start = len(compiled), time.perf_counter()
        result = jax.block_until_ready(call())
        print(f"{label}: {time.perf_counter() - start:.2f} s, {len(compiled) - before} programs compiled", flush=True)
        return result

    bunny, spot = (jv.load_mesh(_common.MESH_DIR / f"{name}.obj") for name in ("stanford-bunny", "spot"))
    grid = jv.Grid.fit(bunny, 4096)
    run("voxelize bunny 4096^3, first call", lambda: jv.voxelize(bunny, grid, progress=False))
    run("voxelize bunny 4096^3, second call", lambda: jv.voxelize(bunny, grid, progress=False))
    run("voxelize spot 4096^3 (a new mesh)", lambda: jv.voxelize(spot, jv.Grid.fit(spot, 4096), progress=False))
    eye, target = jv.look_at_view(bunny)
    o, d = (jnp.reshape(x, (-1, 3)) for x in jv.pinhole_rays(eye, target, width=1920, height=1080))
    dag = jv.build_dag(jv.voxelize(bunny, jv.Grid.fit(bunny, 1024)))
    for prefix in (True, False):
        sparse = jv.compact_dag(dag, prefix=prefix)
        run(f"trace compact_dag(prefix={prefix}), bunny 1024^3, first call", lambda: jv.trace(sparse, o, d))
        run(f"trace compact_dag(prefix={prefix}), bunny 1024^3, second call", lambda: jv.trace(sparse, o, d))
    other = jv.compact_dag(jv.build_dag(jv.voxelize(spot, jv.Grid.fit(spot, 1024))), prefix=False)
    run("trace compact_dag(prefix=False), spot 1024^3 (a new mesh)", lambda: jv.trace(other, o, d))


if __name__ == "__main__":
    main()
