"""Environment lights for the renderers: radiance from infinitely far away, and a sun.

An `Environment` is a lat-long radiance image (or a single pixel: a uniform colour), plus
a gradient sky and optionally a sun, a directional light of given irradiance. Build one
with `uniform_environment`, `sky_environment` (a procedural sky and sun) or
`load_environment` (an EXR, Radiance HDR or ``.npy`` lat-long image).

Importance sampling. For an image of more than one pixel, `Environment.cdf` holds the
cumulative probabilities of its pixels, proportional to luminance times the pixel's solid
angle; `Environment.sample` draws directions from it and `Environment.pdf` gives their
density. The integrator (`jaxvox.render.integrator`) then samples the image directly at
each bounce (next-event estimation) and combines that with the bounce rays that find it
by multiple importance sampling, so that a small bright region (a window, a sun in an
HDR map) is found by the sample that finds it best.
"""

from __future__ import annotations

import dataclasses
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_number, check_vector, refuse
from jaxvox._core.pytree import pytree_dataclass
from jaxvox.io.images import read_exr, read_hdr
from jaxvox.render.materials import check_rgb

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
        sky = jnp.where(
            y[..., None] >= 0,
            self.horizon + (self.zenith - self.horizon) * up,
            self.horizon + (self.ground - self.horizon) * below,
        )
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


def _image_cdf(image: np.ndarray) -> np.ndarray:
    """[H * W] float32 cumulative sums (float64, then rounded) of luminance x pixel solid angle."""
    h, w = image.shape[:2]
    luminance = image.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    edges = np.cos(np.pi * np.arange(h + 1) / h)
    return np.cumsum(luminance * (2 * np.pi / w * (edges[:-1] - edges[1:]))[:, None]).astype(np.float32)


def _environment(
    caller: str,
    image,
    *,
    scale=1.0,
    zenith=0.0,
    horizon=0.0,
    ground=0.0,
    sun_direction=(0.0, 1.0, 0.0),
    sun_irradiance=0.0,
    sun_cos=_SUN_COS,
    sun=False,
    importance=False,
) -> Environment:
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
    fields = dict(
        image=jnp.asarray(image),
        zenith=check_rgb(f"{caller} zenith", zenith),
        horizon=check_rgb(f"{caller} horizon", horizon),
        ground=check_rgb(f"{caller} ground", ground),
        sun_direction=(s / np.linalg.norm(s)).astype(np.float32),
        sun_irradiance=check_rgb(f"{caller} sun_irradiance", sun_irradiance),
        sun_cos=np.float32(sun_cos),
        cdf=_image_cdf(image),
        sun=bool(sun),
    )
    fields["sampled"] = bool(importance and image.shape[0] * image.shape[1] > 1 and fields["cdf"][-1] > 0)
    for name, value in fields.items():
        object.__setattr__(env, name, value if name in ("sun", "sampled") else jnp.asarray(value))
    return env


def uniform_environment(*, rgb=(1.0, 1.0, 1.0)) -> Environment:
    """The same radiance ``rgb`` ([3] or a scalar, linear) from every direction; no sun.

    Raises:
      JaxvoxError: `rgb` not one or three finite non-negative numbers.
    """
    return _environment("uniform_environment", check_rgb("uniform_environment rgb", rgb).reshape(1, 1, 3))


def sky_environment(
    *,
    sun_direction=(0.45, 0.75, 0.5),
    sun_irradiance=(2.2, 2.1, 1.9),
    zenith=(0.10, 0.20, 0.45),
    horizon=(0.45, 0.50, 0.58),
    ground=(0.12, 0.11, 0.10),
    sun_radius_degrees: float = 0.53,
) -> Environment:
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
    irradiance = check_rgb("sky_environment sun_irradiance", sun_irradiance)
    radius = check_number("sky_environment sun_radius_degrees", sun_radius_degrees, minimum=0.0, maximum=90.0)
    return _environment(
        "sky_environment",
        np.zeros((1, 1, 3), np.float32),
        zenith=zenith,
        horizon=horizon,
        ground=ground,
        sun_direction=sun_direction,
        sun_irradiance=irradiance,
        sun_cos=math.cos(math.radians(radius)),
        sun=bool(irradiance.any()),
    )


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
    path = os.fspath(path)
    scale = check_number("load_environment scale", scale, minimum=0.0)
    if not os.path.isfile(path):
        raise refuse(
            "load_environment path",
            "is a directory, expected a file" if os.path.isdir(path) else "file not found",
            path,
        )
    ext = os.path.splitext(path)[1].lower()
    if ext == ".exr":
        channels = read_exr(path)
        if all(c in channels for c in "RGB"):
            image = np.stack([channels[c] for c in "RGB"], axis=-1)
        elif "Y" in channels:
            image = np.repeat(channels["Y"][..., None], 3, axis=-1)
        else:
            raise refuse(
                "load_environment path",
                f"an environment EXR needs channels R, G, B (or Y), has {sorted(channels)}",
                path,
            )
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
