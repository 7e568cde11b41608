"""Pinhole cameras: primary rays for tracing and rendering."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def look_at_view(mesh_or_bounds, *, azimuth: float = 35.0, elevation: float = 25.0,
                 distance: float = 2.2):
    """An eye and target framing a mesh (or ``(lo, hi)`` bounds): ``(eye [3], target [3])`` float32.

    The eye is ``distance`` times the box's largest extent away from the box centre, at
    the given azimuth about +y and elevation above the xz plane (degrees).
    """
    if isinstance(mesh_or_bounds, tuple):
        lo, hi = (np.asarray(b, np.float64) for b in mesh_or_bounds)
    else:
        v = np.asarray(mesh_or_bounds.vertices, np.float64)
        lo, hi = v.min(0), v.max(0)
    centre, extent = (lo + hi) / 2, float(np.max(hi - lo))
    a, e = np.radians(azimuth), np.radians(elevation)
    offset = np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])
    return (centre + distance * extent * offset).astype(np.float32), centre.astype(np.float32)


def pinhole_rays(eye, target, *, width: int, height: int, fov: float = 40.0, up=(0.0, 1.0, 0.0)):
    """Primary rays through pixel centres of a pinhole camera (jittable; sizes are static).

    Args:
      eye, target: [3] float32 camera position and the point it looks at.
      width, height: image size in pixels.
      fov: vertical field of view in degrees.
      up: [3] approximate up direction (must not be parallel to ``target - eye``).

    Returns:
      (origins, directions): [height, width, 3] float32 each; directions are unit
      length, row 0 is the top of the image.
    """
    eye, target = jnp.asarray(eye, jnp.float32), jnp.asarray(target, jnp.float32)
    forward = target - eye
    forward = forward / jnp.linalg.norm(forward)
    right = jnp.cross(forward, jnp.asarray(up, jnp.float32))
    right = right / jnp.linalg.norm(right)
    true_up = jnp.cross(right, forward)
    scale = np.tan(np.radians(fov) / 2)
    ys = (1 - 2 * (jnp.arange(height) + 0.5) / height) * scale
    xs = (2 * (jnp.arange(width) + 0.5) / width - 1) * scale * width / height
    d = forward + xs[None, :, None] * right + ys[:, None, None] * true_up
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    return jnp.broadcast_to(eye, d.shape), d
