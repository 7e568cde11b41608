"""SDF scenes and sphere tracing against float64 numpy references written here."""

from __future__ import annotations

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

import jaxvox as jv
from jaxvox.trace import HIT, INVALID, MISS, STEP_CAP

sdf = jv.sdf
STATUSES = {HIT, MISS, STEP_CAP, INVALID}
F32_REL = 2e-5  # float32 distance tolerance, relative to max(1, |p|)


# ----------------------------------------------------------------------------- float64 references


def ref_sphere(p, r, c):
    return np.linalg.norm(p - c, axis=-1) - r


def ref_box(p, b, c):
    """Outside: distance to the clamped point; inside: minus the distance to the nearest face."""
    q = p - c
    outside = np.linalg.norm(q - np.clip(q, -b, b), axis=-1)
    inside = np.min(b - np.abs(q), axis=-1)
    return np.where(np.all(np.abs(q) <= b, axis=-1), -inside, outside)


def ref_rounded_box(p, b, r, c):
    return ref_box(p, b - r, c) - r  # Minkowski sum of the inner box and a ball


def ref_torus(p, big, small, c):
    q = p - c
    rho = np.linalg.norm(q[:, [0, 2]], axis=-1, keepdims=True)
    ring = np.concatenate([q[:, :1], np.zeros_like(rho), q[:, 2:]], -1) / rho * big  # nearest circle point
    return np.linalg.norm(q - ring, axis=-1) - small


def ref_capsule(p, a, b, r):
    t = np.clip(((p - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
    return np.linalg.norm(p - (a + t[:, None] * (b - a)), axis=-1) - r


def ref_cylinder(p, r, h, c):
    q = p - c
    x = np.stack([np.linalg.norm(q[:, [0, 2]], axis=-1), q[:, 1]], -1)  # (rho, y): a 2D rectangle
    half = np.array([r, h])
    outside = np.linalg.norm(np.abs(x) - np.clip(np.abs(x), 0, half), axis=-1)
    inside = np.min(half - np.abs(x), axis=-1)
    return np.where(np.all(np.abs(x) <= half, axis=-1), -inside, outside)


def ref_plane(p, n, offset):
    return p @ (n / np.linalg.norm(n)) + offset


def ray_sphere(o, u, r):
    """First t >= 0 of unit rays against a sphere at the origin, float64 (inf on a miss)."""
    b = np.sum(o * u, -1)
    disc = b * b - (np.sum(o * o, -1) - r * r)
    root = np.sqrt(np.maximum(disc, 0))
    t0, t1 = -b - root, -b + root
    t = np.where(t0 >= 0, t0, np.where(t1 >= 0, 0.0, np.inf))
    return np.where(disc >= 0, t, np.inf)


def ray_box(o, u, b):
    """First t >= 0 of unit rays against a box at the origin (slabs), float64, and the entry normal."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (-b - o) / u, (b - o) / u
    lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
    t_in, t_out = lo.max(-1), hi.min(-1)
    axis = lo.argmax(-1)
    n = np.zeros_like(o)
    n[np.arange(len(o)), axis] = -np.sign(u[np.arange(len(o)), axis])
    t = np.where((t_in <= t_out) & (t_out >= 0), np.maximum(t_in, 0), np.inf)
    return t, n


def sample_points(rng, n, scale=1.5):
    """Points inside, near the surface of unit-sized shapes, and far away."""
    p = rng.uniform(-scale, scale, (n, 3))
    p[: n // 8] *= 60.0
    p[n // 8 : n // 4] = rng.normal(0, 0.2, (n // 8, 3))
    return p


def check(scene, ref, p):
    got = np.asarray(scene(jnp.asarray(p, jnp.float32)), np.float64)
    p32 = np.asarray(p, np.float32).astype(np.float64)  # the points the scene saw
    want = ref(p32)
    tol = F32_REL * np.maximum(1.0, np.linalg.norm(p32, axis=-1))
    bad = np.abs(got - want) > tol
    assert not bad.any(), (p32[bad][:3], got[bad][:3], want[bad][:3])


# ----------------------------------------------------------------------------- primitives


def test_primitives_match_analytic_distances():
    rng = np.random.default_rng(0)
    p = sample_points(rng, 512)
    c = np.array([0.1, -0.2, 0.05])
    b = np.array([0.6, 0.3, 0.45])
    on_faces = c + rng.uniform(-1, 1, (64, 3)) * b
    on_faces[np.arange(64), rng.integers(0, 3, 64)] = (c + b * rng.choice([-1, 1], (64, 3)))[np.arange(64), 0]
    on_faces = c + np.clip(on_faces - c, -b, b)
    pb = np.concatenate([p, on_faces])
    check(sdf.sphere(0.7, center=c), lambda q: ref_sphere(q, 0.7, c), p)
    check(sdf.box(b, center=c), lambda q: ref_box(q, b, c), pb)
    check(sdf.rounded_box(b, 0.2, center=c), lambda q: ref_rounded_box(q, b, 0.2, c), pb)
    check(sdf.torus(0.8, 0.25, center=c), lambda q: ref_torus(q, 0.8, 0.25, c), p)
    a, e = np.array([-0.5, 0.1, 0.2]), np.array([0.4, -0.3, 0.6])
    check(sdf.capsule(a, e, 0.3), lambda q: ref_capsule(q, a, e, 0.3), p)
    check(sdf.cylinder(0.5, 0.7, center=c), lambda q: ref_cylinder(q, 0.5, 0.7, c), p)
    n = np.array([1.0, 2.0, -2.0])
    check(sdf.plane(n, offset=0.3), lambda q: ref_plane(q, n, 0.3), p)
    assert float(sdf.plane(n, offset=0.3)(-0.3 * n / 3.0)) == pytest.approx(0.0, abs=1e-6)  # passes through -offset n


# ----------------------------------------------------------------------------- transforms


def test_translate_rotate_and_uniform_scale_are_exact():
    rng = np.random.default_rng(1)
    p = sample_points(rng, 256)
    b = np.array([0.6, 0.3, 0.45])
    offset = np.array([0.3, -0.4, 0.2])
    base = sdf.box(b)
    check(sdf.translate(base, offset), lambda q: ref_box(q - offset, b, 0), p)
    r = np.asarray(sdf.rotation((1.0, 2.0, 0.5), 0.7), np.float64)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-6)
    check(sdf.rotate(base, r), lambda q: ref_box(q @ r, b, 0), p)  # local = R^T world
    check(sdf.scale(sdf.torus(0.8, 0.25), 2.5), lambda q: 2.5 * ref_torus(q / 2.5, 0.8, 0.25, 0), p)
    scene = sdf.rotate(sdf.translate(sdf.scale(base, 0.5), offset), r)
    assert sdf.is_exact(scene) and sdf.lipschitz_bound(scene) == 1.0


def test_nonuniform_scale_is_a_sign_consistent_bound():
    s = np.array([1.0, 0.5, 2.0])
    ellipsoid = sdf.scale(sdf.sphere(1.0), s)
    # Dense surface samples: their nearest distance is >= the true distance, by at most the spacing.
    theta, phi = np.meshgrid(np.linspace(0, np.pi, 300), np.linspace(0, 2 * np.pi, 600), indexing="ij")
    surf = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1).reshape(-1, 3) * s
    rng = np.random.default_rng(2)
    p = rng.uniform(-2.5, 2.5, (64, 3))
    sampled = np.sqrt(((p[:, None] - surf[None]) ** 2).sum(-1)).min(1)
    inside = ((p / s) ** 2).sum(-1) < 1
    bound = np.asarray(ellipsoid(jnp.asarray(p, jnp.float32)), np.float64)
    assert ((bound < 0) == inside).all()
    assert (np.abs(bound) <= sampled + 1e-5).all()
    assert (np.abs(bound) >= sampled * s.min() / s.max() - 1e-3).all()  # not a trivial bound
    assert not sdf.is_exact(ellipsoid) and sdf.lipschitz_bound(ellipsoid) == 1.0
    raw = sdf.scale(sdf.sphere(1.0), s, correct=False)
    np.testing.assert_allclose(
        np.asarray(raw(jnp.asarray(p, jnp.float32))), np.linalg.norm(p / s, axis=-1) - 1, rtol=1e-5, atol=1e-5
    )
    assert sdf.lipschitz_bound(raw) == 2.0


# ----------------------------------------------------------------------------- CSG


def test_csg_identities():
    rng = np.random.default_rng(3)
    p = jnp.asarray(sample_points(rng, 256), jnp.float32)
    a = sdf.sphere(0.7, center=(0.2, 0.0, 0.0))
    b = sdf.box((0.4, 0.5, 0.3), center=(-0.2, 0.1, 0.0))
    ev = lambda s: np.asarray(s(p))
    np.testing.assert_array_equal(ev(sdf.union(a, a)), ev(a))
    np.testing.assert_array_equal(ev(sdf.union(a, b)), np.minimum(ev(a), ev(b)))
    np.testing.assert_array_equal(ev(sdf.intersection(a, b)), ev(sdf.intersection(b, a)))
    np.testing.assert_array_equal(ev(sdf.difference(a, b)), ev(sdf.intersection(a, sdf.complement(b))))
    np.testing.assert_array_equal(ev(sdf.mix(a, b, 1.0)), ev(a))
    np.testing.assert_allclose(ev(sdf.smooth_union(a, b, 1e-7)), ev(sdf.union(a, b)), atol=1e-6)
    np.testing.assert_array_equal(ev(sdf.smooth_union(a, b, 0.0)), ev(sdf.union(a, b)))
    assert (ev(sdf.smooth_union(a, b, 0.3)) <= ev(sdf.union(a, b))).all()
    assert (ev(sdf.smooth_intersection(a, b, 0.3)) >= ev(sdf.intersection(a, b))).all()
    assert sdf.is_exact(sdf.complement(a)) and not sdf.is_exact(sdf.union(a, b))
    assert sdf.lipschitz_bound(sdf.mix(a, b, 3.0)) == 5.0
    assert sdf.lipschitz_bound(sdf.smooth_union(a, sdf.mix(a, b, -1.0), 0.1)) == 3.0


# ----------------------------------------------------------------------------- pytree, jit, vmap, grad


def test_jit_vmap_eager_agree_and_retrace_only_on_structure():
    rng = np.random.default_rng(4)
    p = jnp.asarray(sample_points(rng, 128), jnp.float32)
    make = lambda r: sdf.smooth_union(
        sdf.sphere(r), sdf.rotate(sdf.torus(0.8, r / 3), sdf.rotation((1, 0, 0), 0.5)), 0.2
    )
    scene = make(0.5)
    traces = []

    @jax.jit
    def evaluate(s, q):
        traces.append(1)
        return s(q)

    eager = np.asarray(scene(p))
    np.testing.assert_allclose(np.asarray(evaluate(scene, p)), eager, atol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.vmap(scene)(p)), eager, atol=1e-6)
    assert jax.tree.structure(make(0.7)) == jax.tree.structure(scene)
    evaluate(make(0.7), p)
    assert len(traces) == 1
    evaluate(sdf.union(scene, scene), p)
    assert len(traces) == 2
    # Constructors accept tracers (value checks skipped) inside jit.
    inside_jit = jax.jit(lambda r: make(r)(p))(0.5)
    np.testing.assert_allclose(np.asarray(inside_jit), eager, atol=1e-6)


def test_gradients_with_respect_to_parameters():
    p = jnp.array([2.0, 0.5, -0.3])
    g = jax.grad(lambda s: s(p))(sdf.sphere(0.5))
    assert float(g.radius) == pytest.approx(-1.0)
    np.testing.assert_allclose(np.asarray(g.center), -np.asarray(p) / np.linalg.norm(p), rtol=1e-6)
    origin, direction = jnp.array([[-3.0, 0.2, 0.1]]), jnp.array([[3.0, -0.2, -0.1]])  # toward the centre
    t_of = lambda s: jv.sphere_trace(s, origin, direction, t_max=10.0).t[0]
    scene = sdf.sphere(0.5)
    assert float(t_of(scene)) == pytest.approx(np.linalg.norm([-3.0, 0.2, 0.1]) - 0.5, rel=1e-4)
    assert float(jax.grad(t_of)(scene).radius) == pytest.approx(-1.0, rel=1e-4)
    # Off-centre: implicit-function gradient against a central finite difference.
    off_dir = jnp.array([[1.0, 0.0, 0.0]])
    t_off = lambda r: jv.sphere_trace(sdf.sphere(r), origin, off_dir, t_max=10.0, epsilon=1e-6).t[0]
    fd = (float(t_off(0.52)) - float(t_off(0.48))) / 0.04
    assert float(jax.grad(t_off)(0.5)) == pytest.approx(fd, rel=2e-2)


# ----------------------------------------------------------------------------- sphere tracing


def _shell_rays(rng, n):
    o = rng.normal(size=(n, 3))
    o *= rng.uniform(3.0, 5.0, (n, 1)) / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-1.2, 1.2, (n, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.codegen
@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_sphere_trace_matches_analytic_intersections(shape):
    rng = np.random.default_rng(5)
    o, u = _shell_rays(rng, 256)
    o32, u32 = o.astype(np.float32), u.astype(np.float32)
    o, u = o32.astype(np.float64), u32.astype(np.float64)
    band = 1e-2  # rays whose hit/miss flips within this offset of the surface are near-grazing
    if shape == "sphere":
        scene, r = sdf.sphere(1.0), 1.0
        t_ref = ray_sphere(o, u, r)
        grazing = np.isfinite(ray_sphere(o, u, r + band)) != np.isfinite(ray_sphere(o, u, r - band))
        n_ref = (o + np.where(np.isfinite(t_ref), t_ref, 0)[:, None] * u) / r
    else:
        b = np.array([0.6, 0.4, 0.8])
        scene = sdf.box(b)
        t_ref, n_ref = ray_box(o, u, b)
        grazing = np.isfinite(ray_box(o, u, b + band)[0]) != np.isfinite(ray_box(o, u, b - band)[0])
        grazing |= np.isfinite(t_ref) & (np.abs(np.sum(n_ref * u, -1)) < 0.1)  # shallow angle to the face
    hit = jv.sphere_trace(scene, o32, u32 * 2.0, t_max=20.0)  # unnormalized directions
    status, t, n = np.asarray(hit.status), np.asarray(hit.t), np.asarray(hit.normal)
    ok = ~grazing
    assert ok.sum() > 200 and np.isfinite(t_ref[ok]).sum() > 50 and np.isinf(t_ref[ok]).sum() > 20
    np.testing.assert_array_equal(status[ok], np.where(np.isfinite(t_ref[ok]), HIT, MISS))
    h = ok & np.isfinite(t_ref)
    np.testing.assert_allclose(t[h], t_ref[h], rtol=1e-3)
    np.testing.assert_allclose(n[h], n_ref[h], atol=2e-3)
    assert np.isinf(t[status != HIT]).all() and (n[status != HIT] == 0).all()
    assert (np.asarray(hit.voxel) == -1).all() and (np.asarray(hit.index) == -1).all()
    assert set(status.tolist()) <= STATUSES


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=3, max_size=3), st.lists(st.floats(-1, 1), min_size=3, max_size=3))
def test_sphere_trace_single_rays_property(target, jitter):
    origin = np.array([0.0, 0.0, -4.0]) + 0.5 * np.array(jitter)
    u = np.array(target) * 1.5 - origin
    u /= np.linalg.norm(u)
    hit = jv.sphere_trace(sdf.sphere(1.0), origin[None], u[None], t_max=20.0)
    o64, u64 = origin.astype(np.float32).astype(np.float64)[None], u.astype(np.float32).astype(np.float64)[None]
    t_ref = ray_sphere(o64, u64, 1.0)[0]
    if np.isfinite(ray_sphere(o64, u64, 1.01)[0]) != np.isfinite(ray_sphere(o64, u64, 0.99)[0]):
        assert int(hit.status[0]) in STATUSES  # near-grazing: excused
    elif np.isfinite(t_ref):
        assert int(hit.status[0]) == HIT and float(hit.t[0]) == pytest.approx(t_ref, rel=1e-3)
    else:
        assert int(hit.status[0]) == MISS and np.isinf(float(hit.t[0]))


@pytest.mark.codegen
def test_sphere_trace_edge_cases():
    ball = sdf.sphere(1.0)
    o = np.array(
        [
            [0.2, 0.1, 0.0],
            [0.5, 0.0, 0.0],
            [-3.0, 1.0 + 1e-6, 0.0],
            [-3.0, 0.0, 0.0],
            [-3.0, 0.0, 0.0],
            [-3.0, 0.0, 0.0],
            [np.nan, 0.0, 0.0],
        ],
        np.float32,
    )
    d = np.array(
        [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            [np.nan, 1.0, 0.0],
            [1.0, 0.0, 0.0],
        ],
        np.float32,
    )
    # epsilon 1e-7: the hit tolerance near t = 3 is 3e-7, below the 1e-6 miss distance of ray 2.
    hit = jv.sphere_trace(ball, o, d, t_max=10.0, max_steps=64, epsilon=1e-7, t_min=0.1)
    status, t = np.asarray(hit.status), np.asarray(hit.t)
    assert status[:2].tolist() == [HIT, HIT] and np.allclose(t[:2], 0.1)  # inside at t_min
    assert status[2] == STEP_CAP and np.isinf(t[2])  # grazing 1e-6 outside: neither hit nor miss
    assert status[3] == HIT and t[3] == pytest.approx(2.0, abs=1e-5)
    assert status[4:].tolist() == [INVALID] * 3 and np.isinf(t[4:]).all()
    clipped = jv.sphere_trace(ball, o[3], d[3], t_max=1.5)
    assert int(clipped.status) == MISS and np.isinf(float(clipped.t))  # batch shape () too


def test_hits_keep_their_distance_where_the_gradient_is_not_finite():
    """A scene whose value is finite but whose gradient is NaN (a "where" over a NaN
    branch): the hit keeps its traced distance (the implicit correction, 0 in value, must
    not make it NaN), with a zero normal, as where the gradient is zero; its distance's
    gradient with respect to the origin is finite."""
    from jaxvox.sdf.base import SDF, node

    @node
    class NanGradientPlane(SDF):  # the plane x = 0, outside towards +x
        def _distance(self, p):
            return jnp.where(p[..., 1] < 100.0, p[..., 0], jnp.sqrt(p[..., 1] - 100.0))

    scene = NanGradientPlane()
    assert np.isnan(np.asarray(jax.grad(scene._distance)(jnp.float32([1.0, 0.0, 0.0])))).any()
    o, d = np.float32([[2.0, 0.1, 0.2], [3.0, -0.5, 0.0]]), np.float32([[-1.0, 0.0, 0.0], [-1.0, 0.2, 0.1]])
    hit = jv.sphere_trace(scene, o, d, t_max=10.0)  # (the octree's tracing ends in the same `surface_hit`)
    assert np.asarray(hit.status).tolist() == [HIT, HIT]
    np.testing.assert_allclose(np.asarray(hit.t), [2.0, 3.0 * np.linalg.norm(d[1])], rtol=1e-5)
    assert (np.asarray(hit.normal) == 0).all()
    dt = jax.grad(lambda origin: jv.sphere_trace(scene, origin, d[0], t_max=10.0).t)(jnp.asarray(o[0]))
    assert np.isfinite(np.asarray(dt)).all()


def test_relaxation_batch_shapes_and_jit():
    scene = sdf.union(
        sdf.sphere(0.6, center=(-0.5, 0.0, 0.0)),
        sdf.box((0.4, 0.3, 0.5), center=(0.6, 0.2, 0.0)),
        sdf.plane((0.0, 1.0, 0.0), offset=1.0),
    )
    s, v = np.meshgrid(np.linspace(-1.2, 1.2, 16), np.linspace(-1.2, 1.2, 12))
    d = np.stack([s, v, np.full_like(s, 3.0)], -1).astype(np.float32)  # [12, 16, 3]
    origin = np.array([0.0, 0.5, -4.0], np.float32)  # broadcast against directions
    plain, steps1 = jv.sphere_trace(scene, origin, d, t_max=30.0, return_steps=True)
    relaxed, steps16 = jv.sphere_trace(scene, origin, d, t_max=30.0, relaxation=1.6, return_steps=True)
    assert plain.t.shape == (12, 16) and plain.normal.shape == (12, 16, 3) and steps1.dtype == jnp.int32
    np.testing.assert_array_equal(np.asarray(relaxed.status), np.asarray(plain.status))
    assert (np.asarray(plain.status) == HIT).mean() > 0.3
    np.testing.assert_allclose(np.asarray(relaxed.t), np.asarray(plain.t), rtol=1e-3)
    assert float(steps16.mean()) <= float(steps1.mean())
    jitted = jax.jit(lambda sc, dd: jv.sphere_trace(sc, origin, dd, t_max=30.0))(scene, d)
    np.testing.assert_array_equal(np.asarray(jitted.status), np.asarray(plain.status))
    np.testing.assert_allclose(np.asarray(jitted.t), np.asarray(plain.t), rtol=1e-6)


def test_non_lipschitz_scene_reports_valid_statuses():
    a, b = sdf.sphere(1.0), sdf.box((0.5, 0.5, 0.5), center=(0.3, 0.0, 0.0))
    wild = sdf.mix(a, b, 3.0)  # Lipschitz up to 5: steps can overshoot
    assert sdf.lipschitz_bound(wild) == 5.0
    rng = np.random.default_rng(6)
    o, u = _shell_rays(rng, 64)
    status = np.asarray(jv.sphere_trace(wild, o, u, t_max=20.0, max_steps=64).status)
    assert set(status.tolist()) <= STATUSES
    # Under-relaxed by 1 / L the steps are safe: the first crossing of a fine float64 march.
    o, u = o.astype(np.float32).astype(np.float64), u.astype(np.float32).astype(np.float64)

    def f(p):  # 3 sphere - 2 box, float64
        q = np.abs(p - (0.3, 0.0, 0.0)) - 0.5
        box = np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)
        return 3 * (np.linalg.norm(p, axis=-1) - 1.0) - 2 * box

    ts = np.arange(0.0, 20.0, 1e-3)
    values = f(o[:, None] + ts[None, :, None] * u[:, None])  # [64, 20000]
    crossed = values <= 0
    t_ref = np.where(crossed.any(1), ts[crossed.argmax(1)], np.inf)
    safe = jv.sphere_trace(wild, o, u, t_max=20.0, max_steps=4096, relaxation=1 / 5, epsilon=1e-5)
    assert ((np.asarray(safe.status) == HIT) == np.isfinite(t_ref)).all()
    hit = np.isfinite(t_ref)
    assert hit.sum() > 10
    np.testing.assert_allclose(np.asarray(safe.t)[hit], t_ref[hit], atol=2e-3)


# ----------------------------------------------------------------------------- normals and meshing


def test_normals_grad_and_central_agree_with_analytic():
    rng = np.random.default_rng(7)
    c = np.array([0.1, 0.2, -0.3])
    p = rng.normal(size=(64, 3)) + c
    ball = sdf.sphere(0.8, center=c)
    want = (p - c) / np.linalg.norm(p - c, axis=-1, keepdims=True)
    for method in sdf.NORMAL_METHODS:
        np.testing.assert_allclose(np.asarray(sdf.normal(ball, p, method=method)), want, atol=1e-3)
    ring = sdf.smooth_union(sdf.torus(0.8, 0.3), sdf.capsule((0, -1, 0), (0, 1, 0), 0.2), 0.2)
    q = rng.uniform(-1.2, 1.2, (8, 8, 3))  # batch shape kept
    grad_n = np.asarray(sdf.normal(ring, q))
    assert grad_n.shape == (8, 8, 3)
    np.testing.assert_allclose(grad_n, np.asarray(sdf.normal(ring, q, method="central", h=1e-3)), atol=2e-3)


def test_to_mesh_sphere_and_empty():
    grid = jv.Grid(origin=(-1.0, -1.0, -1.0), voxel_size=2.0 / 32, resolution=32)
    c = np.array([0.05, -0.1, 0.0])
    mesh = sdf.to_mesh(sdf.sphere(0.6, center=c), grid)
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    assert mesh.num_faces > 500
    assert np.abs(np.linalg.norm(v - c, axis=1) - 0.6).max() <= 0.5 * float(grid.voxel_size)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # closed: every edge has two faces
    tri = v[f]
    outward = np.sum(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) * (tri.mean(1) - c), -1)
    assert (outward > 0).all()  # counter-clockwise seen from outside
    empty = sdf.to_mesh(sdf.sphere(0.3, center=(5.0, 5.0, 5.0)), grid)
    assert empty.num_faces == 0 and empty.num_vertices == 0
    with pytest.raises(jv.JaxvoxError, match="resolution must be at most 512"):
        sdf.to_mesh(sdf.sphere(0.5), jv.Grid(origin=(0, 0, 0), voxel_size=0.01, resolution=1024))


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: sdf.sphere(-1.0), "sphere radius: must be >= 0"),
        (lambda: sdf.sphere(np.nan), "finite"),
        (lambda: sdf.sphere(1.0, center=(0, 0)), r"shape \(3,\)"),
        (lambda: sdf.box((1.0, 2.0)), r"shape \(3,\)"),
        (lambda: sdf.rounded_box((0.5, 0.5, 0.1), 0.2), "must be <= the smallest half extent"),
        (lambda: sdf.torus(1.0, -0.1), "minor_radius"),
        (lambda: sdf.plane((0, 0, 0), offset=1.0), "nonzero"),
        (lambda: sdf.rotate(sdf.sphere(1.0), np.diag([1.0, 1.0, -1.0])), "must be a rotation"),
        (lambda: sdf.scale(sdf.sphere(1.0), (1.0, 0.0, 1.0)), "must be > 0"),
        (lambda: sdf.union(), "at least one"),
        (lambda: sdf.union(sdf.sphere(1.0), 2.0), "SDF scene"),
        (lambda: sdf.smooth_union(sdf.sphere(1.0), sdf.sphere(1.0), -0.1), "smooth_union k: must be >= 0"),
        (lambda: sdf.normal(sdf.sphere(1.0), np.zeros((4, 3)), method="forward"), "normal method: expected one of"),
        (lambda: sdf.sphere(1.0)(np.zeros((4, 2))), r"\[\.\.\., 3\]"),
        (lambda: jv.sphere_trace(sdf.sphere(1.0), np.zeros((4, 3)), np.ones((5, 3))), "broadcast"),
        (lambda: jv.sphere_trace(sdf.sphere(1.0), np.zeros(3), np.ones(3), relaxation=2.0), "relaxation"),
        (lambda: jv.sphere_trace(sdf.sphere(1.0), np.zeros(3), np.ones(3), max_steps=0), "max_steps"),
        (lambda: jv.sphere_trace(sdf.sphere(1.0), np.zeros(3), np.ones(3), t_max=np.nan), "NaN"),
    ],
)
def test_bad_input_raises(build, message):
    with pytest.raises(jv.JaxvoxError, match=message):
        build()
