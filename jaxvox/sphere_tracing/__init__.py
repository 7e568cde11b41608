"""Sphere tracing (`jaxvox.sphere_tracing`): marching rays through signed distances.

* `analytic`: `sphere_trace` of an SDF scene (`jaxvox.sdf`), with over- and
  under-relaxation and hit refinement;
* `octree`: `voxelize_sdf` and `build_octree_from_sdf` (the voxels an SDF's surface
  crosses, as a tree) and `sphere_trace_octree`, which skips the empty space of that tree;
* `field`: `sphere_trace_field` of a sparse distance field with the field's own octree,
  and `sample_gradient`.

Every tracer returns a `jaxvox.Hit`. The same names are also importable from `jaxvox`.
"""

from jaxvox.sphere_tracing.analytic import sphere_trace
from jaxvox.sphere_tracing.field import sample_gradient, sphere_trace_field
from jaxvox.sphere_tracing.octree import build_octree_from_sdf, sphere_trace_octree, voxelize_sdf

__all__ = [
    "build_octree_from_sdf",
    "sample_gradient",
    "sphere_trace",
    "sphere_trace_field",
    "sphere_trace_octree",
    "voxelize_sdf",
]
