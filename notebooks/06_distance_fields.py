# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # 06 · Distance fields and cascaded clipmaps
#
# Build the distance field of a shared mesh with every method, look at slices of the
# field and of its error against the exact (brute-force) field, plot time against error,
# then follow a moving camera with a cascaded clipmap and sphere-trace through it.
# `SMOKE=1` runs everything at a small size (the test suite does).

# %%
import os
import pathlib
import time

import jax
import matplotlib.pyplot as plt
import numpy as np

import jaxvox as jv

jv.enable_compilation_cache()  # compiled programs persist across sessions (~/.cache/jaxvox/xla)

SMOKE = os.environ.get("SMOKE", "0") == "1"
MESHES = pathlib.Path(os.environ.get("JAXVOX_MESHES", "../../shared/meshes"))  # from notebooks/
RESOLUTION = 16 if SMOKE else 64

path = MESHES / "spot.obj"
mesh = jv.load_mesh(path) if path.exists() else jv.default_scene()
grid = jv.Grid.fit(mesh, resolution=RESOLUTION, padding=0.1)
h = float(grid.voxel_size)
print(f"{mesh.num_faces} triangles, {RESOLUTION}^3, watertight: {jv.open_edges(mesh) == 0}, "
      f"a signed jfa+sweep build needs about {jv.distance_field_bytes(RESOLUTION) / 2**20:.1f} MiB")

# %% [markdown]
# ## Every method against the exact field
# Times are second calls (the first compiles); errors in voxels.

# %%
exact = np.asarray(jv.distance_field(mesh, grid, method="exact"))
fields, rows = {}, []
for method in ["jfa", "jfa-separable", "sweep", "jfa+sweep"]:
    jax.block_until_ready(jv.distance_field(mesh, grid, method=method))
    start = time.perf_counter()
    fields[method] = np.asarray(jax.block_until_ready(jv.distance_field(mesh, grid, method=method)))
    err = np.abs(fields[method] - exact) / h
    rows.append((method, time.perf_counter() - start, err.max(), err.mean()))
    print(f"{method:14s} {rows[-1][1]:7.3f} s   max {err.max():.3f}   mean {err.mean():.4f} voxels   "
          f"sign mismatches {int(((fields[method] < 0) != (exact < 0)).sum())}")

# %%
z = RESOLUTION // 2
fig, axes = plt.subplots(2, 5, figsize=(16, 6.5), constrained_layout=True)
for col, (name, field) in enumerate({"exact": exact, **fields}.items()):
    axes[0, col].imshow(field[:, :, z].T / h, origin="lower", cmap="RdBu")
    axes[0, col].contour(field[:, :, z].T, levels=[0], colors="k")
    axes[0, col].set_title(f"{name} (voxels)")
    im = axes[1, col].imshow((field - exact)[:, :, z].T / h, origin="lower", cmap="RdBu_r", vmin=-1, vmax=1)
    axes[1, col].set_title(f"{name} - exact")
fig.colorbar(im, ax=axes[1], shrink=0.8)

# %%
fig, ax = plt.subplots(figsize=(5, 4))
for method, seconds, max_err, mean_err in rows:
    ax.scatter(seconds, mean_err, label=method)
ax.set(xscale="log", yscale="symlog", xlabel="time (s)", ylabel="mean |error| (voxels)", title="time vs error")
ax.legend()

# %% [markdown]
# ## 16-bit storage

# %%
for fmt in jv.distance.FORMATS:
    q = jv.quantize_field(jax.numpy.asarray(fields["jfa+sweep"]), grid, format=fmt)
    err = np.abs(np.asarray(q.decode()) - fields["jfa+sweep"]) / h
    print(f"{fmt}: {q.values.dtype}, extra error max {err.max():.4f}, mean {err.mean():.5f} voxels")

# %% [markdown]
# ## A clipmap following a moving camera
# Three cascades; each move computes and writes only the newly exposed slabs, each as a
# scissor volume (time-sliced: at most one cascade per frame). With the default
# `method="band"` (the narrow band of truncation + 1 jump-flooding passes, from the
# surface near each slab) and with `method="exact"` the incremental clipmap equals a
# build from scratch; other pipeline methods are within their error of the exact field.

# %%
lo, hi = np.asarray(mesh.vertices).min(0), np.asarray(mesh.vertices).max(0)
size = float((hi - lo).max())
cascade_r = 8 if SMOKE else 32
kw = dict(resolution=cascade_r, num_cascades=3, voxel_size=1.5 * size / cascade_r / 2)
path_points = [lo - 0.6 * size + t * (hi - lo + 1.2 * size) * [1, 0.2, 0.1] for t in np.linspace(0, 0.5, 3 if SMOKE else 12)]
clip = jv.build_clipmap(mesh, path_points[0], **kw)
for frame, camera in enumerate(path_points[1:]):
    clip = jv.update_clipmap(clip, mesh, camera, cascades=jv.time_sliced_cascades(frame, 3))
clip = jv.update_clipmap(clip, mesh, path_points[-1])
exact = jv.build_clipmap(mesh, path_points[-1], method="exact", **kw)
h = kw["voxel_size"] * 2.0 ** np.arange(3)[:, None, None, None]
err = (np.abs(np.asarray(clip.fields)) - np.abs(np.asarray(exact.fields))) / h
flips = (np.sign(clip.fields) != np.sign(exact.fields)) & (np.abs(np.asarray(exact.fields)) / h > 0.5)
scratch = jv.build_clipmap(mesh, path_points[-1], **kw)
print("band: incremental == scratch:", np.allclose(clip.fields, scratch.fields, atol=1e-5))
print(f"incremental band clipmap vs exact: |distance| error {err.min():.3f} .. {err.max():.3f} voxels, "
      f"{int(flips.sum())} sign flips more than half a voxel from the surface")
exact_moved = jv.build_clipmap(mesh, path_points[0], method="exact", **kw)
for frame, camera in enumerate(path_points[1:]):
    exact_moved = jv.update_clipmap(exact_moved, mesh, camera, cascades=jv.time_sliced_cascades(frame, 3))
exact_moved = jv.update_clipmap(exact_moved, mesh, path_points[-1])
print("exact: incremental == scratch:", np.allclose(exact_moved.fields, exact.fields, atol=1e-6))

# Sphere-trace an image from the camera towards the mesh centre.
pixels = 16 if SMOKE else 96
camera = np.asarray(path_points[-1])
forward = (lo + hi) / 2 - camera
forward /= np.linalg.norm(forward)
right = np.cross(forward, [0, 0, 1.0]); right /= np.linalg.norm(right)
up = np.cross(right, forward)
u, v = np.meshgrid(np.linspace(-0.5, 0.5, pixels), np.linspace(-0.5, 0.5, pixels))
dirs = forward + u.reshape(-1, 1) * right + v.reshape(-1, 1) * up
hit = jax.jit(jv.trace_clipmap)(clip, np.repeat(camera[None], len(dirs), 0), dirs)  # a jv.Hit
status = np.asarray(hit.status)
depth = np.where(status == jv.HIT, np.asarray(hit.t), np.nan).reshape(pixels, pixels)
fig, axes = plt.subplots(1, 2, figsize=(9, 4))
axes[0].imshow(depth, origin="lower", cmap="viridis_r")
axes[0].set_title("hit distance")
cascade = np.where(status == jv.HIT, np.asarray(hit.index), np.nan)  # Hit.index: the cascade hit
axes[1].imshow(cascade.reshape(pixels, pixels), origin="lower")
axes[1].set_title("cascade where each ray hit")
print("hits:", int((status == jv.HIT).sum()), "of", len(dirs))
