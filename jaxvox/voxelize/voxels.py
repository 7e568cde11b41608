"""Voxel sets (`Voxels`), the work-buffer sizes of `voxelize_fixed` (`Capacities`) and
the voxelizer's constants: modes (and the mode `jaxvox.solid_boundary` records), overflow
bits and the `UNUSED` padding value."""

from __future__ import annotations

import dataclasses
from typing import Final, Literal, NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int32

from jaxvox import morton
from jaxvox._core.checks import check_choice, check_int, check_type, refuse
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.shapes import voxel_bucket
from jaxvox.grid import Grid
from jaxvox.overflow import Overflow, check_overflow

CONSERVATIVE: Final = "conservative"
SIX_SEPARATING: Final = "6-separating"
SOLID_BOUNDARY: Final = "solid-boundary"
MODES = (CONSERVATIVE, SIX_SEPARATING)  # the voxelizer's rules (`voxelize`'s ``mode``)
SET_MODES = (*MODES, SOLID_BOUNDARY)  # what a `Voxels` may record: also `jaxvox.solid_boundary`'s sets
Mode = Literal["conservative", "6-separating"]

# Overflow bits of `Voxels.overflow` (names kept for `jaxvox.overflow.Overflow`'s members).
OVERFLOW_COLUMNS = Overflow.COLUMNS
OVERFLOW_ROWS = Overflow.ROWS
OVERFLOW_CANDIDATES = Overflow.CANDIDATES
OVERFLOW_VOXELS = Overflow.VOXELS

UNUSED = -1  # value of coordinate and triangle slots past `count`
REGION_SIZE = 1 << morton.WORD_BITS  # largest region sorted with one 32-bit key

ROW_CHUNK = 4  # rows per gather on the host path (`Capacities.row_chunk` of `voxel_capacities`)


class Capacities(NamedTuple):
    """Static sizes of the work buffers of `voxelize_fixed` (changing one recompiles).

    Attributes:
      columns: (triangle, column) work items.
      rows: (triangle, column, row) work items, a multiple of `row_chunk`.
      candidates: voxels emitted before duplicates are removed.
      voxels: unique voxels in the result.
      row_chunk: rows handled together per column (a power of two; about the mean
        number of rows per column is fastest; `voxel_capacities` gives `ROW_CHUNK`).
    """

    columns: int
    rows: int
    candidates: int
    voxels: int
    row_chunk: int = ROW_CHUNK


def check_capacities(what: str, capacities) -> Capacities:
    """`capacities` as `Capacities` of Python ints: sizes >= 1, a power-of-two `row_chunk`
    and `rows` a multiple of it; raises `JaxvoxError` naming `what` otherwise."""
    try:
        caps = Capacities(*capacities)
    except TypeError:
        raise refuse(what, "expected a jaxvox.Capacities (4 or 5 integers)", capacities) from None
    caps = Capacities(*(check_int(f"{what} {name}", c, minimum=1) for name, c in zip(Capacities._fields, caps)))
    if caps.row_chunk & (caps.row_chunk - 1):
        raise refuse(f"{what} row_chunk", "must be a power of two", caps.row_chunk)
    if caps.rows % caps.row_chunk:
        raise refuse(f"{what} rows", f"must be a multiple of row_chunk = {caps.row_chunk}", caps.rows)
    return caps


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Voxels:
    """A set of voxels in a fixed-capacity buffer, in Morton order.

    Slots ``[0, count)`` hold unique voxels sorted by Morton code; later slots hold
    `UNUSED` (-1). `mode` is static (changing it recompiles).

    Attributes:
      coords: [capacity, 3] int32 voxel indices (i, j, k).
      count: [] int32 number of valid voxels.
      overflow: [] int32 bitmask of ``OVERFLOW_*`` flags; nonzero means the buffer
        holds a truncated set. The host-side `voxelize` never returns one.
      triangle: [capacity] int32 id of the triangle closest to each voxel's centre
        among those that set it (ties to the lower id), or None if not requested.
      grid: the `Grid` the indices refer to.
      mode: "conservative" or "6-separating" (`voxelize`'s rules), or "solid-boundary"
        (`jaxvox.solid_boundary`).
    """

    coords: Int32[Array, "*batch capacity 3"]  # [capacity, 3] int32
    count: Int32[Array, " *batch"]  # [] int32
    overflow: Int32[Array, " *batch"]  # [] int32
    triangle: Int32[Array, "*batch capacity"] | None  # [capacity] int32
    grid: Grid
    mode: str = dataclasses.field(metadata=dict(static=True))

    @property
    def capacity(self) -> int:
        """Number of slots in the buffer."""
        return self.coords.shape[-2]

    @classmethod
    def from_coords(cls, ijk, grid: Grid, *, mode: str = CONSERVATIVE) -> Voxels:
        """Voxels from arbitrary voxel indices (host-side): checked, deduplicated, Morton-sorted.

        Args:
          ijk: int [N, 3] voxel indices, each in ``[0, grid.resolution)``, any order,
            repeats allowed.
          grid: the `Grid` they refer to.
          mode: the mode to record (the set is taken as given).

        Raises:
          JaxvoxError: not a `Grid`, a bad mode, wrong shape, non-integer values or
            indices outside the grid.
        """
        check_type("Voxels.from_coords grid", grid, Grid)
        check_choice("Voxels.from_coords mode", mode, SET_MODES)
        try:
            a = np.asarray(ijk)
        except ValueError:  # ragged nested sequences
            raise refuse("Voxels.from_coords ijk", "must have shape [N, 3]", ijk) from None
        if a.size == 0 and a.ndim == 1:  # e.g. []
            a = a.reshape(0, 3)
        if a.size == 0 and a.ndim == 2 and a.shape[1] == 3:
            a = a.astype(np.int32)
        if a.ndim != 2 or a.shape[1] != 3:
            raise refuse("Voxels.from_coords ijk", "must have shape [N, 3]", a.shape)
        if not np.issubdtype(a.dtype, np.integer):
            raise refuse("Voxels.from_coords ijk", "must be integers", a.dtype)
        outside = ((a < 0) | (a >= grid.resolution)).any(1)
        if outside.any():
            raise refuse("Voxels.from_coords ijk", f"holds voxel indices outside [0, {grid.resolution})", a[outside][0])
        a = a.astype(np.int32)
        codes, first = np.unique(morton.encode_host(a), return_index=True)
        n = len(codes)
        coords = np.full((voxel_bucket(n, grid.resolution), 3), UNUSED, np.int32)
        coords[:n] = a[first]
        return cls(jnp.asarray(coords), jnp.int32(n), jnp.int32(0), None, grid, mode)

    def to_numpy(self) -> np.ndarray:
        """The valid voxels as a host int32 [count, 3] array in Morton order.

        Raises:
          JaxvoxError: when the overflow flag is set (the set would be truncated).
        """
        check_overflow("Voxels", self.overflow, "use jaxvox.voxelize, which sizes capacities itself")
        return np.asarray(self.coords)[: int(self.count)]  # sliced on the host: no program per count

    def triangle_ids(self) -> np.ndarray:
        """Host int32 [count] triangle id per voxel (requires ``triangle_ids=True``).

        Raises:
          JaxvoxError: when the voxels carry no triangle ids.
        """
        if self.triangle is None:
            raise refuse(
                "Voxels.triangle_ids self.triangle",
                "must hold triangle ids (voxelize with triangle_ids=True)",
                self.triangle,
            )
        return np.asarray(self.triangle)[: int(self.count)]
