"""Amanatides and Woo's DDA over a dense occupancy grid, the loop behind `trace_dense`."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxvox._core.hit import RUNNING
from jaxvox._core.pytree import pytree_dataclass
from jaxvox.grid import Grid
from jaxvox.trace.ray import Ray, argmin3, first_cell, max3, min3, pick, step_status, times, vec


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class DenseGrid:
    occupancy: jax.Array  # [R^3] bool, flat C order
    grid: Grid


class _Dda(NamedTuple):
    cell: tuple  # 3 x [] int32 mirrored voxel
    status: jax.Array  # [] int32


def dda_init(dense: DenseGrid, ray: Ray, status) -> _Dda:
    corner, half = (jnp.int32(0),) * 3, dense.grid.resolution // 2
    while half >= 1:  # the voxel the ray is in at t_start, by the octree's tie rules
        corner = first_cell(ray, corner, half, ray.t_start)
        half //= 2
    return _Dda(corner, status)


def dda_step(dense: DenseGrid, ray: Ray, s: _Dda) -> _Dda:
    res = dense.grid.resolution
    t0 = times(ray, s.cell)
    t1 = times(ray, vec(lambda c: c + 1, s.cell))
    t_in, t_out = max3(t0), min3(t1)
    i, j, k = vec(lambda c, a: jnp.where((ray.flip >> a) & 1 == 1, res - 1 - c, c), s.cell, (0, 1, 2))
    live = dense.occupancy[(i * res + j) * res + k] & (t_out > 0) & (t_in < t_out)
    axis = argmin3(t1)
    status = step_status((t_in > ray.t_max) | (~live & (pick(s.cell, axis) + 1 >= res)), live)
    go = (s.status == RUNNING) & (status == RUNNING)
    cell = tuple(jnp.where((axis == a) & go, c + 1, c) for a, c in enumerate(s.cell))
    return _Dda(cell, jnp.where(s.status == RUNNING, status, s.status))


def dda_voxel(dense, s: _Dda):
    return s.cell
