"""Sphere tracing of signed distance scenes (Hart 1996), with over-relaxation (Keinert et al. 2014).

From a point at distance ``d`` from every surface the ray can advance by ``d`` without
crossing one (the unbounding sphere), as long as the scene's Lipschitz constant is at
most 1 (`jaxvox.sdf.lipschitz_bound`). Over-relaxation steps ``omega * d`` instead; when
the unbounding spheres at the previous and the new point do not overlap
(``|d_prev| + |d| < step``) the step may have skipped a surface, so the ray goes back to
the previous point, steps by ``d_prev`` and continues with ``omega = 1``. A step that
would end past ``t_max`` (the ray's, or an octree leaf's exit) is never checked, so it
is taken as a plain step (and ``omega = 1``) instead: a ray that leaves
``[t_min, t_max]`` ends at a ``t`` its last sphere vouches for.

Each ray steps a `NamedTuple` state with a step cap, on persistent lanes fed from a
queue of the rays (`jaxvox._core.lanes`: under `vmap` a `while_loop` steps every ray
until the slowest ends, and grazing rays take many times the mean). Rays that reach the
cap report `STEP_CAP`, never a hit or a miss.

**Hit refinement.** The loop stops where ``|f| < epsilon * max(t, 1)``, which at an
incidence ``a`` (from the tangent plane) lies up to ``epsilon * max(t, 1) / sin(a)`` short
of the surface. `refine_hits` then moves ``t`` onto the crossing: probes march away from the
hit point (forward when ``f > 0``, backward when an over-relaxed step ended inside),
each 1.5 times the secant extrapolation of the last two outside values past the last
(at least the unbounding step ``|f|`` there; twice the last step where ``f`` does not
fall), at most `_REACH` ``|f|`` from the hit, until the sign flips; the bracket is then
shrunk by Anderson-Bjorck regula falsi (bisection when an iterate would not move
``t``) until it settles to float32 resolution. ``t`` is the bracket end of smaller
``|f|``. A crossing farther than `_REACH` ``|f|`` (incidence below about 0.45
degrees, or a loose distance bound) keeps the loop's ``t``: the status is never changed.
A feature thinner than the probe spacing can be stepped over, as the hit test itself
reports hits within epsilon of features a ray misses. The cost is one scene evaluation
per iteration, at most `REFINE_STEPS` per hit (one `jax.lax.while_loop` per ray, so
under vmap a batch pays its slowest ray); on spheres and boxes at incidences of 1 to 90
degrees the mean is 3-4 (about 6 below 2 degrees). What remains is float32 rounding of
the scene near the hit: a few ulps of ``|x|`` over ``sin(a)``.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Real

from jaxvox._core.checks import is_concrete
from jaxvox._core.errors import JaxvoxError
from jaxvox._core.geometry import safe_norm
from jaxvox._core.hit import RUNNING
from jaxvox._core.lanes import run_states_in_lanes
from jaxvox.sdf import SDF
from jaxvox.trace import HIT, INVALID, MISS, STEP_CAP, Hit


class _State(NamedTuple):
    """One ray's loop state."""

    t: jax.Array  # [] float32 distance along the unit direction of the point to evaluate
    t_prev: jax.Array  # [] float32 last accepted point
    d_prev: jax.Array  # [] float32 signed distance at t_prev (0 before the first step)
    omega: jax.Array  # [] float32 relaxation, drops to 1 after a failed over-relaxed step
    steps: jax.Array  # [] int32 scene evaluations so far
    status: jax.Array  # [] int32 RUNNING, HIT, MISS, STEP_CAP or INVALID


def _ray_step(scene, o, u, t_min, t_max, epsilon, max_steps):
    """One sphere-tracing step of one ray (origin o, unit direction u): `_State` -> `_State`."""

    def body(s: _State) -> _State:
        d = scene._distance(o + s.t * u)
        overlap_fails = (s.omega > 1.0) & (jnp.abs(d) + jnp.abs(s.d_prev) < s.t - s.t_prev)
        hit = (jnp.abs(d) < epsilon * jnp.maximum(s.t, 1.0)) | ((s.steps == 0) & (d < 0))
        # An over-relaxed step past t_max is never checked, so a surface it jumps over
        # would be missed (or, in an octree leaf, found late in the next leaf, which
        # starts where this one's last step ended): it becomes a plain step.
        unchecked_exit = (s.omega > 1.0) & (s.t + s.omega * d > t_max)
        omega = jnp.where(unchecked_exit, 1.0, s.omega)
        t_next = jnp.maximum(s.t + omega * d, t_min)
        status = jnp.where(
            jnp.isnan(d),
            INVALID,
            jnp.where(hit, HIT, jnp.where((t_next > t_max) | ~jnp.isfinite(t_next), MISS, RUNNING)),
        )
        steps = s.steps + 1
        accepted = _State(jnp.where(hit, s.t, t_next), s.t, d, omega, steps, status)
        fallback = _State(
            s.t_prev + s.d_prev, s.t_prev, s.d_prev, jnp.ones_like(s.omega), steps, jnp.asarray(RUNNING, jnp.int32)
        )
        new = jax.tree.map(lambda a, b: jnp.where(overlap_fails, a, b), fallback, accepted)
        return new._replace(
            status=jnp.where((new.status == RUNNING) & (steps >= max_steps), STEP_CAP, new.status).astype(jnp.int32)
        )

    return body


def _ray_start(o, u, t_min, t_max, relaxation) -> _State:
    """The state of one ray before its first step."""
    bad = jnp.any(jnp.isnan(o)) | jnp.any(jnp.isnan(u)) | jnp.all(u == 0)
    start = jnp.where(t_min > t_max, MISS, RUNNING)
    return _State(
        t_min, t_min, jnp.zeros_like(t_min), relaxation, jnp.int32(0), jnp.where(bad, INVALID, start).astype(jnp.int32)
    )


def march_ray(scene, o, u, t_min, t_max, epsilon, relaxation, max_steps):
    """Sphere traces one ray (origin o, unit direction u); returns the final `_State`."""
    step = _ray_step(scene, o, u, t_min, t_max, epsilon, max_steps)
    return jax.lax.while_loop(lambda s: s.status == RUNNING, step, _ray_start(o, u, t_min, t_max, relaxation))


# Lanes of the sphere-tracing loops (`jaxvox._core.lanes`): rays stepped at once (on the
# CPU, more lanes step more ended rays between refills; fewer pay more refills).
LANES = 1024


def march_rays(scene, o, u, t_min, t_max, epsilon, relaxation, max_steps, *, lanes: int = LANES):
    """Sphere traces rays [n, 3] (unit directions) with scalar bounds; returns the final
    `_State` [n]. The rays run on `lanes` persistent lanes fed from a queue
    (`jaxvox._core.lanes`; a vmapped `march_ray` would step every ray until the slowest
    ended)."""

    def step(oo, uu, s: _State) -> _State:
        return _ray_step(scene, oo, uu, t_min, t_max, epsilon, max_steps)(s)

    def body(rays, s: _State) -> _State:
        rows_o, rows_u = rays
        stepped = jax.vmap(step)(rows_o, rows_u, s)
        keep = s.status != RUNNING
        return jax.tree.map(lambda old, new: jnp.where(keep, old, new), s, stepped)

    start = jax.vmap(_ray_start, in_axes=(0, 0, None, None, None))(o, u, t_min, t_max, relaxation)
    return run_states_in_lanes(body, (o, u), start, lanes=lanes, idle=MISS, steps_per_refill=4)


# Hit refinement, in units of |f| at the hit (see the module docstring).
_FIRST = 2.0  # first probe: a surface met head-on lies |f| away, so this one is across it
_OVERSHOOT = 1.5  # later probes: 1.5 times the secant's estimate of the remaining distance, ...
_GROWTH = 8.0  # ... at least |f| there (a safe step), at most _GROWTH times the last probe's s
_REACH = 128.0  # probes stop 128 |f| from the hit: crossings at incidence above ~0.45 degrees
REFINE_STEPS = 32  # cap on scene evaluations per refined hit (probes and bracket steps together)


class _Refine(NamedTuple):
    """One hit's refinement state.

    Distances ``s >= 0`` run from the hit ``t0`` along ``sigma * u`` (``sigma`` the sign of
    f at the hit) and values are ``g = sigma * f``, so the hit is outside (``g > 0``) and
    the search looks for ``g <= 0``.
    """

    s_out: jax.Array  # [] float32 last probe with g > 0 (0: the hit)
    g_out: jax.Array  # [] float32 g there (> 0)
    s_old: jax.Array  # [] float32 the outside point before s_out (secant while searching)
    g_old: jax.Array  # [] float32 g there
    s_in: jax.Array  # [] float32 nearest point found with g <= 0 (bracketed only)
    g_in: jax.Array  # [] float32 g there (<= 0)
    w_out: jax.Array  # [] float32 Anderson-Bjorck weight of g_out in the regula falsi point
    w_in: jax.Array  # [] float32 ... and of g_in
    last_in: jax.Array  # [] bool the latest evaluation landed inside (g <= 0)
    s_next: jax.Array  # [] float32 where the next evaluation goes
    bracketed: jax.Array  # [] bool a sign change was found
    done: jax.Array  # [] bool
    steps: jax.Array  # [] int32 scene evaluations


def _refine_one(scene, o, u, t0, f0, active, t_lo, t_hi):
    """Moves a hit ``t0`` (with f = `f0` there, ``|f0|`` small) onto the crossing of f = 0.

    Searches at most ``_REACH * |f0|`` away from ``t0``, within [`t_lo`, `t_hi`]; returns
    ``(t, steps)`` ([] float32, [] int32): ``t0`` and 0 where not `active`, and ``t0`` when
    no sign change is found.
    """
    sigma = jnp.where(f0 > 0, 1.0, -1.0)
    g0 = jnp.abs(f0)
    reach = jnp.minimum(_REACH * g0, jnp.where(f0 > 0, t_hi - t0, t0 - t_lo))
    at = lambda s: t0 + sigma * s  # [] float32 t of a distance from the hit
    ulp = jnp.abs(jnp.nextafter(t0, t0 + sigma) - t0)  # probes move t by at least this
    zero, one, no = jnp.zeros_like(g0), jnp.ones_like(g0), jnp.bool_(False)
    init = _Refine(
        s_out=zero,
        g_out=g0,
        s_old=zero,
        g_old=g0,
        s_in=zero,
        g_in=zero,
        w_out=one,
        w_in=one,
        last_in=no,
        s_next=jnp.minimum(jnp.maximum(_FIRST * g0, ulp), reach),
        bracketed=no,
        done=~(active & (g0 > 0) & jnp.isfinite(g0) & (reach > 0)),
        steps=jnp.int32(0),
    )

    def strictly_inside(s, r):  # whether t(s) lies strictly between the bracket ends as float32
        return (sigma * (at(s) - at(r.s_out)) > 0) & (sigma * (at(r.s_in) - at(s)) > 0)

    def body(r: _Refine) -> _Refine:
        t = at(r.s_next)
        s = sigma * (t - t0)  # the distance actually evaluated (t is rounded to float32)
        g = sigma * scene._distance(o + t * u)
        inside = g <= 0
        # Anderson-Bjorck: when the same end is replaced twice running, scale the other's value.
        same = r.bracketed & (inside == r.last_in)
        ratio = jnp.where(inside, g / jnp.where(r.g_in < 0, r.g_in, -1.0), g / r.g_out)  # g_out > 0
        scale = jnp.where(same, jnp.where((ratio < 1) & (ratio >= 0), 1.0 - ratio, 0.5), 1.0)
        r = r._replace(
            s_out=jnp.where(inside, r.s_out, s),
            g_out=jnp.where(inside, r.g_out, g),
            s_old=jnp.where(inside, r.s_old, r.s_out),
            g_old=jnp.where(inside, r.g_old, r.g_out),
            s_in=jnp.where(inside, s, r.s_in),
            g_in=jnp.where(inside, g, r.g_in),
            w_out=jnp.where(inside, r.w_out * scale, 1.0),
            w_in=jnp.where(inside, 1.0, r.w_in * scale),
            last_in=inside,
            bracketed=r.bracketed | inside,
            steps=r.steps + 1,
        )
        # Searching: extrapolate the secant of the last two outside points; where g does not
        # fall (a tangency, or float32 noise just short of the crossing), double the last step.
        last = r.s_out - r.s_old
        slope = (r.g_out - r.g_old) / jnp.where(last > 0, last, 1.0)
        remaining = r.g_out / jnp.where(slope < 0, -slope, 1.0)
        planned = r.s_next  # the probe just made before float32 rounding of t (which may not move t)
        step = jnp.where(slope < 0, jnp.minimum(_OVERSHOOT * remaining, _GROWTH * planned), 2.0 * last)
        probe = jnp.minimum(r.s_out + jnp.maximum(jnp.maximum(step, r.g_out), ulp), reach)  # g_out: a safe step
        # Bracketed: the weighted regula falsi point, or the midpoint.
        wo, wi = r.w_out * r.g_out, r.w_in * r.g_in  # > 0 and <= 0
        falsi = r.s_out + (r.s_in - r.s_out) * wo / jnp.where(wo - wi > 0, wo - wi, 1.0)
        mid = 0.5 * (r.s_out + r.s_in)
        latest = at(jnp.where(inside, r.s_in, r.s_out))
        settled = at(falsi) == latest  # the secant moves t by less than half an ulp from the latest point
        shrink = jnp.where(strictly_inside(falsi, r), falsi, mid)
        converged = r.bracketed & (settled | ~strictly_inside(shrink, r))
        stuck = ~r.bracketed & (planned >= reach)
        done = jnp.isnan(g) | (g == 0) | converged | stuck | (r.steps >= REFINE_STEPS)
        return r._replace(s_next=jnp.where(r.bracketed, shrink, probe), done=done)

    r = jax.lax.while_loop(lambda r: ~r.done, body, init)
    s = jnp.where(r.bracketed, jnp.where(r.g_out < -r.g_in, r.s_out, r.s_in), zero)  # NaN g_out: s_in
    return at(s), r.steps


def refine_hits(scene, o, u, t, f, active, t_lo, t_hi):
    """`_refine_one` over flat hits: o, u [n, 3], t, f [n] float32, active [n] bool,
    t_lo, t_hi [] or [n] float32 -> (t [n] float32, steps [n] int32)."""
    n = t.shape[0]
    t_lo, t_hi = jnp.broadcast_to(t_lo, (n,)), jnp.broadcast_to(t_hi, (n,))
    return jax.vmap(_refine_one, in_axes=(None, 0, 0, 0, 0, 0, 0, 0))(scene, o, u, t, f, active, t_lo, t_hi)


def unit_directions(directions):
    """Unit directions [n, 3] (zero where the direction has zero length)."""
    length = safe_norm(directions)
    u = directions / jnp.where(length > 0, length, 1.0)[:, None]
    return jnp.where((length > 0)[:, None], u, 0.0)


def surface_hit(scene, o, u, t, status, on_surface) -> Hit:
    """A flat `Hit` [n] from traced distances, with implicit gradients for ``t``.

    The loops are not differentiated: the hit t gets its gradient from the implicit
    function theorem (f(o + t u) = 0 => dt = -df / (grad f . u)), for hits on the surface
    (`on_surface`; not rays that start inside). `voxel` and `index` are -1.
    """
    frozen_scene = jax.lax.stop_gradient(scene)
    t_star = jnp.where(status == HIT, jax.lax.stop_gradient(t), 0.0)  # a finite point for misses ("safe where")
    x = o + t_star[:, None] * u
    x_star = jax.lax.stop_gradient(x)
    f_star, g = jax.vmap(jax.value_and_grad(frozen_scene._distance))(x_star)  # [n], [n, 3]
    # A scene that overflows float32 at the hit (NaN or inf there) gives no usable hit.
    status = jnp.where((status == HIT) & ~jnp.isfinite(f_star), INVALID, status)
    is_hit = status == HIT
    g_norm = safe_norm(g)
    n = jnp.where((is_hit & (g_norm > 0))[:, None], g / jnp.where(g_norm > 0, g_norm, 1.0)[:, None], 0.0)
    den = jnp.sum(g * jax.lax.stop_gradient(u), axis=-1)
    # A gradient that is not finite at the hit (a scene's kink, or float code that meets
    # 0 * inf there) gives no normal and no implicit gradient, and reaches neither t nor
    # its gradient: f is taken at the fixed point there ("safe where").
    den_ok = is_hit & on_surface & (den != 0) & jnp.isfinite(den)
    f = scene._distance(jnp.where(den_ok[:, None], x, x_star))
    correction = jnp.where(den_ok, (f - jax.lax.stop_gradient(f)) / jnp.where(den_ok, den, 1.0), 0.0)
    return Hit(
        t=jnp.where(is_hit, t_star - correction, jnp.inf),
        voxel=jnp.full(t.shape + (3,), -1, jnp.int32),
        normal=n,
        index=jnp.full(t.shape, -1, jnp.int32),
        status=status,
    )


@functools.partial(jax.jit, static_argnames=("max_steps", "return_steps"))
def _sphere_trace(scene, origins, directions, t_min, t_max, epsilon, relaxation, max_steps, return_steps):
    batch = origins.shape[:-1]
    o, u = origins.reshape(-1, 3), unit_directions(directions.reshape(-1, 3))
    frozen = jax.lax.stop_gradient((scene, o, u))
    final = march_rays(*frozen, t_min, t_max, epsilon, relaxation, max_steps)
    on_surface = jnp.abs(final.d_prev) < epsilon * jnp.maximum(final.t, 1.0)
    t, extra = refine_hits(*frozen, final.t, final.d_prev, (final.status == HIT) & on_surface, t_min, t_max)
    hit = surface_hit(scene, o, u, t, final.status, on_surface)
    hit = jax.tree.map(lambda x: x.reshape(batch + x.shape[1:]), hit)
    return (hit, (final.steps + extra).reshape(batch)) if return_steps else hit


def sphere_trace(
    scene: SDF,
    origins: Real[ArrayLike, "*o 3"],
    directions: Real[ArrayLike, "*d 3"],
    *,
    t_max=np.inf,
    max_steps: int = 256,
    epsilon=1e-4,
    t_min=0.0,
    relaxation=1.0,
    return_steps: bool = False,
):
    """First surface hit of each ray ``origin + t * direction / |direction|`` by sphere tracing.

    Args:
      scene: a `jaxvox.sdf` scene (Lipschitz constant at most 1 for a safe trace).
      origins: [..., 3] float32 ray origins in world units.
      directions: [..., 3] float32 directions (normalized here; broadcast with `origins`).
      t_max: rays whose next point lies beyond this distance are a `MISS`. With the default
        inf, a ray whose distances keep growing is a `MISS` once its next point overflows
        float32 (about 130 steps in an unbounded scene); one that lingers near a surface
        without reaching it ends as `STEP_CAP`. Pass a finite bound to stop misses early.
      max_steps: scene evaluations per ray before giving up with `STEP_CAP` (static).
      epsilon: a ray hits when ``|f| < epsilon * max(t, 1)`` at a point of its march:
        relative to the distance travelled, absolute within unit distance of the origin.
        ``t`` is then refined onto the crossing of ``f = 0`` (to float32 rounding on
        exact scenes; see the module docstring), so epsilon decides hits and misses, not
        the accuracy of ``t``.
      t_min: distance along the ray where tracing starts. A ray whose first point is inside
        (``f < 0`` at `t_min`) is a `HIT` at ``t = t_min``.
      relaxation: step factor omega in (0, 2); 1 is plain sphere tracing, above 1
        over-relaxes (with the fallback above), below 1 under-relaxes: steps of
        ``omega * d`` are safe for a scene whose Lipschitz bound is at most ``1 / omega``
        (e.g. ``1 / jaxvox.sdf.lipschitz_bound(scene)`` for `mix` or uncorrected scales).
      return_steps: also return the number of scene evaluations per ray, those of the
        hit refinement included (static).

    Returns:
      A `jaxvox.Hit`: ``t`` [...] float32 distance along the unit direction (inf unless
      `HIT`; the loop's ``t`` when no sign change lies within reach of the hit point, e.g.
      below about 0.45 degrees of incidence; `t_min` for a ray that starts inside);
      ``normal`` [..., 3] unit SDF gradient at the hit (zero unless `HIT`, and where the
      gradient is zero or not finite; not differentiated);
      ``voxel`` -1 and ``index`` -1 (no voxels here); ``status`` [...] int32 `HIT`, `MISS`,
      `STEP_CAP` or `INVALID` (NaN origin, zero or NaN direction, NaN distance). With
      ``return_steps``, ``(hit, steps)`` with steps [...] int32. ``t`` is differentiable
      with respect to the scene parameters and the origins by the implicit function
      theorem, ``dt = -df / (grad f . u)`` (0 where ``grad f . u`` is 0 or not finite).

    Raises:
      JaxvoxError: bad shapes, ``max_steps < 1``, or (when concrete) ``epsilon <= 0``,
        relaxation outside (0, 2), NaN ``t_min`` / ``t_max``.
    """
    o, d, scalars = checked_rays(
        scene,
        origins,
        directions,
        t_min=t_min,
        t_max=t_max,
        epsilon=epsilon,
        relaxation=relaxation,
        max_steps=max_steps,
    )
    return _sphere_trace(
        scene,
        o,
        d,
        scalars["t_min"],
        scalars["t_max"],
        scalars["epsilon"],
        scalars["relaxation"],
        int(max_steps),
        bool(return_steps),
    )


def checked_rays(scene, origins, directions, *, max_steps, **scalars):
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
        if is_concrete(v) and np.isnan(float(v)):
            raise JaxvoxError(f"{name} is NaN")
    if is_concrete(scalars["epsilon"]) and not float(scalars["epsilon"]) > 0:
        raise JaxvoxError(f"epsilon must be > 0, got {float(scalars['epsilon'])}")
    if is_concrete(scalars["relaxation"]) and not 0.0 < float(scalars["relaxation"]) < 2.0:
        raise JaxvoxError(f"relaxation must lie in (0, 2), got {float(scalars['relaxation'])}")
    return o, d, scalars
