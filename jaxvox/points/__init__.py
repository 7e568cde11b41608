"""Point queries against triangle meshes (`jaxvox.points`): closest points, signed
distance, generalized winding numbers and occupancy at the caller's own points, with
gradients, plus a training-data sampler.

Build a `MeshIndex` once per mesh (`mesh_index`) and pass it to the queries, inside or
outside `jax.jit`; `stack_indices` batches meshes for `jax.vmap`.
"""

from jaxvox.points.index import MeshIndex, mesh_index, stack_indices
from jaxvox.points.queries import (
    ClosestPoints,
    PointQuery,
    PointStatus,
    closest_points,
    occupancy,
    query_points,
    signed_distance,
    winding_number,
)

__all__ = [
    "ClosestPoints",
    "MeshIndex",
    "PointQuery",
    "PointStatus",
    "closest_points",
    "mesh_index",
    "occupancy",
    "query_points",
    "signed_distance",
    "stack_indices",
    "winding_number",
]
