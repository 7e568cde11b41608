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
  ray toward the sun escapes; no bounce ray can reach it, so it needs no weights. Camera rays also see the sun's disc (angular
  radius from ``sun_cos``) so that it shows in the image; light never bounces off it.

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
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import sys
from collections.abc import Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._checks import (
    check_int,
    check_number,
    check_output_path,
    check_type,
    check_vector,
    refuse,
)
from jaxvox._errors import JaxvoxError
from jaxvox._pytree import pytree_dataclass
from jaxvox.camera import check_view
from jaxvox.mesh import sample_texture, validate_mesh
from jaxvox.octree import MISSING, Octree, voxel_index
from jaxvox.trace import HIT, STEP_CAP, trace
from jaxvox.voxelize import Voxels

_OFFSET = 2.0**-6  # bounce origins sit this many voxel edges off the face they leave
_LIGHT_STREAM = 1 << 16  # random stream of the environment sample at vertex k: _LIGHT_STREAM + k
_SUN_COS = math.cos(math.radians(0.53))  # default sun disc: 0.53 degrees in radius (2x the real sun)


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Environment:
    """Radiance arriving from infinitely far away, as a function of direction (y is up).

    ``radiance(d) = image(d) + sky(d)`` plus, when `sun` is set, a directional light
    of irradiance `sun_irradiance` from `sun_direction`. Build one with
    `uniform_environment`, `sky_environment` or `load_environment`. `sun` is static
    (changing it recompiles, and so does a new image shape).

    Attributes:
      image: [Hi, Wi, 3] float32 lat-long radiance: row 0 looks straight up (+y), row
        ``Hi - 1`` straight down; column ``j`` is the azimuth ``2 pi (j + 0.5) / Wi - pi``
        measured from -z towards +x, so the image centre looks along -z. Looked up
        nearest-neighbour; a [1, 1, 3] image is a uniform environment.
      zenith, horizon, ground: [3] float32 radiance of a gradient sky added to the image:
        ``horizon`` blends into ``zenith`` as ``sqrt(d_y)`` above the horizon, and into
        ``ground`` within 5 degrees below it. Zero for image environments.
      sun_direction: [3] float32 unit vector towards the sun.
      sun_irradiance: [3] float32 irradiance on a surface facing the sun.
      sun_cos: [] float32 cosine of the sun disc's angular radius (camera rays only).
      sun: static bool, whether the sun is traced (one shadow ray per hit).
      cdf: [Hi * Wi] float32 cumulative probabilities of the image's pixels (row-major)
        for importance sampling: luminance times solid angle, normalised.
      sampled: static bool, whether the image is importance-sampled (one more shadow
        ray per bounce); set for images of more than one pixel with any light.
    """

    image: jax.Array  # [Hi, Wi, 3] float32
    zenith: jax.Array  # [3] float32
    horizon: jax.Array  # [3] float32
    ground: jax.Array  # [3] float32
    sun_direction: jax.Array  # [3] float32
    sun_irradiance: jax.Array  # [3] float32
    sun_cos: jax.Array  # [] float32
    cdf: jax.Array  # [Hi * Wi] float32
    sun: bool = dataclasses.field(metadata=dict(static=True))
    sampled: bool = dataclasses.field(metadata=dict(static=True))

    def _pixel(self, d: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(row, col) int32 [...] of the image pixel holding unit directions [..., 3]."""
        h, w = self.image.shape[:2]
        row = jnp.clip(jnp.floor(jnp.arccos(jnp.clip(d[..., 1], -1.0, 1.0)) / jnp.pi * h), 0, h - 1)
        phi = jnp.arctan2(d[..., 0], -d[..., 2])  # 0 along -z, pi / 2 along +x
        col = jnp.clip(jnp.floor((phi + jnp.pi) / (2 * jnp.pi) * w), 0, w - 1)
        return row.astype(jnp.int32), col.astype(jnp.int32)

    def radiance(self, directions: jax.Array) -> jax.Array:
        """Radiance [..., 3] float32 from directions [..., 3] (need not be unit; zero gives the horizon).

        The sun is not included (it is a delta light; see `Environment`).
        """
        d = jnp.asarray(directions, jnp.float32)
        length = jnp.linalg.norm(d, axis=-1, keepdims=True)
        d = d / jnp.where(length > 0, length, 1.0)
        y = d[..., 1]
        row, col = self._pixel(d)
        up = jnp.sqrt(jnp.clip(y, 0.0, 1.0))[..., None]
        below = jnp.clip(-y / math.sin(math.radians(5.0)), 0.0, 1.0)[..., None]
        sky = jnp.where(y[..., None] >= 0, self.horizon + (self.zenith - self.horizon) * up,
                        self.horizon + (self.ground - self.horizon) * below)
        return self.image[row, col] + sky

    def camera_radiance(self, directions: jax.Array) -> jax.Array:
        """`radiance` plus the sun disc (radiance ``E / solid angle``), for camera rays: [..., 3] float32."""
        d = jnp.asarray(directions, jnp.float32)
        d = d / jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), 1e-30)
        solid_angle = 2 * jnp.pi * (1 - self.sun_cos)
        disc = jnp.sum(d * self.sun_direction, axis=-1, keepdims=True) >= self.sun_cos
        sun = jnp.where(disc & self.sun, self.sun_irradiance / jnp.maximum(solid_angle, 1e-12), 0.0)
        return self.radiance(d) + sun

    def sample(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Directions drawn from the image's importance distribution.

        A pixel is picked from `cdf`, then a point uniform in solid angle inside it.

        Args:
          u: [N, 3] float32 uniforms in [0, 1).

        Returns:
          (directions [N, 3] float32 unit, pdf [N] float32 per steradian).
        """
        h, w = self.image.shape[:2]
        pixel = jnp.minimum(jnp.searchsorted(self.cdf, u[:, 0] * self.cdf[-1], side="right"), h * w - 1)
        row, col = pixel // w, pixel % w
        cos_top, cos_bottom = jnp.cos(jnp.pi * row / h), jnp.cos(jnp.pi * (row + 1) / h)
        y = cos_top + u[:, 1] * (cos_bottom - cos_top)
        phi = 2 * jnp.pi * (col + u[:, 2]) / w - jnp.pi
        sin = jnp.sqrt(jnp.maximum(1 - y * y, 0.0))
        d = jnp.stack([sin * jnp.sin(phi), y, -sin * jnp.cos(phi)], -1)
        return d, self.pdf(d)

    def pdf(self, directions: jax.Array) -> jax.Array:
        """[...] float32 probability density (per steradian) of `sample` drawing unit `directions` [..., 3]."""
        h, w = self.image.shape[:2]
        row, col = self._pixel(directions)
        flat = row * w + col
        prob = self.cdf[flat] - jnp.where(flat > 0, self.cdf[jnp.maximum(flat - 1, 0)], 0.0)
        solid = 2 * jnp.pi / w * (jnp.cos(jnp.pi * row / h) - jnp.cos(jnp.pi * (row + 1) / h))
        return prob / self.cdf[-1] / solid


def _rgb(value, name: str) -> np.ndarray:
    """[3] float32 from an RGB triple or one number; refuses other shapes, negatives, NaN, inf."""
    try:
        v = np.broadcast_to(np.asarray(value, np.float32), (3,)).copy()
    except (TypeError, ValueError):
        raise refuse(name, "must be three finite non-negative numbers", value) from None
    if not np.isfinite(v).all() or (v < 0).any():
        raise refuse(name, "must be three finite non-negative numbers", value)
    return v


def _image_cdf(image: np.ndarray) -> np.ndarray:
    """[H * W] float32 cumulative sums (float64, then rounded) of luminance x pixel solid angle."""
    h, w = image.shape[:2]
    luminance = image.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    edges = np.cos(np.pi * np.arange(h + 1) / h)
    return np.cumsum(luminance * (2 * np.pi / w * (edges[:-1] - edges[1:]))[:, None]).astype(np.float32)


def _environment(caller: str, image, *, scale=1.0, zenith=0.0, horizon=0.0, ground=0.0,
                 sun_direction=(0.0, 1.0, 0.0), sun_irradiance=0.0, sun_cos=_SUN_COS, sun=False,
                 importance=False) -> Environment:
    """The `Environment` of a checked image (times `scale`) and sky; errors name `caller`."""
    try:
        image = np.asarray(image, np.float32) * np.float32(scale)
    except (TypeError, ValueError):
        raise refuse(f"{caller} image", "must be an [H, W, 3] array of numbers", image) from None
    if image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        raise refuse(f"{caller} image", "must be [H, W, 3]", image.shape)
    bad = ~(np.isfinite(image) & (image >= 0))
    if bad.any():
        raise refuse(f"{caller} image", "must hold finite non-negative radiance", image[bad][0])
    s = check_vector(f"{caller} sun_direction", sun_direction, 3)
    if not s.any():
        raise refuse(f"{caller} sun_direction", "must be non-zero", sun_direction)
    env = Environment.__new__(Environment)
    fields = dict(image=jnp.asarray(image), zenith=_rgb(zenith, f"{caller} zenith"),
                  horizon=_rgb(horizon, f"{caller} horizon"), ground=_rgb(ground, f"{caller} ground"),
                  sun_direction=(s / np.linalg.norm(s)).astype(np.float32),
                  sun_irradiance=_rgb(sun_irradiance, f"{caller} sun_irradiance"), sun_cos=np.float32(sun_cos),
                  cdf=_image_cdf(image), sun=bool(sun))
    fields["sampled"] = bool(importance and image.shape[0] * image.shape[1] > 1 and fields["cdf"][-1] > 0)
    for name, value in fields.items():
        object.__setattr__(env, name, value if name in ("sun", "sampled") else jnp.asarray(value))
    return env


def uniform_environment(rgb=(1.0, 1.0, 1.0)) -> Environment:
    """The same radiance ``rgb`` ([3] or a scalar, linear) from every direction; no sun.

    Raises:
      JaxvoxError: `rgb` not one or three finite non-negative numbers.
    """
    return _environment("uniform_environment", _rgb(rgb, "uniform_environment rgb").reshape(1, 1, 3))


def sky_environment(*, sun_direction=(0.45, 0.75, 0.5), sun_irradiance=(2.2, 2.1, 1.9),
                    zenith=(0.10, 0.20, 0.45), horizon=(0.45, 0.50, 0.58), ground=(0.12, 0.11, 0.10),
                    sun_radius_degrees: float = 0.53) -> Environment:
    """A built-in procedural sky: a blue gradient over a dim ground, and a sun.

    Args:
      sun_direction: [3] direction towards the sun (normalised here; y is up).
      sun_irradiance: [3] linear irradiance on a surface facing the sun (0 for no sun).
      zenith, horizon, ground: [3] linear radiance of the gradient (see `Environment`).
      sun_radius_degrees: angular radius of the sun disc seen by camera rays, in [0, 90].

    Raises:
      JaxvoxError: a sun direction that is not a finite non-zero [3] vector, radiances
        that are not finite non-negative RGB, a sun radius outside [0, 90].
    """
    irradiance = _rgb(sun_irradiance, "sky_environment sun_irradiance")
    radius = check_number("sky_environment sun_radius_degrees", sun_radius_degrees, minimum=0.0, maximum=90.0)
    return _environment("sky_environment", np.zeros((1, 1, 3), np.float32), zenith=zenith, horizon=horizon,
                        ground=ground, sun_direction=sun_direction, sun_irradiance=irradiance,
                        sun_cos=math.cos(math.radians(radius)), sun=bool(irradiance.any()))


def load_environment(path: str | os.PathLike, *, scale: float = 1.0, importance: bool = True) -> Environment:
    """An environment from a lat-long (equirectangular) HDR image file, times `scale`.

    Reads ``.exr`` files with OpenEXR (channels R, G, B; a single channel Y is grey),
    Radiance ``.hdr`` files (`read_hdr`) and ``.npy`` arrays [H, W, 3]; see `Environment`
    for the layout. No sun. With `importance` (default) the image is also sampled
    directly at every bounce (see the module docstring): less noise from small bright
    regions for one more shadow ray per bounce; without it only bounce rays find it.

    Raises:
      JaxvoxError: missing file, unsupported format, bad contents, or a `scale` that is
        not a finite number >= 0.
    """
    from jaxvox.image import read_exr, read_hdr

    path = os.fspath(path)
    scale = check_number("load_environment scale", scale, minimum=0.0)
    if not os.path.isfile(path):
        raise refuse("load_environment path", "is a directory, expected a file" if os.path.isdir(path)
                     else "file not found", path)
    ext = os.path.splitext(path)[1].lower()
    if ext == ".exr":
        channels = read_exr(path)
        if all(c in channels for c in "RGB"):
            image = np.stack([channels[c] for c in "RGB"], axis=-1)
        elif "Y" in channels:
            image = np.repeat(channels["Y"][..., None], 3, axis=-1)
        else:
            raise refuse("load_environment path", f"an environment EXR needs channels R, G, B (or Y), has "
                         f"{sorted(channels)}", path)
    elif ext == ".hdr":
        image = read_hdr(path)
    elif ext == ".npy":
        try:
            image = np.load(path)
        except (OSError, ValueError) as exc:
            raise refuse("load_environment path", f"not a readable .npy array ({exc})", path) from None
    else:
        raise refuse("load_environment path", "environment maps are read from .exr, .hdr or .npy files", path)
    return _environment("load_environment", image, scale=scale, importance=importance)


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

    radiance: jax.Array  # [H, W, 3] float32
    depth: jax.Array  # [H, W] float32
    normal: jax.Array  # [H, W, 3] float32
    stopped: jax.Array  # [] int32


class _Path(NamedTuple):
    """The state of a batch of [N] paths between segments."""

    origin: jax.Array  # [N, 3] float32 world position
    direction: jax.Array  # [N, 3] float32 unit, zero once the path has ended
    throughput: jax.Array  # [N, 3] float32
    radiance: jax.Array  # [N, 3] float32 gathered so far
    stopped: jax.Array  # [N] bool the path ended early
    pdf: jax.Array  # [N] float32 density of `direction` under cosine sampling; 0 for camera rays


class _Surface(NamedTuple):
    """What a batch of [N] rays found."""

    hit: jax.Array  # [N] bool a surface was hit
    escaped: jax.Array  # [N] bool the ray left the scene
    stopped: jax.Array  # [N] bool neither: step cap, or the ray started inside a voxel
    point: jax.Array  # [N, 3] float32 hit point moved just off the surface, on the ray's side
    normal: jax.Array  # [N, 3] float32 unit normal facing the ray's side
    index: jax.Array  # [N] int32 primitive index (voxel in Morton order, or triangle), 0 unless hit


def _camera_basis(eye, target, up):
    forward = target - eye
    forward = forward / jnp.linalg.norm(forward)
    right = jnp.cross(forward, up)
    right = right / jnp.linalg.norm(right)
    return forward, right, jnp.cross(right, forward)


def _camera_rays(camera, px, py, *, width: int, height: int):
    """Unit directions [N, 3] through continuous pixel positions (``px`` right, ``py`` down).

    Pixel centres (``px = j + 0.5``) give exactly the rays of `jaxvox.pinhole_rays`.
    """
    eye, target, up, fov = camera
    forward, right, true_up = _camera_basis(eye, target, up)
    scale = jnp.tan(jnp.radians(fov) / 2)
    ys = (1 - 2 * py / height) * scale
    xs = (2 * px / width - 1) * scale * width / height
    d = forward + xs[:, None] * right + ys[:, None] * true_up
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)


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


def _voxel_surface(tree: Octree, origin, direction, hit) -> _Surface:
    """The surface a voxel `Hit` found; the offset point is inside the face, just outside the voxel."""
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
    blocked = voxel_index(tree, jnp.floor(across).astype(jnp.int32)) != MISSING
    p = jnp.where(blocked[:, None], diagonal, across)
    point = grid.origin + p * grid.voxel_size
    live = jnp.any(direction != 0, axis=-1)
    return _Surface(hit=is_hit & entered, escaped=live & (hit.status != HIT) & (hit.status != STEP_CAP),
                    stopped=live & ((hit.status == STEP_CAP) | (is_hit & ~entered)),
                    point=point, normal=n, index=jnp.maximum(hit.index, 0))


def _lookup(table, index):
    """Rows of a [1 or V, 3] per-primitive table (a single row is a constant)."""
    return table[jnp.minimum(index, table.shape[0] - 1)]


def _mis(a, b):
    """Power-heuristic weight [N] of a sample drawn with density `a` against a strategy of density `b`."""
    return jnp.where(a > 0, a * a / jnp.maximum(a * a + b * b, 1e-30), 0.0)


def _env_light(env: Environment, surf: _Surface, u, last):
    """The environment sample at each hit that the path leaves by a bounce.

    Returns (directions [N, 3] float32, zero where there is none, and their pdf [N]).
    """
    d, pdf = env.sample(u)
    use = surf.hit & ~last & (jnp.sum(surf.normal * d, -1) > 0) & (pdf > 0)
    return jnp.where(use[:, None], d, 0.0), jnp.where(use, pdf, 0.0)


def _shade(path: _Path, surf: _Surface, sun_visible, u, *, rho, emitted, env: Environment, first: bool,
           last, light=None) -> _Path:
    """One path vertex: gathers emission, escape, the sun and the environment sample;
    samples the next direction.

    ``rho`` and ``emitted`` are the [N, 3] albedo and emission at the hits, ``u`` [N, 2]
    uniforms, ``sun_visible`` [N] float32 whether the shadow ray escaped; ``light`` is
    (directions, pdf, visible) of the environment samples when ``env.sampled``.
    """
    live = jnp.any(path.direction != 0, axis=-1)
    sky = (env.camera_radiance if first else env.radiance)(path.direction)
    if env.sampled and not first:
        sky = sky * _mis(path.pdf, env.pdf(path.direction))[:, None]
    radiance = path.radiance + jnp.where(surf.escaped[:, None], path.throughput * sky, 0.0)
    gathered = emitted
    if env.sun:
        cos = jnp.maximum(jnp.sum(surf.normal * env.sun_direction, -1), 0.0)
        sun = rho / jnp.pi * env.sun_irradiance * (cos * sun_visible)[:, None]
        gathered = gathered + sun
    if env.sampled:
        d, pdf, visible = light
        cos = jnp.sum(surf.normal * d, -1)  # > 0 where pdf > 0
        weight = _mis(pdf, cos / jnp.pi) / jnp.where(pdf > 0, pdf, 1.0) * cos * visible
        gathered = gathered + rho / jnp.pi * env.radiance(d) * weight[:, None]
    radiance = radiance + jnp.where(surf.hit[:, None], path.throughput * gathered, 0.0)
    go_on = surf.hit & ~last & live
    normal = jnp.where(surf.hit[:, None], surf.normal, jnp.array([0.0, 0.0, 1.0]))
    direction = jnp.where(go_on[:, None], _cosine_direction(normal, u), 0.0)
    return _Path(origin=jnp.where(go_on[:, None], surf.point, path.origin), direction=direction,
                 throughput=path.throughput * jnp.where(go_on[:, None], rho, 1.0), radiance=radiance,
                 stopped=path.stopped | surf.stopped, pdf=jnp.sum(normal * direction, -1) / jnp.pi)


def _uniforms(keys, stream: int, n: int):
    """[N, n] float32 uniforms, one draw per path key for the given stream number."""
    return jax.vmap(lambda k: jax.random.uniform(jax.random.fold_in(k, stream), (n,)))(keys)


def _camera_path(camera, key, ids, *, width: int, height: int) -> tuple[_Path, jax.Array]:
    """Jittered camera rays for global pixel-sample ids [N]; returns (path, per-path keys)."""
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(ids)
    u = _uniforms(keys, 0, 2)
    pixel = ids % (width * height)
    px = (pixel % width).astype(jnp.float32) + u[:, 0]
    py = (pixel // width).astype(jnp.float32) + u[:, 1]
    d = _camera_rays(camera, px, py, width=width, height=height)
    zeros = jnp.zeros_like(d)
    path = _Path(origin=jnp.broadcast_to(camera[0], d.shape), direction=d, throughput=jnp.ones_like(d),
                 radiance=zeros, stopped=jnp.zeros(d.shape[0], bool), pdf=jnp.zeros(d.shape[0], jnp.float32))
    return path, keys


@functools.partial(jax.jit, static_argnames=("width", "height", "batch", "max_steps", "lanes"))
def _render_batch(tree, albedo, emission, env, camera, key, start, total, bounces, image, stopped, *, width,
                  height, batch, max_steps, lanes):
    """Traces pixel samples ``start .. start + batch`` (those below `total`) and adds them to `image`."""
    ids = start + jnp.arange(batch, dtype=jnp.int32)
    valid = ids < total
    path, keys = _camera_path(camera, key, jnp.where(valid, ids, 0), width=width, height=height)
    path = path._replace(direction=jnp.where(valid[:, None], path.direction, 0.0))
    go = functools.partial(trace, tree, method="esvo", max_steps=max_steps, lanes=lanes, shard=False)

    def segment(k, path, first):
        surf = _voxel_surface(tree, path.origin, path.direction, go(path.origin, path.direction))
        visible = jnp.zeros(batch, jnp.float32)
        if env.sun:
            towards = jnp.where((surf.hit & (jnp.sum(surf.normal * env.sun_direction, -1) > 0))[:, None],
                                env.sun_direction, 0.0)
            visible = (go(surf.point, towards).status != HIT).astype(jnp.float32)
        light = None
        if env.sampled:
            d, pdf = _env_light(env, surf, _uniforms(keys, _LIGHT_STREAM + k, 3), k >= bounces)
            light = (d, pdf, (go(surf.point, d).status != HIT).astype(jnp.float32))
        return _shade(path, surf, visible, _uniforms(keys, k + 1, 2), rho=_lookup(albedo, surf.index),
                      emitted=_lookup(emission, surf.index), env=env, first=first, last=k >= bounces, light=light)

    path = segment(0, path, True)
    path = jax.lax.fori_loop(1, bounces + 1, lambda k, p: segment(k, p, False), path)
    pixel = jnp.where(valid, ids % (width * height), width * height)
    image = image.at[pixel].add(path.radiance, mode="drop")
    return image, stopped + jnp.sum(path.stopped & valid).astype(jnp.int32)


@functools.partial(jax.jit, static_argnames=("width", "height", "max_steps", "lanes"))
def _aovs(tree, camera, *, width, height, max_steps, lanes):
    """Depth [H, W] and normal [H, W, 3] of the first voxel through each pixel centre."""
    j, i = jnp.meshgrid(jnp.arange(width), jnp.arange(height))
    d = _camera_rays(camera, j.reshape(-1) + 0.5, i.reshape(-1) + 0.5, width=width, height=height)
    hit = trace(tree, jnp.broadcast_to(camera[0], d.shape), d, max_steps=max_steps, lanes=lanes, shard=False)
    is_hit = (hit.status == HIT)[:, None]
    depth = jnp.where(is_hit[:, 0], hit.t, jnp.inf).reshape(height, width)
    return depth, jnp.where(is_hit, hit.normal, 0.0).reshape(height, width, 3)


def _table(what: str, value, rows: int, per: str, default) -> jax.Array:
    """A [1 or rows, 3] float32 table from None, an RGB triple or an array with a row `per`
    voxel or face; errors name `what`."""
    expected = f"must be an RGB triple or a [{per}s, 3] array with at least {rows} rows"
    try:
        a = np.asarray(default if value is None else value, np.float32)
    except (TypeError, ValueError):
        raise refuse(what, expected, value) from None
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] < 3 or not (a.shape[0] == 1 or a.shape[0] >= rows):
        raise refuse(what, expected, f"shape {np.shape(value)}")
    a = a[:, :3]
    bad = ~(np.isfinite(a) & (a >= 0))
    if bad.any():
        raise refuse(what, "must be finite and non-negative", a[bad][0])
    return jnp.asarray(a)


def _check_settings(caller: str, width, height, spp, bounces, batch_rays) -> None:
    for name, value, low in (("width", width, 1), ("height", height, 1), ("spp", spp, 1), ("bounces", bounces, 0),
                             ("batch_rays", batch_rays, 1)):
        check_int(f"{caller} {name}", value, minimum=low)
    if width * height * spp >= 2**31:
        raise refuse(f"{caller} width x height x spp", "must be below 2^31 samples; render fewer",
                     f"{width}x{height} at {spp} spp")


def _as_key(key):
    if isinstance(key, (int, np.integer)):
        return jax.random.key(int(key))
    key = jnp.asarray(key)
    return key if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else jax.random.wrap_key_data(key)


def _camera(caller: str, eye, target, up, fov):
    """The checked camera (eye, target, up [3], fov []) as float32 device arrays."""
    return tuple(jnp.asarray(v, jnp.float32) for v in check_view(caller, eye, target, up, fov))


def _progress(total: int, progress: bool | None, what: str):
    from tqdm.auto import tqdm

    disable = (not sys.stderr.isatty()) if progress is None else not progress
    return tqdm(total=total, desc=what, unit="batch", disable=disable, leave=False)


def render(tree: Octree, eye, target, *, env: Environment | None = None, albedo=None, emission=None,
           width: int = 320, height: int = 240, fov: float = 40.0, up=(0.0, 1.0, 0.0), spp: int = 16,
           bounces: int = 8, key=0, batch_rays: int = 1 << 18, max_steps: int | None = None,
           lanes: int | None = 16384, progress: bool | None = None) -> RenderResult:
    """Path-traces an image of a voxel octree or DAG (see the module docstring).

    Args:
      tree: an `Octree` (SVO or DAG).
      eye, target: [3] camera position and the point it looks at (see `look_at_view`).
      env: the lighting, an `Environment` (default `sky_environment()`).
      albedo: diffuse reflectance in [0, 1], linear: an RGB triple for every voxel, or a
        [V, 3] array (V >= ``voxel_count``) indexed by Morton-order voxel index, e.g.
        `voxel_albedo` of `voxel_attributes`. Default 0.7 grey.
      emission: emitted radiance, linear: None (nothing emits), an RGB triple, or a
        [V, 3] per-voxel array.
      width, height: image size in pixels.
      fov: vertical field of view in degrees; up: approximate up direction [3].
      spp: samples (paths) per pixel.
      bounces: diffuse bounces after the first hit (the slides use 8).
      key: an int seed or a `jax.random` key; the same key and settings give the same image.
      batch_rays: pixel samples traced per batch (memory grows with it); the last batch
        is padded. Static, as is the image size: changing them recompiles (``spp``,
        ``bounces``, the camera, the key and the lighting's arrays do not).
      max_steps, lanes: passed to `trace` for every ray.
      progress: show a progress bar over batches; None shows one on a terminal only.

    Returns:
      A `RenderResult` with [H, W] images.

    Raises:
      JaxvoxError: not an `Octree` or `Environment`, bad settings, camera, albedo or
        emission, `max_steps` or `lanes` not integers >= 1, or a truncated tree.
    """
    check_type("render tree", tree, Octree)
    _check_settings("render", width, height, spp, bounces, batch_rays)
    if int(tree.overflow):
        raise JaxvoxError(f"cannot render a truncated tree (overflow flags {int(tree.overflow)})")
    env = sky_environment() if env is None else check_type("render env", env, Environment)
    rows = int(tree.voxel_count)
    albedo = _table("render albedo", albedo, rows, "voxel", (0.7, 0.7, 0.7))
    emission = _table("render emission", emission, rows, "voxel", (0.0, 0.0, 0.0))
    camera = _camera("render", eye, target, up, fov)
    steps = (check_int("render max_steps", max_steps, minimum=1) if max_steps is not None
             else 6 * tree.grid.resolution + 16 * tree.depth)
    if lanes is not None:
        lanes = check_int("render lanes", lanes, minimum=1)
    key = _as_key(key)
    total = width * height * spp
    batch = min(int(batch_rays), total)
    image = jnp.zeros((width * height, 3), jnp.float32)
    stopped = jnp.zeros((), jnp.int32)
    n_batches = -(-total // batch)
    with _progress(n_batches, progress, "render") as bar:
        for b in range(n_batches):
            image, stopped = _render_batch(tree, albedo, emission, env, camera, key, jnp.int32(b * batch),
                                           jnp.int32(total), jnp.int32(bounces), image, stopped, width=width,
                                           height=height, batch=batch, max_steps=steps, lanes=lanes)
            bar.update(1)
    depth, normal = _aovs(tree, camera, width=width, height=height, max_steps=steps, lanes=lanes)
    return RenderResult(radiance=(image / spp).reshape(height, width, 3), depth=depth, normal=normal,
                        stopped=stopped)


def _embree(mesh):
    """An Embree intersector of `mesh`: (o [N, 3], d [N, 3]) -> (t, prim, u, v, unit Ng), numpy."""
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        raise JaxvoxError("render_mesh needs Embree: pip install 'jaxvox[bench]' (embreex)") from None
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.asarray(mesh.vertices, np.float32)[np.asarray(mesh.faces)])

    def intersect(o, d):
        out = scene.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32), output=1)
        ng = out["Ng"]
        length = np.linalg.norm(ng, axis=-1, keepdims=True)
        return out["tfar"], out["primID"], out["u"], out["v"], ng / np.where(length > 0, length, 1.0)

    return intersect


@functools.partial(jax.jit, static_argnames=("width", "height"))
def _mesh_camera(camera, key, ids, valid, *, width, height):
    path, keys = _camera_path(camera, key, jnp.where(valid, ids, 0), width=width, height=height)
    return path._replace(direction=jnp.where(valid[:, None], path.direction, 0.0)), keys


@functools.partial(jax.jit, static_argnames=("first",))
def _mesh_shade(path, surf, visible, light, keys, k, rho, emitted, env, last, *, first):
    return _shade(path, surf, visible, _uniforms(keys, k + 1, 2), rho=rho, emitted=emitted, env=env, first=first,
                  last=last, light=light)


@jax.jit
def _mesh_light(env, surf, keys, k, last):
    return _env_light(env, surf, _uniforms(keys, _LIGHT_STREAM + k, 3), last)


def _mesh_tables(mesh, albedo, emission):
    """(albedo, per-vertex flag, emission) for `render_mesh`: [F, 3] per-face tables, or
    None and True for the mesh's own colours (interpolated at each hit)."""
    faces = mesh.num_faces
    if isinstance(albedo, str):
        if albedo != "mesh":
            raise refuse("render_mesh albedo", "must be an RGB triple, a [faces, 3] array or 'mesh'", albedo)
        if mesh.colors is None and mesh.texture is None:
            raise refuse("render_mesh albedo", "'mesh' needs a texture or vertex colours, but the mesh has "
                         "neither a texture nor vertex colours", albedo)
        rho, per_vertex = None, True
    else:
        rho, per_vertex = np.asarray(_table("render_mesh albedo", albedo, faces, "face", (0.7, 0.7, 0.7))), False
    return rho, per_vertex, np.asarray(_table("render_mesh emission", emission, faces, "face", (0.0, 0.0, 0.0)))


def _mesh_colour(mesh, face, weights):
    """Linear albedo [N, 3] of a mesh's texture (or vertex colours) at barycentric `weights` [N, 3] of `face` [N]."""
    from jaxvox.image import srgb_to_linear

    corners = np.asarray(mesh.faces)[face]
    if mesh.texture is not None:
        uv = np.einsum("nk,nkd->nd", weights, np.asarray(mesh.uvs)[corners])
        colour = np.asarray(sample_texture(mesh.texture, jnp.asarray(uv, jnp.float32)))
    else:
        colour = np.einsum("nk,nkd->nd", weights, np.asarray(mesh.colors)[corners])
    return srgb_to_linear(colour[:, :3]).astype(np.float32)


def render_mesh(mesh, eye, target, *, env: Environment | None = None, albedo=None, emission=None,
                width: int = 320, height: int = 240, fov: float = 40.0, up=(0.0, 1.0, 0.0), spp: int = 16,
                bounces: int = 8, key=0, batch_rays: int = 1 << 18, progress: bool | None = None) -> RenderResult:
    """Path-traces a triangle mesh with Embree: `render`'s estimator on the exact surface.

    Needs embreex (the ``bench`` extra). The shading, the lighting and the random
    numbers are `render`'s (the same key gives the same camera rays and bounce samples),
    so a voxel render and a mesh render differ only by the geometry. Surfaces are
    two-sided Lambertian with the geometric triangle normal; bounce origins move off the
    surface by ``1e-4`` of the mesh's extent. Embree runs on the host, one call per path
    segment, so this is not jittable.

    Args:
      mesh: a `Mesh`.
      albedo: an RGB triple, a [F, 3] per-face array, or ``"mesh"``: the mesh's texture
        or else its vertex colours (sRGB, decoded to linear) at the hit, as
        `voxel_attributes` takes them for voxels. Default 0.7 grey.
      emission: None, an RGB triple or a [F, 3] per-face array.
      eye, target, env, width, height, fov, up, spp, bounces, key, batch_rays, progress:
        as in `render`.

    Returns:
      A `RenderResult`; ``depth`` and ``normal`` are those of the triangles (normals face
      the camera).

    Raises:
      JaxvoxError: a malformed mesh, not an `Environment`, bad settings, camera, albedo
        or emission, or no Embree.
    """
    validate_mesh(mesh)
    _check_settings("render_mesh", width, height, spp, bounces, batch_rays)
    env = sky_environment() if env is None else check_type("render_mesh env", env, Environment)
    rho_table, per_vertex, emit_table = _mesh_tables(mesh, albedo, emission)
    vertices = np.asarray(mesh.vertices, np.float64)
    eps = 1e-4 * float(np.max(vertices.max(0) - vertices.min(0))) if len(vertices) else 1e-4
    intersect = _embree(mesh)
    camera = _camera("render_mesh", eye, target, up, fov)
    key = _as_key(key)
    total = width * height * spp
    batch = min(int(batch_rays), total)
    image = np.zeros((width * height, 3), np.float64)
    sun = np.asarray(env.sun_direction)

    def surface(o, d):
        live = (d != 0).any(-1)
        n = len(o)
        t, prim, u, v, ng = (np.full(n, np.inf, np.float32), np.full(n, -1, np.int32), np.zeros(n, np.float32),
                             np.zeros(n, np.float32), np.zeros((n, 3), np.float32))
        if live.any():
            t[live], prim[live], u[live], v[live], ng[live] = intersect(o[live], d[live])
        hit = prim >= 0
        ng = np.where((np.sum(ng * d, -1) > 0)[:, None], -ng, ng)
        point = np.where(hit[:, None], o + np.where(hit, t, 0)[:, None] * d + eps * ng, o).astype(np.float32)
        face = np.maximum(prim, 0)
        if per_vertex:
            rho = _mesh_colour(mesh, face, np.stack([1 - u - v, u, v], -1))
        else:
            rho = rho_table[np.minimum(face, len(rho_table) - 1)]
        emitted = emit_table[np.minimum(face, len(emit_table) - 1)]
        surf = _Surface(hit=hit, escaped=live & ~hit, stopped=np.zeros(n, bool), point=point, normal=ng,
                        index=face)
        return surf, t, rho.astype(np.float32), emitted

    n_batches = -(-total // batch)
    with _progress(n_batches, progress, "render mesh") as bar:
        for b in range(n_batches):
            ids = np.int32(b * batch) + np.arange(batch, dtype=np.int32)
            valid = ids < total
            path, keys = _mesh_camera(camera, key, jnp.asarray(ids), jnp.asarray(valid), width=width, height=height)
            for k in range(bounces + 1):
                o, d = np.asarray(path.origin), np.asarray(path.direction)
                if not (d != 0).any():
                    break
                surf, _, rho, emitted = surface(o, d)
                visible = np.zeros(batch, np.float32)
                if env.sun:
                    lit = surf.hit & (np.sum(surf.normal * sun, -1) > 0)
                    if lit.any():
                        _, prim, _, _, _ = intersect(surf.point[lit], np.broadcast_to(sun, (int(lit.sum()), 3)))
                        visible[lit] = prim < 0
                surf = jax.tree.map(jnp.asarray, surf)
                light = None
                if env.sampled:
                    d, pdf = (np.asarray(a) for a in _mesh_light(env, surf, keys, k, jnp.asarray(k >= bounces)))
                    seen = np.zeros(batch, np.float32)
                    use = pdf > 0
                    if use.any():
                        seen[use] = intersect(np.asarray(surf.point)[use], d[use])[1] < 0
                    light = (jnp.asarray(d), jnp.asarray(pdf), jnp.asarray(seen))
                path = _mesh_shade(path, surf, jnp.asarray(visible), light, keys, k, jnp.asarray(rho),
                                   jnp.asarray(emitted), env, jnp.asarray(k >= bounces), first=k == 0)
            np.add.at(image, ids[valid] % (width * height), np.asarray(path.radiance, np.float64)[valid])
            bar.update(1)
    j, i = np.meshgrid(np.arange(width), np.arange(height))
    d = np.asarray(_camera_rays(camera, jnp.asarray(j.reshape(-1) + 0.5, jnp.float32),
                                jnp.asarray(i.reshape(-1) + 0.5, jnp.float32), width=width, height=height))
    surf, t, _, _ = surface(np.broadcast_to(np.asarray(camera[0]), d.shape).astype(np.float32), d)
    depth = np.where(surf.hit, t, np.inf).astype(np.float32).reshape(height, width)
    normal = np.where(surf.hit[:, None], surf.normal, 0.0).astype(np.float32).reshape(height, width, 3)
    return RenderResult(radiance=jnp.asarray((image / spp).astype(np.float32).reshape(height, width, 3)),
                        depth=jnp.asarray(depth), normal=jnp.asarray(normal), stopped=jnp.int32(0))


def box_emission(vox, lo, hi, rgb) -> jax.Array:
    """Per-voxel emission: `rgb` for the voxels whose centres lie in a world-space box.

    Args:
      vox: `Voxels` in Morton order (from `jaxvox.voxelize`, or `jaxvox.expand` of a tree).
      lo, hi: [3] box corners in world units (inclusive).
      rgb: [3] (or a scalar) linear emitted radiance.

    Returns:
      [capacity, 3] float32 for `render`'s ``emission`` (zero outside the box and in
      unused slots); add several for several boxes.

    Raises:
      JaxvoxError: not `Voxels`, corners that are not three finite numbers, or `rgb` not
        finite non-negative radiance.
    """
    check_type("box_emission vox", vox, Voxels)
    lo, hi = check_vector("box_emission lo", lo, 3), check_vector("box_emission hi", hi, 3)
    rgb = _rgb(rgb, "box_emission rgb")
    centre = vox.grid.origin + (vox.coords.astype(jnp.float32) + 0.5) * vox.grid.voxel_size
    inside = jnp.all((centre >= jnp.asarray(lo, jnp.float32)) & (centre <= jnp.asarray(hi, jnp.float32)), axis=-1)
    inside = inside & (jnp.arange(vox.coords.shape[0]) < vox.count)
    return jnp.where(inside[:, None], jnp.asarray(rgb), 0.0)


def voxel_albedo(attributes: dict, *, default=(0.7, 0.7, 0.7), srgb: bool = True) -> jax.Array:
    """Per-voxel linear albedo from `voxel_attributes` (or `load_attributes`) output.

    Args:
      attributes: dict with an optional ``"color"`` [V, 3 or 4] array in [0, 1].
      default: RGB in [0, 1] used when there are no colours (a material colour).
      srgb: the colours are sRGB-encoded (vertex colours usually are): decode to linear.

    Returns:
      [V, 3] float32 (or [1, 3] when there are no colours), for `render`'s ``albedo``.

    Raises:
      JaxvoxError: `attributes` not a dict, colours that are not [V, 3 or 4] numbers, or
        a default outside [0, 1].
    """
    from jaxvox.image import srgb_to_linear

    if attributes is not None and not isinstance(attributes, Mapping):
        raise refuse("voxel_albedo attributes", "expected a dict of arrays", type(attributes))
    color = attributes.get("color") if attributes else None
    if color is None:
        rgb = _rgb(default, "voxel_albedo default")
        if (rgb > 1).any():
            raise refuse("voxel_albedo default", "an albedo must lie in [0, 1]", default)
        return jnp.asarray(rgb[None])
    try:
        c = np.asarray(color, np.float32)
    except (TypeError, ValueError):
        raise refuse("voxel_albedo attributes['color']", "must be a [V, 3] or [V, 4] array", color) from None
    if c.ndim != 2 or c.shape[1] not in (3, 4):
        raise refuse("voxel_albedo attributes['color']", "must be a [V, 3] or [V, 4] array", c.shape)
    c = c[:, :3]
    return jnp.asarray((srgb_to_linear(c) if srgb else np.clip(c, 0.0, 1.0)).astype(np.float32))


def save_render(path: str | os.PathLike, result: RenderResult, *, exposure: float = 0.0,
                curve: str = "aces", far: float = float("inf")) -> tuple[str, str]:
    """Writes a render as a linear EXR at `path` and a tone-mapped sRGB PNG beside it.

    The EXR holds float32 channels ``R, G, B`` (linear radiance, the environment
    included: not premultiplied), ``Z`` (depth: the distance from the eye to the surface
    seen through the pixel centre, ``far`` where that ray escapes), ``A`` (coverage: 1
    where the pixel centre sees a surface, 0 where it sees the environment; use it to
    mask ``Z`` and the normals or to composite) and ``N.X, N.Y, N.Z`` (unit normal, 0
    where the ray escapes). The PNG has the same name with the suffix ``.png``.

    Args:
      path: the ``.exr`` file to write.
      result: a `RenderResult` from `render` or `render_mesh`.
      exposure: stops applied before tone mapping the PNG (the EXR stays linear).
      curve: the PNG's tone curve, one of `jaxvox.image.TONEMAP_CURVES`.
      far: the depth written where the ray escapes; ``inf`` by default (legal in EXR,
        and what `RenderResult.depth` holds), or a finite value for tools that expect one.

    Returns:
      (exr path, png path).
    """
    from jaxvox.image import tonemap, write_exr, write_png

    path = check_output_path("save_render path", path)
    far = check_number("save_render far", far, above=0.0, finite=False)
    check_number("save_render exposure", exposure)
    check_type("save_render result", result, RenderResult)
    rgb, depth, normal = (np.asarray(a) for a in (result.radiance, result.depth, result.normal))
    covered = np.isfinite(depth)
    channels = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "Z": np.where(covered, depth, far),
                "A": covered.astype(np.float32), "N.X": normal[..., 0], "N.Y": normal[..., 1], "N.Z": normal[..., 2]}
    png = os.path.splitext(path)[0] + ".png"
    write_exr(path, channels)
    write_png(png, tonemap(rgb, exposure=exposure, curve=curve))
    return path, png
