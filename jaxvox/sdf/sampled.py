"""A sampled scene node: a sparse narrow-band distance field (`jaxvox.SparseField`) as an SDF.

`sampled(field)` wraps a field so that every scene query (`jaxvox.sphere_trace`,
`jaxvox.sphere_trace_octree`, `normal`, `to_mesh`, CSG with analytic nodes) accepts it; its
distance is ``jaxvox.sample(field, p)[0]``, the trilinear interpolation of the band values
with the clamp ``+-band * h`` for neighbours outside the band or the grid.

**Lipschitz constant.** In one interpolation cell each partial derivative of the trilinear
interpolant is a convex (bilinear) combination of the four finite differences
``(v_{i+1} - v_i) / h`` along that axis. Band values are exact distances, so a difference
between two band voxels is at most 1; a neighbour outside the band reads the clamp
``s * band * h`` and, for ``band >= 2``, ``s`` is the true sign of its distance (a band
voxel one cell diagonal away, ``sqrt(3) h < band h``, cannot have the other sign), so the
cell's values are the truncated distance ``sign(d) min(|d|, band h)``, still 1-Lipschitz
on the grid. Hence ``|grad| <= sqrt(3)`` (`LIPSCHITZ`), and the bound is attained: at a
voxel centre on a point-like surface the three axis differences are all 1 (meshes approach
it at sharp vertices).
With ``band < 2`` a clamp can take the wrong sign next to the surface; values then lie in
``[-h, h]`` and differences are at most 2, giving ``2 sqrt(3)`` (`LIPSCHITZ_THIN_BAND`).
Two places break the argument: inside the surface beyond the band, where all 8 neighbours
are missing and the field reads ``+band * h`` (no sign is stored there: the value jumps at
the inner edge of the band), and a band cut by the grid, where a neighbour outside the
grid reads the clamp with the sign of the present ones although it may lie on the other
side of the surface (the zero set then moves by up to a voxel within ``band`` voxels of a
grid face). Rays must start outside the surface or inside the band; see
`jaxvox.sphere_trace_field` for what happens otherwise.

`lipschitz_bound` reports `LIPSCHITZ` (so `jaxvox.voxelize_sdf` keeps every cell the
surface can cross). Sphere tracing is provably safe with ``relaxation=1 / sqrt(3)``; near
a smooth surface the gradient norm is 1 up to O(h / radius) and it exceeds 1 only near
sharp features (measured up to 1.38), so full steps lose no hits in practice (measured in
`jaxvox.sphere_tracing.field`, whose `sphere_trace_field` defaults to 1).

**Meshing.** `to_mesh` of the node also meshes a spurious surface 2.5-6 voxels inside
the real one, where the clamp jumps from ``-band * h`` to ``+band * h`` at the inner edge
of the band; the real surface is the component outside it.
"""

from __future__ import annotations

import math

from jaxvox._core.checks import check_type
from jaxvox.distance.sparse import SparseField, sample
from jaxvox.sdf.base import SDF, node

LIPSCHITZ = math.sqrt(3.0)  # Lipschitz bound of a sampled field with band >= 2
LIPSCHITZ_THIN_BAND = 2.0 * math.sqrt(3.0)  # ... with band 0 or 1 (clamps may take the wrong sign)


@node
class Sampled(SDF):
    """A sparse narrow-band field as a scene node: ``jaxvox.sample(field, p)[0]``. A bound, not exact.

    Outside the band (or the grid) the value is the clamp ``+-band * h`` (a lower bound on
    the distance where its sign is right); inside the surface beyond the band it reads
    ``+band * h`` (see the module docstring). Lipschitz bound `LIPSCHITZ` (`lipschitz`).
    The field's ``band`` is static (changing it recompiles).
    """

    field: SparseField

    def _distance(self, p):
        return sample(self.field, p)[0]

    @property
    def lipschitz(self) -> float:
        """Upper bound on the Lipschitz constant: `LIPSCHITZ` for ``band >= 2``, else `LIPSCHITZ_THIN_BAND`."""
        return LIPSCHITZ if self.field.band >= 2 else LIPSCHITZ_THIN_BAND


def sampled(field: SparseField) -> Sampled:
    """The scene node of a sparse narrow-band distance field (`jaxvox.sparse_distance_field`).

    Args:
      field: a `jaxvox.SparseField`; its values are signed distances in world units.

    Returns:
      A `Sampled` node: calling it on points ``f32[..., 3]`` gives ``f32[...]``, the
      trilinear interpolation of `jaxvox.sample`, differentiable in the points.

    Raises:
      JaxvoxError: `field` is not a `jaxvox.SparseField`.
    """
    check_type("sampled field", field, SparseField)
    return Sampled(field)
