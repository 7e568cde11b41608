"""Hit refinement of sphere tracing: ``t`` on the surface to float32 rounding.

References are float64 numpy ray-sphere and ray-box (slab) intersections written here, of
the float32 rays the tracer sees. Incidence angles are measured from the tangent plane at
the hit (90 degrees: head-on).

Run as a script to print (not assert) the mean extra scene evaluations per hit and the
old (unrefined loop) vs new maximum error at grazing incidence::

    .venv/bin/python tests/test_sphere_refine.py
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvox as jv
from jaxvox.sphere_tracing.analytic import REFINE_STEPS, refine_hits

sdf = jv.sdf
REL = 1e-5  # target: relative error of t at incidence >= 1 degree, float32 tracing
INCIDENCE = np.geomspace(1.0, 90.0, 600)  # degrees; one batch size, so one compiled program per scene type
SPHERES = [(0.5, (0.1, -0.2, 0.3)), (1.3, (-0.4, 0.2, 0.0)), (0.05, (0.3, 0.3, -0.3))]
BOX_HALF, BOX_CENTER = np.array([0.6, 0.3, 0.45]), np.array([0.2, -0.1, 0.3])
BOX_ROTATION = ((1.0, 2.0, 0.5), 0.7)  # axis, angle


# ----------------------------------------------------------------------------- float64 references


def _unit64(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def ray_sphere(o, u, r, c):
    """First t >= 0 of rays (u normalized here) against a sphere, float64; inf on a miss."""
    u = _unit64(u)
    oc = o - c
    b = np.sum(oc * u, -1)
    disc = b * b - (np.sum(oc * oc, -1) - r * r)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc >= 0) & (t >= 0), t, np.inf)


def ray_box(o, u, b):
    """First t >= 0 of rays (u normalized here) against the box |x_i| <= b_i (slabs), float64."""
    u = _unit64(u)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (-b - o) / u, (b - o) / u
    t_in, t_out = np.minimum(ta, tb).max(-1), np.maximum(ta, tb).min(-1)
    return np.where((t_in <= t_out) & (t_in >= 0), t_in, np.inf)


def _tangent(rng, normal):
    """Random unit vectors [n, 3] perpendicular to the unit `normal` [n, 3]."""
    w = rng.normal(size=normal.shape)
    return _unit64(w - np.sum(w * normal, -1, keepdims=True) * normal)


def _incoming(rng, point, normal, degrees, back):
    """float32 rays (o, u) that reach `point` at `degrees` from the tangent plane after `back`."""
    a = np.radians(degrees)[:, None]
    u = -np.sin(a) * normal + np.cos(a) * _tangent(rng, normal)
    return (point - back[:, None] * u).astype(np.float32), u.astype(np.float32)


def sphere_rays(rng, degrees, r, c):
    """Rays from outside hitting the sphere (r, c) at the given incidences; float32 o, u."""
    normal = _unit64(rng.normal(size=(len(degrees), 3)))
    return _incoming(rng, c + r * normal, normal, degrees, rng.uniform(1.0, 3.0, len(degrees)))


def box_scene_and_rays(rng, degrees):
    """The rotated, translated box of `BOX_*`, rays hitting a face at the given incidences,
    and the float64 reference t of the float32 rays."""
    half, center = BOX_HALF, BOX_CENTER
    rot32 = np.asarray(sdf.rotation(*BOX_ROTATION))
    rot = rot32.astype(np.float64)
    scene = sdf.translate(sdf.rotate(sdf.box(half), rot32), center)
    n = len(degrees)
    axis, sign = rng.integers(0, 3, n), rng.choice([-1.0, 1.0], n)
    normal = np.zeros((n, 3))
    normal[np.arange(n), axis] = sign
    point = rng.uniform(-0.9, 0.9, (n, 3)) * half  # inside a face, away from its edges
    point[np.arange(n), axis] = sign * half[axis]
    o, u = _incoming(rng, point, normal, degrees, rng.uniform(1.0, 3.0, n))  # local frame
    o = (o.astype(np.float64) @ rot.T + center).astype(np.float32)  # world: x = R x_local + c
    u = (u.astype(np.float64) @ rot.T).astype(np.float32)
    o64, u64 = o.astype(np.float64), u.astype(np.float64)
    return scene, o, u, ray_box((o64 - center) @ rot, u64 @ rot, half)  # scene: box(R^T (x - c))


def _rel_error(t, t_ref):
    return np.abs(np.asarray(t, np.float64) - t_ref) / t_ref


# ----------------------------------------------------------------------------- accuracy


@pytest.mark.parametrize("relaxation", [1.0, 1.6])
def test_sphere_hits_accurate_at_any_incidence(relaxation):
    rng = np.random.default_rng(0)
    for r, c in SPHERES:
        o, u = sphere_rays(rng, INCIDENCE, r, np.array(c))
        t_ref = ray_sphere(o.astype(np.float64), u.astype(np.float64), r, np.array(c))
        assert np.isfinite(t_ref).all()
        hit = jv.sphere_trace(sdf.sphere(r, center=c), o, u * 3.0, t_max=20.0, relaxation=relaxation)
        assert (np.asarray(hit.status) == jv.HIT).all()
        err = _rel_error(hit.t, t_ref)
        assert err.max() <= REL, (r, c, INCIDENCE[err.argmax()], err.max())


def test_box_hits_accurate_at_any_incidence():
    scene, o, u, t_ref = box_scene_and_rays(np.random.default_rng(1), INCIDENCE)
    assert np.isfinite(t_ref).all()
    # Grazing rays along a box face need many plain steps: a generous cap, so that all hit.
    hit = jv.sphere_trace(scene, o, u, t_max=20.0, max_steps=4096)
    assert (np.asarray(hit.status) == jv.HIT).all()
    err = _rel_error(hit.t, t_ref)
    assert err.max() <= REL, (INCIDENCE[err.argmax()], err.max())
    # The normal is taken at the refined point: the face normal, in world space.
    rot = np.asarray(sdf.rotation(*BOX_ROTATION), np.float64)
    x_local = (o + np.asarray(hit.t)[:, None] * _unit64(u.astype(np.float64)) - BOX_CENTER) @ rot
    face = np.abs(np.abs(x_local) - BOX_HALF).argmin(-1)
    n_local = np.zeros_like(x_local)
    n_local[np.arange(len(face)), face] = np.sign(x_local[np.arange(len(face)), face])
    np.testing.assert_allclose(np.asarray(hit.normal), n_local @ rot.T, atol=1e-5)


def test_octree_tracing_is_refined_too():
    r, c = 0.55, np.array([0.05, -0.02, 0.01])
    scene = sdf.sphere(r, center=c)
    tree = jv.build_octree_from_sdf(scene, jv.Grid(origin=(-1.0, -1.0, -1.0), voxel_size=2.0 / 16, resolution=16))
    o, u = sphere_rays(np.random.default_rng(2), INCIDENCE, r, c)
    hit = jv.sphere_trace_octree(scene, tree, o, u, t_max=6.0, max_steps=512)
    assert (np.asarray(hit.status) == jv.HIT).all()
    assert _rel_error(hit.t, ray_sphere(o.astype(np.float64), u.astype(np.float64), r, c)).max() <= REL


# ----------------------------------------------------------------------------- unchanged behaviour


def test_inside_starts_and_misses_unchanged():
    r, c = 0.5, np.array([0.1, -0.2, 0.3])
    scene = sdf.sphere(r, center=c)
    rng = np.random.default_rng(3)
    n = 64
    d = _unit64(rng.normal(size=(n, 3)))
    # Inside (the last one within epsilon of the surface, heading inwards): a HIT at t_min
    # after one evaluation, never moved by the refinement (which stays at or beyond t_min).
    inside = c + d * np.concatenate([rng.uniform(0.0, 0.3, n - 1), [r - 1e-5]])[:, None]
    heading = np.concatenate([d[::-1][:-1], -d[-1:]])
    for t_min in (0.0, 0.1):
        hit, steps = jv.sphere_trace(scene, inside, heading, t_max=5.0, t_min=t_min, return_steps=True)
        assert (np.asarray(hit.status) == jv.HIT).all() and (np.asarray(steps) == 1).all()
        np.testing.assert_array_equal(np.asarray(hit.t), np.float32(t_min))
    # Misses by a margin (passing 1e-2 outside at the closest point): MISS, t = inf.
    normal = _unit64(rng.normal(size=(n, 3)))
    along = _tangent(rng, normal)
    o = (c + (r + 1e-2) * normal - 2.0 * along).astype(np.float32)
    miss = jv.sphere_trace(scene, o, along.astype(np.float32), t_max=5.0)
    assert (np.asarray(miss.status) == jv.MISS).all() and np.isinf(np.asarray(miss.t)).all()
    # Grazing within epsilon without crossing (1e-5 outside): still a HIT, at the loop's point
    # (no sign change to refine towards): outside the surface, within the hit tolerance.
    o = (c + (r + 1e-5) * normal - 2.0 * along).astype(np.float32)
    graze = jv.sphere_trace(scene, o, along.astype(np.float32), t_max=5.0)
    assert (np.asarray(graze.status) == jv.HIT).all()
    t = np.asarray(graze.t, np.float64)
    f = np.linalg.norm(o + t[:, None] * _unit64(along.astype(np.float32).astype(np.float64)) - c, axis=-1) - r
    assert (f > -1e-6).all() and (f < 1e-4 * np.maximum(t, 1.0)).all()


@jax.tree_util.register_static
class _Plane(sdf.SDF):
    """``x . n - offset``, NaN where ``x_0 > nan_beyond``: a test-only scene (no parameters)."""

    def __init__(self, n, offset, nan_beyond=np.inf):
        self.n, self.offset, self.nan_beyond = tuple(float(v) for v in n), offset, nan_beyond

    def _distance(self, p):
        return jnp.where(p[..., 0] > self.nan_beyond, jnp.nan, p @ jnp.asarray(self.n, jnp.float32) - self.offset)


def test_refinement_brackets_both_ways_keeps_unbracketed_hits():
    n = _unit64(np.array([-1.0, 0.3, 0.0]))
    plane = _Plane(n, -1.0)  # surface x . n = -1
    o = jnp.zeros((5, 3))
    u = jnp.asarray(
        _unit64(np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])),
        jnp.float32,
    )
    root = 1.0 / float(-n @ np.asarray(u[0]))  # where ray 0 crosses
    t0 = jnp.array([root - 2e-4, root + 2e-4, 1.0, root, root - 2e-4], jnp.float32)  # ray 3: |f| ~ rounding
    f0 = jax.vmap(plane._distance)(o + t0[:, None] * u)
    active = jnp.array([True, True, True, True, False])
    t, steps = refine_hits(plane, o, u, t0, f0, active, 0.0, jnp.inf)
    t, steps = np.asarray(t), np.asarray(steps)
    for i in (0, 1, 3):  # from outside, from inside, from within float32 rounding of the root
        assert t[i] == pytest.approx(root, rel=1e-6)
    assert t[2] == np.float32(1.0) and steps[2] > 0  # parallel to the plane: no sign change, kept
    assert t[4] == t0[4] and steps[4] == 0  # not active
    assert (steps <= REFINE_STEPS).all()
    # The search stays within t_lo / t_hi, and NaN distances stop it with a finite t.
    t_cut, _ = refine_hits(plane, o[:2], u[:2], t0[:2], f0[:2], active[:2], root + 1e-4, root - 1e-4)
    np.testing.assert_array_equal(np.asarray(t_cut), np.asarray(t0[:2]))
    nan_plane = _Plane(n, -1.0, nan_beyond=float(t0[0] * u[0, 0]) + 1e-5)
    t_nan, _ = refine_hits(nan_plane, o[:1], u[:1], t0[:1], f0[:1], active[:1], 0.0, jnp.inf)
    assert np.asarray(t_nan)[0] == t0[0]


# ----------------------------------------------------------------------------- gradients, jit, vmap


@pytest.mark.parametrize("degrees", [3.0, 30.0, 89.0])
def test_gradients_match_analytic(degrees):
    """dt/d(radius), dt/d(centre) and dt/d(origin) by the implicit function theorem, now that f = 0
    at the returned t, against the analytic derivatives, at the default epsilon."""
    r, c = 0.5, np.array([0.1, -0.2, 0.3])
    o, u = sphere_rays(np.random.default_rng(4), np.array([degrees]), r, c)
    o64, u64 = o[0].astype(np.float64), _unit64(u[0].astype(np.float64))
    t_ref = ray_sphere(o64[None], u64[None], r, c)[0]
    normal = (o64 + t_ref * u64 - c) / r
    cos = -normal @ u64  # sin of the incidence from the tangent plane
    t_of = lambda radius, center, origin: jv.sphere_trace(sdf.sphere(radius, center=center), origin, u[0], t_max=10.0).t
    dr, dc, do = jax.grad(t_of, argnums=(0, 1, 2))(jnp.float32(r), jnp.asarray(c, jnp.float32), jnp.asarray(o[0]))
    assert float(dr) == pytest.approx(-1.0 / cos, rel=1e-4)  # t = -b - sqrt(b^2 - |o - c|^2 + r^2)
    np.testing.assert_allclose(np.asarray(dc), -normal / cos, rtol=1e-4, atol=1e-4 / cos)
    np.testing.assert_allclose(np.asarray(do), normal / cos, rtol=1e-4, atol=1e-4 / cos)  # -g / (g . u)


def test_box_gradient_matches_analytic():
    """A face hit of an axis-aligned box: o_x + t u_x = c_x + b_x, so dt/db_x = 1 / u_x."""
    o = jnp.array([2.0, 0.05, -0.1])
    u = jnp.asarray(_unit64(np.array([-1.0, 0.01, 0.03])), jnp.float32)  # ~88 degrees to the x face
    grad = jax.grad(lambda b: jv.sphere_trace(sdf.box(b), o, u, t_max=10.0).t)(jnp.array([0.5, 0.4, 0.3]))
    np.testing.assert_allclose(np.asarray(grad), [1.0 / float(u[0]), 0.0, 0.0], rtol=1e-5, atol=1e-6)


def test_eager_jit_and_vmap_agree():
    r, c = 0.5, (0.1, -0.2, 0.3)
    o, u = sphere_rays(np.random.default_rng(5), INCIDENCE[::10], r, np.array(c))
    scene = sdf.sphere(r, center=c)
    eager = jv.sphere_trace(scene, o, u, t_max=20.0)
    jitted = jax.jit(lambda s, oo, uu: jv.sphere_trace(s, oo, uu, t_max=20.0))(scene, o, u)
    mapped = jax.vmap(lambda oo, uu: jv.sphere_trace(scene, oo, uu, t_max=20.0))(jnp.asarray(o), jnp.asarray(u))
    for other in (jitted, mapped):
        np.testing.assert_array_equal(np.asarray(other.status), np.asarray(eager.status))
        np.testing.assert_allclose(np.asarray(other.t), np.asarray(eager.t), rtol=1e-6)
    t_ref = ray_sphere(o.astype(np.float64), u.astype(np.float64), r, np.array(c))
    assert _rel_error(mapped.t, t_ref).max() <= REL


# ----------------------------------------------------------------------------- measurement (script)


def _measure():  # pragma: no cover - run by hand
    """Mean extra scene evaluations per hit, and unrefined (the loop's t, as before) vs refined
    maximum relative and absolute errors of t, by incidence band."""
    from jaxvox.sphere_tracing.analytic import march_ray, unit_directions

    rng = np.random.default_rng(0)
    degrees = np.geomspace(1.0, 90.0, 4000)
    r, c = 0.5, np.array([0.1, -0.2, 0.3])
    cases = {"sphere r=0.5": (sdf.sphere(r, center=c), *sphere_rays(rng, degrees, r, c))}
    o, u = cases["sphere r=0.5"][1:]
    cases["sphere r=0.5"] += (ray_sphere(o.astype(np.float64), u.astype(np.float64), r, c),)
    cases["rotated box"] = box_scene_and_rays(rng, degrees)
    for name, (scene, o, u, t_ref) in cases.items():
        hit, steps = jv.sphere_trace(scene, o, u, t_max=20.0, max_steps=4096, return_steps=True)
        loop = jax.vmap(lambda sc, oo, uu: march_ray(sc, oo, uu, 0.0, 20.0, 1e-4, 1.0, 4096), in_axes=(None, 0, 0))(
            scene, jnp.asarray(o), unit_directions(jnp.asarray(u))
        )
        extra = np.asarray(steps) - np.asarray(loop.steps)
        print(
            f"{name}: {len(o)} rays, incidence 1-90 degrees, epsilon 1e-4; extra evaluations per hit: "
            f"mean {extra.mean():.2f}, max {extra.max()} (cap {REFINE_STEPS})"
        )
        for lo, hi in [(1, 2), (2, 10), (10, 90)]:
            band = (degrees >= lo) & (degrees <= hi)
            old, new = np.abs(np.asarray(loop.t) - t_ref)[band], np.abs(np.asarray(hit.t) - t_ref)[band]
            print(
                f"  {lo:>2}-{hi:<2} deg: max |dt| old {old.max():.2e} new {new.max():.2e}; max relative old "
                f"{(old / t_ref[band]).max():.2e} new {(new / t_ref[band]).max():.2e}; extra evaluations "
                f"mean {extra[band].mean():.2f}"
            )


if __name__ == "__main__":
    _measure()
