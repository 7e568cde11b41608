# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # 02 · Sparse voxel octrees and DAGs
#
# Voxelize a shared mesh, build its sparse voxel octree (SVO) and DAG, compare node
# counts per level and the memory of several layouts, and look voxel attributes up
# through the per-node prefix sums. `SMOKE=1` runs everything at a small size.

# %%
import os
import pathlib

import matplotlib.pyplot as plt
import numpy as np

import jaxvox as jv

jv.enable_compilation_cache()  # compiled programs persist across sessions (~/.cache/jaxvox/xla)

SMOKE = os.environ.get("SMOKE", "0") == "1"
MESHES = pathlib.Path(os.environ.get("JAXVOX_MESHES", "../../shared/meshes"))  # from notebooks/
RESOLUTION = 64 if SMOKE else 1024

path = MESHES / "stanford-bunny.obj"
mesh = jv.load_mesh(path) if path.exists() else jv.default_scene()
grid = jv.Grid.fit(mesh, resolution=RESOLUTION)
vox = jv.voxelize(mesh, grid, triangle_ids=True)
svo = jv.build_octree(vox)
dag = jv.build_dag(vox)
print(f"{int(vox.count):,} voxels at {RESOLUTION}^3")
print(f"SVO: {svo.num_nodes:,} nodes, {svo.compact_nbytes / 2**20:.2f} MiB")
print(f"DAG: {dag.num_nodes:,} nodes, {dag.compact_nbytes / 2**20:.2f} MiB "
      f"({svo.num_nodes / dag.num_nodes:.1f}x fewer nodes)")

# Both trees expand back to exactly the voxels they were built from.
assert np.array_equal(jv.expand(dag).to_numpy(), vox.to_numpy())
assert np.array_equal(jv.expand(svo).to_numpy(), vox.to_numpy())

# %% [markdown]
# ## Nodes per level
# The octree grows about 4x per level on a surface; the DAG stops growing near the
# bottom, where few distinct small subtrees exist (at most 255 distinct masks at the
# level above the voxels).

# %%
levels = np.arange(svo.depth)
fig, (ax, ax_mem) = plt.subplots(1, 2, figsize=(11, 4))
ax.bar(levels - 0.2, svo.level_sizes, width=0.4, label="octree")
ax.bar(levels + 0.2, dag.level_sizes, width=0.4, label="DAG")
ax.set(yscale="log", xlabel="level (0 = root)", ylabel="nodes", title="nodes per level")
ax.legend()

# %% [markdown]
# ## Memory of each layout
# The node tables as stored (mask, 8 child pointers and 8 prefix sums per node above
# the mask-only level) against a dense bit grid and the DAG without prefix sums.

# %%
def table_bytes(tree, prefix=True):
    inner = sum(tree.level_sizes[:-1])
    return tree.num_nodes + 32 * inner * (2 if prefix else 1)


layouts = {
    "dense bits": RESOLUTION**3 / 8,
    "octree": table_bytes(svo, prefix=False),
    "octree + prefix": jv.compact(svo).nbytes,  # without the ladder's padding rows
    "DAG": table_bytes(dag, prefix=False),
    "DAG + prefix": jv.compact(dag).nbytes,
}
assert layouts["octree + prefix"] == table_bytes(svo) and layouts["DAG + prefix"] == table_bytes(dag)
ax_mem.barh(list(layouts), [v / 2**20 for v in layouts.values()])
ax_mem.set(xscale="log", xlabel="MiB", title=f"layouts at {RESOLUTION}^3")
plt.tight_layout()
plt.show()
for name, size in layouts.items():
    print(f"{name:>16}: {size / 2**20:10.3f} MiB, {8 * size / int(vox.count):7.2f} bits/voxel")

# %% [markdown]
# ## Attributes through the prefix sums
# The DAG shares subtrees, so it cannot store per-voxel data in its nodes. Each node
# stores, per child, the number of voxels before it; summing them on the way down
# gives the voxel's index in Morton order, which addresses a separate attribute array.

# %%
attributes = jv.voxel_attributes(mesh, vox)  # triangle id and face normal per voxel
rng = np.random.default_rng(0)
ijk = vox.to_numpy()
queries = np.concatenate([ijk[rng.integers(0, len(ijk), 5)], [[0, 0, 0]]])  # 5 voxels and (probably) empty space
index = np.asarray(jv.voxel_index(dag, queries))
for q, i in zip(queries, index):
    if i < 0:
        print(f"voxel {q}: empty")
    else:
        n = np.asarray(attributes["normal"][i])
        print(f"voxel {q}: index {i}, triangle {int(attributes['triangle'][i])}, normal {np.round(n, 3)}")
assert (index[:-1] >= 0).all()
assert np.array_equal(np.asarray(attributes["triangle"])[index[:-1]],
                      vox.triangle_ids()[index[:-1]])

# Shade the voxels by their normal, looked up through the DAG for a slice of the grid.
k = int(np.median(ijk[:, 2]))
ii, jj = np.meshgrid(np.arange(RESOLUTION), np.arange(RESOLUTION), indexing="ij")
slab = np.stack([ii, jj, np.full_like(ii, k)], -1)
idx = np.asarray(jv.voxel_index(dag, slab))
normals = np.asarray(attributes["normal"])[np.maximum(idx, 0)]
image = np.where(idx[..., None] >= 0, 0.5 + 0.5 * normals, 1.0)
plt.figure(figsize=(4, 4))
plt.imshow(np.transpose(image, (1, 0, 2)), origin="lower")
plt.title(f"normals of the voxels in slice k = {k}")
plt.axis("off")
plt.show()

# %% [markdown]
# ## Saving and loading
# A versioned, checksummed file; attributes travel with the tree.

# %%
import tempfile

with tempfile.TemporaryDirectory() as tmp:
    file = pathlib.Path(tmp) / "bunny.jvx"
    jv.save(file, dag, attributes=attributes)
    back = jv.load(file)
    print(f"{file.stat().st_size / 2**20:.2f} MiB on disk; attributes: {sorted(jv.load_attributes(file))}")
    assert back.level_sizes == dag.level_sizes
