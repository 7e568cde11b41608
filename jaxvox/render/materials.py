"""Per-voxel and per-face materials for the renderers: albedo and emission tables.

`render` and `render_mesh` take an albedo and an emission as a [1 or V, 3] float32 table,
indexed by primitive (a voxel in Morton order, or a triangle); a single row is a
constant. `voxel_albedo` makes the albedo table from voxel colours, `box_emission` an
emission table that lights the voxels inside a box. `check_rgb` and `rgb_table` are the
checks the renderers and environments share.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_type, check_vector, refuse
from jaxvox._core.shapes import pad_rows, voxel_bucket
from jaxvox.io.images import srgb_to_linear
from jaxvox.voxelize import Voxels


def check_rgb(name: str, value) -> np.ndarray:
    """[3] float32 from an RGB triple or one number; refuses other shapes, negatives, NaN, inf."""
    try:
        v = np.broadcast_to(np.asarray(value, np.float32), (3,)).copy()
    except (TypeError, ValueError):
        raise refuse(name, "must be three finite non-negative numbers", value) from None
    if not np.isfinite(v).all() or (v < 0).any():
        raise refuse(name, "must be three finite non-negative numbers", value)
    return v


def rgb_table(what: str, value, rows: int, per: str, default, resolution: int | None = None) -> jax.Array | np.ndarray:
    """A [1 or n >= rows, 3] float32 table from None, an RGB triple or an array with a row
    `per` voxel or face; errors name `what`. With a grid `resolution` a per-voxel table is
    extended to the voxel-list ladder (`voxel_bucket`, see `_on_ladder`), so that its
    length is not a new key of a compiled program for every tree. A JAX array on the
    ladder is returned as it is; other values as a checked host array, for the caller to
    place on its devices."""
    expected = f"must be an RGB triple or a [{per}s, 3] array with at least {rows} rows"
    if _ready(value, rows, resolution, nonnegative=True):
        return value
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
    return _on_ladder(a, resolution if a.shape[0] > 1 else None)


def normal_table(what: str, value, rows: int, resolution: int) -> jax.Array | np.ndarray:
    """A [1 or n >= rows, 3] float32 table of per-voxel shading normals from None (one zero
    row: no shading normals) or a [V, 3] array of finite values, extended and returned like
    `rgb_table`'s."""
    if value is None:
        return np.zeros((1, 3), np.float32)
    if _ready(value, rows, resolution, nonnegative=False):
        return value
    try:
        a = np.asarray(value, np.float32)
    except (TypeError, ValueError):
        raise refuse(what, f"must be a [voxels, 3] array with at least {rows} rows", value) from None
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < rows:
        raise refuse(what, f"must be a [voxels, 3] array with at least {rows} rows", f"shape {np.shape(value)}")
    if not np.isfinite(a).all():
        raise refuse(what, "must be finite", a[~np.isfinite(a)][0])
    return _on_ladder(a, resolution)


def _ready(value, rows: int, resolution: int | None, *, nonnegative: bool) -> bool:
    """Whether `value` is a table the renderer takes as it is, with no copy: a float32
    [n, 3] JAX array, n >= `rows` on the voxel-list ladder of `resolution`, all finite
    (and non-negative). Other values take the host path, which also says what is wrong."""
    if resolution is None or not isinstance(value, jax.Array) or value.dtype != jnp.float32:
        return False
    if value.ndim != 2 or value.shape[1] != 3 or value.shape[0] < max(rows, 2):
        return False
    return value.shape[0] == voxel_bucket(value.shape[0], resolution) and bool(_valid(value, nonnegative))


@functools.partial(jax.jit, static_argnames="nonnegative")
def _valid(table, nonnegative):
    return jnp.all(jnp.isfinite(table) & ((table >= 0) | (not nonnegative)))


def _on_ladder(a: np.ndarray, resolution: int | None) -> np.ndarray:
    """The [n, 3] float32 host table `a`, with a grid `resolution` extended to the
    voxel-list ladder. Where `a` is the leading rows of a buffer that already holds that
    many (the attribute memmaps of `mesh_to_dag`, whose files are written to that length
    with zero rows), the buffer's rows are taken as they are; else zero rows are appended
    in a copy. Rows past `a`'s are never read (voxel indices stay below n). Placed on a CPU
    device (on all of them at once, see `render`), such a host table is not copied."""
    if resolution is None:
        return a
    rows = voxel_bucket(a.shape[0], resolution)
    base: object = a if a.flags.c_contiguous else None
    while isinstance(base, np.ndarray):
        if (
            base.dtype == a.dtype
            and base.shape[1:] == a.shape[1:]
            and base.shape[0] >= rows
            and base.flags.c_contiguous
            and base.ctypes.data == a.ctypes.data
        ):
            return base[:rows]
        base = base.base
    return pad_rows(a, rows)


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
    rgb = check_rgb("box_emission rgb", rgb)
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
    if attributes is not None and not isinstance(attributes, Mapping):
        raise refuse("voxel_albedo attributes", "expected a dict of arrays", type(attributes))
    color = attributes.get("color") if attributes else None
    if color is None:
        rgb = check_rgb("voxel_albedo default", default)
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
