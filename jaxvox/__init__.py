"""jaxvox: voxel geometry in JAX.

Exact conservative and 6-separating triangle voxelization, sparse voxel octrees and
DAGs with per-node prefix sums for voxel attributes, ray traversal of octrees, DAGs and
dense grids, dense distance fields (jump flooding, fast sweeping, solid voxelization and fast
winding numbers for the sign) and cascaded clipmaps, all with fixed-capacity jittable cores and host-side
APIs that size capacities by counting passes. Analytic signed distance function scenes
(primitives, transforms, CSG) are jittable pytrees (`jaxvox.sdf`), rendered by sphere
tracing and meshed by marching cubes. A diffuse path tracer (`jaxvox.render`) renders
voxel DAGs (textured or vertex-coloured, emissive) under an importance-sampled
environment light to EXR and PNG files.
"""

from jaxvox import morton, points, sdf
from jaxvox._errors import JaxvoxError
from jaxvox.batch import (
    BatchResult,
    batch_capacities,
    run_batch,
    stack_grids,
    stack_meshes,
    voxelize_build_trace,
)
from jaxvox.camera import look_at_view, pinhole_rays
from jaxvox.compilation_cache import enable_compilation_cache
from jaxvox.distance import (
    Clipmap,
    QuantizedField,
    build_clipmap,
    clipmap_corners,
    distance_field,
    distance_field_bytes,
    quantize_field,
    time_sliced_cascades,
    trace_clipmap,
    union_clipmaps,
    update_clipmap,
)
from jaxvox.field_mesh import field_to_mesh
from jaxvox.field_trace import sample_gradient, sphere_trace_field
from jaxvox.grid import Grid
from jaxvox.image import read_exr, read_hdr, save_render, tonemap, write_exr, write_png
from jaxvox.io import load, load_attributes, save
from jaxvox.mesh import Mesh, load_mesh, pad_mesh, sample_texture, save_mesh
from jaxvox.octree import (
    EMPTY,
    MISSING,
    OVERFLOW_NODES,
    CompactDag,
    Octree,
    build_dag,
    build_octree,
    compact,
    compact_dag,
    expand,
    mesh_to_dag,
    octree_capacities,
    voxel_attributes,
    voxel_index,
)
from jaxvox.overflow import Overflow
from jaxvox.points import (
    ClosestPoints,
    MeshIndex,
    PointQuery,
    PointStatus,
    closest_points,
    mesh_index,
    occupancy,
    query_points,
    signed_distance,
    stack_indices,
    winding_number,
)
from jaxvox.points.sample import SdfSamples, sample_meshes, sample_sdf
from jaxvox.render import (
    Environment,
    RenderResult,
    box_emission,
    load_environment,
    render,
    render_mesh,
    sky_environment,
    uniform_environment,
    voxel_albedo,
)
from jaxvox.scene import default_scene
from jaxvox.sdf_octree import build_octree_from_sdf, sphere_trace_octree, voxelize_sdf
from jaxvox.solid import open_edges, solid_boundary, solid_voxelize
from jaxvox.sparse_field import SparseField, sample, sparse_distance_field, sparse_field_regions
from jaxvox.sphere_tracing import sphere_trace
from jaxvox.trace import (
    HIT,
    INVALID,
    MISS,
    STEP_CAP,
    TRACE_METHODS,
    Hit,
    trace,
    trace_dense,
)
from jaxvox.voxel_files import load_binvox, load_voxels, save_binvox, save_voxels
from jaxvox.voxel_surface import voxels_to_mesh
from jaxvox.voxelize import (
    CONSERVATIVE,
    OVERFLOW_CANDIDATES,
    OVERFLOW_COLUMNS,
    OVERFLOW_ROWS,
    OVERFLOW_VOXELS,
    SIX_SEPARATING,
    SOLID_BOUNDARY,
    UNUSED,
    Capacities,
    Voxels,
    voxel_capacities,
    voxelize,
    voxelize_fixed,
)
from jaxvox.winding import winding_numbers

__version__ = "0.1.0"

__all__ = [
    "BatchResult",
    "CONSERVATIVE",
    "Capacities",
    "Clipmap",
    "ClosestPoints",
    "CompactDag",
    "EMPTY",
    "Environment",
    "Grid",
    "HIT",
    "Hit",
    "INVALID",
    "JaxvoxError",
    "MISS",
    "MISSING",
    "Mesh",
    "MeshIndex",
    "OVERFLOW_CANDIDATES",
    "OVERFLOW_COLUMNS",
    "OVERFLOW_NODES",
    "OVERFLOW_ROWS",
    "OVERFLOW_VOXELS",
    "Octree",
    "Overflow",
    "PointQuery",
    "PointStatus",
    "QuantizedField",
    "RenderResult",
    "SIX_SEPARATING",
    "SOLID_BOUNDARY",
    "STEP_CAP",
    "SdfSamples",
    "SparseField",
    "TRACE_METHODS",
    "UNUSED",
    "Voxels",
    "batch_capacities",
    "box_emission",
    "build_clipmap",
    "build_dag",
    "build_octree",
    "build_octree_from_sdf",
    "clipmap_corners",
    "closest_points",
    "compact",
    "compact_dag",
    "default_scene",
    "distance_field",
    "distance_field_bytes",
    "enable_compilation_cache",
    "expand",
    "field_to_mesh",
    "load",
    "load_attributes",
    "load_binvox",
    "load_environment",
    "load_mesh",
    "load_voxels",
    "look_at_view",
    "mesh_index",
    "mesh_to_dag",
    "morton",
    "occupancy",
    "octree_capacities",
    "open_edges",
    "pad_mesh",
    "pinhole_rays",
    "points",
    "quantize_field",
    "query_points",
    "read_exr",
    "read_hdr",
    "render",
    "render_mesh",
    "run_batch",
    "sample",
    "sample_gradient",
    "sample_meshes",
    "sample_sdf",
    "sample_texture",
    "save",
    "save_binvox",
    "save_mesh",
    "save_render",
    "save_voxels",
    "sdf",
    "signed_distance",
    "sky_environment",
    "solid_boundary",
    "solid_voxelize",
    "sparse_distance_field",
    "sparse_field_regions",
    "sphere_trace",
    "sphere_trace_field",
    "sphere_trace_octree",
    "stack_grids",
    "stack_indices",
    "stack_meshes",
    "time_sliced_cascades",
    "tonemap",
    "trace",
    "trace_clipmap",
    "trace_dense",
    "uniform_environment",
    "union_clipmaps",
    "update_clipmap",
    "voxel_albedo",
    "voxel_attributes",
    "voxel_capacities",
    "voxel_index",
    "voxelize",
    "voxelize_build_trace",
    "voxelize_fixed",
    "voxelize_sdf",
    "voxels_to_mesh",
    "winding_number",
    "winding_numbers",
    "write_exr",
    "write_png",
]
