# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # 04 · Path tracing voxel DAGs
#
# `jv.render` path-traces a voxel DAG: jittered camera rays, diffuse (Lambertian) voxels
# with a per-voxel albedo, cosine-weighted bounces, an environment light (a procedural
# sky with a sun, a uniform colour, or a lat-long HDR image), shadow rays toward the sun
# and emissive voxels. `jv.render_mesh` runs the same estimator on the triangles with
# Embree, so the two images differ only by the geometry. `SMOKE=1` runs everything at a
# small size.

# %%
import os
import pathlib
import tempfile
import time

import matplotlib.pyplot as plt
import numpy as np

import jaxvox as jv

jv.enable_compilation_cache()  # compiled programs persist across sessions (~/.cache/jaxvox/xla)

SMOKE = os.environ.get("SMOKE", "0") == "1"
MESHES = pathlib.Path(os.environ.get("JAXVOX_MESHES", "../../shared/meshes"))  # from notebooks/
RESOLUTION = 32 if SMOKE else 512  # smoke sizes = tests/test_render.py's CLI render: they share compiled programs
WIDTH, HEIGHT = (64, 48) if SMOKE else (480, 360)
SPP, BOUNCES = (2, 2) if SMOKE else (32, 8)

# %% [markdown]
# ## The default scene with its vertex colours
# The built-in scene is modelled with +z up; the sky has +y up, so turn it upright first.
# `voxel_attributes` interpolates the vertex colours at each voxel; `voxel_albedo`
# decodes them from sRGB to linear reflectance, in Morton order, as `Hit.index` reads them.

# %%
scene = jv.default_scene()
v = np.asarray(scene.vertices)
scene = jv.Mesh(np.stack([v[:, 0], v[:, 2], -v[:, 1]], 1), scene.faces, colors=scene.colors)
vox = jv.voxelize(scene, jv.Grid.fit(scene, resolution=RESOLUTION), triangle_ids=True)
dag = jv.build_dag(vox)
albedo = jv.voxel_albedo(jv.voxel_attributes(scene, vox))
eye, target = jv.look_at_view(scene, distance=1.8)
start = time.perf_counter()
result = jv.render(dag, eye, target, env=jv.sky_environment(), albedo=albedo, width=WIDTH, height=HEIGHT,
                   spp=SPP, bounces=BOUNCES, key=0)
seconds = time.perf_counter() - start
print(f"{WIDTH}x{HEIGHT}, {SPP} spp, {BOUNCES} bounces: {seconds:.1f} s including compilation")
fig, axes = plt.subplots(1, 3, figsize=(14, 4))
axes[0].imshow(jv.tonemap(result.radiance))
axes[0].set_title("radiance (tone-mapped)")
depth = np.asarray(result.depth)
axes[1].imshow(np.where(np.isfinite(depth), depth, np.nan))
axes[1].set_title("depth AOV")
axes[2].imshow(0.5 + 0.5 * np.asarray(result.normal))
axes[2].set_title("normal AOV")
for ax in axes:
    ax.axis("off")
plt.show()

# %% [markdown]
# ## Same seed, same image; EXR keeps every bit
# Each pixel sample draws from `fold_in(key, sample index)`, so the batch size does not
# change which random numbers a sample gets. The EXR file holds linear float32 radiance
# with depth and normal channels; the PNG beside it is tone-mapped sRGB.

# %%
again = jv.render(dag, eye, target, env=jv.sky_environment(), albedo=albedo, width=WIDTH, height=HEIGHT,
                  spp=SPP, bounces=BOUNCES, key=0)
print("same image:", np.array_equal(np.asarray(again.radiance), np.asarray(result.radiance)))
with tempfile.TemporaryDirectory() as folder:
    exr, png = jv.save_render(os.path.join(folder, "scene.exr"), result)
    channels = jv.read_exr(exr)
    print(sorted(channels), "round trip exact:", np.array_equal(channels["R"], np.asarray(result.radiance)[..., 0]))

# %% [markdown]
# ## A white furnace
# Albedo 1 under a uniform environment of radiance 1: light is neither created nor
# absorbed, so every pixel is 1, object or not (up to paths cut by the bounce cap).

# %%
furnace = jv.render(dag, eye, target, env=jv.uniform_environment(rgb=1.0), albedo=(1.0, 1.0, 1.0), width=WIDTH,
                    height=HEIGHT, spp=SPP, bounces=32, key=1)
rgb = np.asarray(furnace.radiance)
print(f"furnace: mean {rgb.mean():.6f}, min {rgb.min():.4f}, max {rgb.max():.6f}")

# %% [markdown]
# ## Emissive voxels in the dark
# A black environment and a few glowing voxels: the only light in the scene.

# %%
emission = np.zeros((int(dag.voxel_count), 3), np.float32)
emission[:: 40] = (6.0, 3.0, 1.0)
glow = jv.render(dag, eye, target, env=jv.uniform_environment(rgb=0.0), albedo=albedo, emission=emission,
                 width=WIDTH, height=HEIGHT, spp=SPP, bounces=BOUNCES, key=2)
plt.imshow(jv.tonemap(glow.radiance, exposure=1.0))
plt.axis("off")
plt.show()

# %% [markdown]
# ## Voxels against the mesh
# The bunny's DAG at two resolutions against Embree on its triangles, same seed and
# settings (`experiments/render_vs_mesh.py` sweeps resolutions and measures PSNR and SSIM).

# %%
path = MESHES / "stanford-bunny.obj"
bunny = jv.load_mesh(path) if path.exists() else scene
eye, target = jv.look_at_view(bunny, distance=1.6)
settings = dict(env=jv.sky_environment(), width=WIDTH, height=HEIGHT, spp=SPP, bounces=BOUNCES, key=3)
images = {}
for R in ([RESOLUTION] if SMOKE else [128, 1024]):
    tree = jv.build_dag(jv.voxelize(bunny, jv.Grid.fit(bunny, resolution=R)))
    images[f"DAG {R}^3"] = jv.render(tree, eye, target, **settings).radiance
try:
    images["mesh (Embree)"] = jv.render_mesh(bunny, eye, target, **settings).radiance
except jv.JaxvoxError as exc:
    print(exc)
fig, axes = plt.subplots(1, len(images), figsize=(5 * len(images), 4))
for ax, (name, image) in zip(np.atleast_1d(axes), images.items()):
    ax.imshow(jv.tonemap(image))
    ax.set_title(name)
    ax.axis("off")
plt.show()
