# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # 03 · Tracing rays through octrees and DAGs
#
# Build a shared mesh's DAG, trace a depth image and a normal image with `jv.trace`,
# check a few rays against a brute-force slab test of every voxel (float64 numpy), compare
# the two traversals (ESVO-style PUSH/ADVANCE/POP and the talk's save-state-and-go-down
# stack loop) and the dense DDA, and plot Mrays/s against resolution. `SMOKE=1` runs
# everything at a small size.

# %%
import os
import pathlib
import time

import jax
import matplotlib.pyplot as plt
import numpy as np

import jaxvox as jv
from jaxvox.plot import hit_image

jv.enable_compilation_cache()  # compiled programs persist across sessions (~/.cache/jaxvox/xla)

SMOKE = os.environ.get("SMOKE", "0") == "1"
MESHES = pathlib.Path(os.environ.get("JAXVOX_MESHES", "../../shared/meshes"))  # from notebooks/
RESOLUTION = 32 if SMOKE else 1024  # the smoke run's speed point below reuses this tree's programs
WIDTH, HEIGHT = (64, 48) if SMOKE else (960, 720)

path = MESHES / "stanford-bunny.obj"
mesh = jv.load_mesh(path) if path.exists() else jv.default_scene()
grid = jv.Grid.fit(mesh, resolution=RESOLUTION)
dag = jv.build_dag(jv.voxelize(mesh, grid))
print(f"{int(dag.voxel_count):,} voxels, DAG of {dag.num_nodes:,} nodes ({dag.compact_nbytes / 2**20:.1f} MiB)")

# %% [markdown]
# ## A depth image and a normal image
# `pinhole_rays` gives one ray per pixel; `trace` returns a `Hit` with the entry distance
# `t`, the voxel, the normal of the face the ray entered, the voxel's Morton index (for
# attribute arrays) and a status per ray.

# %%
eye, target = jv.look_at_view(mesh)
origins, directions = jv.pinhole_rays(eye, target, width=WIDTH, height=HEIGHT)
hit = jax.block_until_ready(jv.trace(dag, origins, directions))
fig, axes = plt.subplots(1, 2, figsize=(10, 4))
axes[0].imshow(hit_image(hit, "depth"))
axes[0].set_title("depth")
axes[1].imshow(hit_image(hit, "normal"))
axes[1].set_title("entry-face normal")
for ax in axes:
    ax.axis("off")
plt.show()
print({name: int((np.asarray(hit.status) == code).sum()) for name, code in
       (("hit", jv.HIT), ("miss", jv.MISS), ("step cap", jv.STEP_CAP), ("invalid", jv.INVALID))})

# %% [markdown]
# ## Against a brute-force reference
# A float64 slab test of each ray against every voxel box: the first voxel the ray passes
# through. The traversal must find the same `t`, and the same voxel unless two tie.

# %%
ijk = np.asarray(jv.expand(dag).to_numpy(), np.float64)
h = float(grid.voxel_size)
o_grid = (np.asarray(origins).reshape(-1, 3) - np.asarray(grid.origin)) / h
d_grid = np.asarray(directions).reshape(-1, 3) / h
picks = np.random.default_rng(0).choice(len(o_grid), 12, replace=False)
for i in picks:
    with np.errstate(divide="ignore"):
        inv = 1.0 / d_grid[i]
    ta, tb = (ijk - o_grid[i]) * inv, (ijk + 1 - o_grid[i]) * inv
    t_in, t_out = np.minimum(ta, tb).max(1), np.maximum(ta, tb).min(1)
    ok = (t_in < t_out) & (t_out > 0)
    t_ref = np.maximum(t_in[ok], 0).min() if ok.any() else np.inf
    t_got = float(np.asarray(hit.t).reshape(-1)[i])
    print(f"ray {i:6d}: brute force t = {t_ref:9.5f}, trace t = {t_got:9.5f}")
    assert (np.isinf(t_ref) and np.isinf(t_got)) or abs(t_ref - t_got) < 1e-3 * max(1, t_ref)

# %% [markdown]
# ## Two traversals, one answer
# Both octree traversals and the dense DDA give identical hits. ESVO pops any number of
# levels in one step (the highest changed bit of the cell corner names the ancestor) and
# keeps only node rows on its stack, so it needs fewer steps than the stack loop, which
# pops one level per step.

# %%
stack = jv.trace(dag, origins, directions, method="stack")
print("esvo == stack:", all(np.array_equal(np.asarray(a), np.asarray(b))
                            for a, b in zip(jax.tree.leaves(hit), jax.tree.leaves(stack))))
if RESOLUTION <= 256:
    occupancy = np.zeros((RESOLUTION,) * 3, bool)
    occupancy[tuple(ijk.astype(int).T)] = True
    dense = jv.trace_dense(occupancy, grid, origins, directions)
    print("esvo == dense DDA:", np.array_equal(np.asarray(dense.voxel), np.asarray(hit.voxel)))

# %% [markdown]
# ## Speed against resolution
# Mrays/s of primary rays (median of three calls after a compiling one). The benchmark
# script `experiments/bench_trace.py` does this at 1920x1080 against Embree.

# %%
rates = {}
for R in ([RESOLUTION] if SMOKE else [256, 512, 1024, 2048]):
    tree = jv.build_dag(jv.voxelize(mesh, jv.Grid.fit(mesh, resolution=R)))
    for method in jv.TRACE_METHODS:
        jax.block_until_ready(jv.trace(tree, origins, directions, method=method))
        times = []
        for _ in range(3):
            start = time.perf_counter()
            jax.block_until_ready(jv.trace(tree, origins, directions, method=method))
            times.append(time.perf_counter() - start)
        rates.setdefault(method, []).append((R, WIDTH * HEIGHT / np.median(times) / 1e6))
for method, points in rates.items():
    plt.plot(*zip(*points), "o-", label=method)
plt.xscale("log", base=2)
plt.xlabel("resolution R")
plt.ylabel("Mrays/s")
plt.legend()
plt.title(f"{WIDTH}x{HEIGHT} primary rays, DAG")
plt.show()
print(rates)
