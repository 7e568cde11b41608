"""Sphere tracing of signed distance scenes (Hart 1996), with over-relaxation (Keinert et al. 2014).

From a point at distance ``d`` from every surface the ray can advance by ``d`` without
crossing one (the unbounding sphere), as long as the scene's Lipschitz constant is at
most 1 (`jaxvox.sdf.lipschitz_bound`). Over-relaxation steps ``omega * d`` instead; when
the unbounding spheres at the previous and the new point do not overlap
(``|d_prev| + |d| < step``) the step may have skipped a surface, so the ray goes back to
the previous point, steps by ``d_prev`` and continues with ``omega = 1``.

Each ray is a `jax.lax.while_loop` over a `NamedTuple` state with a step cap, vmapped
over the flattened batch; rays that reach the cap report `STEP_CAP`, never a hit or a
miss.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._errors import JaxvoxError
from jaxvox.sdf import SDF, _is_concrete, _safe_norm
from jaxvox.trace import _RUNNING, HIT, INVALID, MISS, STEP_CAP, Hit


class _State(NamedTuple):
    """One ray's loop state."""

    t: jax.Array  # [] float32 distance along the unit direction of the point to evaluate
    t_prev: jax.Array  # [] float32 last accepted point
    d_prev: jax.Array  # [] float32 signed distance at t_prev (0 before the first step)
    omega: jax.Array  # [] float32 relaxation, drops to 1 after a failed over-relaxed step
    steps: jax.Array  # [] int32 scene evaluations so far
    status: jax.Array  # [] int32 _RUNNING, HIT, MISS, STEP_CAP or INVALID


def _trace_one(scene, o, u, t_min, t_max, epsilon, relaxation, max_steps):
    """Sphere traces one ray (origin o, unit direction u); returns the final `_State`."""

    def body(s: _State) -> _State:
        d = scene._distance(o + s.t * u)
        overlap_fails = (s.omega > 1.0) & (jnp.abs(d) + jnp.abs(s.d_prev) < s.t - s.t_prev)
        hit = (jnp.abs(d) < epsilon * jnp.maximum(s.t, 1.0)) | ((s.steps == 0) & (d < 0))
        t_next = jnp.maximum(s.t + s.omega * d, t_min)
        status = jnp.where(jnp.isnan(d), INVALID,
                           jnp.where(hit, HIT, jnp.where(t_next > t_max, MISS, _RUNNING)))
        steps = s.steps + 1
        accepted = _State(jnp.where(hit, s.t, t_next), s.t, d, s.omega, steps, status)
        fallback = _State(s.t_prev + s.d_prev, s.t_prev, s.d_prev, jnp.ones_like(s.omega), steps,
                          jnp.asarray(_RUNNING, jnp.int32))
        new = jax.tree.map(lambda a, b: jnp.where(overlap_fails, a, b), fallback, accepted)
        return new._replace(status=jnp.where((new.status == _RUNNING) & (steps >= max_steps), STEP_CAP,
                                             new.status).astype(jnp.int32))

    bad = jnp.any(jnp.isnan(o)) | jnp.any(jnp.isnan(u)) | jnp.all(u == 0)
    start = jnp.where(t_min > t_max, MISS, _RUNNING)
    init = _State(t_min, t_min, jnp.zeros_like(t_min), relaxation, jnp.int32(0),
                  jnp.where(bad, INVALID, start).astype(jnp.int32))
    return jax.lax.while_loop(lambda s: s.status == _RUNNING, body, init)


def _unit(directions):
    """Unit directions [n, 3] (zero where the direction has zero length)."""
    length = _safe_norm(directions)
    u = directions / jnp.where(length > 0, length, 1.0)[:, None]
    return jnp.where((length > 0)[:, None], u, 0.0)


def _surface_hit(scene, o, u, t, status, on_surface) -> Hit:
    """A flat `Hit` [n] from traced distances, with implicit gradients for ``t``.

    The loops are not differentiated: the hit t gets its gradient from the implicit
    function theorem (f(o + t u) = 0 => dt = -df / (grad f . u)), for hits on the surface
    (`on_surface`; not rays that start inside). `voxel` and `index` are -1.
    """
    frozen_scene = jax.lax.stop_gradient(scene)
    is_hit = status == HIT
    t_star = jnp.where(is_hit, jax.lax.stop_gradient(t), 0.0)  # a finite point for misses ("safe where")
    x_star = jax.lax.stop_gradient(o + t_star[:, None] * u)
    g = jax.vmap(jax.grad(frozen_scene._distance))(x_star)  # [n, 3]
    g_norm = _safe_norm(g)
    n = jnp.where((is_hit & (g_norm > 0))[:, None], g / jnp.where(g_norm > 0, g_norm, 1.0)[:, None], 0.0)
    den = jnp.sum(g * jax.lax.stop_gradient(u), axis=-1)
    den_ok = is_hit & on_surface & (den != 0)
    f = scene._distance(o + t_star[:, None] * u)
    correction = jnp.where(den_ok, (f - jax.lax.stop_gradient(f)) / jnp.where(den_ok, den, 1.0), 0.0)
    return Hit(t=jnp.where(is_hit, t_star - correction, jnp.inf), voxel=jnp.full(t.shape + (3,), -1, jnp.int32),
               normal=n, index=jnp.full(t.shape, -1, jnp.int32), status=status)


@functools.partial(jax.jit, static_argnames=("max_steps", "return_steps"))
def _sphere_trace(scene, origins, directions, t_min, t_max, epsilon, relaxation, max_steps, return_steps):
    batch = origins.shape[:-1]
    o, u = origins.reshape(-1, 3), _unit(directions.reshape(-1, 3))
    frozen = jax.lax.stop_gradient((scene, o, u))
    trace = lambda s, oo, uu: _trace_one(s, oo, uu, t_min, t_max, epsilon, relaxation, max_steps)
    final = jax.vmap(trace, in_axes=(None, 0, 0))(*frozen)
    on_surface = jnp.abs(final.d_prev) < epsilon * jnp.maximum(final.t, 1.0)
    hit = _surface_hit(scene, o, u, final.t, final.status, on_surface)
    hit = jax.tree.map(lambda x: x.reshape(batch + x.shape[1:]), hit)
    return (hit, final.steps.reshape(batch)) if return_steps else hit


def sphere_trace(scene: SDF, origins, directions, *, t_max=np.inf, max_steps: int = 256, epsilon=1e-4,
                 t_min=0.0, relaxation=1.0, return_steps: bool = False):
    """First surface hit of each ray ``origin + t * direction / |direction|`` by sphere tracing.

    Args:
      scene: a `jaxvox.sdf` scene (Lipschitz constant at most 1 for a safe trace).
      origins: [..., 3] float32 ray origins in world units.
      directions: [..., 3] float32 directions (normalized here; broadcast with `origins`).
      t_max: rays whose next point lies beyond this distance are a `MISS`. With the default
        inf a ray that never hits ends as `STEP_CAP`; pass a finite bound.
      max_steps: scene evaluations per ray before giving up with `STEP_CAP` (static).
      epsilon: a ray hits at t when ``|f| < epsilon * max(t, 1)``: relative to the distance
        travelled, absolute within unit distance of the origin.
      t_min: distance along the ray where tracing starts. A ray whose first point is inside
        (``f < 0`` at `t_min`) is a `HIT` at ``t = t_min``.
      relaxation: step factor omega in (0, 2); 1 is plain sphere tracing, above 1
        over-relaxes (with the fallback above), below 1 under-relaxes: steps of
        ``omega * d`` are safe for a scene whose Lipschitz bound is at most ``1 / omega``
        (e.g. ``1 / jaxvox.sdf.lipschitz_bound(scene)`` for `mix` or uncorrected scales).
      return_steps: also return the number of scene evaluations per ray (static).

    Returns:
      A `jaxvox.Hit`: ``t`` [...] float32 distance along the unit direction (inf unless
      `HIT`); ``normal`` [..., 3] unit SDF gradient at the hit (zero unless `HIT`; not
      differentiated);
      ``voxel`` -1 and ``index`` -1 (no voxels here); ``status`` [...] int32 `HIT`, `MISS`,
      `STEP_CAP` or `INVALID` (NaN origin, zero or NaN direction, NaN distance). With
      ``return_steps``, ``(hit, steps)`` with steps [...] int32. ``t`` is differentiable
      with respect to the scene parameters and the origins by the implicit function
      theorem, ``dt = -df / (grad f . u)``.

    Raises:
      JaxvoxError: bad shapes, ``max_steps < 1``, or (when concrete) ``epsilon <= 0``,
        relaxation outside (0, 2), NaN ``t_min`` / ``t_max``.
    """
    o, d, scalars = _checked(scene, origins, directions, t_min=t_min, t_max=t_max, epsilon=epsilon,
                             relaxation=relaxation, max_steps=max_steps)
    return _sphere_trace(scene, o, d, scalars["t_min"], scalars["t_max"], scalars["epsilon"],
                         scalars["relaxation"], int(max_steps), bool(return_steps))


def _checked(scene, origins, directions, *, max_steps, **scalars):
    """Validated (origins, directions) float32 [..., 3] broadcast, and float32 scalars."""
    if not isinstance(scene, SDF):
        raise JaxvoxError(f"sphere tracing needs a jaxvox.sdf scene, got {type(scene).__name__}")
    o = jnp.asarray(origins, jnp.float32)
    d = jnp.asarray(directions, jnp.float32)
    if o.shape[-1:] != (3,) or d.shape[-1:] != (3,):
        raise JaxvoxError(f"origins and directions must have shape [..., 3], got {o.shape} and {d.shape}")
    try:
        o, d = jnp.broadcast_arrays(o, d)
    except ValueError as exc:
        raise JaxvoxError(f"origins {o.shape} and directions {d.shape} do not broadcast") from exc
    if int(max_steps) != max_steps or max_steps < 1:
        raise JaxvoxError(f"max_steps must be a positive integer, got {max_steps!r}")
    scalars = {name: jnp.asarray(v, jnp.float32) for name, v in scalars.items()}
    for name, v in scalars.items():
        if v.shape != ():
            raise JaxvoxError(f"{name} must be a scalar, got shape {v.shape}")
        if _is_concrete(v) and np.isnan(float(v)):
            raise JaxvoxError(f"{name} is NaN")
    if _is_concrete(scalars["epsilon"]) and not float(scalars["epsilon"]) > 0:
        raise JaxvoxError(f"epsilon must be > 0, got {float(scalars['epsilon'])}")
    if _is_concrete(scalars["relaxation"]) and not 0.0 < float(scalars["relaxation"]) < 2.0:
        raise JaxvoxError(f"relaxation must lie in (0, 2), got {float(scalars['relaxation'])}")
    return o, d, scalars
