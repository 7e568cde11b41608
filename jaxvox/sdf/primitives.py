"""SDF primitives: sphere, boxes, torus, capsule, cylinder and half space, all exact."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import is_concrete, refuse
from jaxvox._core.geometry import safe_norm
from jaxvox.sdf.base import SDF, node, param


def _axial(p, center):
    """Distance from the y axis through `center` and the height along it: ([...], [...])."""
    q = p - center
    return safe_norm(q[..., 0::2]), q[..., 1]


@node
class Sphere(SDF):
    """Sphere ``|p - center| - radius``. Exact."""

    radius: jax.Array  # [] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        return safe_norm(p - self.center) - self.radius


@node
class Box(SDF):
    """Axis-aligned box of half extents ``b``: ``|max(q, 0)| + min(max_i q_i, 0)``, ``q = |p - c| - b``. Exact."""

    half_extents: jax.Array  # [3] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        q = jnp.abs(p - self.center) - self.half_extents
        return safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q, axis=-1), 0.0)


@node
class RoundedBox(SDF):
    """Box of outer half extents ``b`` with edges rounded by ``radius`` (the box of half
    extents ``b - radius`` offset by ``radius``). Exact (offsetting a convex exact SDF is exact)."""

    half_extents: jax.Array  # [3] float32
    radius: jax.Array  # [] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        q = jnp.abs(p - self.center) - self.half_extents + self.radius
        inner = safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q, axis=-1), 0.0)
        return inner - self.radius


@node
class Torus(SDF):
    """Torus in the xz-plane around the y axis through `center`:
    ``|(|p.xz| - major_radius, p.y)| - minor_radius``. Exact."""

    major_radius: jax.Array  # [] float32
    minor_radius: jax.Array  # [] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        radial, height = _axial(p, self.center)
        return safe_norm(jnp.stack([radial - self.major_radius, height], axis=-1)) - self.minor_radius


@node
class Capsule(SDF):
    """Segment ``[a, b]`` thickened by `radius` (a sphere when a = b). Exact."""

    a: jax.Array  # [3] float32
    b: jax.Array  # [3] float32
    radius: jax.Array  # [] float32
    exact = True

    def _distance(self, p):
        pa, ba = p - self.a, self.b - self.a
        den = jnp.sum(ba * ba)
        den_ok = den > 0
        h = jnp.where(den_ok, jnp.sum(pa * ba, axis=-1) / jnp.where(den_ok, den, 1.0), 0.0)
        return safe_norm(pa - ba * jnp.clip(h, 0.0, 1.0)[..., None]) - self.radius


@node
class Cylinder(SDF):
    """Capped cylinder around the y axis through `center`, ``|y - c_y| <= half_height``. Exact."""

    radius: jax.Array  # [] float32
    half_height: jax.Array  # [] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        d = jnp.abs(jnp.stack(_axial(p, self.center), axis=-1)) - jnp.stack([self.radius, self.half_height])
        return jnp.minimum(jnp.max(d, axis=-1), 0.0) + safe_norm(jnp.maximum(d, 0.0))


@node
class Plane(SDF):
    """Half space ``n . p + offset <= 0`` (unit normal n points outside). Exact."""

    normal: jax.Array  # [3] float32, unit length
    offset: jax.Array  # [] float32
    exact = True

    def _distance(self, p):
        return jnp.sum(p * self.normal, axis=-1) + self.offset


def sphere(radius, *, center=(0.0, 0.0, 0.0)) -> Sphere:
    """Sphere of `radius` >= 0 (world units) around `center` [3]. Exact."""
    return Sphere(param(radius, "sphere radius", (), minimum=0.0), param(center, "sphere center", (3,)))


def box(half_extents, *, center=(0.0, 0.0, 0.0)) -> Box:
    """Axis-aligned box with `half_extents` [3] (or a scalar: a cube) >= 0 around `center`. Exact."""
    return Box(param(half_extents, "box half_extents", (3,), minimum=0.0), param(center, "box center", (3,)))


def rounded_box(half_extents, radius, *, center=(0.0, 0.0, 0.0)) -> RoundedBox:
    """Box with outer `half_extents` [3] and edges rounded by ``0 <= radius <= min(half_extents)``. Exact."""
    b = param(half_extents, "rounded_box half_extents", (3,), minimum=0.0)
    r = param(radius, "rounded_box radius", (), minimum=0.0)
    if is_concrete(b) and is_concrete(r) and float(r) > float(jnp.min(b)):
        raise refuse("rounded_box radius", f"must be <= the smallest half extent {float(jnp.min(b))}", float(r))
    return RoundedBox(b, r, param(center, "rounded_box center", (3,)))


def torus(major_radius, minor_radius, *, center=(0.0, 0.0, 0.0)) -> Torus:
    """Torus in the xz-plane (axis y): ring radius `major_radius`, tube radius `minor_radius`. Exact."""
    return Torus(
        param(major_radius, "torus major_radius", (), minimum=0.0),
        param(minor_radius, "torus minor_radius", (), minimum=0.0),
        param(center, "torus center", (3,)),
    )


def capsule(a, b, radius) -> Capsule:
    """Capsule: points within `radius` of the segment from `a` [3] to `b` [3]. Exact."""
    return Capsule(
        param(a, "capsule a", (3,)), param(b, "capsule b", (3,)), param(radius, "capsule radius", (), minimum=0.0)
    )


def cylinder(radius, half_height, *, center=(0.0, 0.0, 0.0)) -> Cylinder:
    """Capped cylinder, axis y, of `radius` and height ``2 * half_height`` around `center`. Exact."""
    return Cylinder(
        param(radius, "cylinder radius", (), minimum=0.0),
        param(half_height, "cylinder half_height", (), minimum=0.0),
        param(center, "cylinder center", (3,)),
    )


def plane(normal, *, offset=0.0) -> Plane:
    """Half space ``{p : n . p + offset <= 0}``, ``n = normal / |normal|``.

    The distance is ``n . p + offset``: positive on the side `normal` points to, so the
    plane passes through ``-offset * n``. Exact.
    """
    n = param(normal, "plane normal", (3,))
    if is_concrete(n) and not np.asarray(n).any():
        raise refuse("plane normal", "must be nonzero", n)
    return Plane(n / safe_norm(n), param(offset, "plane offset", ()))
