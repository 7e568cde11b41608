"""Triangle meshes: the `Mesh` pytree, validation, padding and texture lookups.

Mesh files are read and written by `jaxvox.io.meshes` (`load_mesh`, `save_mesh`)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float32, Int32

from jaxvox._core.checks import is_concrete, refuse
from jaxvox._core.pytree import pytree_dataclass


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    All fields are array leaves (or None), so a `Mesh` can be passed through `jax.jit`
    and batched with `jax.vmap` (pad meshes to a common size with degenerate faces
    ``(0, 0, 0)``, which add at most the voxel holding vertex 0 in conservative mode;
    see `pad_mesh`).

    Attributes:
      vertices: [V, 3] float32 positions in world units.
      faces: [F, 3] int32 vertex indices, counter-clockwise seen from outside.
      colors: [V, C] float32 vertex colours in [0, 1] (C = 3 RGB or 4 RGBA), or None.
      uvs: [V, 2] float32 texture coordinates (OBJ convention: v = 0 is the image's
        bottom row; repeating outside [0, 1]), or None.
      texture: [H, W, C] float32 image in [0, 1] (row 0 on top, C = 3 or 4), or None;
        given together with `uvs`. Where present it is the surface colour (see
        `sample_texture`) and takes precedence over `colors`.
    """

    vertices: Float32[Array, "*batch V 3"]  # [V, 3] float32
    faces: Int32[Array, "*batch F 3"]  # [F, 3] int32
    colors: Float32[Array, "*batch V C"] | None = None  # [V, C] float32
    uvs: Float32[Array, "*batch V 2"] | None = None  # [V, 2] float32
    texture: Float32[Array, "*batch H W C"] | None = None  # [H, W, C] float32

    def __init__(self, vertices, faces, *, colors=None, uvs=None, texture=None):
        optional = lambda name, a: None if a is None else _numeric(f"Mesh {name}", a, jnp.float32)
        object.__setattr__(self, "vertices", _numeric("Mesh vertices", vertices, jnp.float32))
        object.__setattr__(self, "faces", _numeric("Mesh faces", faces, jnp.int32))
        object.__setattr__(self, "colors", optional("colors", colors))
        object.__setattr__(self, "uvs", optional("uvs", uvs))
        object.__setattr__(self, "texture", optional("texture", texture))

    @property
    def num_faces(self) -> int:
        """Number of triangles F."""
        return self.faces.shape[0]

    @property
    def num_vertices(self) -> int:
        """Number of vertices V."""
        return self.vertices.shape[0]

    def triangles(self) -> jax.Array:
        """Corner positions of every face: [F, 3 corners, 3 xyz] float32."""
        return self.vertices[self.faces]


def host_triangles(mesh: Mesh) -> np.ndarray:
    """Corner positions of every face on the host: [F, 3, 3] float64 (`Mesh.triangles`
    without a device program per mesh size)."""
    return np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)].reshape(-1, 3, 3)


def _numeric(what: str, value, dtype) -> jax.Array:
    """`value` as a `dtype` array; concrete values must be numbers, and integer-valued for int32."""
    if not is_concrete(value):
        return jnp.asarray(value, dtype)
    try:
        a = np.asarray(value)
        ok = a.dtype.kind in ("biu" if dtype == jnp.int32 else "biuf")
        ok = ok or (dtype == jnp.int32 and a.dtype.kind == "f")
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise refuse(what, f"must be an array of {'integers' if dtype == jnp.int32 else 'numbers'}", value)
    if dtype == jnp.int32 and a.dtype.kind == "f":
        whole = np.isfinite(a) & (a == np.round(a))
        if not whole.all():
            raise refuse(what, "must hold integer vertex indices", a[~whole].ravel()[0])
    if dtype == jnp.int32 and a.size and (a.min() < np.iinfo(np.int32).min or a.max() > np.iinfo(np.int32).max):
        raise refuse(what, "vertex indices must fit in int32", a.max() if a.max() > 0 else a.min())
    if dtype == jnp.float32 and a.dtype.kind == "f" and a.size:
        finite = a[np.isfinite(a)]
        if finite.size and np.abs(finite).max() > np.finfo(np.float32).max:
            raise refuse(what, "has values beyond float32's range", np.abs(finite).max())
    return jnp.asarray(a, dtype)


MAX_UV = 1e6  # texture coordinates beyond this repeat the texture more often than float32 can place a texel


def validate_mesh(mesh: Mesh) -> None:
    """Raises `JaxvoxError` naming the problem when `mesh` is malformed (host-side check).

    Checks shapes, that every vertex coordinate is finite, that every face index lies
    in ``[0, V)``, that colours (if any) are [V, 3] or [V, 4] in [0, 1], and that
    texture coordinates and a texture come together, [V, 2] within +-`MAX_UV` and [H, W, 3 or 4]
    in [0, 1]. (`Mesh` itself refuses non-numeric arrays and fractional face indices.)
    """
    if not isinstance(mesh, Mesh):
        raise refuse("mesh", "expected a jaxvox.Mesh", type(mesh))
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise refuse("Mesh vertices", "must have shape [V, 3]", v.shape)
    if f.ndim != 2 or f.shape[1] != 3:
        raise refuse("Mesh faces", "must have shape [F, 3]", f.shape)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise refuse("Mesh vertices", f"{int(bad.sum())} hold NaN or inf (first: vertex {first})", v[first])
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        bad_face = int(np.flatnonzero((f < 0).any(1) | (f >= len(v)).any(1))[0])
        raise refuse("Mesh faces", f"index out of range [0, {len(v)}) in face {bad_face}", f[bad_face])
    if mesh.colors is not None:
        c = np.asarray(mesh.colors)
        if c.ndim != 2 or c.shape[0] != len(v) or c.shape[1] not in (3, 4):
            raise refuse("Mesh colors", f"must have shape [V, 3] or [V, 4] with V = {len(v)}", c.shape)
        _unit_range("Mesh colors", c)
    if (mesh.uvs is None) != (mesh.texture is None):
        raise refuse(
            "Mesh texture",
            "needs both uvs [V, 2] and texture [H, W, C]",
            "only uvs" if mesh.texture is None else "only a texture",
        )
    if mesh.uvs is not None:
        uv, tex = np.asarray(mesh.uvs), np.asarray(mesh.texture)
        if uv.shape != (len(v), 2):
            raise refuse("Mesh uvs", f"must have shape [V, 2] with V = {len(v)}", uv.shape)
        bad = ~(np.abs(uv) <= MAX_UV).all(1)
        if bad.any():
            raise refuse(
                "Mesh uvs", f"must be finite and at most {MAX_UV:.0e} in magnitude (the texture repeats)", uv[bad][0]
            )
        if tex.ndim != 3 or min(tex.shape[:2]) < 1 or tex.shape[2] not in (3, 4):
            raise refuse("Mesh texture", "must have shape [H, W, 3] or [H, W, 4]", tex.shape)
        _unit_range("Mesh texture", tex)


def _unit_range(what: str, a: np.ndarray) -> None:
    """Raises unless every value of `a` lies in [0, 1] (NaN refused)."""
    bad = ~((a >= 0) & (a <= 1))
    if bad.any():
        raise refuse(what, "must lie in [0, 1]", a[bad].ravel()[0])


def sample_texture(texture: jax.Array, uv: jax.Array) -> jax.Array:
    """Bilinear texture lookup with repeat wrapping (jittable, vmappable).

    Args:
      texture: [H, W, C] float32, row 0 on top.
      uv: [..., 2] float32 texture coordinates; v = 0 is the bottom row (OBJ/glTF
        images are stored top row first, so v is flipped).

    Returns:
      [..., C] float32.
    """
    h, w = texture.shape[:2]
    x = uv[..., 0] * w - 0.5
    y = (1.0 - uv[..., 1]) * h - 0.5
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
    texel = lambda dy, dx: texture[jnp.mod(y0 + dy, h), jnp.mod(x0 + dx, w)]
    top = texel(0, 0) * (1 - fx) + texel(0, 1) * fx
    bottom = texel(1, 0) * (1 - fx) + texel(1, 1) * fx
    return top * (1 - fy) + bottom * fy


def pad_mesh(mesh: Mesh, num_vertices: int, num_faces: int) -> Mesh:
    """Pads a mesh to a fixed size so several meshes can be stacked for `jax.vmap`.

    Extra vertices repeat vertex 0 and extra faces are ``(0, 0, 0)``: a degenerate
    triangle at vertex 0. In 6-separating mode it adds nothing; in conservative mode it
    adds only voxels touching vertex 0, which its real faces already produce.
    """
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    if num_vertices < len(v) or num_faces < len(f):
        raise refuse(
            "pad_mesh num_vertices, num_faces",
            f"must be at least the mesh's ({len(v)}, {len(f)})",
            (num_vertices, num_faces),
        )
    repeat_first = lambda a: np.concatenate([a, np.repeat(a[:1], num_vertices - len(a), axis=0)])
    f_pad = np.concatenate([f, np.zeros((num_faces - len(f), 3), np.int32)])
    colors, uvs = (None if a is None else repeat_first(np.asarray(a)) for a in (mesh.colors, mesh.uvs))
    return Mesh(repeat_first(v), f_pad, colors=colors, uvs=uvs, texture=mesh.texture)
