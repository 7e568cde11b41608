"""Files in and out (`jaxvox.io`): meshes, voxels, trees and images.

* `meshes`: `load_mesh` (any format trimesh reads) and `save_mesh` (PLY, OBJ);
* `voxels`: `save_voxels`, `load_voxels`, `save_binvox`, `load_binvox` (binvox, npz,
  and the voxels' surface as PLY or OBJ);
* `tree`: `save`, `load`, `load_attributes`: the octree and DAG file format (``.jvx``);
* `images`: `write_exr`, `read_exr` (OpenEXR), `read_hdr` (Radiance), `tonemap`,
  `write_png`;
* `files`: the file reading shared by the formats.

The same names are also importable from `jaxvox`. A render is written by
`jaxvox.save_render` (in `jaxvox.render.output`), which uses `images`.
"""

from jaxvox.io.images import TONEMAP_CURVES, read_exr, read_hdr, tonemap, write_exr, write_png
from jaxvox.io.meshes import MESH_SAVE_FORMATS, load_mesh, save_mesh
from jaxvox.io.tree import load, load_attributes, save
from jaxvox.io.voxels import LOAD_FORMATS, SAVE_FORMATS, load_binvox, load_voxels, save_binvox, save_voxels

__all__ = [
    "LOAD_FORMATS",
    "MESH_SAVE_FORMATS",
    "SAVE_FORMATS",
    "TONEMAP_CURVES",
    "load",
    "load_attributes",
    "load_binvox",
    "load_mesh",
    "load_voxels",
    "read_exr",
    "read_hdr",
    "save",
    "save_binvox",
    "save_mesh",
    "save_voxels",
    "tonemap",
    "write_exr",
    "write_png",
]
