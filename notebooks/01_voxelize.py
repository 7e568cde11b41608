# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # 01 · Voxelizing triangle meshes
#
# Load a shared mesh, voxelize it conservatively and 6-separating, look at the voxels,
# compare the two sets, and time a resolution sweep. Set the environment variable
# `SMOKE=1` to run everything at a small size (the test suite does).

# %%
import os
import pathlib
import time

import matplotlib.pyplot as plt
import numpy as np

import jaxvox as jv
from jaxvox.plot import projection_image

jv.enable_compilation_cache()  # compiled programs persist across sessions (~/.cache/jaxvox/xla)

SMOKE = os.environ.get("SMOKE", "0") == "1"
MESHES = pathlib.Path(os.environ.get("JAXVOX_MESHES", "../../shared/meshes"))  # from notebooks/
RESOLUTION = 32 if SMOKE else 128
SWEEP = [RESOLUTION] if SMOKE else [64, 128, 256, 512]  # smoke: the programs compiled above

path = MESHES / "spot.obj"
mesh = jv.load_mesh(path) if path.exists() else jv.default_scene()
grid = jv.Grid.fit(mesh, resolution=RESOLUTION)
print(f"{mesh.num_faces} triangles, grid {RESOLUTION}^3, voxel size {float(grid.voxel_size):.4g}")

# %%
cons = jv.voxelize(mesh, grid, mode="conservative").to_numpy()
sep6 = jv.voxelize(mesh, grid, mode="6-separating").to_numpy()
print(f"conservative: {len(cons):,} voxels; 6-separating: {len(sep6):,} voxels "
      f"({100 * len(sep6) / len(cons):.1f}% of conservative)")

# The 6-separating set is a subset of the conservative one.
key = lambda a: set(map(tuple, a))
only_cons = np.array(sorted(key(cons) - key(sep6))).reshape(-1, 3)
assert key(sep6) <= key(cons)

# %% [markdown]
# ## The voxels
# A 3D scatter of voxel centres (conservative in grey, the voxels only conservative mode
# sets in orange) and a depth-shaded projection of each set.

# %%
fig = plt.figure(figsize=(12, 4))
ax = fig.add_subplot(1, 3, 1, projection="3d")
ax.scatter(*sep6.T, s=1, c="0.5", alpha=0.3)
ax.scatter(*only_cons.T, s=1, c="tab:orange", alpha=0.3)
ax.set_title("6-separating (grey) + conservative-only (orange)")
for i, (name, ijk) in enumerate([("conservative", cons), ("6-separating", sep6)]):
    ax2 = fig.add_subplot(1, 3, 2 + i)
    ax2.imshow(projection_image(ijk, RESOLUTION, axis=0, size=RESOLUTION), cmap="gray")
    ax2.set_title(f"{name}: view along x")
    ax2.axis("off")
plt.tight_layout()
plt.show()

# %% [markdown]
# ## Resolution sweep
# Median of three timed calls after a warm-up call (which includes compilation).

# %%
rows = []
for r in SWEEP:
    g = jv.Grid.fit(mesh, resolution=r)
    for mode in ("conservative", "6-separating"):
        jv.voxelize(mesh, g, mode=mode)  # compile
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            vox = jv.voxelize(mesh, g, mode=mode)
            vox.coords.block_until_ready()
            times.append(time.perf_counter() - t0)
        rows.append((r, mode, int(vox.count), float(np.median(times))))
        print(f"{r:5d} {mode:13s} {rows[-1][2]:>10,d} voxels {rows[-1][3]:.3f} s")

fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
for mode in ("conservative", "6-separating"):
    rr = [x for x in rows if x[1] == mode]
    ax[0].loglog([x[0] for x in rr], [x[3] for x in rr], "o-", label=mode)
    ax[1].loglog([x[0] for x in rr], [x[2] for x in rr], "o-", label=mode)
ax[0].set(xlabel="resolution", ylabel="seconds", title="time")
ax[1].set(xlabel="resolution", ylabel="voxels", title="voxel count (~R^2: surface)")
ax[0].legend()
plt.tight_layout()
plt.show()
