"""jaxvox: voxel geometry in JAX.

Exact conservative and 6-separating triangle voxelization with fixed-capacity,
jittable cores and host-side APIs that size capacities by counting passes.
"""

from jaxvox import morton
from jaxvox._errors import JaxvoxError
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, load_mesh, pad_mesh
from jaxvox.scene import default_scene
from jaxvox.voxelize import (
    CONSERVATIVE,
    OVERFLOW_CANDIDATES,
    OVERFLOW_COLUMNS,
    OVERFLOW_ROWS,
    OVERFLOW_VOXELS,
    SIX_SEPARATING,
    UNUSED,
    Capacities,
    Voxels,
    voxel_capacities,
    voxelize,
    voxelize_fixed,
)

__version__ = "0.1.0"

__all__ = [
    "CONSERVATIVE",
    "OVERFLOW_CANDIDATES",
    "OVERFLOW_COLUMNS",
    "OVERFLOW_ROWS",
    "OVERFLOW_VOXELS",
    "SIX_SEPARATING",
    "UNUSED",
    "Capacities",
    "Grid",
    "JaxvoxError",
    "Mesh",
    "Voxels",
    "default_scene",
    "load_mesh",
    "morton",
    "pad_mesh",
    "voxel_capacities",
    "voxelize",
    "voxelize_fixed",
]
