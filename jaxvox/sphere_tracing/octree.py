"""Octrees of signed distance scenes, and sphere tracing accelerated by them.

**SDF to octree.** Adaptive subdivision from the root, one level at a time: a cell is
split only where the surface may cross it, ``|f(centre)| <= L * half diagonal`` (``L``
the scene's Lipschitz bound, `jaxvox.sdf.lipschitz_bound`; for ``L <= 1`` the value is
a lower bound on the distance to the surface, so a cell failing the test holds no
surface). The voxels kept at the finest level are every voxel the surface crosses, plus
some near it; they come out in Morton order, because each cell's children are emitted
in child-slot order. Work and memory follow the surface (8 evaluations per kept cell per
level), never the R^3 volume. Each level is one jitted evaluation over a buffer padded
to a power of two (so levels of similar size share compiled code); the host compacts
the kept cells between levels.

**Octree-accelerated sphere tracing** (Munini, ``../shared/seeds/002_*.txt``, after
Laine & Karras): `jaxvox.trace` finds the first occupied leaf along the ray, the ray is
sphere-traced only inside that leaf's box, and if it leaves the box without a hit the
traversal resumes where sphere tracing stopped. Empty space costs octree steps instead
of scene evaluations. One traversal of the whole batch first ends the rays that enter
no leaf; the loop then runs in rounds (one traversal and a leaf march of at most `MARCH`
evaluations per round) on persistent lanes fed from a queue of the rays that remain
(`jaxvox._core.lanes`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_choice, check_int, check_number, check_type, refuse
from jaxvox._core.hit import RUNNING
from jaxvox._core.lanes import run_states_in_lanes
from jaxvox._core.shapes import bucket
from jaxvox.grid import Grid
from jaxvox.octree import Octree, build_dag, build_octree, voxel_index
from jaxvox.sdf import SDF, lipschitz_bound
from jaxvox.sdf.base import check_scene
from jaxvox.sphere_tracing.analytic import (
    LANES,
    checked_rays,
    march_ray,
    refine_hits,
    surface_hit,
    unit_directions,
)
from jaxvox.trace import HIT, INVALID, MISS, STEP_CAP, TRACE_METHODS, trace
from jaxvox.voxelize import CONSERVATIVE, UNUSED, Voxels

# Child offsets in slot order (slot = x | y << 1 | z << 2, as in `jaxvox.octree`).
_CHILD_OFFSETS = np.array([[s & 1, (s >> 1) & 1, (s >> 2) & 1] for s in range(8)], np.int32)


@jax.jit
def _crossed(scene: SDF, cells, grid: Grid, lipschitz, slack, shift):
    """Whether the surface may cross each cell of edge ``2^shift`` voxels: [C] bool.

    Also returns whether the scene was NaN at any centre ([] bool).
    """
    size = jnp.exp2(shift.astype(jnp.float32))
    centre = grid.origin + (cells.astype(jnp.float32) + 0.5) * size * grid.voxel_size
    d = scene._distance(centre)
    radius = 0.5 * np.float32(math.sqrt(3.0)) * size * grid.voxel_size
    return jnp.abs(d) <= lipschitz * radius * (1.0 + 1e-5) + slack, jnp.any(jnp.isnan(d))


def voxelize_sdf(scene: SDF, grid: Grid, *, lipschitz: float | None = None) -> Voxels:
    """Voxels the surface ``scene == 0`` may cross, by adaptive subdivision (host-side).

    Contains every voxel the surface crosses when `lipschitz` bounds the scene's
    Lipschitz constant; for the others a voxel is kept when ``|f(centre)| <= lipschitz *
    sqrt(3)/2 * voxel_size``, with a float32 rounding slack.

    Args:
      scene: a `jaxvox.sdf` scene.
      grid: the `Grid` (any power-of-two resolution; work grows with the surface).
      lipschitz: Lipschitz bound used by the split test (default
        `jaxvox.sdf.lipschitz_bound` of the scene).

    Returns:
      `Voxels` in Morton order (mode "conservative", no triangle ids).

    Raises:
      JaxvoxError: not a scene or `Grid`, the scene is NaN at a cell centre, or
        `lipschitz` (given or computed) is not a finite number > 0.
    """
    check_type("voxelize_sdf grid", grid, Grid)
    check_scene(scene, "voxelize_sdf scene")
    lip = check_number("voxelize_sdf lipschitz", lipschitz_bound(scene) if lipschitz is None else lipschitz, above=0.0)
    extent = float(np.abs(np.asarray(grid.origin)).max()) + grid.resolution * float(grid.voxel_size)
    slack = np.float32(8 * np.finfo(np.float32).eps * extent)  # centre rounding in float32
    depth = grid.resolution.bit_length() - 1
    cells = np.zeros((1, 3), np.int32)
    for shift in range(depth, -1, -1):
        if shift < depth:
            cells = (cells[:, None, :] * 2 + _CHILD_OFFSETS).reshape(-1, 3)
        n = len(cells)
        if n == 0:
            break
        padded = np.zeros((bucket(n, 64), 3), np.int32)
        padded[:n] = cells
        keep, nan = _crossed(scene, jnp.asarray(padded), grid, np.float32(lip), slack, np.int32(shift))
        if bool(nan):
            raise refuse(
                "voxelize_sdf scene",
                f"must not be NaN at a cell centre (NaN at the level with cells of {2**shift} voxels)",
                scene,
            )
        cells = cells[np.asarray(keep)[:n]]
    n = len(cells)
    coords = np.full((bucket(n), 3), UNUSED, np.int32)
    coords[:n] = cells
    return Voxels(jnp.asarray(coords), jnp.int32(n), jnp.int32(0), None, grid, CONSERVATIVE)


def build_octree_from_sdf(scene: SDF, grid: Grid, *, dag: bool = False, lipschitz: float | None = None) -> Octree:
    """Sparse voxel octree (or DAG) of the voxels the surface of `scene` may cross.

    `voxelize_sdf` followed by `jaxvox.build_octree` (or `jaxvox.build_dag` when `dag`);
    host-side. Memory follows the surface: no array of the grid's volume is made.

    Raises:
      JaxvoxError: as `voxelize_sdf`.
    """
    check_type("build_octree_from_sdf grid", grid, Grid)
    vox = voxelize_sdf(scene, grid, lipschitz=lipschitz)
    return build_dag(vox) if dag else build_octree(vox)


class _Round(NamedTuple):
    """Per-ray state between rounds (flat [n])."""

    t: jax.Array  # float32 distance along the unit direction where the next round starts
    status: jax.Array  # int32 RUNNING, HIT, MISS, STEP_CAP or INVALID
    steps: jax.Array  # int32 scene evaluations so far
    leaves: jax.Array  # int32 leaves entered so far
    voxel: jax.Array  # [n, 3] int32 leaf of the last round
    on_surface: jax.Array  # bool: the hit is a surface point (not a start inside)
    d: jax.Array  # float32 signed distance at t of the last leaf march (the hit test's value)


def _exit_distance(grid: Grid, voxel, o, u):
    """Distance along unit u from o to where the ray leaves the voxel's box: [n]."""
    lo = grid.origin + voxel.astype(jnp.float32) * grid.voxel_size
    far = jnp.where(u > 0, lo + grid.voxel_size, lo)
    t = jnp.where(u != 0, (far - o) / jnp.where(u != 0, u, 1.0), jnp.inf)
    return jnp.min(t, axis=-1)


# Scene evaluations per leaf and round: a ray still inside its leaf after them goes on
# in the next round (its traversal finds the same leaf at once). A vmapped march waits
# for its slowest lane, and near-tangent rays take tens of steps inside one leaf, so an
# unbounded march made each round cost that many evaluations for every ray.
MARCH = 4


@functools.partial(jax.jit, static_argnames=("max_steps", "max_leaves", "method", "lanes"))
def _octree_trace(scene, tree, o, u, t_max, epsilon, relaxation, *, max_steps, max_leaves, method, lanes):
    n = o.shape[0]
    nudge = 1e-4 * tree.grid.voxel_size  # past a leaf's exit face, so the next round leaves it
    bad = jnp.any(jnp.isnan(o), -1) | jnp.any(jnp.isnan(u), -1) | jnp.all(u == 0, -1)
    march = jax.vmap(lambda oo, uu, t0, t1, cap: march_ray(scene, oo, uu, t0, t1, epsilon, relaxation, cap))

    def body(rays, s: _Round) -> _Round:
        o, u = rays
        running = s.status == RUNNING
        start = o + s.t[:, None] * u
        leaf = trace(tree, start, u, t_max=jnp.where(running, t_max - s.t, -jnp.inf), method=method, shard=False)
        entered = running & (leaf.status == HIT)
        t_in = s.t + jnp.where(entered, leaf.t, 0.0)
        t_out = jnp.maximum(_exit_distance(tree.grid, leaf.voxel, o, u), t_in)
        budget = jnp.maximum(max_steps - s.steps, 1)
        final = march(o, u, t_in, jnp.where(entered, jnp.minimum(t_out, t_max), -jnp.inf), jnp.minimum(budget, MARCH))
        left = final.status == MISS  # left the leaf (or passed t_max) without a hit
        paused = (final.status == STEP_CAP) & (budget > MARCH)  # still in the leaf: the next round goes on
        steps = s.steps + jnp.where(entered, final.steps, 0)
        leaves = s.leaves + (entered & ~paused)
        status = jnp.where(left | paused, RUNNING, final.status)
        status = jnp.where((status == RUNNING) & ((leaves >= max_leaves) | (steps >= max_steps)), STEP_CAP, status)
        status = jnp.where(entered, status, jnp.where(running, leaf.status, s.status))
        t_next = jnp.where(left, jnp.maximum(final.t, t_out + nudge), final.t)
        return _Round(
            t=jnp.where(entered, t_next, s.t),
            status=status.astype(jnp.int32),
            steps=steps,
            leaves=leaves,
            voxel=jnp.where(entered[:, None], leaf.voxel, s.voxel),
            on_surface=jnp.where(entered, jnp.abs(final.d_prev) < epsilon * jnp.maximum(final.t, 1.0), s.on_surface),
            d=jnp.where(entered, final.d_prev, s.d),
        )

    inside = scene._distance(o) < 0  # starts inside the surface: a hit at t = 0, as sphere_trace
    state = _Round(
        t=jnp.zeros(n, jnp.float32),
        status=jnp.where(bad, INVALID, jnp.where(inside, HIT, RUNNING)).astype(jnp.int32),
        steps=jnp.ones(n, jnp.int32),
        leaves=jnp.zeros(n, jnp.int32),
        voxel=jnp.full((n, 3), -1, jnp.int32),
        on_surface=jnp.zeros(n, bool),
        d=jnp.zeros(n, jnp.float32),
    )
    # One traversal first ends the rays that enter no leaf (88% of the csg scene's image),
    # so that the rounds, whose marches cost the whole batch MARCH evaluations, start on
    # the rays that do: when at most 1/8 remain, the first stage is skipped. The others
    # start just before their first leaf (the space before it is empty).
    running = state.status == RUNNING
    leaf = trace(tree, o, u, t_max=jnp.where(running, t_max, -jnp.inf), method=method, shard=False)
    entered = running & (leaf.status == HIT)
    state = state._replace(
        t=jnp.where(entered, jnp.maximum(leaf.t - nudge, 0.0), state.t),
        status=jnp.where(running & ~entered, leaf.status, state.status).astype(jnp.int32),
    )
    # Grazing rays enter tens of leaves where most stop in one or two: the rounds run on
    # persistent lanes refilled after every round (`jaxvox._core.lanes`).
    return run_states_in_lanes(body, (o, u), state, lanes=lanes, idle=MISS, steps_per_refill=1)


def sphere_trace_octree(
    scene: SDF,
    tree: Octree,
    origins,
    directions,
    *,
    t_max=np.inf,
    max_steps: int = 256,
    max_leaves: int = 256,
    epsilon=1e-4,
    relaxation=1.0,
    method: str = "esvo",
    return_steps: bool = False,
):
    """Sphere tracing that skips empty space with an octree of the scene.

    As `jaxvox.sphere_trace` with ``t_min = 0`` (same hit test and refinement of ``t``
    onto the surface, ``t`` along the unit direction, same statuses; a ray whose origin
    is inside is a `HIT` at ``t = 0``;
    the first scene evaluation is that inside test), except that space
    outside the tree's leaves is never sampled: build the tree with
    `build_octree_from_sdf` of the same scene (at any resolution), or a surface outside
    the leaves is missed.

    Args:
      scene: the `jaxvox.sdf` scene.
      tree: an `Octree` (SVO or DAG) whose leaves cover the surface.
      origins, directions: [..., 3] float32 world rays (directions normalized here).
      t_max: rays are a `MISS` beyond this distance.
      max_steps: cap on scene evaluations per ray (static); reaching it gives `STEP_CAP`.
      max_leaves: cap on leaves entered per ray (static); reaching it gives `STEP_CAP`.
      epsilon, relaxation: as in `jaxvox.sphere_trace` (relaxation restarts in each leaf
        and every `MARCH` evaluations in it;
        a step that would leave a leaf is a plain one, so none is taken unchecked).
      method: the octree traversal, "esvo" or "stack" (static).
      return_steps: also return scene evaluations per ray (static).

    Returns:
      A `jaxvox.Hit` with ``voxel`` and ``index`` of the leaf holding the hit (for
      attribute lookup), ``t`` differentiable as in `jaxvox.sphere_trace`; with
      `return_steps`, ``(hit, steps)``.

    Raises:
      JaxvoxError: not an `Octree`, `max_leaves` not an integer >= 1, a bad method, or
        bad input to `jaxvox.sphere_trace`.
    """
    check_type("sphere_trace_octree tree", tree, Octree)
    max_leaves = check_int("sphere_trace_octree max_leaves", max_leaves, minimum=1)
    check_choice("sphere_trace_octree method", method, TRACE_METHODS)
    o, d, scalars = checked_rays(
        scene, origins, directions, t_max=t_max, epsilon=epsilon, relaxation=relaxation, max_steps=max_steps
    )
    batch = o.shape[:-1]
    hit, steps = _sphere_trace_octree(
        scene,
        tree,
        o.reshape(-1, 3),
        d.reshape(-1, 3),
        scalars["t_max"],
        scalars["epsilon"],
        scalars["relaxation"],
        max_steps=int(max_steps),
        max_leaves=max_leaves,
        method=method,
    )
    hit = jax.tree.map(lambda x: x.reshape(batch + x.shape[1:]), hit)
    return (hit, steps.reshape(batch)) if return_steps else hit


@functools.partial(jax.jit, static_argnames=("max_steps", "max_leaves", "method", "lanes"))
def _sphere_trace_octree(
    scene, tree, o, directions, t_max, epsilon, relaxation, *, max_steps, max_leaves, method, lanes=LANES
):
    """Flat [n] rays (any batch shape of the same size shares this compiled program);
    `lanes` is the lane count of `run_states_in_lanes` (the tests compare lane counts)."""
    u = unit_directions(directions)
    frozen = jax.lax.stop_gradient((scene, tree, o, u))
    final = _octree_trace(
        *frozen,
        t_max,
        epsilon,
        relaxation,
        max_steps=max_steps,
        max_leaves=max_leaves,
        method=method,
        lanes=lanes,
    )
    is_hit = final.status == HIT
    t, extra = refine_hits(frozen[0], frozen[2], frozen[3], final.t, final.d, is_hit & final.on_surface, 0.0, t_max)
    hit = surface_hit(scene, o, u, t, final.status, final.on_surface)
    voxel = jnp.where(is_hit[:, None], final.voxel, -1)
    index = jnp.where(is_hit, voxel_index(frozen[1], jnp.maximum(voxel, 0)), -1)
    return dataclasses.replace(hit, voxel=voxel, index=index), final.steps + extra
