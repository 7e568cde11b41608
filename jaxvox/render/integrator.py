"""A diffuse path tracer over voxel octrees and DAGs, lit by an environment.

Light transport. Every voxel is a Lambertian (diffuse) surface with a per-voxel albedo
and an optional per-voxel emitted radiance; the light comes from an `Environment`: a
smooth part (a lat-long image, a uniform colour or a gradient sky) and optionally a sun,
a directional light of given irradiance. The estimator is the simplest unbiased one:

* camera rays are jittered uniformly over each pixel (box filter);
* at a surface hit the path adds ``throughput * emission`` and continues in a
  cosine-weighted direction about the face normal, from a point just off the face
  (``throughput *= albedo``: the cosine and the BRDF's ``1/pi`` cancel against the pdf);
* a ray that escapes adds ``throughput * env(direction)``;
* an environment image is also sampled directly (next-event estimation with importance
  sampling): at each hit that the path leaves by a bounce, one direction is drawn with
  probability proportional to the image's luminance times its pixels' solid angle, and
  a shadow ray toward it adds the light it sees. The two ways of finding the environment
  are combined by multiple importance sampling (Veach's power heuristic), so the
  estimate stays unbiased and a small bright region (a window, a sun in an HDR map) is
  found by the sample that finds it best;
* the sun, a delta light that no bounce ray can hit, is only found by a shadow ray at
  each hit (next-event estimation): ``throughput * albedo / pi * E_sun * cos`` when the
  ray toward the sun escapes; no bounce ray can reach it, so it needs no weights.
  Camera rays also see the sun's disc (angular radius from ``sun_cos``) so that it
  shows in the image; light never bounces off it.

A path has at most ``bounces + 1`` segments; ``bounces=0`` shows emission, the direct
sun and the environment behind the scene (the environment's light on surfaces arrives
with the first bounce, by either strategy). A path whose ray hits the traversal's step
cap, or starts inside a voxel (a float32 tie at a voxel edge), ends there and is counted
in `RenderResult.stopped`.

Randomness. Each pixel sample (sample ``s`` of pixel ``p``) draws from its own key,
``fold_in(key, s * H * W + p)``, so an image depends on the key and the settings, not on
how the samples are split into batches (with a different ``batch_rays`` the sums are
taken in another order: equal to float32 rounding). The same key and settings give the
same bits.

Memory. Pixel samples are traced in batches of ``batch_rays`` paths (a host loop with a
progress bar); the traversal's own memory is bounded by its lanes.

`jaxvox.render.mesh_reference` runs the same estimator on triangle meshes: the names
here without a leading underscore that `jaxvox` does not export (`PathState`, `Surface`,
`shade`, `camera_path`, ...) are the parts it shares, not public API.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float32, Int32

from jaxvox._core.checks import check_int, check_type, refuse
from jaxvox._core.devices import everywhere, on_all_devices, on_each_device
from jaxvox._core.errors import JaxvoxError
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.scan import on_marked
from jaxvox.camera import check_view, pixel_directions
from jaxvox.octree import CompactDag, Octree, occupied
from jaxvox.render.environment import Environment, sky_environment
from jaxvox.render.materials import normal_table, rgb_table
from jaxvox.trace import HIT, STEP_CAP, default_max_steps, jit_trace, trace, valid_rays

_OFFSET = 2.0**-6  # bounce origins sit this many voxel edges off the face they leave
_CORNER_CHUNK = 4096  # hits on a voxel edge or corner checked per walk of `occupied` (see `_voxel_surface`)
# Shadow rays from a voxel with a smooth shading normal start this many voxel edges
# above the hit along it: from the face itself, a ray toward a light low over a smooth
# surface meets the surface's own staircase of voxels (shadow acne). The lift was
# chosen against Embree's renders of the meshes (`experiments/render_vs_mesh.py`; the
# figures are in docs/design-history.md). With face normals there is no lift: there the
# steps are the surface and their shadows belong to it.
SHADOW_LIFT = 1.5
LIGHT_STREAM = 1 << 16  # random stream of the environment sample at vertex k: LIGHT_STREAM + k


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class RenderResult:
    """A rendered image and its auxiliary outputs (AOVs).

    Attributes:
      radiance: [H, W, 3] float32 linear radiance, the mean over the pixel's samples.
      depth: [H, W] float32 distance from the eye to the first surface through the pixel
        centre, inf where the ray escapes.
      normal: [H, W, 3] float32 unit normal of that surface (a voxel face normal, or the
        triangle normal for meshes), 0 where the ray escapes.
      stopped: [] int32 paths ended early: a ray reached the traversal's step cap or
        started inside a voxel (see the module docstring).
    """

    radiance: Float32[Array, "H W 3"]  # [H, W, 3] float32
    depth: Float32[Array, "H W"]  # [H, W] float32
    normal: Float32[Array, "H W 3"]  # [H, W, 3] float32
    stopped: Int32[Array, ""]  # [] int32


class PathState(NamedTuple):
    """The state of a batch of [N] paths between segments."""

    origin: jax.Array  # [N, 3] float32 world position
    direction: jax.Array  # [N, 3] float32 unit, zero once the path has ended
    throughput: jax.Array  # [N, 3] float32
    radiance: jax.Array  # [N, 3] float32 gathered so far
    stopped: jax.Array  # [N] bool the path ended early
    pdf: jax.Array  # [N] float32 density of `direction` under cosine sampling; 0 for camera rays


class Surface(NamedTuple):
    """What a batch of [N] rays found."""

    hit: jax.Array  # [N] bool a surface was hit
    escaped: jax.Array  # [N] bool the ray left the scene
    stopped: jax.Array  # [N] bool neither: step cap, or the ray started inside a voxel
    point: jax.Array  # [N, 3] float32 hit point moved just off the surface, on the ray's side
    normal: jax.Array  # [N, 3] float32 unit geometric normal facing the ray's side
    shading: jax.Array  # [N, 3] float32 unit shading normal on the same side (the geometric one by default)
    index: jax.Array  # type: ignore[assignment]  # [N] int32 primitive index (voxel in Morton order, or triangle), 0 unless hit


def camera_rays(camera, px, py, *, width: int, height: int):
    """Unit directions [N, 3] through continuous pixel positions (``px`` right, ``py`` down)."""
    eye, target, up, fov = camera
    return pixel_directions(
        eye, target, up, px, py, width=width, height=height, tan_half_fov=jnp.tan(jnp.radians(fov) / 2)
    )


def _cosine_direction(normal, u):
    """Cosine-weighted unit directions [N, 3] about unit normals [N, 3], from uniforms [N, 2].

    Uses the branchless orthonormal basis of Duff et al. (2017).
    """
    x, y, z = normal[:, 0], normal[:, 1], normal[:, 2]
    sign = jnp.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = jnp.stack([1 + sign * x * x * a, sign * b, -sign * x], -1)
    t2 = jnp.stack([b, sign + y * y * a, -y], -1)
    r, phi = jnp.sqrt(u[:, 0:1]), 2 * jnp.pi * u[:, 1:2]
    local_z = jnp.sqrt(jnp.maximum(1 - u[:, 0:1], 0.0))
    d = r * jnp.cos(phi) * t1 + r * jnp.sin(phi) * t2 + local_z * normal
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def _voxel_surface(tree: Octree | CompactDag, origin, direction, hit, normals) -> Surface:
    """The surface a voxel `Hit` found; the offset point is inside the face, just outside
    the voxel. The shading normal is the voxel's row of `normals` ([1 or V, 3]; a zero row
    means none), turned to the side of the entered face; the face normal where there is none."""
    grid = tree.grid
    is_hit = hit.status == HIT
    entered = jnp.any(hit.normal != 0, axis=-1)  # False when the ray started inside the voxel
    t = jnp.where(is_hit, hit.t, 0.0)
    p = grid.to_grid_units(origin + t[:, None] * direction)
    v = jnp.maximum(hit.voxel, 0).astype(jnp.float32)
    n = hit.normal
    inside = jnp.clip(p, v + _OFFSET, v + 1 - _OFFSET)
    across = jnp.where(n != 0, v + 0.5 + n * (0.5 + _OFFSET), inside)
    # A ray through a voxel edge or corner comes in diagonally, and the voxel across the
    # entry face it reports can be occupied (a bounce from there would start inside it).
    # Then the point leaves through every face the hit touches on the side the ray came
    # from, into the voxel the ray crossed just before.
    incoming = jnp.where(direction > 0, v, v + 1)
    touching = (n != 0) | (jnp.abs(p - incoming) <= _OFFSET)
    diagonal = jnp.where(touching, v + 0.5 - jnp.sign(direction) * (0.5 + _OFFSET), inside)
    # A ray through the interior of the entered face came from the voxel across it, so
    # only hits on an edge or corner of the voxel can find that voxel occupied: the
    # lookups (a walk down the tree each) run on those alone.
    corner = is_hit & (jnp.sum(touching, axis=-1) >= 2)
    cells = jnp.floor(across).astype(jnp.int32)
    blocked = on_marked(lambda c: occupied(tree, c), corner, cells, jnp.bool_(False), _CORNER_CHUNK)
    p = jnp.where(blocked[:, None], diagonal, across)
    point = grid.origin + p * grid.voxel_size
    live = valid_rays(origin, direction)
    index = jnp.maximum(hit.index, 0)
    given = _lookup(normals, index)
    length = jnp.sqrt(jnp.sum(given * given, -1, keepdims=True))
    facing = jnp.where(jnp.sum(given * n, -1, keepdims=True) < 0, -given, given)
    shading = jnp.where(length > 0.5, facing / jnp.maximum(length, 0.5), n)
    return Surface(
        hit=is_hit & entered,
        escaped=live & (hit.status != HIT) & (hit.status != STEP_CAP),
        stopped=live & ((hit.status == STEP_CAP) | (is_hit & ~entered)),
        point=point,
        normal=n,
        shading=shading,
        index=index,
    )


def shadow_origins(tree: Octree | CompactDag, surf: Surface) -> jax.Array:
    """[N, 3] float32 origins of shadow rays from voxel hits.

    Where the shading normal differs from the entered face's, the voxels stand for a
    smooth surface and their steps must not shadow it: the origin is `SHADOW_LIFT` voxel
    edges above the hit along the shading normal. In a crease that point can lie in an
    occupied voxel, and the shadow ray, starting inside, reports the sun hidden. (Falling
    back to the hit point there instead changed the images by little and cost a lookup
    per shadow ray.) Shaded by its faces, the
    staircase is the surface and casts its own shadows: the origin is the hit point.
    """
    smooth = jnp.any(surf.shading != surf.normal, axis=-1, keepdims=True)
    return surf.point + jnp.where(smooth, surf.shading * (SHADOW_LIFT * tree.grid.voxel_size), 0.0)


def _lookup(table, index):
    """Rows of a [1 or V, 3] per-primitive table (a single row is a constant)."""
    return table[jnp.minimum(index, table.shape[0] - 1)]


def _mis(a, b):
    """Power-heuristic weight [N] of a sample drawn with density `a` against a strategy of density `b`."""
    return jnp.where(a > 0, a * a / jnp.maximum(a * a + b * b, 1e-30), 0.0)


def environment_sample(env: Environment, surf: Surface, u, last):
    """The environment sample at each hit that the path leaves by a bounce.

    Returns (directions [N, 3] float32, zero where there is none, and their pdf [N]).
    """
    d, pdf = env.sample(u)
    leaves = (jnp.sum(surf.normal * d, -1) > 0) & (jnp.sum(surf.shading * d, -1) > 0)
    use = surf.hit & ~last & leaves & (pdf > 0)
    return jnp.where(use[:, None], d, 0.0), jnp.where(use, pdf, 0.0)


def shade(
    path: PathState, surf: Surface, sun_visible, u, *, rho, emitted, env: Environment, first, last, light=None
) -> PathState:
    """One path vertex: gathers emission, escape, the sun and the environment sample;
    samples the next direction.

    ``rho`` and ``emitted`` are the [N, 3] albedo and emission at the hits, ``u`` [N, 2]
    uniforms, ``sun_visible`` [N] float32 whether the shadow ray escaped; ``light`` is
    (directions, pdf, visible) of the environment samples when ``env.sampled``.

    Cosines and the bounce's cosine lobe use the shading normal. A bounce direction that
    would go back through the face the ray entered (possible when the shading normal
    leans away from the face normal) is mirrored in the face's plane, so that every
    bounce leaves the surface and none starts inside its own voxel.
    """
    live = valid_rays(path.origin, path.direction)
    sky = jnp.where(first, env.camera_radiance(path.direction), env.radiance(path.direction))
    if env.sampled:
        sky = sky * jnp.where(first, 1.0, _mis(path.pdf, env.pdf(path.direction)))[:, None]
    radiance = path.radiance + jnp.where(surf.escaped[:, None], path.throughput * sky, 0.0)
    gathered = emitted
    if env.sun:
        cos = jnp.maximum(jnp.sum(surf.shading * env.sun_direction, -1), 0.0)
        sun = rho / jnp.pi * env.sun_irradiance * (cos * sun_visible)[:, None]
        gathered = gathered + sun
    if env.sampled:
        d, pdf, visible = light
        cos = jnp.sum(surf.shading * d, -1)  # > 0 where pdf > 0
        weight = _mis(pdf, cos / jnp.pi) / jnp.where(pdf > 0, pdf, 1.0) * cos * visible
        gathered = gathered + rho / jnp.pi * env.radiance(d) * weight[:, None]
    radiance = radiance + jnp.where(surf.hit[:, None], path.throughput * gathered, 0.0)
    go_on = surf.hit & ~last & live
    up = jnp.array([0.0, 0.0, 1.0])
    normal = jnp.where(surf.hit[:, None], surf.shading, up)
    face = jnp.where(surf.hit[:, None], surf.normal, up)
    lobe = _cosine_direction(normal, u)
    pdf = jnp.sum(normal * lobe, -1) / jnp.pi
    back = jnp.sum(face * lobe, -1, keepdims=True)
    lobe = jnp.where(back <= 0, lobe - 2 * back * face, lobe)
    return PathState(
        origin=jnp.where(go_on[:, None], surf.point, path.origin),
        direction=jnp.where(go_on[:, None], lobe, 0.0),
        throughput=path.throughput * jnp.where(go_on[:, None], rho, 1.0),
        radiance=radiance,
        stopped=path.stopped | surf.stopped,
        pdf=jnp.where(go_on, pdf, 0.0),
    )


def uniforms(keys, stream: int | jax.Array, n: int):
    """[N, n] float32 uniforms, one draw per path key for the given stream number."""
    return jax.vmap(lambda k: jax.random.uniform(jax.random.fold_in(k, stream), (n,)))(keys)


def camera_path(camera, key, ids, *, width: int, height: int) -> tuple[PathState, jax.Array]:
    """Jittered camera rays for global pixel-sample ids [N]; returns (path, per-path keys)."""
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(ids)
    u = uniforms(keys, 0, 2)
    pixel = ids % (width * height)
    px = (pixel % width).astype(jnp.float32) + u[:, 0]
    py = (pixel // width).astype(jnp.float32) + u[:, 1]
    d = camera_rays(camera, px, py, width=width, height=height)
    zeros = jnp.zeros_like(d)
    path = PathState(
        origin=jnp.broadcast_to(camera[0], d.shape),
        direction=d,
        throughput=jnp.ones_like(d),
        radiance=zeros,
        stopped=jnp.zeros(d.shape[0], bool),
        pdf=jnp.zeros(d.shape[0], jnp.float32),
    )
    return path, keys


@functools.partial(jax.jit, static_argnames=("width", "height", "batch", "max_steps", "lanes", "shard"))
def _render_batch(
    tree,
    albedo,
    emission,
    normals,
    env,
    camera,
    key,
    start,
    total,
    bounces,
    image,
    stopped,
    *,
    width,
    height,
    batch,
    max_steps,
    lanes,
    shard,
):
    """Traces pixel samples ``start .. start + batch`` (those below `total`) and adds them
    to `image`; with `shard`, each JAX device traces its own slice of them (`batch` is a
    multiple of the device count)."""
    ids = start + jnp.arange(batch, dtype=jnp.int32)
    shared = (tree, albedo, emission, normals, env, camera, key, total, bounces)
    paths = functools.partial(_paths, width=width, height=height, max_steps=max_steps, lanes=lanes)
    radiance, ended = on_each_device(paths, shared, ids) if shard else paths(shared, ids)
    valid = ids < total
    pixel = jnp.where(valid, ids % (width * height), width * height)
    image = image.at[pixel].add(radiance, mode="drop")
    carried = image, stopped + jnp.sum(ended & valid).astype(jnp.int32)
    return jax.lax.with_sharding_constraint(carried, everywhere()) if shard else carried


def _paths(shared, ids, *, width, height, max_steps, lanes):
    """Radiance [N, 3] and early ends [N] of the paths of pixel samples `ids` [N] (those
    at or above `total` are not traced); `shared` holds `_render_batch`'s arguments up to
    `bounces`."""
    tree, albedo, emission, normals, env, camera, key, total, bounces = shared
    batch = ids.shape[0]
    valid = ids < total
    path, keys = camera_path(camera, key, jnp.where(valid, ids, 0), width=width, height=height)
    path = path._replace(direction=jnp.where(valid[:, None], path.direction, 0.0))
    # Morton indices of the hits only where a table has a row per voxel (shadow rays
    # never need them): each is a walk down the tree.
    per_voxel = max(albedo.shape[0], emission.shape[0], normals.shape[0]) > 1

    def go(origin, direction, indexed):
        return jit_trace(
            tree,
            origin,
            direction,
            jnp.float32(jnp.inf),
            method="esvo",
            max_steps=max_steps,
            lanes=lanes,
            shard=False,
            beam=None,
            indexed=indexed,
        )

    # One segment program for every vertex (the first one too: `first` is traced) and one
    # traversal for all its shadow rays: each traversal written into the program costs
    # its compile time again.
    def segment(k, path):
        first, last = k == 0, k >= bounces
        surf = _voxel_surface(tree, path.origin, path.direction, go(path.origin, path.direction, per_voxel), normals)
        shadow = shadow_origins(tree, surf) if env.sun or env.sampled else surf.point
        towards = []  # shadow ray directions: to the sun, to the environment sample
        if env.sun:
            lit = surf.hit & (jnp.sum(surf.shading * env.sun_direction, -1) > 0)
            towards.append(jnp.where(lit[:, None], env.sun_direction, 0.0))
        if env.sampled:
            d, pdf = environment_sample(env, surf, uniforms(keys, LIGHT_STREAM + k, 3), last)
            towards.append(d)
        visible, light = jnp.zeros(batch, jnp.float32), None
        if towards:
            hits = go(jnp.concatenate([shadow] * len(towards)), jnp.concatenate(towards), False).status
            escaped = jnp.split((hits != HIT).astype(jnp.float32), len(towards))
            if env.sun:
                visible = escaped[0]
            if env.sampled:
                light = (d, pdf, escaped[-1])
        return shade(
            path,
            surf,
            visible,
            uniforms(keys, k + 1, 2),
            rho=_lookup(albedo, surf.index),
            emitted=_lookup(emission, surf.index),
            env=env,
            first=first,
            last=last,
            light=light,
        )

    path = jax.lax.fori_loop(0, bounces + 1, segment, path)
    return path.radiance, path.stopped


@functools.partial(jax.jit, static_argnames=("width", "height", "max_steps", "lanes", "shard"))
def _aovs(tree, camera, *, width, height, max_steps, lanes, shard):
    """Depth [H, W] and normal [H, W, 3] of the first voxel through each pixel centre."""
    j, i = jnp.meshgrid(jnp.arange(width), jnp.arange(height))
    d = camera_rays(camera, j.reshape(-1) + 0.5, i.reshape(-1) + 0.5, width=width, height=height)
    hit = trace(tree, jnp.broadcast_to(camera[0], d.shape), d, max_steps=max_steps, lanes=lanes, shard=shard)
    is_hit = (hit.status == HIT)[:, None]
    depth = jnp.where(is_hit[:, 0], hit.t, jnp.inf).reshape(height, width)
    return depth, jnp.where(is_hit, hit.normal, 0.0).reshape(height, width, 3)


def check_settings(caller: str, width, height, spp, bounces, batch_rays) -> None:
    for name, value, low in (
        ("width", width, 1),
        ("height", height, 1),
        ("spp", spp, 1),
        ("bounces", bounces, 0),
        ("batch_rays", batch_rays, 1),
    ):
        check_int(f"{caller} {name}", value, minimum=low)
    if width * height * spp >= 2**31:
        raise refuse(
            f"{caller} width x height x spp",
            "must be below 2^31 samples; render fewer",
            f"{width}x{height} at {spp} spp",
        )


def as_key(key):
    if isinstance(key, (int, np.integer)):
        return jax.random.key(int(key))
    key = jnp.asarray(key)
    return key if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else jax.random.wrap_key_data(key)


def checked_camera(caller: str, eye, target, up, fov):
    """The checked camera (eye, target, up [3], fov []) as float32 device arrays."""
    return tuple(jnp.asarray(v, jnp.float32) for v in check_view(caller, eye, target, up, fov))


def progress_bar(total: int, progress: bool | None, what: str):
    from tqdm.auto import tqdm

    disable = (not sys.stderr.isatty()) if progress is None else not progress
    return tqdm(total=total, desc=what, unit="batch", disable=disable, leave=False)


def render(
    tree: Octree | CompactDag,
    eye,
    target,
    *,
    env: Environment | None = None,
    albedo=None,
    emission=None,
    normals=None,
    width: int = 320,
    height: int = 240,
    fov: float = 40.0,
    up=(0.0, 1.0, 0.0),
    spp: int = 16,
    bounces: int = 8,
    key=0,
    batch_rays: int = 1 << 18,
    max_steps: int | None = None,
    lanes: int | None = 1024,
    shard: bool = True,
    progress: bool | None = None,
) -> RenderResult:
    """Path-traces an image of a voxel octree or DAG (see the module docstring).

    Args:
      tree: an `Octree` (SVO or DAG) or a `CompactDag` (per-voxel albedo and emission
        need its prefix sums).
      eye, target: [3] camera position and the point it looks at (see `look_at_view`).
      env: the lighting, an `Environment` (default `sky_environment()`).
      albedo: diffuse reflectance in [0, 1], linear: an RGB triple for every voxel, or a
        [V, 3] array (V >= ``voxel_count``) indexed by Morton-order voxel index, e.g.
        `voxel_albedo` of `voxel_attributes`. Default 0.7 grey.
      emission: emitted radiance, linear: None (nothing emits), an RGB triple, or a
        [V, 3] per-voxel array.
      normals: None (shade with the normal of the voxel face each ray enters), or a
        [V, 3] per-voxel array of shading normals in Morton order, e.g. the ``"normal"``
        of `voxel_attributes` (the face normal of the triangle that set the voxel);
        rows of zeros fall back to the face normal, and a normal is turned to the side
        the ray came from. Bounces still leave through the entered face (see `shade`).
        Host tables are checked and placed on the devices on every call; the memmaps of
        `mesh_to_dag`'s ``attributes`` are placed without a copy (their files hold the
        rows of the voxel-list ladder), other host arrays are copied once per call.
      width, height: image size in pixels.
      fov: vertical field of view in degrees; up: approximate up direction [3].
      spp: samples (paths) per pixel.
      bounces: diffuse bounces after the first hit (the slides use 8).
      key: an int seed or a `jax.random` key; the same key and settings give the same image.
      batch_rays: pixel samples traced per batch (memory grows with it), rounded up to
        a multiple of the device count when sharded; the last batch is padded. Static,
        as is the image size: changing them recompiles (``spp``, ``bounces``, the
        camera, the key and the lighting's arrays do not).
      max_steps, lanes: passed to `trace` for every ray (`lanes` per device).
      shard: split each batch's paths across all JAX devices, each tracing its own
        (configure one CPU device per core with
        ``jax.config.update("jax_num_cpu_devices", os.cpu_count())`` before JAX starts;
        the command line does). The image is the same up to float32 rounding.
      progress: show a progress bar over batches; None shows one on a terminal only.

    Returns:
      A `RenderResult` with [H, W] images.

    Raises:
      JaxvoxError: not an `Octree` or `Environment`, bad settings, camera, albedo or
        emission, `max_steps` or `lanes` not integers >= 1, or a truncated tree.
    """
    check_type("render tree", tree, (Octree, CompactDag))
    check_settings("render", width, height, spp, bounces, batch_rays)
    if int(tree.overflow):
        raise JaxvoxError(f"cannot render a truncated tree (overflow flags {int(tree.overflow)})")
    env = sky_environment() if env is None else check_type("render env", env, Environment)
    rows = int(tree.voxel_count)
    resolution = tree.grid.resolution
    albedo = rgb_table("render albedo", albedo, rows, "voxel", (0.7, 0.7, 0.7), resolution)
    emission = rgb_table("render emission", emission, rows, "voxel", (0.0, 0.0, 0.0), resolution)
    normals = normal_table("render normals", normals, rows, resolution)
    if (
        isinstance(tree, CompactDag)
        and not tree.prefix
        and max(albedo.shape[0], emission.shape[0], normals.shape[0]) > 1
    ):
        raise refuse(
            "render tree",
            "per-voxel albedo, emission or normals need prefix sums: compact_dag(tree, prefix=True)",
            "prefix=False",
        )
    camera = checked_camera("render", eye, target, up, fov)
    steps = check_int("render max_steps", max_steps, minimum=1) if max_steps is not None else default_max_steps(tree)
    if lanes is not None:
        lanes = check_int("render lanes", lanes, minimum=1)
    key = as_key(key)
    total = width * height * spp
    devices = len(jax.devices()) if shard else 1
    batch = -(-min(int(batch_rays), total) // devices) * devices
    image = jnp.zeros((width * height, 3), jnp.float32)
    stopped = jnp.zeros((), jnp.int32)
    if devices > 1:
        # Every device reads the whole tree and tables: placed on each once per call, not
        # once per batch (a jit over all devices copies each argument that is not). On CPU
        # they are aliased, not copied (`on_all_devices`); the image is written, so each
        # device gets its own.
        tree, albedo, emission, normals, env = on_all_devices((tree, albedo, emission, normals, env))
        image, stopped = jax.device_put((image, stopped), everywhere())
    else:
        albedo, emission, normals = jax.device_put((albedo, emission, normals))
    n_batches = -(-total // batch)
    with progress_bar(n_batches, progress, "render") as bar:
        for b in range(n_batches):
            image, stopped = _render_batch(
                tree,
                albedo,
                emission,
                normals,
                env,
                camera,
                key,
                jnp.int32(b * batch),
                jnp.int32(total),
                jnp.int32(bounces),
                image,
                stopped,
                width=width,
                height=height,
                batch=batch,
                max_steps=steps,
                lanes=lanes,
                shard=devices > 1,
            )
            bar.update(1)
    depth, normal = _aovs(tree, camera, width=width, height=height, max_steps=steps, lanes=lanes, shard=devices > 1)
    radiance = jax.device_put(np.asarray(image).reshape(height, width, 3) / np.float32(spp))  # no program per size
    return RenderResult(radiance=radiance, depth=depth, normal=normal, stopped=stopped)
