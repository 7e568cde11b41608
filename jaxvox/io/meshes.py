"""Triangle mesh files: `load_mesh` (any format trimesh reads, with vertex colours and
textures) and `save_mesh` (binary PLY or OBJ)."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from jaxvox._core.checks import check_choice, check_output_path, refuse
from jaxvox.mesh import Mesh, validate_mesh


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Loads a triangle mesh from any file format trimesh can read.

    Scenes are flattened into one mesh; polygons are triangulated by trimesh. Vertex
    colours, when the file has them, become `Mesh.colors` (RGBA in [0, 1]); a colour
    texture (an OBJ material's ``map_Kd``, a glTF base colour texture) with texture
    coordinates becomes `Mesh.uvs` and `Mesh.texture`. Texture coordinates without an
    image are dropped.

    Args:
      path: file path (OBJ, PLY, STL, OFF, GLB, ...).

    Returns:
      A validated `Mesh` with float32 vertices and int32 faces.

    Raises:
      JaxvoxError: when the file is missing, unreadable, holds no triangles, or has
        non-finite vertices or out-of-range face indices.
    """
    import trimesh

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise refuse("load_mesh path", "is a directory" if os.path.isdir(path) else "file not found", path)
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise refuse("load_mesh path", f"cannot read the mesh ({type(exc).__name__}: {exc})", path) from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise refuse("load_mesh path", "holds no triangles", path)
    colors = uvs = texture = None
    visual: Any = loaded.visual  # ColorVisuals or TextureVisuals, told apart by `kind`
    kind = getattr(visual, "kind", None)
    if kind == "vertex":
        colors = np.asarray(visual.vertex_colors, np.float32) / 255.0
    elif kind == "texture" and visual.uv is not None:
        material = visual.material
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if image is not None:
            uvs = np.asarray(visual.uv, np.float32)
            texture = np.asarray(image.convert("RGBA"), np.float32) / 255.0
    mesh = Mesh(
        np.asarray(loaded.vertices, np.float32),
        np.asarray(loaded.faces, np.int32),
        colors=colors,
        uvs=uvs,
        texture=texture,
    )
    validate_mesh(mesh)
    return mesh


MESH_SAVE_FORMATS = (".ply", ".obj")  # extensions `save_mesh` writes


def file_format(what: str, path: str | os.PathLike, formats: tuple[str, ...]) -> str:
    """The lower-case extension of `path` (e.g. ``".ply"``) if it is one of `formats`; raises naming them."""
    return check_choice(f"{what} extension", os.path.splitext(os.fspath(path))[1].lower(), formats)


def save_mesh(path: str | os.PathLike, mesh: Mesh) -> None:
    """Writes a triangle mesh as binary little-endian PLY or Wavefront OBJ, chosen by the extension.

    Vertex positions (float32 in PLY, 8 decimals in OBJ) and faces are written as they
    are, with vertex colours (8-bit RGBA) where the mesh has them; no normals (a
    viewer computes flat ones from the counter-clockwise faces). Texture coordinates
    and a texture are not written. `load_mesh` reads both formats back.

    Args:
      path: destination file ending in one of `MESH_SAVE_FORMATS` (any case).
      mesh: a `Mesh`.

    Raises:
      JaxvoxError: an unknown extension, a missing folder or a malformed mesh.
    """
    import trimesh

    path = check_output_path("save_mesh path", path)
    ext = file_format("save_mesh path", path, MESH_SAVE_FORMATS)
    validate_mesh(mesh)
    colors = None if mesh.colors is None else np.round(np.asarray(mesh.colors) * 255).astype(np.uint8)
    out = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), vertex_colors=colors, process=False)
    if ext == ".ply":
        data = trimesh.exchange.ply.export_ply(out, encoding="binary", vertex_normal=False)
    else:
        data = trimesh.exchange.obj.export_obj(out, include_normals=False, include_texture=False).encode()
    with open(path, "wb") as fh:
        fh.write(data)
