"""Ray traversal against a float64 brute-force slab test (work in progress, issue 4)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import jaxvox as jv
from jaxvox.trace import HIT, INVALID, MISS, trace

TINY = 2.0**-100


def brute_force(ijk, origins, directions, tie=1e-4):
    """First hit of each ray among closed voxel boxes, float64: (t [n], tied voxels per ray)."""
    lo = ijk.astype(np.float64)
    hi = lo + 1.0
    ts, ties = [], []
    for o, d in zip(origins.astype(np.float64), directions.astype(np.float64)):
        inv = 1.0 / np.where(d == 0, TINY, d)
        ta, tb = (lo - o) * inv, (hi - o) * inv
        t_in, t_out = np.minimum(ta, tb).max(1), np.maximum(ta, tb).min(1)
        ok = (t_in <= t_out) & (t_out > 0)
        if not ok.any():
            ts.append(np.inf)
            ties.append(set())
            continue
        t = np.maximum(t_in, 0.0)
        first = t[ok].min()
        ts.append(first)
        ties.append({tuple(v) for v in ijk[ok & (t <= first + tie)]})
    return np.array(ts), ties


@pytest.fixture(scope="module")
def scene(meshes_dir):
    resolution = 32
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    v = np.asarray(mesh.vertices)
    v = (v - v.min(0)) / np.ptp(v, 0).max() * (resolution - 2) + 1
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=resolution)
    vox = jv.voxelize(jv.Mesh(v, mesh.faces), grid)
    ijk = vox.to_numpy()
    rng = np.random.default_rng(0)
    n = 1500
    o = rng.uniform(-10, resolution + 10, (n, 3)).astype(np.float32)
    d = (rng.uniform(0, resolution, (n, 3)) - o).astype(np.float32)
    d[np.arange(200), rng.integers(0, 3, 200)] = 0  # zero components
    d[200:300] = np.eye(3, dtype=np.float32)[rng.integers(0, 3, 100)] * rng.choice([-1, 1], (100, 1))
    o[300:400] = ijk[rng.integers(0, len(ijk), 100)] + 0.5  # inside occupied voxels
    o[400:500] = np.round(o[400:500])  # on voxel corners
    return vox, ijk, o, d


@pytest.mark.parametrize("build", [jv.build_octree, jv.build_dag])
def test_trace_matches_brute_force(scene, build):
    vox, ijk, o, d = scene
    tree = build(vox)
    hit = trace(tree, o, d)
    t_ref, ties = brute_force(ijk, o, d)
    status, voxel, t = np.asarray(hit.status), np.asarray(hit.voxel), np.asarray(hit.t)
    for i in range(len(o)):
        if np.isinf(t_ref[i]):
            assert status[i] == MISS, i
        else:
            assert status[i] == HIT and tuple(voxel[i]) in ties[i], i
            assert abs(t[i] - t_ref[i]) <= 1e-3 * max(1.0, t_ref[i]), i
    assert (status[300:400] == HIT).all() and (t[300:400] == 0).all()
    hits = status == HIT
    np.testing.assert_array_equal(np.asarray(hit.index)[hits], np.asarray(jv.voxel_index(tree, voxel[hits])))


def test_trace_invalid_rays_and_jit(scene):
    vox, ijk, o, d = scene
    tree = jv.build_dag(vox)
    bad_o = np.array([[np.nan, 0, 0], [1, 1, 1], [1, 1, 1]], np.float32)
    bad_d = np.array([[1, 0, 0], [0, 0, 0], [np.nan, 1, 0]], np.float32)
    assert (np.asarray(trace(tree, bad_o, bad_d).status) == INVALID).all()
    eager = trace(tree, o[:100], d[:100])
    jitted = jax.jit(lambda oo, dd: trace(tree, oo, dd))(o[:100].reshape(10, 10, 3), d[:100].reshape(10, 10, 3))
    np.testing.assert_array_equal(np.asarray(jitted.voxel).reshape(-1, 3), np.asarray(eager.voxel))
    clipped = trace(tree, o[:100], d[:100], t_max=0.5)
    assert (np.asarray(clipped.t)[np.asarray(clipped.status) == HIT] <= 0.5).all()
