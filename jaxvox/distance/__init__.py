"""Dense distance fields of triangle meshes, their 16-bit storage and cascaded clipmaps.

The pipeline follows Boissé's thread (``../shared/seeds/003_*.txt``), in grid units
(voxel edge 1; results are scaled to world units at the end):

1. **Closest-triangle voxelization.** Every voxel the surface touches (conservative
   voxelization) gets the id of the triangle nearest its centre among the triangles
   that touch it, ties to the lower id (`jaxvox.voxelize` with ``triangle_ids=True``,
   a lexicographic sort on (voxel, distance, id)). Each triangle also seeds the voxels
   holding its centroid and its three corners clamped into the grid, merged with a
   scatter-min on (distance bits, id), so that geometry outside the grid still reaches
   it (only through those voxels: a triangle outside the grid whose nearest region in
   the grid is cut off from them is found late, see the test suite's bounds).
2. **Narrow band.** ``band`` separable 3x3x3 passes of jump flooding on triangle ids
   (one axis at a time, neighbours at -1, +1): every voxel within ``band`` voxels
   (Chebyshev) of a seeded voxel holds the exact point-triangle distance to the best
   triangle found among its neighbours.
3. **Propagation** to the whole grid, one of:

   * ``"jfa"``: jump flooding on triangle ids with steps R/2, R/4, ..., 1, each
     pass comparing the 26 neighbours at that step (Jacobi within a pass);
   * ``"jfa-separable"`` (the default): the same steps, each as three one-axis passes
     (2 neighbours each: 6 candidates per step instead of 26); measured the most
     accurate for its time (docs/distance-fields.md);
   * ``"sweep"``: Zhao's fast sweeping of the eikonal equation ``|grad d| = 1`` on
     *distances* (not ids): Gauss-Seidel sweeps in the 8 diagonal orders, the
     Godunov upwind update, ``sweeps`` iterations; seeded voxels are kept fixed;
   * ``"jfa+sweep"``: the thread's pipeline, the narrow band (default one separable
     3x3x3 pass) followed by sweeps;
   * ``"exact"``: the brute-force minimum over all triangles at every voxel, chunked
     (O(R^3 F): a reference for small grids);
   * ``"band"``: none; the narrow band alone (default 4 passes), +inf beyond it. Its
     value at a voxel depends only on the seeds within ``band`` voxels (Chebyshev),
     which is what truncated fields such as the clipmap's need. Values are distances
     to real triangles (never below exact); voxels within about ``band - 1`` voxels of
     the surface have jump flooding's accuracy, farther ones in the band may have
     been reached only from a farther part of the surface.

   Methods on ids give distances to real triangles, so they never underestimate;
   sweeping can (by about 0.3 voxel along ridges of the field, where the upwind
   update mixes two fronts) and overestimates diagonally from small features.
4. **Sign** from a solid voxelization of the voxel centres (`jaxvox.distance.solid`): ``"parity"`` (Schwarz &
   Seidel: every triangle flips the inside bit of the voxels of a +x column beyond
   the column's crossing, then a prefix XOR along x; exact and O(surface), right for
   watertight meshes only, which it checks) or ``"winding"`` (the generalized
   winding number, inside where it exceeds 1/2, by `jaxvox.winding_numbers`' tree of
   dipoles: right for open meshes with holes, like the bunny, and for closed ones).

Modules: `field` (`distance_field`, the method table, memory estimates), `exact`, `jfa`
(seeds, narrow band, jump flooding) and `sweep` (fast sweeping, in JAX by hyperplanes
of a skewed grid), `quantize` (16-bit storage), `clipmap` (cascaded clipmaps and
their tracing); the sign is `jaxvox.distance.solid`'s. The public names are re-exported here
and from `jaxvox`; everything else is private.
"""

from jaxvox.distance.clipmap import (
    Clipmap,
    build_clipmap,
    clipmap_corners,
    time_sliced_cascades,
    trace_clipmap,
    union_clipmaps,
    update_clipmap,
)
from jaxvox.distance.field import BYTES_PER_VOXEL, METHODS, distance_field, distance_field_bytes
from jaxvox.distance.jfa import NO_TRIANGLE
from jaxvox.distance.meshing import field_to_mesh
from jaxvox.distance.quantize import FORMATS, QuantizedField, quantize_field
from jaxvox.distance.solid import SIGN_BYTES_PER_VOXEL, SIGN_METHODS, open_edges, solid_boundary, solid_voxelize
from jaxvox.distance.sparse import SparseField, sample, sparse_distance_field, sparse_field_regions
from jaxvox.distance.winding import winding_numbers

__all__ = [
    "BYTES_PER_VOXEL",
    "Clipmap",
    "FORMATS",
    "METHODS",
    "NO_TRIANGLE",
    "QuantizedField",
    "SIGN_BYTES_PER_VOXEL",
    "SIGN_METHODS",
    "SparseField",
    "build_clipmap",
    "clipmap_corners",
    "distance_field",
    "distance_field_bytes",
    "field_to_mesh",
    "open_edges",
    "quantize_field",
    "sample",
    "solid_boundary",
    "solid_voxelize",
    "sparse_distance_field",
    "sparse_field_regions",
    "time_sliced_cascades",
    "trace_clipmap",
    "union_clipmaps",
    "update_clipmap",
    "winding_numbers",
]
