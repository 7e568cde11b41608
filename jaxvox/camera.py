"""Pinhole cameras: primary rays for tracing and rendering."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float32, Real

from jaxvox._core.checks import check_int, check_number, check_vector, is_concrete, refuse


def look_at_view(mesh_or_bounds, *, azimuth: float = 35.0, elevation: float = 25.0, distance: float = 2.2):
    """An eye and target framing a mesh (or ``(lo, hi)`` bounds): ``(eye [3], target [3])`` float32.

    The eye is ``distance`` times the box's largest extent away from the box centre, at
    the given azimuth about +y and elevation above the xz plane (degrees).

    Raises:
      JaxvoxError: bounds that are not two finite 3-vectors, a mesh without vertices or
        with non-finite ones, non-finite angles or a distance that is not > 0.
    """
    if isinstance(mesh_or_bounds, tuple) and len(mesh_or_bounds) == 2:
        lo, hi = (check_vector("look_at_view bounds", b, 3) for b in mesh_or_bounds)
    elif hasattr(mesh_or_bounds, "vertices"):
        v = np.asarray(mesh_or_bounds.vertices, np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or not len(v) or not np.isfinite(v).all():
            raise refuse(
                "look_at_view mesh", "needs [V, 3] vertices, V >= 1, all finite", v if v.size <= 12 else v.shape
            )
        lo, hi = v.min(0), v.max(0)
    else:
        raise refuse("look_at_view mesh_or_bounds", "expected a jaxvox.Mesh or (lo, hi) bounds", mesh_or_bounds)
    azimuth, elevation = (
        check_number(f"look_at_view {n}", a) for n, a in (("azimuth", azimuth), ("elevation", elevation))
    )
    distance = check_number("look_at_view distance", distance, above=0.0)
    centre, extent = (lo + hi) / 2, float(np.max(hi - lo))
    a, e = np.radians(azimuth), np.radians(elevation)
    offset = np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])
    with np.errstate(over="ignore"):
        eye, target = (centre + distance * extent * offset).astype(np.float32), centre.astype(np.float32)
    if not (np.isfinite(eye).all() and np.isfinite(target).all()):
        raise refuse("look_at_view distance", "puts the eye beyond float32 for these bounds", distance)
    return eye, target


def check_view(caller: str, eye, target, up, fov) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A camera's concrete ``(eye, target, up)`` as float64 [3] vectors and its field of view.

    Raises:
      JaxvoxError (naming `caller`): vectors that are not three finite numbers, a target
        equal to the eye, an ``up`` parallel to the view direction, a field of view
        outside (0, 180) degrees.
    """
    e, t = check_vector(f"{caller} eye", eye, 3), check_vector(f"{caller} target", target, 3)
    u = check_vector(f"{caller} up", up, 3)
    fov = check_number(f"{caller} fov", fov, above=0.0, below=180.0)
    # The camera's basis is computed in float32: the view vector and `up` must have a
    # float32 length that is finite, not denormal, and beyond the rounding of the positions.
    e32, t32, u32 = (a.astype(np.float32) for a in (e, t, u))
    forward = t32 - e32
    length = np.linalg.norm(forward)
    if not (np.isfinite(length) and length > max(1e-12, 1e-6 * float(np.abs([e32, t32]).max()))):
        raise refuse(f"{caller} target", "must differ from the eye by more than float32 rounding (1e-6 relative)", t)
    view = forward / length
    up_length = np.linalg.norm(u32)
    if not (np.isfinite(up_length) and up_length > 1e-12 and np.linalg.norm(np.cross(view, u32 / up_length)) > 1e-6):
        raise refuse(f"{caller} up", f"must not be zero or parallel to the view direction {view.round(6).tolist()}", u)
    return e, t, u, fov


def pinhole_rays(
    eye: Real[ArrayLike, 3] | Sequence[float],
    target: Real[ArrayLike, 3] | Sequence[float],
    *,
    width: int,
    height: int,
    fov: float = 40.0,
    up: Real[ArrayLike, 3] | Sequence[float] = (0.0, 1.0, 0.0),
) -> tuple[Float32[Array, "H W 3"], Float32[Array, "H W 3"]]:
    """Primary rays through pixel centres of a pinhole camera (jittable; sizes are static).

    Args:
      eye, target: [3] float32 camera position and the point it looks at.
      width, height: image size in pixels.
      fov: vertical field of view in degrees.
      up: [3] approximate up direction (must not be parallel to ``target - eye``).

    Returns:
      (origins, directions): [height, width, 3] float32 each; directions are unit
      length, row 0 is the top of the image.

    Raises:
      JaxvoxError: sizes that are not integers >= 1, a field of view outside (0, 180),
        and (for concrete values) non-finite or coincident eye and target, or an ``up``
        parallel to the view direction.
    """
    width, height = (
        check_int("pinhole_rays width", width, minimum=1),
        check_int("pinhole_rays height", height, minimum=1),
    )
    if all(is_concrete(x) for x in (eye, target, up)):
        check_view("pinhole_rays", eye, target, up, fov)
    as32 = lambda v: jnp.asarray(v, jnp.float32)
    return _pinhole(as32(eye), as32(target), as32(up), np.tan(np.radians(fov) / 2), width=width, height=height)


@functools.partial(jax.jit, static_argnames=("width", "height"))
def _pinhole(eye, target, up, tan_half_fov, *, width: int, height: int):
    """`pinhole_rays` as one program per image size (eagerly it would be a dozen)."""
    px = (jnp.arange(width) + 0.5)[None, :]
    py = (jnp.arange(height) + 0.5)[:, None]
    d = pixel_directions(eye, target, up, px, py, width=width, height=height, tan_half_fov=tan_half_fov)
    return jnp.broadcast_to(eye, d.shape), d


def camera_basis(eye, target, up):
    """The orthonormal basis of a pinhole camera: ``(forward, right, true_up)``, [3] float32 each.

    ``forward`` is the unit vector from `eye` to `target`, ``right`` the unit
    ``forward x up`` and ``true_up = right x forward``. Jittable, unchecked: `eye`,
    `target` and `up` are [3] float32 arrays that `check_view` accepts.
    """
    forward = target - eye
    forward = forward / jnp.linalg.norm(forward)
    right = jnp.cross(forward, up)
    right = right / jnp.linalg.norm(right)
    return forward, right, jnp.cross(right, forward)


def pixel_directions(eye, target, up, px, py, *, width: int, height: int, tan_half_fov):
    """Unit ray directions [..., 3] float32 through continuous pixel positions (jittable).

    Args:
      eye, target, up: [3] float32 camera, as in `camera_basis`.
      px, py: float32 arrays that broadcast together: positions in pixels, ``px`` to the
        right from the image's left edge, ``py`` down from its top edge; pixel centres
        are ``j + 0.5`` and ``i + 0.5``.
      width, height: image size in pixels.
      tan_half_fov: tangent of half the vertical field of view.

    Returns:
      [*broadcast(px, py), 3] float32 unit directions. `pinhole_rays` is this at pixel
      centres; the renderer jitters ``px`` and ``py`` within each pixel.
    """
    forward, right, true_up = camera_basis(eye, target, up)
    ys = (1 - 2 * py / height) * tan_half_fov
    xs = (2 * px / width - 1) * tan_half_fov * width / height
    d = forward + xs[..., None] * right + ys[..., None] * true_up
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)
