"""Per-voxel attributes (triangle id, normal, colour) from the triangles that set each
voxel, in Morton order, to be indexed by `voxel_index`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxvox._core.checks import check_type, refuse
from jaxvox._core.shapes import bucket
from jaxvox.mesh import Mesh, pad_mesh, sample_texture, validate_mesh
from jaxvox.voxelize import Voxels


def voxel_attributes(mesh: Mesh, vox: Voxels) -> dict[str, jax.Array]:
    """Per-voxel attributes from the triangle that set each voxel, in Morton order.

    Args:
      mesh: the mesh the voxels came from.
      vox: `Voxels` from ``jaxvox.voxelize(..., triangle_ids=True)``.

    Returns:
      A dict of arrays over the voxel buffer's slots (``[capacity, ...]``; slots past
      ``vox.count`` are zero or -1), to be indexed by `voxel_index`:

      * ``"triangle"``: int32 [capacity] triangle id (-1 in unused slots);
      * ``"normal"``: float32 [capacity, 3] unit face normal (0 for degenerate faces);
      * ``"color"``: float32 [capacity, C], only when the mesh has a texture or vertex
        colours: the texture (`sample_texture` at the interpolated texture coordinates)
        or the vertex colours, interpolated at the point of the triangle's plane nearest
        the voxel centre (barycentric weights clipped to the triangle).

    Raises:
      JaxvoxError: a malformed mesh, not `Voxels`, or voxels without triangle ids.
    """
    validate_mesh(mesh)
    check_type("voxel_attributes vox", vox, Voxels)
    if vox.triangle is None:
        raise refuse(
            "voxel_attributes vox.triangle", "must hold triangle ids (voxelize with triangle_ids=True)", vox.triangle
        )
    # Padded to the shape ladder, so that meshes of similar size share the program.
    return _attributes(pad_mesh(mesh, bucket(mesh.num_vertices), bucket(mesh.num_faces)), vox)


@jax.jit
def _attributes(mesh: Mesh, vox: Voxels) -> dict[str, jax.Array]:
    assert vox.triangle is not None  # checked by `voxel_attributes`
    valid = jnp.arange(vox.coords.shape[0]) < vox.count
    tri = jnp.where(valid, vox.triangle, 0)
    corners = mesh.vertices[mesh.faces[tri]]  # [C, 3, 3]
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    normal = jnp.cross(e1, e2)
    length = jnp.linalg.norm(normal, axis=-1, keepdims=True)
    unit = jnp.where(length > 0, normal / jnp.where(length > 0, length, 1.0), 0.0)
    out = {"triangle": jnp.where(valid, vox.triangle, -1), "normal": jnp.where(valid[:, None], unit, 0.0)}
    if mesh.texture is not None or mesh.colors is not None:
        centre = vox.grid.origin + (vox.coords.astype(jnp.float32) + 0.5) * vox.grid.voxel_size
        weights = _barycentric(corners, centre, normal)
        if mesh.texture is not None and mesh.uvs is not None:
            colour = sample_texture(mesh.texture, jnp.einsum("ck,ckd->cd", weights, mesh.uvs[mesh.faces[tri]]))
        elif mesh.colors is not None:
            colour = jnp.einsum("ck,ckd->cd", weights, mesh.colors[mesh.faces[tri]])
        out["color"] = jnp.where(valid[:, None], colour, 0.0)
    return out


def _barycentric(corners, point, normal):
    """Clipped barycentric weights [C, 3] of `point` projected onto each triangle's plane."""
    area2 = jnp.sum(normal * normal, axis=-1)
    safe = jnp.where(area2 > 0, area2, 1.0)
    sub = lambda a, b: jnp.sum(jnp.cross(corners[:, b] - point, corners[:, a] - point) * normal, -1)
    w = jnp.stack([sub(2, 1), sub(0, 2), sub(1, 0)], axis=-1) / safe[:, None]
    w = jnp.where(area2[:, None] > 0, jnp.clip(w, 0.0, None), 1.0)
    return w / jnp.sum(w, axis=-1, keepdims=True)
