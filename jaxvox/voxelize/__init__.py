"""Exact conservative and 6-separating triangle voxelization (Schwarz & Seidel 2010).

Each triangle picks its dominant axis ``w`` (the largest component of its plane
normal) and the two others ``u`` (columns) and ``v`` (rows). Every voxel test is a
linear inequality in the voxel's integer corner, so for a fixed column the valid rows
form an interval, and for a fixed (column, row) the valid depths form an interval:

* columns: the triangle's bounding box along ``u``;
* rows: the dominant projection's three edge functions (and, in 6-separating mode, the
  diamond's two axes), intersected with the bounding box along ``v``;
* depths: the plane (critical corners in conservative mode; the centre segment along
  ``w`` in 6-separating mode), the two side projections' edge functions, and the
  bounding box along ``w``.

The modes differ only in the edge constants (box corner vs. inscribed diamond). Work is
expanded in JAX with fixed-size padding: per-triangle column counts, a prefix sum and an
expansion into a column capacity; per-column row counts, a prefix sum and an expansion
into a row capacity; per-row depth intervals, a prefix sum and an expansion into a candidate
capacity; the candidates are sorted by Morton code and made unique. No dense ``R^3`` array
is formed. Large triangles cost one work item per (column, row), not per bounding-box
voxel.

All tests run in float32 on coordinates local to the triangle (grid units relative to an
integer cell near its minimum corner). Every half-plane is widened by a tolerance of
``2^-19 * (1 + L)`` voxels (L: the triangle's extent in voxels) and the plane test by the
largest distance of the triangle's corners from the float32 plane, so rounding can only
add voxels that lie within that tolerance of the exact decision boundary, never drop one.
"""

# The subpackage and its function share the name `voxelize`: `jaxvox/__init__.py` imports
# the function, so after ``import jaxvox`` the attribute `jaxvox.voxelize` is the function
# and ``sys.modules["jaxvox.voxelize"]`` is this package.
from jaxvox.voxelize.fixed import voxelize_fixed
from jaxvox.voxelize.host import voxel_capacities, voxelize
from jaxvox.voxelize.surface import voxels_to_mesh
from jaxvox.voxelize.voxels import (
    CONSERVATIVE,
    MODES,
    OVERFLOW_CANDIDATES,
    OVERFLOW_COLUMNS,
    OVERFLOW_ROWS,
    OVERFLOW_VOXELS,
    REGION_SIZE,
    ROW_CHUNK,
    SET_MODES,
    SIX_SEPARATING,
    SOLID_BOUNDARY,
    UNUSED,
    Capacities,
    Mode,
    Voxels,
    check_capacities,
)

__all__ = [
    "CONSERVATIVE",
    "Capacities",
    "MODES",
    "Mode",
    "OVERFLOW_CANDIDATES",
    "OVERFLOW_COLUMNS",
    "OVERFLOW_ROWS",
    "OVERFLOW_VOXELS",
    "REGION_SIZE",
    "ROW_CHUNK",
    "SET_MODES",
    "SIX_SEPARATING",
    "SOLID_BOUNDARY",
    "UNUSED",
    "Voxels",
    "check_capacities",
    "voxel_capacities",
    "voxelize",
    "voxelize_fixed",
    "voxels_to_mesh",
]
