# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # 07 · Many meshes: a training-data pipeline
#
# A batch of meshes becomes occupancy grids, DAGs and depth images in **one jitted call**:
# the meshes are padded to common sizes (`jv.stack_meshes`), and `jv.voxelize_build_trace`
# vmaps the fixed-capacity voxelizer, the DAG build and the tracer over the batch. The
# capacities are static, found once on the host (`jv.batch_capacities`) and rounded on the
# shape ladder, so the next batch of similar meshes runs the same compiled program; items
# that do not fit raise an overflow flag, and `jv.run_batch` re-runs only those.
#
# We time it against the same work mesh by mesh with the host API (`jv.voxelize`,
# `jv.build_dag`, `jv.trace`) and against Open3D, and count compiles with
# `jax.monitoring`. `SMOKE=1` runs everything at a small size.

# %%
import os
import pathlib
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxvox as jv

SMOKE = os.environ.get("SMOKE", "0") == "1"
MESHES = pathlib.Path(os.environ.get("JAXVOX_MESHES", "../../shared/meshes"))  # from notebooks/
RESOLUTION = 16 if SMOKE else 128
BATCH = 2 if SMOKE else 16
WIDTH, HEIGHT = (32, 24) if SMOKE else (128, 96)
NAMES = (["suzanne", "woody"] if SMOKE else
         ["suzanne", "woody", "beetle", "spot", "cow", "teapot", "fandisk", "stanford-bunny"])

# No persistent compilation cache here (unlike the other notebooks): the point is to
# measure what compiling costs.
compiles = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, **kw: compiles.append(seconds)
    if event == "/jax/core/compile/backend_compile_duration" else None)

# %% [markdown]
# ## The data: randomly rotated and scaled meshes in one shared grid
# Every variant is centred, rotated at random, scaled anisotropically and fitted into the
# cube ``[-0.5, 0.5]^3``, so one `Grid` serves the whole batch. Its voxel size ``1 / R`` is
# a power of two: then grid units are exact however XLA evaluates ``x / h``, and the
# batched results are bit for bit those of the host path. Colours and textures are
# dropped (`stack_meshes` stacks them only when every mesh has them, of one shape).

# %%
rng = np.random.default_rng(0)
if MESHES.is_dir():
    sources = [jv.load_mesh(MESHES / f"{name}.obj") for name in NAMES]
else:
    print(f"{MESHES} not found: using the built-in scene")
    sources = [jv.default_scene()]


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def variant(mesh, rng):
    """A randomly rotated, anisotropically scaled copy, fitted into [-0.45, 0.45]^3."""
    v = np.asarray(mesh.vertices, np.float64)
    v = (v - (v.min(0) + v.max(0)) / 2) @ random_rotation(rng).T * rng.uniform(0.6, 1.0, 3)
    v = v / np.abs(v).max() * 0.45
    return jv.Mesh(v.astype(np.float32), mesh.faces)


def make_batch(rng):
    meshes = [variant(sources[b % len(sources)], rng) for b in range(BATCH)]
    eyes = [jv.look_at_view(m, azimuth=rng.uniform(0, 360), elevation=rng.uniform(-30, 60)) for m in meshes]
    rays = [jv.pinhole_rays(eye, target, width=WIDTH, height=HEIGHT) for eye, target in eyes]
    origins, directions = (np.stack([np.asarray(a) for a in parts]) for parts in zip(*rays))
    return meshes, origins, directions


grid = jv.Grid(origin=(-0.5, -0.5, -0.5), voxel_size=1.0 / RESOLUTION, resolution=RESOLUTION)
meshes, origins, directions = make_batch(rng)
print(f"{BATCH} meshes of {min(m.num_faces for m in meshes):,} to {max(m.num_faces for m in meshes):,} "
      f"faces, R = {RESOLUTION}, {WIDTH}x{HEIGHT} rays each")

# %% [markdown]
# ## Capacities, once
# `batch_capacities` counts on the host what every item needs (voxelizer work buffers, and
# octree nodes per level) and rounds it on the shape ladder. Fresh batches of similar
# meshes fall in the same buckets; one that does not is caught by the overflow flags.

# %%
start = time.perf_counter()
capacities, tree_capacities = jv.batch_capacities(meshes, grid)
print(f"capacities found in {time.perf_counter() - start:.1f} s:", capacities, tree_capacities)

# %% [markdown]
# ## One jitted call: occupancy, DAGs and depth images
# `training_batch` wraps the pipeline: the voxels also become dense occupancy grids
# ``[B, R, R, R]`` and the hits depth images ``[B, H, W]`` (inf where the ray misses),
# all inside one `jax.jit`. The overflow flags come back per item.

# %%
@jax.jit
def training_batch(meshes, origins, directions):
    vox, dag, hit = jv.voxelize_build_trace(meshes, grid, origins, directions, capacities=capacities,
                                            tree_capacities=tree_capacities)

    def occupancy(coords, count):
        valid = jnp.arange(coords.shape[0]) < count
        index = jnp.where(valid[:, None], coords, RESOLUTION)  # unused slots are dropped
        return jnp.zeros((RESOLUTION,) * 3, bool).at[tuple(index.T)].set(True, mode="drop")

    depth = jnp.where(hit.status == jv.HIT, hit.t, jnp.inf)
    return jax.vmap(occupancy)(vox.coords, vox.count), dag, depth, dag.overflow


def timed(fn, *args):
    n, start = len(compiles), time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start, len(compiles) - n


stacked = jv.stack_meshes(meshes)
(occupancy, dags, depth, overflow), batch_first, batch_compiles = timed(training_batch, stacked, origins, directions)
_, batch_steady, _ = timed(training_batch, stacked, origins, directions)
print(f"first call {batch_first:.2f} s ({batch_compiles} compile), then {batch_steady:.3f} s; "
      f"overflow flags {np.asarray(overflow).tolist()}")

fig, axes = plt.subplots(2, BATCH, figsize=(2.2 * BATCH, 4.4))
for b in range(BATCH):
    axes[0, b].imshow(np.asarray(occupancy[b]).any(axis=2).T, origin="lower", cmap="gray")
    axes[1, b].imshow(np.where(np.isfinite(depth[b]), depth[b], np.nan), cmap="viridis")
    for ax in axes[:, b]:
        ax.axis("off")
axes[0, 0].set_title("occupancy (z projection)", loc="left")
axes[1, 0].set_title("depth", loc="left")
plt.show()

# %% [markdown]
# ## The next batch runs the same program
# Fresh random variants of the same meshes pad to the same sizes and fall in the same
# capacity buckets (the flags say so), so the compiled program is reused as it is.

# %%
meshes2, origins2, directions2 = make_batch(rng)
(occupancy2, _, _, overflow2), second, second_compiles = timed(training_batch, jv.stack_meshes(meshes2), origins2,
                                                      directions2)
print(f"second batch: {second:.3f} s, {second_compiles} compiles, overflow flags {np.asarray(overflow2).tolist()}")

# %% [markdown]
# ## Items that do not fit
# With a voxel capacity below the largest item's count (half the power of two above it),
# the items with the most voxels overflow: their flags are set, and `run_batch` re-runs
# only those, as a smaller batch, with the capacities `batch_capacities` counts for them. Its per-item results (host voxels, compact DAGs, hits) are
# those of the host path.

# %%
counts = np.asarray(occupancy2.sum(axis=(1, 2, 3)))
tight = capacities._replace(voxels=max(256, 1 << (int(counts.max()) - 1).bit_length() - 1))
print(f"voxels per item {counts.tolist()}, voxel capacity {tight.voxels}")
n = len(compiles)
result = jv.run_batch(meshes2, grid, origins2, directions2, capacities=tight, tree_capacities=tree_capacities)
print(f"items re-run per round: {result.retried}; {len(compiles) - n} compiles")
for b, mesh in enumerate(meshes2):
    assert np.array_equal(result.voxels[b], jv.voxelize(mesh, grid).to_numpy())


# %% [markdown]
# ## Mesh by mesh with the host API
# The same work, one mesh at a time: `voxelize` (nothing to size), `build_dag`,
# `trace`. The first pass includes compilation; a second pass over the same meshes is
# the compiled speed. The results equal the batched ones.

# %%
def host_pass(meshes, origins, directions):
    out = []
    for mesh, o, d in zip(meshes, origins, directions):
        vox = jv.voxelize(mesh, grid)
        dag = jv.build_dag(vox)
        hit = jax.block_until_ready(jv.trace(dag, o, d))
        out.append((vox.to_numpy(), jv.compact(dag), np.where(np.asarray(hit.status) == jv.HIT, hit.t, np.inf)))
    return out


host, host_first, host_compiles = timed(host_pass, meshes, origins, directions)
host, host_steady, _ = timed(host_pass, meshes, origins, directions)
for b, (ijk, dag, image) in enumerate(host):
    dense = np.zeros((RESOLUTION,) * 3, bool)
    dense[tuple(ijk.T)] = True
    assert np.array_equal(dense, np.asarray(occupancy[b]))
    assert np.array_equal(image, np.asarray(depth[b]))
    batched = jv.compact(jax.tree.map(lambda x: x[b], dags))
    assert all(np.array_equal(np.asarray(getattr(dag, f)), np.asarray(getattr(batched, f)))
               for f in ("mask", "child", "prefix", "level_count"))
print(f"host API: first pass {host_first:.2f} s ({host_compiles} compiles), then {host_steady:.3f} s; "
      "occupancy, DAGs and depth images equal the batched ones")

# %% [markdown]
# ## Open3D
# Open3D's `VoxelGrid.create_from_triangle_mesh_within_bounds` on the same grid and
# `RaycastingScene.cast_rays` on the same rays (against the triangles, so its depth is
# the surface's, not the first voxel's: the voxel depth is at most a voxel diagonal
# nearer). Open3D is not a jaxvox dependency; this part is skipped without it.

# %%
try:
    import open3d as o3d
except ImportError as exc:
    o3d = None
    print(f"Open3D not available ({exc}); skipping the comparison")


def open3d_pass(meshes, origins, directions):
    out = []
    lo, hi = np.full(3, -0.5), np.full(3, 0.5)
    for mesh, o, d in zip(meshes, origins, directions):
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        tri = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v.astype(np.float64)),
                                        o3d.utility.Vector3iVector(f.astype(np.int32)))
        voxels = o3d.geometry.VoxelGrid.create_from_triangle_mesh_within_bounds(tri, 1.0 / RESOLUTION, lo, hi)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(v, f.astype(np.uint32))
        rays = o3d.core.Tensor(np.concatenate([o, d], axis=-1).astype(np.float32))
        out.append((len(voxels.get_voxels()), scene.cast_rays(rays)["t_hit"].numpy()))
    return out


if o3d is not None:
    peer, peer_time, _ = timed(open3d_pass, meshes, origins, directions)
    both = [(t, np.asarray(depth[b])) for b, (_, t) in enumerate(peer)]
    gaps = np.concatenate([t[hit] - v[hit] for t, v in both for hit in [np.isfinite(t) & np.isfinite(v)]])
    gaps *= RESOLUTION
    print(f"Open3D: {peer_time:.3f} s; voxels {[n for n, _ in peer]} vs jaxvox "
          f"{[len(ijk) for ijk, _, _ in host]}; surface depth - voxel depth: median {np.median(gaps):.2f}, "
          f"range [{gaps.min():.2f}, {gaps.max():.2f}] voxels")

# %% [markdown]
# ## Summary

# %%
rows = [("batched, first call (compiles)", batch_first, batch_compiles),
        ("batched, compiled", batch_steady, 0),
        ("mesh by mesh, first pass", host_first, host_compiles),
        ("mesh by mesh, compiled", host_steady, 0)]
if o3d is not None:
    rows.append(("Open3D", peer_time, 0))
print(f"{BATCH} meshes, R = {RESOLUTION}, {WIDTH}x{HEIGHT} rays each")
for name, seconds, count in rows:
    print(f"  {name:32s} {seconds:8.3f} s  {count:3d} compiles  {BATCH / seconds:8.1f} meshes/s")
plt.barh([r[0] for r in rows][::-1], [r[1] for r in rows][::-1])
plt.xscale("log")
plt.xlabel("seconds for the batch")
plt.show()
