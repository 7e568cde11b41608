"""Octrees of SDF scenes and octree-accelerated sphere tracing.

References: dense sampling of the scene (5^3 points per voxel, corners included) for the
voxels the surface crosses, float64 analytic ray-sphere intersection, and plain
`jaxvox.sphere_trace` ray for ray.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvox as jv

R = 32
GRID = jv.Grid(origin=(-1.0, -1.0, -1.0), voxel_size=2.0 / R, resolution=R)
SCENES = {
    "sphere": jv.sdf.sphere(0.55, center=(0.05, -0.02, 0.01)),
    "csg": jv.sdf.difference(
        jv.sdf.union(
            jv.sdf.box((0.4, 0.3, 0.35)),
            jv.sdf.sphere(0.3, center=(0.45, 0.2, 0.0)),
            jv.sdf.capsule((-0.6, -0.5, 0.0), (0.2, 0.6, 0.3), 0.12),
        ),
        jv.sdf.cylinder(0.15, 0.8),
    ),
    "thin torus": jv.sdf.rotate(jv.sdf.torus(0.6, 0.03), jv.sdf.rotation((1.0, 0.0, 0.2), 0.7)),
    "mix k=3": jv.sdf.mix(jv.sdf.sphere(0.5), jv.sdf.box((0.35, 0.35, 0.35)), 3.0),
}


def _dense_crossed(scene, grid) -> np.ndarray:
    """[R^3] bool: voxels where 5^3 samples (corners included) of the scene change sign or touch 0."""
    r = grid.resolution
    sub = np.indices((5, 5, 5)).reshape(3, -1).T / 4.0
    f = jax.jit(lambda p: scene(p))
    out = np.zeros(r**3, bool)
    for i in range(r):  # one x-slab at a time
        ijk = np.stack(np.meshgrid([i], np.arange(r), np.arange(r), indexing="ij"), -1).reshape(-1, 3)
        p = (ijk[:, None, :] + sub[None]) * float(grid.voxel_size) + np.asarray(grid.origin)
        v = np.asarray(f(jnp.asarray(p, jnp.float32)))
        out[i * r * r : (i + 1) * r * r] = (v.min(1) <= 0) & (v.max(1) >= 0)
    return out


def _flat(coords, r) -> np.ndarray:
    return (coords[:, 0] * r + coords[:, 1]) * r + coords[:, 2]


@pytest.mark.parametrize("name", list(SCENES))
def test_octree_holds_every_crossed_voxel(name):
    scene = SCENES[name]
    vox = jv.voxelize_sdf(scene, GRID)
    coords = vox.to_numpy()
    got = np.zeros(R**3, bool)
    got[_flat(coords, R)] = True
    crossed = _dense_crossed(scene, GRID)
    assert crossed.sum() > 50
    assert not (crossed & ~got).any(), f"{(crossed & ~got).sum()} crossed voxels missing"
    # No voxel is kept that the split test rules out: |f(centre)| <= L * half diagonal.
    centres = (coords + 0.5) * float(GRID.voxel_size) + np.asarray(GRID.origin)
    f = np.abs(np.asarray(scene(jnp.asarray(centres, jnp.float32))))
    lip = jv.sdf.lipschitz_bound(scene)
    assert (f <= lip * math.sqrt(3) / 2 * float(GRID.voxel_size) * (1 + 1e-4)).all()
    # Morton order, unique: the same set as the reference constructor.
    np.testing.assert_array_equal(coords, jv.Voxels.from_coords(coords[::-1], GRID).to_numpy())


@pytest.fixture(scope="module")
def trees():
    """DAGs of the sphere and CSG scenes (shared: tracing compiles once per tree)."""
    return {name: jv.build_octree_from_sdf(SCENES[name], GRID, dag=True) for name in ("sphere", "csg")}


def test_svo_and_dag_of_a_scene(trees):
    scene = SCENES["csg"]
    coords = jv.voxelize_sdf(scene, GRID).to_numpy()
    svo = jv.build_octree_from_sdf(scene, GRID)
    np.testing.assert_array_equal(jv.expand(svo).to_numpy(), coords)
    np.testing.assert_array_equal(jv.expand(trees["csg"]).to_numpy(), coords)
    assert sum(svo.level_sizes) > sum(trees["csg"].level_sizes)


def test_memory_follows_the_surface():
    """A sphere at 1024^3: the kept voxels are a thin shell (a few per surface voxel),
    never the volume."""
    grid = jv.Grid(origin=(-1.0, -1.0, -1.0), voxel_size=2.0 / 1024, resolution=1024)
    vox = jv.voxelize_sdf(jv.sdf.sphere(0.5), grid)
    area = 4 * math.pi * (0.5 / float(grid.voxel_size)) ** 2  # surface in voxel faces
    assert area < int(vox.count) < 3 * area
    assert vox.capacity < 4 * area


def test_empty_and_bad_scenes():
    far = jv.sdf.sphere(0.1, center=(5.0, 5.0, 5.0))
    vox = jv.voxelize_sdf(far, GRID)
    assert int(vox.count) == 0
    tree = jv.build_octree_from_sdf(far, GRID)
    hit = jv.sphere_trace_octree(far, tree, np.zeros((4, 3)), np.eye(4, 3) + 0.1, t_max=20.0)
    assert (np.asarray(hit.status) == jv.MISS).all()
    with pytest.raises(jv.JaxvoxError, match="lipschitz"):
        jv.voxelize_sdf(far, GRID, lipschitz=0.0)
    with pytest.raises(jv.JaxvoxError, match="NaN"):
        jv.voxelize_sdf(jax.tree.map(lambda x: x * np.nan, jv.sdf.sphere(0.5)), GRID)  # bypasses the checks
    with pytest.raises(jv.JaxvoxError, match="Octree"):
        jv.sphere_trace_octree(far, vox, np.zeros(3), np.ones(3))


def _camera_rays(n, rng):
    o = np.tile(np.float32([[1.7, 1.1, 2.1]]), (n, 1))
    target = rng.uniform(-0.9, 0.9, (n, 3))
    return o, (target - o).astype(np.float32)


N_RAYS = 1500
TRACE = dict(t_max=6.0, max_steps=512, return_steps=True)  # one compiled program per tree


@pytest.mark.parametrize("name", ["sphere", "csg"])
def test_octree_tracing_matches_plain(trees, name):
    scene, tree = SCENES[name], trees[name]
    o, d = _camera_rays(N_RAYS, np.random.default_rng(1))
    plain, plain_steps = jv.sphere_trace(scene, o, d, **TRACE)
    fast, fast_steps = jv.sphere_trace_octree(scene, tree, o, d, **TRACE)
    a, b = np.asarray(plain.status), np.asarray(fast.status)
    assert set(np.unique(b)) <= {jv.HIT, jv.MISS}
    assert (a == b).mean() > 0.995  # grazing rays may differ
    both = (a == jv.HIT) & (b == jv.HIT)
    np.testing.assert_allclose(np.asarray(fast.t)[both], np.asarray(plain.t)[both], atol=2e-3)
    # The leaf and its attribute index are reported.
    hit_voxels = np.asarray(fast.voxel)[b == jv.HIT]
    np.testing.assert_array_equal(np.asarray(jv.voxel_index(tree, hit_voxels)), np.asarray(fast.index)[b == jv.HIT])
    p = o[b == jv.HIT] + np.asarray(fast.t)[b == jv.HIT, None] * d[b == jv.HIT] / np.linalg.norm(
        d[b == jv.HIT], axis=1, keepdims=True
    )
    cell = np.floor((p - np.asarray(GRID.origin)) / float(GRID.voxel_size))
    assert (np.abs(cell - hit_voxels) <= 1).all()  # the hit point lies in (or on) its leaf
    assert np.asarray(fast_steps).mean() < np.asarray(plain_steps).mean()


def test_the_lane_count_changes_no_ray(trees):
    """Rays run on persistent lanes fed from a queue (`jaxvox._core.lanes`). On 64 lanes
    (each refilled as its ray ends) or one lane per ray, every ray ends with the same
    status, leaf and index, and the same distance and normal up to float32 rounding (the
    lane counts give programs of other sizes, which XLA may fuse differently; so may the
    refinement's evaluation count, by at most 2), for the octree and for plain sphere
    tracing. Grazing rays on the csg scene take the most steps."""
    import importlib

    octree_module = importlib.import_module("jaxvox.sphere_tracing.octree")
    plain_module = importlib.import_module("jaxvox.sphere_tracing.analytic")
    n = 4096
    scene, tree = SCENES["csg"], trees["csg"]
    o, d = _camera_rays(n, np.random.default_rng(7))
    o, d = jnp.asarray(o), jnp.asarray(d)
    args = (scene, tree, o, d, jnp.float32(6.0), jnp.float32(1e-4), jnp.float32(1.0))
    kw = dict(max_steps=512, max_leaves=256, method="esvo")
    staged, staged_steps = octree_module._sphere_trace_octree(*args, **kw, lanes=64)
    whole, whole_steps = octree_module._sphere_trace_octree(*args, **kw, lanes=n)
    for field in ("status", "voxel", "index"):
        np.testing.assert_array_equal(np.asarray(getattr(staged, field)), np.asarray(getattr(whole, field)))
    for field in ("t", "normal"):
        np.testing.assert_allclose(
            np.asarray(getattr(staged, field)), np.asarray(getattr(whole, field)), rtol=1e-6, atol=1e-6
        )
    moved = np.abs(np.asarray(staged_steps) - np.asarray(whole_steps))
    assert moved.max() <= 2 and (moved > 0).mean() < 0.03, (moved.max(), moved.mean())
    # The lanes were refilled many times: more than 64 rays take over 3x the median's rounds.
    assert (np.asarray(whole_steps) > 3 * np.median(np.asarray(whole_steps))).sum() > 64
    # Plain sphere tracing: the loop's state ray for ray.
    u = o * 0 + d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    plain = (scene, o, u, jnp.float32(0.0), jnp.float32(6.0), jnp.float32(1e-4), jnp.float32(1.0), 512)
    staged = jax.jit(lambda: plain_module.march_rays(*plain, lanes=64))()
    whole = jax.jit(lambda: plain_module.march_rays(*plain, lanes=n))()
    for field in ("status", "steps"):
        np.testing.assert_array_equal(np.asarray(getattr(staged, field)), np.asarray(getattr(whole, field)))
    hits = np.asarray(whole.status) == jv.HIT  # a miss's last t (past t_max) is not reported
    np.testing.assert_allclose(np.asarray(staged.t)[hits], np.asarray(whole.t)[hits], rtol=1e-6, atol=1e-6)
    assert (np.asarray(whole.steps) > 3 * np.median(np.asarray(whole.steps))).sum() > 64


@pytest.mark.parametrize("relaxation", [1.2, 1.6])
def test_over_relaxation_finds_the_same_hits(trees, relaxation):
    """Over-relaxed steps that leave a leaf are checked: the hits are those of plain steps
    (they used to land up to half a voxel late, in the next leaf)."""
    scene, tree = SCENES["sphere"], trees["sphere"]
    o, d = _camera_rays(N_RAYS, np.random.default_rng(4))
    plain, _ = jv.sphere_trace_octree(scene, tree, o, d, **TRACE)
    relaxed, _ = jv.sphere_trace_octree(scene, tree, o, d, relaxation=relaxation, **TRACE)
    a, b = np.asarray(plain.status), np.asarray(relaxed.status)
    assert (a == b).mean() > 0.995
    both = (a == jv.HIT) & (b == jv.HIT)
    np.testing.assert_allclose(np.asarray(relaxed.t)[both], np.asarray(plain.t)[both], atol=2e-3)


def test_against_analytic_sphere_and_edge_cases(trees):
    c, radius = np.array([0.05, -0.02, 0.01]), 0.55
    scene, tree = SCENES["sphere"], trees["sphere"]
    o, d = _camera_rays(N_RAYS, np.random.default_rng(2))
    # Origins inside the sphere, NaN and zero directions ride along in the same batch.
    o[:3], d[:3] = c, np.eye(3)
    o[3:5], d[3:5] = 0.0, [[np.nan, 0, 1], [0, 0, 0]]
    u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    oc = o - c
    b = np.sum(oc * u, 1)
    disc = b * b - (np.sum(oc * oc, 1) - radius**2)
    t_ref = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    hit, _ = jv.sphere_trace_octree(scene, tree, o, d, **TRACE)
    status, t = np.asarray(hit.status), np.asarray(hit.t)
    assert (status[:3] == jv.HIT).all() and (t[:3] == 0).all()
    assert (status[3:5] == jv.INVALID).all() and np.isinf(t[3:5]).all()
    firm = np.abs(disc) > 1e-3  # not grazing
    firm[:5] = False
    assert ((status == jv.HIT) == np.isfinite(t_ref))[firm].all()
    both = firm & np.isfinite(t_ref)
    # |f| < 1e-4 t at the hit: t is off by at most that over the cosine of incidence.
    cos = np.abs(np.sum((oc + t_ref[:, None] * u) / radius * u, 1))
    assert (np.abs(t[both] - t_ref[both]) <= 1.5e-4 * np.maximum(t_ref[both], 1) / cos[both] + 1e-5).all()
    # t_max (traced, same program), any batch shape of the same size, the leaf and step caps.
    short, _ = jv.sphere_trace_octree(
        scene, tree, o.reshape(3, -1, 3), d.reshape(3, -1, 3), **(TRACE | dict(t_max=0.1))
    )
    assert short.t.shape == (3, N_RAYS // 3)
    assert (np.asarray(short.status).reshape(-1)[5:] == jv.MISS).all()
    capped = jv.sphere_trace_octree(scene, tree, o[both][:50], d[both][:50], max_leaves=1, max_steps=2)
    assert set(np.unique(np.asarray(capped.status))) <= {jv.HIT, jv.STEP_CAP}
    assert (np.asarray(capped.status) == jv.STEP_CAP).any()


def test_hit_distance_gradient_through_octree_tracing(trees):
    """d t / d radius = -1 for a ray toward the centre, as for plain sphere tracing; under
    the caller's jit."""
    o, d = jnp.array([0.05, -0.02, 2.0]), jnp.array([0.0, 0.0, -1.0])
    t = lambda r: (
        jv.sphere_trace_octree(jv.sdf.sphere(r, center=(0.05, -0.02, 0.01)), trees["sphere"], o, d, t_max=5.0).t
    )
    np.testing.assert_allclose(float(jax.jit(jax.grad(t))(0.55)), -1.0, atol=1e-4)
