"""Ray traversal (esvo, stack, dense DDA) against a float64 brute-force slab test and the mesh."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import textwrap

import hypothesis.strategies as st
import jax
import numpy as np
import pytest
from hypothesis import given, settings

import jaxvox as jv
from jaxvox.trace import HIT, INVALID, MISS, STEP_CAP

from .reference import first_hit

TINY = 2.0**-100
FULL = os.environ.get("JAXVOX_SLOW_SCALE") == "full"


def brute_force(ijk, origins, directions, t_max=np.inf, tie=1e-4):
    """First hit of each ray among closed voxel boxes, float64: (t [n], tied voxels per ray)."""
    lo = ijk.astype(np.float64)
    hi = lo + 1.0
    ts, ties = [], []
    t_max = np.broadcast_to(np.asarray(t_max, np.float64), len(origins))
    for o, d, t_max in zip(origins.astype(np.float64), directions.astype(np.float64), t_max):
        inv = 1.0 / np.where(d == 0, TINY, d)
        ta, tb = (lo - o) * inv, (hi - o) * inv
        t_in, t_out = np.minimum(ta, tb).max(1), np.maximum(ta, tb).min(1)
        ok = (t_in < t_out) & (t_out > 0) & (t_in <= t_max)
        t = np.maximum(t_in, 0.0)
        first = t[ok].min() if ok.any() else np.inf
        ts.append(first)
        ties.append({tuple(v) for v in ijk[ok & (t <= first + tie)]})
    return np.array(ts), ties


def assert_matches(hit, ijk, o, d, t_max=np.inf):
    """Same hit/miss as the brute force, t within 1e-3, a voxel tied for first."""
    t_ref, ties = brute_force(ijk, o, d, t_max)
    status, voxel, t = np.asarray(hit.status), np.asarray(hit.voxel), np.asarray(hit.t)
    for i in range(len(o)):
        if np.isinf(t_ref[i]):
            assert status[i] == MISS and voxel[i].tolist() == [-1, -1, -1], (i, o[i], d[i], voxel[i])
        else:
            assert status[i] == HIT and tuple(voxel[i]) in ties[i], (i, o[i], d[i], voxel[i], ties[i])
            assert abs(t[i] - t_ref[i]) <= 1e-3 * max(1.0, t_ref[i]), (i, t[i], t_ref[i])


def assert_same(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def rays(rng, n, resolution, ijk):
    """Random rays with the hard cases: zero components, axis-aligned, inside voxels, on corners."""
    o = rng.uniform(-10, resolution + 10, (n, 3)).astype(np.float32)
    d = (rng.uniform(0, resolution, (n, 3)) - o).astype(np.float32)
    k = n // 8
    d[np.arange(k), rng.integers(0, 3, k)] = 0  # zero components
    d[k : 2 * k] = np.eye(3, dtype=np.float32)[rng.integers(0, 3, k)] * rng.choice([-1, 1], (k, 1))
    o[2 * k : 3 * k] = ijk[rng.integers(0, len(ijk), k)] + 0.5  # inside occupied voxels
    o[3 * k : 4 * k] = np.round(o[3 * k : 4 * k])  # on voxel corners
    o[4 * k : 5 * k, 0] = np.round(o[4 * k : 5 * k, 0])  # in voxel planes, moving along them
    d[4 * k : 5 * k, 0] = 0
    return o, d


def spot_scene(meshes_dir):
    """(voxels, ijk, origins, directions): spot at 32^3 in grid units and `rays` at it."""
    resolution = 32
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    v = np.asarray(mesh.vertices)
    v = (v - v.min(0)) / np.ptp(v, 0).max() * (resolution - 2) + 1
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=resolution)
    vox = jv.voxelize(jv.Mesh(v, mesh.faces), grid)
    ijk = vox.to_numpy()
    o, d = rays(np.random.default_rng(0), 1200, resolution, ijk)
    return vox, ijk, o, d


@pytest.fixture(scope="module")
def scene(meshes_dir):
    return spot_scene(meshes_dir)


@pytest.fixture(scope="module")
def trees(scene):
    vox = scene[0]
    return {"svo": jv.build_octree(vox), "dag": jv.build_dag(vox)}


@pytest.mark.codegen
@pytest.mark.parametrize("method", jv.TRACE_METHODS)
@pytest.mark.parametrize("kind", ["svo", "dag"])
def test_trace_matches_brute_force(scene, trees, kind, method):
    vox, ijk, o, d = scene
    tree = trees[kind]
    hit = jv.trace(tree, o, d, method=method)
    assert_matches(hit, ijk, o, d)
    k = len(o) // 8
    assert (np.asarray(hit.status)[2 * k : 3 * k] == HIT).all() and (np.asarray(hit.t)[2 * k : 3 * k] == 0).all()
    hits = np.asarray(hit.status) == HIT
    voxel = np.asarray(hit.voxel)
    np.testing.assert_array_equal(np.asarray(hit.index)[hits], np.asarray(jv.voxel_index(tree, voxel[hits])))
    np.testing.assert_array_equal(np.asarray(hit.index)[~hits], -1)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["cow", "stanford-bunny"])
def test_data_meshes_against_brute_force(meshes_dir, name):
    """Every test mesh's DAG at 128^3 (64^3 unless JAXVOX_SLOW_SCALE=full), 2000 rays each."""
    resolution = 128 if FULL else 64
    mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
    v = np.asarray(mesh.vertices)
    v = (v - v.min(0)) / np.ptp(v, 0).max() * (resolution - 2) + 1
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=resolution)
    vox = jv.voxelize(jv.Mesh(v, mesh.faces), grid)
    ijk = vox.to_numpy()
    o, d = rays(np.random.default_rng(len(name)), 2000, resolution, ijk)
    assert_matches(jv.trace(jv.build_dag(vox), o, d), ijk, o, d)


def test_methods_and_drivers_agree_ray_for_ray(scene, trees):
    """esvo and stack on the SVO and the DAG, the dense DDA, lanes and plain vmap: identical."""
    vox, ijk, o, d = scene
    reference = jv.trace(trees["dag"], o, d)
    for tree in trees.values():
        for method in jv.TRACE_METHODS:
            for lanes in (None, 64):
                assert_same(jv.trace(tree, o, d, method=method, lanes=lanes), reference)
    occupancy = np.zeros((32,) * 3, bool)
    occupancy[tuple(ijk.T)] = True
    dense = jv.trace_dense(occupancy, vox.grid, o, d)
    for name in ("t", "voxel", "normal", "status"):
        np.testing.assert_array_equal(np.asarray(getattr(dense, name)), np.asarray(getattr(reference, name)))
    hits = np.asarray(dense.status) == HIT
    v = np.asarray(dense.voxel)[hits]
    np.testing.assert_array_equal(np.asarray(dense.index)[hits], (v[:, 0] * 32 + v[:, 1]) * 32 + v[:, 2])


def test_normals_point_back_at_the_ray(scene, trees):
    vox, ijk, o, d = scene
    hit = jv.trace(trees["dag"], o, d)
    entered = (np.asarray(hit.status) == HIT) & (np.asarray(hit.t) > 0)
    n = np.asarray(hit.normal)[entered]
    assert (np.abs(n).sum(1) == 1).all()
    assert (np.einsum("ij,ij->i", n, d[entered]) < 0).all()
    # the entry point lies on the face the normal names
    p = o[entered] + np.asarray(hit.t)[entered, None] * d[entered]
    face = np.asarray(hit.voxel)[entered] + (n > 0)
    axis = np.abs(n).argmax(1)
    rows = np.arange(len(axis))
    np.testing.assert_allclose(p[rows, axis], face[rows, axis], atol=1e-3)


def test_world_coordinates_and_t_max(meshes_dir):
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    grid = jv.Grid.fit(mesh, 32)
    vox = jv.voxelize(mesh, grid)
    tree = jv.build_dag(vox)
    rng = np.random.default_rng(1)
    lo, hi = np.asarray(grid.origin), np.asarray(grid.origin) + 32 * float(grid.voxel_size)
    o = rng.uniform(lo - 0.2, hi + 0.2, (400, 3)).astype(np.float32)
    d = rng.normal(size=(400, 3)).astype(np.float32)
    t_max = rng.uniform(0, 0.5, 400).astype(np.float32)
    hit = jv.trace(tree, o, d, t_max=t_max)
    h = float(grid.voxel_size)
    og = ((o - lo) / h).astype(np.float32)
    dg = (d / h).astype(np.float32)
    assert_matches(hit, vox.to_numpy(), og, dg, t_max=t_max)  # t is the world ray parameter


def test_agrees_with_the_mesh(meshes_dir):
    """Conservative voxels contain the surface: a ray that hits a triangle hits a voxel no later."""
    resolution = 64
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    grid = jv.Grid.fit(mesh, resolution)
    tree = jv.build_dag(jv.voxelize(mesh, grid))
    v = np.asarray(mesh.vertices, np.float64)
    centre, radius = (v.min(0) + v.max(0)) / 2, np.ptp(v, 0).max()
    eye = centre + np.array([0.4, 0.3, 1.5]) * radius
    ys, xs = np.meshgrid(np.linspace(-0.35, 0.35, 24), np.linspace(-0.35, 0.35, 32), indexing="ij")
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    right = np.cross(forward, [0, 1, 0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    d = (forward + xs[..., None] * right + ys[..., None] * up).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape)
    t_mesh = first_hit(v, np.asarray(mesh.faces), o, d)
    hit = jv.trace(tree, o.astype(np.float32), d.astype(np.float32))
    t_vox, status = np.asarray(hit.t, np.float64), np.asarray(hit.status)
    mesh_hits = np.isfinite(t_mesh)
    assert mesh_hits.mean() > 0.2
    assert (status[mesh_hits] == HIT).all()
    h = float(grid.voxel_size)
    assert (t_vox[mesh_hits] <= t_mesh[mesh_hits] + 1e-4 * h).all()
    # where both hit, the voxel depth is about a voxel diagonal from the surface (more for
    # grazing rays, which cross the conservative shell at a slant)
    gap = (t_mesh[mesh_hits] - t_vox[mesh_hits]) / h
    assert np.median(gap) < np.sqrt(3) and np.quantile(gap, 0.9) < 2 * np.sqrt(3)
    # rays that miss the surface but hit voxels pass within a voxel diagonal of it
    near = (status == HIT) & ~mesh_hits
    assert near.mean() < 0.1


def test_invalid_rays_and_step_cap(scene, trees):
    vox, ijk, o, d = scene
    tree = trees["dag"]
    bad_o = np.array([[np.nan, 0, 0], [1, 1, 1], [1, 1, 1], [1, 1, 1]], np.float32)
    bad_d = np.array([[1, 0, 0], [0, 0, 0], [np.nan, 1, 0], [1, 1, 1]], np.float32)
    for method in jv.TRACE_METHODS:
        hit = jv.trace(tree, bad_o, bad_d, t_max=np.array([1, 1, 1, np.nan], np.float32), method=method)
        assert (np.asarray(hit.status) == INVALID).all()
        assert np.isinf(np.asarray(hit.t)).all() and (np.asarray(hit.index) == -1).all()
    full = jv.trace(tree, o, d)
    for method in jv.TRACE_METHODS:
        capped = jv.trace(tree, o, d, method=method, max_steps=4)
        status = np.asarray(capped.status)
        assert (status == STEP_CAP).any()
        # a capped ray is never reported as a hit or a miss; finished rays are unchanged
        done = status != STEP_CAP
        np.testing.assert_array_equal(status[done], np.asarray(full.status)[done])
        np.testing.assert_array_equal(np.asarray(capped.voxel)[done], np.asarray(full.voxel)[done])


def test_jit_vmap_and_batch_shapes(scene, trees):
    vox, ijk, o, d = scene
    tree = trees["dag"]
    eager = jv.trace(tree, o[:120], d[:120])
    jitted = jax.jit(lambda t, a, b: jv.trace(t, a, b))(tree, o[:120].reshape(10, 12, 3), d[:120].reshape(10, 12, 3))
    assert jitted.t.shape == (10, 12) and jitted.voxel.shape == (10, 12, 3)
    assert_same(jax.tree.map(lambda x: x.reshape((120,) + x.shape[2:]), jitted), eager)
    mapped = jax.vmap(lambda a, b: jv.trace(tree, a, b))(o[:120].reshape(4, 30, 3), d[:120].reshape(4, 30, 3))
    assert_same(jax.tree.map(lambda x: x.reshape((120,) + x.shape[2:]), mapped), eager)
    one = jv.trace(tree, o[0], d[0])  # a single ray
    assert one.t.shape == () and int(one.status) == int(eager.status[0])
    empty = jv.trace(tree, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    assert empty.t.shape == (0,)


def test_empty_tree_and_bad_arguments(scene):
    vox = scene[0]
    empty = jv.Voxels.from_coords(np.zeros((0, 3), np.int32), vox.grid)
    hit = jv.trace(jv.build_dag(empty), np.zeros((2, 3), np.float32), np.ones((2, 3), np.float32))
    assert (np.asarray(hit.status) == MISS).all()
    with pytest.raises(jv.JaxvoxError, match="method"):
        jv.trace(jv.build_dag(vox), np.zeros((1, 3)), np.ones((1, 3)), method="bfs")
    with pytest.raises(jv.JaxvoxError, match="shape"):
        jv.trace_dense(np.zeros((8, 8, 8), bool), vox.grid, np.zeros((1, 3)), np.ones((1, 3)))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([4, 16]))
def test_random_sets_and_lattice_rays(seed, resolution):
    """Random voxel sets at small R; rays with integer and half-integer coordinates (ties everywhere)."""
    rng = np.random.default_rng(seed)
    count = rng.integers(1, max(2, resolution**3 // 4))
    ijk = np.unique(rng.integers(0, resolution, (count, 3)), axis=0).astype(np.int32)
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=resolution)
    full = tuple(8**level for level in range(resolution.bit_length() - 1))  # one compile per R
    tree = jv.build_octree(jv.Voxels.from_coords(ijk, grid), capacities=full)
    o = (rng.integers(-2, 2 * resolution + 4, (64, 3)) / 2.0).astype(np.float32)
    d = rng.integers(-2, 3, (64, 3)).astype(np.float32)
    d[(d == 0).all(1), 0] = 1
    hit = jv.trace(tree, o, d, method="esvo", lanes=16)
    assert_matches(hit, ijk, o, d)
    assert_same(jv.trace(tree, o, d, method="stack", lanes=None), hit)


def test_sharded_over_four_host_devices(scene, tmp_path):
    """`trace` and `render` on four host devices give what they give on one; what the
    renderer places on every device shares one buffer."""
    vox, ijk, o, d = scene
    np.savez(tmp_path / "rays.npz", ijk=ijk, o=o, d=d)
    script = textwrap.dedent(f"""
        import jax, numpy as np, jaxvox as jv
        jv.enable_compilation_cache()  # $JAXVOX_CACHE_DIR from the suite: a warm suite compiles nothing here
        assert len(jax.devices()) == 4, jax.devices()
        z = np.load({str(tmp_path / "rays.npz")!r})
        grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=32)
        tree = jv.build_dag(jv.Voxels.from_coords(z["ijk"], grid))
        # 1201 rays: the shape-ladder bucket of the image below, so that the two
        # one-device traces share a program (compiling is most of this test's time).
        a = jv.trace(tree, z["o"][:1201], z["d"][:1201])
        b = jv.trace(tree, z["o"][:1201], z["d"][:1201], shard=False)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        # An image with the beam start, unpadded: 1443 rays, one more added on the
        # devices to split them evenly; each device groups its own rows (9.3 rows each,
        # 8 of them in whole bands of tiles): the hits of one device without the beam,
        # left sharded over the four devices.
        o2, d2 = jv.pinhole_rays((-20.0, -15.0, 40.0), z["ijk"].mean(0), width=39, height=37)
        beamed, plain = jv.trace(tree, o2, d2, beam=True), jv.trace(tree, o2, d2, shard=False)
        for x, y in zip(jax.tree.leaves(beamed), jax.tree.leaves(plain)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        assert beamed.t.shape == (37, 39) and len(beamed.t.sharding.device_set) == 4
        assert (np.asarray(plain.status) == 0).sum() > 100
        # The renderer splits each batch's paths over the devices (1001 samples in
        # three batches of 400, the last one partly padding): the same image up to
        # float32 rounding, and one program for every batch (each batch's image keeps
        # its sharding).
        import logging
        logs = []
        handler = logging.Handler()
        handler.emit = lambda record: logs.append(record.getMessage())
        logging.getLogger("jax").addHandler(handler)
        jax.config.update("jax_log_compiles", True)
        view = dict(width=13, height=11, spp=7, bounces=2, batch_rays=400, lanes=64)
        r = jv.render(tree, (-20.0, -15.0, 40.0), z["ijk"].mean(0), **view)
        assert sum("compilation of jit(_render_batch)" in m for m in logs) == 1, logs
        s = jv.render(tree, (-20.0, -15.0, 40.0), z["ijk"].mean(0), shard=False, **view)
        np.testing.assert_allclose(np.asarray(r.radiance), np.asarray(s.radiance), rtol=1e-5, atol=1e-6)
        assert int(r.stopped) == int(s.stopped) and float(np.asarray(r.radiance).max()) > 0
        # The tree and tables the renderer places on every device are aliased, not copied.
        from jaxvox._core.devices import on_all_devices
        table = jax.numpy.arange(12.0).reshape(4, 3)
        shared = on_all_devices(table)
        pointers = {{x.data.unsafe_buffer_pointer() for x in shared.addressable_shards}}
        assert pointers == {{table.unsafe_buffer_pointer()}}
        assert len(shared.addressable_shards) == 4 and np.array_equal(np.asarray(shared), np.asarray(table))
        print("OK", int((np.asarray(a.status) == 0).sum()))
    """)
    flags = " ".join([os.environ.get("XLA_FLAGS", ""), "--xla_force_host_platform_device_count=4"]).strip()
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")  # (the suite's emitters: tests/conftest.py)
    result = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.startswith("OK")


def _camera_rays(eye, target, height, width, jitter=0.0, seed=0):
    """[height, width, 3] pinhole rays in grid units, optionally with jittered directions."""
    eye, target = np.asarray(eye, np.float32), np.asarray(target, np.float32)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0] if abs(forward[2]) < 0.9 else [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    v, u = np.meshgrid(np.linspace(-0.4, 0.4, height), np.linspace(-0.4, 0.4, width), indexing="ij")
    d = forward + u[..., None] * right + v[..., None] * up
    d += np.random.default_rng(seed).normal(0, jitter, d.shape)
    return np.broadcast_to(eye, d.shape).astype(np.float32), d.astype(np.float32)


def test_beam_start_changes_no_hit(scene, trees):
    """Image rays ([H, W] not multiples of 8) from outside, inside the grid, inside a voxel,
    on voxel planes and looking along an axis: identical with and without the beam start,
    for both traversals, and equal to the brute force."""
    vox, ijk, _, _ = scene
    centre = ijk.mean(0)
    inside = ijk[len(ijk) // 2] + 0.5
    cameras = [
        ((-20.0, -15.0, 40.0), centre, 0.0),  # outside, looking at the cow
        ((16.0, 16.0, 16.0), (40.0, 30.0, 10.0), 0.0),  # inside the grid
        (tuple(inside), centre + 3.0, 0.0),  # inside an occupied voxel
        ((-5.0, 12.0, 9.0), (40.0, 12.0, 9.0), 0.0),  # eye on voxel planes, along x
        ((50.0, 3.0, 17.0), centre, 0.3),  # outside, incoherent directions
    ]
    for k, (eye, target, jitter) in enumerate(cameras):
        o, d = _camera_rays(eye, target, 19, 21, jitter, seed=k)
        plain = jv.trace(trees["dag"], o, d, beam=False)
        for kind, tree in trees.items():
            for method in jv.TRACE_METHODS:
                assert_same(jv.trace(tree, o, d, method=method, beam=True), plain)
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), plain)
        assert_matches(flat, ijk, o.reshape(-1, 3), d.reshape(-1, 3))
    jitted = jax.jit(lambda t, a, b: jv.trace(t, a, b, beam=True))(trees["dag"], o, d)
    assert_same(jitted, plain)
    away = jv.trace(trees["dag"], *_camera_rays((-20.0, -15.0, 40.0), (-60.0, -45.0, 80.0), 16, 16), beam=True)
    assert (np.asarray(away.status) == MISS).all()


def test_beam_by_default_for_camera_rays(scene, trees, monkeypatch):
    """The default `beam=None` takes the beam start for image-shaped rays (a camera's
    [H, W, 3], a stack of images) and the plain loop for a list of rays or thin batches;
    ``beam=False`` and ``beam=True`` override it. Hits are the same either way."""
    api = importlib.import_module("jaxvox.trace.api")  # (`jaxvox.trace` is also the function)
    chosen = []
    layout = api.beam_layout
    monkeypatch.setattr(api, "beam_layout", lambda batch, n: chosen.append(batch) or layout(batch, n))
    o, d = _camera_rays((-20.0, -15.0, 40.0), scene[1].mean(0), 9, 10)
    cases = [
        ((o, d), {}, True),  # a camera image
        ((o[None], d), {}, True),  # a stack of one image (origins broadcast)
        ((o.reshape(-1, 3), d.reshape(-1, 3)), {}, False),  # the same rays as a list
        ((o[:4], d[:4]), {}, False),  # 4 x 10: too thin for 8 x 8 tiles
        ((o, d), dict(beam=False), False),
        ((o.reshape(-1, 3), d.reshape(-1, 3)), dict(beam=True), True),
    ]
    for (a, b), options, beam in cases:
        chosen.clear()
        hit = jv.trace(trees["dag"], a, b, **options)
        assert bool(chosen) == beam, (np.shape(a), options)
        flat = jax.tree.map(lambda x: np.asarray(x).reshape((-1,) + np.shape(x)[hit.t.ndim :]), hit)
        b_full = np.broadcast_to(b, np.broadcast_shapes(np.shape(a), np.shape(b)))
        assert_matches(flat, scene[1], np.broadcast_to(a, b_full.shape).reshape(-1, 3), b_full.reshape(-1, 3))


def test_beam_groups_round_trip():
    import jax.numpy as jnp

    from jaxvox.trace.beam import BEAM_RAYS, beam_layout, per_group, tiles, ungroup_values

    for batch in [(5,), (3, 8, 8), (2, 9, 17), (1, 1), (130,)]:
        n = int(np.prod(batch)) + 7  # padding rays past the batch
        layout = beam_layout(batch, n - 7)
        x = jnp.arange(n, dtype=jnp.float32) + 1
        tiled = tiles(x, layout)
        assert tiled.shape[2] * tiled.shape[4] == BEAM_RAYS
        # each ray gets its group's least value: the first ray of its tile (x grows in row order)
        firsts = ungroup_values(per_group((jax.lax.min,), (jnp.where(tiled > 0, tiled, jnp.inf),))[0], layout, n)
        assert (np.asarray(firsts)[n - 7 :] == 0).all()
        if len(batch) >= 2:  # the corner of each ray's tile
            index = np.indices(batch)
            corner = (*index[:-2], index[-2] // 8 * 8, index[-1] // 8 * 8)
            first = np.ravel_multi_index(corner, batch).reshape(-1)
        else:
            first = np.arange(n - 7) // BEAM_RAYS * BEAM_RAYS
        np.testing.assert_array_equal(np.asarray(firsts)[: n - 7], first + 1)


@pytest.mark.parametrize(
    "n, chunk, share", [(0, 4, 0.5), (1, 4, 1.0), (37, 8, 0.0), (37, 8, 0.3), (37, 8, 1.0), (64, 16, 0.5)]
)
def test_on_marked_runs_the_marked_rows_only(n, chunk, share):
    """`on_marked` gives ``fn(rows)`` on the marked rows and the fill elsewhere, for no,
    some and all rows marked and chunks that do or do not divide the rows, and never
    calls `fn` on more chunks than the marked rows fill."""
    import jax.numpy as jnp

    from jaxvox._core.scan import on_marked

    rng = np.random.default_rng(n + chunk)
    rows = rng.integers(-50, 50, (n, 3)).astype(np.int32)
    marked = rng.uniform(size=n) < share
    calls = []

    def fn(r):
        calls.append(r.shape)
        return r[:, 0] * 7 + r[:, 2]

    run = jax.jit(lambda m, r: on_marked(fn, m, r, jnp.int32(-99), chunk))
    got = np.asarray(run(marked, rows))
    np.testing.assert_array_equal(got, np.where(marked, rows[:, 0] * 7 + rows[:, 2], -99))
    assert got.dtype == np.int32 and calls == ([(chunk, 3)] if n else [])  # traced once, inside the loop
